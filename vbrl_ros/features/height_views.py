"""The height-map modalities of one scan, seen from one viewpoint or several.

:class:`HeightMapModalities` is what the featurizer reads from the height map of
:mod:`.height_map`: the map itself (with mirrored blind wedges hidden), the height block
from every viewpoint of translation search and the spectrum block, which a translation
does not change.

Binning an occupied map column into its voxel from a viewpoint (a square root and an
angular bin) was most of the time of describing a scan from translation search's 11
viewpoints. That voxel depends only on the column and the viewpoint, not on the scan, so
:func:`view_table` bins every column of the map once per grid and set of viewpoints (tens
of milliseconds; int16, ~4 MB for 11 views of the built-in grid) and each scan reads its
columns' voxels from the table: the voxels the per-column kernels give, so the same heights.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from numba import njit

from vbrl_ros.config import VBRLConfig, VoxelGridConfig
from vbrl_ros.features.bev_spectrum import SpectrumSampler
from vbrl_ros.features.blind_wedges import azimuth_bins, hide_mirrored_wedges
from vbrl_ros.features.field_of_view import half_turn_in_sensor, mirrored_top, mirrors
from vbrl_ros.features.height_map import (
    CELL_M,
    MARGIN_M,
    cartesian_column_voxels,
    column_centres,
    height_cells,
    map_side,
    polar_column_voxels,
)
from vbrl_ros.grids.ground_frame import GroundFrame
from vbrl_ros.grids.kinds import make_grid

#: Tables kept for reuse: a node or an evaluation uses one (grid, viewpoints) pair, tests a few.
CACHED_TABLES = 4


@dataclass(frozen=True)
class HeightCells:
    """The occupied columns of a scan's height map, one row each (see :func:`height_cells`)."""

    xy: np.ndarray  # (n, 2) column centre, metres
    height: np.ndarray  # (n,) top above the layer's floor
    layer: np.ndarray  # (n,) int64
    column: np.ndarray  # (n,) int64 column of the map, iy * side + ix

    def subset(self, keep: np.ndarray) -> HeightCells:
        return HeightCells(self.xy[keep], self.height[keep], self.layer[keep], self.column[keep])


def map_reach(grid: VoxelGridConfig) -> float:
    """How far the height map reaches in x and y: the grid's reach plus room for viewpoints."""
    return (grid.max_range if grid.kind == "polar" else grid.extent_xy) + MARGIN_M


@lru_cache(maxsize=CACHED_TABLES)
def view_table(grid: VoxelGridConfig, offsets: tuple[tuple[float, float], ...]) -> np.ndarray:
    """(columns, len(offsets)) the voxel within a layer of every map column from every
    viewpoint (x, y), -1 outside the grid; int16 when the layer's voxels fit."""
    reach = map_reach(grid)
    side = map_side(reach, CELL_M)
    centres = column_centres(side, CELL_M, reach)
    per_layer = grid.n_voxels // grid.n_layers
    table = np.empty((side * side, len(offsets)), np.int16 if per_layer < 2**15 else np.int32)
    if grid.kind == "polar":
        bound_cos, bound_sin = make_grid(grid).angular_bounds(1)
        for v, (dx, dy) in enumerate(offsets):
            table[:, v] = polar_column_voxels(centres, dx, dy, grid.max_range, grid.rings, grid.sectors,
                                              bound_cos, bound_sin)
    else:
        for v, (dx, dy) in enumerate(offsets):
            table[:, v] = cartesian_column_voxels(centres, dx, dy, grid.extent_xy, grid.cells_xy)
    table.flags.writeable = False  # shared by every featurizer of this grid
    return table


@lru_cache(maxsize=CACHED_TABLES)
def column_azimuth_bins(reach: float) -> np.ndarray:
    """(columns,) the azimuth bin of every map column's centre (:func:`azimuth_bins`, once
    per map instead of an arctangent per occupied column and scan)."""
    bins = azimuth_bins(column_centres(map_side(reach, CELL_M), CELL_M, reach)).astype(np.int16)
    bins.flags.writeable = False
    return bins


@njit(cache=True, nogil=True)
def view_tops(table, column, height, layer, per_layer, layers):
    """(views, voxels) top height of every voxel from every viewpoint of ``table``, and its
    count of map columns."""
    views = table.shape[1]
    top = np.zeros((views, layers * per_layer))
    count = np.zeros((views, layers * per_layer), np.int64)
    for k in range(column.shape[0]):
        row = table[column[k]]
        base = layer[k] * per_layer
        h = height[k]
        for v in range(views):
            j = row[v]
            if j >= 0:
                j += base
                count[v, j] += 1
                if h > top[v, j]:
                    top[v, j] = h
    return top, count


class HeightMapModalities:
    """The height map of a scan and the height and spectrum blocks read from it."""

    def __init__(self, config: VBRLConfig) -> None:
        self.config = config
        self.reach = map_reach(config.grid)
        self.z_edges = np.asarray(config.grid.z_edges, dtype=np.float64)

    def cells(self, points: np.ndarray, frame: GroundFrame | None = None) -> HeightCells:
        """The height map of (N, 3+) points, taken into ``frame`` (default: already in it)."""
        frame = frame or GroundFrame.identity()
        half_turn, top_tan = np.eye(3), np.inf
        if self.config.features.mirror_field_of_view and mirrors(frame.rotation, frame.field_top):
            half_turn = half_turn_in_sensor(frame.rotation)
            top_tan = math.tan(mirrored_top(frame.rotation, frame.field_top))
        cells = HeightCells(*height_cells(points, frame.rotation, float(frame.height), self.reach, CELL_M,
                                          self.z_edges, self.config.features.drop_weather_clutter,
                                          half_turn, top_tan))
        if self.config.features.mirror_blind_wedges:
            keep = hide_mirrored_wedges(cells.xy, column_azimuth_bins(self.reach)[cells.column])
            if not keep.all():  # most scans see all round: nothing to copy
                cells = cells.subset(keep)
        return cells

    def heights(self, cells: HeightCells, offsets: np.ndarray) -> np.ndarray:
        """(len(offsets), n_voxels) the height block seen from each viewpoint (x, y); voxels
        with fewer than ``min_points`` map cells are empty."""
        grid = self.config.grid
        key = tuple((float(dx), float(dy)) for dx, dy in np.asarray(offsets, dtype=np.float64).reshape(-1, 2))
        top, count = view_tops(view_table(grid, key), cells.column, cells.height, cells.layer,
                               grid.n_voxels // grid.n_layers, grid.n_layers)
        top[count < self.config.features.min_points] = 0.0
        return top

    def spectrum(self, cells: HeightCells) -> np.ndarray:
        """The spectrum block (n_voxels, 1): one spectrum of each layer's bird's-eye image."""
        sampler = self._spectrum_sampler
        return np.concatenate([sampler.spectrum(sampler.image(cells.xy[cells.layer == layer],
                                                              cells.height[cells.layer == layer]))
                               for layer in range(self.config.grid.n_layers)])[:, None]

    @cached_property
    def _spectrum_sampler(self) -> SpectrumSampler:
        return SpectrumSampler(self.config.grid.rings, self.config.grid.sectors)
