"""What a model learned, as text: modality shares, layer shares, the most important voxels.

On a polar grid the voxel importances are tied across sectors: the report
lists (layer, ring) columns with their radius range instead of voxels.
"""

from __future__ import annotations

import numpy as np

from vbrl_ros.grids.cartesian import CartesianVoxelGrid
from vbrl_ros.model.model_file import VBRLModel

LAYER_NAMES = {3: ("bottom", "middle", "top")}


def layer_names(n_layers: int) -> tuple[str, ...]:
    return LAYER_NAMES.get(n_layers, tuple(f"layer {k}" for k in range(n_layers)))


def layer_shares(model: VBRLModel) -> np.ndarray:
    """Share of the voxel importance in each height layer (sums to 1).

    w_voxel is layer-major on both grids (voxel j // cells², or column
    ``layer * rings + ring``), so a reshape splits it by layer.
    """
    grid = model.config.grid
    return model.w_voxel.reshape(grid.n_layers, -1).sum(axis=1)


def importance_report(model: VBRLModel, top_voxels: int = 5) -> str:
    """The paper's Fig. 4 figures as a plain-text table."""
    lines = ["modality shares (paper Fig. 4a):"]
    lines += [f"  {name:<11s} {100 * share:6.2f} %" for name, share in zip(model.config.features.modalities, model.w_modality)]
    lines.append("layer shares (bottom/middle/top):")
    names = layer_names(model.config.grid.n_layers)
    edges = model.config.grid.z_edges
    lines += [
        f"  {name:<11s} {100 * share:6.2f} %   z in [{lo:g}, {hi:g}) m"
        for name, share, lo, hi in zip(names, layer_shares(model), edges, edges[1:])
    ]
    if model.config.grid.kind == "polar":
        return "\n".join(lines + _top_columns(model, top_voxels))
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


def _top_columns(model: VBRLModel, top: int) -> list[str]:
    """Polar grid: the most important (layer, ring) columns, each one weight for all sectors."""
    grid = model.config.grid
    names = layer_names(grid.n_layers)
    order = np.argsort(model.w_voxel)[::-1][:top]
    lines = [f"top {len(order)} ring/layer columns ({grid.sectors} sectors each, weights tied "
             "across sectors):"]
    for j in order:
        layer, ring = divmod(int(j), grid.rings)
        lines.append(
            f"  ring {ring:3d} r in [{ring * grid.ring_width:5.1f}, {(ring + 1) * grid.ring_width:5.1f}) m"
            f"  {names[layer]:<8s} z in [{grid.z_edges[layer]:g}, {grid.z_edges[layer + 1]:g}) m"
            f"  {100 * model.w_voxel[j]:5.2f} %"
        )
    zero = int(np.sum(model.w_voxel < 1e-6 * model.w_voxel.max()))
    lines.append(f"columns switched off by the sparsity norms: {zero} of {len(model.w_voxel)}")
    return lines
