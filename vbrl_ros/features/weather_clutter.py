"""Returns from rain, snow or dust near the sensor, taken out of the height map.

A LiDAR in rain or snow gets some of its returns from the airborne particles a few
metres away instead of from the surface behind them. Each such point stands alone in the
air, and the height modality keeps the highest point of every column of the map, so a
single one sets the height of its whole voxel: 0.4 % of the rays returned from rain
(the simulator's rain, mostly within 12 m) took a forward-looking sensor's Recall@1
across two sessions from .99 to .83.

A column's top is taken for such a return when nothing supports it: no other point of
the column, and no neighbouring column, reaches within ``SUPPORT_GAP_M`` below it. Any
surface a LiDAR samples densely is continuous across neighbouring columns or (a pole, a
sign) has points below its top in its own column. A sparse sensor, or a keyframe thinned
to a voxel, leaves real structure just as alone, so a lone top is only dropped where the
sensor sampled the ground around it densely (``MIN_OCCUPIED_NEIGHBOURS`` of the 24
columns around it hold a point): there, a surface would have been sampled densely too.
The column then keeps its next-highest point, or is empty.
"""

from __future__ import annotations

from numba import njit

#: Only within this range of the sensor: airborne returns come from the first few metres.
CLUTTER_RANGE_M = 12.0
#: A point within this much below a column's top, in it or beside it, supports the top.
SUPPORT_GAP_M = 0.5
#: Tops lower than this are ground or kerbs, whatever stands there: left alone.
MIN_TOP_M = 0.3
#: Of the 24 columns around a lone top (a 1 m square at the map's 0.2 m), this many must hold a
#: point for the sampling there to count as dense. On the shared recordings at most a few dozen
#: tops per scan are dropped, none of voxel-thinned keyframes; with 6 a hand-held sensor lost some.
MIN_OCCUPIED_NEIGHBOURS = 10


@njit(cache=True, nogil=True)
def drop_lone_tops(top, second, side, layers, cell, reach):
    """Each map column's top with lone near tops replaced by the column's next-highest point.

    ``top``, ``second``: (layers * side * side [+ spare],) the highest and next-highest
    layer-relative height of every column (-1: none), columns numbered as
    :func:`~vbrl_ros.features.height_map.height_cells` numbers them, the sensor at the map's
    centre. Returns a new ``top``; every test reads the map as it was.
    """
    out = top.copy()
    near = int(CLUTTER_RANGE_M / cell) + 1
    centre = int(reach / cell)  # the column under the sensor
    plane = side * side
    for layer in range(layers):
        base = layer * plane
        for iy in range(max(centre - near, 2), min(centre + near + 1, side - 2)):
            for ix in range(max(centre - near, 2), min(centre + near + 1, side - 2)):
                c = base + iy * side + ix
                h = top[c]
                if h < MIN_TOP_M or second[c] >= h - SUPPORT_GAP_M:
                    continue
                x, y = (ix + 0.5) * cell - reach, (iy + 0.5) * cell - reach
                if x * x + y * y > CLUTTER_RANGE_M * CLUTTER_RANGE_M:
                    continue
                supported = False
                occupied = 0
                for dy in range(-2, 3):
                    for dx in range(-2, 3):
                        if dx == 0 and dy == 0:
                            continue
                        t = top[base + (iy + dy) * side + ix + dx]
                        occupied += t >= 0.0
                        if abs(dx) <= 1 and abs(dy) <= 1 and t >= h - SUPPORT_GAP_M:
                            supported = True
                if not supported and occupied >= MIN_OCCUPIED_NEIGHBOURS:
                    out[c] = second[c]
    return out
