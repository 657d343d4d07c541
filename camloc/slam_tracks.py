"""Pixels no landmark explains, gathered until their rays fix a landmark (delayed initialization).

A pixel observation the association leaves unassigned (and that no landmark in view fits) may be
clutter or a landmark the map lacks; it gives a ray, not a point. It is kept in a **track** of
rays (the camera's centre and direction): a later one joins the track when they meet (every ray
within ``RAY_SIGMAS`` of its angular noise of the point nearest to all of them; rays from one
centre when they are parallel within that noise). A track becomes a landmark once it holds
``CONFIRM_OBSERVATIONS`` rays with ``MIN_PARALLAX_DEG`` of parallax and its first and latest rays
fix the depth well enough (``camloc.slam_anchors.MAX_DEPTH_SPREAD``); one not extended within
``TRACK_WINDOW`` poses is dropped. (An observation with range enters the state at once as a
tentative landmark instead: ``camloc.slam_landmarks``.)

The landmark is made from the track's first ray, cast from a pose kept in the filter's state for
it (a clone: ``camloc.slam_anchors``, ``camloc.slam_rays``), and its latest, with their joint
Jacobians: consistent whatever the odometry's drift between the two views. (Before, the track's
rays were triangulated as if the poses they were cast from were exact, and the landmark entered
from the latest ray with that depth: overconfident by far with an accurate camera, see
docs/performance.md.) The rays between the two are only what ties the track together.

Pure: no I/O, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

CONFIRM_OBSERVATIONS = 3
TRACK_WINDOW = 10
RAY_SIGMAS = 3.0
MIN_PARALLAX_DEG = 1.0


@dataclass
class Track:
    """Unassigned rays that meet.

    origins, directions : the rays' camera centres and unit directions (pixel observations).
    sigma_angle : each ray's angular standard deviation, radians.
    observations : observation indices; last_pose : the pose it last grew at.
    """

    last_pose: int
    observations: list = field(default_factory=list)
    origins: list = field(default_factory=list)
    directions: list = field(default_factory=list)
    sigma_angle: list = field(default_factory=list)


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

    def add_ray(self, k: int, obs: int, origin: np.ndarray, direction: np.ndarray, sigma_angle: float,
                fits: Optional[Callable[[list], bool]] = None) -> Track:
        """A pixel observation, the ray from ``origin`` along the unit ``direction``: joins a
        track whose rays it meets (and, given ``fits``, whose observations it fits otherwise: a
        tag's orientation), or starts one."""
        for track in self.tracks:
            if obs in track.observations or (fits is not None and not fits(track.observations)):
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
        return parallax_deg(np.array(track.directions)) >= MIN_PARALLAX_DEG

    def remove(self, track: Track) -> None:
        self.tracks = [t for t in self.tracks if t is not track]
