"""Scoring a query scan against templates with the learned importances (paper Eq. 4).

    s(x, x~) = sum_i sum_j wM(i) * wV(j) * || x_ij - x~_ij ||_1

``wM`` (per modality) and ``wV`` (per voxel) are the group norms of W —
``||W_modality(i)||_F`` and ``||W_voxel(j)||_F`` — each normalised to sum to 1;
these are also the percentages the paper reports (its Fig. 4).

**Direction: s is a distance. Lower means more similar; 0 is identical.**
Rows whose weight ``wM * wV`` is zero (voxels or modalities the sparsity
norms switched off) do not contribute, so they are dropped before scoring.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class RowLayout(Protocol):
    """Anything that says which voxel and modality each descriptor row belongs to."""

    @property
    def voxel_of_row(self) -> np.ndarray: ...

    @property
    def modality_of_row(self) -> np.ndarray: ...

    @property
    def n_voxels(self) -> int: ...

    @property
    def n_modalities(self) -> int: ...


def _normalised(norms: np.ndarray) -> np.ndarray:
    total = norms.sum()
    if not np.isfinite(total) or total <= 0:
        # W == 0 (e.g. lambda huge) says nothing: weigh everything equally
        return np.full(norms.shape, 1.0 / len(norms))
    return norms / total


def importance_weights(W: np.ndarray, layout: RowLayout) -> tuple[np.ndarray, np.ndarray]:
    """(wM, wV): modality and voxel importances from the group norms of W, each summing to 1."""
    W = np.asarray(W, dtype=np.float64)
    if W.ndim != 2 or W.shape[0] != len(layout.voxel_of_row):
        raise ValueError(
            f"W must have one row per descriptor row ({len(layout.voxel_of_row)}), "
            f"got shape {W.shape}"
        )
    row_energy = np.einsum("rc,rc->r", W, W)
    w_modality = np.sqrt(
        np.bincount(layout.modality_of_row, weights=row_energy, minlength=layout.n_modalities)
    )
    w_voxel = np.sqrt(
        np.bincount(layout.voxel_of_row, weights=row_energy, minlength=layout.n_voxels)
    )
    return _normalised(w_modality), _normalised(w_voxel)


def row_weights(w_modality: np.ndarray, w_voxel: np.ndarray, layout: RowLayout) -> np.ndarray:
    """Per-row weight wM(modality(r)) * wV(voxel(r)), shape (d,)."""
    return w_modality[layout.modality_of_row] * w_voxel[layout.voxel_of_row]


class WeightedL1Scorer:
    """Eq. 4 for one query against many templates, restricted to the rows that matter.

    ``prune`` drops rows whose weight is below ``prune`` times the largest
    weight (0 keeps every row with a non-zero weight, which is exact).
    """

    def __init__(self, weights: np.ndarray, prune: float = 0.0) -> None:
        weights = np.asarray(weights, dtype=np.float64)
        if weights.ndim != 1 or not np.all(np.isfinite(weights)) or np.any(weights < 0):
            raise ValueError("row weights must be a finite, non-negative 1-D array")
        if not 0.0 <= prune < 1.0:
            raise ValueError(f"prune must be in [0, 1), got {prune}")
        self.dimension = len(weights)
        threshold = prune * weights.max() if len(weights) else 0.0
        self.active_rows = np.flatnonzero(weights > threshold)
        self.active_weights = weights[self.active_rows].astype(np.float32)

    def compact(self, descriptors: np.ndarray) -> np.ndarray:
        """Keep only the active rows of (d,) or (N, d) descriptors (what a database stores)."""
        descriptors = np.asarray(descriptors)
        if descriptors.shape[-1] != self.dimension:
            raise ValueError(
                f"descriptor length {descriptors.shape[-1]} != model dimension {self.dimension}"
            )
        return descriptors[..., self.active_rows]

    def distances_compact(self, query: np.ndarray, templates: np.ndarray) -> np.ndarray:
        """Distances from a compacted query (k,) to compacted templates (N, k); lower = closer."""
        return np.abs(templates - query) @ self.active_weights

    def distances(self, query: np.ndarray, templates: np.ndarray) -> np.ndarray:
        """Eq. 4 distances (N,) from a full query (d,) to full templates (N, d); lower = closer."""
        templates = np.atleast_2d(templates)
        return self.distances_compact(self.compact(query), self.compact(templates))
