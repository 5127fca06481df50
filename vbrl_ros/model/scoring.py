"""Scoring a query scan against templates with the learned importances (paper Eq. 4).

    s(x, x~) = sum_i sum_j wM(i) * wV(j) * || x_ij - x~_ij ||_1

``wM`` (per modality) and ``wV`` (per voxel) are the group norms of W —
``||W_modality(i)||_F`` and ``||W_voxel(j)||_F`` — each normalised to sum to 1;
these are also the percentages the paper reports (its Fig. 4).

**Direction: s is a distance. Lower means more similar; 0 is identical.**
Rows whose weight ``wM * wV`` is zero (voxels or modalities the sparsity
norms switched off) do not contribute, so they are dropped before scoring.

On a polar grid (``sector_rows``, weights tied across sectors) the distance is
minimised over circular sector shifts and comes with the yaw of the best
shift (:mod:`vbrl_ros.model.sector_shift`): heading-robust recognition.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from vbrl_ros.model.distance_kernels import at_shifts, min_over_shifts
from vbrl_ros.model.sector_shift import refined_yaw, yaw_of_shift


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

    ``sector_rows`` (S, R) int64 (a polar grid's
    :attr:`~vbrl_ros.features.featurizer.FeatureLayout.sector_rows`): row ``sector_rows[s, r]``
    is column r of sector s, and weights must be equal across sectors in a
    column (tied). A column is kept or pruned in every sector at once, and
    ``active_rows = sector_rows[:, active_columns].ravel()``, so a compact
    descriptor is sector-major: ``compact(x).reshape(S, R_active)``. Distances
    are then minimised over circular sector shifts (see
    :mod:`vbrl_ros.model.sector_shift` for the yaw that comes with them). Without
    ``sector_rows``: S = 1, ``active_rows`` ascending.
    """

    def __init__(self, weights: np.ndarray, prune: float = 0.0,
                 sector_rows: np.ndarray | None = None) -> None:
        weights = np.asarray(weights, dtype=np.float64)
        if weights.ndim != 1 or not np.all(np.isfinite(weights)) or np.any(weights < 0):
            raise ValueError("row weights must be a finite, non-negative 1-D array")
        if not 0.0 <= prune < 1.0:
            raise ValueError(f"prune must be in [0, 1), got {prune}")
        self.dimension = len(weights)
        threshold = prune * weights.max() if len(weights) else 0.0
        if sector_rows is None:
            self.sectors = 1
            self.active_rows = np.flatnonzero(weights > threshold)
        else:
            rows = _check_sector_rows(sector_rows, weights)
            self.sectors = rows.shape[0]
            active_columns = np.flatnonzero(weights[rows[0]] > threshold)
            self.active_rows = rows[:, active_columns].ravel()
        self.sector_angle = 2.0 * math.pi / self.sectors
        self.active_weights = weights[self.active_rows].astype(np.float32)
        # one weight per active column (the tied weights of sector 0)
        self.column_weights = np.ascontiguousarray(
            self.active_weights[: len(self.active_rows) // self.sectors])

    def compact(self, descriptors: np.ndarray) -> np.ndarray:
        """Keep only the active rows of (d,) or (N, d) descriptors (what a database stores)."""
        descriptors = np.asarray(descriptors)
        if descriptors.shape[-1] != self.dimension:
            raise ValueError(
                f"descriptor length {descriptors.shape[-1]} != model dimension {self.dimension}"
            )
        return descriptors[..., self.active_rows]

    def distances_compact(self, query: np.ndarray, templates: np.ndarray) -> np.ndarray:
        """Distances from a compacted query (k,) to compacted templates (N, k); lower = closer.

        S > 1: ``min_k sum_s sum_r w_r |q[(s + k) % S, r] - t[s, r]|`` (float32 sums).
        """
        if self.sectors == 1:
            return np.abs(templates - query) @ self.active_weights
        return self.distances_and_yaws_compact(query, templates)[0]

    def distances_and_yaws_compact(
        self, query: np.ndarray, templates: np.ndarray, refine: bool = False
    ) -> tuple[np.ndarray, np.ndarray]:
        """(distances (N,), yaws (N,) radians in (-pi, pi]) from a compacted query.

        The yaw is the best shift k times ``sector_angle``: the query scan is the
        template scan rotated by +yaw about z (T_query_match has this yaw); 0 for
        S = 1. ``refine`` moves it to the vertex of the parabola through the
        distances at k - 1, k, k + 1 (at most half a sector; needs S >= 3).
        """
        q = np.ascontiguousarray(query, dtype=np.float32)
        t = np.ascontiguousarray(np.atleast_2d(templates), dtype=np.float32)
        if q.shape != (len(self.active_rows),) or t.shape[1:] != q.shape:
            raise ValueError(f"compact shapes {q.shape} and {t.shape} do not match "
                             f"{len(self.active_rows)} active rows")
        rows = np.arange(len(t), dtype=np.int64)
        distances = np.empty(len(t), np.float32)
        shifts = np.empty(len(t), np.int64)
        min_over_shifts(t, rows, q, self.column_weights, self.sectors, distances, shifts)
        if not refine or self.sectors < 3:
            return distances, yaw_of_shift(shifts, self.sectors)
        around = np.stack([(shifts - 1) % self.sectors, (shifts + 1) % self.sectors], axis=1)
        side = np.empty(around.shape, np.float32)
        at_shifts(t, rows, around, q, self.column_weights, self.sectors, side)
        return distances, refined_yaw(shifts, side[:, 0], distances, side[:, 1], self.sectors)

    def distances(self, query: np.ndarray, templates: np.ndarray) -> np.ndarray:
        """Eq. 4 distances (N,) from a full query (d,) to full templates (N, d); lower = closer."""
        templates = np.atleast_2d(templates)
        return self.distances_compact(self.compact(query), self.compact(templates))


def _check_sector_rows(sector_rows: np.ndarray, weights: np.ndarray) -> np.ndarray:
    rows = np.asarray(sector_rows)
    if rows.ndim != 2 or rows.dtype.kind not in "iu" or rows.size != len(weights) or not (
        np.array_equal(np.sort(rows.ravel()), np.arange(len(weights)))
    ):
        raise ValueError(
            f"sector_rows must be an (S, d // S) integer array holding every one of the "
            f"{len(weights)} rows once, got {rows.dtype} {rows.shape}"
        )
    tied = weights[rows]
    if np.any(tied != tied[0]):
        column = int(np.flatnonzero(np.any(tied != tied[0], axis=0))[0])
        raise ValueError(f"weights of column {column} differ across sectors (must be tied)")
    return rows.astype(np.int64)
