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
    views, offsets = checked_views(views, offsets)
    wanted = top_k if len(views) == 1 and rescore is None else max(pool, top_k)
    if len(views) == 1:  # the index's own yaws: no view to pick
        base = index.search_with_yaw(views[0], wanted, allowed, exact=exact)
        rows = base.indices
        ranked = ranked_by(rows, base.distances, rescore)
        order = np.lexsort((rows, ranked))[:top_k]
        return ViewSearchResult(rows[order], ranked[order], base.shifts[order], base.yaws[order],
                                np.zeros((len(order), 2)))
    found = view_pool(index, views, wanted, allowed, exact=exact)
    ranked = ranked_by(found.rows, found.distances, rescore)
    order = np.lexsort((found.rows, ranked))[:top_k]
    rows, distances, shifts, winner = (found.rows[order], found.distances[order], found.shifts[order],
                                       found.winner[order])
    return ViewSearchResult(rows, ranked[order], shifts, pool_yaws(index, views, rows, distances, shifts, winner),
                            offsets[winner])


def checked_views(views: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``views`` (V, d) and ``offsets`` (V, 2) as arrays, or ``ValueError`` when they do not pair up."""
    views = np.asarray(views)
    offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 2)
    if views.ndim != 2 or len(views) != len(offsets) or len(views) == 0:
        raise ValueError(f"{len(views)} views for {len(offsets)} offsets")
    return views, offsets


@dataclass(frozen=True)
class ViewPool:
    """Keyframes of one index nearest a query described from several viewpoints, unranked."""

    rows: np.ndarray  # int64, the index's rows
    distances: np.ndarray  # float32, each the minimum over the views
    shifts: np.ndarray  # int64, the sector shift of that minimum
    winner: np.ndarray  # int64, the view it was found under


def view_pool(index: KeyframeIndex, views: np.ndarray, wanted: int, allowed: Allowed = None, *,
              exact: bool = False) -> ViewPool:
    """The ``wanted`` keyframes nearest the first of ``views`` (V, d), each re-scored under every
    view within :data:`SHIFT_RADIUS` sector shifts of its best."""
    base = index.search_with_yaw(views[0], wanted, allowed, exact=exact)
    rows, n = base.indices, len(base.indices)
    distances = base.distances.astype(np.float32)
    shifts, winner = base.shifts.copy(), np.zeros(n, np.int64)
    if n == 0:
        return ViewPool(rows, distances, shifts, winner)
    sectors = index.sectors
    radius = min(SHIFT_RADIUS, (sectors - 1) // 2)
    around = (base.shifts[:, None] + np.arange(-radius, radius + 1)) % sectors
    for v in range(1, len(views)):
        at = index.distances_at_shifts(views[v], rows, around)
        k = np.argmin(at, axis=1)
        d = at[np.arange(n), k]
        better = d < distances
        distances[better], shifts[better], winner[better] = d[better], around[better, k[better]], v
    return ViewPool(rows, distances, shifts, winner)


def pool_yaws(index: KeyframeIndex, views: np.ndarray, rows: np.ndarray, distances: np.ndarray,
              shifts: np.ndarray, winner: np.ndarray) -> np.ndarray:
    """The yaw of each of ``rows`` from its own distances under the view that won it, not the
    ranking's."""
    yaws = np.empty(len(rows))
    for v in np.unique(winner):
        at = winner == v
        yaws[at] = index.refined_yaws(views[v], rows[at], distances[at], shifts[at])
    return yaws


def ranked_by(rows: np.ndarray, distances: np.ndarray, rescore: Rescore | None) -> np.ndarray:
    """float64 distances the pool is ranked by: its own, or ``rescore``'s."""
    return np.asarray(distances if rescore is None else rescore(rows, distances), np.float64)
