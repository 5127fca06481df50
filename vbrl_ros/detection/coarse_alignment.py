"""Coarse alignment of two levelled clouds before KISS-ICP: yaw and x, y by correlating their
bird's-eye structure, over every heading.

KISS-ICP converges from within about +-10 degrees of yaw and a few metres; a loop closure
gives it two single scans that can be any heading and metres apart. The recogniser's own
yaw is not enough: in a square room or a symmetric street the descriptor's best sector shift
is often 90 or 180 degrees off (measured: on a hand-held recording half of the true
candidates came with a yaw 35-180 degrees wrong, and KISS-ICP registered none of those).
Here each cloud's structure (ground left out) becomes a bird's-eye occupancy image; the
match's image is built at every ``YAW_STEP_DEG`` and cross-correlated with the query's by
FFT; the highest peak gives yaw and translation to a step and a cell, well inside KISS-ICP's
basin. A parabola through the peaks of the neighbouring headings, and one through the
correlation around the peak at that heading, then place yaw and translation between the
steps: KISS-ICP needs fewer iterations the closer it starts.

Translations are searched within a disc: a caller that rejects closures beyond some distance
passes it, and the peak is the best overlay *within* it. Searched farther, a reversed revisit
seen partly (a hidden wedge, a narrow field of view) was often matched 10-18 m away, to other
facades, with nothing to refine from (measured on simulated reversed revisits).

The query's image and its transform do not depend on the match: :class:`HeadingSearch`
keeps them for every candidate of one query, and all headings of a match are transformed
as one stack.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numba import njit
from scipy import fft

CELL_M = 1.0  # occupancy cell; KISS-ICP refines from here
EXTENT_M = 40.0  # structure within this many metres (x and y) of each sensor
YAW_STEP_DEG = 10.0  # half of KISS-ICP's yaw basin
#: Translations searched by default: up to this far; the FFT is padded by the search radius
#: instead of by the image size.
MAX_SHIFT_M = 16.0

_SIZE = round(2 * EXTENT_M / CELL_M)
_YAWS = np.deg2rad(np.arange(0.0, 360.0, YAW_STEP_DEG))
# Headings transformed together: stacks of all 36 (1.3 MB per array) took twice as long, in
# fresh memory pages the allocator maps and the kernel zeroes for every array.
_YAWS_PER_STACK = 9


@dataclass(frozen=True)
class CoarseAlignment:
    T_query_match: np.ndarray  # (4, 4), a yaw and a horizontal translation
    score: float  # the correlation peak: structure cells that coincide (blurred), >= 0


@lru_cache(maxsize=8)
def _blur_response(padded: int) -> np.ndarray:
    """|K|^2 of the 3 x 3 box blur K on the ``padded`` grid, in rfft2's layout.

    Each image used to be blurred by one cell so that a cell's worth of misalignment still
    correlates; blurring both images is a product of spectra with K and conj(K), so it is
    applied once, to the query's transform, instead of to every rotated match image.
    """
    box = np.zeros((padded, padded))
    box[np.ix_([-1, 0, 1], [-1, 0, 1])] = 1.0 / 9.0
    return (np.abs(fft.rfft2(box)) ** 2).astype(np.float32)


def _occupancy(points_xy: np.ndarray, yaws: np.ndarray, padded: int) -> np.ndarray:
    """(len(yaws), padded, padded) float32 binary occupancy of the (N, 2) points turned by each
    yaw, on a grid centred on the sensor (cells beyond the image stay empty: the FFT's padding)."""
    grid = np.zeros((len(yaws), padded, padded), dtype=np.float32)
    _rasterise(np.ascontiguousarray(points_xy, dtype=np.float64), np.cos(yaws), np.sin(yaws), grid,
               EXTENT_M, CELL_M, _SIZE)
    return grid


@njit(cache=True, nogil=True)
def _rasterise(xy, cos, sin, grid, extent, cell, size):  # pragma: no cover - compiled
    # one pass per heading over the points: numpy's version materialises every heading's
    # indices and took most of the search's time
    for y in range(len(cos)):
        c, s = cos[y], sin[y]
        for n in range(len(xy)):
            x, z = xy[n, 0], xy[n, 1]
            i = int(np.floor((c * x - s * z + extent) / cell))  # R(yaw) p
            j = int(np.floor((s * x + c * z + extent) / cell))
            if 0 <= i < size and 0 <= j < size:
                grid[y, i, j] = 1.0


def _window(correlation: np.ndarray, limit: int) -> np.ndarray:
    """The shifts |k_x|, |k_y| <= limit of (..., padded, padded) correlations (k modulo the padded
    size), reordered so that index ``limit`` is shift 0."""
    rows = np.concatenate([correlation[..., -limit:, :], correlation[..., :limit + 1, :]], axis=-2)
    return np.concatenate([rows[..., -limit:], rows[..., :limit + 1]], axis=-1)


def _vertex(below: float, peak: float, above: float) -> float:
    """Offset in [-0.5, 0.5] steps of the top of the parabola through three equally spaced values."""
    if not (np.isfinite(below) and np.isfinite(above)):  # at the edge of the search disc
        return 0.0
    curvature = below - 2.0 * peak + above
    if curvature >= 0:  # not a maximum (flat or rounding): stay on the sample
        return 0.0
    return float(np.clip(0.5 * (below - above) / curvature, -0.5, 0.5))


class HeadingSearch:
    """The query's side of :func:`coarse_alignment`, computed once for all its candidates;
    translations up to ``max_shift_m`` are searched."""

    def __init__(self, query_structure: np.ndarray, max_shift_m: float = MAX_SHIFT_M) -> None:
        if not (np.isfinite(max_shift_m) and max_shift_m > 0):
            raise ValueError(f"max_shift_m must be a positive number of metres, got {max_shift_m!r}")
        # beyond the image's size nothing overlaps: no need to search (nor pad) farther
        self.limit = min(int(np.ceil(max_shift_m / CELL_M)), _SIZE)
        self.padded = _SIZE + self.limit  # no wrap-around within the limit
        k = np.arange(-self.limit, self.limit + 1)
        self.outside = (k[:, None] ** 2 + k[None, :] ** 2) * CELL_M ** 2 > max_shift_m ** 2
        query = _occupancy(np.asarray(query_structure, dtype=np.float64)[:, :2], np.zeros(1), self.padded)[0]
        self.spectrum = fft.rfft2(query) * _blur_response(self.padded)

    def align(self, match_structure: np.ndarray) -> CoarseAlignment:
        """The yaw and x, y that best overlay ``match_structure`` ((N, 3) levelled, non-ground
        points) on the query's, as ``T_query_match``."""
        return self.alignments(match_structure, 1)[0]

    def alignments(self, match_structure: np.ndarray, count: int) -> list[CoarseAlignment]:
        """Up to ``count`` overlays of ``match_structure`` on the query's, best peak first: the
        headings whose peak is higher than both neighbouring headings', each placed as
        :meth:`align` places the best. A square courtyard or a crossing overlays almost as well
        turned by 90 degrees; a caller that can tell the overlays apart by what both sensors saw
        (:func:`~vbrl_ros.detection.overlap.covisible_overlap`) picks among them."""
        match_xy = np.asarray(match_structure, dtype=np.float64)[:, :2]
        side = 2 * self.limit + 1
        peaks = np.concatenate([
            self._correlate(match_xy, _YAWS[k:k + _YAWS_PER_STACK]).reshape(-1, side * side).max(axis=1)
            for k in range(0, len(_YAWS), _YAWS_PER_STACK)])
        if peaks.max() <= 0:
            return [CoarseAlignment(np.eye(4), 0.0)]
        # local maxima over the circle of headings (a plateau counts once: ">" on one side)
        summits = np.flatnonzero((peaks > np.roll(peaks, 1)) & (peaks >= np.roll(peaks, -1)) & (peaks > 0))
        if len(summits) == 0:  # every heading equal
            summits = np.array([int(np.argmax(peaks))])
        best = summits[np.argsort(-peaks[summits], kind="stable")][:max(int(count), 1)]
        return [self._placed(match_xy, peaks, int(b)) for b in best]

    def _placed(self, match_xy: np.ndarray, peaks: np.ndarray, best: int) -> CoarseAlignment:
        """The overlay at heading ``best``: yaw and shift refined between the steps and cells."""
        step = np.deg2rad(YAW_STEP_DEG)
        yaw = _YAWS[best] + step * _vertex(peaks[best - 1], peaks[best], peaks[(best + 1) % len(_YAWS)])
        window = self._correlate(match_xy, np.array([yaw]))[0]
        k = np.unravel_index(int(np.argmax(window)), window.shape)
        shift = np.array(k, dtype=np.float64) - self.limit
        # a sub-cell peak where it has neighbours on both sides (not at the search's edge)
        if 0 < k[0] < 2 * self.limit:
            shift[0] += _vertex(window[k[0] - 1, k[1]], window[k], window[k[0] + 1, k[1]])
        if 0 < k[1] < 2 * self.limit:
            shift[1] += _vertex(window[k[0], k[1] - 1], window[k], window[k[0], k[1] + 1])
        T = np.eye(4)
        T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        T[:2, 3] = shift * CELL_M
        return CoarseAlignment(T, max(float(window[k]), 0.0))

    def _correlate(self, match_xy: np.ndarray, yaws: np.ndarray) -> np.ndarray:
        """(len(yaws), 2 limit + 1, 2 limit + 1): the blurred correlation of the query's image with
        the match's turned by each yaw, at every shift k (cells) of the match within the limit;
        -inf beyond the search radius."""
        spectra = fft.rfft2(_occupancy(match_xy, yaws, self.padded))
        window = _window(fft.irfft2(self.spectrum * np.conj(spectra), s=(self.padded, self.padded)), self.limit)
        window[:, self.outside] = -np.inf
        return window


def coarse_alignment(query_structure: np.ndarray, match_structure: np.ndarray,
                     max_shift_m: float = MAX_SHIFT_M) -> CoarseAlignment:
    """The yaw and x, y within ``max_shift_m`` that best overlay ``match_structure`` on
    ``query_structure`` ((N, 3) levelled, non-ground points of each scan), as ``T_query_match``."""
    return HeadingSearch(query_structure, max_shift_m).align(match_structure)
