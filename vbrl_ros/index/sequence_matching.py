"""Sequence matching: a place is recognised by the last few keyframes, not by one alone.

A keyframe's distance to every candidate is noisy: a passer-by, rain, the other side of a
path or a glimpse past a corner moves it, and on its own a revisit may rank behind some
other place that happens to look alike. Revisits come as runs of keyframes, driven the same
way or the other way round, so a candidate keyframe ``j`` of the current keyframe ``i`` is
also scored by how the previous keyframes ``i-1, i-2, ...`` matched the keyframes next to
``j``: ``j-1, j-2, ...`` (same direction) or ``j+1, j+2, ...`` (reversed), each allowed
:data:`SLACK` keyframes either way because two passes are not keyframed at the same spots.
The sequence distance is the weighted mean of those distances, the current keyframe's
counted :data:`CURRENT_WEIGHT` times, minimised over the two directions.

It needs only what the search already computed: each earlier keyframe's pool of candidates
with their distances (:class:`SequenceHistory` keeps the last few). A neighbour outside an
earlier pool counts as that pool's farthest distance. Keyframe ids must number consecutive
keyframes consecutively — the database's ids do, and so do the rows of one recording.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from numba import njit

from vbrl_ros.index.keyframe_places import KeyframePlaces

#: Keyframes per sequence, the current one included (1: off). Measured on the shared
#: recordings and the simulated sensors (docs/results/recordings.md): 3 to 5 all help, 4 helped everywhere.
DEFAULT_LENGTH = 4
#: Keyframes of slack per step: passes are keyframed at different spots and speeds.
SLACK = 1
#: How much more the current keyframe's own distance counts than each earlier one's.
CURRENT_WEIGHT = 2.0


#: How far (metres) a stored keyframe may lie from the place an earlier term asks about,
#: the spatial counterpart of :data:`SLACK`: keyframed 1-2 m apart, the other lane 1-3 m off.
PLACE_SLACK_M = 2.5


@dataclass(frozen=True)
class _Pool:
    ids: np.ndarray  # sorted keyframe ids
    distances: np.ndarray  # their distances, same order
    farthest: float
    typical: float  # the median distance: a candidate of no note
    here: np.ndarray | None = None  # (3,) where its keyframe was taken
    positions: np.ndarray | None = None  # (n, 3) where its candidates were, same order as ids


class SequenceHistory:
    """The candidate pools of the last ``length - 1`` keyframes of one stream, in order.

    Call :meth:`rescore` once per keyframe, in the order the keyframes come: it scores the
    current keyframe's pool and then remembers it.
    """

    def __init__(self, length: int = DEFAULT_LENGTH) -> None:
        if not (isinstance(length, (int, np.integer)) and length >= 1):
            raise ValueError(f"sequence length must be an integer >= 1, got {length!r}")
        self.length = int(length)
        self._pools: deque[_Pool | None] = deque(maxlen=max(self.length - 1, 1))

    def __len__(self) -> int:
        return len(self._pools)

    def clear(self) -> None:
        """Forget the earlier keyframes (a new stream starts)."""
        self._pools.clear()

    def rescore(self, ids: np.ndarray, distances: np.ndarray, *, here: np.ndarray | None = None,
                places: KeyframePlaces | None = None) -> np.ndarray:
        """Sequence distances of the current keyframe's candidates ``ids`` (keyframe ids) given
        their own ``distances``; then remember this pool for the keyframes after it.

        ``here`` (3,): where the current keyframe was taken, in the frame of ``places``' positions
        (odometry). With both, candidates with a position are matched by place, the others by id."""
        ids = np.asarray(ids, dtype=np.int64)
        distances = np.asarray(distances, dtype=np.float64)
        if ids.shape != distances.shape or ids.ndim != 1:
            raise ValueError(f"ids {ids.shape} and distances {distances.shape} must be equal 1-D arrays")
        if places is None or here is None or not np.isfinite(here).all():
            here, positions = None, None
        else:
            here, positions = np.asarray(here, np.float64).reshape(3), places.positions(ids)
        if self.length == 1:
            return distances
        if positions is None:
            scored = self._sequence_distances(ids, distances)
        else:  # by id only where a candidate has no position (another session, no pose)
            scored = self._place_distances(positions, distances, here, places)
            unplaced = np.isnan(scored)
            if unplaced.any():
                scored[unplaced] = self._sequence_distances(ids[unplaced], distances[unplaced])
        self._pools.appendleft(_pool(ids, distances, here, positions))
        return scored

    def _place_distances(self, positions: np.ndarray, distances: np.ndarray, here: np.ndarray,
                         places: KeyframePlaces) -> np.ndarray:
        """Sequence distances by place: the earlier keyframe ``i-k`` against the candidates of its
        pool near candidate ``j``'s position moved as the query moved since (``p_j + p_(i-k) - p_i``),
        whichever way and along whichever street the earlier pass drove there. Such a place a
        stored keyframe is near but none of the pool counts as the pool's farthest distance, one
        no stored keyframe is near as its median (nothing to compare); NaN where the candidate has
        no position."""
        located = np.isfinite(positions).all(axis=1)
        total = CURRENT_WEIGHT * distances
        for step in range(1, self.length):
            pool = self._pools[step - 1] if step - 1 < len(self._pools) else None
            if pool is None or pool.here is None:
                total = total + distances
                continue
            places_then = positions + (pool.here - here)
            term = _least_near(places_then, pool.positions, pool.distances, PLACE_SLACK_M)
            missing = ~np.isfinite(term)
            if missing.any():
                stored = places.any_within(places_then[missing], PLACE_SLACK_M)
                term[missing] = np.where(stored, pool.farthest, pool.typical)
            total = total + term
        return np.where(located, total / (CURRENT_WEIGHT + self.length - 1), np.nan)

    def _sequence_distances(self, ids: np.ndarray, distances: np.ndarray) -> np.ndarray:
        best = np.full(len(ids), np.inf)
        for direction in (-1, 1):  # -1: the earlier pass driven the same way; +1: reversed
            total = CURRENT_WEIGHT * distances
            for step in range(1, self.length):
                pool = self._pools[step - 1] if step - 1 < len(self._pools) else None
                # no earlier keyframe yet (or it found nothing): its term is the current one's
                total = total + (distances if pool is None else
                                 _nearest_in_pool(pool, ids + direction * step))
            best = np.minimum(best, total / (CURRENT_WEIGHT + self.length - 1))
        return best


@njit(cache=True, nogil=True)
def _least_near(points: np.ndarray, positions: np.ndarray, distances: np.ndarray, radius: float) -> np.ndarray:
    """For each point the least of ``distances`` whose ``positions`` lie within ``radius`` (inf: none)."""
    out = np.full(len(points), np.inf)
    r2 = radius * radius
    for n in range(len(points)):
        x, y, z = points[n, 0], points[n, 1], points[n, 2]
        for m in range(len(positions)):
            dx, dy, dz = positions[m, 0] - x, positions[m, 1] - y, positions[m, 2] - z
            if dx * dx + dy * dy + dz * dz <= r2 and distances[m] < out[n]:  # NaN: never near
                out[n] = distances[m]
    return out


def _pool(ids: np.ndarray, distances: np.ndarray, here: np.ndarray | None,
          positions: np.ndarray | None) -> _Pool | None:
    finite = np.isfinite(distances)
    if not finite.any():
        return None
    order = np.argsort(ids[finite], kind="stable")
    return _Pool(ids[finite][order], distances[finite][order], float(distances[finite].max()),
                 float(np.median(distances[finite])), here, None if positions is None else positions[finite][order])


def _nearest_in_pool(pool: _Pool, centres: np.ndarray) -> np.ndarray:
    """For each centre id, the least pool distance among ids within :data:`SLACK` of it
    (the pool's farthest distance where none is)."""
    out = np.full(len(centres), pool.farthest)
    for offset in range(-SLACK, SLACK + 1):
        wanted = centres + offset
        at = np.searchsorted(pool.ids, wanted)
        inside = at < len(pool.ids)
        hit = np.zeros(len(wanted), dtype=bool)
        hit[inside] = pool.ids[at[inside]] == wanted[inside]
        out[hit] = np.minimum(out[hit], pool.distances[at[hit]])
    return out
