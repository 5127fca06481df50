"""Benchmark descriptors: the polar set from a trained (here: synthetic) polar model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vbrl_ros.bench import descriptors as bd
from vbrl_ros.config import VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.model.builtin import load_paper_model
from vbrl_ros.model.model_file import VBRLModel

POLAR = VBRLConfig(grid=VoxelGridConfig(kind="polar", rings=3, sectors=6, max_range=20.0))


def _polar_model() -> VBRLModel:
    d = Featurizer(POLAR).dimension
    rng = np.random.default_rng(0)
    return VBRLModel(config=POLAR, W=rng.normal(size=(d, 2)), feature_mean=rng.normal(size=d),
                     feature_scale=rng.uniform(0.5, 2, size=d), lambda1=1.0, lambda2=0.1,
                     scenarios=["summer_clear", "winter_snow"])


@pytest.fixture(scope="module")
def scans():
    return bd.simulated_scans(beams=16, columns=360, spacing_m=20.0)


def test_polar_set_uses_the_given_models_grid_standardisation_and_weights(scans):
    model = _polar_model()
    data = bd.polar_set(scans, seed=4, model=model)
    scorer = model.scorer()
    assert data.sectors == 6 and data.descriptors.shape == (len(scans), len(scorer.active_weights))
    np.testing.assert_array_equal(data.weights, scorer.active_weights)
    # a summer scan is described as it is; a winter one turned by the pose's extra yaw
    first = scorer.compact(model.standardize(model.featurizer().describe(scans[0][0])))
    np.testing.assert_allclose(data.descriptors[0], first, rtol=1e-6, atol=1e-6)
    winter = int(np.flatnonzero(data.session == 1)[0])
    turn = np.linalg.solve(scans[winter][1], data.poses[winter])  # T_lidar_rotated
    assert abs(math.atan2(turn[1, 0], turn[0, 0])) > 1e-6
    # pruned as the node would store it: fewer rows, the same weights on those kept
    pruned = bd.polar_set(scans[:2], seed=4, model=model, prune=0.8)  # random W: near-uniform
    kept = model.scorer(prune=0.8)
    assert len(kept.active_weights) < len(scorer.active_weights)
    np.testing.assert_array_equal(pruned.weights, kept.active_weights)


def test_polar_set_refuses_a_cartesian_model(scans):
    with pytest.raises(ValueError, match="needs a polar model"):
        bd.polar_set(scans[:2], model=load_paper_model())
