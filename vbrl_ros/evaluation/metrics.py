"""Loop-closure metrics for the protocols of docs/design.md section 3.

Generic core: queries with positions, a database with positions, and for each
query its top-K retrieved database indices with distances (lower = more
similar). Each query q may only see a *prefix* of the database,
``database[:database_limit[q]]``; that single rule expresses both protocols:

- P1 (online, one session): query i sees scans 0..i-E, i.e. limit i-E+1
  (:func:`online_database_limits`); query and database positions coincide.
- P2 (cross-session): every query sees the whole of session A.

Definitions (R = radius, all distances in metres, comparisons strict):

- a *query* is a query whose visible database is non-empty;
- a query is a *revisit* if some visible database position is within R;
- a retrieved index is *correct* if it is visible (``0 <= j < limit``) and
  within R of the query. A match the method returns from outside the visible
  prefix (e.g. inside the P1 exclusion window) is never correct: it counts as
  wrong (a false positive if accepted), never silently dropped;
- index -1 or a non-finite distance means "no candidate" (never accepted).

Threshold sweep on the top-1 distance s: a query is *accepted* at threshold
t if s <= t. TP = accepted & correct, FP = accepted & wrong,
FN = revisits - TP (every correct top-1 is a revisit, so FN counts revisit
queries that are not accepted-and-correct). The sweep visits every distinct
top-1 distance (ties enter together), computed with one sort and cumulative
sums.

- precision = TP / (TP + FP), recall = TP / revisits;
- max F1 over the sweep (0 if nothing is ever correct);
- average precision AP = sum_k (recall_k - recall_{k-1}) * precision_k over
  the distinct thresholds in ascending order, recall_0 = 0: the step-wise
  area under the PR curve without interpolation (the same definition as
  scikit-learn's ``average_precision_score``);
- recall at 100 % precision: the largest recall with FP = 0 (0 if the most
  confident match is wrong);
- Recall@K: fraction of revisit queries with a correct index among the
  first K retrieved (None when fewer than K columns were retrieved).

With no revisit queries, recall-based metrics are undefined and reported as
NaN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "PRCurve",
    "RetrievalMetrics",
    "online_database_limits",
    "revisit_mask",
    "correct_mask",
    "pr_curve",
    "evaluate_retrieval",
    "evaluate_online",
    "evaluate_cross_session",
    "apply_transform",
]


@dataclass(frozen=True)
class PRCurve:
    """Precision/recall at each distinct top-1 distance, ascending thresholds."""

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    f1: np.ndarray


@dataclass(frozen=True)
class RetrievalMetrics:
    num_queries: int
    num_revisits: int
    max_f1: float
    average_precision: float
    recall_at_100_precision: float
    recall_at_1: float
    recall_at_5: float | None
    threshold_at_max_f1: float  # accept s <= this for max F1 (inf if never correct)
    pr: PRCurve = field(repr=False)

    def summary(self) -> dict[str, Any]:
        """JSON-friendly scalars (no curve arrays)."""
        return {
            "num_queries": self.num_queries,
            "num_revisits": self.num_revisits,
            "max_f1": self.max_f1,
            "average_precision": self.average_precision,
            "recall_at_100_precision": self.recall_at_100_precision,
            "recall_at_1": self.recall_at_1,
            "recall_at_5": self.recall_at_5,
            "threshold_at_max_f1": self.threshold_at_max_f1,
        }


#: P1's default exclusion: a query matches scans recorded at least this many scans before it.
DEFAULT_EXCLUDE = 50


def online_database_limits(n: int, exclude: int = DEFAULT_EXCLUDE) -> np.ndarray:
    """P1: query i sees scans 0..i-exclude, i.e. a prefix of length max(0, i-exclude+1)."""
    if exclude < 1:
        raise ValueError("exclude must be >= 1 (a scan must not match itself)")
    return np.maximum(np.arange(n) - exclude + 1, 0)


def apply_transform(positions: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """p -> R p + t for a 4x4 (or 3x4) homogeneous transform."""
    t = np.asarray(transform, dtype=np.float64)
    if t.shape not in ((4, 4), (3, 4)):
        raise ValueError(f"transform must be 4x4 or 3x4, got {t.shape}")
    return np.asarray(positions, dtype=np.float64) @ t[:3, :3].T + t[:3, 3]


def _as_positions(p: np.ndarray, name: str) -> np.ndarray:
    arr = np.asarray(p, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be (n, 3), got {arr.shape}")
    return arr


def _limits(database_limit: np.ndarray | None, n_query: int, n_db: int) -> np.ndarray:
    if database_limit is None:
        return np.full(n_query, n_db, dtype=np.int64)
    lim = np.asarray(database_limit, dtype=np.int64)
    if lim.shape != (n_query,):
        raise ValueError(f"database_limit must have shape ({n_query},), got {lim.shape}")
    return np.clip(lim, 0, n_db)


def revisit_mask(
    query_positions: np.ndarray,
    database_positions: np.ndarray,
    radius: float,
    database_limit: np.ndarray | None = None,
) -> np.ndarray:
    """(n_query,) bool: some visible database position lies strictly within ``radius``."""
    q = _as_positions(query_positions, "query_positions")
    db = _as_positions(database_positions, "database_positions")
    lim = _limits(database_limit, len(q), len(db))
    out = np.zeros(len(q), dtype=bool)
    if len(q) == 0 or len(db) == 0:
        return out
    # All (query, db) pairs within radius in one call; filtering them by the
    # visible prefix is then a vectorised mask (no per-query Python loop).
    pairs = cKDTree(q).sparse_distance_matrix(cKDTree(db), radius, output_type="ndarray")
    ok = (pairs["v"] < radius) & (pairs["j"] < lim[pairs["i"]])
    out[pairs["i"][ok]] = True
    return out


def correct_mask(
    query_positions: np.ndarray,
    database_positions: np.ndarray,
    indices: np.ndarray,
    radius: float,
    database_limit: np.ndarray | None = None,
) -> np.ndarray:
    """(n_query, K) bool: retrieved index is visible and strictly within ``radius``."""
    q = _as_positions(query_positions, "query_positions")
    db = _as_positions(database_positions, "database_positions")
    idx = np.asarray(indices, dtype=np.int64)
    if idx.ndim != 2 or idx.shape[0] != len(q):
        raise ValueError(f"indices must be (n_query, K), got {idx.shape}")
    lim = _limits(database_limit, len(q), len(db))
    visible = (idx >= 0) & (idx < lim[:, None])
    safe = np.where(visible, idx, 0)
    if len(db) == 0:
        return np.zeros(idx.shape, dtype=bool)
    dist = np.linalg.norm(db[safe] - q[:, None, :], axis=2)
    return visible & (dist < radius)


def pr_curve(top1_distances: np.ndarray, top1_correct: np.ndarray, num_revisits: int) -> PRCurve:
    """Sweep the acceptance threshold over the distinct finite top-1 distances."""
    s = np.asarray(top1_distances, dtype=np.float64)
    c = np.asarray(top1_correct, dtype=bool)
    has = np.isfinite(s)
    s, c = s[has], c[has]
    order = np.argsort(s, kind="stable")
    s, c = s[order], c[order]
    tp = np.cumsum(c)
    fp = np.cumsum(~c)
    # Ties are accepted together: keep the last position of each distinct value.
    last = np.ones(len(s), dtype=bool)
    last[:-1] = s[1:] != s[:-1]
    thresholds, tp, fp = s[last], tp[last].astype(np.float64), fp[last].astype(np.float64)
    precision = tp / np.maximum(tp + fp, 1.0)
    if num_revisits > 0:
        recall = tp / num_revisits
    else:
        recall = np.full(len(tp), np.nan)
    denom = precision + recall
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = np.where(denom > 0, 2.0 * precision * recall / np.where(denom > 0, denom, 1.0), 0.0)
    if num_revisits == 0:
        f1 = np.full(len(tp), np.nan)
    return PRCurve(thresholds, precision, recall, f1)


def _summarise(curve: PRCurve, num_revisits: int) -> tuple[float, float, float, float]:
    """(max F1, AP, recall at 100 % precision, threshold at max F1)."""
    if num_revisits == 0:
        return math.nan, math.nan, math.nan, math.inf
    if len(curve.thresholds) == 0:
        return 0.0, 0.0, 0.0, math.inf
    best = int(np.argmax(curve.f1))
    max_f1 = float(curve.f1[best])
    threshold = float(curve.thresholds[best]) if max_f1 > 0 else math.inf
    ap = float(np.sum(np.diff(curve.recall, prepend=0.0) * curve.precision))
    perfect = curve.precision >= 1.0
    r100 = float(curve.recall[perfect].max()) if perfect.any() else 0.0
    return max_f1, ap, r100, threshold


def evaluate_retrieval(
    query_positions: np.ndarray,
    database_positions: np.ndarray,
    indices: np.ndarray,
    distances: np.ndarray,
    radius: float,
    database_limit: np.ndarray | None = None,
) -> RetrievalMetrics:
    """All metrics of the module docstring from top-K results.

    ``indices``/``distances``: (n_query, K), best first, -1 / inf padding.
    ``database_limit``: (n_query,) visible prefix length per query (None = all).
    """
    if not (math.isfinite(radius) and radius > 0):
        raise ValueError("radius must be finite and > 0")
    idx = np.atleast_2d(np.asarray(indices, dtype=np.int64))
    dist = np.atleast_2d(np.asarray(distances, dtype=np.float64))
    if idx.shape != dist.shape or idx.shape[1] < 1:
        raise ValueError(f"indices {idx.shape} and distances {dist.shape} must be equal (n, K>=1)")
    q = _as_positions(query_positions, "query_positions")
    db = _as_positions(database_positions, "database_positions")
    lim = _limits(database_limit, len(q), len(db))
    # "No candidate" is normalised once so every metric agrees on it.
    missing = (idx < 0) | ~np.isfinite(dist)
    idx = np.where(missing, -1, idx)
    dist = np.where(missing, np.inf, dist)

    has_db = lim > 0
    revisit = revisit_mask(q, db, radius, lim)
    correct = correct_mask(q, db, idx, radius, lim)
    n_rev = int(revisit.sum())
    top1 = np.where(has_db, dist[:, 0], np.inf)  # queries without a database never accept
    curve = pr_curve(top1, correct[:, 0], n_rev)
    max_f1, ap, r100, thr = _summarise(curve, n_rev)

    def recall_at(k: int) -> float:
        if n_rev == 0:
            return math.nan
        return float(correct[revisit, :k].any(axis=1).sum() / n_rev)

    return RetrievalMetrics(
        num_queries=int(has_db.sum()),
        num_revisits=n_rev,
        max_f1=max_f1,
        average_precision=ap,
        recall_at_100_precision=r100,
        recall_at_1=recall_at(1),
        recall_at_5=recall_at(5) if idx.shape[1] >= 5 else None,
        threshold_at_max_f1=thr,
        pr=curve,
    )


def evaluate_online(
    positions: np.ndarray,
    indices: np.ndarray,
    distances: np.ndarray,
    radius: float = 3.0,
    exclude: int = 50,
) -> RetrievalMetrics:
    """P1: one session, query i against scans 0..i-exclude."""
    p = _as_positions(positions, "positions")
    return evaluate_retrieval(p, p, indices, distances, radius, online_database_limits(len(p), exclude))


def evaluate_cross_session(
    query_positions: np.ndarray,
    database_positions: np.ndarray,
    indices: np.ndarray,
    distances: np.ndarray,
    radius: float = 3.0,
    query_alignment: np.ndarray | None = None,
) -> RetrievalMetrics:
    """P2: queries = session B, database = session A.

    ``query_alignment`` (4x4, T_A<-B) maps B's positions into A's frame; it is
    used for the ground truth only - the method never sees it.
    """
    q = _as_positions(query_positions, "query_positions")
    if query_alignment is not None:
        q = apply_transform(q, query_alignment)
    return evaluate_retrieval(q, database_positions, indices, distances, radius)
