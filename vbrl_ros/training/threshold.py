"""A model's recommended acceptance threshold, from its own training keyframes.

Eq. 4 distances have no universal scale (they depend on the learned weights
and the standardisation), so every model carries the distance threshold
that maximised F1 on its training keyframes; the online node uses it unless
told otherwise. Accept a candidate when ``distance <= threshold``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from vbrl_ros.evaluation.methods import scorer_top_k
from vbrl_ros.evaluation.metrics import evaluate_retrieval, pr_curve
from vbrl_ros.evaluation.protocols import protocol_pairs
from vbrl_ros.model.model_file import VBRLModel


def recommend_threshold(model: VBRLModel, descriptors: np.ndarray, labels: np.ndarray,
                        positions: np.ndarray, source_of_row: np.ndarray,
                        keyframe_index: np.ndarray, radius: float = 3.0,
                        exclude: int = 50, protocols: tuple[str, ...] = ("P1", "P2"),
                        ) -> dict[str, Any] | None:
    """Max-F1 acceptance threshold of ``model`` on its training keyframes.

    P1 within each source (the online node's situation: one growing session,
    the last ``exclude`` scans excluded), top-1 distances and correctness
    pooled over sources; if no source revisits a place, P2 between scenarios.
    ``protocols`` sets the order tried. None without poses or revisits.
    Training keyframes make it optimistic;
    it is a starting default, to be checked with ``vbrl eval`` on other data.
    """
    known = np.isfinite(positions).all(axis=1)
    if not known.any():
        return None
    rows = np.flatnonzero(known)
    d, lab, pos = descriptors[rows], np.asarray(labels)[rows], positions[rows]
    src, ki = source_of_row[rows], keyframe_index[rows]
    scorer = model.scorer()
    X = scorer.compact(model.standardize(d))
    for protocol in protocols:
        dists, correct, revisits = [], [], 0
        pairs = (protocol_pairs(np.zeros(len(rows), int), ki, src, exclude) if protocol == "P1"
                 else protocol_pairs(lab, ki, src, exclude) if len(np.unique(lab)) >= 2 else ())
        for q_rows, db_rows, limits in pairs:
            idx, dist, _ = scorer_top_k(X[q_rows], X[db_rows], scorer, 1, limits)
            m = evaluate_retrieval(pos[q_rows], pos[db_rows], idx, dist, radius, limits)
            revisits += m.num_revisits
            ok = np.isfinite(dist[:, 0])
            hit = np.zeros(len(q_rows), bool)
            j = idx[ok, 0]
            hit[ok] = np.linalg.norm(pos[db_rows][j] - pos[q_rows][ok], axis=1) < radius
            dists.append(dist[:, 0]), correct.append(hit)
        if revisits == 0:
            continue
        curve = pr_curve(np.concatenate(dists), np.concatenate(correct), revisits)
        if len(curve.f1) == 0 or np.nanmax(curve.f1) <= 0:
            continue
        best = int(np.nanargmax(curve.f1))
        return {"distance_threshold": float(curve.thresholds[best]), "protocol": protocol,
                "max_f1": float(curve.f1[best]), "precision": float(curve.precision[best]),
                "recall": float(curve.recall[best]), "revisits": int(revisits), "radius": radius}
    return None
