"""Typed, validated configuration of the voxel grid and the per-voxel features.

The configuration is part of every model file: a model trained with one grid
cannot score scans featurized with another, so the config round-trips through
``to_dict``/``from_dict`` and compares by value.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any


def _require(condition: bool, name: str, message: str) -> None:
    if not condition:
        raise ValueError(f"invalid {name}: {message}")


@dataclass(frozen=True)
class VoxelGridConfig:
    """The paper's grid: XY cells around the sensor x bottom/middle/top layers.

    The grid is centred on the sensor and fixed to its axes. It covers
    ``[-extent_xy, extent_xy)`` in x and y with ``cells_xy`` cells per side,
    and the height bands ``z_edges[k] <= z < z_edges[k+1]`` (sensor frame,
    metres), one layer per band. Points outside are dropped.
    """

    extent_xy: float = 40.0
    cells_xy: int = 8
    z_edges: tuple[float, ...] = (-3.0, -1.0, 1.0, 6.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "z_edges", tuple(float(z) for z in self.z_edges))
        _require(
            math.isfinite(self.extent_xy) and self.extent_xy > 0,
            "grid.extent_xy",
            f"must be a positive number of metres, got {self.extent_xy!r}",
        )
        _require(
            isinstance(self.cells_xy, int) and 1 <= self.cells_xy <= 256,
            "grid.cells_xy",
            f"must be an integer in [1, 256], got {self.cells_xy!r}",
        )
        _require(
            len(self.z_edges) >= 2,
            "grid.z_edges",
            f"needs at least two edges (one layer), got {self.z_edges!r}",
        )
        _require(
            all(math.isfinite(z) for z in self.z_edges)
            and all(b > a for a, b in zip(self.z_edges, self.z_edges[1:])),
            "grid.z_edges",
            f"must be finite and strictly increasing, got {self.z_edges!r}",
        )

    @property
    def n_layers(self) -> int:
        return len(self.z_edges) - 1

    @property
    def n_voxels(self) -> int:
        return self.cells_xy * self.cells_xy * self.n_layers

    @property
    def cell_size_xy(self) -> float:
        return 2.0 * self.extent_xy / self.cells_xy


@dataclass(frozen=True)
class FeatureConfig:
    """Per-voxel features: covariance, three HOG snapshots, subvoxel occupancy.

    Each voxel's points are rasterised on its XY, XZ and YZ faces into
    ``raster_size`` x ``raster_size`` snapshots (point counts scaled to a
    maximum of 1, so HOG does not depend on point density), and a HOG with
    ``hog_orientations`` unsigned bins over ``hog_cells`` x ``hog_cells``
    cells is taken of each. Voxels with fewer than ``min_points`` points are
    treated as empty: all their features are zero.
    """

    raster_size: int = 8
    hog_orientations: int = 9
    hog_cells: int = 1
    min_points: int = 3

    def __post_init__(self) -> None:
        _require(
            # a power of two: voxelization splits sub-cells with bit shifts,
            # and occupancy octants are raster halves
            self.raster_size in (2, 4, 8, 16, 32),
            "features.raster_size",
            f"must be one of 2, 4, 8, 16, 32, got {self.raster_size!r}",
        )
        _require(
            isinstance(self.hog_orientations, int) and 1 <= self.hog_orientations <= 36,
            "features.hog_orientations",
            f"must be an integer in [1, 36], got {self.hog_orientations!r}",
        )
        _require(
            isinstance(self.hog_cells, int)
            and self.hog_cells >= 1
            and self.raster_size % self.hog_cells == 0,
            "features.hog_cells",
            f"must be a positive divisor of raster_size={self.raster_size}, "
            f"got {self.hog_cells!r}",
        )
        _require(
            isinstance(self.min_points, int) and self.min_points >= 1,
            "features.min_points",
            f"must be an integer >= 1, got {self.min_points!r}",
        )

    @property
    def hog_length(self) -> int:
        """Length of one plane's HOG vector."""
        return self.hog_cells * self.hog_cells * self.hog_orientations


@dataclass(frozen=True)
class VBRLConfig:
    """Everything that decides what a scan's descriptor vector means."""

    grid: VoxelGridConfig = field(default_factory=VoxelGridConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["grid"]["z_edges"] = list(self.grid.z_edges)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "VBRLConfig":
        """Build from a plain dict; unknown keys are an error, not ignored."""
        if not isinstance(data, dict):
            raise ValueError(f"invalid config: expected a mapping, got {type(data).__name__}")
        unknown = set(data) - {"grid", "features"}
        if unknown:
            raise ValueError(f"invalid config: unknown section(s) {sorted(unknown)}")
        return cls(
            grid=_build(VoxelGridConfig, data.get("grid", {}), "grid"),
            features=_build(FeatureConfig, data.get("features", {}), "features"),
        )

    def differences(self, other: "VBRLConfig") -> list[str]:
        """Human-readable list of settings that differ, e.g. ``grid.cells_xy: 8 != 10``."""
        mine, theirs = self.to_dict(), other.to_dict()
        return [
            f"{section}.{key}: {mine[section][key]!r} != {theirs[section][key]!r}"
            for section in mine
            for key in mine[section]
            if mine[section][key] != theirs[section][key]
        ]


def _build(cls: type, values: Any, section: str) -> Any:
    if not isinstance(values, dict):
        raise ValueError(f"invalid config: section '{section}' must be a mapping")
    known = {f.name for f in fields(cls)}
    unknown = set(values) - known
    if unknown:
        raise ValueError(f"invalid config: unknown key(s) {sorted(f'{section}.{k}' for k in unknown)}")
    return cls(**values)
