"""What Y, the regression target of Eq. 3, labels: scenarios or places.

The paper (docs/design.md §2.2): one column per *scenario* (the
session/season/weather a scan was recorded in). On the simulator's long-term
protocol that makes the sparsity norms pick the features that tell scenarios
apart — exactly what changes between sessions — and full VBRL loses to its
unregularised ablation (docs/results/baselines.md). Labelling *places* instead (keyframe positions binned
into cells) asks W for the features that tell places apart across
scenarios, which is what recognition needs.
"""

from __future__ import annotations

import numpy as np

TARGETS = ("scenarios", "places", "pairs")


def place_labels(positions: np.ndarray, cell_m: float,
                 frame_of_row: np.ndarray | None = None) -> tuple[np.ndarray, list[str]]:
    """One label per ``cell_m`` x ``cell_m`` cell of the XY positions.

    ``frame_of_row``: which world frame each position is in (e.g. its source, for recordings
    that do not share one); cells of different frames are different places. None: one frame.
    """
    if not cell_m > 0:
        raise ValueError(f"--place-size must be positive, got {cell_m}")
    positions = np.asarray(positions, dtype=np.float64)
    if len(positions) == 0 or not np.isfinite(positions[:, :2]).all():
        raise ValueError("--targets places needs a pose for every keyframe (see --poses)")
    cells = np.floor(positions[:, :2] / cell_m).astype(np.int64)
    frames = np.zeros(len(cells), np.int64) if frame_of_row is None else np.asarray(frame_of_row, np.int64)
    unique, labels = np.unique(np.column_stack([frames, cells]), axis=0, return_inverse=True)
    names = [f"place_{x}_{y}" if frame_of_row is None else f"place_{f}_{x}_{y}" for f, x, y in unique]
    return labels.ravel(), names
