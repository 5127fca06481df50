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


GRID_KINDS: tuple[str, ...] = ("cartesian", "polar")
#: "sensor": the grid is fixed to the sensor (the paper); "ground": each scan is first
#: levelled on its own ground and heights are measured from it (grids/ground_frame.py).
FRAMES: tuple[str, ...] = ("sensor", "ground")
#: The paper's five modalities, in descriptor order.
PAPER_MODALITIES: tuple[str, ...] = ("covariance", "hog_xy", "hog_xz", "hog_yz", "occupancy")
#: Modalities read from the scan's height map: "height", the highest point above the voxel's
#: floor, and "spectrum", the bird's-eye height image's Fourier magnitude (polar grids only).
HEIGHT_MAP_MODALITIES: tuple[str, ...] = ("height", "spectrum")
#: Every modality a descriptor may hold.
MODALITY_NAMES: tuple[str, ...] = (*PAPER_MODALITIES, *HEIGHT_MAP_MODALITIES)
#: The longest trail (features.trail_m) a keyframe is described with: odometry over more drifts.
MAX_TRAIL_M = 20.0
#: The longest trail a forward-looking keyframe is described with (features.forward_trail_m):
#: lidar-inertial odometry over 100 m is good to decimetres.
MAX_FORWARD_TRAIL_M = 100.0

#: Settings only one kind of grid reads; the other kind must leave them at their
#: defaults, so that one grid has one dict (and one model identity hash) — see to_dict.
_CARTESIAN_ONLY = ("extent_xy", "cells_xy")
_POLAR_ONLY = ("rings", "sectors", "max_range")


@dataclass(frozen=True)
class VoxelGridConfig:
    """The voxel grid around the sensor: Cartesian (the paper's) or polar.

    Both are centred on the sensor and cut height into the bands
    ``z_edges[k] <= z < z_edges[k+1]`` (sensor frame, metres), one layer per band.

    ``kind="cartesian"`` (default): XY cells fixed to the sensor axes covering
    ``[-extent_xy, extent_xy)`` in x and y, ``cells_xy`` cells per side.

    ``kind="polar"``: ``rings`` equal-width annuli over ``[0, max_range)`` x
    ``sectors`` equal angles over ``[0, 2π)``, starting at +x and counter-
    clockwise. A scan rotated about z by whole sectors permutes the sectors of
    its descriptor (see :mod:`vbrl_ros.grids.polar`).

    ``frame="ground"`` levels each scan on its own ground first and measures z from
    it, so that layers mean the same on any mounting; ``"sensor"`` (default) is the
    sensor's own frame, as in the paper.

    Points outside the grid are dropped.
    """

    extent_xy: float = 40.0
    cells_xy: int = 8
    z_edges: tuple[float, ...] = (-3.0, -1.0, 1.0, 6.0)
    kind: str = "cartesian"
    rings: int = 8
    sectors: int = 24
    max_range: float = 40.0
    frame: str = "sensor"

    def __post_init__(self) -> None:
        object.__setattr__(self, "z_edges", tuple(float(z) for z in self.z_edges))
        _require(
            self.frame in FRAMES,
            "grid.frame",
            f"must be one of {', '.join(FRAMES)}, got {self.frame!r}",
        )
        _require(
            self.kind in GRID_KINDS,
            "grid.kind",
            f"must be one of {', '.join(GRID_KINDS)}, got {self.kind!r}",
        )
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
        _require(
            isinstance(self.rings, int) and 1 <= self.rings <= 256,
            "grid.rings",
            f"must be an integer in [1, 256], got {self.rings!r}",
        )
        _require(
            isinstance(self.sectors, int) and 2 <= self.sectors <= 360,
            "grid.sectors",
            f"must be an integer in [2, 360], got {self.sectors!r}",
        )
        _require(
            isinstance(self.max_range, (int, float))
            and math.isfinite(self.max_range)
            and self.max_range > 0,
            "grid.max_range",
            f"must be a positive number of metres, got {self.max_range!r}",
        )
        object.__setattr__(self, "max_range", float(self.max_range))
        unused = _CARTESIAN_ONLY if self.kind == "polar" else _POLAR_ONLY
        defaults = VoxelGridConfig.__dataclass_fields__
        for name in unused:
            _require(
                getattr(self, name) == defaults[name].default,
                f"grid.{name}",
                f"is not used by the {self.kind} grid; leave it at its default",
            )

    @property
    def n_layers(self) -> int:
        return len(self.z_edges) - 1

    @property
    def n_voxels(self) -> int:
        if self.kind == "polar":
            return self.rings * self.sectors * self.n_layers
        return self.cells_xy * self.cells_xy * self.n_layers

    @property
    def cell_size_xy(self) -> float:
        return 2.0 * self.extent_xy / self.cells_xy

    @property
    def ring_width(self) -> float:
        """Radial width of one ring in metres (polar grid)."""
        return self.max_range / self.rings

    @property
    def n_sectors(self) -> int:
        """Angular sectors: ``sectors`` for the polar grid, 1 for the Cartesian one."""
        return self.sectors if self.kind == "polar" else 1

    def to_dict(self) -> dict[str, Any]:
        """Only the settings this kind of grid reads.

        A Cartesian grid gives exactly the dict it gave before polar grids
        existed, so model files and their identity hashes are unchanged.
        """
        out = asdict(self)
        out["z_edges"] = list(self.z_edges)
        unused = (*_POLAR_ONLY, "kind") if self.kind == "cartesian" else _CARTESIAN_ONLY
        for name in unused:
            del out[name]
        if self.frame == "sensor":  # grids from before the ground frame keep their identity
            del out["frame"]
        return out


@dataclass(frozen=True)
class FeatureConfig:
    """Per-voxel features: the paper's covariance, three HOG snapshots and subvoxel
    occupancy, the highest point above the voxel's floor (``height``) and, on a polar grid,
    the bird's-eye height spectrum in each (frequency ring, direction sector) (``spectrum``).

    ``modalities`` picks which, in descriptor order (default: the paper's five).
    ``normalise`` scales each modality's block of a descriptor to unit L1 norm, so
    Eq. 4 compares the shape of two scans' feature distributions, not how much of
    each scan was seen (a sparse or partly blind scan is not near every other sparse one).
    ``mirror_blind_wedges`` also hides the mirror image of every wedge the sensor did not
    see (:mod:`vbrl_ros.features.blind_wedges`), so reversed revisits of a partly blind
    sensor compare the same directions; height-map modalities only.
    ``mirror_field_of_view`` keeps of a tilted sensor's scan only what it would also see turned
    half a turn (:mod:`vbrl_ros.features.field_of_view`), so a reversed pass keeps the same band
    of the world; height-map modalities on a levelled (``grid.frame="ground"``) grid only.
    ``trail_m`` describes a keyframe with the keyframes of the last ``trail_m`` metres of
    odometry merged in, when its pose is known (:mod:`vbrl_ros.features.trail`; 0 = alone);
    ``forward_trail_m`` describes a forward-looking keyframe with the earlier keyframes of the
    last ``forward_trail_m`` metres that looked at where it stands
    (:mod:`vbrl_ros.features.forward_trail`; 0 = alone).
    ``trail_ahead_m`` also merges the keyframes of the next ``trail_ahead_m`` metres into a
    keyframe with a trail, which waits to be described until the sensor has passed it
    (:mod:`vbrl_ros.features.trail_ahead`; 0 = described when it comes); it needs ``trail_m``.
    ``fill_blind_wedges`` also describes a keyframe with a blind wedge all round where the
    keyframes of its forward trail saw into the wedge, compared only with keyframes described
    so (:mod:`vbrl_ros.index.all_round`); it needs ``mirror_blind_wedges`` and ``forward_trail_m``.
    ``drop_weather_clutter`` takes lone points in the air near the sensor (returns from rain,
    snow or dust) out of the height map (:mod:`vbrl_ros.features.weather_clutter`); it
    changes the height-map modalities only.

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
    modalities: tuple[str, ...] = PAPER_MODALITIES
    normalise: bool = False
    mirror_blind_wedges: bool = False
    mirror_field_of_view: bool = False
    drop_weather_clutter: bool = False
    trail_m: float = 0.0
    forward_trail_m: float = 0.0
    fill_blind_wedges: bool = False
    trail_ahead_m: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "modalities", tuple(self.modalities))
        _require(
            len(self.modalities) > 0
            and all(m in MODALITY_NAMES for m in self.modalities)
            and len(set(self.modalities)) == len(self.modalities),
            "features.modalities",
            f"must be distinct names out of {', '.join(MODALITY_NAMES)}, got {list(self.modalities)!r}",
        )
        _require(
            isinstance(self.normalise, bool),
            "features.normalise",
            f"must be true or false, got {self.normalise!r}",
        )
        for name in ("mirror_blind_wedges", "mirror_field_of_view"):  # both act on the height map
            value = getattr(self, name)
            _require(
                isinstance(value, bool) and (not value or set(self.modalities) <= set(HEIGHT_MAP_MODALITIES)),
                f"features.{name}",
                f"must be true or false, and true only with height-map modalities "
                f"({', '.join(HEIGHT_MAP_MODALITIES)}), got {value!r}",
            )
        _require(
            isinstance(self.drop_weather_clutter, bool)
            and (not self.drop_weather_clutter or bool(set(self.modalities) & set(HEIGHT_MAP_MODALITIES))),
            "features.drop_weather_clutter",
            f"must be true or false, and true only with a height-map modality "
            f"({', '.join(HEIGHT_MAP_MODALITIES)}), got {self.drop_weather_clutter!r}",
        )
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
        _require(
            isinstance(self.trail_m, (int, float)) and not isinstance(self.trail_m, bool)
            and math.isfinite(self.trail_m) and 0.0 <= self.trail_m <= MAX_TRAIL_M,
            "features.trail_m",
            f"must be a number of metres in [0, {MAX_TRAIL_M:g}], got {self.trail_m!r}",
        )
        _require(
            isinstance(self.forward_trail_m, (int, float)) and not isinstance(self.forward_trail_m, bool)
            and math.isfinite(self.forward_trail_m) and 0.0 <= self.forward_trail_m <= MAX_FORWARD_TRAIL_M,
            "features.forward_trail_m",
            f"must be a number of metres in [0, {MAX_FORWARD_TRAIL_M:g}], got {self.forward_trail_m!r}",
        )
        _require(
            isinstance(self.trail_ahead_m, (int, float)) and not isinstance(self.trail_ahead_m, bool)
            and math.isfinite(self.trail_ahead_m) and 0.0 <= self.trail_ahead_m <= MAX_TRAIL_M
            and (self.trail_ahead_m == 0.0 or self.trail_m > 0.0),
            "features.trail_ahead_m",
            f"must be a number of metres in [0, {MAX_TRAIL_M:g}], and above 0 only with a trail_m, "
            f"got {self.trail_ahead_m!r}",
        )
        _require(
            isinstance(self.fill_blind_wedges, bool)
            and (not self.fill_blind_wedges or (self.mirror_blind_wedges and self.forward_trail_m > 0)),
            "features.fill_blind_wedges",
            f"must be true or false, and true only with mirror_blind_wedges and a forward_trail_m, "
            f"got {self.fill_blind_wedges!r}",
        )

    def to_dict(self) -> dict[str, Any]:
        """Every setting; the ones added after the paper's only when not at their defaults,
        so older model files keep their identity hash."""
        out = asdict(self)
        out["modalities"] = list(self.modalities)
        if self.modalities == PAPER_MODALITIES:
            del out["modalities"]
        if not self.normalise:
            del out["normalise"]
        if not self.mirror_blind_wedges:
            del out["mirror_blind_wedges"]
        if not self.mirror_field_of_view:
            del out["mirror_field_of_view"]
        if not self.drop_weather_clutter:
            del out["drop_weather_clutter"]
        if not self.fill_blind_wedges:
            del out["fill_blind_wedges"]
        if self.trail_m == 0.0:
            del out["trail_m"]
        if self.forward_trail_m == 0.0:
            del out["forward_trail_m"]
        if self.trail_ahead_m == 0.0:
            del out["trail_ahead_m"]
        return out

    @property
    def hog_length(self) -> int:
        """Length of one plane's HOG vector."""
        return self.hog_cells * self.hog_cells * self.hog_orientations


@dataclass(frozen=True)
class VBRLConfig:
    """Everything that decides what a scan's descriptor vector means."""

    grid: VoxelGridConfig = field(default_factory=VoxelGridConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)

    def __post_init__(self) -> None:
        _require(
            "spectrum" not in self.features.modalities or self.grid.kind == "polar",
            "features.modalities",
            "'spectrum' needs a polar grid: its rings and sectors are frequency and direction",
        )
        _require(
            not self.features.mirror_field_of_view or self.grid.frame == "ground",
            "features.mirror_field_of_view",
            "needs a levelled grid (grid.frame: ground): the tilt it mirrors is the levelling's",
        )

    def to_dict(self) -> dict[str, Any]:
        return {"grid": self.grid.to_dict(), "features": self.features.to_dict()}

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
        # every field, not to_dict(): a Cartesian and a polar grid have different key sets
        mine, theirs = _all_settings(self), _all_settings(other)
        return [
            f"{section}.{key}: {mine[section][key]!r} != {theirs[section][key]!r}"
            for section in mine
            for key in mine[section]
            if mine[section][key] != theirs[section][key]
        ]


def _all_settings(config: VBRLConfig) -> dict[str, dict[str, Any]]:
    out = asdict(config)
    out["grid"]["z_edges"] = list(config.grid.z_edges)
    return out


def _build(cls: type, values: Any, section: str) -> Any:
    if not isinstance(values, dict):
        raise ValueError(f"invalid config: section '{section}' must be a mapping")
    known = {f.name for f in fields(cls)}
    unknown = set(values) - known
    if unknown:
        raise ValueError(f"invalid config: unknown key(s) {sorted(f'{section}.{k}' for k in unknown)}")
    return cls(**values)
