"""What a model learned, as text: modality shares, layer shares, the most important voxels."""

from __future__ import annotations

import numpy as np

from vbrl_ros.features import MODALITIES
from vbrl_ros.model import VBRLModel
from vbrl_ros.voxelization import CartesianVoxelGrid

LAYER_NAMES = {3: ("bottom", "middle", "top")}


def layer_names(n_layers: int) -> tuple[str, ...]:
    return LAYER_NAMES.get(n_layers, tuple(f"layer {k}" for k in range(n_layers)))


def layer_shares(model: VBRLModel) -> np.ndarray:
    """Share of the voxel importance in each height layer (sums to 1)."""
    grid = model.config.grid
    return model.w_voxel.reshape(grid.n_layers, -1).sum(axis=1)


def importance_report(model: VBRLModel, top_voxels: int = 5) -> str:
    """The paper's Fig. 4 figures as a plain-text table."""
    lines = ["modality shares (paper Fig. 4a):"]
    lines += [f"  {name:<11s} {100 * share:6.2f} %" for name, share in zip(MODALITIES, model.w_modality)]
    lines.append("layer shares (bottom/middle/top):")
    names = layer_names(model.config.grid.n_layers)
    edges = model.config.grid.z_edges
    lines += [
        f"  {name:<11s} {100 * share:6.2f} %   z in [{lo:g}, {hi:g}) m"
        for name, share, lo, hi in zip(names, layer_shares(model), edges, edges[1:])
    ]
    centers = CartesianVoxelGrid(model.config.grid).voxel_centers()
    order = np.argsort(model.w_voxel)[::-1][:top_voxels]
    lines.append(f"top {len(order)} voxels (centre x, y, z in the sensor frame):")
    lines += [
        f"  voxel {j:4d} ({centers[j, 0]:6.1f}, {centers[j, 1]:6.1f}, {centers[j, 2]:5.1f}) m"
        f"  {100 * model.w_voxel[j]:5.2f} %"
        for j in order
    ]
    zero = int(np.sum(model.w_voxel < 1e-6 * model.w_voxel.max()))
    lines.append(f"voxels switched off by the sparsity norms: {zero} of {len(model.w_voxel)}")
    return "\n".join(lines)
