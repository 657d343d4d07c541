"""Which landmarks a camera may see: a uniform grid hash of the map, queried with the smallest
ball around the view cone, then the cone's own test. The cost grows with the landmarks near the
view, not with the map (the numpy twin is ``camloc.association.candidate_indices`` over a k-d tree).
A planar robot's own sensor (point2, marker) sees the landmarks of its kind within a radius of the
robot (``landmarks_near``; the numpy twin ``AssociationScene._visible_planar``).
"""

from __future__ import annotations

import math

import numpy as np

from camloc.constants import MAX_HALF_ANGLE_DEG, WIDENED_VIEW_SIGMAS
from camloc.kernels._jit import FIRST, entry, inlined, jit
from camloc.kernels.camera import camera_pose
from camloc.kernels.planar import SE2_DIM
from camloc.kernels.small import sorted_ints
from camloc.measurement import MARKER, POINT2

# Cells per axis at most, so that a cell's key (ix + nx (iy + ny iz)) fits in 63 bits.
MAX_CELLS_PER_AXIS = 1 << 20
# Up to this many cells in all, a table by key finds a cell's landmarks without a binary search.
MAX_DENSE_CELLS = 1 << 22


def build_grid(landmark_xyz: np.ndarray, cell: float):
    """(origin (3,), cell (1,), dims (3,), keys (G,), start (G + 1,), items (L,), their
    coordinates (L, 3), offsets by key (nx ny nz + 1,) or empty) of a grid hash of landmarks
    (L, 3) with cells of side ``cell`` (widened where the map's extent would need more than
    ``MAX_CELLS_PER_AXIS`` cells on an axis)."""
    if landmark_xyz.shape[0] == 0:
        return (np.zeros(3), np.ones(1), np.ones(3, np.int64), np.zeros(0, np.int64), np.zeros(1, np.int64), np.zeros(0, np.int64),
                np.zeros((0, 3)), np.zeros(0, np.int64))
    origin = landmark_xyz.min(axis=0)
    extent = landmark_xyz.max(axis=0) - origin
    cell = max(float(cell), float(extent.max()) / (MAX_CELLS_PER_AXIS - 1), 1e-9)
    index = np.minimum(np.floor((landmark_xyz - origin) / cell).astype(np.int64), MAX_CELLS_PER_AXIS - 1)
    dims = index.max(axis=0) + 1
    key = index[:, 0] + dims[0] * (index[:, 1] + dims[1] * index[:, 2])
    items = np.argsort(key, kind="stable").astype(np.int64)
    keys, start = np.unique(key[items], return_index=True)
    dense = np.zeros(0, np.int64)
    if int(np.prod(dims)) <= MAX_DENSE_CELLS:
        dense = np.searchsorted(key[items], np.arange(int(np.prod(dims)) + 1)).astype(np.int64)
    return (origin, np.array([cell]), dims.astype(np.int64), keys.astype(np.int64), np.append(start, items.size).astype(np.int64), items,
            np.ascontiguousarray(landmark_xyz[items], dtype=float), dense)


@entry
def view_cone_ball(apex, axis, depth, half_angle):
    """The smallest ball (centre (3,), radius) holding a view cone: apex, unit axis, points up to
    ``depth`` along it within ``half_angle`` of it. Up to 45 deg it passes through the apex and
    the base's rim; wider, it is the base's rim ball."""
    along, radius = cone_ball_along(depth, half_angle)
    return apex + along * axis, radius


@jit
def cone_ball_along(depth, half_angle):
    """``view_cone_ball``'s ball as (the distance of its centre from the apex along the axis, its
    radius): scalars, for ``visible``, which runs per hypothesis and camera."""
    half_angle = min(half_angle, math.radians(89.9))
    cos = math.cos(half_angle)
    if cos * cos >= 0.5:
        along = depth / (2.0 * cos * cos)
        radius = along
    else:
        along = depth
        radius = depth * math.tan(half_angle)
    return along, radius * (1.0 + 1e-9) + 1e-9


@jit
def visible(scene, R_wc, centre, max_angle, margin):
    """Sorted indices of the landmarks in the view of a camera at (R_wc, centre): depth within
    (min_depth, max_depth) and within ``max_angle`` of the optical axis, within the candidates'
    distance of the camera (``view_limits[6]``, where given); with ``margin`` metres the camera's
    position may be off, every landmark that close to the view too. The cone's axis, apex, ball
    and cell range are scalars, not arrays: this runs per hypothesis and camera, and each array
    was an allocation and its reference counts (eight a call)."""
    min_depth, max_depth = scene.view_limits[0], scene.view_limits[1]
    max_distance = scene.view_limits[6] + margin if scene.view_limits.shape[0] > 6 else np.inf
    axis = (R_wc[0, 2], R_wc[1, 2], R_wc[2, 2])
    back = margin / math.sin(max_angle) if margin > 0.0 else 0.0
    apex = (centre[0] - back * axis[0], centre[1] - back * axis[1], centre[2] - back * axis[2])
    reach = max_depth + margin + back
    along, radius = cone_ball_along(reach, max_angle)
    ball = (apex[0] + along * axis[0], apex[1] + along * axis[1], apex[2] + along * axis[2])
    cone = (math.tan(max_angle), math.cos(max_angle), math.sin(max_angle))
    found = np.empty(256, np.int64)
    count = FIRST    # a counter passed to kernels: int64 from the start (see FIRST)
    cell, origin, dims = scene.grid_cell[0], scene.grid_origin, scene.grid_dims
    lo0, hi0 = cell_range(ball[0], radius, origin[0], cell, dims[0])
    lo1, hi1 = cell_range(ball[1], radius, origin[1], cell, dims[1])
    lo2, hi2 = cell_range(ball[2], radius, origin[2], cell, dims[2])
    if hi0 < lo0 or hi1 < lo1 or hi2 < lo2:
        return found[:0]
    cells = (hi0 - lo0 + 1) * (hi1 - lo1 + 1) * (hi2 - lo2 + 1)
    keys = scene.grid_keys
    dense = scene.grid_dense_start.size > 0
    scan_all = cells > keys.size                       # a ball wider than the map: visit occupied cells
    n_keys = keys.size if scan_all else cells
    for q in range(n_keys):
        if scan_all:
            key = keys[q]
            ix, rest = key % dims[0], key // dims[0]
            iy, iz = rest % dims[1], rest // dims[1]
            if ix < lo0 or ix > hi0 or iy < lo1 or iy > hi1 or iz < lo2 or iz > hi2:
                continue
            first, stop = scene.grid_start[q], scene.grid_start[q + 1]
        else:
            nx, ny = hi0 - lo0 + 1, hi1 - lo1 + 1
            ix, iy, iz = lo0 + q % nx, lo1 + (q // nx) % ny, lo2 + q // (nx * ny)
            key = ix + dims[0] * (iy + dims[1] * iz)
            if dense:
                first, stop = scene.grid_dense_start[key], scene.grid_dense_start[key + 1]
            else:
                g = np.searchsorted(keys, key)
                if g >= keys.size or keys[g] != key:
                    continue
                first, stop = scene.grid_start[g], scene.grid_start[g + 1]
        if stop == first or not cell_near_cone(origin, cell, ix, iy, iz, apex, axis, reach, cone[1], cone[2], min_depth - margin):
            continue
        if count + (stop - first) > found.size:
            grown = np.empty(2 * (count + stop - first), np.int64)
            for i in range(count):
                grown[i] = found[i]
            found = grown
        count = cone_members(scene.grid_xyz, scene.grid_items, first, stop, R_wc, centre, ball, radius, min_depth - margin,
                             max_depth + margin, back, cone[0], max_distance * max_distance, found, count)
    return sort_distinct_in_place(found[:count])


@jit
def cell_range(ball_a, radius, origin_a, cell, dim_a):
    """The grid cells (first, last) a ball (its centre's coordinate ``ball_a``, ``radius``) spans on
    one axis; last < first where it misses the grid."""
    return (max(0, int(math.floor((ball_a - radius - origin_a) / cell))),
            min(dim_a - 1, int(math.floor((ball_a + radius - origin_a) / cell))))


# Up to this many, a view's landmarks are sorted in place by insertion (no array allocated); more,
# by ``small.sorted_ints``. Their indices are distinct: any sort gives the one order.
SMALL_VIEW_SORT = 64


@jit
def sort_distinct_in_place(values):
    """``values`` (distinct int64) sorted: in place by insertion up to ``SMALL_VIEW_SORT`` of them,
    else ``sorted_ints``' (a new array)."""
    if values.size > SMALL_VIEW_SORT:
        return sorted_ints(values)
    for i in range(1, values.size):
        v = values[i]
        j = i
        while j > 0 and v < values[j - 1]:
            values[j] = values[j - 1]
            j -= 1
        values[j] = v
    return values


@jit
def cone_members(grid_xyz, grid_items, first, stop, R_wc, centre, ball, radius, min_depth, max_depth, back, tan, distance2,
                 found, count):
    """Append the landmarks first..stop-1 of the grid's order (``scene.grid_xyz``, ``grid_items``)
    that lie in the ball (its centre ``ball``, a tuple) and the view
    (depth within (min_depth, max_depth), within the cone widened ``back`` metres behind the
    camera, their squared distance from it at most ``distance2``) to found (room for all of them) from ``count``; returns the new count. Without
    branches: which side of each test a landmark falls on is a coin toss the CPU would guess
    wrong half the time."""
    b0, b1, b2, c0, c1, c2 = ball[0], ball[1], ball[2], centre[0], centre[1], centre[2]
    r2 = radius * radius
    for s in range(first, stop):
        l0, l1, l2 = grid_xyz[s, 0], grid_xyz[s, 1], grid_xyz[s, 2]
        d0, d1, d2 = l0 - b0, l1 - b1, l2 - b2
        v0, v1, v2 = l0 - c0, l1 - c1, l2 - c2
        px = R_wc[0, 0] * v0 + R_wc[1, 0] * v1 + R_wc[2, 0] * v2
        py = R_wc[0, 1] * v0 + R_wc[1, 1] * v1 + R_wc[2, 1] * v2
        depth = R_wc[0, 2] * v0 + R_wc[1, 2] * v1 + R_wc[2, 2] * v2
        cone_radius = (depth + back) * tan
        inside = ((d0 * d0 + d1 * d1 + d2 * d2 <= r2) & (depth > min_depth) & (depth < max_depth) & (cone_radius >= 0.0)
                  & (px * px + py * py <= cone_radius * cone_radius) & (v0 * v0 + v1 * v1 + v2 * v2 <= distance2))
        found[count] = grid_items[s]
        count += inside
    return count


@jit
def cell_near_cone(origin, cell, ix, iy, iz, apex, axis, depth, cos_half_angle, sin_half_angle, min_depth):
    """Whether grid cell (ix, iy, iz) may hold a point of the view cone (apex, unit axis (tuples),
    points up to ``depth`` along it and beyond ``min_depth``, within the half-angle of it): its ball's distance
    to the cone is at most its radius (a conservative test: a cell it keeps may hold none)."""
    h = 0.8660254037844386 * cell                      # half the cell's diagonal
    v0 = origin[0] + (ix + 0.5) * cell - apex[0]
    v1 = origin[1] + (iy + 0.5) * cell - apex[1]
    v2 = origin[2] + (iz + 0.5) * cell - apex[2]
    along = v0 * axis[0] + v1 * axis[1] + v2 * axis[2]
    if along < min(min_depth, 0.0) - h or along > depth + h:
        return False
    p0, p1, p2 = v0 - along * axis[0], v1 - along * axis[1], v2 - along * axis[2]
    perp = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    # signed distance to the cone's side: perp cos - along sin (negative inside)
    return perp * cos_half_angle - along * sin_half_angle <= h


@entry
def widened_view(P, max_angle):
    """(margin metres, half-angle) of a view widened by three standard deviations of the
    position and of the orientation of P, for a prior too wide for the data's own margins (a
    planar state's: of (x, y) and of the heading)."""
    if P.shape[0] == SE2_DIM:
        margin = WIDENED_VIEW_SIGMAS * math.sqrt(max(np.linalg.eigvalsh(np.ascontiguousarray(P[:2, :2]))[-1], 0.0))
        widened = max_angle + WIDENED_VIEW_SIGMAS * math.sqrt(max(P[2, 2], 0.0))
        return margin, max(max_angle, min(widened, math.radians(MAX_HALF_ANGLE_DEG)))
    margin = WIDENED_VIEW_SIGMAS * math.sqrt(max(np.linalg.eigvalsh(np.ascontiguousarray(P[:3, :3]))[-1], 0.0))
    widened = max_angle + WIDENED_VIEW_SIGMAS * math.sqrt(max(np.linalg.eigvalsh(np.ascontiguousarray(P[3:6, 3:6]))[-1], 0.0))
    return margin, max(max_angle, min(widened, math.radians(MAX_HALF_ANGLE_DEG)))


@inlined
def sensor_candidates(scene, x, c, max_angle, margin):
    """Sorted landmarks sensor c (a row of the scene's sensor tables) may see from state x: a
    camera's in its view (``visible``; on a planar robot, only the 3-D points and tags: the floor's
    landmarks are its own sensor's), a planar sensor's those of its kind within its range
    (``view_limits[5]``) of the robot; ``margin`` metres widen either. Inlined: a call taking the
    scene counts a reference to each of its arrays (``_jit``), and this runs per hypothesis."""
    kind = scene.camera_K[c, 4]
    if kind == POINT2 or kind == MARKER:
        return landmarks_near(scene, x[0], x[1], scene.view_limits[5] + margin, kind)
    R_wc, centre = camera_pose(x, scene.camera_R[c], scene.camera_t[c])
    found = visible(scene, R_wc, centre, max_angle, margin)
    if x.shape[0] == SE2_DIM:
        found = found[scene.landmark_sensor_kind[found] < 0]
    return found


@jit
def landmarks_near(scene, x0, x1, radius, kind):
    """Sorted indices of the landmarks that sensor ``kind`` (point2 or marker) observes
    (``scene.landmark_sensor_kind``) within ``radius`` of (x0, x1, 0), through the grid."""
    cell, origin, dims = scene.grid_cell[0], scene.grid_origin, scene.grid_dims
    centre = (x0, x1, 0.0)
    lo, hi = np.empty(3, np.int64), np.empty(3, np.int64)
    for a in range(3):
        lo[a] = max(0, int(math.floor((centre[a] - radius - origin[a]) / cell)))
        hi[a] = min(dims[a] - 1, int(math.floor((centre[a] + radius - origin[a]) / cell)))
        if hi[a] < lo[a]:
            return np.empty(0, np.int64)
    found = np.empty(64, np.int64)
    count = 0
    r2 = radius * radius
    for ix in range(lo[0], hi[0] + 1):
        for iy in range(lo[1], hi[1] + 1):
            for iz in range(lo[2], hi[2] + 1):
                key = ix + dims[0] * (iy + dims[1] * iz)
                if scene.grid_dense_start.size > 0:
                    first, stop = scene.grid_dense_start[key], scene.grid_dense_start[key + 1]
                else:
                    g = np.searchsorted(scene.grid_keys, key)
                    if g >= scene.grid_keys.size or scene.grid_keys[g] != key:
                        continue
                    first, stop = scene.grid_start[g], scene.grid_start[g + 1]
                for q in range(first, stop):
                    d0, d1, d2 = scene.grid_xyz[q, 0] - x0, scene.grid_xyz[q, 1] - x1, scene.grid_xyz[q, 2]
                    landmark = scene.grid_items[q]
                    if d0 * d0 + d1 * d1 + d2 * d2 <= r2 and scene.landmark_sensor_kind[landmark] == kind:
                        if count == found.size:
                            grown = np.empty(2 * count, np.int64)
                            for i in range(count):
                                grown[i] = found[i]
                            found = grown
                        found[count] = landmark
                        count += 1
    return sorted_ints(found[:count])
