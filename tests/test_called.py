"""A kernel called by its address, not linked into its callers (``camloc.kernels._jit.called``):
the same results as the direct call, its exceptions raised through, its code absent from the
caller's module, and both cached: a second process loads them and compiles nothing."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np

from camloc.kernels import _jit, update
from camloc.kernels import beam_chain as compiled_chain

_KERNELS = textwrap.dedent('''
    import numpy as np
    from camloc.kernels._jit import called, entry, jit

    @jit
    def scaled(x, P, k):
        if k < 0:
            raise ValueError("k < 0")
        s = 0.0
        for i in range(x.size):
            s += x[i] * P[i, i] * k
        return x * s, P.copy()

    scaled_at = called(scaled)

    @entry
    def by_address(x, P, k):
        return scaled_at(x, P, k)

    @entry
    def direct(x, P, k):
        return scaled(x, P, k)

    @jit
    def rare(x, k):
        return x * k, k + 1

    rare_at = called(rare, deferred=True)

    @entry
    def sometimes(x, k):
        if k > 100:
            return rare_at(x, k)[0].sum()
        return 0.0

    @entry
    def caught(x, P, k):
        try:
            return scaled_at(x, P, k)[0].sum()
        except Exception:
            return -1.0
''')

_RUN = textwrap.dedent('''
    import numpy as np
    import pointer_kernels as m
    x, P, k = np.arange(1.0, 4.0), np.diag([1.0, 2.0, 3.0]), np.int64(2)
    a, b = m.by_address(x, P, k)
    c, d = m.direct(x, P, k)
    assert np.array_equal(a, c) and np.array_equal(b, d)
    assert m.caught(x, P, np.int64(-1)) == -1.0
    try:
        m.by_address(x, P, np.int64(-1))
        raise AssertionError("not raised")
    except ValueError as error:
        assert "k < 0" in str(error)
    sometimes_compiled = len(m.rare.signatures)
    assert m.sometimes(x, np.int64(1)) == 0.0 and len(m.rare.signatures) == 0      # typed, not compiled, not reached
    assert m.sometimes(x, np.int64(101)) == 606.0 and len(m.rare.signatures) == 1   # compiled where first reached
    sig = m.by_address.signatures[0]
    defined = [line for line in m.by_address.inspect_llvm(sig).splitlines() if line.startswith("define") and "scaled" in line]
    print(len(defined), sum(m.by_address.stats.cache_misses.values()), sum(m.scaled.stats.cache_misses.values()),
          sum(m.by_address.stats.cache_hits.values()), sum(m.scaled.stats.cache_hits.values()),
          sum(m.rare.stats.cache_misses.values()), sum(m.rare.stats.cache_hits.values()), sometimes_compiled)
''')


def test_a_kernel_called_by_address_is_the_direct_call_compiled_once_and_cached(tmp_path):
    (tmp_path / "pointer_kernels.py").write_text(_KERNELS)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=str(tmp_path))
    runs = [subprocess.run([sys.executable, "-c", _RUN], env=env, capture_output=True, text=True, cwd=tmp_path)
            for _ in range(2)]
    for run in runs:
        assert run.returncode == 0, run.stderr
    # first process: both compiled, the callee's code not in the caller's module, the deferred
    # callee only once reached; second: all loaded
    assert runs[0].stdout.split() == ["0", "1", "1", "0", "0", "1", "0", "0"]
    assert runs[1].stdout.split()[1:] == ["0", "0", "1", "1", "0", "1", "0"]


@_jit.entry
def _checked_by_address(model, iterations, x, P, root_x, root_P, pairs, first, count):
    return compiled_chain.checked_at(model, iterations, x, P, root_x, root_P, pairs, first, count)


def test_the_beam_s_chain_check_by_address_is_the_direct_call_bit_for_bit():
    from camloc.localizer import LocalizerConfig
    from camloc.scene import build_scene, build_settings
    from camloc.simulate import SimulationConfig, simulate

    dataset = simulate(SimulationConfig(poses=12, cameras=2, measurement="pixel", intrinsics="pixel", trajectory="smooth3d",
                                        odometry_sigma_scale=3.0), seed=201)
    config = LocalizerConfig()
    scene, settings = build_scene(dataset, config), build_settings(config)
    model = update.pair_model(scene)
    rng = np.random.default_rng(5)
    k = 6
    obs = np.flatnonzero(dataset.obs_pose_index == k)[:4].astype(np.int64)
    pairs = np.c_[obs, rng.integers(0, dataset.landmark_ids.size, obs.size)].astype(np.int64)
    root_x = np.r_[dataset.truth_xyz[k], 0.1, -0.05, 0.2]
    root_P = np.diag([0.3**2] * 3 + [np.radians(3.6) ** 2] * 3)
    for x in (root_x + 0.5, root_x + 0.01):                     # a chain far off (checked again) and one near
        args = (model, settings.iterations, x, root_P * 0.01, root_x, root_P, pairs, np.int64(0), np.int64(obs.size))
        direct = _jit.from_python(compiled_chain.checked)(*args)
        again = _checked_by_address(*args)
        assert np.array_equal(direct[0], again[0]) and np.array_equal(direct[1], again[1])
