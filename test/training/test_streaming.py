"""The streamed Gram path gives the same standardisation and model as the in-memory path."""

import numpy as np
import pytest

from vbrl_ros.config import VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.training.fit import fit_model, standardization
from vbrl_ros.training.streaming import RawMoments, fit_from_moments

SMALL = VBRLConfig(grid=VoxelGridConfig(extent_xy=20.0, cells_xy=2, z_edges=(-2.0, 0.0, 3.0)))


def _problem(n: int, seed: int = 0):
    """Raw descriptors with offsets, different scales and constant (empty-voxel) features."""
    rng = np.random.default_rng(seed)
    d = Featurizer(SMALL).dimension
    labels = rng.integers(0, 2, n)
    X = rng.standard_normal((n, d)) * rng.uniform(0.1, 5.0, d) + rng.uniform(-3, 30, d)
    X[:, : d // 8] += labels[:, None] * 0.7  # something to learn
    X[:, -20:] = 0.0  # always-empty voxels: constant features
    return X.astype(np.float32), labels


def _stream(X, labels, chunk):
    moments = RawMoments(X.shape[1], 2)
    for k in range(0, len(X), chunk):
        moments.add(X[k:k + chunk], labels[k:k + chunk])
    return moments


@pytest.mark.parametrize("n", [120, 500])  # n < d (Woodbury in memory) and n > d (Gram both)
def test_streamed_model_matches_in_memory(n):
    X, labels = _problem(n)
    moments = _stream(X, labels, chunk=64)
    stats, mean, scale = moments.standardized()
    ref_mean, ref_scale = standardization(X)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(scale, ref_scale, rtol=1e-7)
    Xs = (X.astype(np.float64) - ref_mean) / ref_scale
    np.testing.assert_allclose(stats.G, Xs.T @ Xs, atol=1e-7 * n)
    np.testing.assert_allclose(stats.B, Xs.T @ np.eye(2)[labels], atol=1e-8 * n)
    assert stats.n == n and stats.yy == n

    memory = fit_model(X, labels, ["a", "b"], SMALL, lambda1=1.0, lambda2=0.1, tol=1e-10,
                       max_iter=500).model
    streamed = fit_from_moments(moments, ["a", "b"], SMALL, 1.0, 0.1, tol=1e-10, max_iter=500).model
    assert streamed.metadata["solver_path"] == "gram"
    np.testing.assert_allclose(streamed.W, memory.W, atol=2e-4 * np.abs(memory.W).max())
    np.testing.assert_allclose(streamed.w_modality, memory.w_modality, atol=1e-4)
    np.testing.assert_allclose(streamed.w_voxel, memory.w_voxel, atol=1e-4)


def test_chunking_does_not_matter():
    X, labels = _problem(200, seed=1)
    a = _stream(X, labels, chunk=7).standardized()
    b = _stream(X, labels, chunk=200).standardized()
    np.testing.assert_allclose(a[0].G, b[0].G, atol=1e-8)
    np.testing.assert_allclose(a[2], b[2])


def test_needs_two_scans():
    X, labels = _problem(1)
    with pytest.raises(ValueError, match="at least 2"):
        _stream(X, labels, 1).standardized()


def test_streamed_and_in_memory_training_read_the_same_trailed_keyframes(tmp_path):
    """Both training paths describe each keyframe with the config's trail, from the source's poses."""
    from dataclasses import replace

    from vbrl_ros.datasets.kitti_style import write_kitti_style
    from vbrl_ros.training.streaming import stream_moments
    from vbrl_ros.training.training_data import load_training_data

    sim = pytest.importorskip("vbrl_ros.simulator")
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=5)
    run = sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=1.0, max_scans=8)),
                           sim.LidarConfig(beams=16, columns=360), "summer_clear", seed=1)
    folder = write_kitti_style(tmp_path / "run", run.point_clouds(progress=False), run.poses, run.stamps)
    options = dict(topic=None, poses="auto", keyframe_distance=None, every=None, workers=1, progress=False)
    means = {}
    for trail in (0.0, 3.0):
        config = replace(SMALL, features=replace(SMALL.features, trail_m=trail))
        data = load_training_data([folder], config, labels=None, **options)
        moments, _ = stream_moments([folder], ["run"], config, **options)
        means[trail] = data.descriptors.astype(np.float64).mean(axis=0)
        np.testing.assert_allclose(moments.standardized()[1], means[trail], rtol=1e-6, atol=1e-9)
    assert not np.allclose(means[0.0], means[3.0])  # the trail changed what both read
