"""What Y, the regression target of Eq. 3, labels: scenarios or places.

The paper (docs/design.md §2.2): one column per *scenario* (the
session/season/weather a scan was recorded in). On the simulator's long-term
protocol that makes the sparsity norms pick the features that tell scenarios
apart — exactly what changes between sessions — and full VBRL loses to its
unregularised ablation (docs/results.md). Labelling *places* instead (keyframe positions binned
into cells) asks W for the features that tell places apart across
scenarios, which is what recognition needs.
"""

from __future__ import annotations

import numpy as np

TARGETS = ("scenarios", "places")


def place_labels(positions: np.ndarray, cell_m: float) -> tuple[np.ndarray, list[str]]:
    """One label per ``cell_m`` x ``cell_m`` cell of the XY positions (all sources pooled)."""
    if not cell_m > 0:
        raise ValueError(f"--place-size must be positive, got {cell_m}")
    positions = np.asarray(positions, dtype=np.float64)
    if len(positions) == 0 or not np.isfinite(positions[:, :2]).all():
        raise ValueError("--targets places needs a pose for every keyframe (see --poses)")
    cells = np.floor(positions[:, :2] / cell_m).astype(np.int64)
    unique, labels = np.unique(cells, axis=0, return_inverse=True)
    names = [f"place_{x}_{y}" for x, y in unique]
    return labels.ravel(), names
