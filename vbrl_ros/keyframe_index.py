"""Fast nearest-keyframe search for the rotation-minimised Eq. 4 distance: keys + exact re-rank.

A compact descriptor is sector-major, ``x.reshape(S, R)`` (S sectors of a
polar grid, S = 1 for the Cartesian grid), with column weights ``w`` (R,)
tied across sectors. The distance is (**lower = more similar**)

    D(q, t) = min_k D_k(q, t),   D_k = sum_s sum_r w_r |q[(s + k) % S, r] - t[s, r]|

and the best ``k`` gives the yaw (see :class:`SearchResult`). A linear scan
costs N * S * d per query (seconds at 100k polar keyframes). Next to every
descriptor the index keeps small keys and searches in (up to) four stages:

1. **Candidates** from a rotation-invariant key: each column summed over the
   sectors, ``c_r = sum_s x[s, r]``, the columns split at random (seeded) into
   ``key_dim`` groups, key_j = sum over the group of ``sign_r w_r c_r`` (random
   signs). By the triangle inequality ``||key(a) - key(b)||_1 <= D_k(a, b)`` for
   every shift k: a lower bound whatever the heading. 4 bits per entry with a
   fixed scale from the weights (no training, O(d) inserts, never a rebuild),
   scanned at memory speed keeping the ``scan_pool x candidates`` best
   (:mod:`vbrl_ros.index_keys`); a finer *refine key* (the same construction
   with ``refine_dim`` groups, kept row-major) re-scores those and keeps the
   ``candidates`` best. Twice the groups rank the true match much better (at
   100k keyframes, within the 1024 candidates for 32 of 40 winter queries
   instead of 26) but would double the scan; re-scoring 4096 costs ~0.5-0.7 ms.
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
   The yaw key ranks the best shift first for only ~83 % of true matches (in
   the top 2 for ~93 %, measured on a simulated drive), and a true match
   scored at a wrong shift looks far away; completing a few rows is the
   cheapest fix (~0.8 ms at S = 24, d ~ 16k) and found 24 of the 34 top-1
   disagreements with brute force that stages 1-3 alone left.

The result equals brute force whenever the true nearest keyframe survives
stages 1 and 2 and either its best shift is among those tried or it is one of
the ``complete_rows`` nearest after stage 3.

Exclusion: ``allowed`` is ``None``, a boolean mask over the stored keyframes
(``True`` = may be returned; applied inside the key scan, so it is exact) or a
callable returning that mask for an int64 array of every index.
Persistence: :meth:`KeyframeIndex.state` / :meth:`KeyframeIndex.from_state`
(plain arrays, no pickle; :mod:`vbrl_ros.keyframe_index_state`). Speed and
recall: ``vbrl bench`` (:mod:`vbrl_ros.index_bench`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from vbrl_ros import index_keys as kk
from vbrl_ros import row_selection as rs
from vbrl_ros.index_parameters import checked_int, search_parameters
from vbrl_ros.model import distance_kernels as wk
from vbrl_ros.keyframe_index_state import (  # noqa: F401 - re-exported
    INDEX_FORMAT,
    INDEX_FORMAT_VERSION,
    index_from_state,
    index_state,
)
from vbrl_ros.model.sector_shift import refined_yaw, yaw_of_shift

_INITIAL_CAPACITY = 64
_BATCH_ROWS = 4096  # keys of a bulk insert are computed in chunks of this many rows
_STORAGE = {"float32": np.float32, "float16": np.float16}
_FLOAT16_MAX = 65504.0
# candidates the coarse yaw bound passes on, per candidate re-ranked: 3 and 4 lost one of
# 40 winter queries at 1k or 10k keyframes that the unscreened index found, 6 none
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


def grown(array: np.ndarray, needed: int) -> np.ndarray:
    """``array`` with capacity >= needed along axis 0, doubling so growth is amortised O(1)."""
    capacity = len(array)
    if needed <= capacity:
        return array
    out = np.empty((max(needed, 2 * capacity, _INITIAL_CAPACITY), *array.shape[1:]), array.dtype)
    out[:capacity] = array
    return out


class KeyframeIndex:
    """Rotation-minimised Eq. 4 nearest-keyframe index; distances: lower = more similar.

    ``weights``: the scorer's active weights (``WeightedL1Scorer.active_weights``),
    one per compact row, sector-major and equal across sectors. ``sectors``: S.
    ``key_dim``: scan-key entries per keyframe (4 bits each). ``refine_dim``
    (0 = none) and ``scan_pool``: the refine key's entries and how many times
    ``candidates`` the scan passes to it. ``candidates``:
    keyframes kept by the key scan. ``rerank`` (S > 1; S = 1 re-ranks all
    candidates): keyframes kept by the yaw keys and scored exactly at their
    ``yaw_shifts`` best shifts, chosen among the ``bound_shifts`` (default S)
    best by the yaw key's first quarter. ``complete_rows`` (S > 1): the nearest so many
    (at least ``top_k``) are then scored at every shift. ``yaw_dim``: yaw-key groups per sector
    (S * yaw_dim float32 per keyframe; 0 when S = 1). ``yaw_refine``: refine the
    yaw of the returned keyframes by a parabola through D at k - 1, k, k + 1
    (two more distances each; the distance itself stays that of shift k).
    ``None`` picks :func:`~vbrl_ros.index_parameters.default_parameters`. ``storage``: ``"float32"`` or
    ``"float16"`` (half the memory; distances from the rounded descriptors).
    ``key_clip_sigma``: see :class:`~vbrl_ros.index_keys.KeyCodec`.
    """

    def __init__(
        self,
        weights: np.ndarray,
        *,
        sectors: int = 1,
        key_dim: int | None = None,
        candidates: int | None = None,
        rerank: int | None = None,
        yaw_dim: int | None = None,
        yaw_shifts: int | None = None,
        bound_shifts: int | None = None,
        complete_rows: int | None = None,
        refine_dim: int | None = None,
        scan_pool: int | None = None,
        yaw_refine: bool = False,
        seed: int = 0,
        storage: str = "float32",
        key_clip_sigma: float = 3.0,
    ) -> None:
        weights = np.asarray(weights, dtype=np.float32)
        if weights.ndim != 1 or len(weights) == 0:
            raise ValueError("weights must be a non-empty 1-D array (the scorer's active weights)")
        if not np.all(np.isfinite(weights)) or np.any(weights < 0):
            raise ValueError("weights must be finite and non-negative")
        sectors = checked_int("sectors", sectors, 1, len(weights))
        if len(weights) % sectors:
            raise ValueError(f"{len(weights)} weights do not split into {sectors} sectors")
        tied = weights.reshape(sectors, -1)
        if np.any(tied != tied[0]):
            raise ValueError("weights must be equal across sectors (tied) for every column")
        width = tied.shape[1]
        chosen = search_parameters(width, sectors, key_dim=key_dim, candidates=candidates,
                                   rerank=rerank, yaw_dim=yaw_dim, yaw_shifts=yaw_shifts,
                                   bound_shifts=bound_shifts,
                                   complete_rows=complete_rows, refine_dim=refine_dim,
                                   scan_pool=scan_pool)
        self.key_dim, self.candidates = chosen["key_dim"], chosen["candidates"]
        self.refine_dim, self.scan_pool = chosen["refine_dim"], chosen["scan_pool"]
        self.rerank, self.complete_rows = chosen["rerank"], chosen["complete_rows"]
        self.yaw_dim, self.yaw_shifts = chosen["yaw_dim"], chosen["yaw_shifts"]
        self.bound_shifts = chosen["bound_shifts"]
        if storage not in _STORAGE:
            raise ValueError(f"storage must be one of {sorted(_STORAGE)}, got {storage!r}")
        if not key_clip_sigma > 0:
            raise ValueError(f"key_clip_sigma must be positive, got {key_clip_sigma!r}")
        self.weights = weights
        self.column_weights = np.ascontiguousarray(tied[0])
        self.sectors, self.width, self.dimension = sectors, width, len(weights)
        self.sector_angle = 2.0 * math.pi / sectors
        self.yaw_refine = bool(yaw_refine)
        self.seed = int(seed)
        self.storage = storage
        self.key_clip_sigma = float(key_clip_sigma)

        self._codec = kk.KeyCodec(self.column_weights, sectors, self.key_dim, self.yaw_dim,
                                  self.seed, self.key_clip_sigma, self.refine_dim)
        self._size = 0
        self._descriptors = np.empty((_INITIAL_CAPACITY, self.dimension), _STORAGE[storage])
        self._key_blocks = np.empty((1, self._key_bytes(), kk.BLOCK), np.uint8)
        self._refine_keys = np.empty((_INITIAL_CAPACITY, -(-self.refine_dim // 2)), np.uint8)
        # the yaw key's first quarter of groups is kept apart to screen candidates cheaply
        self._coarse_groups = self.yaw_dim // 4
        self._all_shifts = np.empty((0, sectors), np.int64)
        self._yaw_coarse = np.empty((_INITIAL_CAPACITY, sectors, self._coarse_groups), np.float32)
        self._yaw_fine = np.empty((_INITIAL_CAPACITY, sectors, self.yaw_dim - self._coarse_groups),
                                  np.float32)

    def options(self) -> dict[str, Any]:
        """Constructor keywords that rebuild an index with the same parameters (no data)."""
        names = ("sectors", "key_dim", "candidates", "rerank", "yaw_dim", "yaw_shifts",
                 "bound_shifts", "complete_rows", "refine_dim", "scan_pool", "yaw_refine", "seed", "storage",
                 "key_clip_sigma")
        return {name: getattr(self, name) for name in names}

    def empty_like(self) -> KeyframeIndex:
        """A new, empty index with the same weights and parameters."""
        return type(self)(self.weights, **self.options())

    # -- size and memory ------------------------------------------------------

    def __len__(self) -> int:
        return self._size

    def bytes_breakdown(self) -> dict[str, int]:
        """Per-keyframe bytes of the descriptor (d x 4 or 2), the 4-bit key and the yaw key."""
        return {"descriptor": self.dimension * np.dtype(_STORAGE[self.storage]).itemsize,
                "key": self._key_bytes() + self._refine_keys.shape[1],
                "yaw_key": 4 * self.sectors * self.yaw_dim}

    def _key_bytes(self) -> int:
        return -(-self.key_dim // 2)  # two 4-bit entries per byte

    def bytes_per_keyframe(self) -> int:
        """Descriptor + keys per keyframe; excludes growth slack."""
        return sum(self.bytes_breakdown().values())

    def reserve(self, capacity: int) -> None:
        """Pre-allocate room for ``capacity`` keyframes (avoids doubling copies in bulk loads)."""
        self._reserve(int(capacity))

    def _reserve(self, needed: int) -> None:
        self._descriptors = grown(self._descriptors, needed)
        self._yaw_coarse = grown(self._yaw_coarse, needed)
        self._yaw_fine = grown(self._yaw_fine, needed)
        self._refine_keys = grown(self._refine_keys, needed)
        self._key_blocks = grown(self._key_blocks, -(-needed // kk.BLOCK))

    # -- reading --------------------------------------------------------------

    def descriptors(self) -> np.ndarray:
        """Read-only view of the stored descriptors (n, d) in the storage dtype."""
        view = self._descriptors[: self._size]
        view.flags.writeable = False
        return view

    def descriptor(self, index: int) -> np.ndarray:
        """A copy of stored descriptor ``index`` as float32 (as stored: float16-rounded if so)."""
        if not -self._size <= index < self._size:
            raise IndexError(f"keyframe index {index} out of range for {self._size} keyframes")
        return self._descriptors[index % self._size].astype(np.float32)

    # -- keys -------------------------------------------------------------------

    def raw_keys(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unquantised (candidate keys (n, key_dim), yaw keys (n, S, yaw_dim)) of (n, d).

        Their L1 distances (the yaw key's under a circular shift of its first
        axis) are lower bounds of D_k for every shift k.
        """
        x = np.ascontiguousarray(descriptors, dtype=np.float32).reshape(-1, self.dimension)
        return self._codec.raw(x)[:2]

    def keys_as_stored(self, descriptors: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(candidate keys (n, key_dim) int8, yaw keys (n, S, yaw_dim) float32, refine keys
        (n, refine_dim) int8) of compact descriptors (n, d), from one pass over them."""
        x = np.ascontiguousarray(descriptors, dtype=np.float32).reshape(-1, self.dimension)
        keys, yaw, refine = self._codec.raw(x)
        return (self._codec.quantised(keys).astype(np.int8) - 8, yaw,
                self._codec.refine_quantised(refine).astype(np.int8) - 8)

    def keys(self, descriptors: np.ndarray) -> np.ndarray:
        """Candidate keys (n, key_dim) or (key_dim,) of compact descriptors: int8 in [-7, 7]."""
        x = np.asarray(descriptors)
        return self.keys_as_stored(x)[0].reshape(*x.shape[:-1], self.key_dim)

    def refine_keys(self, descriptors: np.ndarray) -> np.ndarray:
        """Refine keys (n, refine_dim) of compact descriptors (n, d): int8 in [-7, 7]."""
        return self.keys_as_stored(descriptors)[2]

    def stored_refine_keys(self) -> np.ndarray:
        """The stored refine keys (n, refine_dim), int8 in [-7, 7]."""
        return kk.unpacked(self._refine_keys[: self._size], self.refine_dim).astype(np.int8) - 8

    def stored_keys(self) -> np.ndarray:
        """The stored candidate keys (n, key_dim), int8 in [-7, 7], row-major."""
        pairs = self._key_blocks.transpose(0, 2, 1).reshape(-1, self._key_bytes())[: self._size]
        return kk.unpacked(pairs, self.key_dim).astype(np.int8) - 8

    # -- writing ----------------------------------------------------------------

    def check(self, descriptors: np.ndarray, ndim: int = 1) -> np.ndarray:
        """float32 (d,) or (n, d) compact descriptor(s), or ``ValueError`` naming the problem."""
        # aligned + contiguous: numba compiles unaligned views (e.g. from an .npz) to scalar code
        x = np.require(descriptors, np.float32, ["C", "A"])
        if x.ndim != ndim or x.shape[-1] != self.dimension:
            what = "(d,)" if ndim == 1 else "(n, d)"
            raise ValueError(
                f"compact descriptor(s) must have shape {what} with d = {self.dimension} active "
                f"rows, got {x.shape} (pass scorer.compact(descriptor))"
            )
        if not np.all(np.isfinite(x)):
            raise ValueError("descriptor contains NaN or inf")
        if self.storage == "float16" and x.size and float(np.abs(x).max()) > _FLOAT16_MAX:
            raise ValueError("descriptor exceeds the float16 range; use storage='float32'")
        return x

    def add(self, descriptor_compact: np.ndarray) -> int:
        """Insert one compact descriptor; returns its index (insertion order, from 0). O(d) amortised."""
        return int(self._insert(self.check(descriptor_compact)[None])[0])

    def add_batch(self, descriptors_compact: np.ndarray) -> np.ndarray:
        """Insert (m, d) descriptors; returns their indices."""
        return self._insert(self.check(descriptors_compact, 2))

    def _insert(self, x: np.ndarray) -> np.ndarray:
        n, m = self._size, len(x)
        self._reserve(n + m)
        for start in range(0, m, _BATCH_ROWS):
            chunk = np.ascontiguousarray(x[start : start + _BATCH_ROWS])
            rows = np.arange(n + start, n + start + len(chunk))
            if self.storage == "float32":
                self._descriptors[rows[0] : rows[-1] + 1] = chunk
            else:  # keys of the values as stored, so the bounds stay valid
                wk.store_half(chunk, self._store()[rows[0] : rows[-1] + 1])
            keys, yaw, refine = self._codec.raw(self._store()[rows[0] : rows[-1] + 1])
            self._write_keys(rows, self._codec.quantised(keys), yaw,
                             self._codec.refine_quantised(refine))
        self._size = n + m
        return np.arange(n, n + m, dtype=np.int64)

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
        n = self._size
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
        key, yaw_key, refine_key = self._codec.raw(q[None])
        rows, key_scores = self._candidates(key[0], refine_key[0], mask, top_k)
        if self.sectors == 1:
            tried = np.zeros((len(rows), 1), np.int64)
            promise = key_scores
        else:  # stage 2: yaw-key bounds
            keep = max(self.rerank, top_k)
            rows, bounded, bounds = self._yaw_bounds(rows, yaw_key[0], keep)
            chosen = rs.lowest_rows(bounds, keep)  # ties: lower row, as rows ascend
            rows, bounded, bounds = rows[chosen], bounded[chosen], bounds[chosen]
            best, _ = rs.smallest(bounds, self.yaw_shifts)
            tried = rs.gathered(bounded, best)  # ascending, as bounded is
            promise = rs.row_minima(bounds)
        # stage 3: exact distances at the shifts tried, most promising rows first, dropping
        # a row as soon as it cannot be among the `wanted` nearest (stage 4 takes those)
        completing = self.complete_rows > 0 and self.yaw_shifts < self.sectors
        wanted = max(self.complete_rows, top_k) if completing else top_k
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

    def _candidates(self, key: np.ndarray, refine_key: np.ndarray, mask: np.ndarray | None,
                    top_k: int) -> tuple[np.ndarray, np.ndarray]:
        """Stage 1: the candidate rows (ascending) and their key scores (lower = closer).

        The rotation-invariant scan (mask applied inside) keeps its best
        ``scan_pool x candidates``; the finer refine key re-scores those and keeps
        the best ``candidates`` (ties: lower row).
        """
        n = self._size
        want = min(max(self.candidates, top_k), n)
        pool = min(want * self.scan_pool, n) if self.refine_dim else want
        rows = np.empty(pool, np.int64)
        scores = np.empty(pool, np.int32)
        found = kk.scan_top(self._key_blocks, kk.padded(self._codec.quantised(key)), n,
                            np.empty(0, np.bool_) if mask is None else mask, pool, rows, scores)
        rows, scores = rows[:found], scores[:found]  # ascending rows: sequential gathers
        if self.refine_dim and found > want:
            kk.refine_scores(self._refine_keys, rows,
                             kk.padded(self._codec.refine_quantised(refine_key)), scores)
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
        their ``bound_shifts`` best shifts by it (default: all). Fewer is ~0.9 ms
        faster at 100k keyframes (m = 4 of 24) and agreed with brute force as
        well on the padded bench, but lost real within-session matches: top-1
        equal to brute force on mid360_walk (town0polar) fell from 1068 to
        1033 of 1069 queries at m = 4 and 1059 at m = 8.
        """
        split, sectors = self._coarse_groups, self.sectors
        every = self._every_shift(len(rows))
        fine_query = np.ascontiguousarray(query_yaw[:, split:])
        if not split:  # too few groups to split: the whole bound at every shift
            bounds = np.empty((len(rows), sectors), np.float32)
            kk.yaw_bounds(self._yaw_fine, rows, fine_query, every, bounds)
            return rows, every, bounds
        coarse = np.empty((len(rows), sectors), np.float32)
        kk.yaw_bounds(self._yaw_coarse, rows, np.ascontiguousarray(query_yaw[:, :split]), every,
                      coarse)
        screened = rs.lowest_rows(coarse, _SCREEN_PER_KEPT * keep)
        rows, coarse = rows[screened], coarse[screened]
        if self.bound_shifts < sectors:
            shifts, picked = rs.smallest(coarse, self.bound_shifts)
        else:
            shifts, picked = self._every_shift(len(rows)), coarse
        rest = np.empty(shifts.shape, np.float32)
        kk.yaw_bounds(self._yaw_fine, rows, fine_query, shifts, rest)
        return rows, shifts, picked + rest

    def _every_shift(self, n: int) -> np.ndarray:
        """(n, S) int64 rows of 0..S-1, C-contiguous (kernels take it faster than a broadcast)."""
        if len(self._all_shifts) < n:
            self._all_shifts = np.tile(np.arange(self.sectors), (max(n, self.candidates), 1))
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
        wk.nearest(self._store(), rows, q, self.column_weights, self.sectors, top_k, limits,
                   distances, shifts)

    def _store(self) -> np.ndarray:
        return self._descriptors if self.storage == "float32" else self._descriptors.view(np.uint16)

    def _at_shifts(self, q: np.ndarray, rows: np.ndarray, shifts: np.ndarray,
                   keep: int = 0) -> np.ndarray:
        out = np.empty(shifts.shape, np.float32)
        wk.at_shifts(self._store(), rows, shifts, q, self.column_weights, self.sectors, out, keep)
        return out

    def _result(self, q: np.ndarray, rows: np.ndarray, distances: np.ndarray,
                shifts: np.ndarray, top_k: int = 0) -> SearchResult:
        order = np.lexsort((rows, distances))[:top_k]  # distance, then insertion order
        rows, distances, shifts = rows[order].astype(np.int64), distances[order], shifts[order]
        yaws = yaw_of_shift(shifts, self.sectors)
        if self.yaw_refine and self.sectors >= 3 and len(rows):
            around = np.stack([(shifts - 1) % self.sectors, (shifts + 1) % self.sectors], axis=1)
            side = self._at_shifts(q, rows, around)
            yaws = refined_yaw(shifts, side[:, 0], distances, side[:, 1], self.sectors)
        return SearchResult(rows, distances.astype(np.float64), shifts.astype(np.int64), yaws)

    def _mask(self, allowed: np.ndarray | Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        if callable(allowed):
            allowed = allowed(np.arange(self._size, dtype=np.int64))
        mask = np.asarray(allowed)
        if mask.dtype != bool or mask.shape != (self._size,):
            raise ValueError(
                f"allowed must be a boolean mask of shape ({self._size},) (or a callable "
                f"returning one) or None; got {mask.dtype} {mask.shape}"
            )
        return np.ascontiguousarray(mask)

    # -- persistence -------------------------------------------------------------

    def state(self, prefix: str = "index_") -> dict[str, np.ndarray]:
        """Plain arrays (no objects) to store in an ``.npz``; restore with :meth:`from_state`."""
        return index_state(self, prefix)

    @classmethod
    def from_state(cls, arrays: Mapping[str, np.ndarray], prefix: str = "index_") -> KeyframeIndex:
        """Rebuild from :meth:`state` arrays; raises ``ValueError`` naming the problem."""
        return index_from_state(cls, arrays, prefix)

    def stored_yaw_keys(self) -> np.ndarray:
        """The stored yaw keys (n, S, yaw_dim) float32 (a copy)."""
        n = self._size
        return np.concatenate([self._yaw_coarse[:n], self._yaw_fine[:n]], axis=2)

    def _write_keys(self, rows: np.ndarray, key_codes: np.ndarray, yaw: np.ndarray,
                    refine_codes: np.ndarray) -> None:
        """Store the keys of consecutive ``rows`` (nibble codes: value + 8)."""
        first, last, split = rows[0], rows[-1] + 1, self._coarse_groups
        self._key_blocks[rows // kk.BLOCK, :, rows % kk.BLOCK] = kk.packed(key_codes)
        self._refine_keys[first:last] = kk.packed(refine_codes)
        self._yaw_coarse[first:last] = yaw[:, :, :split]
        self._yaw_fine[first:last] = yaw[:, :, split:]

    def _adopt(self, descriptors: np.ndarray, keys: np.ndarray, yaw_keys: np.ndarray,
               refine_keys: np.ndarray) -> None:
        """Take over validated stored arrays (from :func:`index_from_state`)."""
        n = len(descriptors)
        self._size = 0
        self._reserve(n)
        self._descriptors[:n] = descriptors
        if n:
            self._write_keys(np.arange(n), (keys + 8).astype(np.uint8), yaw_keys,
                             (refine_keys + 8).astype(np.uint8))
        self._size = n

