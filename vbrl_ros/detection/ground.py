"""Which points of a levelled scan lie on the ground.

Verification leaves the ground out of what decides a loop closure: at KISS-ICP's
1.5-voxel downsampling it is 60-80 % of a single scan, and its sampling is
sensor-centric (rings, the blind disc under the sensor). Scan-to-scan, those
artefacts pull the solution towards "both sensors at the same place" and make
unrelated places overlap on the ground alone. KISS-ICP odometry avoids this because
its map accumulates many scans; a loop closure compares two single scans.
"""

from __future__ import annotations

import numpy as np


def ground_mask(points: np.ndarray, cell: float = 2.0, tolerance: float = 0.3) -> np.ndarray:
    """True for points on the ground (sensor roughly upright, z up, as for Scan Context).

    A point is ground if it lies within ``tolerance`` of its grid cell's lowest
    point and that cell's lowest point is within 0.5 m of the lowest point of
    the 3x3 neighbouring cells (so car roofs and wall tops are not ground).
    """
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    ij = np.floor(points[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0) - 1  # non-negative, with a free border for neighbour lookups
    width = int(ij[:, 1].max()) + 2
    keys, inverse = np.unique(ij[:, 0] * width + ij[:, 1], return_inverse=True)
    lowest = np.full(len(keys), np.inf)
    np.minimum.at(lowest, inverse, points[:, 2])
    reference = lowest.copy()
    for offset in (-width - 1, -width, -width + 1, -1, 1, width - 1, width, width + 1):
        position = np.minimum(np.searchsorted(keys, keys + offset), len(keys) - 1)
        found = keys[position] == keys + offset
        reference[found] = np.minimum(reference[found], lowest[position[found]])
    ground_cell = lowest - reference < 0.5
    return (points[:, 2] - lowest[inverse] < tolerance) & ground_cell[inverse]
