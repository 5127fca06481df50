"""The grid a configuration names: Cartesian (the paper's) or polar."""

from __future__ import annotations

from vbrl_ros.config import VoxelGridConfig
from vbrl_ros.grids.base import VoxelGrid
from vbrl_ros.grids.cartesian import CartesianVoxelGrid
from vbrl_ros.grids.polar import PolarVoxelGrid

GRID_CLASSES: dict[str, type] = {"cartesian": CartesianVoxelGrid, "polar": PolarVoxelGrid}


def make_grid(config: VoxelGridConfig) -> VoxelGrid:
    """The grid class ``config.kind`` names."""
    return GRID_CLASSES[config.kind](config)
