"""The height modality: the highest point above each voxel's floor.

Scan Context's observation, kept as one VBRL modality: the tallest structure in a
column of space survives thinning, sparse beams and changing density far better
than the shape of the points inside it. Heights are read from a fine map of the
scan — the highest point of every ``CELL_M`` column of each layer — rather than from
the points themselves, so that describing the same scan from a few metres to the
side (translation search, for revisits on the other lane) costs a pass over the
map's occupied cells, not over the points.

Voxel numbering is the grids' own (:mod:`vbrl_ros.grids`); polar bins use the polar
grid's exact angular-bin rule, so a map cell lands in the voxel the grid assigns its
centre to. Which voxel of a layer a map column falls in from a viewpoint
(:func:`polar_column_voxels`, :func:`cartesian_column_voxels`) depends only on the
column, not on the scan: :func:`.height_views.view_table` computes it once for every column.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from vbrl_ros.features.kernels import angular_bin
from vbrl_ros.features.weather_clutter import drop_lone_tops

CELL_M = 0.2  # well below any voxel, and ~10k-30k occupied cells for a 120k-point scan
MARGIN_M = 4.0  # the map reaches this far beyond the grid, for shifted viewpoints


def map_side(reach: float, cell: float) -> int:
    """Columns along each of x and y of a map ``reach`` metres each side of the origin."""
    return int(2.0 * reach / cell) + 1


@njit(cache=True, nogil=True, inline="always")
def _column_centre(column, side, cell, reach):
    """(x, y) of the centre of map column ``column`` (row-major, y rows)."""
    return (column % side + 0.5) * cell - reach, (column // side + 0.5) * cell - reach


@njit(cache=True, nogil=True)
def height_cells(points, rotation, lift, reach, cell, z_edges, drop_clutter, half_turn, top_tan):
    """The scan as a height map: ``(cells, 2)`` x, y of each occupied column centre,
    ``(cells,)`` its layer-relative top height, ``(cells,)`` its layer and ``(cells,)`` its
    column (``iy * side + ix``, see :func:`map_side`).

    Points are taken into the grid frame on the fly, ``R p + (0, 0, lift)`` (the scan's
    ground frame; identity and 0 for points already in it). Columns are ``cell`` metres
    wide, within ``reach`` metres of the origin in x and y; points outside the layers (and
    non-finite ones) are dropped, and so are those a tilted sensor would not see turned half a
    turn (``half_turn`` and ``top_tan``, :mod:`.field_of_view`; ``top_tan`` inf: all kept).
    ``drop_clutter``: lone tops near the sensor are taken for rain or snow
    (:mod:`.weather_clutter`) and each such column keeps its next-highest point.
    """
    layers = z_edges.shape[0] - 1
    side = int(2.0 * reach / cell) + 1
    columns = side * side * layers
    # No branches on the point: whether it is kept (a third of a levelled scan is ground
    # just below z = 0) and whether it is higher than its column's top are coin tosses on
    # points in no particular order, which the CPU mispredicts. Dropped points are
    # written to a spare last entry instead, and the top is kept with max().
    top = np.full(columns + 1, -1.0)
    # each column's next-highest point, which only dropping clutter reads
    second = np.full(columns + 1 if drop_clutter else 1, -1.0)
    R = rotation
    # a tilted sensor's field of view mirrored (.field_of_view): a point is kept only where the
    # sensor turned half a turn (``half_turn``, sensor frame) sees it below ``top_tan``
    mirror = top_tan < np.inf
    M = half_turn
    for i in range(points.shape[0]):
        px, py, pz = np.float64(points[i, 0]), np.float64(points[i, 1]), np.float64(points[i, 2])
        x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz
        y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz
        z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + lift
        kept = (abs(x) < reach) & (abs(y) < reach) & (z >= z_edges[0]) & (z < z_edges[layers])
        if mirror:  # the same for every point: predicted
            tx = M[0, 0] * px + M[0, 1] * py + M[0, 2] * pz
            ty = M[1, 0] * px + M[1, 1] * py + M[1, 2] * pz
            tz = M[2, 0] * px + M[2, 1] * py + M[2, 2] * pz
            kept = kept & (tz <= top_tan * math.sqrt(tx * tx + ty * ty))
        layer = 0
        for e in range(1, layers):
            if z >= z_edges[e]:
                layer += 1
        row = (y + reach) / cell
        column = (x + reach) / cell
        row = row if kept else 0.0  # NaN and inf are never converted to int
        column = column if kept else 0.0
        c = (layer * side + int(row)) * side + int(column)
        c = c if kept else columns
        h = z - z_edges[layer]
        t = top[c]
        if drop_clutter:  # the same for every point: predicted
            second[c] = max(second[c], min(t, h))
        top[c] = max(h, t)
    if drop_clutter:
        top = drop_lone_tops(top, second, side, layers, cell, reach)
    n = 0
    for c in range(columns):
        if top[c] >= 0.0:
            n += 1
    xy = np.empty((n, 2))
    height = np.empty(n)
    layer_of = np.empty(n, np.int64)
    column_of = np.empty(n, np.int64)
    k = 0
    plane = side * side
    for c in range(columns):
        if top[c] >= 0.0:
            rest = c % plane
            xy[k, 0], xy[k, 1] = _column_centre(rest, side, cell, reach)
            height[k] = top[c]
            layer_of[k] = c // plane
            column_of[k] = rest
            k += 1
    return xy, height, layer_of, column_of


@njit(cache=True, nogil=True)
def column_centres(side, cell, reach):
    """(side * side, 2) x, y of every map column's centre, as :func:`height_cells` gives them."""
    xy = np.empty((side * side, 2))
    for c in range(side * side):
        xy[c, 0], xy[c, 1] = _column_centre(c, side, cell, reach)
    return xy


@njit(cache=True, nogil=True)
def polar_column_voxels(xy, offset_x, offset_y, max_range, rings, sectors, bound_cos, bound_sin):
    """(n,) the polar voxel within a layer (``ring * sectors + sector``) of every column centre
    ``xy`` seen from (offset_x, offset_y); -1 outside the grid."""
    voxel = np.full(xy.shape[0], -1, np.int64)
    ring_scale = rings / max_range
    angle_scale = sectors / (2.0 * np.pi)
    b = 0
    for k in range(xy.shape[0]):
        x = xy[k, 0] - offset_x
        y = xy[k, 1] - offset_y
        r = np.sqrt(x * x + y * y)
        if not (r > 0.0 and r * ring_scale < rings):
            continue
        b = angular_bin(x, y, bound_cos, bound_sin, sectors, angle_scale, b)
        voxel[k] = min(int(r * ring_scale), rings - 1) * sectors + b
    return voxel


@njit(cache=True, nogil=True)
def cartesian_column_voxels(xy, offset_x, offset_y, extent, cells):
    """(n,) the Cartesian voxel within a layer (``iy * cells + ix``) of every column centre
    ``xy`` seen from (offset_x, offset_y); -1 outside the grid."""
    voxel = np.full(xy.shape[0], -1, np.int64)
    scale = cells / (2.0 * extent)
    for k in range(xy.shape[0]):
        sx = (xy[k, 0] - offset_x + extent) * scale
        sy = (xy[k, 1] - offset_y + extent) * scale
        if not (sx >= 0 and sx < cells and sy >= 0 and sy < cells):
            continue
        voxel[k] = int(sy) * cells + int(sx)
    return voxel
