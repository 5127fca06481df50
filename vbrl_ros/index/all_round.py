"""All-round descriptors: partly blind keyframes compared all round where both can be.

A mast hiding a wedge behind the sensor makes a keyframe hide that wedge and its mirror image
(:mod:`vbrl_ros.features.blind_wedges`), half the circle for a 90° wedge, so that two passes
either way compare the same directions. But the keyframes behind it looked forward into what is
now behind it: where they saw into the wedge, the keyframe is also described all round
(:meth:`~vbrl_ros.features.trail.Trail.clouds`). An all-round descriptor is compared only with
another: one keyframe described all round and another with half the circle hidden describe
different things (filling wedges in place of hiding them lost a courtyard whose first keyframes,
standing still, had nothing to fill theirs from; docs/results/blind_and_sparse.md).

Every keyframe keeps the descriptor it always had, in the main index; the all-round ones sit in
an :class:`AllRoundIndex` of their own. A query with one is searched in both, and each keyframe
found counts at the nearer of its two distances, the all-round one times
:data:`ALL_ROUND_SCALE`: twice the circle compared, two different places also differ more.
A keyframe that saw all round by itself (a car's, say, where a robot with a mast queries it) is
described all round by its main descriptor, so all-round queries meet those as well, and such a
keyframe's query meets the all-round descriptors.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from vbrl_ros.index.keyframe_index import Allowed, KeyframeIndex
from vbrl_ros.index.keyframe_store import grown
from vbrl_ros.index.parameters import IndexParameters
from vbrl_ros.index.translation_search import (POOL, Rescore, ViewSearchResult, checked_views, pool_yaws,
                                               ranked_by, search_views, view_pool)

#: An all-round distance counts this many times over against a hidden one. Counted equal, all-round
#: lookalikes outranked the hidden matches of keyframes that could not fill their wedge (a standing
#: start); weighed more, the all-round matches lost their lead (measured with the wedge hidden from
#: the simulated low robot and two shared recordings).
ALL_ROUND_SCALE = 1.0 / 0.85


class AllRoundIndex:
    """The all-round descriptors of the keyframes that have one, and which row of the main index
    (the database's keyframes) each belongs to."""

    def __init__(self, weights: np.ndarray, parameters: IndexParameters | None = None) -> None:
        self.index = KeyframeIndex(weights, parameters)
        self._rows = np.zeros(0, np.int64)
        self._sees = np.zeros(0, bool)  # per main row: its main descriptor is all round
        self._keyframes = 0

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

    @property
    def sees_all_round(self) -> np.ndarray:
        """(keyframes,) bool: which main rows saw all round by themselves (:meth:`note`)."""
        return self._sees[: self._keyframes]

    def note(self, sees_all_round: bool) -> None:
        """The main index's next keyframe: whether it saw all round by itself, so its main
        descriptor is an all-round one. Called once per keyframe, before :meth:`add`."""
        self._sees = grown(self._sees, self._keyframes + 1)
        self._sees[self._keyframes] = bool(sees_all_round)
        self._keyframes += 1

    def add(self, row: int, descriptor_compact: np.ndarray) -> None:
        """Keep the all-round descriptor of the main index's ``row``."""
        n = len(self.index)
        self.index.add(descriptor_compact)
        self._rows = grown(self._rows, n + 1)
        self._rows[n] = int(row)

    def bytes_per_descriptor(self) -> int:
        """What each keyframe also described all round adds: its descriptor with its search keys
        and the main row it belongs to (each keyframe's own flag is not counted here)."""
        return self.index.bytes_per_keyframe() + self._rows.itemsize

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
        return {**self.index.state(prefix), f"{prefix}rows": self.rows.copy(),
                f"{prefix}sees": self.sees_all_round.copy()}

    @classmethod
    def from_state(cls, arrays: Mapping[str, np.ndarray], like: KeyframeIndex,
                   prefix: str = "all_round_") -> AllRoundIndex:
        """Rebuild from :meth:`state` arrays; an empty one like the main index ``like`` when there
        are none (a file written before keyframes were described all round)."""
        out = cls.like(like)
        sees = np.asarray(arrays.get(f"{prefix}sees", np.zeros(len(like), bool)))
        if sees.shape != (len(like),) or sees.dtype != bool:
            raise ValueError(f"{prefix}sees: {sees.dtype} {sees.shape}, expected one bool per keyframe ({len(like)})")
        out._sees, out._keyframes = sees.copy(), len(like)
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
                     all_round_views: np.ndarray | None = None, sees_all_round: bool = False,
                     pool: int = POOL, exact: bool = False, rescore: Rescore | None = None) -> ViewSearchResult:
    """:func:`~vbrl_ros.index.translation_search.search_views` of a query described from
    ``offsets`` by ``views`` and, when it has them, all round by ``all_round_views`` (V, d); a
    query that ``sees_all_round`` by itself is all round by its ``views``. All round, it is also
    searched among ``all_round``'s descriptors and, when described so by filling, among the
    keyframes that saw all round by themselves. A keyframe found several ways counts at the nearest
    (an all-round comparison's times :data:`ALL_ROUND_SCALE`, unless both saw all round by
    themselves: that is the main search); one in some pools only counts by those: outside the
    others' ``pool`` nearest, it is far that way."""
    full_views = all_round_views if all_round_views is not None else (views if sees_all_round else None)
    searches = [(index, views, None, allowed, 1.0)]  # (index, query views, its rows' main rows, allowed, scale)
    if all_round is not None and full_views is not None and top_k > 0:
        if len(all_round):
            searches.append((all_round.index, full_views, all_round.rows, all_round.allowed(allowed),
                             ALL_ROUND_SCALE))
        if all_round_views is not None and all_round.sees_all_round.any():
            sees = all_round.sees_all_round
            searches.append((index, full_views, None, sees if allowed is None else _and(allowed, sees),
                             ALL_ROUND_SCALE))
    if len(searches) == 1:  # nothing to compare all round: the main search alone, as it always was
        return search_views(index, views, offsets, top_k, allowed, pool=pool, exact=exact, rescore=rescore)
    views, offsets = checked_views(views, offsets)
    searches = [(kind, checked_views(kind_views, offsets)[0], *rest) for kind, kind_views, *rest in searches]
    wanted = max(pool, top_k)
    pools = [view_pool(kind, kind_views, wanted, kind_allowed, exact=exact)
             for kind, kind_views, _, kind_allowed, _ in searches]
    found = [p.rows if to_main is None else to_main[p.rows] for p, (_, _, to_main, _, _) in zip(pools, searches)]
    rows = np.unique(np.concatenate(found))
    distances = np.full(len(rows), np.inf)
    source = np.zeros(len(rows), np.int64)  # which search found the row nearest
    entry = np.zeros(len(rows), np.int64)  # its position in that search's pool
    for k, (search, pool_k) in enumerate(zip(searches, pools)):
        at = np.searchsorted(rows, found[k])
        scaled = pool_k.distances.astype(np.float64) * search[4]
        nearer = scaled < distances[at]
        distances[at[nearer]], source[at[nearer]], entry[at[nearer]] = scaled[nearer], k, np.flatnonzero(nearer)
    ranked = ranked_by(rows, distances, rescore)
    order = np.lexsort((rows, ranked))[:top_k]
    rows, source, entry = rows[order], source[order], entry[order]
    shifts, yaws, winner = np.empty(len(rows), np.int64), np.empty(len(rows)), np.empty(len(rows), np.int64)
    for k, ((kind, kind_views, *_), chosen) in enumerate(zip(searches, pools)):
        at = source == k
        e = entry[at]
        shifts[at], winner[at] = chosen.shifts[e], chosen.winner[e]
        yaws[at] = pool_yaws(kind, kind_views, chosen.rows[e], chosen.distances[e], chosen.shifts[e], chosen.winner[e])
    return ViewSearchResult(rows, ranked[order], shifts, yaws, offsets[winner])


def _and(allowed: Allowed, sees: np.ndarray) -> Allowed:
    """``allowed`` (a mask or a callable) and the keyframes that saw all round by themselves."""
    if callable(allowed):
        return lambda rows: np.asarray(allowed(rows)) & sees[rows]
    return np.asarray(allowed) & sees
