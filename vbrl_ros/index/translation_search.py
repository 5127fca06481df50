"""Translation search: a revisit seen from a few metres to the side still finds its keyframe.

A place revisited the other way round comes back rotated ~180 degrees *and* 1-3 m off
laterally (the other lane, the other side of a path); nearby structure then lands in other
rings and sectors and the descriptor no longer matches. The query is described again from
a few viewpoints around the sensor (:meth:`~vbrl_ros.features.featurizer.Featurizer.describe_views`),
the index proposes candidates for the query as seen from where it was taken, and each
candidate is re-scored exactly under every view near its best sector shift. The winning
view is the match's position in the query's (levelled) frame: with the yaw it seeds
geometric verification.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from vbrl_ros.index.keyframe_index import Allowed, KeyframeIndex

#: Candidates re-scored under every view (measured: the right keyframe is often outside
#: the unshifted query's first 30 and mostly inside its first 100).
POOL = 100
#: Sector shifts tried around a candidate's best unshifted shift, each side.
SHIFT_RADIUS = 2


def view_offsets(step_m: float) -> np.ndarray:
    """(V, 2) viewpoints (x, y) in metres: the sensor itself first, then a 3 x 3 grid of
    ``step_m`` and two lateral ones at twice that (the opposite lane). ``step_m`` = 0: the sensor only."""
    if not (np.isfinite(step_m) and step_m >= 0):
        raise ValueError(f"translation search step must be >= 0 metres, got {step_m!r}")
    if step_m == 0:
        return np.zeros((1, 2))
    grid = [(x, y) for x in (-step_m, 0.0, step_m) for y in (-step_m, 0.0, step_m) if (x, y) != (0, 0)]
    return np.array([(0.0, 0.0), *grid, (0.0, 2 * step_m), (0.0, -2 * step_m)])


@dataclass(frozen=True)
class ViewSearchResult:
    """Like :class:`~vbrl_ros.index.keyframe_index.SearchResult` (distance ascending), plus the
    viewpoint (x, y) under which each match was found: the match's position in the query frame."""

    indices: np.ndarray
    distances: np.ndarray
    shifts: np.ndarray
    yaws: np.ndarray
    offsets: np.ndarray  # (k, 2) metres


#: Rescores a pool: (rows, their distances) -> the distances to rank them by.
Rescore = Callable[[np.ndarray, np.ndarray], np.ndarray]


def search_views(index: KeyframeIndex, views: np.ndarray, offsets: np.ndarray, top_k: int,
                 allowed: Allowed = None, *, pool: int = POOL, exact: bool = False,
                 rescore: Rescore | None = None) -> ViewSearchResult:
    """The ``top_k`` nearest keyframes to a query described from several viewpoints.

    ``views`` (V, d) compact descriptors of the query from ``offsets`` (V, 2), the first
    from the sensor itself; candidates come from the index (``exact``: brute force) for the
    first view, the distance of each is the minimum over all views. ``rescore`` (e.g.
    :meth:`~vbrl_ros.index.sequence_matching.SequenceHistory.rescore` by row) turns the
    pool's distances into the ones the result is ranked by and reports.
    """
    views = np.asarray(views)
    offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 2)
    if views.ndim != 2 or len(views) != len(offsets) or len(views) == 0:
        raise ValueError(f"{len(views)} views for {len(offsets)} offsets")
    wanted = top_k if len(views) == 1 and rescore is None else max(pool, top_k)
    base = index.search_with_yaw(views[0], wanted, allowed, exact=exact)
    rows, n = base.indices, len(base.indices)
    if len(views) == 1 or n == 0:
        ranked = _ranked(rows, base.distances, rescore)
        order = np.lexsort((rows, ranked))[:top_k]
        return ViewSearchResult(rows[order], ranked[order], base.shifts[order], base.yaws[order],
                                np.zeros((len(order), 2)))
    sectors = index.sectors
    radius = min(SHIFT_RADIUS, (sectors - 1) // 2)
    around = (base.shifts[:, None] + np.arange(-radius, radius + 1)) % sectors
    distances = base.distances.astype(np.float32)
    shifts, winner = base.shifts.copy(), np.zeros(n, np.int64)
    for v in range(1, len(views)):
        at = index.distances_at_shifts(views[v], rows, around)
        k = np.argmin(at, axis=1)
        d = at[np.arange(n), k]
        better = d < distances
        distances[better], shifts[better], winner[better] = d[better], around[better, k[better]], v
    ranked = _ranked(rows, distances, rescore)
    order = np.lexsort((rows, ranked))[:top_k]
    rows, distances, shifts, winner = rows[order], distances[order], shifts[order], winner[order]
    yaws = np.empty(len(rows))
    for v in np.unique(winner):  # the yaw from the keyframe's own distances, not the ranking's
        at = winner == v
        yaws[at] = index.refined_yaws(views[v], rows[at], distances[at], shifts[at])
    return ViewSearchResult(rows, ranked[order], shifts, yaws, offsets[winner])


def _ranked(rows: np.ndarray, distances: np.ndarray, rescore: Rescore | None) -> np.ndarray:
    """float64 distances the pool is ranked by: its own, or ``rescore``'s."""
    return np.asarray(distances if rescore is None else rescore(rows, distances), np.float64)
