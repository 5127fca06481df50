"""Point -> voxel assignment on a polar grid: rings x sectors x height layers.

Why polar: the paper's Cartesian grid is fixed to the sensor axes, so a place
revisited with another heading gives another descriptor. Here a scan rotated
about z by exactly ``k`` sectors gives a descriptor whose sectors are a
circular shift by ``k`` of the original's, which a scorer can undo (and so
read off the yaw).

Geometry (see :class:`~vbrl_ros.config.VoxelGridConfig`): ``rings`` equal
annuli over ``[0, max_range)``, ``sectors`` equal angles over ``[0, 2π)``
starting at +x, counter-clockwise, and the config's height layers. Voxel
``j = (layer * rings + ring) * sectors + sector`` (sector fastest), so
``j // sectors`` is the voxel's (layer, ring) column.

What makes the shift exact, voxel by voxel:

- every point is expressed in its voxel's LOCAL frame, the sensor frame
  rotated by the sector's centre angle (x' radial, y' tangential, z): the
  covariance of a voxel does not change when the scan turns by whole sectors;
- the sub-cell lattice inside a voxel is (radial fraction of the ring,
  angular fraction of the sector, z fraction of the layer), so snapshots and
  octants turn with the sector.

Points on the z axis (x = y = 0) have no azimuth and are dropped with the
non-finite and out-of-range ones.

Angular bins without per-point trigonometry (``atan2`` costs ~60 ns a point,
most of the describe budget): a polynomial arctangent (error about 1e-5 rad)
guesses the bin of ``sectors * subdivisions`` equal angular bins, and exact
sign tests against the bins' boundary directions walk from the guess to the
one bin that has the point on or left of its first boundary and right of
the next. Any start reaches that bin, so the result depends only on the
sign tests: the compiled kernel
(:func:`~vbrl_ros.features.kernels.accumulate_polar_voxels`), which starts from
the previous point's bin (scans come in azimuth order), and the numpy path
below agree bit for bit. The arctangent's coefficients live in the kernel's
module, since numba's cache keys on that file: this grid imports them from there.
"""

from __future__ import annotations

import numpy as np

from vbrl_ros.config import VoxelGridConfig
from vbrl_ros.features.kernels import ATAN_COEFFICIENTS
from vbrl_ros.grids.base import LayeredGrid, VoxelAssignment

TWO_PI = 2.0 * np.pi


class PolarVoxelGrid(LayeredGrid):
    """Vectorised assignment of points to the voxels of a polar :class:`VoxelGridConfig`."""

    kind = "polar"

    def __init__(self, config: VoxelGridConfig) -> None:
        super().__init__(config)
        centres = (np.arange(config.sectors) + 0.5) * (TWO_PI / config.sectors)
        # rotating by -centre takes a point into its sector's local frame
        self.centre_cos = np.cos(centres)
        self.centre_sin = np.sin(centres)
        self._bounds: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    @property
    def rings(self) -> int:
        return self.config.rings

    @property
    def sectors(self) -> int:
        return self.config.sectors

    def angular_bounds(self, subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
        """(cos, sin) of the boundary directions of the ``sectors * subdivisions`` angular bins.

        ``bins + 1`` entries; the last repeats the first exactly (bin ``bins - 1`` ends where
        bin 0 starts), so ``b + 1`` never needs a modulo.
        """
        if subdivisions not in self._bounds:
            bins = self.config.sectors * subdivisions
            angles = np.arange(bins) * (TWO_PI / bins)
            cos, sin = np.append(np.cos(angles), 1.0), np.append(np.sin(angles), 0.0)
            cos[0], sin[0] = 1.0, 0.0
            self._bounds[subdivisions] = (cos, sin)
        return self._bounds[subdivisions]

    # -- voxel geometry (reports, plots, tests) ---------------------------------

    def voxel_layer(self) -> np.ndarray:
        """Layer (0 = bottom) of every voxel, shape (n_voxels,)."""
        return np.repeat(np.arange(self.config.n_layers), self.rings * self.sectors)

    def voxel_ring(self) -> np.ndarray:
        """Ring (0 = innermost) of every voxel, shape (n_voxels,)."""
        return np.tile(np.repeat(np.arange(self.rings), self.sectors), self.config.n_layers)

    def voxel_sector(self) -> np.ndarray:
        """Sector (0 starts at +x) of every voxel, shape (n_voxels,)."""
        return np.tile(np.arange(self.sectors), self.rings * self.config.n_layers)

    def ring_edges(self) -> np.ndarray:
        """Ring radii in metres, shape (rings + 1,)."""
        return np.arange(self.rings + 1) * self.config.ring_width

    def voxel_centers(self) -> np.ndarray:
        """Mid-radius, mid-angle, mid-height point of every voxel (sensor frame), (n_voxels, 3)."""
        radius = (self.voxel_ring() + 0.5) * self.config.ring_width
        sector = self.voxel_sector()
        z = 0.5 * (self._z_edges[:-1] + self._z_edges[1:])
        return np.stack([radius * self.centre_cos[sector], radius * self.centre_sin[sector],
                         z[self.voxel_layer()]], axis=1)

    # -- assignment -----------------------------------------------------------

    def assign(self, points: np.ndarray, subdivisions: int = 2) -> VoxelAssignment:
        """Assign (N, 3+) points to voxels; ``xyz`` and ``subcell`` are voxel-local (see module).

        ``subcell`` rows are (radial, angular, z) on a ``subdivisions``-per-axis
        lattice; ``xyz`` rows are (x', y', z), the points rotated by minus their
        sector's centre angle (garbage but finite-indexed for dropped points).
        """
        if subdivisions < 1 or subdivisions & (subdivisions - 1):
            raise ValueError(f"subdivisions must be a power of two, got {subdivisions}")
        points = np.asarray(points)
        if points.ndim != 2 or points.shape[1] < 3:
            raise ValueError(f"points must be an (N, 3) array, got shape {points.shape}")
        cfg, sub = self.config, subdivisions
        rings, sectors = cfg.rings, cfg.sectors
        xyz = np.array(points[:, :3].T, dtype=np.float64, order="C")
        x, y, z = xyz
        # The formulas and their order are the kernel's: both must round alike.
        r = np.sqrt(x * x + y * y)
        sr = r * (rings * sub / cfg.max_range)
        layer = np.zeros(z.shape, dtype=np.intp)
        for edge in self._z_edges[1:-1]:
            layer += z >= edge
        sz = (z * self._z_slope[layer] + self._z_intercept[layer]) * sub
        # NaN fails every comparison and inf fails the bounds: non-finite points drop out.
        inside = (r > 0) & (sr < rings * sub) & (z >= self._z_edges[0]) & (z < self._z_edges[-1])

        subcell = np.empty((3, len(z)), dtype=np.intp)
        with np.errstate(invalid="ignore"):  # NaN -> int is garbage, masked below
            subcell[0], subcell[2] = sr, sz
        subcell[1] = self._angular_bins(x, y, inside, sub)
        limit = [[rings * sub - 1], [sectors * sub - 1], [cfg.n_layers * sub - 1]]
        np.minimum(subcell, np.array(limit, dtype=np.intp), out=subcell)
        shift = sub.bit_length() - 1
        cell = subcell >> shift
        subcell &= sub - 1
        ring, sector, _ = cell
        voxel = (layer * rings + ring) * sectors + sector
        voxel[~inside] = cfg.n_voxels
        # angular bins are in range for every point, so the table lookup is safe
        c, s = self.centre_cos[sector], self.centre_sin[sector]
        local = np.empty_like(xyz)
        local[0] = x * c + y * s
        local[1] = y * c - x * s
        local[2] = z
        return VoxelAssignment(
            voxel=voxel, subcell=subcell, xyz=local, n_voxels=cfg.n_voxels, subdivisions=sub
        )

    def _angular_bins(self, x: np.ndarray, y: np.ndarray, inside: np.ndarray,
                      sub: int) -> np.ndarray:
        """Bin in [0, sectors * sub) of each point's azimuth (0 for dropped points)."""
        bins = self.config.sectors * sub
        with np.errstate(invalid="ignore", divide="ignore"):
            guess = approximate_azimuth(x, y) * (bins / TWO_PI)
            guess[~inside] = 0.0
            b = np.minimum(guess.astype(np.intp), bins - 1)  # the azimuth == 2π rounding edge
        cos, sin = self.angular_bounds(sub)
        rows = np.flatnonzero(inside)
        px, py, pb = x[rows], y[rows], b[rows]
        # A point is in bin b when it is on or left of boundary b and right of boundary b+1.
        # The guess is off by at most one bin; the loops are bounded all the same.
        for _ in range(bins):
            back = cos[pb] * py - sin[pb] * px < 0
            if not back.any():
                break
            pb[back] = np.where(pb[back] == 0, bins - 1, pb[back] - 1)
        for _ in range(bins):
            ahead = cos[pb + 1] * py - sin[pb + 1] * px >= 0
            if not ahead.any():
                break
            pb[ahead] = np.where(pb[ahead] == bins - 1, 0, pb[ahead] + 1)
        b[rows] = pb
        return b


def approximate_azimuth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Azimuth in [0, 2π] within 1.2e-5 rad, no trigonometry (NaN where x = y = 0).

    The same operations as the kernel's ``_approximate_azimuth``.
    """
    ax, ay = np.abs(x), np.abs(y)
    t = np.minimum(ax, ay) / np.maximum(ax, ay)
    t2 = t * t
    c1, c3, c5, c7, c9 = ATAN_COEFFICIENTS
    a = t * (c1 + t2 * (c3 + t2 * (c5 + t2 * (c7 + t2 * c9))))
    a = np.where(ay > ax, 0.5 * np.pi - a, a)
    a = np.where(x < 0, np.pi - a, a)
    return np.where(y < 0, TWO_PI - a, a)
