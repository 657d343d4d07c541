"""The one place the kernels' numba options live: every kernel is ``@jit`` (called only from
compiled code) or ``@entry`` (called from Python too), never a bare ``numba.njit``, so that caching
and the error model are never retyped (``tests/test_kernels.py`` checks that every compiled
function of this package carries them).

``cache=True`` writes the compiled code beside the source, or, where that folder is not writable
(a system-wide install), in numba's per-user cache directory (``NUMBA_CACHE_DIR`` overrides both).
"""

from __future__ import annotations

import os
import types
from functools import partial

import numba
import numpy as np

from camloc.kernels.stale_cache import check_cache

# numba's cache of these kernels, cleared first where any kernel's source changed since it was written
CACHE_FOLDER = check_cache()

OPTIONS = dict(cache=True, nogil=True, error_model="numpy")

# LLVM's optimization level for the modules numba compiles (``NUMBA_OPT``; numba's default 3),
# unless the user set it. About half of a first compile is LLVM optimizing and generating each
# module again (below); at level 1 the first compile took 73.5 s of CPU against 93.0 at 3, with
# warm runs no slower (the 20k pixel and depth worlds) and every result bit for bit the same
# (docs/performance.md, 2026-12-05, "The kernels at LLVM's level 1"). numba reads its environment
# again before each compile, so this holds for the kernels compiled after it (and, being the
# process's environment, for a background compile it starts and the user's own numba code).
KERNEL_OPT_LEVEL = "1"
os.environ.setdefault("NUMBA_OPT", KERNEL_OPT_LEVEL)
# LLVM's loop vectorizer, which numba runs at every level (``NUMBA_LOOP_VECTORIZE``, default on),
# off unless the user set it: the kernels' loops run over 3 or 6 entries or a pose's few candidates,
# where a vectorized body, its runtime checks and its remainder loop are code to optimize and
# generate in every module that copies the loop, not speed. Without fast-math it vectorizes no
# floating-point sum, so every result is bit for bit the same (docs/performance.md, 2026-12-05
# (eighth session), "The loop vectorizer off").
KERNEL_LOOP_VECTORIZE = "0"
os.environ.setdefault("NUMBA_LOOP_VECTORIZE", KERNEL_LOOP_VECTORIZE)

# A first index, a counter's start, or a capacity of one, as a kernel's argument: numba types a
# literal 0 or 1 as a value of its own and compiles the callee (with all it calls) once more for it;
# an int64 is the type the other call sites pass.
FIRST = np.int64(0)
ONE = np.int64(1)
# Likewise a flag: a literal True or False is a type of its own (``Literal[bool]``), so a callee
# passed both and a flag computed at run time compiled three times, each with all it calls (the
# update's ``map_cost``: ``updated`` three times in a first run, about 5% of it); a numpy bool is
# the one type every call site passes.
TRUE = np.bool_(True)
FALSE = np.bool_(False)

# Kernels copy an array into a slice or row entry by entry (``put_state``), never ``a[i] = b`` with
# an array b: numba compiles that assignment with a formatter of its shape-mismatch message (string
# joins and copies, about 3,000 LLVM instructions), linked into every kernel that reaches it. Seven
# such lines had put it into 23 of 283 compiled modules; without them the first compile is ~8% shorter.

# A kernel that Python calls (the loop's entry points and the slip search's steps, ``camloc.loop``
# and ``camloc.seeds``): numba gives it a wrapper that unboxes Python's arguments.
entry = partial(numba.njit, **OPTIONS)

# A step called only from compiled code, without that wrapper: the wrapper of a function taking the
# scene unboxes its 31 arrays, and compiling it took longer than most steps' own code (0.33 s
# against 0.06 s a function). Dropping it from the 74 steps cut the first compile by about a tenth.
# Python (a test checking one step) calls one through ``from_python``.
jit = partial(numba.njit, no_cpython_wrapper=True, no_cfunc_wrapper=True, **OPTIONS)

# A step of a larger kernel, called only from compiled code, whose body numba copies into its
# callers: numba compiles every other function on its own, with the code of everything it calls
# optimized and generated once more, so that a deep call tree costs its depth times its size
# to compile. Inlining the middle of the tree (the beam's steps) cut the first compile 140 -> 120 s.
# A step called from several places (the beam's settle and options_of) is a plain ``jit`` again:
# inlined, its body was copied into every site (``explain_all`` 12-13 -> 8 s of its own to compile).
# The filter's re-check and oracle pairing, each called from one place, are inlined as well: the
# first compile 102 -> 90.5 s (since then the re-check grew, and its judging step ``recheck``, with
# the leave-one-out costs and margins inlined into it, is a ``jit`` of its own again: inlined into
# ``filter_poses`` it took numba's inlining pass 6.9 s, which grows with the caller's size; on its
# own, 1.1 s: a first compile of the world 99 -> 85 s of CPU, docs/performance.md,
# 2026-12-06 (sixteenth session)). The update's steps (point_step, correction, innovation_cost) saved 3 s
# more inlined but ran the beam about 2% slower, at the edge of this machine's noise: not kept; the
# steps of a restart only (point_step, restart_cost), which most updates never reach, are inlined.
# Small steps of one caller are inlined too (``condition``, ``settled``, ``seeds_worth_trying``), but
# not into ``explain_all``: a kernel's LLVM time grows faster than its size, and ``explain_all``
# inlined into ``run_poses`` (to compile it once, not also as an entry) took 142 s of CPU to
# compile where the two had taken 45 (docs/performance.md, 2026-12-05 (eighth session)).
# The leaves run once per candidate landmark (camera.observe_into, sym3.spread,
# beam.pair_in_best_coordinates) are inlined: a call that is not increfs every array it is passed
# on entry and decrefs it on return, which cost them more than their arithmetic (the warm 20k
# world 3.49 -> 3.09 s); a step run once per grid cell takes the two arrays it reads, not the scene.
# An inlined step's arguments are counted too, as it binds them, and numba's pruning pass removes
# those counts only where nothing between them and their release defeats it: a loop to a count read
# when it runs (a cycle), or a branch whose two arms release different arrays (LLVM merges the
# releases into one of either). With the planar state's size read from the arrays, both stood inside
# the candidates' loops and the 20k depth world's beam ran a fifth slower, its reference counts
# 3.3 times as many in ``condition_into``. Hence: the sensor's kind and the state's size pick the
# loop, not each step of one loop (``camera.predict_candidates``), and a size-long loop takes the
# size as a constant (``sym3.spread``) or counts to 6 skipping the smaller state's entries.
# Measured on the beam (docs/performance.md, 2026-12-05, "The beam's allocations and reference
# counts"): a small ``jit`` leaf is inlined by LLVM within its caller's module already, with no
# count; ``inlined`` tiny per-candidate leaves (``as_point``, ``is_taken``) made the beam 4% slower.
# A scratch array passed down, or a view of one, is counted as an allocated one costs (17 against
# 14 ns): a work handed through the update's calls cut the allocations a pose 3,350 -> 1,494 and ran
# 3-6% slower. What pays is fewer arrays passed to a non-inlined call (``types.PairModel``), and
# to an inlined step in a hot loop: ``explain_all``'s counts were mostly its inlined steps binding
# whole tuples (the scene's 31 arrays, a generation's 8) per partial explanation; passed the arrays
# they read, the 20k pixel world ran 10% faster (docs/performance.md, 2026-12-06, "The beam's bookkeeping").
inlined = partial(numba.njit, inline="always", **OPTIONS)

_FROM_PYTHON: dict = {}


def from_python(kernel):
    """``kernel`` callable from Python: itself where it has numba's wrapper (``entry``, ``inlined``),
    else the same function compiled once more with it (cached apart from the step's own code,
    which calls the same compiled steps). For tests and notebooks that check one step at a time."""
    if not kernel.targetoptions.get("no_cpython_wrapper", False):
        return kernel
    if kernel not in _FROM_PYTHON:
        function = kernel.py_func
        twin = types.FunctionType(function.__code__, function.__globals__, function.__name__, function.__defaults__,
                                  function.__closure__)
        # numba names a cache file by the function's qualified name: the twin must not share the step's
        twin.__qualname__ = function.__qualname__ + "__from_python"
        twin.__module__ = function.__module__
        twin.__doc__ = function.__doc__
        _FROM_PYTHON[kernel] = entry(twin)
    return _FROM_PYTHON[kernel]


class FromPython:
    """A kernel module whose every compiled function is callable from Python (``from_python``);
    its other names (constants, plain functions) are the module's own."""

    def __init__(self, module: types.ModuleType):
        self._module = module

    def __getattr__(self, name: str):
        value = getattr(self._module, name)
        return from_python(value) if isinstance(value, numba.core.registry.CPUDispatcher) else value


def address_of(kernel, argtypes) -> int:
    """The address of ``kernel``'s compiled code for ``argtypes`` (numba's calling convention),
    compiled or loaded from the cache first: what a kernel compiled with ``called`` asks the first
    time it runs in a process."""
    kernel.compile(argtypes)
    compiled = kernel.overloads[argtypes]
    return compiled.library.get_pointer_to_function(compiled.fndesc.llvm_func_name)


# The (kernel, argument types) a ``called(kernel, deferred=True)`` call site was typed for in this
# process: compiled only where the call first runs (``compile_deferred`` compiles them all).
DEFERRED: set = set()


def return_type_of(kernel, argtypes):
    """The type ``kernel`` returns for ``argtypes``, from numba's type inference alone (its own code
    not lowered nor given to LLVM; the kernels it calls are compiled, as typing a call compiles
    them); from its compiled overload where it has one (compiled or loaded from the cache)."""
    from numba.core import compiler
    from numba.core.typed_passes import NopythonTypeInference

    if argtypes in kernel.overloads:
        return kernel.overloads[argtypes].signature.return_type

    class TypesOnly(compiler.Compiler):
        """numba's pipeline, up to its type inference; its result the return type."""

        def define_pipelines(self):
            full = compiler.DefaultPassBuilder.define_nopython_pipeline(self.state)
            typing = compiler.PassManager("camloc types only")
            for pass_, description in full.passes:
                typing.add_pass(pass_, description)
                if pass_ is NopythonTypeInference:
                    break
            typing.add_pass(_ReturnType, "the inferred return type, as the result")
            typing.finalize()
            return [typing]

    front = kernel._compiler
    flags = compiler.Flags()
    front.targetdescr.options.parse_as_flags(flags, front.targetoptions)
    return compiler.compile_extra(front.targetdescr.typing_context, front.targetdescr.target_context, kernel.py_func, args=argtypes,
                                  return_type=None, flags=flags, locals=front.locals, pipeline_class=TypesOnly)


def compile_deferred() -> list:
    """Compile (and so cache) every kernel that a deferred call site typed in this process calls,
    for its argument types (the background compile's last step: the runs after it then compile
    nothing, whichever of those calls they reach). Returns the kernels."""
    for kernel, argtypes in list(DEFERRED):                # a copy: a compile may type more call sites
        kernel.compile(argtypes)
    return [kernel for kernel, _ in DEFERRED]


def called(kernel, deferred: bool = False):
    """``kernel``, called by its address, not linked: numba links every callee's compiled module
    into each caller's, where LLVM optimizes and generates it again; a call through this compiles
    the kernel once, in its own module (and its own cache file), and the caller's module holds a
    slot for its address, filled the first time the call runs in a process (by ``address_of``,
    holding the GIL), and an indirect call with numba's calling convention (exceptions propagate).

    ``deferred``: typing the caller infers the kernel's return type (``return_type_of``) but does
    not compile it: a kernel that a run may never reach (a rare branch's) is compiled where the
    call first runs, and ``compile_deferred`` compiles it for a background compile."""
    from llvmlite import ir
    from numba.core import cgutils
    from numba.core import types as nbtypes
    from numba.core.extending import intrinsic

    module_name, name = kernel.py_func.__module__, kernel.py_func.__name__

    @intrinsic
    def call(typingctx, *args):
        argtypes = tuple(nbtypes.unliteral(a) for a in args)
        if deferred:
            restype = return_type_of(kernel, argtypes)
            DEFERRED.add((kernel, argtypes))
        else:
            kernel.compile(argtypes)
            restype = kernel.overloads[argtypes].signature.return_type
        # numba passes a variadic intrinsic its arguments as one tuple
        signature = restype(nbtypes.StarArgTuple.from_types(argtypes))

        def codegen(context, builder, sig, packed):
            llargs = [builder.extract_value(packed[0], i) for i in range(len(argtypes))]
            fnty = context.call_conv.get_function_type(restype, argtypes)
            slot = cgutils.add_global_variable(builder.module, fnty.as_pointer(), f"camloc.address.{module_name}.{name}")
            slot.linkage = "internal"
            slot.initializer = ir.Constant(fnty.as_pointer(), None)
            with builder.if_then(cgutils.is_null(builder, builder.load(slot)), likely=False):
                pyapi = context.get_python_api(builder)
                gil = pyapi.gil_ensure()
                jit_module = pyapi.import_module(context.insert_const_string(builder.module, __name__))
                find = pyapi.object_getattr_string(jit_module, "address_of")
                home = pyapi.import_module(context.insert_const_string(builder.module, module_name))
                callee = pyapi.object_getattr_string(home, name)
                types_object = pyapi.unserialize(pyapi.serialize_object(argtypes))
                address = pyapi.call_function_objargs(find, (callee, types_object))
                with builder.if_else(cgutils.is_null(builder, address)) as (failed, found):
                    with failed:
                        pyapi.err_write_unraisable(find)   # printed; the call raises below
                    with found:
                        builder.store(builder.bitcast(pyapi.long_as_voidptr(address), fnty.as_pointer()), slot)
                        pyapi.decref(address)
                for obj in (types_object, callee, home, find, jit_module):
                    pyapi.decref(obj)
                pyapi.gil_release(gil)
            pointer = builder.load(slot)
            with builder.if_then(cgutils.is_null(builder, pointer), likely=False):
                context.call_conv.return_user_exc(builder, RuntimeError, (f"no address for {module_name}.{name}",))
            status, result = context.call_conv.call_function(builder, pointer, restype, argtypes, llargs)
            with cgutils.if_unlikely(builder, status.is_error):
                context.call_conv.return_status_propagate(builder, status)
            return result

        return signature, codegen

    return call


def _define_return_type_pass():
    """``return_type_of``'s last pass: ends numba's pipeline with the inferred return type."""
    from numba.core.compiler import _EarlyPipelineCompletion
    from numba.core.compiler_machinery import AnalysisPass, register_pass

    @register_pass(mutates_CFG=False, analysis_only=True)
    class ReturnType(AnalysisPass):
        _name = "camloc_return_type"

        def __init__(self):
            AnalysisPass.__init__(self)

        def run_pass(self, state):
            raise _EarlyPipelineCompletion(state.return_type)

    return ReturnType


_ReturnType = _define_return_type_pass()
