import numpy as np
import pytest

from vbrl_ros.features import FeatureLayout
from vbrl_ros.scoring import WeightedL1Scorer, importance_weights, row_weights

LAYOUT = FeatureLayout(n_voxels=3, features_per_modality=(2, 1))  # d = 3*2 + 3*1 = 9


def test_importances_are_normalised_group_norms():
    W = np.zeros((LAYOUT.dimension, 2))
    W[LAYOUT.modality_of_row == 0] = 1.0  # 6 rows of modality 0, two columns: norm sqrt(12)
    W[(LAYOUT.modality_of_row == 1) & (LAYOUT.voxel_of_row == 2)] = [3.0, 4.0]  # norm 5
    w_modality, w_voxel = importance_weights(W, LAYOUT)
    np.testing.assert_allclose(w_modality, np.array([12**0.5, 5.0]) / (12**0.5 + 5.0))
    voxel_norms = np.array([2.0, 2.0, np.sqrt(4.0 + 25.0)])  # voxel j: 2 rows of ones (x2 cols) + ...
    np.testing.assert_allclose(w_voxel, voxel_norms / voxel_norms.sum())
    assert w_modality.sum() == pytest.approx(1) and w_voxel.sum() == pytest.approx(1)


def test_zero_W_weighs_everything_equally():
    w_modality, w_voxel = importance_weights(np.zeros((LAYOUT.dimension, 1)), LAYOUT)
    assert np.allclose(w_modality, 0.5) and np.allclose(w_voxel, 1 / 3)


def test_distance_is_eq4_and_lower_means_more_similar():
    rng = np.random.default_rng(0)
    w_modality = np.array([0.7, 0.3])
    w_voxel = np.array([0.5, 0.5, 0.0])  # voxel 2 switched off by the sparsity norm
    weights = row_weights(w_modality, w_voxel, LAYOUT)
    scorer = WeightedL1Scorer(weights)
    assert len(scorer.active_rows) == 6  # voxel 2's rows dropped
    query = rng.normal(size=LAYOUT.dimension)
    templates = rng.normal(size=(5, LAYOUT.dimension))
    templates[3] = query
    templates[4] = query
    templates[4, LAYOUT.voxel_of_row == 2] += 100.0  # differs only where weight is 0
    expected = np.array(
        [
            sum(
                w_modality[i] * w_voxel[j]
                * np.abs(query - t)[(LAYOUT.modality_of_row == i) & (LAYOUT.voxel_of_row == j)].sum()
                for i in range(2)
                for j in range(3)
            )
            for t in templates
        ]
    )
    got = scorer.distances(query, templates)
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    assert got[3] == 0 and got[4] == 0
    assert got.argmin() in (3, 4)


def test_scorer_rejects_bad_weights_and_lengths():
    with pytest.raises(ValueError):
        WeightedL1Scorer(np.array([1.0, np.nan]))
    with pytest.raises(ValueError):
        WeightedL1Scorer(np.array([1.0, -1.0]))
    with pytest.raises(ValueError, match="descriptor length"):
        WeightedL1Scorer(np.ones(4)).distances(np.ones(3), np.ones((2, 3)))
