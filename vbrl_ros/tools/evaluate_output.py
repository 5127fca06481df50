"""How ``vbrl eval`` prints its tables and writes its matches dump."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from vbrl_ros.evaluation.metrics import RetrievalMetrics
from vbrl_ros.io.atomic import atomic_write


def json_safe(value: Any) -> Any:
    """JSON has no NaN/inf: undefined metrics become null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list):
        return [json_safe(v) for v in value]
    return value


def cell(x: float | None, width: int = 7) -> str:
    return f"{'-':>{width}s}" if x is None or not math.isfinite(x) else f"{x:{width}.3f}"


def format_table(metrics: dict[str, dict[float, RetrievalMetrics]], radii: list[float]) -> str:
    lines = []
    for r in radii:
        lines.append(f"radius {r:g} m")
        lines.append(f"  {'method':<24s} {'R@1':>7s} {'R@5':>7s} {'maxF1':>7s} {'AP':>7s} "
                     f"{'R@100P':>7s} {'revisits':>9s} {'queries':>8s}")
        for name, by_radius in metrics.items():
            m = by_radius[r]
            lines.append(f"  {name:<24s} {cell(m.recall_at_1)} {cell(m.recall_at_5)} {cell(m.max_f1)} "
                         f"{cell(m.average_precision)} {cell(m.recall_at_100_precision)} "
                         f"{m.num_revisits:>9d} {m.num_queries:>8d}")
    return "\n".join(lines)


def write_matches(path: Path, entries: list[dict[str, Any]], query_scans: np.ndarray,
                  database_scans: np.ndarray) -> Path:
    """The matches dump; with --verify its fitness is NaN where no candidate was verified."""
    if not (np.array_equal(query_scans, np.arange(len(query_scans)))
            and np.array_equal(database_scans, np.arange(len(database_scans)))):
        for e in entries:  # keyframe ordinals differ from scan indices: say both
            e["query_scan"] = int(query_scans[e["query"]])
            e["match_scan"] = int(database_scans[e["match"]]) if e["match"] >= 0 else -1
    text = json.dumps(entries, indent=1)
    return atomic_write(path, lambda handle: handle.write(text.encode()))
