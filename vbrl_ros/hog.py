"""Histogram of oriented gradients for a batch of small rasters, vectorised.

Follows scikit-image's ``hog`` (Dalal & Triggs) for a single-channel image
with ``cells_per_block=(1, 1)`` and ``block_norm="L2"``, so the test suite can
use scikit-image as an independent reference: central-difference gradients
(zero on the border), unsigned orientations in [0, 180) degrees split into
equal bins without interpolation, each cell's histogram the mean gradient
magnitude per bin, then each cell normalised by its L2 norm.

Unlike scikit-image this runs on a whole stack of rasters at once (one per
voxel), which is what keeps featurization free of Python loops over voxels.
"""

from __future__ import annotations

import numpy as np

#: scikit-image's block-normalisation epsilon, kept identical for the reference test.
HOG_EPS = 1e-5


def hog_batch(rasters: np.ndarray, orientations: int = 9, cells: int = 1) -> np.ndarray:
    """HOG of each raster in a (B, R, R) stack -> (B, cells * cells * orientations).

    The output of raster ``b`` is ordered (cell row, cell column, orientation),
    matching ``skimage.feature.hog(..., feature_vector=True)``. An all-constant
    (e.g. empty) raster has no gradient and gives an all-zero vector.
    """
    rasters = np.asarray(rasters, dtype=np.float64)
    if rasters.ndim != 3 or rasters.shape[1] != rasters.shape[2]:
        raise ValueError(f"rasters must be a (B, R, R) stack, got shape {rasters.shape}")
    batch, size, _ = rasters.shape
    if size % cells:
        raise ValueError(f"raster size {size} is not divisible by cells={cells}")
    pixels_per_cell = size // cells

    g_row = np.zeros_like(rasters)
    g_col = np.zeros_like(rasters)
    g_row[:, 1:-1, :] = rasters[:, 2:, :] - rasters[:, :-2, :]
    g_col[:, :, 1:-1] = rasters[:, :, 2:] - rasters[:, :, :-2]
    magnitude = np.hypot(g_row, g_col)
    orientation = np.rad2deg(np.arctan2(g_row, g_col)) % 180.0
    bin_index = np.minimum((orientation * (orientations / 180.0)).astype(np.intp), orientations - 1)

    cell_of_pixel = np.arange(size) // pixels_per_cell
    cell_index = cell_of_pixel[:, None] * cells + cell_of_pixel[None, :]  # (R, R)
    flat = (
        (np.arange(batch)[:, None, None] * (cells * cells) + cell_index[None]) * orientations
        + bin_index
    )
    hist = np.bincount(
        flat.ravel(), weights=magnitude.ravel(), minlength=batch * cells * cells * orientations
    ).reshape(batch, cells * cells, orientations)
    hist /= pixels_per_cell * pixels_per_cell
    hist /= np.sqrt(np.sum(hist * hist, axis=2, keepdims=True) + HOG_EPS**2)
    return hist.reshape(batch, cells * cells * orientations)

