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

Settings = namedtuple("Settings", [
    "iterations",           # int: linearizations per update
    "recheck",              # bool
    "recheck_margin", "recheck_steal_margin",
    "slip_inflation",
    # the beam
    "beam_width", "beam_delta", "branch_delta", "merge_sigma", "slip_cost", "partial_budget",
    "pool_gate_factor",
    "null_offset",          # how much the scene's null cost was lowered: the null option's viability is
                            # judged before it (``beam_types.BeamSettings.null_offset``)
])

# The scratch of iterated updates of up to p pairs (``update.update_work``): a caller that updates
# many times (the beam's pose, the filter's run) allocates it once and passes it down, where each
# update allocated its own 27 small arrays, more time than its 6 x 6 arithmetic. Arrays whose
# first axis is the pairs' are used as views of their first p rows; those of 3p x 3p or n x 3p
# (the few pairs' textbook gain, 3p <= n) are flat, reshaped per call.
UpdateWork = namedtuple("UpdateWork", [
    "z", "R", "R_inverse", "landmark_xyz", "pair_camera",   # the pairs' measurements, noise, landmarks, cameras (``updated``)
    "R_inverse_H", "information", "M", "pivots", "AP", "g",  # the information form (``information_into``)
    "PHt", "S", "L", "K", "stacked",                         # the textbook gain (``gain_into``), flat
    "z_hat", "H", "r",                                       # each linearization's predictions and residual
    "d_position", "frame_R", "frame_E", "frame_t",           # ``observe_pairs_into``'s scratch
    "delta", "step", "moved",                                # the iterations' steps (n,)
    "square", "square2", "column",                           # (n, n), (n, n), (n, 1) scratch of the posterior and MAP cost
    "none",                                                  # an empty start (``updated``'s ``start``: none)
])
