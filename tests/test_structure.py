"""The code's shape, kept (issue 35): no import cycle among camloc's modules (an import inside a
function counts: it is a cycle deferred, not removed), no class over 250 lines, no function over
80, and the compiled engine does not reach into the numpy one. Read from the sources with ``ast``,
without importing them."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# The folders parsed, and the package each one is installed as (cli/ is camloc.cli: pyproject.toml).
PACKAGES = {"camloc": "camloc", "cli": "camloc.cli"}

MAX_CLASS_LINES = 250
MAX_FUNCTION_LINES = 80

# The compiled engine: the loop, the run's fixed arrays, the seed search over the kernels, the kernels.
COMPILED = ("camloc.loop", "camloc.scene", "camloc.seeds", "camloc.kernels")
# The numpy engine's own modules: the localizer, its update, association and the numpy beam.
NUMPY_ENGINE = ("camloc.localizer", "camloc.stacked_update", "camloc.association", "camloc.associators", "camloc.jcbb",
                "camloc.replay", "camloc.beam", "camloc.beam_types", "camloc.beam_expansion", "camloc.beam_seeded",
                "camloc.pair_options")


def _modules() -> dict[str, tuple[Path, ast.Module]]:
    """Dotted name -> (file, syntax tree) of every module of camloc/ and cli/."""
    out = {}
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = path.relative_to(ROOT / folder).with_suffix("").parts
            name = ".".join((package, *parts)).removesuffix(".__init__")
            out[name] = (path, ast.parse(path.read_text(encoding="utf-8"), filename=str(path)))
    return out


MODULES = _modules()


def _imported(name: str, path: Path, tree: ast.Module) -> set[str]:
    """The camloc modules ``name`` imports anywhere in its file (inside functions too): for
    ``from package import x``, the submodule ``package.x`` where x is one, else ``package``."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            for alias in node.names:
                found.add(f"{target}.{alias.name}" if f"{target}.{alias.name}" in MODULES else target)
    return {m for m in found if m in MODULES and m != name}


IMPORTS = {name: _imported(name, path, tree) for name, (path, tree) in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, edges = work[-1]
            child = next(edges, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_the_cycle_finder_finds_a_lazy_cycle_and_passes_a_chain():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    lazy = ast.parse("def f():\n    from camloc import beam\n")
    assert "camloc.beam" in _imported("camloc.x", ROOT / "camloc" / "x.py", lazy)


def test_no_module_imports_itself_through_others():
    assert _cycles(IMPORTS) == []


def _definitions(kind: type) -> list[tuple[int, str]]:
    """(lines, module.qualified name) of every definition of ``kind`` in camloc/ and cli/."""
    out = []
    for name, (_, tree) in MODULES.items():
        for node in ast.walk(tree):
            if isinstance(node, kind):
                out.append((node.end_lineno - node.lineno + 1, f"{name}.{node.name}"))
    return out


def test_no_class_is_longer_than_250_lines():
    assert [(n, what) for n, what in _definitions(ast.ClassDef) if n > MAX_CLASS_LINES] == []


def test_no_function_is_longer_than_80_lines():
    functions = _definitions(ast.FunctionDef) + _definitions(ast.AsyncFunctionDef)
    assert [(n, what) for n, what in functions if n > MAX_FUNCTION_LINES] == []


def _reachable(name: str) -> set[str]:
    seen, todo = set(), [name]
    while todo:
        for module in IMPORTS[todo.pop()]:
            if module not in seen:
                seen.add(module)
                todo.append(module)
    return seen


def _in(name: str, packages: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in packages)


@pytest.mark.parametrize("module", sorted(m for m in MODULES if _in(m, COMPILED)))
def test_the_compiled_engine_does_not_reach_into_the_numpy_one(module):
    # directly or through any module it imports: what both engines need lives in modules of its
    # own (camloc.observation_space, camloc.constants, camloc.measurement, ...)
    assert sorted(m for m in _reachable(module) if _in(m, NUMPY_ENGINE)) == []
