"""A model's recommended acceptance threshold, from its own training keyframes.

The online node accepts a candidate when its Eq. 4 distance is below a
threshold. Distances have no universal scale (they depend on the learned
weights and the standardisation), so each model carries the threshold that
maximised F1 when its training keyframes of one scenario were queried
against those of every other scenario (ground truth from positions, radius
R) — the cross-session situation the threshold matters most in.
"""

from __future__ import annotations

import numpy as np

from vbrl_ros.evaluation.metrics import pr_curve
from vbrl_ros.model import VBRLModel


def recommended_threshold(
    model: VBRLModel,
    descriptors: np.ndarray,
    labels: np.ndarray,
    positions: np.ndarray,
    radius: float = 3.0,
    exclude: int = 10,
) -> float:
    """Distance threshold (accept ``distance < threshold``) at max F1 over scenario pairs.

    With a single scenario there is no pair; the scenario is then queried
    against itself without the ``exclude`` keyframes either side of the
    query, a stand-in for the online recency exclusion.
    """
    scorer = model.scorer()
    compact = scorer.compact(model.standardize(descriptors))
    labels = np.asarray(labels)
    positions = np.asarray(positions, dtype=np.float64)
    scenarios = np.unique(labels)
    top1_distance, top1_correct, revisits = [], [], 0
    for a in scenarios:
        others = [b for b in scenarios if b != a] or [a]
        for b in others:
            database = np.flatnonzero(labels == b)
            for rank, q in enumerate(np.flatnonzero(labels == a)):
                visible = np.ones(len(database), dtype=bool)
                if a == b:
                    visible[max(0, rank - exclude): rank + exclude + 1] = False
                candidates = database[visible]
                if len(candidates) == 0:
                    continue
                distances = scorer.distances_compact(compact[q], compact[candidates])
                metres = np.linalg.norm(positions[candidates] - positions[q], axis=1)
                best = int(np.argmin(distances))
                revisits += bool((metres < radius).any())
                top1_distance.append(float(distances[best]))
                top1_correct.append(bool(metres[best] < radius))
    distances = np.array(top1_distance)
    curve = pr_curve(distances, np.array(top1_correct), revisits)
    if len(curve.f1) == 0 or not np.nanmax(curve.f1) > 0:
        return float(np.median(distances)) if len(distances) else 1.0
    accepted = curve.thresholds[int(np.nanargmax(curve.f1))]
    # pr_curve thresholds mean "accept <=": put ours halfway to the next larger distance
    larger = distances[distances > accepted]
    return float((accepted + larger.min()) / 2 if len(larger) else accepted * 1.01)
