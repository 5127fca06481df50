"""One compiled pass over a scan's points: the featurizer's hot loop.

The numpy implementation (:meth:`Featurizer.modalities_numpy`) needs ~20
passes over the points and a fresh allocation per pass; on a 120k-point scan
that is 15-25 ms, over the 10 ms budget. This kernel reads each point once
and accumulates, per voxel, the point count, the nine moment sums of the
covariance and the three snapshot rasters. It computes exactly what the
numpy path computes — same float64 formulas, same order of summation — and a
test checks the two agree. ``nogil``: the node's worker thread featurizes
while rclpy's executor keeps receiving.

:func:`accumulate_polar_voxels` is the same pass on the polar grid of
:mod:`vbrl_ros.grids.polar` (voxel-local coordinates and sub-cells).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Odd polynomial for atan(t), t in [0, 1], error < 1.2e-5 rad (Abramowitz & Stegun 4.4.49).
#: Here and not in grids/polar.py: numba's cache keys on this file, so the kernel
#: recompiles when they change.
ATAN_COEFFICIENTS = (0.9998660, -0.3302995, 0.1801410, -0.0851330, 0.0208351)
_C1, _C3, _C5, _C7, _C9 = ATAN_COEFFICIENTS
_TWO_PI = 2.0 * math.pi
_HALF_PI = 0.5 * math.pi


@njit(cache=True, nogil=True, inline="always")
def _accumulate(counts, moments, rasters, octants, voxel, x, y, z, pu, pv, pz, half) -> None:
    """Add one point to its voxel: count, moment sums, the three rasters, its octant.

    Shared by both grids so their features are computed the same way; (x, y)
    and (pu, pv) are the voxel's own frame and raster cell (sensor axes on the
    Cartesian grid, radial/tangential on the polar one).
    """
    counts[voxel] += 1
    m = moments[voxel]
    m[0] += x
    m[1] += y
    m[2] += z
    m[3] += x * x
    m[4] += y * y
    m[5] += z * z
    m[6] += x * y
    m[7] += x * z
    m[8] += y * z
    rasters[0, voxel, pv, pu] += 1.0
    rasters[1, voxel, pz, pu] += 1.0
    rasters[2, voxel, pz, pv] += 1.0
    octant = (1 if pu >= half else 0) + (2 if pv >= half else 0) + (4 if pz >= half else 0)
    octants[voxel, octant] += 1.0


@njit(cache=True, nogil=True)
def accumulate_voxels(
    points: np.ndarray,  # (N, >=3) float32 or float64
    extent_xy: float,
    cells: int,
    z_edges: np.ndarray,  # (layers + 1,) float64
    z_slope: np.ndarray,  # (layers,) float64
    z_intercept: np.ndarray,  # (layers,) float64
    size: int,  # raster size, a power of two
):
    """Per voxel: counts (v,), moment sums (v, 9), XY/XZ/YZ rasters (3, v, size, size), octants (v, 8).

    Moments are sums of x, y, z, xx, yy, zz, xy, xz, yz. Points that are
    non-finite or outside the grid are skipped (the numpy path's sentinel).
    """
    layers = len(z_slope)
    v = cells * cells * layers
    counts = np.zeros(v, dtype=np.int64)
    moments = np.zeros((v, 9))
    rasters = np.zeros((3, v, size, size))
    octants = np.zeros((v, 8))
    scale = cells * size / (2.0 * extent_xy)
    limit_xy = cells * size
    z_low, z_high = z_edges[0], z_edges[-1]
    half = size // 2
    shift = 0
    while (1 << shift) < size:
        shift += 1
    for k in range(points.shape[0]):
        x = np.float64(points[k, 0])
        y = np.float64(points[k, 1])
        z = np.float64(points[k, 2])
        sx = (x + extent_xy) * scale
        sy = (y + extent_xy) * scale
        # same tests as the numpy path; NaN fails them, inf fails the bounds
        if not (sx >= 0 and sx < limit_xy and sy >= 0 and sy < limit_xy and z >= z_low and z < z_high):
            continue
        layer = 0
        for e in range(1, layers):
            if z >= z_edges[e]:
                layer += 1
        sz = (z * z_slope[layer] + z_intercept[layer]) * size
        isx = min(int(sx), limit_xy - 1)
        isy = min(int(sy), limit_xy - 1)
        isz = min(int(sz), layers * size - 1)
        ix, iy = isx >> shift, isy >> shift
        px, py, pz = isx & (size - 1), isy & (size - 1), isz & (size - 1)
        voxel = (layer * cells + iy) * cells + ix
        _accumulate(counts, moments, rasters, octants, voxel, x, y, z, px, py, pz, half)
    return counts, moments, rasters, octants


@njit(cache=True, nogil=True)
def _approximate_azimuth(x: float, y: float) -> float:
    """grids.polar.approximate_azimuth for one point, same operations in the same order."""
    ax, ay = abs(x), abs(y)
    t = min(ax, ay) / max(ax, ay)
    t2 = t * t
    a = t * (_C1 + t2 * (_C3 + t2 * (_C5 + t2 * (_C7 + t2 * _C9))))
    if ay > ax:
        a = _HALF_PI - a
    if x < 0:
        a = math.pi - a
    if y < 0:
        a = _TWO_PI - a
    return a


@njit(cache=True, nogil=True, inline="always")
def angular_bin(x, y, bound_cos, bound_sin, bins, angle_scale, start) -> int:
    """The polar grid's angular bin of (x, y): the unique b with the point on or left of
    boundary b and right of boundary b+1 (see grids/polar.py).

    Walking from ANY start reaches it; ``start`` is a guess (scans come in azimuth order,
    so the previous point's bin is usually right: two sign tests instead of the arctangent).
    """
    b = start
    if not (bound_cos[b] * y - bound_sin[b] * x >= 0
            and not bound_cos[b + 1] * y - bound_sin[b + 1] * x >= 0):
        b = min(int(_approximate_azimuth(x, y) * angle_scale), bins - 1)
        for _ in range(bins):
            if not bound_cos[b] * y - bound_sin[b] * x < 0:
                break
            b = bins - 1 if b == 0 else b - 1
        for _ in range(bins):
            if not bound_cos[b + 1] * y - bound_sin[b + 1] * x >= 0:
                break
            b = 0 if b == bins - 1 else b + 1
    return b


@njit(cache=True, nogil=True)
def accumulate_polar_voxels(
    points: np.ndarray,  # (N, >=3) float32 or float64
    max_range: float,
    rings: int,
    sectors: int,
    bound_cos: np.ndarray,  # (sectors * size + 1,) angular bin boundaries, see PolarVoxelGrid
    bound_sin: np.ndarray,
    centre_cos: np.ndarray,  # (sectors,) cos/sin of each sector's centre angle
    centre_sin: np.ndarray,
    z_edges: np.ndarray,  # (layers + 1,) float64
    z_slope: np.ndarray,  # (layers,) float64
    z_intercept: np.ndarray,  # (layers,) float64
    size: int,  # raster size, a power of two
):
    """:func:`accumulate_voxels` on the polar grid: same outputs, voxel-local frames.

    Moments are sums of the local x', y', z (and products); rasters and
    octants are over (radial, angular, z) sub-cells. Mirrors
    ``PolarVoxelGrid.assign`` operation for operation; points that are
    non-finite, on the z axis or outside the grid are skipped.
    """
    layers = len(z_slope)
    v = rings * sectors * layers
    counts = np.zeros(v, dtype=np.int64)
    moments = np.zeros((v, 9))
    rasters = np.zeros((3, v, size, size))
    octants = np.zeros((v, 8))
    radial_scale = rings * size / max_range
    limit_r = rings * size
    bins = sectors * size
    angle_scale = bins / _TWO_PI
    z_low, z_high = z_edges[0], z_edges[-1]
    half = size // 2
    shift = 0
    while (1 << shift) < size:
        shift += 1
    previous_bin = 0
    for k in range(points.shape[0]):
        x = np.float64(points[k, 0])
        y = np.float64(points[k, 1])
        z = np.float64(points[k, 2])
        r = math.sqrt(x * x + y * y)
        sr = r * radial_scale
        if not (r > 0 and sr < limit_r and z >= z_low and z < z_high):
            continue
        layer = 0
        for e in range(1, layers):
            if z >= z_edges[e]:
                layer += 1
        sz = (z * z_slope[layer] + z_intercept[layer]) * size
        b = angular_bin(x, y, bound_cos, bound_sin, bins, angle_scale, previous_bin)
        previous_bin = b
        isr = min(int(sr), limit_r - 1)
        isz = min(int(sz), layers * size - 1)
        ring, sector = isr >> shift, b >> shift
        pr, pa, pz = isr & (size - 1), b & (size - 1), isz & (size - 1)
        voxel = (layer * rings + ring) * sectors + sector
        c, s = centre_cos[sector], centre_sin[sector]
        lx = x * c + y * s
        ly = y * c - x * s
        _accumulate(counts, moments, rasters, octants, voxel, lx, ly, z, pr, pa, pz, half)
    return counts, moments, rasters, octants
