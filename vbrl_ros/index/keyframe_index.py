"""Fast nearest-keyframe search for the rotation-minimised Eq. 4 distance: keys + exact re-rank.

A compact descriptor is sector-major, ``x.reshape(S, R)`` (S sectors of a
polar grid, S = 1 for the Cartesian grid), with column weights ``w`` (R,)
tied across sectors. The distance is (**lower = more similar**)

    D(q, t) = min_k D_k(q, t),   D_k = sum_s sum_r w_r |q[(s + k) % S, r] - t[s, r]|

and the best ``k`` gives the yaw (see :class:`SearchResult`). A linear scan
costs N * S * d per query (seconds at 100k polar keyframes). Next to every
descriptor the index keeps small keys and searches in (up to) four stages:

1. **Candidates** from a rotation-invariant key: each column summed over the
   sectors, ``c_r = sum_s x[s, r]`` (and, for a descriptor of fewer than
   ``key_dim`` columns, the magnitudes of the column's first DFT harmonics over
   the sectors, :mod:`vbrl_ros.index.harmonics`), these features split at random
   (seeded) into ``key_dim`` groups, key_j = sum over the group of
   ``sign_f coefficient_f feature_f`` (random signs). By the triangle inequality
   ``||key(a) - key(b)||_1 <= D_k(a, b)`` for every shift k: a lower bound
   whatever the heading. 4 bits per entry with scales fixed by the weights
   (no training, O(d) inserts, never a rebuild), scanned at memory speed keeping the ``scan_pool x candidates`` best
   (:mod:`vbrl_ros.index.keys`); a finer *refine key* (the same construction
   with ``refine_dim`` groups, kept row-major) re-scores those and keeps the
   ``candidates`` best. Twice the groups rank the true match much better but
   would double the scan; re-scoring 4096 costs ~0.5-0.7 ms.
2. **Yaw keys** (S > 1). Re-ranking C candidates at all S shifts costs
   C * S * d, and summing over sectors discards where things are around the
   sensor, so the invariant key is coarse. A per-sector yaw key — ``yaw_dim``
   signed group sums per sector, (S, yaw_dim) float32 — bounds every D_k from
   below too. Its first quarter of groups, compared under all S shifts, screens
   the candidates and picks each one's ``bound_shifts`` most promising shifts
   (default: all of them); the whole key at those keeps the ``rerank`` candidates with the smallest
   bound and, for each, its ``yaw_shifts`` most promising shifts.
3. **Exact re-rank**: D_k at those shifts, in float32, with the same compiled
   sums as :meth:`KeyframeIndex.exact_search` (:mod:`vbrl_ros.model.distance_kernels`),
   so a keyframe's distance is bitwise the same in both. Only the nearest
   ``max(complete_rows, top_k)`` (``top_k`` when S = 1) matter from here, so the
   rows go most promising first (smallest bound or key score) and a row is
   dropped once its partial sums exceed the so-many-th distance found so far:
   exact for the rows that matter, and most rows stop after a few sectors.
4. **Shift completion** (S > 1): the ``complete_rows`` nearest keyframes so far
   are scored at every shift (dropping a shift once its partial sum exceeds
   the keyframe's stage-3 distance or the top_k cut-off: it cannot win).
   The yaw key does not always rank a true match's best shift first, and a
   true match scored at a wrong shift looks far away; completing a few rows
   is the cheapest fix (~0.8 ms at S = 24, d ~ 16k).

The result equals brute force whenever the true nearest keyframe survives
stages 1 and 2 and either its best shift is among those tried or it is one of
the ``complete_rows`` nearest after stage 3.

Exclusion: ``allowed`` is ``None``, a boolean mask over the stored keyframes
(``True`` = may be returned; applied inside the key scan, so it is exact) or a
callable returning that mask for an int64 array of every index.
Parameters: :class:`~vbrl_ros.index.parameters.IndexParameters`. Storage:
:class:`~vbrl_ros.index.keyframe_store.KeyframeStore`. Persistence:
:meth:`KeyframeIndex.state` / :meth:`KeyframeIndex.from_state` (plain arrays,
no pickle; :mod:`vbrl_ros.index.state`). Speed and recall: ``vbrl bench``
(:mod:`vbrl_ros.bench.index`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from vbrl_ros.index import keys as kk
from vbrl_ros.index import selection as rs
from vbrl_ros.index.keyframe_store import KeyframeStore
from vbrl_ros.index.parameters import IndexParameters, checked_int
from vbrl_ros.index.state import read_arrays, read_parameters, state_arrays
from vbrl_ros.model import distance_kernels as wk
from vbrl_ros.model.sector_shift import refined_yaw, yaw_of_shift

# candidates the coarse yaw bound passes on, per candidate re-ranked: fewer lost
# cross-season matches that the unscreened index finds
_SCREEN_PER_KEPT = 6

Allowed = Callable[[np.ndarray], np.ndarray] | np.ndarray | None


@dataclass(frozen=True)
class SearchResult:
    """Nearest keyframes, distance ascending (ties: insertion order).

    ``distances``: rotation-minimised Eq. 4, lower = more similar.
    ``shifts``: the best sector shift k of each match (0 when S = 1).
    ``yaws``: radians in (-pi, pi], ``k * 2 pi / S`` (plus the parabola
    refinement if enabled): **the query scan is the match's scan rotated by
    +yaw about z** (counter-clockwise), i.e. ``T_query_match`` has this yaw —
    the seed for geometric verification. 0 for the Cartesian grid.
    """

    indices: np.ndarray  # int64
    distances: np.ndarray  # float64
    shifts: np.ndarray  # int64
    yaws: np.ndarray  # float64


class KeyframeIndex:
    """Rotation-minimised Eq. 4 nearest-keyframe index; distances: lower = more similar.

    ``weights``: the scorer's active weights (``WeightedL1Scorer.active_weights``),
    one per compact row, sector-major and equal across sectors.
    ``parameters`` (:class:`~vbrl_ros.index.parameters.IndexParameters`; default:
    every default) sets S = ``sectors`` and the search; ``None`` values become
    :func:`~vbrl_ros.index.parameters.default_parameters` for the weights' shape
    (``index.parameters`` holds the resolved ones). ``key_dim``: scan-key entries
    per keyframe (4 bits each). ``refine_dim`` (0 = none) and ``scan_pool``: the
    refine key's entries and how many times ``candidates`` the scan passes to
    it. ``candidates``: keyframes kept by the key scan. ``rerank`` (S > 1; S = 1
    re-ranks all candidates): keyframes kept by the yaw keys and scored exactly
    at their ``yaw_shifts`` best shifts, chosen among the ``bound_shifts``
    (default S) best by the yaw key's first quarter. ``complete_rows`` (S > 1):
    the nearest so many (at least ``top_k``) are then scored at every shift.
    ``yaw_dim``: yaw-key groups per sector (S * yaw_dim float32 per keyframe; 0
    when S = 1). ``yaw_refine``: refine the yaw of the returned keyframes by a
    parabola through D at k - 1, k, k + 1 (two more distances each; the distance
    itself stays that of shift k). ``storage``: ``"float32"`` or ``"float16"``
    (half the memory; distances from the rounded descriptors).
    ``key_clip_sigma``: see :class:`~vbrl_ros.index.keys.KeyCodec`.
    """

    def __init__(self, weights: np.ndarray, parameters: IndexParameters | None = None) -> None:
        weights = np.asarray(weights, dtype=np.float32)
        if weights.ndim != 1 or len(weights) == 0:
            raise ValueError("weights must be a non-empty 1-D array (the scorer's active weights)")
        if not np.all(np.isfinite(weights)) or np.any(weights < 0):
            raise ValueError("weights must be finite and non-negative")
        given = parameters or IndexParameters()
        sectors = checked_int("sectors", given.sectors, 1, len(weights))
        if len(weights) % sectors:
            raise ValueError(f"{len(weights)} weights do not split into {sectors} sectors")
        tied = weights.reshape(sectors, -1)
        if np.any(tied != tied[0]):
            raise ValueError("weights must be equal across sectors (tied) for every column")
        self.parameters = given.resolved(tied.shape[1])
        self.weights = weights
        self.column_weights = np.ascontiguousarray(tied[0])
        self.sectors, self.width, self.dimension = sectors, tied.shape[1], len(weights)
        self.sector_angle = 2.0 * math.pi / sectors
        self.store = KeyframeStore(self.column_weights, self.parameters, self.dimension)
        self._all_shifts = np.empty((0, sectors), np.int64)

    def empty_like(self) -> KeyframeIndex:
        """A new, empty index with the same weights and parameters."""
        return type(self)(self.weights, self.parameters)

    # -- the stored keyframes (see KeyframeStore) ----------------------------------

    def __len__(self) -> int:
        return len(self.store)

    def bytes_breakdown(self) -> dict[str, int]:
        """Per-keyframe bytes of the descriptor (d x 4 or 2), the 4-bit keys and the yaw key."""
        return self.store.bytes_breakdown()

    def bytes_per_keyframe(self) -> int:
        """Descriptor + keys per keyframe; excludes growth slack."""
        return sum(self.bytes_breakdown().values())

    def reserve(self, capacity: int) -> None:
        """Pre-allocate room for ``capacity`` keyframes (avoids doubling copies in bulk loads)."""
        self.store.reserve(int(capacity))

    def descriptors(self) -> np.ndarray:
        """Read-only view of the stored descriptors (n, d) in the storage dtype."""
        return self.store.descriptors()

    def descriptor(self, index: int) -> np.ndarray:
        """A copy of stored descriptor ``index`` as float32 (as stored: float16-rounded if so)."""
        return self.store.descriptor(index)

    def check(self, descriptors: np.ndarray, ndim: int = 1) -> np.ndarray:
        """float32 (d,) or (n, d) compact descriptor(s), or ``ValueError`` naming the problem."""
        return self.store.check(descriptors, ndim)

    def add(self, descriptor_compact: np.ndarray) -> int:
        """Insert one compact descriptor; returns its index (insertion order, from 0). O(d) amortised."""
        return int(self.store.insert(self.check(descriptor_compact)[None])[0])

    def add_batch(self, descriptors_compact: np.ndarray) -> np.ndarray:
        """Insert (m, d) descriptors; returns their indices."""
        return self.store.insert(self.check(descriptors_compact, 2))

    # -- searching --------------------------------------------------------------

    def search(self, query: np.ndarray, top_k: int = 1,
               allowed: Allowed = None) -> tuple[np.ndarray, np.ndarray]:
        """(indices, distances) of the ``top_k`` nearest allowed keyframes, distance ascending."""
        result = self.search_with_yaw(query, top_k, allowed)
        return result.indices, result.distances

    def exact_search(self, query: np.ndarray, top_k: int = 1,
                     allowed: Allowed = None) -> tuple[np.ndarray, np.ndarray]:
        """Brute-force reference: every allowed keyframe at every shift (same ordering rules)."""
        result = self.search_with_yaw(query, top_k, allowed, exact=True)
        return result.indices, result.distances

    def search_with_yaw(self, query: np.ndarray, top_k: int = 1, allowed: Allowed = None,
                        *, exact: bool = False) -> SearchResult:
        """The ``top_k`` nearest allowed keyframes with their yaws (see :class:`SearchResult`).

        ``exact=True`` is brute force over every keyframe and shift; otherwise the
        staged search, exact for the keyframes it returns.
        """
        q = self.check(query)
        n = len(self.store)
        if top_k <= 0 or n == 0:
            return self._result(q, np.empty(0, np.int64), np.empty(0, np.float32),
                                np.empty(0, np.int64))
        mask = None if allowed is None else self._mask(allowed)
        if exact:
            rows = np.arange(n, dtype=np.int64) if mask is None else np.flatnonzero(mask)
            distances = np.empty(len(rows), np.float32)
            shifts = np.empty(len(rows), np.int64)
            self._nearest(q, rows, min(top_k, len(rows)), distances, shifts)
            done = shifts >= 0  # the others provably are not among the top_k
            return self._result(q, rows[done], distances[done], shifts[done], top_k)
        key, yaw_key, refine_key = self.store.codec.raw(q[None])
        rows, key_scores = self._candidates(key[0], refine_key[0], mask, top_k)
        if self.sectors == 1:
            tried = np.zeros((len(rows), 1), np.int64)
            promise = key_scores
        else:  # stage 2: yaw-key bounds
            keep = max(self.parameters.rerank, top_k)
            rows, bounded, bounds = self._yaw_bounds(rows, yaw_key[0], keep)
            chosen = rs.lowest_rows(bounds, keep)  # ties: lower row, as rows ascend
            rows, bounded, bounds = rows[chosen], bounded[chosen], bounds[chosen]
            best, _ = rs.smallest(bounds, self.parameters.yaw_shifts)
            tried = rs.gathered(bounded, best)  # ascending, as bounded is
            promise = rs.row_minima(bounds)
        # stage 3: exact distances at the shifts tried, most promising rows first, dropping
        # a row as soon as it cannot be among the `wanted` nearest (stage 4 takes those)
        completing = self.parameters.complete_rows > 0 and self.parameters.yaw_shifts < self.sectors
        wanted = max(self.parameters.complete_rows, top_k) if completing else top_k
        order = np.argsort(promise, kind="stable")
        rows, tried = rows[order], tried[order]
        at = self._at_shifts(q, rows, tried, keep=wanted)
        best, distances = rs.smallest(at, 1)  # tried shifts ascend, so the smallest k on ties
        distances, shifts = distances[:, 0], rs.gathered(tried, best)[:, 0]
        kept = np.isfinite(distances)
        rows, distances, shifts = rows[kept], distances[kept], shifts[kept]
        if completing:
            self._complete(q, rows, distances, shifts, wanted, top_k)
        return self._result(q, rows, distances, shifts, top_k)

    def distances_at_shifts(self, query: np.ndarray, rows: np.ndarray,
                            shifts: np.ndarray) -> np.ndarray:
        """(len(rows), m) float32: D_k(query, keyframe) at each row's ``shifts`` (m per row)."""
        rows = np.ascontiguousarray(rows, dtype=np.int64)
        shifts = np.ascontiguousarray(shifts, dtype=np.int64).reshape(len(rows), -1)
        return self._at_shifts(self.check(query), rows, shifts)

    def refined_yaws(self, query: np.ndarray, rows: np.ndarray, distances: np.ndarray,
                     shifts: np.ndarray) -> np.ndarray:
        """Yaws of each row's best ``shifts`` (refined by a parabola through the distances at the
        neighbouring shifts if the parameters say so), in the order given, as searches give them."""
        return self._yaws(self.check(query), np.asarray(rows, np.int64),
                          np.asarray(distances, np.float32), np.asarray(shifts, np.int64))

    def _yaws(self, q: np.ndarray, rows: np.ndarray, distances: np.ndarray,
              shifts: np.ndarray) -> np.ndarray:
        if not (self.parameters.yaw_refine and self.sectors >= 3 and len(rows)):
            return yaw_of_shift(shifts, self.sectors)
        around = np.stack([(shifts - 1) % self.sectors, (shifts + 1) % self.sectors], axis=1)
        side = self._at_shifts(q, rows, around)
        return refined_yaw(shifts, side[:, 0], distances, side[:, 1], self.sectors)

    def _candidates(self, key: np.ndarray, refine_key: np.ndarray, mask: np.ndarray | None,
                    top_k: int) -> tuple[np.ndarray, np.ndarray]:
        """Stage 1: the candidate rows (ascending) and their key scores (lower = closer).

        The rotation-invariant scan (mask applied inside) keeps its best
        ``scan_pool x candidates``; the finer refine key re-scores those and keeps
        the best ``candidates`` (ties: lower row).
        """
        n = len(self.store)
        want = min(max(self.parameters.candidates, top_k), n)
        pool = min(want * self.parameters.scan_pool, n) if self.parameters.refine_dim else want
        rows = np.empty(pool, np.int64)
        scores = np.empty(pool, np.int32)
        found = kk.scan_top(self.store.key_blocks, kk.padded(self.store.codec.quantised(key)), n,
                            np.empty(0, np.bool_) if mask is None else mask, pool, rows, scores)
        rows, scores = rows[:found], scores[:found]  # ascending rows: sequential gathers
        if self.parameters.refine_dim and found > want:
            kk.refine_scores(self.store.refine_key_bytes, rows,
                             kk.padded(self.store.codec.refine_quantised(refine_key)), scores)
            codes = (scores.astype(np.int64) << 32) | rows  # smaller score, then lower row
            chosen = np.sort(np.argpartition(codes, want - 1)[:want])
            rows, scores = rows[chosen], scores[chosen]
        return rows, scores

    def _yaw_bounds(self, rows: np.ndarray, query_yaw: np.ndarray,
                    keep: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The candidates worth finishing, and their yaw-key bounds at their most promising shifts.

        Returns (rows', shifts (len(rows'), m), bounds (len(rows'), m)), shifts
        ascending per row. The bound is a sum over the yaw key's groups, so the
        first quarter of them alone is a weaker bound at a quarter of the cost.
        It is computed at every shift and screens the candidates down to
        ``_SCREEN_PER_KEPT * keep``; only those get the rest of the sum, at
        their ``bound_shifts`` best shifts by it (default: all). Fewer is faster
        (~0.9 ms at 100k keyframes, m = 4 of 24) but loses real within-session
        matches that a padded benchmark does not show.
        """
        split, sectors = self.store.coarse_groups, self.sectors
        every = self._every_shift(len(rows))
        fine_query = np.ascontiguousarray(query_yaw[:, split:])
        if not split:  # too few groups to split: the whole bound at every shift
            bounds = np.empty((len(rows), sectors), np.float32)
            kk.yaw_bounds(self.store.yaw_fine, rows, fine_query, every, bounds)
            return rows, every, bounds
        coarse = np.empty((len(rows), sectors), np.float32)
        kk.yaw_bounds(self.store.yaw_coarse, rows, np.ascontiguousarray(query_yaw[:, :split]), every,
                      coarse)
        screened = rs.lowest_rows(coarse, _SCREEN_PER_KEPT * keep)
        rows, coarse = rows[screened], coarse[screened]
        if self.parameters.bound_shifts < sectors:
            shifts, picked = rs.smallest(coarse, self.parameters.bound_shifts)
        else:
            shifts, picked = self._every_shift(len(rows)), coarse
        rest = np.empty(shifts.shape, np.float32)
        kk.yaw_bounds(self.store.yaw_fine, rows, fine_query, shifts, rest)
        return rows, shifts, picked + rest

    def _every_shift(self, n: int) -> np.ndarray:
        """(n, S) int64 rows of 0..S-1, C-contiguous (kernels take it faster than a broadcast)."""
        if len(self._all_shifts) < n:
            self._all_shifts = np.tile(np.arange(self.sectors), (max(n, self.parameters.candidates), 1))
        return self._all_shifts[:n]

    def _complete(self, q: np.ndarray, rows: np.ndarray, distances: np.ndarray,
                  shifts: np.ndarray, count: int, top_k: int) -> None:
        """Stage 4: min over every shift for the ``count`` nearest rows, in place."""
        nearest = np.lexsort((rows, distances))[:count]  # nearest first: abandons early
        full_d = np.empty(len(nearest), np.float32)
        full_k = np.empty(len(nearest), np.int64)
        # a shift is dropped once it exceeds the row's stage-3 distance: it cannot improve it
        self._nearest(q, rows[nearest], min(top_k, len(nearest)), full_d, full_k,
                      row_limits=distances[nearest])
        # same sums as stage 3, so the shift found there gives an equal value; <= keeps
        # the smallest k on ties. Abandoned rows (k = -1) cannot reach the top_k.
        better = (full_k >= 0) & (full_d <= distances[nearest])
        distances[nearest[better]] = full_d[better]
        shifts[nearest[better]] = full_k[better]

    def _nearest(self, q: np.ndarray, rows: np.ndarray, top_k: int, distances: np.ndarray,
                 shifts: np.ndarray, row_limits: np.ndarray | None = None) -> None:
        limits = np.full(len(rows), np.inf, np.float32) if row_limits is None else row_limits
        wk.nearest(self.store.kernel_view(), rows, q, self.column_weights, self.sectors, top_k, limits,
                   distances, shifts)

    def _at_shifts(self, q: np.ndarray, rows: np.ndarray, shifts: np.ndarray,
                   keep: int = 0) -> np.ndarray:
        out = np.empty(shifts.shape, np.float32)
        wk.at_shifts(self.store.kernel_view(), rows, shifts, q, self.column_weights, self.sectors, out, keep)
        return out

    def _result(self, q: np.ndarray, rows: np.ndarray, distances: np.ndarray,
                shifts: np.ndarray, top_k: int = 0) -> SearchResult:
        order = np.lexsort((rows, distances))[:top_k]  # distance, then insertion order
        rows, distances, shifts = rows[order].astype(np.int64), distances[order], shifts[order]
        yaws = self._yaws(q, rows, distances, shifts)
        return SearchResult(rows, distances.astype(np.float64), shifts.astype(np.int64), yaws)

    def _mask(self, allowed: np.ndarray | Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        if callable(allowed):
            allowed = allowed(np.arange(len(self.store), dtype=np.int64))
        mask = np.asarray(allowed)
        if mask.dtype != bool or mask.shape != (len(self.store),):
            raise ValueError(
                f"allowed must be a boolean mask of shape ({len(self.store)},) (or a callable "
                f"returning one) or None; got {mask.dtype} {mask.shape}"
            )
        return np.ascontiguousarray(mask)

    # -- persistence -------------------------------------------------------------

    def state(self, prefix: str = "index_") -> dict[str, np.ndarray]:
        """Plain arrays (no objects) to store in an ``.npz``; restore with :meth:`from_state`."""
        return state_arrays(self.parameters, self.weights, self.store.arrays(), prefix)

    @classmethod
    def from_state(cls, arrays: Mapping[str, np.ndarray], prefix: str = "index_") -> KeyframeIndex:
        """Rebuild from :meth:`state` arrays; raises ``ValueError`` naming the problem."""
        parameters, weights = read_parameters(arrays, prefix)
        index = cls(weights, parameters)
        index.store.restore(read_arrays(arrays, prefix, index.parameters, index.dimension))
        return index
