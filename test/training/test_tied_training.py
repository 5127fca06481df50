"""Training on a polar grid: one standardisation and one weight group per sector-tied column."""

import numpy as np
import pytest

from vbrl_ros.config import VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.training.fit import fit_model, pool_tied, row_groups, standardization
from vbrl_ros.training.streaming import RawMoments, fit_from_moments

POLAR = VBRLConfig(grid=VoxelGridConfig(kind="polar", rings=2, sectors=3, max_range=20.0,
                                        z_edges=(-2.0, 0.0, 3.0)))
LAYOUT = Featurizer(POLAR).layout


def _problem(n: int, seed: int = 0):
    """Raw descriptors whose sectors have different offsets and scales, plus constant rows."""
    rng = np.random.default_rng(seed)
    d = LAYOUT.dimension
    labels = rng.integers(0, 2, n)
    X = rng.standard_normal((n, d)) * rng.uniform(0.1, 5.0, d) + rng.uniform(-3, 30, d)
    X[:, : d // 8] += labels[:, None] * 0.7
    X[:, LAYOUT.sector_rows[:, -3:]] = 0.0  # a column empty in every sector: constant
    return X.astype(np.float32), labels


def test_tied_standardisation_pools_each_column_over_sectors():
    X, _ = _problem(50)
    mean, scale = standardization(X, LAYOUT.tie_of_row)
    rows = LAYOUT.sector_rows
    for values in (mean, scale):
        np.testing.assert_array_equal(values[rows], np.broadcast_to(values[rows[0]], rows.shape))
    # = mean and standard deviation over all scans and all sectors of the column
    pooled = X.astype(np.float64)[:, rows]  # (n, S, columns)
    np.testing.assert_allclose(mean[rows[0]], pooled.mean(axis=(0, 1)), rtol=1e-12, atol=1e-12)
    expected = pooled.std(axis=(0, 1))
    expected[expected < 1e-6] = 1.0
    np.testing.assert_allclose(scale[rows[0]], expected, rtol=1e-10)
    assert (scale[rows[:, -3:]] == 1.0).all()
    # without ties: per row, as before
    untied_mean, untied_scale = standardization(X)
    assert not np.allclose(untied_scale, scale)


def test_untied_rows_standardise_bit_identically():
    X, _ = _problem(40)
    d = X.shape[1]
    for a, b in zip(standardization(X), standardization(X, np.arange(d))):
        np.testing.assert_array_equal(a, b)
    mean, var = np.arange(5.0), np.ones(5)
    pooled_mean, pooled_var = pool_tied(mean, var, np.arange(5))
    assert pooled_mean is mean and pooled_var is var  # nothing pooled, nothing copied


def test_streamed_tied_standardisation_equals_in_memory():
    X, labels = _problem(300, seed=1)
    moments = RawMoments(X.shape[1], 2)
    for k in range(0, len(X), 64):
        moments.add(X[k:k + 64], labels[k:k + 64])
    stats, mean, scale = moments.standardized(LAYOUT.tie_of_row)
    ref_mean, ref_scale = standardization(X, LAYOUT.tie_of_row)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(scale, ref_scale, rtol=1e-7)
    Xs = (X.astype(np.float64) - ref_mean) / ref_scale
    np.testing.assert_allclose(stats.G, Xs.T @ Xs, atol=1e-7 * len(X))
    np.testing.assert_allclose(stats.B, Xs.T @ np.eye(2)[labels], atol=1e-8 * len(X))


def test_row_groups_are_the_tied_columns():
    groups = row_groups(LAYOUT)
    assert groups.n_voxels == 2 * 2 and groups.d == LAYOUT.dimension
    cartesian = Featurizer(VBRLConfig(grid=VoxelGridConfig(cells_xy=2))).layout
    np.testing.assert_array_equal(row_groups(cartesian).voxel_of_row, cartesian.voxel_of_row)


@pytest.mark.parametrize("n", [60, 550])  # Woodbury in memory (n < d = 492) and the Gram path
def test_polar_fit_gives_column_weights_equal_across_sectors(n):
    X, labels = _problem(n, seed=2)
    model = fit_model(X, labels, ["a", "b"], POLAR, lambda1=1.0, lambda2=0.1, tol=1e-7,
                      max_iter=100).model
    assert model.w_voxel.shape == (POLAR.grid.rings * POLAR.grid.n_layers,)
    rows = LAYOUT.sector_rows
    weights = model.row_weights()
    np.testing.assert_array_equal(weights[rows], np.broadcast_to(weights[rows[0]], rows.shape))
    for values in (model.feature_mean, model.feature_scale):
        np.testing.assert_array_equal(values[rows], np.broadcast_to(values[rows[0]], rows.shape))
    if n < X.shape[1]:
        return  # the streamed path solves on the Gram matrix: compare where in-memory does too
    moments = RawMoments(X.shape[1], 2)
    moments.add(X, labels)
    streamed = fit_from_moments(moments, ["a", "b"], POLAR, 1.0, 0.1, tol=1e-7,
                                max_iter=100).model
    np.testing.assert_allclose(streamed.feature_scale, model.feature_scale, rtol=1e-7)
    np.testing.assert_allclose(streamed.w_voxel, model.w_voxel, atol=1e-4)
