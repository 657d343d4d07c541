"""Observations no landmark explains, gathered until they agree on a new one (delayed initialization).

An observation the association leaves unassigned may be clutter or a landmark the map lacks. It
is kept as a **track**: a world point (an observation with range: the point it measures, with the
robot's uncertainty and its own noise) or a ray (a pixel: the camera's centre and direction). A
later unassigned observation that agrees with a track joins it (within the chi^2 gate of a point,
or, for rays, when they meet: every ray within ``RAY_SIGMAS`` of its angular noise of the point
nearest to all of them). A track becomes a landmark once it holds ``CONFIRM_OBSERVATIONS``
observations (and, of rays, parallax enough to fix the depth: ``MIN_PARALLAX_DEG``); one not
extended within ``TRACK_WINDOW`` poses is dropped. Clutter, uniform over what the cameras see,
almost never repeats at one place, so it stays a track and expires.

Why delayed and not inverse depth: the landmark enters the filter's state from the observation at
the pose that confirms it, through the inverse observation (a point's own noise plus the robot's
translation error: consistent in the invariant error, ``camloc.slam``). A ray gives no depth: its
depth then comes from the track's triangulation (its standard deviation widened by
``DEPTH_VARIANCE_INFLATION`` for the drift between the views, which the triangulation takes as
exact), so the earlier views contribute only the depth and the filter never counts a measurement
twice. Inverse depth would enter every ray at once, but as a 6-parameter landmark the filter's
models (and the smoother's) would carry only for rays; the delay costs a few poses per landmark.

Pure: no I/O, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

CONFIRM_OBSERVATIONS = 3
TRACK_WINDOW = 10
RAY_SIGMAS = 3.0
MIN_PARALLAX_DEG = 1.0
DEPTH_VARIANCE_INFLATION = 4.0


@dataclass
class Track:
    """Unassigned observations that agree with one another.

    point, point_cov : (3,), (3, 3) the latest point measured (observations with range), or None.
    origins, directions : the rays' camera centres and unit directions (pixel observations).
    sigma_angle : each ray's angular standard deviation, radians.
    observations : observation indices; last_pose : the pose it last grew at.
    """

    last_pose: int
    observations: list = field(default_factory=list)
    point: np.ndarray | None = None
    point_cov: np.ndarray | None = None
    origins: list = field(default_factory=list)
    directions: list = field(default_factory=list)
    sigma_angle: list = field(default_factory=list)

    @property
    def is_ray(self) -> bool:
        return self.point is None


def triangulate(origins: np.ndarray, directions: np.ndarray, sigma_angle: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The point nearest to every ray (m, 3) in the least-squares sense of their angular noise,
    and its covariance (3, 3); None where the rays fix no point (one centre, or parallel)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for o, d, s in zip(origins, directions, sigma_angle):
        perpendicular = np.eye(3) - np.outer(d, d)
        # a ray's angular noise is a perpendicular spread growing with range: weigh by the
        # distance to the current guess (one pass from the unweighted point is enough here)
        A += perpendicular / (s * s)
        b += perpendicular @ o / (s * s)
    w = np.linalg.eigvalsh(A)
    if w[0] <= 1e-9 * w[-1]:
        return None
    point = np.linalg.solve(A, b)
    A, b = np.zeros((3, 3)), np.zeros(3)
    for o, d, s in zip(origins, directions, sigma_angle):
        r2 = max(float((point - o) @ (point - o)), 1e-6)
        perpendicular = np.eye(3) - np.outer(d, d)
        A += perpendicular / (s * s * r2)
        b += perpendicular @ o / (s * s * r2)
    w = np.linalg.eigvalsh(A)
    if w[0] <= 1e-9 * w[-1]:
        return None
    point = np.linalg.solve(A, b)
    return point, np.linalg.inv(A)


def rays_meet(origins: np.ndarray, directions: np.ndarray, sigma_angle: np.ndarray, min_depth: float,
              max_depth: float) -> np.ndarray | None:
    """The point where rays from two or more centres meet (in front of every one, within the depth
    range, each ray within ``RAY_SIGMAS`` of its noise of it), or None where they do not."""
    fix = triangulate(origins, directions, sigma_angle)
    if fix is None:
        return None
    point = fix[0]
    offsets = point - origins
    along = np.einsum("ij,ij->i", offsets, directions)
    if np.any(along < max(min_depth, 1e-3)) or np.any(along > max_depth):
        return None
    distance = np.linalg.norm(offsets, axis=1)
    angle = np.arccos(np.clip(along / distance, -1.0, 1.0))
    return point if np.all(angle <= RAY_SIGMAS * np.asarray(sigma_angle)) else None


def parallel_within_noise(directions: np.ndarray, sigma_angle: np.ndarray) -> bool:
    """Rays from one centre agree when every one is within ``RAY_SIGMAS`` of the first's noise."""
    cosines = np.clip(directions @ directions[0], -1.0, 1.0)
    return bool(np.all(np.arccos(cosines) <= RAY_SIGMAS * np.sqrt(2.0) * np.asarray(sigma_angle)))


def parallax_deg(directions: np.ndarray) -> float:
    """The widest angle between two of the rays (degrees)."""
    cosines = np.clip(directions @ directions.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cosines.min())))


class Tracks:
    """The tracks of a run (``Track``), matched and confirmed as observations arrive."""

    def __init__(self, gate: float, min_depth: float, max_depth: float):
        self.gate, self.min_depth, self.max_depth = gate, min_depth, max_depth
        self.tracks: list[Track] = []

    def expire(self, k: int) -> None:
        """Drop the tracks not extended within ``TRACK_WINDOW`` poses of pose k."""
        self.tracks = [t for t in self.tracks if k - t.last_pose <= TRACK_WINDOW]

    def add_point(self, k: int, obs: int, point: np.ndarray, cov: np.ndarray, drift) -> Track:
        """An observation with range measuring ``point`` (3,) with covariance ``cov`` (its own
        noise): joins the nearest track it agrees with (chi^2 gate, 3 dof), or starts one.
        ``drift(poses, point)``: the covariance (3, 3) of how far the robot's estimate may have
        moved relative to itself over that many poses, as seen at ``point`` (both observations are
        made from the robot: only its motion between them separates them, not its place)."""
        best, best_d2 = None, self.gate
        for track in self.tracks:
            if track.is_ray:
                continue
            offset = point - track.point
            d2 = float(offset @ np.linalg.solve(cov + track.point_cov + drift(k - track.last_pose, point), offset))
            if d2 < best_d2:
                best, best_d2 = track, d2
        if best is None:
            best = Track(last_pose=k)
            self.tracks.append(best)
        best.observations.append(obs)
        best.point, best.point_cov, best.last_pose = point, cov, k
        return best

    def add_ray(self, k: int, obs: int, origin: np.ndarray, direction: np.ndarray, sigma_angle: float) -> Track:
        """A pixel observation, the ray from ``origin`` along the unit ``direction``: joins a
        track whose rays it meets, or starts one."""
        for track in self.tracks:
            if not track.is_ray or obs in track.observations:
                continue
            origins = np.array(track.origins + [origin])
            directions = np.array(track.directions + [direction])
            sigmas = np.array(track.sigma_angle + [sigma_angle])
            one_centre = np.allclose(origins, origins[0], atol=1e-9)
            if (parallel_within_noise(directions, sigmas) if one_centre
                    else rays_meet(origins, directions, sigmas, self.min_depth, self.max_depth) is not None):
                track.origins.append(origin)
                track.directions.append(direction)
                track.sigma_angle.append(sigma_angle)
                track.observations.append(obs)
                track.last_pose = k
                return track
        track = Track(last_pose=k, observations=[obs], origins=[origin], directions=[direction], sigma_angle=[sigma_angle])
        self.tracks.append(track)
        return track

    def confirmed(self, track: Track) -> bool:
        """Whether the track holds enough observations (and, of rays, parallax) to be a landmark."""
        if len(track.observations) < CONFIRM_OBSERVATIONS:
            return False
        return not track.is_ray or parallax_deg(np.array(track.directions)) >= MIN_PARALLAX_DEG

    def remove(self, track: Track) -> None:
        self.tracks = [t for t in self.tracks if t is not track]
