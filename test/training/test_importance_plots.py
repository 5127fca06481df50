"""Figures of what a model learned: PNGs next to the model, no global backend change."""

import matplotlib
import numpy as np

from vbrl_ros.config import VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.model.model_file import VBRLModel
from vbrl_ros.training.plots import save_importance_plots
from vbrl_ros.training.report import importance_report, layer_shares

PNG = b"\x89PNG\r\n\x1a\n"


def _model(zero_modality: bool = False) -> VBRLModel:
    config = VBRLConfig(grid=VoxelGridConfig(extent_xy=20.0, cells_xy=4, z_edges=(-2.0, 0.0, 2.0, 5.0)))
    layout = Featurizer(config).layout
    rng = np.random.default_rng(0)
    W = rng.standard_normal((layout.dimension, 2))
    if zero_modality:
        W[layout.modality_slice(0)] = 0.0  # a switched-off modality must still plot
    d = layout.dimension
    return VBRLModel(config=config, W=W, feature_mean=np.zeros(d), feature_scale=np.ones(d),
                     lambda1=10.0, lambda2=0.1, scenarios=["a", "b"])


def test_three_pngs_next_to_the_model(tmp_path):
    backend = matplotlib.get_backend()
    paths = save_importance_plots(_model(), tmp_path / "town.npz")
    assert {p.name for p in paths.values()} == {"town.modalities.png", "town.voxels.png",
                                                 "town.layers.png"}
    for p in paths.values():
        assert p.read_bytes()[:8] == PNG and p.stat().st_size > 5000
    assert matplotlib.get_backend() == backend


def test_zero_shares_plot(tmp_path):
    paths = save_importance_plots(_model(zero_modality=True), tmp_path / "z.npz")
    assert all(p.is_file() for p in paths.values())


def _polar_model() -> VBRLModel:
    config = VBRLConfig(grid=VoxelGridConfig(kind="polar", rings=5, sectors=12, max_range=25.0))
    layout = Featurizer(config).layout
    W = np.zeros((layout.dimension, 2))
    # only ring 3 of the middle layer matters: column 1 * rings + 3
    W[layout.weight_layout.voxel_of_row == 1 * 5 + 3] = 1.0
    W[layout.weight_layout.voxel_of_row == 0 * 5 + 1] = 0.1
    d = layout.dimension
    return VBRLModel(config=config, W=W, feature_mean=np.zeros(d), feature_scale=np.ones(d),
                     lambda1=10.0, lambda2=0.1, scenarios=["a", "b"])


def test_polar_model_plots_ring_maps(tmp_path):
    model = _polar_model()
    paths = save_importance_plots(model, tmp_path / "polar.npz")
    for p in paths.values():
        assert p.read_bytes()[:8] == PNG and p.stat().st_size > 5000
    # the ring map is its own figure, not the Cartesian image
    cartesian = save_importance_plots(_model(), tmp_path / "cartesian.npz")
    assert paths["voxels"].read_bytes() != cartesian["voxels"].read_bytes()


def test_polar_report_lists_ring_layer_columns():
    model = _polar_model()
    text = importance_report(model, top_voxels=2)
    lines = text.splitlines()
    top = lines.index(next(line for line in lines if line.startswith("top 2 ring/layer columns")))
    assert "ring   3 r in [ 15.0,  20.0) m  middle" in lines[top + 1]
    assert "ring   1 r in [  5.0,  10.0) m  bottom" in lines[top + 2]
    assert "columns switched off by the sparsity norms: 13 of 15" in text
    np.testing.assert_allclose(layer_shares(model).sum(), 1.0)
    assert layer_shares(model)[1] > 0.9


def test_cartesian_report_still_lists_voxels():
    text = importance_report(_model())
    assert "top 5 voxels (centre x, y, z in the sensor frame):" in text
    assert "voxels switched off by the sparsity norms" in text
