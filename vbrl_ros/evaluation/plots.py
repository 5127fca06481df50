"""PR curves of several methods and the leave-one-recording-out summary, written as PNG
without a display.

Uses matplotlib's object API with the Agg canvas directly instead of pyplot,
so importing this module never changes the global backend of the caller.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .metrics import RetrievalMetrics

__all__ = ["leave_one_out_figure", "plot_leave_one_out", "plot_pr_curves"]


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


#: The bars of each recording's panel: (row key, label); "node" is the node's verified recall.
LOO_BARS = (("max_f1", "retrieval\nmax F1"), ("recall_at_1", "retrieval\nRecall@1"),
            ("verified_max_f1", "verified\nmax F1"), ("node", "node\nrecall"))
LOO_METHODS = (("vbrl", "VBRL"), ("scan_context", "Scan Context"))


def _bar_height(result: Mapping, key: str) -> float:
    value = result["node"]["recall"] if key == "node" else result[key]
    return 0.0 if value is None or not math.isfinite(value) else float(value)


def leave_one_out_figure(rows: Sequence[Mapping], title: str | None = None) -> Figure:
    """One panel per recording of ``vbrl loo``'s rows: VBRL's and Scan Context's retrieval, verified
    and node figures side by side, the node's precision written over its recall. A recording
    without revisits shows the closures each method would publish there, all false."""
    fig = Figure(figsize=(3.2 * max(len(rows), 1), 3.6))
    FigureCanvasAgg(fig)
    width = 0.38
    x = np.arange(len(LOO_BARS))
    for k, row in enumerate(rows):
        ax = fig.add_subplot(1, max(len(rows), 1), k + 1)
        ax.set_title(str(row["recording"]), fontsize="small")
        ax.set_ylim(0.0, 1.2)
        if row["vbrl"]["revisits"] == 0:
            published = "\n".join(f"{label}: {row[name]['node']['accepted']} closures"
                                   for name, label in LOO_METHODS)
            ax.text(0.5, 0.5, f"no revisits\n{published}\n(each would be false)", ha="center", va="center",
                    transform=ax.transAxes, fontsize="small")
            ax.set_xticks([])
            ax.set_yticks([])
            continue
        for m, (name, label) in enumerate(LOO_METHODS):
            heights = [_bar_height(row[name], key) for key, _ in LOO_BARS]
            bars = ax.bar(x + (m - 0.5) * width, heights, width, label=label, color=f"C{m}")
            precision = row[name]["node"]["precision"]
            if precision is not None and math.isfinite(precision):
                node_bar = bars[len(LOO_BARS) - 1]
                ax.text(node_bar.get_x() + width / 2, node_bar.get_height() + 0.01, f"P {precision:.2f}",
                        ha="center", va="bottom", fontsize="x-small", rotation=90)
        ax.set_xticks(x, [label for _, label in LOO_BARS], fontsize="x-small")
        ax.grid(True, axis="y", alpha=0.3)
        if k == 0:
            ax.legend(loc="lower left", fontsize="x-small")
    if title:
        fig.suptitle(title, fontsize="small")
    fig.tight_layout()
    return fig


def plot_leave_one_out(rows: Sequence[Mapping], path: str | Path, title: str | None = None,
                       dpi: int = 120) -> Path:
    """:func:`leave_one_out_figure` as a PNG at ``path``; returns it."""
    out = Path(path)
    leave_one_out_figure(rows, title).savefig(out, format="png", dpi=dpi, bbox_inches="tight")
    return out
