"""Point -> voxel assignment on the sensor-centred Cartesian grid of the VBRL paper.

Voxel ``j`` is numbered layer-major: ``j = (layer * cells + iy) * cells + ix``,
so ``j // cells**2`` is the bottom/middle/top layer and a layer's voxels
reshape to a ``cells x cells`` image (row = y, column = x) seen from above.
"""

from __future__ import annotations

import numpy as np

from vbrl_ros.grids.base import LayeredGrid, VoxelAssignment


class CartesianVoxelGrid(LayeredGrid):
    """Vectorised assignment of points to the voxels of a :class:`VoxelGridConfig`."""

    kind = "cartesian"

    def voxel_layer(self) -> np.ndarray:
        """Layer (0 = bottom) of every voxel, shape (n_voxels,)."""
        return np.repeat(np.arange(self.config.n_layers), self.config.cells_xy**2)

    def voxel_centers(self) -> np.ndarray:
        """Centre of every voxel in the sensor frame, shape (n_voxels, 3)."""
        c = self.config.cells_xy
        xy = -self.config.extent_xy + (np.arange(c) + 0.5) * self.config.cell_size_xy
        z = 0.5 * (self._z_edges[:-1] + self._z_edges[1:])
        zz, yy, xx = np.meshgrid(z, xy, xy, indexing="ij")
        return np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)

    def assign(self, points: np.ndarray, subdivisions: int = 2) -> VoxelAssignment:
        """Assign (N, 3+) points to voxels and sub-cells; extra columns are ignored.

        ``subdivisions`` (a power of two) is the sub-cell lattice per voxel axis.
        """
        if subdivisions < 1 or subdivisions & (subdivisions - 1):
            raise ValueError(f"subdivisions must be a power of two, got {subdivisions}")
        points = np.asarray(points)
        if points.ndim != 2 or points.shape[1] < 3:
            raise ValueError(f"points must be an (N, 3) array, got shape {points.shape}")
        cfg = self.config
        cells, sub = cfg.cells_xy, subdivisions
        xyz = np.array(points[:, :3].T, dtype=np.float64, order="C")
        x, y, z = xyz
        # Positions in units of sub-cells. In z each layer's band maps affinely
        # onto [layer * sub, (layer + 1) * sub), layers may differ in height.
        scale = cells * sub / (2.0 * cfg.extent_xy)
        sx = (x + cfg.extent_xy) * scale
        sy = (y + cfg.extent_xy) * scale
        layer = np.zeros(z.shape, dtype=np.intp)
        for edge in self._z_edges[1:-1]:  # a handful of layers: cheaper than searchsorted
            layer += z >= edge
        sz = (z * self._z_slope[layer] + self._z_intercept[layer]) * sub
        # NaN fails every comparison and inf fails the bounds, so this mask
        # also removes non-finite points.
        inside = (sx >= 0) & (sx < cells * sub) & (sy >= 0) & (sy < cells * sub)
        inside &= (z >= self._z_edges[0]) & (z < self._z_edges[-1])

        # intp throughout: np.bincount converts any other index type first.
        subcell = np.empty((3, len(z)), dtype=np.intp)
        with np.errstate(invalid="ignore"):  # NaN -> int is garbage, masked below
            subcell[0], subcell[1], subcell[2] = sx, sy, sz
        # Rounding can land a point just inside the far edge on the edge itself.
        limit = [[cells * sub - 1], [cells * sub - 1], [cfg.n_layers * sub - 1]]
        np.minimum(subcell, np.array(limit, dtype=np.intp), out=subcell)
        # sub is a power of two: shift and mask instead of (slow) integer
        # division; both stay in range even for the garbage of sentinel points.
        shift = sub.bit_length() - 1
        cell = subcell >> shift
        subcell &= sub - 1
        ix, iy, _ = cell
        voxel = (layer * cells + iy) * cells + ix
        voxel[~inside] = cfg.n_voxels
        return VoxelAssignment(
            voxel=voxel, subcell=subcell, xyz=xyz, n_voxels=cfg.n_voxels, subdivisions=sub
        )
