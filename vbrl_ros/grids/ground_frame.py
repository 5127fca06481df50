"""A sensor-independent frame: each scan levelled on its own ground, heights measured from it.

Real sensors sit 0.5-2.5 m above the ground and hand-held ones tilt 20 degrees and more,
so height bands fixed to the sensor mean different things on different robots. Each scan
is rotated so that the ground plane under it is horizontal (heading kept) and shifted so
that the ground is at z = 0: the same place then gives the same heights whatever carried
the sensor.

The ground is the plane through the lowest points of most ~1 m columns around the sensor:
a RANSAC over those lowest points (a fixed sample sequence, so a scan always gives the same
frame) that prefers planes with few points below them, refined by least squares on its
inliers. The search reaches ``MAX_TILT_DEG``; a hand-held sensor held steeper (up to
``MAX_HELD_TILT_DEG``) is levelled by fitting again in the frame the last fit levelled, and, when
no plane in reach held enough of the lowest points, by searches started tilted towards
several headings. With a
gravity rotation (odometry's roll and pitch) only the height is fitted. Without a ground in
sight (indoors on a mast, a sensor looking up) the scan keeps its tilt and its lowest points
stand in for the ground.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

CELL_M = 1.0  # lowest-point cell: wide enough to reach the ground between objects
MIN_RANGE_M, MAX_RANGE_M = 1.0, 30.0
INLIER_M = 0.15
MAX_TILT_DEG = 30.0
#: A fit tilted more than this is fitted again in the frame it levelled, up to MAX_REFITS times:
#: the ground of a sensor tilted near or beyond MAX_TILT_DEG lies at the edge of the search.
REFIT_TILT_DEG = 15.0
MAX_REFITS = 3
#: No frame tilts the scan further than this: a hand-held sensor is held steeper than a wall is
#: tilted, and a wall must never become the ground.
MAX_HELD_TILT_DEG = 45.0
#: Without a plane within MAX_TILT_DEG that holds this fraction of the lowest points, the search
#: starts again this many times, tilted by MAX_TILT_DEG towards evenly spaced headings. The
#: ground seen from a simulated mount holds far more; the best plane in reach of a sensor held at
#: 35 degrees, far fewer.
MIN_SUPPORT = 0.2
STEEP_STARTS = 8
HYPOTHESES = 128
MIN_INLIERS = 8
FALLBACK_HEIGHT_M = (0.3, 3.0)  # without a ground plane: the lowest points, within these bounds


@dataclass(frozen=True)
class GroundFrame:
    """Rotation R (sensor -> levelled) and the sensor's height h above the ground:
    p_levelled = R p_sensor + (0, 0, h)."""

    rotation: np.ndarray  # (3, 3)
    height: float
    found: bool  # False: no ground plane was found (see the module docstring)
    # the top of the sensor's field of view (elevation, radians, its own frame) where the height
    # map mirrors it (vbrl_ros.features.field_of_view); NaN: not read
    field_top: float = math.nan

    @classmethod
    def identity(cls) -> "GroundFrame":
        """The sensor's own frame (grids with ``frame="sensor"``)."""
        return cls(np.eye(3), 0.0, False)

    @property
    def matrix(self) -> np.ndarray:
        """The 4x4 homogeneous transform sensor -> levelled."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[2, 3] = self.height
        return T

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N, 3+) sensor-frame points in this frame, as float64 (N, 3)."""
        xyz = np.asarray(points, dtype=np.float64)[:, :3] @ self.rotation.T
        xyz[:, 2] += self.height
        return xyz


@njit(cache=True, nogil=True)
def lowest_points(points, cell, min_range, max_range):
    """The lowest finite point of every occupied cell x cell column within the range ring,
    float64; ``points`` (N, 3+) float32 or float64 (read as float64: no converted copy)."""
    n_side = int(2.0 * max_range / cell) + 1
    low = np.full(n_side * n_side, np.inf)
    idx = np.full(n_side * n_side, -1, np.int64)
    r0, r1 = min_range * min_range, max_range * max_range
    for i in range(points.shape[0]):
        x, y, z = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            continue
        rr = x * x + y * y
        if rr < r0 or rr >= r1:
            continue
        c = int((x + max_range) / cell) * n_side + int((y + max_range) / cell)
        if z < low[c]:
            low[c] = z
            idx[c] = i
    count = 0
    for c in range(idx.shape[0]):
        if idx[c] >= 0:
            count += 1
    out = np.empty((count, 3))
    k = 0
    for c in range(idx.shape[0]):
        if idx[c] >= 0:
            for a in range(3):
                out[k, a] = points[idx[c], a]
            k += 1
    return out


def _rotation_onto_z(normal: np.ndarray) -> np.ndarray:
    """The rotation taking the unit vector ``normal`` onto +z that keeps the heading: the
    sensor's x axis still points the same way in the horizontal plane (the smallest rotation
    would turn it by up to ~2 degrees under a combined roll and pitch of 20 degrees)."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(normal, z)
    s, c = float(np.linalg.norm(axis)), float(normal @ z)
    if s < 1e-12:
        return np.eye(3)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return _without_yaw(np.eye(3) + k + k @ k * ((1.0 - c) / (s * s)))


def _without_yaw(R: np.ndarray) -> np.ndarray:
    """``R`` turned about z so that its x axis has no heading: Rz(-yaw) R."""
    yaw = math.atan2(R[1, 0], R[0, 0])
    c, s = math.cos(-yaw), math.sin(-yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R


def _sample_triples(n: int, count: int) -> np.ndarray:
    rng = np.random.default_rng(0x5EED)  # fixed: the same scan always gives the same frame
    return rng.integers(0, n, size=(count, 3))  # repeated indices give no normal: dropped


@njit(cache=True, nogil=True, inline="always")
def _above(columns, k, normal, height):
    """Height of lowest point ``k`` (``columns``: (3, n) x, y, z) above the plane."""
    return columns[0, k] * normal[0] + columns[1, k] * normal[1] + columns[2, k] * normal[2] + height


@njit(cache=True, nogil=True)
def _plane_scores(columns, normals, heights):
    """(H,) score of every plane: the ground has most lowest points on it and few below it
    (below = a wrong, raised plane). One pass per plane, no (cells, H) temporaries."""
    score = np.zeros(normals.shape[0], np.int64)
    for h in range(normals.shape[0]):
        total = 0
        for k in range(columns.shape[1]):
            signed = _above(columns, k, normals[h], heights[h])
            total += (1 if abs(signed) < INLIER_M else 0) - (3 if signed < -3 * INLIER_M else 0)
        score[h] = total
    return score


@njit(cache=True, nogil=True)
def _plane_inliers(columns, normal, height):
    """(n,) bool: the lowest points within ``INLIER_M`` of the plane, as :func:`_plane_scores` counts them."""
    inliers = np.empty(columns.shape[1], np.bool_)
    for k in range(columns.shape[1]):
        inliers[k] = abs(_above(columns, k, normal, height)) < INLIER_M
    return inliers


def fit_ground(low: np.ndarray, max_tilt_deg: float = MAX_TILT_DEG) -> tuple[np.ndarray, float] | None:
    """(unit normal with n_z > 0, height of the origin above the plane) or None.

    The hypotheses are scored in a compiled loop rather than through a (cells, H) matrix
    product, which allocated ~2 MB per scan; the two round differently only in the last
    bit, so a lowest point would have to lie within ~1e-16 m of an inlier bound to count
    differently.
    """
    if len(low) < MIN_INLIERS:
        return None
    tri = low[_sample_triples(len(low), HYPOTHESES)]  # (H, 3, 3)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-9
    normals = normals[ok] / norms[ok, None]
    normals *= np.sign(normals[:, 2:3]) + (normals[:, 2:3] == 0)
    heights = -np.einsum("hk,hk->h", normals, tri[ok, 0])  # n.p + h = 0 on the plane
    ok = (normals[:, 2] >= math.cos(math.radians(max_tilt_deg))) & (heights > 0)
    if not ok.any():
        return None
    normals, heights = np.ascontiguousarray(normals[ok]), heights[ok]
    columns = np.ascontiguousarray(low.T)
    best = int(np.argmax(_plane_scores(columns, normals, heights)))
    chosen = low[_plane_inliers(columns, normals[best], heights[best])]
    if len(chosen) < MIN_INLIERS:
        return None
    centre = chosen.mean(0)
    normal = np.linalg.svd(chosen - centre, full_matrices=False)[2][2]
    normal = normal if normal[2] > 0 else -normal
    return normal, float(-normal @ centre)


def gravity_rotation(world_rotation: np.ndarray) -> np.ndarray:
    """Roll and pitch of a sensor's orientation in a gravity-aligned world (odometry's), its
    yaw removed: the ``gravity_rotation`` that :func:`ground_frame` levels by."""
    return _without_yaw(np.asarray(world_rotation, dtype=np.float64)[:3, :3])


def ground_frame(points: np.ndarray, gravity_rotation: np.ndarray | None = None) -> GroundFrame:
    """The levelled, ground-referenced frame of one scan given in the sensor frame.

    ``gravity_rotation`` (3x3, sensor -> a gravity-aligned frame, e.g. odometry's roll and
    pitch) replaces the fitted tilt; only the height is fitted then.
    """
    base = np.eye(3) if gravity_rotation is None else np.asarray(gravity_rotation, np.float64)
    if gravity_rotation is None:  # read as given: a float64 copy of a 120k-point scan costs more than the pass
        xyz = np.asarray(points)
        xyz = xyz if xyz.dtype in (np.float32, np.float64) else xyz.astype(np.float64)
    else:
        xyz = np.ascontiguousarray(np.asarray(points, dtype=np.float64)[:, :3]) @ base.T
    low = lowest_points(xyz, CELL_M, MIN_RANGE_M, MAX_RANGE_M)
    fit = fit_ground(low, max_tilt_deg=MAX_TILT_DEG if gravity_rotation is None else 5.0)
    if gravity_rotation is not None:
        if fit is None:
            return _without_ground(base, low)
        normal, height = fit
        # keep the given tilt; the plane only sets the height: the ground straight below the
        # sensor (on a slope: height / cos(slope))
        return GroundFrame(base, height / normal[2], True)
    first = None
    if fit is not None:
        support = int(_plane_inliers(np.ascontiguousarray(low.T), fit[0], fit[1]).sum())
        first = (_rotation_onto_z(fit[0]), fit[1], _tilt_deg(fit[0]), support)
    xyz64 = None  # read once, only for a second search
    if first is None or first[3] < MIN_SUPPORT * len(low):  # held steeper than the search reaches?
        xyz64 = np.ascontiguousarray(np.asarray(points, dtype=np.float64)[:, :3])
        found = [f for f in (first, _steep_fit(xyz64)) if f is not None]
        if not found:
            return _without_ground(base, low)
        first = max(found, key=lambda f: f[3])
    rotation, height, increment, _ = first
    # held at 35 degrees, the best plane within MAX_TILT_DEG stops short of the ground: each
    # refit searches around the last one
    for _ in range(MAX_REFITS):
        if increment <= REFIT_TILT_DEG:
            break
        if xyz64 is None:
            xyz64 = np.ascontiguousarray(np.asarray(points, dtype=np.float64)[:, :3])
        refit = _refit(xyz64, rotation)
        if refit is None:
            break
        rotation, height, increment, _ = refit
    return GroundFrame(rotation, height, True)


def _without_ground(base: np.ndarray, low: np.ndarray) -> GroundFrame:
    """The frame of a scan with no ground plane found: its own tilt, its lowest points as ground."""
    below = -float(np.percentile(low[:, 2], 10)) if len(low) else FALLBACK_HEIGHT_M[1]
    return GroundFrame(base, float(np.clip(below, *FALLBACK_HEIGHT_M)), False)


def _tilt_deg(normal: np.ndarray) -> float:
    return math.degrees(math.acos(min(1.0, float(normal[2]))))


def _refit(xyz: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, float, float, int] | None:
    """The ground of the scan ``xyz`` (N, 3) float64 fitted in the frame ``rotation`` levels it to:
    (the refined rotation, the height, the refinement's tilt in degrees, the plane's inlier count),
    or None when no plane is found or the refined frame would tilt the scan by more than
    ``MAX_HELD_TILT_DEG``."""
    levelled = xyz @ rotation.T
    low = lowest_points(levelled, CELL_M, MIN_RANGE_M, MAX_RANGE_M)
    fit = fit_ground(low)
    if fit is None:
        return None
    normal, height = fit
    refined = _without_yaw(_rotation_onto_z(normal) @ rotation)
    if refined[2, 2] < math.cos(math.radians(MAX_HELD_TILT_DEG)):
        return None
    support = int(_plane_inliers(np.ascontiguousarray(low.T), normal, height).sum())
    return refined, height, _tilt_deg(normal), support


def _steep_fit(xyz: np.ndarray) -> tuple[np.ndarray, float, float, int] | None:
    """The best-supported ground of searches started tilted by ``MAX_TILT_DEG`` towards
    ``STEEP_STARTS`` headings, as :func:`_refit` gives it, or None."""
    best = None
    tilt = math.radians(MAX_TILT_DEG)
    for k in range(STEEP_STARTS):
        heading = 2.0 * math.pi * k / STEEP_STARTS
        up = np.array([math.sin(tilt) * math.cos(heading), math.sin(tilt) * math.sin(heading), math.cos(tilt)])
        refit = _refit(xyz, _rotation_onto_z(up))
        if refit is not None and (best is None or refit[3] > best[3]):
            best = refit
    return best
