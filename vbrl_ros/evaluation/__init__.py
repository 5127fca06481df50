"""Offline evaluation: protocols P1/P2 of docs/design.md section 3.

- :mod:`.metrics` - revisit ground truth, threshold sweep, F1/AP/Recall@K;
- :mod:`.retrieval` - descriptor-agnostic top-K drivers for P1 and P2;
- :mod:`.matches_json` - per-query match dump/loader for external tools;
- :mod:`.plots` - PR-curve PNG (imported on demand: it pulls in matplotlib).
"""

from .matches_json import dump_matches, evaluate_matches_file, load_matches, matches_to_json
from .metrics import (
    PRCurve,
    RetrievalMetrics,
    apply_transform,
    correct_mask,
    evaluate_cross_session,
    evaluate_online,
    evaluate_retrieval,
    online_database_limits,
    pr_curve,
    revisit_mask,
)
from .retrieval import RetrievalResults, cross_session_retrieval, online_retrieval, select_top_k

__all__ = [
    "PRCurve",
    "RetrievalMetrics",
    "RetrievalResults",
    "apply_transform",
    "correct_mask",
    "cross_session_retrieval",
    "dump_matches",
    "evaluate_cross_session",
    "evaluate_matches_file",
    "evaluate_online",
    "evaluate_retrieval",
    "load_matches",
    "matches_to_json",
    "online_database_limits",
    "online_retrieval",
    "pr_curve",
    "revisit_mask",
    "select_top_k",
]
