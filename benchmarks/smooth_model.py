"""Does the smoother's step model hold? For each step of a planar or 3-D smoothing (IRLS first,
then Newton; a rejected Newton step retried as IRLS, as ``camloc.smoother`` does), prints by
factor kind the model's predicted change of the cost, the robust cost of the linearized residuals
``r + J delta`` and the actual change, the observations crossing the Huber threshold, and those
the step carries past the apex of their cone (``camloc.huber_apex``) with their share of the
model's error (docs/performance.md, "The planar smoother with no map", 2026-12-04 (late), and
"The 3-D smoother with no map", 2026-12-05).

    nice python benchmarks/smooth_model.py WORLD.g2o RUN_DIR [--map none] [--steps 12] [--cut] [--apex]

``--cut``: each landmark's step cut as the smoother now cuts it (``smoother._landmark_line_search``);
without it, the full Newton step (the solver before the cut). ``--apex``: a Newton step that
carries observations past their apex is solved again with their IRLS rows and the cheaper of the
two taken, as the smoother now does (``smoother._apex_limited_step``).
"""

from __future__ import annotations

import argparse

import numpy as np

from camloc import geometry, planar
from camloc import smoother as S
from camloc.g2o import read_g2o
from camloc.huber_apex import past_apex
from camloc.measurement import KINDS
from camloc.results import load_run
from camloc.smoother import SmootherConfig, huber_rho, huber_weight, robust_cost
from camloc.smoother_se2 import planar_problem


def prepared(world: str, run_dir: str, mode: str):
    dataset, run = read_g2o(world), load_run(run_dir)
    if dataset.planar:
        problem = planar_problem(dataset, run, SmootherConfig(map=mode))
        x = planar.flatten(geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw))
        x[0] = problem.start_state
    else:
        problem = S.problem_from_run(dataset, run, SmootherConfig(map=mode))
        x = S.initial_poses(dataset, run)
    problem, _ = S._with_initial_landmarks(problem, x)
    problem, _ = S._without_unprojectable(problem, x)
    problem, _ = S._without_undetermined_landmarks(problem, x)
    return problem, x


def by_kind(problem, lin, change, f: float) -> dict[str, tuple[float, float, float]]:
    """Per kind: (the Newton model's change, the IRLS model's, the linearized residuals' robust cost change)."""
    M, start = len(lin.obs_sq), lin.odom_dim * len(lin.odom_sq)
    r, obs = lin.residual, slice(start, start + 3 * M)
    rb, jb = r[obs].reshape(-1, 3), change[obs].reshape(-1, 3)
    s, w = lin.obs_sq, huber_weight(lin.obs_sq, f)
    u = rb / np.sqrt(np.maximum(s, 1e-300))[:, None]
    first, quad = w * np.einsum("mi,mi->m", rb, jb), np.einsum("mi,mi->m", jb, jb)
    newton = first + 0.5 * w * np.where(s > f * f, quad - np.einsum("mi,mi->m", u, jb) ** 2, quad)
    irls = first + 0.5 * w * quad
    linearized = 0.5 * (huber_rho(np.einsum("mi,mi->m", rb + jb, rb + jb), f) - huber_rho(s, f))
    plain = r[:start] @ change[:start] + 0.5 * change[:start] @ change[:start]
    kind = np.zeros(M, dtype=np.int64) if problem.obs_kind is None else problem.obs_kind
    kinds = {KINDS[code].name: kind == code for code in np.unique(kind)}
    return {"odometry": (plain, plain, plain)} | {k: (newton[m].sum(), irls[m].sum(), linearized[m].sum()) for k, m in kinds.items()}


def apex_report(lin, step, f: float) -> str:
    """The observations the step carries past their apex, and their share of the Newton model's error."""
    past = past_apex(lin.residual, lin.jacobian, step, lin.odom_dim * len(lin.odom_sq), lin.obs_sq, f)
    first, M = lin.odom_dim * len(lin.odom_sq), len(lin.obs_sq)
    rb = lin.residual[first:first + 3 * M].reshape(-1, 3)
    jb = (lin.jacobian @ step)[first:first + 3 * M].reshape(-1, 3)
    s, w = lin.obs_sq, huber_weight(lin.obs_sq, f)
    u = rb / np.sqrt(np.maximum(s, 1e-300))[:, None]
    quad = np.einsum("mi,mi->m", jb, jb)
    newton = w * np.einsum("mi,mi->m", rb, jb) + 0.5 * w * np.where(s > f * f, quad - np.einsum("mi,mi->m", u, jb) ** 2, quad)
    error = 0.5 * (huber_rho(np.einsum("mi,mi->m", rb + jb, rb + jb), f) - huber_rho(s, f)) - newton
    return (f"past the apex {past.sum()}: linearized - Newton model {error[past].sum():+.5g} of {error.sum():+.5g} "
            f"(all observations)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("world")
    parser.add_argument("run_dir")
    parser.add_argument("--map", default="none")
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--cut", action="store_true")
    parser.add_argument("--apex", action="store_true")
    args = parser.parse_args()
    f = SmootherConfig().huber
    problem, x = prepared(args.world, args.run_dir, args.map)
    X = problem.landmarks.xyz if problem.landmarks is not None else None
    lin = problem.linearize(x, X)
    cost, majorize = robust_cost(lin, f), True
    for number in range(1, args.steps + 1):
        H, g = S.normal_equations(lin, f, newton=False) if majorize else S.newton_equations(problem, lin, f)
        Hs, d = S._scaled(H)
        num_pose = problem.num_pose_unknowns if problem.num_landmarks else problem.num_unknowns
        lu = S._factorization(Hs, num_pose)
        step = d * lu.solve(-d * g)
        limited = S._apex_limited_step(problem, lin, step, (lu, d), f, num_pose) if args.apex and not majorize else None
        notes = [f"    the full Newton step: {apex_report(lin, step, f)}"] if not majorize else []
        if args.cut and problem.num_landmarks:
            step = S._landmark_line_search(problem, lin, step, f)
        moved, moved_X = problem.retract(x, X, step)
        after = problem.linearize(moved, moved_X)
        new_cost = robust_cost(after, f)
        if limited is not None:
            if args.cut and problem.num_landmarks:
                limited = S._landmark_line_search(problem, lin, limited, f)
            other_x, other_X = problem.retract(x, X, limited)
            other = problem.linearize(other_x, other_X)
            notes.append(f"    stopped at the apexes: actual {robust_cost(other, f) - cost:+.6g} "
                         f"(the full Newton step's {new_cost - cost:+.6g})")
            if robust_cost(other, f) < new_cost:
                step, moved, moved_X, after, new_cost = limited, other_x, other_X, other, robust_cost(other, f)
        model = g @ step + 0.5 * step @ (H @ step)
        print(f"step {number} {'IRLS' if majorize else 'Newton'}: largest component {np.abs(step).max():.3g}, "
              f"model {model:+.6g}, actual {new_cost - cost:+.6g}")
        for note in notes:
            print(note)
        for kind, (newton, irls, linearized) in by_kind(problem, lin, lin.jacobian @ step, f).items():
            print(f"    {kind:8s} Newton model {newton:+.5g}  IRLS model {irls:+.5g}  linearized {linearized:+.5g}")
        beyond, beyond_after = lin.obs_sq > f * f, after.obs_sq > f * f
        print(f"    beyond the threshold {beyond.sum()} -> {beyond_after.sum()} "
              f"(in {np.sum(beyond & ~beyond_after)}, out {np.sum(~beyond & beyond_after)})", flush=True)
        if new_cost <= cost:
            x, X, lin, cost, majorize = moved, moved_X, after, new_cost, False
        else:
            majorize = True


if __name__ == "__main__":
    main()
