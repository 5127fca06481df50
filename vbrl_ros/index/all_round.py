"""All-round descriptors: partly blind keyframes compared all round where both can be.

A mast hiding a wedge behind the sensor makes a keyframe hide that wedge and its mirror image
(:mod:`vbrl_ros.features.blind_wedges`), half the circle for a 90° wedge, so that two passes
either way compare the same directions. But the keyframes behind it looked forward into what is
now behind it: where they fill the wedge whole, the keyframe is also described all round
(:meth:`~vbrl_ros.features.trail.Trail.clouds`). An all-round descriptor is compared only with
another: one keyframe described all round and another with half the circle hidden describe
different things (filling wedges in place of hiding them lost a courtyard whose first keyframes,
standing still, had nothing to fill theirs from; docs/results/blind_and_sparse.md).

Every keyframe keeps the descriptor it always had, in the main index; the all-round ones sit in
an :class:`AllRoundIndex` of their own. A query with one is searched in both, and each keyframe
found counts at the nearer of its two distances, the all-round one times
:data:`ALL_ROUND_SCALE`: twice the circle compared, two different places also differ more.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from vbrl_ros.index.keyframe_index import Allowed, KeyframeIndex
from vbrl_ros.index.keyframe_store import grown
from vbrl_ros.index.parameters import IndexParameters
from vbrl_ros.index.translation_search import (POOL, Rescore, ViewSearchResult, checked_views, pool_yaws,
                                               ranked_by, search_views, view_pool)

#: An all-round distance counts this many times over against a hidden one.
ALL_ROUND_SCALE = 1.0 / 0.85


class AllRoundIndex:
    """The all-round descriptors of the keyframes that have one, and which row of the main index
    (the database's keyframes) each belongs to."""

    def __init__(self, weights: np.ndarray, parameters: IndexParameters | None = None) -> None:
        self.index = KeyframeIndex(weights, parameters)
        self._rows = np.zeros(0, np.int64)

    @classmethod
    def like(cls, index: KeyframeIndex) -> AllRoundIndex:
        """An empty one for the descriptors of ``index``."""
        return cls(index.weights, index.parameters)

    def __len__(self) -> int:
        return len(self.index)

    @property
    def rows(self) -> np.ndarray:
        """(n,) int64: the main index's row of each all-round descriptor, in insertion order."""
        return self._rows[: len(self.index)]

    def add(self, row: int, descriptor_compact: np.ndarray) -> None:
        """Keep the all-round descriptor of the main index's ``row``."""
        n = len(self.index)
        self.index.add(descriptor_compact)
        self._rows = grown(self._rows, n + 1)
        self._rows[n] = int(row)

    def allowed(self, allowed: Allowed) -> Allowed:
        """``allowed`` (over the main index's rows) for this index's entries."""
        if allowed is None:
            return None
        rows = self.rows
        if callable(allowed):
            return lambda entries: allowed(rows[entries])
        return np.asarray(allowed)[rows]

    def state(self, prefix: str = "all_round_") -> dict[str, np.ndarray]:
        """Plain arrays to store in an ``.npz``; restore with :meth:`from_state`."""
        return {**self.index.state(prefix), f"{prefix}rows": self.rows.copy()}

    @classmethod
    def from_state(cls, arrays: Mapping[str, np.ndarray], like: KeyframeIndex,
                   prefix: str = "all_round_") -> AllRoundIndex:
        """Rebuild from :meth:`state` arrays; an empty one like the main index ``like`` when there
        are none (a file written before keyframes were described all round)."""
        out = cls.like(like)
        if f"{prefix}rows" not in arrays:
            return out
        out.index = KeyframeIndex.from_state(arrays, prefix)
        rows = np.asarray(arrays[f"{prefix}rows"], np.int64)
        if rows.shape != (len(out.index),) or (len(rows) and (rows.min() < 0 or rows.max() >= len(like))):
            raise ValueError(f"{prefix}rows: {rows.shape} rows for {len(out.index)} descriptors, "
                             f"not all among the {len(like)} keyframes")
        out._rows = rows.copy()
        return out


def search_all_round(index: KeyframeIndex, views: np.ndarray, offsets: np.ndarray, top_k: int,
                     allowed: Allowed = None, *, all_round: AllRoundIndex | None = None,
                     all_round_views: np.ndarray | None = None, pool: int = POOL, exact: bool = False,
                     rescore: Rescore | None = None) -> ViewSearchResult:
    """:func:`~vbrl_ros.index.translation_search.search_views` of a query described from
    ``offsets`` by ``views`` and, when it has them, all round by ``all_round_views`` (V, d):
    those are searched among ``all_round``'s, and a keyframe found both ways counts at the nearer
    distance (the all-round one times :data:`ALL_ROUND_SCALE`). A keyframe in one pool only counts
    by that distance: outside the other's ``pool`` nearest, it is far that way."""
    if all_round is None or all_round_views is None or len(all_round) == 0 or top_k <= 0:
        return search_views(index, views, offsets, top_k, allowed, pool=pool, exact=exact, rescore=rescore)
    views, offsets = checked_views(views, offsets)
    all_round_views, _ = checked_views(all_round_views, offsets)
    wanted = max(pool, top_k)
    kinds = (index, all_round.index)
    pools = (view_pool(index, views, wanted, allowed, exact=exact),
             view_pool(all_round.index, all_round_views, wanted, all_round.allowed(allowed), exact=exact))
    found = (pools[0].rows, all_round.rows[pools[1].rows])
    rows = np.union1d(*found)
    distances = np.full(len(rows), np.inf)
    kind = np.zeros(len(rows), np.int64)
    entry = np.zeros(len(rows), np.int64)  # the row's position in its kind's pool
    for k, scale in enumerate((1.0, ALL_ROUND_SCALE)):
        at = np.searchsorted(rows, found[k])
        scaled = pools[k].distances.astype(np.float64) * scale
        nearer = scaled < distances[at]
        distances[at[nearer]], kind[at[nearer]], entry[at[nearer]] = scaled[nearer], k, np.flatnonzero(nearer)
    ranked = ranked_by(rows, distances, rescore)
    order = np.lexsort((rows, ranked))[:top_k]
    rows, kind, entry = rows[order], kind[order], entry[order]
    shifts, yaws, winner = np.empty(len(rows), np.int64), np.empty(len(rows)), np.empty(len(rows), np.int64)
    for k, (kind_index, kind_views) in enumerate(zip(kinds, (views, all_round_views))):
        at = kind == k
        chosen = pools[k]
        e = entry[at]
        shifts[at], winner[at] = chosen.shifts[e], chosen.winner[e]
        yaws[at] = pool_yaws(kind_index, kind_views, chosen.rows[e], chosen.distances[e], chosen.shifts[e],
                             chosen.winner[e])
    return ViewSearchResult(rows, ranked[order], shifts, yaws, offsets[winner])
