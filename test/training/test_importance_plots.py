"""Figures of what a model learned: PNGs next to the model, no global backend change."""

import matplotlib
import numpy as np

from vbrl_ros.config import VBRLConfig, VoxelGridConfig
from vbrl_ros.features import Featurizer
from vbrl_ros.model import VBRLModel
from vbrl_ros.training.plots import save_importance_plots

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
