"""The VBRL feature modalities of every voxel, and the descriptor layout.

A scan's descriptor is one vector of length d. Its rows are grouped
modality-major, in the configuration's modality order (the paper's:
covariance, XY-HOG, XZ-HOG, YZ-HOG, subvoxel occupancy; ``height``, the
top of each voxel's points, see :mod:`.height_map`; ``spectrum``, see
:mod:`.bev_spectrum`); inside a modality, voxel-major.
:class:`FeatureLayout` says which voxel and modality each row belongs to —
the groups of the structured-sparsity norms and of the score.

On the polar grid (:mod:`vbrl_ros.grids.polar`) the layout also says which
rows are the same feature in different sectors (``sector_rows``), and the
weights are tied across sectors: a sparsity group and an importance wV
belong to a (layer, ring) column of voxels (``weight_layout``), so a scan
compared under a circular sector shift is weighed the same in every sector.

A grid in the ground frame (``grid.frame="ground"``) levels each scan first
(:mod:`vbrl_ros.grids.ground_frame`); :meth:`Featurizer.describe_views` describes
one levelled scan from several nearby viewpoints, for translation search.

The hot path (:meth:`Featurizer.modalities`) reads the points once in a
compiled kernel (:mod:`vbrl_ros.features.kernels`); :meth:`Featurizer.modalities_numpy`
computes the same with a handful of ``np.bincount`` calls and is the
reference the tests hold the kernel to. Neither loops over voxels in Python.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from vbrl_ros.config import HEIGHT_MAP_MODALITIES, MODALITY_NAMES, PAPER_MODALITIES, VBRLConfig
from vbrl_ros.features.blind_wedges import hide_mirrored_wedges
from vbrl_ros.features.field_of_view import field_top, tilted
from vbrl_ros.features.height_map import CELL_M
from vbrl_ros.features.height_views import HeightMapModalities, map_reach
from vbrl_ros.features.hog import hog_batch
from vbrl_ros.features.kernels import accumulate_polar_voxels, accumulate_voxels
from vbrl_ros.features.weather_clutter import drop_lone_tops
from vbrl_ros.grids.ground_frame import GroundFrame, ground_frame
from vbrl_ros.grids.kinds import make_grid

#: The paper's modalities (the default descriptor); ``MODALITY_NAMES`` adds ``height``.
MODALITIES: tuple[str, ...] = PAPER_MODALITIES
COVARIANCE_ENTRIES = 6  # xx, yy, zz, xy, xz, yz
OCCUPANCY_BITS = 8  # one per octant


@dataclass(frozen=True, eq=False)
class TiedLayout:
    """Groups of rows that share one weight: a :class:`~vbrl_ros.model.scoring.RowLayout`.

    ``voxel_of_row`` numbers weight groups (e.g. a polar grid's (layer, ring)
    columns), not voxels of the grid.
    """

    voxel_of_row: np.ndarray
    modality_of_row: np.ndarray
    n_voxels: int
    n_modalities: int


@dataclass(frozen=True)
class FeatureLayout:
    """Which voxel and which modality each descriptor row belongs to.

    ``sectors`` > 1 (polar grid): voxel ``j`` is in sector ``j % sectors`` and
    column ``j // sectors``; the Cartesian grid is one sector.
    """

    n_voxels: int
    features_per_modality: tuple[int, ...]  # per-voxel feature count of each modality
    sectors: int = 1

    def __post_init__(self) -> None:
        if self.sectors < 1 or self.n_voxels % self.sectors:
            raise ValueError(f"{self.n_voxels} voxels do not split into {self.sectors} sectors")

    @property
    def n_modalities(self) -> int:
        return len(self.features_per_modality)

    @property
    def dimension(self) -> int:
        return self.n_voxels * sum(self.features_per_modality)

    @cached_property
    def voxel_of_row(self) -> np.ndarray:
        return np.concatenate(
            [np.repeat(np.arange(self.n_voxels), k) for k in self.features_per_modality]
        )

    @cached_property
    def modality_of_row(self) -> np.ndarray:
        return np.repeat(
            np.arange(self.n_modalities),
            [self.n_voxels * k for k in self.features_per_modality],
        )

    def modality_slice(self, modality: int) -> slice:
        start = self.n_voxels * sum(self.features_per_modality[:modality])
        return slice(start, start + self.n_voxels * self.features_per_modality[modality])

    @cached_property
    def sector_rows(self) -> np.ndarray:
        """(sectors, d // sectors) int64: row ``sector_rows[s, c]`` is feature ``c`` of sector ``s``.

        For a scan rotated counter-clockwise about z by ``k`` sectors (yaw
        ``+k * 2π / sectors``), ``describe(rotated)[sector_rows[(s + k) % S]]
        == describe(scan)[sector_rows[s]]`` (HOG and occupancy exactly,
        covariances to round-off, unless rotation rounding moves a point across
        a sub-cell edge). Columns are in descriptor order
        with the sector left out: modality, then layer, then ring, then the
        modality's feature index — the same (modality, layer, ring, feature)
        in every sector. Cartesian: one row, ``arange(d)``.
        """
        sector = self.voxel_of_row % self.sectors
        # stable sort keeps each sector's rows in descriptor order: equal columns line up
        rows = np.argsort(sector, kind="stable").astype(np.int64)
        return rows.reshape(self.sectors, -1)

    @cached_property
    def tie_of_row(self) -> np.ndarray:
        """Column of ``sector_rows`` of every row (its tie class); ``arange(d)`` for Cartesian."""
        tie = np.empty(self.dimension, dtype=np.int64)
        tie[self.sector_rows] = np.arange(self.sector_rows.shape[1])
        return tie

    @cached_property
    def weight_layout(self) -> FeatureLayout | TiedLayout:
        """The groups of the sparsity norms and of wV: voxels, or (layer, ring) columns if polar.

        Voxel ids of the tied layout are ``layer * rings + ring``. Cartesian:
        this layout itself.
        """
        if self.sectors == 1:
            return self
        return TiedLayout(
            voxel_of_row=self.voxel_of_row // self.sectors,
            modality_of_row=self.modality_of_row,
            n_voxels=self.n_voxels // self.sectors,
            n_modalities=self.n_modalities,
        )


class Featurizer:
    """Turns one scan (points in the sensor frame) into a VBRL descriptor."""

    def __init__(self, config: VBRLConfig | None = None) -> None:
        self.config = config or VBRLConfig()
        self.grid = make_grid(self.config.grid)
        f = self.config.features
        per_voxel = {"covariance": COVARIANCE_ENTRIES, "hog_xy": f.hog_length, "hog_xz": f.hog_length,
                     "hog_yz": f.hog_length, "occupancy": OCCUPANCY_BITS, "height": 1, "spectrum": 1}
        assert set(per_voxel) == set(MODALITY_NAMES)
        self.layout = FeatureLayout(
            n_voxels=self.grid.n_voxels,
            features_per_modality=tuple(per_voxel[m] for m in f.modalities),
            sectors=self.config.grid.n_sectors,
        )

    @property
    def dimension(self) -> int:
        return self.layout.dimension

    @property
    def modality_names(self) -> tuple[str, ...]:
        return self.config.features.modalities

    def frame(self, points: np.ndarray, gravity: np.ndarray | None = None,
              scan: np.ndarray | None = None) -> GroundFrame:
        """The frame the grid reads ``points`` (sensor frame) in: levelled on the scan's ground
        (``gravity``: 3x3 sensor -> gravity-aligned rotation, if known) or the sensor's own.
        ``scan``: the keyframe's own points when ``points`` holds its trail as well: the sensor's
        field of view is read from them (``features.mirror_field_of_view``)."""
        if self.config.grid.frame != "ground":
            return GroundFrame.identity()
        frame = ground_frame(_as_points(points), gravity)
        if self.config.features.mirror_field_of_view and tilted(frame.rotation):  # level: nothing to mirror
            frame = replace(frame, field_top=field_top(points if scan is None else scan))
        return frame

    def describe(self, points: np.ndarray, gravity: np.ndarray | None = None,
                 scan: np.ndarray | None = None) -> np.ndarray:
        """Descriptor (d,) float32 of a scan given as (N, 3+) sensor-frame points (extra
        columns ignored); see :meth:`frame` for ``gravity`` and ``scan``."""
        points = _as_points(points)
        frame = self.frame(points, gravity, scan)
        if self._height_map_only:  # levelled inside the height map's pass
            return self.describe_views(points, np.zeros((1, 2)), frame)[0]
        return self.describe_framed(points if self.config.grid.frame == "sensor" else frame.apply(points))

    def describe_framed(self, points: np.ndarray) -> np.ndarray:
        """Descriptor of points already in the grid's frame (see :meth:`frame`)."""
        return self._vector(self.modalities(points))

    def describe_views(self, points: np.ndarray, offsets: np.ndarray,
                       frame: GroundFrame | None = None) -> np.ndarray:
        """(len(offsets), d) float32: the scan described from each of the viewpoints (x, y) in
        ``offsets`` (metres, in the grid's frame), as if the sensor had stood there.

        ``points`` are in the grid's frame, or in the sensor frame with their ``frame``
        (:meth:`frame`). Descriptors of height-map modalities read every view from one height
        map (cheap; the spectrum, which a translation does not change, is computed once);
        others re-run the featurizer on shifted points.
        """
        offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 2)
        points = _as_points(points)
        if self._height_map_only:
            if not len(offsets):
                return np.zeros((0, self.dimension), np.float32)
            cells = self._height_map.cells(points, frame)
            spectrum = self._height_map.spectrum(cells) if "spectrum" in self.modality_names else None
            return np.stack([self._vector(self._select([], top[:, None], spectrum))
                             for top in self._height_map.heights(cells, offsets)])
        if frame is not None:
            points = frame.apply(points)
        shift = np.zeros(points.shape[1])
        rows = []
        for dx, dy in offsets:
            shift[:2] = dx, dy
            rows.append(self.describe_framed(points - shift))
        return np.stack(rows) if rows else np.zeros((0, self.dimension), np.float32)

    @cached_property
    def _height_map_only(self) -> bool:
        return set(self.modality_names) <= set(HEIGHT_MAP_MODALITIES)

    @cached_property
    def _height_map(self) -> HeightMapModalities:
        return HeightMapModalities(self.config)

    def _vector(self, blocks: list[np.ndarray]) -> np.ndarray:
        parts = [b.ravel() for b in blocks]
        if self.config.features.normalise:  # each modality's block to unit L1 norm
            parts = [p / total if (total := np.abs(p).sum()) > 0 else p for p in parts]
        return np.concatenate(parts).astype(np.float32)

    def modalities(self, points: np.ndarray) -> list[np.ndarray]:
        """The configured per-voxel feature blocks, each (n_voxels, k_i), float64 (compiled
        path); ``points`` (N, 3+) in the grid's frame."""
        points = _as_points(points)
        names = self.modality_names
        cells = self._height_map.cells(points) if set(names) & set(HEIGHT_MAP_MODALITIES) else None
        heights = self._height_map.heights(cells, np.zeros((1, 2)))[0][:, None] if "height" in names else None
        spectrum = self._height_map.spectrum(cells) if "spectrum" in names else None
        if not set(names) & set(PAPER_MODALITIES):
            return self._select([], heights, spectrum)
        grid, size = self.grid, self.config.features.raster_size
        if grid.kind == "polar":
            bound_cos, bound_sin = grid.angular_bounds(size)
            accumulated = accumulate_polar_voxels(
                points, grid.config.max_range, grid.rings, grid.sectors, bound_cos, bound_sin,
                grid.centre_cos, grid.centre_sin, grid.z_edges, grid.z_slope, grid.z_intercept,
                size,
            )
        else:
            accumulated = accumulate_voxels(
                points, float(self.config.grid.extent_xy), self.config.grid.cells_xy,
                grid.z_edges, grid.z_slope, grid.z_intercept, size,
            )
        return self._select(self._finish(*accumulated), heights, spectrum)

    def _select(self, paper: list[np.ndarray], heights: np.ndarray | None,
                spectrum: np.ndarray | None = None) -> list[np.ndarray]:
        blocks = dict(zip(PAPER_MODALITIES, paper), height=heights, spectrum=spectrum)
        return [blocks[name] for name in self.modality_names]

    def modalities_numpy(self, points: np.ndarray, offset: tuple[float, float] = (0.0, 0.0)) -> list[np.ndarray]:
        """Reference implementation of :meth:`modalities` in plain numpy (same results).

        ``offset`` (x, y): the viewpoint the height map is read from, as :meth:`describe_views`
        reads it for height-map modalities; the paper's modalities describe the points moved
        by minus ``offset``.

        Grid-agnostic: the grid's assignment gives sub-cells and (for the polar
        grid, voxel-local) coordinates; everything after is the same.
        """
        points = _as_points(points)
        # the spectrum has no second implementation: it is numpy already
        spectrum = (self._height_map.spectrum(self._height_map.cells(points)) if "spectrum" in self.modality_names
                    else None)
        shift = np.array([*offset, *[0.0] * (points.shape[1] - 2)])
        return self._select(self._paper_numpy(points - shift), self._heights_numpy(points, offset), spectrum)

    def _heights_numpy(self, points: np.ndarray, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """The height block from first principles: every map column's top, its centre seen
        from ``offset`` assigned by the grid, the top of the columns per voxel."""
        cfg, edges = self.config.grid, self.grid.z_edges
        reach = map_reach(cfg)
        x, y, z = (np.asarray(points[:, k], dtype=np.float64) for k in range(3))
        ok = (np.abs(x) < reach) & (np.abs(y) < reach) & (z >= edges[0]) & (z < edges[-1])
        x, y, z = x[ok], y[ok], z[ok]
        layer = np.searchsorted(edges, z, side="right") - 1
        side = int(2.0 * reach / CELL_M) + 1
        ix, iy = ((x + reach) / CELL_M).astype(np.intp), ((y + reach) / CELL_M).astype(np.intp)
        column = (layer * side + iy) * side + ix
        top = np.full(side * side * cfg.n_layers, -1.0)
        np.maximum.at(top, column, z - edges[layer])
        if self.config.features.drop_weather_clutter:
            top = drop_lone_tops(top, _second_highest(column, z - edges[layer], len(top)), side, cfg.n_layers,
                                 CELL_M, reach)
        cells = np.flatnonzero(top >= 0)
        rest = cells % (side * side)
        centres = np.column_stack([(rest % side + 0.5) * CELL_M - reach, (rest // side + 0.5) * CELL_M - reach,
                                   edges[cells // (side * side)]])  # each column at its layer's floor
        if self.config.features.mirror_blind_wedges:
            keep = hide_mirrored_wedges(centres[:, :2])
            cells, centres = cells[keep], centres[keep]
        centres[:, :2] -= offset  # the map stays; the viewpoint moves
        voxel = self.grid.assign(centres).voxel
        v = self.grid.n_voxels
        out = np.zeros(v + 1)
        np.maximum.at(out, voxel, top[cells])
        count = np.bincount(voxel, minlength=v + 1)
        out[count < self.config.features.min_points] = 0.0
        return out[:v, None]

    def _paper_numpy(self, points: np.ndarray) -> list[np.ndarray]:
        v = self.grid.n_voxels
        size = self.config.features.raster_size
        a = self.grid.assign(points, subdivisions=size)
        px, py, pz = a.subcell
        counts = np.bincount(a.voxel, minlength=v + 1)[:v]
        base = a.voxel * size
        rasters = np.stack(
            [  # rows x columns: XY = y x x, XZ = z x x, YZ = z x y
                _histogram((base + py) * size + px, v * size * size),
                _histogram((base + pz) * size + px, v * size * size),
                _histogram((base + pz) * size + py, v * size * size),
            ]
        ).reshape(3, v, size, size)
        half = size // 2  # octant bit order: x + 2y + 4z
        octant = (px >= half) + 2 * (py >= half) + 4 * (pz >= half)
        octants = _histogram(a.voxel * OCCUPANCY_BITS + octant, v * OCCUPANCY_BITS)
        x, y, z = a.xyz

        def total(weights: np.ndarray) -> np.ndarray:
            return np.bincount(a.voxel, weights=weights, minlength=v + 1)[:v]

        moments = np.stack([total(w) for w in (x, y, z, x * x, y * y, z * z, x * y, x * z, y * z)],
                           axis=1)
        return self._finish(counts, moments, rasters, octants.reshape(v, OCCUPANCY_BITS))

    def _finish(self, counts: np.ndarray, moments: np.ndarray, rasters: np.ndarray,
                octants: np.ndarray) -> list[np.ndarray]:
        """Per-voxel accumulations -> the five feature blocks."""
        cfg = self.config.features
        v = self.grid.n_voxels
        kept = counts >= cfg.min_points  # sparser voxels count as empty
        hog = np.zeros((3, v, cfg.hog_length))
        if kept.any():  # empty voxels have no gradient: skip their rasters
            snapshots = rasters[:, kept]
            snapshots /= snapshots.max(axis=(2, 3), keepdims=True)  # density-independent
            size = cfg.raster_size
            hog[:, kept] = hog_batch(
                snapshots.reshape(-1, size, size), cfg.hog_orientations, cfg.hog_cells
            ).reshape(3, -1, cfg.hog_length)
        occupancy = (octants > 0).astype(np.float64)
        blocks = [_covariance(counts, moments), hog[0], hog[1], hog[2], occupancy]
        for block in blocks:
            block[~kept] = 0.0
        return blocks


def _as_points(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must be an (N, 3) array, got shape {points.shape}")
    if points.dtype not in (np.float32, np.float64):
        points = points.astype(np.float64)
    return points


def _second_highest(column: np.ndarray, height: np.ndarray, n_columns: int) -> np.ndarray:
    """(n_columns,) each column's next-highest ``height`` (-1: fewer than two points)."""
    order = np.lexsort((-height, column))
    column, height = column[order], height[order]
    second = np.full(n_columns, -1.0)
    has_two = column[1:] == column[:-1]
    first_of_column = np.r_[True, column[1:] != column[:-1]][:-1]
    at = first_of_column & has_two  # a column's highest, followed by its next-highest
    second[column[1:][at]] = height[1:][at]
    return second


def _histogram(index: np.ndarray, length: int) -> np.ndarray:
    """Counts of ``index`` in [0, length); larger indices (sentinel points) are dropped."""
    return np.bincount(index, minlength=length + 1)[:length].astype(np.float64)


def _covariance(counts: np.ndarray, moments: np.ndarray) -> np.ndarray:
    """Sample covariance (n - 1 normalisation, as numpy.cov) from per-voxel moment sums.

    ``moments`` holds the sums of x, y, z, xx, yy, zz, xy, xz, yz. One pass
    of sums in float64 is enough: with coordinates within ~100 m of the
    sensor, E[pp^T] - mean mean^T loses ~1e-12 m^2, far below any real spread.
    Fewer than 2 points -> zeros.
    """
    n = counts.astype(np.float64)
    sums = moments[:, :3]
    mean = sums / np.maximum(n, 1.0)[:, None]
    index = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
    cov = np.stack([moments[:, 3 + k] - sums[:, i] * mean[:, j] for k, (i, j) in enumerate(index)],
                   axis=1)
    cov /= np.maximum(n - 1.0, 1.0)[:, None]
    cov[n < 2] = 0.0
    return cov
