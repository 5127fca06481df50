"""PR-curve figure for several methods, written as PNG without a display.

Uses matplotlib's object API with the Agg canvas directly instead of pyplot,
so importing this module never changes the global backend of the caller.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .metrics import RetrievalMetrics

__all__ = ["plot_pr_curves"]


def plot_pr_curves(
    methods: Mapping[str, RetrievalMetrics],
    path: str | Path,
    title: str | None = None,
    dpi: int = 120,
) -> Path:
    """One PR curve per method (legend: max F1 and AP); returns the PNG path."""
    fig = Figure(figsize=(5.5, 4.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for name, m in methods.items():
        # Start at recall 0 with the first precision so the step reads from the axis.
        recall = np.concatenate([[0.0], m.pr.recall])
        precision = np.concatenate([m.pr.precision[:1] if len(m.pr.precision) else [1.0], m.pr.precision])
        label = f"{name} (max F1 {m.max_f1:.3f}, AP {m.average_precision:.3f})"
        ax.step(recall, precision, where="post", label=label)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.02)
    ax.grid(True, alpha=0.3)
    if title:
        ax.set_title(title)
    if methods:
        ax.legend(loc="best", fontsize="small")
    out = Path(path)
    fig.savefig(out, format="png", dpi=dpi, bbox_inches="tight")
    return out
