"""Pixel-only cameras on a map that lacks half its landmarks (issue 38, not solved): what was measured.

Worlds: ``camloc simulate --measurement pixel --cameras 2 --withhold-map 0.5`` (``--poses``, per
trajectory and seed), made in memory. Experiments (``--experiments``, comma-separated):

- ``screen``: rays screened as ``slam_landmarks.lacking_landmarks`` screens points: the exact map's
  run's rejected rays, placed through its estimate, gathered into tracks (``camloc.slam_tracks``);
  a track of 3 poses with 1 degree of parallax whose point lies more than 3 sigma from every mapped
  landmark is a place the map lacks one at. Printed for the complete map, the complete map with 10%
  clutter and half of it withheld: whether rays tell a lacking map from a complete one.
- ``diverge``: where the beam's run leaves the true association's (its error 0.3 m above the
  oracle's) and, before that, how many rays of landmarks the map lacks it paired with mapped ones.
- ``variants``: the beam with the null cost lowered by 4 (``localizer.LACKING_NULL_OFFSET``), the
  same with the mapping localizer taking its pairs (what screening rays would run), and the mapping
  localizer deciding every pair itself by JCBB.
- ``pseudo``: every ray given a depth, triangulated from the rays of its landmark within 5 poses
  through the odometry (a track's depth), as a depth camera's observation (variance 4x the
  triangulation's), then the default localizer (which then screens points, lowers the null cost and
  maps). Grouped by the file's landmark ids (``ids``: an upper bound, the grouping is the oracle's)
  or by ``slam_tracks.Tracks`` (``tracks``: what a localizer could do).
- ``bound``: the beam with every ray of a landmark the map lacks left out (the file's ids): what a
  perfect screening of rays would reach.
- ``depthz``: the beam's pairs up to 10 poses past where it leaves the true association's estimate,
  right and wrong, and how many the depth of the pair's track tells apart (the rays of the same
  true landmark within 5 poses triangulated through the run's poses, against the paired
  landmark's depth along the ray; the grouping is the oracle's).
- ``chunked``: screening as the run goes: the beam over the poses so far, then the latest 20
  poses' rays of ``slam_tracks.Tracks`` tracks far from every mapped landmark (placed through that
  estimate) left out of every later pass.
- ``chunked_ids``: the same every 10 poses, leaving out each pair whose track's depth (``depthz``,
  the oracle's grouping) disagrees with its landmark's by over 3 sigma: an upper bound of judging
  a pair by its track, pose by pose. Slow (6-10 min a world: a beam pass every 10 poses).

2026-12-04 (branch issue38-pixel-track): docs/performance.md, "Judging a pair by its track".

    nice python benchmarks/pixel_lacking.py --experiments screen,diverge --seeds 0,1,2,3
    nice python benchmarks/pixel_lacking.py --experiments variants,pseudo --trajectories grid --seeds 0
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from camloc import geometry, measurement
from camloc.association import PointIndex
from camloc.dataset import first_poses
from camloc.localizer import _localize_exact, localize
from camloc.localizer_config import LocalizerConfig
from camloc.observation_space import candidate_range, landmark_rows
from camloc.results import UNASSOCIATED
from camloc.sensors import sensors_of
from camloc.simulate import SimulationConfig, simulate_labelled
from camloc.slam_run import localize_mapping
from camloc.slam_tracks import Tracks, parallax_deg, triangulate

HOOKS = dict(parallel=False, engine="auto", on_compile=None, on_background_compile=None)
SCREEN_POSES, SCREEN_SIGMAS = 3, 3.0
PSEUDO_WINDOW, PSEUDO_INFLATION, PSEUDO_MAX_RELATIVE = 5, 4.0, 0.3


def world_rays(dataset, T_world_robot: np.ndarray, obs: np.ndarray):
    """Pixel observations ``obs`` (m,) as world rays through the poses (N, 4, 4): camera centres
    (m, 3), unit directions (m, 3), angular standard deviations (m,) in radians."""
    sensors, obs_sensor = sensors_of(dataset)
    origins, directions, sigmas = np.zeros((obs.size, 3)), np.zeros((obs.size, 3)), np.zeros(obs.size)
    for sensor_id in np.unique(obs_sensor[obs]).tolist():
        at = obs_sensor[obs] == sensor_id
        mine, sensor = obs[at], sensors[sensor_id]
        fx, fy, cx, cy = sensor.intrinsics[:4]
        z = dataset.obs_z[mine]
        T = T_world_robot[dataset.obs_pose_index[mine]] @ sensor.T_robot_camera
        d = np.einsum("nij,nj->ni", T[:, :3, :3], np.stack([(z[:, 0] - cx) / fx, (z[:, 1] - cy) / fy, np.ones(mine.size)], axis=1))
        origins[at], directions[at] = T[:, :3, 3], d / np.linalg.norm(d, axis=1, keepdims=True)
        cov = dataset.obs_cov[mine]
        sigmas[at] = np.sqrt(np.maximum(cov[:, 0, 0] / fx**2, cov[:, 1, 1] / fy**2))
    return origins, directions, sigmas


def lacking_from_rays(dataset, T_world_robot: np.ndarray, pose_cov: np.ndarray, rejected: np.ndarray) -> int:
    """How many places away from every mapped landmark the rejected rays meet at (``screen``)."""
    return len(lacking_tracks(dataset, T_world_robot, pose_cov, rejected))


def lacking_tracks(dataset, T_world_robot: np.ndarray, pose_cov: np.ndarray, screened: np.ndarray) -> list:
    """The tracks (observation indices) of the ``screened`` rays that meet away from every mapped landmark."""
    obs = np.flatnonzero(screened & measurement.is_ray(dataset.obs_kind))
    obs = obs[np.argsort(dataset.obs_pose_index[obs], kind="stable")]
    origins, directions, sigmas = world_rays(dataset, T_world_robot, obs)
    landmarks = PointIndex(dataset.landmark_xyz)
    min_depth, max_depth, _ = candidate_range(dataset, LocalizerConfig())
    tracks, places = Tracks(0.0, min_depth, max_depth), []
    for n, o in enumerate(obs.tolist()):
        k = int(dataset.obs_pose_index[o])
        tracks.expire(k)
        track = tracks.add_ray(k, o, origins[n], directions[n], float(sigmas[n]))
        poses = np.unique(dataset.obs_pose_index[track.observations])
        if poses.size < SCREEN_POSES or not tracks.confirmed(track):
            continue
        tracks.remove(track)  # a place counted once
        fix = triangulate(np.array(track.origins), np.array(track.directions), np.array(track.sigma_angle))
        if fix is None:
            continue
        cov = fix[1] + pose_cov[poses, :3, :3].mean(axis=0)
        near = landmarks.within(fix[0], SCREEN_SIGMAS * float(np.sqrt(np.linalg.eigvalsh(cov)[-1])))
        offsets = landmarks.points[near] - fix[0]
        if np.all(np.einsum("ni,ij,nj->n", offsets, np.linalg.inv(cov), offsets) > SCREEN_SIGMAS**2):
            places.append(list(track.observations))
    return places


def world(trajectory: str, seed: int, poses: int, **options):
    return simulate_labelled(SimulationConfig(trajectory=trajectory, poses=poses, measurement="pixel", cameras=2, **options), seed=seed).dataset


def rmse(dataset, result) -> float:
    return float(np.sqrt(np.mean(np.sum((result.estimate_xyz - dataset.truth_xyz) ** 2, axis=1))))


def screen(trajectory: str, seed: int, poses: int) -> None:
    for name, options in [("complete", {}), ("complete, 10% clutter", {"clutter_fraction": 0.1}), ("half withheld", {"withhold_map": 0.5})]:
        ds = world(trajectory, seed, poses, **options)
        run = _localize_exact(ds, LocalizerConfig(), None, **HOOKS)
        rejected = run.associations.landmark == UNASSOCIATED
        places = lacking_from_rays(ds, geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw), run.estimate_cov, rejected)
        print(f"{trajectory}/{seed} | screen | {name} | rays rejected {int(rejected.sum())} | places {places}", flush=True)


def diverge(trajectory: str, seed: int, poses: int) -> None:
    ds = world(trajectory, seed, poses, withhold_map=0.5)
    beam = _localize_exact(ds, LocalizerConfig(), None, **HOOKS)
    oracle = _localize_exact(ds, LocalizerConfig(association="oracle"), None, **HOOKS)
    error = np.linalg.norm(beam.estimate_xyz - ds.truth_xyz, axis=1)
    worse = np.flatnonzero(error - np.linalg.norm(oracle.estimate_xyz - ds.truth_xyz, axis=1) > 0.3)
    first = int(worse[0]) if worse.size else ds.num_poses
    before = ds.obs_pose_index < first
    paired, truth = beam.associations.landmark, ds.obs_true_landmark
    mapped = np.isin(truth, ds.landmark_ids)
    print(f"{trajectory}/{seed} | diverge | beam {rmse(ds, beam):.3f} m, oracle {rmse(ds, oracle):.3f} m | leaves it at pose {first} | "
          f"before: rays of mapped landmarks {int(np.sum(before & mapped))} (right {int(np.sum(before & mapped & (paired == truth)))}, "
          f"left out {int(np.sum(before & mapped & (paired < 0)))}), of lacking ones {int(np.sum(before & ~mapped))} "
          f"(paired with mapped ones {int(np.sum(before & ~mapped & (paired >= 0)))})", flush=True)


def variants(trajectory: str, seed: int, poses: int) -> None:
    ds = world(trajectory, seed, poses, withhold_map=0.5)
    config = LocalizerConfig(map="exact")
    for name in ("beam, null -4", "beam null -4, mapping", "mapping, JCBB"):
        started = time.perf_counter()
        if name == "mapping, JCBB":
            result = localize_mapping(ds, replace(config, association="jcbb"))
        else:
            result = _localize_exact(ds, config, None, null_cost_offset=4.0, **HOOKS)
            if name.endswith("mapping"):
                result = localize_mapping(ds, config, None, landmark_rows(ds.landmark_ids, result.associations.landmark))
        print(f"{trajectory}/{seed} | variants | {name} | {rmse(ds, result):.3f} m | {time.perf_counter() - started:.1f} s", flush=True)


def subset(dataset, kept: np.ndarray):
    """``dataset`` with only the observations ``kept`` (K,) bool (no tag orientations)."""
    fields = ("obs_pose_index", "obs_camera", "obs_z", "obs_info", "obs_cov", "obs_true_landmark", "obs_kind", "obs_partner")
    return replace(dataset, **{name: getattr(dataset, name)[kept] for name in fields})


def veto(trajectory: str, seed: int, poses: int) -> None:
    """Every ray screened through the last pass's estimate; the rays of tracks far from the map
    are left out of the next beam pass (the map's pairs of the others decided again)."""
    ds = world(trajectory, seed, poses, withhold_map=0.5)
    run, kept = _localize_exact(ds, LocalizerConfig(), None, **HOOKS), np.ones(ds.num_observations, bool)
    figures = [f"{rmse(ds, run):.3f}"]
    mapped = np.isin(ds.obs_true_landmark, ds.landmark_ids)
    for _ in range(3):
        T = geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw)
        far = [o for track in lacking_tracks(ds, T, run.estimate_cov, np.ones(ds.num_observations, bool)) for o in track]
        kept = np.ones(ds.num_observations, bool)
        kept[far] = False
        run = _localize_exact(subset(ds, kept), LocalizerConfig(), None, **HOOKS)
        figures.append(f"{rmse(ds, run):.3f} (left out: {int(np.sum(~kept & ~mapped))} rays of lacking, {int(np.sum(~kept & mapped))} of mapped)")
    print(f"{trajectory}/{seed} | veto | {' -> '.join(figures)}", flush=True)


def odometry_poses(dataset) -> np.ndarray:
    T = [dataset.T_world_start]
    for increment in dataset.T_odometry:
        T.append(T[-1] @ increment)
    return np.array(T)


def groups_by_tracks(dataset, obs: np.ndarray, origins, directions, sigmas) -> dict:
    """Each ray's fellow rays (observation indices), by ``slam_tracks.Tracks`` over the rays in order."""
    min_depth, max_depth, _ = candidate_range(dataset, LocalizerConfig())
    tracks, track_of = Tracks(0.0, min_depth, max_depth), {}
    for n in np.argsort(dataset.obs_pose_index[obs], kind="stable").tolist():
        k = int(dataset.obs_pose_index[obs[n]])
        tracks.expire(k)
        track_of[int(obs[n])] = tracks.add_ray(k, int(obs[n]), origins[n], directions[n], float(sigmas[n]))
    return {o: np.array(t.observations) for o, t in track_of.items()}


def with_pseudo_depth(dataset, grouping: str):
    """The rays as depth observations where their group's triangulation fixes a depth (``pseudo``)."""
    obs = np.flatnonzero(measurement.is_ray(dataset.obs_kind))
    T = odometry_poses(dataset)
    origins, directions, sigmas = world_rays(dataset, T, obs)
    row = {int(o): n for n, o in enumerate(obs.tolist())}
    if grouping == "ids":
        ids, k = dataset.obs_true_landmark, dataset.obs_pose_index
        groups = {int(o): obs[(ids[obs] == ids[o]) & (np.abs(k[obs] - k[o]) <= PSEUDO_WINDOW)] for o in obs.tolist()}
    else:
        groups = groups_by_tracks(dataset, obs, origins, directions, sigmas)
    z, cov, kind = dataset.obs_z.copy(), dataset.obs_cov.copy(), dataset.obs_kind.copy()
    for o, group in groups.items():
        rows = [row[int(g)] for g in group]
        if len(rows) < 3 or parallax_deg(directions[rows]) < 1.0:
            continue
        fix = triangulate(origins[rows], directions[rows], sigmas[rows])
        if fix is None:
            continue
        T_camera = T[dataset.obs_pose_index[o]] @ dataset.cameras[int(dataset.obs_camera[o])].T_robot_camera
        axis = T_camera[:3, 2]
        depth, variance = float(axis @ (fix[0] - T_camera[:3, 3])), PSEUDO_INFLATION * float(axis @ fix[1] @ axis)
        if depth > 0.05 and np.sqrt(variance) <= PSEUDO_MAX_RELATIVE * depth:
            z[o, 2], cov[o, 2, :], cov[o, :, 2], cov[o, 2, 2] = depth, 0.0, 0.0, variance
            kind[o] = measurement.DEPTH
    return replace(dataset, obs_z=z, obs_cov=cov, obs_info=np.linalg.inv(cov), obs_kind=kind), float(np.mean(kind[obs] == measurement.DEPTH))


def pseudo(trajectory: str, seed: int, poses: int) -> None:
    ds = world(trajectory, seed, poses, withhold_map=0.5)
    for grouping in ("ids", "tracks"):
        started = time.perf_counter()
        given, share = with_pseudo_depth(ds, grouping)
        result = localize(given, LocalizerConfig(map="exact"))
        print(f"{trajectory}/{seed} | pseudo depth, grouped by {grouping} | rays given a depth {share:.2f} | {rmse(ds, result):.3f} m | "
              f"{time.perf_counter() - started:.1f} s", flush=True)


# --- 2026-12-04 (branch issue38-pixel-track): the track lead measured ---------------------------

TRACK_WINDOW_POSES, DEPTH_Z = 5, 3.0


def _depth_z(dataset, run_T, run_cov, o: int, landmark_xyz: np.ndarray, group: np.ndarray):
    """How far (in sigmas) the depth along ray ``o`` at which its ``group`` of rays meets (placed
    through the run's poses ``run_T``; placed by the odometry relative to ``o``'s pose instead, in
    a scratch version, it flagged 30% of the right pairs on grid 0: the odometry's drift) is from
    ``landmark_xyz``'s depth along it (its variance: the triangulation's, 4x, and the pose's along
    the ray); nan where the group fixes no point (under 3 rays or 0.5 degree of parallax)."""
    if group.size < 3:
        return np.nan
    k = int(dataset.obs_pose_index[o])
    origins, directions, sigmas = world_rays(dataset, run_T, group)
    if parallax_deg(directions) < 0.5:
        return np.nan
    fix = triangulate(origins, directions, sigmas)
    if fix is None:
        return np.nan
    m = int(np.flatnonzero(group == o)[0])
    d = directions[m]
    depth, variance = float(d @ (fix[0] - origins[m])), PSEUDO_INFLATION * float(d @ fix[1] @ d)
    along = float(d @ run_cov[k][:3, :3] @ d)
    return (depth - float(d @ (landmark_xyz - origins[m]))) / np.sqrt(variance + along)


def bound(trajectory: str, seed: int, poses: int) -> None:
    """The beam with every ray of a landmark the map lacks left out (the file's ids): what a
    perfect screening of rays would give."""
    ds = world(trajectory, seed, poses, withhold_map=0.5)
    mapped = np.isin(ds.obs_true_landmark, ds.landmark_ids)
    run = _localize_exact(subset(ds, mapped), LocalizerConfig(), None, **HOOKS)
    print(f"{trajectory}/{seed} | bound | lacking rays left out: beam {rmse(ds, run):.3f} m", flush=True)


def depthz(trajectory: str, seed: int, poses: int) -> None:
    """The beam's pairs up to 10 poses past where it leaves the true association's estimate:
    right and wrong ones, and how many a track's depth tells apart (``_depth_z`` over the rays of
    the same true landmark within ``TRACK_WINDOW_POSES``: the grouping is the oracle's)."""
    ds = world(trajectory, seed, poses, withhold_map=0.5)
    beam = _localize_exact(ds, LocalizerConfig(), None, **HOOKS)
    oracle = _localize_exact(ds, LocalizerConfig(association="oracle"), None, **HOOKS)
    worse = np.flatnonzero(np.linalg.norm(beam.estimate_xyz - ds.truth_xyz, axis=1)
                           - np.linalg.norm(oracle.estimate_xyz - ds.truth_xyz, axis=1) > 0.3)
    first = int(worse[0]) if worse.size else ds.num_poses
    T = geometry.pose_from_quat(beam.estimate_xyz, beam.estimate_quat_xyzw)
    rays = np.flatnonzero(measurement.is_ray(ds.obs_kind))
    paired, truth, k = beam.associations.landmark, ds.obs_true_landmark, ds.obs_pose_index
    xyz = dict(zip(ds.landmark_ids.tolist(), ds.landmark_xyz))
    rows = {"right": [], "wrong": []}
    for o in np.flatnonzero((paired >= 0) & (k < first + 10)).tolist():
        group = rays[(truth[rays] == truth[o]) & (np.abs(k[rays] - k[o]) <= TRACK_WINDOW_POSES)]
        rows["wrong" if paired[o] != truth[o] else "right"].append(abs(_depth_z(ds, T, beam.estimate_cov, o, xyz[int(paired[o])], group)))
    text = []
    for name, z in rows.items():
        z = np.array(z)
        known = np.isfinite(z)
        text.append(f"{name} {z.size} (depth known {np.mean(known):.2f}, over {DEPTH_Z:g} sigma {np.mean(z[known] > DEPTH_Z) if known.any() else 0:.2f})")
    print(f"{trajectory}/{seed} | depthz | leaves at pose {first} | {' | '.join(text)}", flush=True)


def chunked(trajectory: str, seed: int, poses: int, chunk: int = 20, ids: bool = False) -> None:
    """Screening as the run goes: the beam over the poses so far (rays left out so far left out),
    then the latest ``chunk`` poses' rays screened through its estimate and left out of every later
    pass: by ``lacking_tracks`` (rays of tracks far from every mapped landmark), or with ``ids`` by
    ``_depth_z`` of each pair over its true landmark's rays (the oracle's grouping: an upper bound
    of judging a pair by its track)."""
    ds = world(trajectory, seed, poses, withhold_map=0.5)
    kept, k, truth = np.ones(ds.num_observations, bool), ds.obs_pose_index, ds.obs_true_landmark
    rays = np.flatnonzero(measurement.is_ray(ds.obs_kind))
    xyz = dict(zip(ds.landmark_ids.tolist(), ds.landmark_xyz))
    for t in range(chunk, ds.num_poses + chunk, chunk):
        part = first_poses(ds, min(t, ds.num_poses))
        n = part.num_observations  # the observations are in pose order
        run = _localize_exact(subset(part, kept[:n]), LocalizerConfig(), None, **HOOKS)
        T = geometry.pose_from_quat(run.estimate_xyz, run.estimate_quat_xyzw)
        if ids:
            paired = np.full(n, -1)
            paired[kept[:n]] = run.associations.landmark
            mine = rays[rays < n]
            for o in np.flatnonzero((paired >= 0) & (k[:n] >= t - chunk)).tolist():
                group = mine[(truth[mine] == truth[o]) & (np.abs(k[mine] - k[o]) <= TRACK_WINDOW_POSES)]
                if abs(_depth_z(part, T, run.estimate_cov, o, xyz[int(paired[o])], group)) > DEPTH_Z:
                    kept[o] = False
        else:
            screened = kept[:n] & (k[:n] >= t - chunk - 10)
            for track in lacking_tracks(part, T, run.estimate_cov, screened):
                kept[[o for o in track if k[o] >= t - chunk]] = False
    run = _localize_exact(subset(ds, kept), LocalizerConfig(), None, **HOOKS)
    mapped = np.isin(truth, ds.landmark_ids)
    print(f"{trajectory}/{seed} | chunked{' ids' if ids else ''} | {rmse(ds, run):.3f} m | left out: rays of lacking landmarks "
          f"{int(np.sum(~kept & ~mapped))} of {int(np.sum(~mapped))}, of mapped ones {int(np.sum(~kept & mapped))} of {int(np.sum(mapped))}", flush=True)


def chunked_ids(trajectory: str, seed: int, poses: int) -> None:
    chunked(trajectory, seed, poses, chunk=10, ids=True)


EXPERIMENTS = {"screen": screen, "diverge": diverge, "variants": variants, "pseudo": pseudo, "veto": veto,
               "bound": bound, "depthz": depthz, "chunked": chunked, "chunked_ids": chunked_ids}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trajectories", default="grid,smooth3d,aerial")
    parser.add_argument("--seeds", default="0,1,2,3")
    parser.add_argument("--poses", type=int, default=300)
    parser.add_argument("--experiments", default="screen,diverge", help=f"of {','.join(EXPERIMENTS)}")
    args = parser.parse_args()
    for trajectory in args.trajectories.split(","):
        for seed in [int(s) for s in args.seeds.split(",")]:
            for name in args.experiments.split(","):
                EXPERIMENTS[name](trajectory, seed, args.poses)


if __name__ == "__main__":
    main()
