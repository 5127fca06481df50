"""Choosing (λ1, λ2) by place-disjoint cross-validation, and a recommended acceptance threshold.

Folds are split by PLACE, not by scan: neighbouring scans of one drive are
near-duplicates, so a random split would score memorisation. The first source
with poses is the reference route; it is cut into K stretches of equal
length of new ground (travel over already visited places does not count). Every reference keyframe belongs to the stretch where its
place was FIRST visited (a loop revisiting stretch 0 in stretch 2 stays in
fold 0), every keyframe of the other sources to the fold of its nearest
reference keyframe. Training for fold f then also drops every keyframe within
``radius`` of a held-out one, so no held-out place is ever in training.

Score (the paper's Fig. 4c: performance over λ1, λ2): Recall@1 of retrieving
held-out keyframes of scenario b against held-out keyframes of scenario a
(P2-style, every ordered pair a ≠ b, positions as ground truth, radius 3 m),
pooled over folds and pairs: hits / revisit queries. Recall@1 is chosen over
max F1 because it does not depend on a threshold and is what a back-end with
geometric verification consumes; the mean max F1 is reported too and breaks
ties. With a single scenario: P1 within the held-out keyframes of each source
(query i against held-out keyframes at least ``exclude`` scans earlier).
Positions of all sources must share one world frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from tqdm import tqdm

from vbrl_ros.config import VBRLConfig
from vbrl_ros.evaluation.methods import scorer_top_k
from vbrl_ros.evaluation.metrics import evaluate_retrieval
from vbrl_ros.evaluation.protocols import protocol_pairs
from vbrl_ros.model.model_file import VBRLModel
from vbrl_ros.training.fit import fit_model

DEFAULT_LAMBDA1_GRID = (0.0, 1.0, 10.0, 100.0)
DEFAULT_LAMBDA2_GRID = (0.0, 0.01, 0.1, 1.0)


@dataclass
class CVResult:
    lambda1_grid: list[float]
    lambda2_grid: list[float]
    recall_at_1: np.ndarray  # (len λ1, len λ2), pooled over folds
    max_f1: np.ndarray  # (len λ1, len λ2), mean over folds / scenario pairs
    folds: int
    protocol: str  # "P2" (scenario pairs) or "P1" (single scenario)
    best: tuple[float, float]

    def metadata(self) -> dict[str, Any]:
        return {
            "folds": self.folds, "protocol": self.protocol, "score": "recall_at_1",
            "lambda1_grid": self.lambda1_grid, "lambda2_grid": self.lambda2_grid,
            "recall_at_1": np.round(self.recall_at_1, 4).tolist(),
            "max_f1": np.round(self.max_f1, 4).tolist(),
            "best_lambda1": self.best[0], "best_lambda2": self.best[1],
        }


def place_folds(positions: np.ndarray, source_of_row: np.ndarray, k: int,
                radius: float = 3.0) -> np.ndarray:
    """Fold (0..k-1) of every keyframe, by place; see the module docstring."""
    positions = np.asarray(positions, dtype=np.float64)
    known = np.isfinite(positions).all(axis=1)
    if not known.all():
        raise ValueError("cross-validation splits by place and needs poses for every keyframe")
    if k < 2:
        raise ValueError(f"--cv needs at least 2 folds, got {k}")
    reference = np.flatnonzero(source_of_row == source_of_row[0])
    ref_pos = positions[reference]
    steps = np.linalg.norm(np.diff(ref_pos, axis=0), axis=1)
    path = np.concatenate([[0.0], np.cumsum(steps)])
    # First visit of each place: the earliest reference keyframe within radius that was
    # left and come back to (> 2·radius of travel in between; neighbours on one pass do
    # not count).
    tree = cKDTree(ref_pos)
    pairs = tree.query_pairs(radius, output_type="ndarray")  # (i, j), i < j
    first = np.arange(len(ref_pos))
    if len(pairs):
        back = pairs[path[pairs[:, 1]] - path[pairs[:, 0]] > 2 * radius]
        np.minimum.at(first, back[:, 1], back[:, 0])
    # Stretches of equal length of NEW ground: travel over revisited places does not count,
    # else a route driven twice would put its whole second half in folds with no new place.
    travelled = np.concatenate([[0.0], np.cumsum(steps * (first[1:] == np.arange(1, len(first))))])
    stretch = np.minimum((k * travelled / max(travelled[-1], 1e-9)).astype(int), k - 1)
    ref_fold = stretch[first]
    _, nearest = tree.query(positions)
    folds = ref_fold[nearest]
    if len(np.unique(folds)) < k:
        raise ValueError(f"the route is too short for {k} place-disjoint folds; use fewer (--cv)")
    return folds


def _pooled_scores(model: VBRLModel, descriptors: np.ndarray, labels: np.ndarray,
                   positions: np.ndarray, keyframe_index: np.ndarray, source_of_row: np.ndarray,
                   radius: float, exclude: int) -> tuple[int, int, list[float]]:
    """(Recall@1 hits, revisit queries, max F1 per evaluated pair/source) of ``model`` on these rows."""
    scorer = model.scorer()
    X = scorer.compact(model.standardize(descriptors))
    hits, revisits, f1s = 0, 0, []
    for q_rows, db_rows, limits in protocol_pairs(labels, keyframe_index, source_of_row, exclude):
        idx, dist, _ = scorer_top_k(X[q_rows], X[db_rows], scorer, 1, limits)
        m = evaluate_retrieval(positions[q_rows], positions[db_rows], idx, dist, radius, limits)
        if m.num_revisits:
            hits += round(m.recall_at_1 * m.num_revisits)
            revisits += m.num_revisits
            f1s.append(m.max_f1)
    return hits, revisits, f1s


def cross_validate(
    descriptors: np.ndarray,
    labels: np.ndarray,
    scenario_names: list[str],
    positions: np.ndarray,
    source_of_row: np.ndarray,
    keyframe_index: np.ndarray,
    config: VBRLConfig,
    *,
    folds: int = 3,
    lambda1_grid: tuple[float, ...] = DEFAULT_LAMBDA1_GRID,
    lambda2_grid: tuple[float, ...] = DEFAULT_LAMBDA2_GRID,
    radius: float = 3.0,
    exclude: int = 50,
    progress: bool = True,
) -> CVResult:
    """Grid search of (λ1, λ2) by place-disjoint K-fold cross-validation."""
    labels = np.asarray(labels)
    fold_of = place_folds(positions, source_of_row, folds, radius)
    tree = cKDTree(positions)
    splits = []
    for f in range(folds):
        held = np.flatnonzero(fold_of == f)
        near = np.zeros(len(labels), dtype=bool)
        for nb in tree.query_ball_point(positions[held], radius):
            near[nb] = True  # held-out places and their surroundings stay out of training
        train = np.flatnonzero(~near & (fold_of != f))
        if len(train) < 2:
            raise ValueError(f"fold {f} leaves fewer than 2 training keyframes; use fewer folds")
        splits.append((train, held))
    protocol = "P2" if len(np.unique(labels)) >= 2 else "P1"
    recall = np.zeros((len(lambda1_grid), len(lambda2_grid)))
    f1 = np.zeros_like(recall)
    bar = tqdm(total=recall.size * folds, desc="cross-validation", unit="fit", disable=not progress)
    for a, l1 in enumerate(lambda1_grid):
        for b, l2 in enumerate(lambda2_grid):
            hits = revisits = 0
            f1s: list[float] = []
            for train, held in splits:
                model = fit_model(descriptors[train], labels[train], scenario_names, config,
                                  lambda1=l1, lambda2=l2).model
                h, r, f = _pooled_scores(model, descriptors[held], labels[held], positions[held],
                                         keyframe_index[held], source_of_row[held], radius, exclude)
                hits, revisits, f1s = hits + h, revisits + r, f1s + f
                bar.update()
            if revisits == 0:
                raise ValueError("no held-out keyframe has a revisit within the radius: "
                                 "cross-validation cannot score; use fewer folds or more data")
            recall[a, b], f1[a, b] = hits / revisits, float(np.mean(f1s))
    bar.close()
    # Best Recall@1; max F1 breaks ties; then the first (smallest λ) pair in grid order.
    order = np.lexsort((-f1.ravel(), -recall.ravel()))
    a, b = np.unravel_index(order[0], recall.shape)
    return CVResult(list(map(float, lambda1_grid)), list(map(float, lambda2_grid)), recall, f1,
                    folds, protocol, (float(lambda1_grid[a]), float(lambda2_grid[b])))


def format_cv_table(result: CVResult) -> str:
    """Recall@1 (max F1) for every (λ1, λ2); the chosen pair is starred."""
    head = "λ1 \\ λ2  " + "".join(f"{l2:>16g}" for l2 in result.lambda2_grid)
    lines = [f"cross-validation ({result.folds} place-disjoint folds, {result.protocol}): "
             "held-out Recall@1 (mean max F1)", head]
    for a, l1 in enumerate(result.lambda1_grid):
        cells = []
        for b, l2 in enumerate(result.lambda2_grid):
            star = "*" if (l1, l2) == result.best else " "
            cells.append(f"{result.recall_at_1[a, b]:7.3f} ({result.max_f1[a, b]:.3f}){star}")
        lines.append(f"{l1:<9g}" + "".join(f"{c:>16s}" for c in cells))
    lines.append(f"chosen: λ1 = {result.best[0]:g}, λ2 = {result.best[1]:g}")
    return "\n".join(lines)


def plot_cv(result: CVResult, path: str | Path, dpi: int = 120) -> Path:
    """Heat map of held-out Recall@1 over the λ grid (paper Fig. 4c), chosen pair marked."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    fig = Figure(figsize=(5.0, 4.2))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    image = ax.imshow(result.recall_at_1, origin="lower", cmap="viridis", vmin=0.0, vmax=1.0)
    for (a, b), value in np.ndenumerate(result.recall_at_1):
        ax.text(b, a, f"{value:.2f}", ha="center", va="center",
                color="black" if value > 0.6 else "white", fontsize=8)
    row, col = result.lambda1_grid.index(result.best[0]), result.lambda2_grid.index(result.best[1])
    ax.add_patch(Rectangle((col - 0.5, row - 0.5), 1, 1, fill=False, edgecolor="red", linewidth=2))
    ax.set_xticks(range(len(result.lambda2_grid)), [f"{v:g}" for v in result.lambda2_grid])
    ax.set_yticks(range(len(result.lambda1_grid)), [f"{v:g}" for v in result.lambda1_grid])
    ax.set_xlabel("λ2 (modality + row norms)")
    ax.set_ylabel("λ1 (voxel norm)")
    ax.set_title(f"held-out Recall@1, {result.folds} place-disjoint folds ({result.protocol})")
    fig.colorbar(image, ax=ax, label="Recall@1")
    out = Path(path)
    fig.savefig(out, format="png", dpi=dpi, bbox_inches="tight")
    return out
