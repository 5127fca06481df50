"""Why the node did not publish a revisit: the verified output's misses, counted by cause.

Recall at the node's settings says how many revisits were lost, not where. Each revisit it did
not publish correctly is put down to the first of:

* ``wrong place``: it published a closure, to a keyframe outside the radius;
* ``no right candidate``: none of the candidates it verified lies within the radius (retrieval's
  miss);
* ``below min_fitness``: a right candidate passed every test of the rule but the fitness;
* ``degenerate``: a right candidate registered, but its surfaces left the position along some
  horizontal direction unfixed (a corridor, a street's side facades);
* ``too far``: a right candidate's registration ended beyond ``max_closure_distance``;
* ``other``: the rest (not converged, or ruled out by odometry before it was registered).

A right candidate is counted by its best verdict, in that order: the cause nearest to publishing.
"""

from __future__ import annotations

import numpy as np

from vbrl_ros.evaluation.metrics import correct_mask, revisit_mask
from vbrl_ros.evaluation.verified import Candidates, VerifiedCandidates

__all__ = ["MISSED_REASONS", "missed_revisits"]

MISSED_REASONS = ("wrong place", "no right candidate", "below min_fitness", "degenerate", "too far", "other")
_VERDICT_REASON = {None: "below min_fitness", "low fitness": "below min_fitness", "degenerate": "degenerate",
                   "too far": "too far"}


def missed_revisits(query_positions: np.ndarray, database_positions: np.ndarray, limits: np.ndarray | None,
                    candidates: Candidates, verified: VerifiedCandidates, published: np.ndarray,
                    radius: float, min_fitness: float) -> dict[str, int]:
    """Count by :data:`MISSED_REASONS` the revisits (a visible keyframe within ``radius``) whose
    ``published`` keyframe ((n, 1), -1: none) is not within it. Positions are the ground truth, the
    queries' in the database's frame; ``limits`` (n,): the database prefix each query saw (None: all)."""
    revisit = revisit_mask(query_positions, database_positions, radius, limits)
    right_published = correct_mask(query_positions, database_positions, published, radius, limits)[:, 0]
    right = correct_mask(query_positions, database_positions, candidates.indices, radius, limits)
    counts = dict.fromkeys(MISSED_REASONS, 0)
    for q in np.flatnonzero(revisit & ~right_published):
        if published[q, 0] >= 0:
            reason = "wrong place"
        elif not right[q].any():
            reason = "no right candidate"
        else:
            reasons = {_reason(verified.rejection[q, r], verified.fitness[q, r], min_fitness)
                       for r in np.flatnonzero(right[q])}
            reason = next(r for r in MISSED_REASONS if r in reasons)
        counts[reason] += 1
    return counts


def _reason(verdict: str | None, fitness: float, min_fitness: float) -> str:
    """The cause one right candidate's ``verdict`` (the rule's, None: passed) and ``fitness`` give."""
    if verdict is None and not fitness < min_fitness:
        return "other"  # passed, yet not published: the node's retry or distance rules
    return _VERDICT_REASON.get(verdict, "other")
