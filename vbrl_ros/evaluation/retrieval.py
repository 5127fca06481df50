"""Descriptor-agnostic retrieval drivers producing top-K results for the metrics.

A method is a callable ``distances_fn(query_index, candidate_indices) ->
distances`` (lower = more similar), called once per query with the whole
visible database as one int array, so a method can score it in a single
vectorised call. A method with its own prefilter (e.g. Scan Context's
ring-key tree) returns ``inf`` for candidates it did not score; those are
never retrieved. Ties are broken by the lower database index, so results are
deterministic.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from .metrics import online_database_limits

__all__ = ["RetrievalResults", "DistancesFn", "select_top_k", "online_retrieval", "cross_session_retrieval"]

DistancesFn = Callable[[int, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class RetrievalResults:
    """Per-query top-K, best first. Padding: index -1, distance inf.

    ``database_limit[q]`` is the length of the database prefix query q saw
    (0 = no database: the row is all padding).
    """

    indices: np.ndarray  # (n_query, K) int64
    distances: np.ndarray  # (n_query, K) float64
    database_limit: np.ndarray  # (n_query,) int64

    @property
    def num_queries(self) -> int:
        return int(self.indices.shape[0])

    @property
    def k(self) -> int:
        return int(self.indices.shape[1])


def select_top_k(candidates: np.ndarray, distances: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` smallest finite distances (ties: lower index), padded to length k."""
    cand = np.asarray(candidates, dtype=np.int64)
    dist = np.asarray(distances, dtype=np.float64)
    if cand.shape != dist.shape or cand.ndim != 1:
        raise ValueError(f"distances_fn returned shape {dist.shape} for {cand.shape} candidates")
    if np.isnan(dist).any():
        raise ValueError("distances_fn returned NaN; use inf for 'not scored'")
    finite = np.isfinite(dist)
    cand, dist = cand[finite], dist[finite]
    if len(dist) > k:  # O(n) preselection before the small exact sort
        part = np.argpartition(dist, k - 1)[:k]
        # Anything tied with the k-th value must stay eligible for the tie-break.
        kth = dist[part].max()
        part = np.flatnonzero(dist <= kth)
        cand, dist = cand[part], dist[part]
    order = np.lexsort((cand, dist))[:k]
    out_i = np.full(k, -1, dtype=np.int64)
    out_d = np.full(k, np.inf)
    out_i[: len(order)] = cand[order]
    out_d[: len(order)] = dist[order]
    return out_i, out_d


def _progress(it: Iterable[int], total: int, enabled: bool, desc: str) -> Iterable[int]:
    if not enabled:
        return it
    from tqdm import tqdm  # optional dependency, imported only when asked for

    return tqdm(it, total=total, desc=desc)


def _run(
    limits: np.ndarray, top: int, distances_fn: DistancesFn, progress: bool, desc: str
) -> RetrievalResults:
    if top < 1:
        raise ValueError("top_k must be >= 1")
    n = len(limits)
    indices = np.full((n, top), -1, dtype=np.int64)
    distances = np.full((n, top), np.inf)
    for i in _progress(range(n), n, progress, desc):
        if limits[i] > 0:
            cand = np.arange(limits[i], dtype=np.int64)
            indices[i], distances[i] = select_top_k(cand, distances_fn(i, cand), top)
    return RetrievalResults(indices, distances, limits.astype(np.int64))


def online_retrieval(
    n: int,
    exclude: int,
    top_k: int,
    distances_fn: DistancesFn,
    progress: bool = False,
) -> RetrievalResults:
    """P1: query i (in increasing order) against scans 0..i-exclude.

    Calls are made in increasing i, so an online method may insert scan
    ``i - exclude`` lazily inside ``distances_fn``.
    """
    return _run(online_database_limits(n, exclude), top_k, distances_fn, progress, "P1 queries")


def cross_session_retrieval(
    n_query: int,
    n_db: int,
    top_k: int,
    distances_fn: DistancesFn,
    progress: bool = False,
) -> RetrievalResults:
    """P2: every query of session B against all ``n_db`` scans of session A."""
    limits = np.full(n_query, n_db, dtype=np.int64)
    return _run(limits, top_k, distances_fn, progress, "P2 queries")
