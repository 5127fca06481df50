"""Coarse alignment of two levelled clouds before KISS-ICP: yaw and x, y by correlating their
bird's-eye structure, over every heading.

KISS-ICP converges from within about +-10 degrees of yaw and a few metres; a loop closure
gives it two single scans that can be any heading and metres apart. The recogniser's own
yaw is not enough: in a square room or a symmetric street the descriptor's best sector shift
is often 90 or 180 degrees off (measured: on a hand-held recording half of the true
candidates came with a yaw 35-180 degrees wrong, and KISS-ICP registered none of those).
Here each cloud's structure (ground left out) becomes a bird's-eye occupancy image; the
match's image is built at every ``YAW_STEP_DEG`` and cross-correlated with the query's by
FFT; the highest peak gives yaw and translation to a cell and a step, well inside KISS-ICP's
basin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft
from scipy.ndimage import uniform_filter

CELL_M = 1.0  # occupancy cell; KISS-ICP refines from here
EXTENT_M = 40.0  # structure within this many metres (x and y) of each sensor
YAW_STEP_DEG = 10.0  # half of KISS-ICP's yaw basin
#: Translations searched: up to this far; the FFT is padded by it instead of by the image size.
MAX_SHIFT_M = 16.0


@dataclass(frozen=True)
class CoarseAlignment:
    T_query_match: np.ndarray  # (4, 4), a yaw and a horizontal translation
    score: float  # the correlation peak: structure cells that coincide (blurred), >= 0


def _occupancy(points_xy: np.ndarray, size: int) -> np.ndarray:
    """Binary occupancy of (N, 2) points on a size x size grid centred on the sensor, blurred by
    one cell so that a cell's worth of misalignment still correlates."""
    grid = np.zeros((size, size))
    ij = np.floor((points_xy + EXTENT_M) / CELL_M).astype(np.int64)
    inside = np.all((ij >= 0) & (ij < size), axis=1)
    grid[ij[inside, 0], ij[inside, 1]] = 1.0
    return uniform_filter(grid, 3, mode="constant")


def coarse_alignment(query_structure: np.ndarray, match_structure: np.ndarray) -> CoarseAlignment:
    """The yaw and x, y that best overlay ``match_structure`` on ``query_structure`` ((N, 3)
    levelled, non-ground points of each scan), as ``T_query_match``."""
    size = int(round(2 * EXTENT_M / CELL_M))
    padded = size + int(np.ceil(MAX_SHIFT_M / CELL_M))  # no wrap-around within MAX_SHIFT_M
    query = fft.rfft2(_occupancy(query_structure[:, :2], size), s=(padded, padded))
    best = (-np.inf, 0.0, np.zeros(2))
    limit = int(np.ceil(MAX_SHIFT_M / CELL_M))
    for yaw in np.deg2rad(np.arange(0.0, 360.0, YAW_STEP_DEG)):
        c, s = np.cos(yaw), np.sin(yaw)
        rotated = match_structure[:, :2] @ np.array([[c, s], [-s, c]])  # R(yaw) p, row-wise
        match = fft.rfft2(_occupancy(rotated, size), s=(padded, padded))
        correlation = fft.irfft2(query * np.conj(match), s=(padded, padded))
        # shift k (cells, modulo the padded size) moves the match by k: keep |k| <= limit
        window = np.concatenate([correlation[:limit + 1], correlation[-limit:]])
        window = np.concatenate([window[:, :limit + 1], window[:, -limit:]], axis=1)
        k = np.unravel_index(int(np.argmax(window)), window.shape)
        if window[k] > best[0]:
            shift = np.array([k[0] if k[0] <= limit else k[0] - 2 * limit - 1,
                              k[1] if k[1] <= limit else k[1] - 2 * limit - 1], dtype=np.float64)
            best = (float(window[k]), yaw, shift * CELL_M)
    score, yaw, shift = best
    T = np.eye(4)
    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    T[:2, 3] = shift
    return CoarseAlignment(T, max(score, 0.0))
