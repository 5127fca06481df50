"""Per-query matches as JSON, so any external tool can recompute the metrics.

Format: a JSON list, one object per query that had a non-empty database, in
increasing query order (indices are scan indices in source order, 0-based)::

    [{"query": 57, "match": 3, "distance": 0.21}, ...]

- ``distance``: lower = more similar (the method's own scale); the loader
  also accepts the key ``score`` (docs/design.md §4.4).
- A query whose method returned no candidate has ``"match": -1,
  "distance": null``.
- Queries without a database (P1: i < exclude) get no entry; on loading, a
  query without an entry is "no candidate" (so it still counts as a false
  negative if it is a revisit).
- Optional ``"candidates"`` / ``"candidate_distances"``: the top-K lists
  (best first, padding omitted), written with ``include_top_k=True``;
  Recall@5 needs them. On loading, K is the longest list (or ``top_k``).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from .metrics import RetrievalMetrics, evaluate_cross_session, evaluate_online
from .retrieval import RetrievalResults

__all__ = ["matches_to_json", "dump_matches", "load_matches", "evaluate_matches_file"]


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def matches_to_json(results: RetrievalResults, include_top_k: bool = False) -> list[dict[str, Any]]:
    entries: list[dict[str, Any]] = []
    for q in np.flatnonzero(results.database_limit > 0):
        j, s = int(results.indices[q, 0]), float(results.distances[q, 0])
        missing = j < 0 or not math.isfinite(s)
        entry: dict[str, Any] = {"query": int(q), "match": -1 if missing else j,
                                 "distance": None if missing else s}
        if include_top_k:
            keep = (results.indices[q] >= 0) & np.isfinite(results.distances[q])
            entry["candidates"] = [int(v) for v in results.indices[q][keep]]
            entry["candidate_distances"] = [_num(v) for v in results.distances[q][keep]]
        entries.append(entry)
    return entries


def dump_matches(path: str | Path, results: RetrievalResults, include_top_k: bool = False) -> None:
    """Write atomically (temp file + rename): a crash never leaves half a file."""
    path = Path(path)
    text = json.dumps(matches_to_json(results, include_top_k), indent=1, allow_nan=False)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_matches(path: str | Path, n_query: int, top_k: int = 1) -> RetrievalResults:
    """Read a dump back as (n_query, K) results; K = max(top_k, longest candidate list).

    ``database_limit`` is not stored in the file: it is set to 1 for queries
    with an entry and 0 otherwise (the metrics recompute visibility from the
    protocol, not from this field).
    """
    entries = json.loads(Path(path).read_text(encoding="utf-8"))
    if not isinstance(entries, list):
        raise ValueError("matches file must hold a JSON list")
    k = max([top_k] + [len(e.get("candidates", [])) for e in entries])
    indices = np.full((n_query, k), -1, dtype=np.int64)
    distances = np.full((n_query, k), np.inf)
    seen = np.zeros(n_query, dtype=bool)
    for e in entries:
        q = int(e["query"])
        if not 0 <= q < n_query:
            raise ValueError(f"query index {q} out of range [0, {n_query})")
        if seen[q]:
            raise ValueError(f"query {q} appears twice")
        seen[q] = True
        if "candidates" in e:
            cand = [int(v) for v in e["candidates"]]
            dist = [math.inf if v is None else float(v) for v in e["candidate_distances"]]
            if len(cand) != len(dist):
                raise ValueError(f"query {q}: candidates and candidate_distances differ in length")
            indices[q, : len(cand)] = cand
            distances[q, : len(dist)] = dist
        s = e.get("distance", e.get("score"))
        indices[q, 0] = int(e["match"])
        distances[q, 0] = math.inf if s is None else float(s)
    return RetrievalResults(indices, distances, seen.astype(np.int64))


def evaluate_matches_file(
    path: str | Path,
    query_positions: np.ndarray,
    radius: float = 3.0,
    database_positions: np.ndarray | None = None,
    exclude: int = 50,
    query_alignment: np.ndarray | None = None,
    top_k: int = 1,
) -> RetrievalMetrics:
    """Metrics from a dump: P1 (``exclude``) if ``database_positions`` is None, else P2."""
    q = np.asarray(query_positions, dtype=np.float64)
    res = load_matches(path, len(q), top_k)
    if database_positions is None:
        if query_alignment is not None:
            raise ValueError("query_alignment only applies to P2 (cross-session)")
        return evaluate_online(q, res.indices, res.distances, radius, exclude)
    return evaluate_cross_session(q, database_positions, res.indices, res.distances, radius, query_alignment)
