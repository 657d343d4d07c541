"""What the kernels take: the run's fixed arrays (``SceneArrays``, built by ``camloc.scene``) and
its settings (``Settings``), as named tuples that numba passes by reference."""

from __future__ import annotations

from collections import namedtuple

SceneArrays = namedtuple("SceneArrays", [
    # the map and its spatial index (a uniform grid hash: ``camloc.kernels.view``)
    "landmark_xyz",        # (L, 3) world frame; a planar robot's map (L, 4): a marker's heading (radians) fourth, 0 for others
    "landmark_sensor_kind",  # (L,) int64 the planar kind that observes each landmark (point2, marker), -1 for a camera's
    "grid_origin",         # (3,) corner of cell (0, 0, 0)
    "grid_cell",           # (1,) side of a cell, metres
    "grid_dims",           # (3,) int64 cells along x, y, z
    "grid_keys",           # (G,) int64 sorted keys of the occupied cells
    "grid_start",          # (G + 1,) int64 offsets of each cell's landmarks in grid_items
    "grid_items",          # (L,) int64 landmark indices, cell by cell
    "grid_xyz",            # (L, 3) their coordinates in that order (a query reads them in sequence)
    "grid_dense_start",    # (nx ny nz + 1,) int64 offsets by key where the grid is small, else empty
    # cameras
    # a row per sensor: a camera and its measurements' kind (``sensors.sensors_of``)
    "camera_R", "camera_t", "camera_K",   # (C, 3, 3) R_robot_camera, (C, 3) t, (C, 5) fx fy cx cy kind
    # observations
    "obs_camera",          # (K,) int64 row of the camera (sensor) tables
    "z",                   # (K, 3) the measurement (``camloc.measurement``'s layout: u, v, depth / 0 / 1/depth)
    "R_file",              # (K, 3, 3) the file's noise: what the estimate weighs pairs by
    "R_file_inverse",      # (K, 3, 3) its information
    "R_assoc",             # (K, 3, 3) the noise association judges pairs by (floored, ``observation_space.noise_floored``)
    "R_assoc_inverse",     # (K, 3, 3)
    "log_det_R",           # (K,) ln det R_assoc
    "point",               # (K, 3) each observation as a camera-frame point
    "point_cov",           # (K, 3, 3) its covariance (from R_assoc)
    "point_cov_inverse",   # (K, 3, 3)
    "log_det_point_cov",   # (K,)
    "null_cost",           # (K,) cost of leaving the observation unassigned
    "true_index",          # (K,) int64 landmark index of the file's id, -1 where not in the map
    "pose_obs",            # (K,) int64 observations, pose by pose (in file order within a pose)
    "pose_obs_start",      # (N + 1,) int64 offsets into pose_obs
    # odometry
    "T_increment",         # (N - 1, 4, 4)
    "odom_cov",            # (N - 1, 6, 6)
    # view limits and consistency bounds
    "view_limits",         # (7,) min_depth, max_depth, max_angle (rad), the detection range (low, high:
                           # ``observation_space.detection_range``; 0, 0 without pixel observations), the
                           # planar sensors' range (``observation_space.planar_range``; 0 without them), and
                           # the candidates' distance from the camera (``candidate_distance``; inf: no bound)
    "nis_bound",           # (3 P + 4,) the 99.9% chi^2 quantile of d degrees of freedom, by d
    "obs_gate",            # (K,) the chi^2 gate of each observation's pairs, at its dof
    "obs_dof",             # (K,) int64 each observation's degrees of freedom
])

# What an update and a pair's cost read of the scene (``update.updated``, ``update.point_step``,
# ``beam.condition_into``; built by ``update.pair_model``): a kernel that is not inlined counts a
# reference to every array it is passed, on entry and on return, and the beam's updates and
# conditioned options (about a hundred of each a pose on a pixel-only world) were passed the
# scene's 31 where they read these 16.
PairModel = namedtuple("PairModel", [
    "z", "obs_camera", "obs_dof", "nis_bound", "obs_gate",    # the observations, their dof, chi^2 bounds and gates
    "landmark_xyz", "camera_R", "camera_t", "camera_K",       # the map and the sensors
    "R_assoc", "R_assoc_inverse", "log_det_R",                # the pairs' noise as association judges them
    "point", "point_cov", "point_cov_inverse", "log_det_point_cov",   # each observation as a camera-frame point
])

Settings = namedtuple("Settings", [
    "iterations",           # int: linearizations per update
    "recheck",              # bool
    "recheck_margin", "recheck_steal_margin", "recheck_ray_margin",
    "slip_inflation",
    # the beam
    "beam_width", "beam_delta", "branch_delta", "merge_sigma", "slip_cost", "partial_budget",
    "pool_gate_factor",
    "null_offset",          # how much the scene's null cost was lowered: the null option's viability is
                            # judged before it (``beam_types.BeamSettings.null_offset``)
])
