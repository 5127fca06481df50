"""What every voxel grid shares: the point -> voxel assignment, the z layers, the protocol.

A grid cuts height into the bands ``z_edges[k] <= z < z_edges[k+1]`` (sensor
frame, metres), one layer per band; :mod:`.cartesian` and :mod:`.polar` cut
the plane. Both satisfy :class:`VoxelGrid`; :func:`~vbrl_ros.grids.kinds.make_grid`
picks one from the configuration.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from vbrl_ros.config import VoxelGridConfig


@dataclass(frozen=True)
class VoxelAssignment:
    """Every input point with its voxel and its sub-cell inside that voxel.

    Points that are dropped (NaN/inf, or outside the grid) are *not* removed:
    they get ``voxel == n_voxels``, a sentinel bin that consumers discard.
    Compacting the arrays would cost more than computing the features
    themselves (a gather over strided memory), and ``np.bincount`` with one
    spare bin makes the sentinel free.

    ``subcell`` is each point's position inside its voxel on a
    ``subdivisions``-per-axis lattice, ``(3, N)`` intp in ``[0, subdivisions)``
    (x, y, z; 0 = the voxel's min corner); garbage but in range for sentinel
    points. ``xyz`` is the points as float64, axis-first ``(3, N)``.
    """

    voxel: np.ndarray  # (N,) intp, n_voxels = dropped
    subcell: np.ndarray  # (3, N) intp
    xyz: np.ndarray  # (3, N) float64
    n_voxels: int
    subdivisions: int

    @property
    def n_inside(self) -> int:
        return int(np.count_nonzero(self.voxel < self.n_voxels))


def layer_bands(config: VoxelGridConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(z_edges, slope, intercept): ``z * slope[layer] + intercept[layer]`` maps a layer's band
    onto [layer, layer + 1), so layers may differ in height."""
    edges = np.asarray(config.z_edges, dtype=np.float64)
    heights = np.diff(edges)
    return edges, 1.0 / heights, np.arange(config.n_layers) - edges[:-1] / heights


class LayeredGrid:
    """What every grid shares: its config (checked to be of ``kind``) and its z layer bands."""

    kind = ""

    def __init__(self, config: VoxelGridConfig) -> None:
        if config.kind != self.kind:
            raise ValueError(f"{type(self).__name__} needs a {self.kind} grid config, "
                             f"got {config.kind!r}")
        self.config = config
        self._z_edges, self._z_slope, self._z_intercept = layer_bands(config)

    @property
    def n_voxels(self) -> int:
        return self.config.n_voxels

    @property
    def z_edges(self) -> np.ndarray:
        return self._z_edges

    @property
    def z_slope(self) -> np.ndarray:
        return self._z_slope

    @property
    def z_intercept(self) -> np.ndarray:
        return self._z_intercept


class VoxelGrid(Protocol):
    """What the featurizer and the reports need of a grid, Cartesian or polar."""

    kind: str
    config: VoxelGridConfig

    @property
    def n_voxels(self) -> int: ...

    def voxel_layer(self) -> np.ndarray: ...

    def voxel_centers(self) -> np.ndarray: ...

    def assign(self, points: np.ndarray, subdivisions: int = 2) -> VoxelAssignment: ...
