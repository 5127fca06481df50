"""What a model learned, as figures (the paper's Fig. 4a/4b and its layer shares).

- ``MODEL.modalities.png``: share of each feature modality (pie and bar);
- ``MODEL.voxels.png``: voxel importance per height layer, seen from above,
  sensor frame with the sensor at the centre (x right, y up), one colour scale;
  on a polar grid one polar map per layer: concentric rings, since the
  importances are tied across sectors;
- ``MODEL.layers.png``: bottom / middle / top layer shares.

Uses matplotlib's object API with the Agg canvas directly (no pyplot), so the
caller's global backend is never touched.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from vbrl_ros.model.model_file import VBRLModel
from vbrl_ros.training.ablations import sibling_path
from vbrl_ros.training.report import layer_names, layer_shares

__all__ = ["plot_modalities", "plot_voxels", "plot_layers", "save_importance_plots"]


def _figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: str | Path, dpi: int) -> Path:
    out = Path(path)
    fig.savefig(out, format="png", dpi=dpi, bbox_inches="tight")
    return out


def plot_modalities(model: VBRLModel, path: str | Path, dpi: int = 120) -> Path:
    """Modality shares (paper Fig. 4a) as a pie and, for small shares, a bar chart."""
    shares = 100.0 * model.w_modality
    names = model.config.features.modalities
    fig = _figure(10.0, 4.0)
    pie, bar = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    fig.subplots_adjust(wspace=0.5)  # room for the pie's outer labels
    colors = [f"C{k}" for k in range(len(shares))]
    shown = shares > 0  # a pie cannot draw zero wedges; the bar chart still lists them
    pie.pie(shares[shown], labels=[m for m, s in zip(names, shown) if s],
            colors=[c for c, s in zip(colors, shown) if s], autopct="%1.1f%%", startangle=90)
    pie.set_title("modality shares")
    bar.bar(range(len(shares)), shares, color=colors)
    bar.set_xticks(range(len(shares)), names, rotation=30, ha="right")
    bar.set_ylabel("share of ‖W‖ (%)")
    bar.grid(True, axis="y", alpha=0.3)
    fig.suptitle(f"λ1 = {model.lambda1:g}, λ2 = {model.lambda2:g}")
    return _save(fig, path, dpi)


def plot_voxels(model: VBRLModel, path: str | Path, dpi: int = 120) -> Path:
    """Voxel importance (paper Fig. 4b): one top-down map per layer, sensor at the centre.

    Voxel j = layer·c² + iy·c + ix (see CartesianVoxelGrid.voxel_centers), so a
    reshape gives [layer, y, x]; ``origin="lower"`` puts +y up and +x right.
    """
    grid = model.config.grid
    if grid.kind == "polar":
        return _plot_rings(model, path, dpi)
    c, e = grid.cells_xy, grid.extent_xy
    maps = 100.0 * model.w_voxel.reshape(grid.n_layers, c, c)
    names = layer_names(grid.n_layers)
    fig = _figure(4.2 * grid.n_layers + 1.0, 4.2)
    axes = [fig.add_subplot(1, grid.n_layers, k + 1) for k in range(grid.n_layers)]
    vmax = max(float(maps.max()), 1e-12)  # one colour scale: layers are comparable
    for k, ax in enumerate(axes):
        image = ax.imshow(maps[k], origin="lower", extent=(-e, e, -e, e), cmap="viridis",
                          vmin=0.0, vmax=vmax, interpolation="nearest")
        ax.plot(0.0, 0.0, marker="^", color="red", markersize=9, markeredgecolor="white",
                linestyle="none", label="sensor (heading +x)")
        lo, hi = grid.z_edges[k], grid.z_edges[k + 1]
        ax.set_title(f"{names[k]}: z ∈ [{lo:g}, {hi:g}) m, {maps[k].sum():.1f} %")
        ax.set_xlabel("x (m, forward)")
        if k == 0:
            ax.set_ylabel("y (m, left)")
            ax.legend(loc="upper left", fontsize="small")
    fig.colorbar(image, ax=axes, label="voxel share (%)", shrink=0.85)
    fig.suptitle("voxel importance, seen from above (sensor frame)")
    return _save(fig, path, dpi)


def _plot_rings(model: VBRLModel, path: str | Path, dpi: int) -> Path:
    """Polar grid: per layer, the (layer, ring) column importances as annuli around the sensor.

    Column = layer * rings + ring (FeatureLayout.weight_layout), so a reshape
    gives [layer, ring]. Angle 0 is +x (forward), counter-clockwise.
    """
    grid = model.config.grid
    maps = 100.0 * model.w_voxel.reshape(grid.n_layers, grid.rings)
    names = layer_names(grid.n_layers)
    radii = np.arange(grid.rings + 1) * grid.ring_width
    theta = np.linspace(0.0, 2.0 * np.pi, max(4 * grid.sectors, 96) + 1)  # smooth circles
    fig = _figure(4.2 * grid.n_layers + 1.0, 4.4)
    axes = [fig.add_subplot(1, grid.n_layers, k + 1, projection="polar")
            for k in range(grid.n_layers)]
    vmax = max(float(maps.max()), 1e-12)  # one colour scale: layers are comparable
    for k, ax in enumerate(axes):
        values = np.repeat(maps[k][:, None], len(theta) - 1, axis=1)  # (rings, angles)
        mesh = ax.pcolormesh(theta, radii, values, cmap="viridis", vmin=0.0, vmax=vmax,
                             shading="flat")
        ax.set_xticks(np.arange(grid.sectors) * 2.0 * np.pi / grid.sectors, [])  # sector edges
        ax.set_ylim(0.0, radii[-1])
        ax.grid(True, color="white", alpha=0.4)
        lo, hi = grid.z_edges[k], grid.z_edges[k + 1]
        ax.set_title(f"{names[k]}: z ∈ [{lo:g}, {hi:g}) m, {maps[k].sum():.1f} %", pad=12)
    fig.colorbar(mesh, ax=axes, label="ring share (%), same in every sector", shrink=0.85)
    fig.suptitle(f"ring importance, seen from above ({grid.rings} rings to {grid.max_range:g} m, "
                 f"{grid.sectors} sectors, 0° = +x forward)")
    return _save(fig, path, dpi)


def plot_layers(model: VBRLModel, path: str | Path, dpi: int = 120) -> Path:
    """Share of the voxel importance in each height layer."""
    shares = 100.0 * layer_shares(model)
    names = layer_names(model.config.grid.n_layers)
    edges = model.config.grid.z_edges
    fig = _figure(5.0, 3.8)
    ax = fig.add_subplot(1, 1, 1)
    bars = ax.bar(range(len(shares)), shares, color="C0")
    ax.bar_label(bars, labels=[f"{s:.1f} %" for s in shares])
    ax.set_xticks(range(len(shares)),
                  [f"{n}\n[{lo:g}, {hi:g}) m" for n, lo, hi in zip(names, edges, edges[1:])])
    ax.set_ylabel("share of voxel importance (%)")
    ax.set_ylim(0.0, min(100.0, float(shares.max()) * 1.15) + 2.0)  # room for the labels
    ax.set_title("layer shares")
    ax.grid(True, axis="y", alpha=0.3)
    return _save(fig, path, dpi)


def save_importance_plots(model: VBRLModel, model_path: str | Path) -> dict[str, Path]:
    """The three figures next to the model: MODEL.modalities/voxels/layers.png."""
    return {
        "modalities": plot_modalities(model, sibling_path(model_path, "modalities.png")),
        "voxels": plot_voxels(model, sibling_path(model_path, "voxels.png")),
        "layers": plot_layers(model, sibling_path(model_path, "layers.png")),
    }
