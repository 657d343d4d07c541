"""The mapping runs of small worlds of every kind, saved in one tree and compared with another's:
every association and landmark id equal, poses, covariances and the map within 1e-10 (a change
that should not change results: the mapping pass compiled, issue 38).

    nice python benchmarks/mapping_equal.py save /tmp/new.npz [force]
    PYTHONPATH=/path/to/other/tree nice python benchmarks/mapping_equal.py save /tmp/old.npz
    python benchmarks/mapping_equal.py compare /tmp/old.npz /tmp/new.npz

``force``: the compiled mapping steps on every world ("auto" takes them from 300 poses on)."""

from __future__ import annotations

import sys

import numpy as np

from camloc.simulate import simulate, SimulationConfig
from camloc.localizer import localize
from camloc.localizer_config import LocalizerConfig

WORLDS = [
    ("grid half withheld", dict(trajectory="grid", withhold_map=0.5), ("exact", "prior"), (0, 1)),
    ("smooth3d quarter moved", dict(trajectory="smooth3d", move_map=0.25), ("prior",), (0, 1)),
    ("aerial no map", dict(trajectory="aerial", no_map=True), ("none",), (0,)),
    ("pixel 2-camera withheld", dict(trajectory="smooth3d", measurement="pixel", cameras=2, withhold_map=0.5), ("exact", "prior"), (0,)),
    ("smooth3d 30% withheld 10% clutter", dict(trajectory="smooth3d", withhold_map=0.3, clutter_fraction=0.1), ("exact",), (0,)),
    ("disparity half withheld", dict(trajectory="grid", measurement="disparity", withhold_map=0.5), ("prior",), (0,)),
]
POSES = (200, 300)


def save(path):
    out = {}
    for name, kw, modes, seeds in WORLDS:
        for poses in POSES:
            for seed in seeds:
                try:
                    ds = simulate(SimulationConfig(poses=poses, **kw), seed=seed)
                except Exception as e:
                    print("skip", name, e); break
                for mode in modes:
                    r = localize(ds, LocalizerConfig(map=mode))
                    key = f"{name}|{poses}|{seed}|{mode}"
                    m = r.landmark_map
                    out[key + "|assoc"] = r.associations.landmark
                    out[key + "|xyz"] = r.estimate_xyz
                    out[key + "|quat"] = r.estimate_quat_xyzw
                    out[key + "|cov"] = r.estimate_cov
                    if m is not None:
                        out[key + "|map_ids"] = m.ids
                        out[key + "|map_xyz"] = m.xyz
                        out[key + "|map_cov"] = m.cov
                    print(key, r.summary["timing"].get("engine"), "added", (r.summary.get("map") or {}).get("added"), flush=True)
    np.savez(path, **out)


def compare(a, b):
    A, B = np.load(a), np.load(b)
    assert set(A.files) == set(B.files), set(A.files) ^ set(B.files)
    worst = {}
    bad = 0
    for k in sorted(A.files):
        x, y = A[k], B[k]
        if x.shape != y.shape:
            print("SHAPE", k, x.shape, y.shape); bad += 1; continue
        if k.endswith(("assoc", "map_ids")):
            if not np.array_equal(x, y):
                print("DIFFERENT", k, int(np.sum(x != y))); bad += 1
            continue
        d = float(np.max(np.abs(x - y))) if x.size else 0.0
        kind = k.rsplit("|", 1)[1]
        worst[kind] = max(worst.get(kind, 0.0), d)
        if d > 1e-10:
            print("OFF", k, d); bad += 1
    print(f"{len(A.files)} arrays, {bad} differing; largest differences: " + ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] not in ("save", "compare") or (sys.argv[1] == "compare" and len(sys.argv) < 4):
        sys.exit(__doc__)
    if "force" in sys.argv:  # the compiled mapping update on every world (auto takes it from 300 poses)
        from camloc import slam_run
        _original = slam_run.localize_mapping
        slam_run.localize_mapping = lambda *a, compiled=True, **k: _original(*a, compiled=True, **k)
    save(sys.argv[2]) if sys.argv[1] == "save" else compare(sys.argv[2], sys.argv[3])
