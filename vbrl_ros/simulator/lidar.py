"""Spinning multi-beam LiDAR: beam layout, per-scan culling and rendering.

A scan is a ``beams`` x ``columns`` grid of rays from the sensor origin: beam
elevations evenly spread over ``vertical_fov_deg``, columns evenly spread over
360 degrees (column 0 points backwards, azimuth -pi; azimuth grows
counter-clockwise, x forward, y left, z up). Ray ``row * columns + col``.

Rendering does not test every ray against every primitive. For each primitive
the renderer bounds the azimuth interval and the elevation interval it
subtends as seen from the sensor (exact footprint corners for boxes, tangent
lines for cylinders/ellipsoids, conservative in elevation) and only generates
(ray, primitive) pairs inside that window -- a rasteriser's bounding-box test.
Primitives whose footprint lies beyond ``max_range_m`` are culled. The windows
are world azimuth/elevation intervals, so they hold for a level sensor only.

A tilted sensor (a hand-held one, or one mounted with roll or pitch; up to
``MAX_TILT_DEG``) is rendered through a level one: a level sensor at the same
origin and heading, with the same beam spacing and columns but its vertical
field of view widened by the tilt on both sides (:func:`level_cover`), so that
it covers every elevation the tilted beams reach. Its points are rotated into
the tilted sensor frame and kept if they lie inside the tilted sensor's own
vertical field of view, to within half a beam spacing; each is labelled with
the nearest of the sensor's beams. Every point is an exact hit of an exactly
cast ray, so the geometry and the poses are exact and rendering stays as fast
as the culling makes it (about twice the rays for a 20 degree tilt of a 40
degree field of view).

What is approximated is the beam pattern. A real tilted sensor fires along
cones about its own z axis, at azimuths evenly spaced in its own frame. The
level render fires along level cones, which cross the tilted field of view
obliquely: the angular spacing of the points is the sensor's, but a beam of
the tilted scan (its ring label) is the band of level points within half a
spacing of that beam's cone, not one cone, its points are not evenly spaced
in the sensor's azimuth, and the field of view's edges are cut along the
level rings. What reads the points' geometry (voxel grids, ground fits,
registration) sees a tilted sensor; what relies on the ring structure
(range images, per-ring ground segmentation) sees the difference. Exactly
level poses take the direct path, unchanged.

A sensor partly hidden by its own robot (a mast, the body) is modelled by
``LidarConfig.blocked_azimuth_deg``: every return whose azimuth in the sensor
frame lies in that wedge is dropped after rendering, so the rest of the scan
is exactly the unblocked scan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from vbrl_ros.datasets.blocked_wedge import checked_wedge, outside_wedge

from .geometry import REFLECTIVITY, Material, PrimitiveKind
from .scene import Hits, PairLists, Scene

# Default vertical field of view per beam count, roughly the common sensors
# (VLP-16, HDL-32E, a 64-beam spinning LiDAR, OS-128).
DEFAULT_VERTICAL_FOV_DEG = {16: (-15.0, 15.0), 32: (-30.0, 10.0), 64: (-25.0, 15.0), 128: (-22.5, 22.5)}
_RANGE_FALLOFF_M = 60.0  # range at which the received power has halved (before weather)
#: Largest tilt (angle between the sensor's z axis and the world's) a pose may have.
MAX_TILT_DEG = 60.0
_MAX_BEAMS = 512
_LEVEL_TILT_RAD = 1e-9  # below this a pose takes the level path
_SINGLE_BEAM_STEP_DEG = 0.4  # elevation spacing of the level render of a tilted one-beam sensor


@dataclass(frozen=True)
class LidarConfig:
    """Sensor model. ``vertical_fov_deg=None`` picks the default for ``beams``.

    ``blocked_azimuth_deg=(start, end)`` is a wedge the sensor cannot see, in
    degrees of sensor-frame azimuth (0 forward, counter-clockwise positive),
    swept counter-clockwise from ``start`` to ``end``: ``(150, -150)`` blocks
    the 60 degrees straight behind. ``None`` blocks nothing.
    """

    beams: int = 64
    columns: int = 1800
    vertical_fov_deg: tuple[float, float] | None = None
    max_range_m: float = 100.0
    min_range_m: float = 0.5
    range_noise_std_m: float = 0.02
    intensity_noise_std: float = 0.02
    blocked_azimuth_deg: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.beams, int) or not 1 <= self.beams <= 512:
            raise ValueError(f"LidarConfig.beams must be an integer in [1, 512], got {self.beams!r}")
        if not isinstance(self.columns, int) or not 8 <= self.columns <= 8192:
            raise ValueError(f"LidarConfig.columns must be an integer in [8, 8192], got {self.columns!r}")
        if self.vertical_fov_deg is None:
            object.__setattr__(self, "vertical_fov_deg", DEFAULT_VERTICAL_FOV_DEG.get(self.beams, (-25.0, 15.0)))
        fov = tuple(float(v) for v in self.vertical_fov_deg)  # type: ignore[union-attr]
        if len(fov) != 2 or not -90 < fov[0] < fov[1] < 90 or (self.beams > 1 and fov[0] == fov[1]):
            raise ValueError(f"LidarConfig.vertical_fov_deg must be (low, high) with -90 < low < high < 90, "
                             f"got {self.vertical_fov_deg!r}")
        object.__setattr__(self, "vertical_fov_deg", fov)
        if not (math.isfinite(self.max_range_m) and self.max_range_m > 0):
            raise ValueError(f"LidarConfig.max_range_m must be positive, got {self.max_range_m!r}")
        if not 0 <= self.min_range_m < self.max_range_m:
            raise ValueError(f"LidarConfig.min_range_m must lie in [0, max_range_m), got {self.min_range_m!r}")
        for name in ("range_noise_std_m", "intensity_noise_std"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"LidarConfig.{name} must be a non-negative number, got {value!r}")
        if self.blocked_azimuth_deg is not None:
            object.__setattr__(self, "blocked_azimuth_deg",
                               checked_wedge(self.blocked_azimuth_deg, "LidarConfig.blocked_azimuth_deg"))

    def sees(self, xyz: np.ndarray) -> np.ndarray:
        """(N,) bool: the sensor-frame points ``xyz`` lie outside the blocked wedge."""
        return outside_wedge(xyz, self.blocked_azimuth_deg)

    @property
    def n_rays(self) -> int:
        return self.beams * self.columns

    def elevations(self) -> np.ndarray:
        """(beams,) beam elevation angles in radians, ascending."""
        low, high = self.vertical_fov_deg  # type: ignore[misc]
        return np.radians(np.linspace(low, high, self.beams)) if self.beams > 1 else np.radians([low])

    def azimuths(self) -> np.ndarray:
        """(columns,) column azimuths in radians, from -pi."""
        return -math.pi + np.arange(self.columns) * (2 * math.pi / self.columns)

    def directions(self) -> np.ndarray:
        """(beams * columns, 3) unit ray directions in the sensor frame, row-major."""
        return _directions(self.beams, self.columns, self.vertical_fov_deg)  # type: ignore[arg-type]


@lru_cache(maxsize=8)
def _directions(beams: int, columns: int, fov: tuple[float, float]) -> np.ndarray:
    config = LidarConfig(beams=beams, columns=columns, vertical_fov_deg=fov)
    elevation, azimuth = np.meshgrid(config.elevations(), config.azimuths(), indexing="ij")
    dirs = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                     np.sin(elevation)], axis=-1).reshape(-1, 3)
    dirs.flags.writeable = False  # shared cache entry
    return dirs


@dataclass(frozen=True)
class WeatherEffects:
    """Per-ray degradation; see :mod:`.scenarios` for the presets.

    ``clutter_prob`` rays return from airborne particles at
    ``min_range + Exp(clutter_scale_m)`` (if nearer than the true hit), with
    intensity uniform in ``clutter_intensity``. ``extinction_per_m`` is the
    atmospheric extinction coefficient: a return from range r survives with
    probability exp(-2 alpha r) and its intensity is scaled by the same.
    ``dropout_prob`` loses returns at random (wet/iced optics, specular
    surfaces); ``extra_noise_m`` adds to the range noise.
    """

    clutter_prob: float = 0.0
    clutter_scale_m: float = 5.0
    clutter_intensity: tuple[float, float] = (0.0, 0.05)
    extinction_per_m: float = 0.0
    dropout_prob: float = 0.0
    extra_noise_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("clutter_prob", "dropout_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"WeatherEffects.{name} must lie in [0, 1], got {getattr(self, name)!r}")
        for name in ("clutter_scale_m", "extinction_per_m", "extra_noise_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"WeatherEffects.{name} must be a non-negative number, got {value!r}")
        low, high = self.clutter_intensity
        if not 0.0 <= low <= high <= 1.0:
            raise ValueError(f"WeatherEffects.clutter_intensity must be 0 <= low <= high <= 1, "
                             f"got {self.clutter_intensity!r}")


def _culling_window(scene: Scene, origin: np.ndarray, max_range: float) -> dict[PrimitiveKind, tuple]:
    """Per kind: (ids, az_lo, az_hi, full_turn, el_lo, el_hi) in the world-yaw frame."""
    windows = {}
    o_xy, o_z = origin[:2], origin[2]
    for kind in (PrimitiveKind.BOX, PrimitiveKind.CYLINDER, PrimitiveKind.ELLIPSOID):
        batch = scene.batch(kind)
        if kind == PrimitiveKind.BOX:
            cos_y, sin_y = np.cos(batch.yaw), np.sin(batch.yaw)
            rel = batch.center[:, :2] - o_xy
            # Sensor in the box frame: distance to the footprint rectangle.
            local = np.stack([cos_y * -rel[:, 0] + sin_y * -rel[:, 1], -sin_y * -rel[:, 0] + cos_y * -rel[:, 1]], 1)
            outside = np.maximum(np.abs(local) - batch.half_size[:, :2], 0.0)
            h_min = np.linalg.norm(outside, axis=1)
            signs = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=np.float64)
            corner_local = signs[None] * batch.half_size[:, None, :2]  # (n, 4, 2)
            corner = np.stack([cos_y[:, None] * corner_local[..., 0] - sin_y[:, None] * corner_local[..., 1],
                               sin_y[:, None] * corner_local[..., 0] + cos_y[:, None] * corner_local[..., 1]], -1)
            corner_rel = corner + rel[:, None, :]
            h_max = np.linalg.norm(corner_rel, axis=2).max(axis=1)
            az_centre = np.arctan2(rel[:, 1], rel[:, 0])
            delta = np.arctan2(corner_rel[..., 1], corner_rel[..., 0]) - az_centre[:, None]
            delta = (delta + np.pi) % (2 * np.pi) - np.pi
            az_lo, az_hi = az_centre + delta.min(axis=1), az_centre + delta.max(axis=1)
            full = h_min < 0.05
            z_lo, z_hi = batch.center[:, 2] - batch.half_size[:, 2], batch.center[:, 2] + batch.half_size[:, 2]
        else:
            if kind == PrimitiveKind.CYLINDER:
                rel, radius = batch.center_xy - o_xy, batch.radius
                z_lo, z_hi = batch.z_min, batch.z_max
            else:
                rel, radius = batch.center[:, :2] - o_xy, batch.radii[:, :2].max(axis=1)
                z_lo, z_hi = batch.center[:, 2] - batch.radii[:, 2], batch.center[:, 2] + batch.radii[:, 2]
            d_xy = np.linalg.norm(rel, axis=1)
            full = d_xy <= radius + 0.05
            half = np.arcsin(np.clip(radius / np.maximum(d_xy, 1e-9), 0.0, 1.0))
            az_centre = np.arctan2(rel[:, 1], rel[:, 0])
            az_lo, az_hi = az_centre - half, az_centre + half
            h_min, h_max = np.maximum(d_xy - radius, 0.0), d_xy + radius
        dz_lo, dz_hi = z_lo - o_z, z_hi - o_z
        # Lowest elevation: bottom seen from nearest (if below) or farthest (if above) footprint point.
        el_lo = np.arctan2(dz_lo, np.where(dz_lo >= 0, h_max, h_min))
        el_hi = np.arctan2(dz_hi, np.where(dz_hi >= 0, h_min, h_max))
        ids = np.flatnonzero(h_min < max_range)
        windows[kind] = (ids, az_lo[ids], az_hi[ids], full[ids], el_lo[ids], el_hi[ids])
    return windows


def candidate_pairs(scene: Scene, lidar: LidarConfig, origin: np.ndarray, yaw: float) -> PairLists:
    """(ray, primitive) pairs whose primitive's angular window covers the ray."""
    elevations = lidar.elevations()
    step = 2 * math.pi / lidar.columns
    pairs: PairLists = {}
    for kind, (ids, az_lo, az_hi, full, el_lo, el_hi) in _culling_window(scene, origin, lidar.max_range_m).items():
        row_lo = np.searchsorted(elevations, el_lo - 1e-9, side="left")
        n_rows = np.searchsorted(elevations, el_hi + 1e-9, side="right") - row_lo
        # One column of slack each side guards against rounding at the window edge.
        col_lo = np.ceil((az_lo - yaw + math.pi) / step).astype(np.int64) - 1
        n_cols = np.floor((az_hi - yaw + math.pi) / step).astype(np.int64) + 1 - col_lo + 1
        col_lo = np.where(full, 0, col_lo)
        n_cols = np.where(full, lidar.columns, np.minimum(n_cols, lidar.columns))
        count = np.where(n_rows > 0, n_rows * n_cols, 0)
        total = int(count.sum())
        owner = np.repeat(np.arange(len(ids)), count)
        local = np.arange(total) - np.repeat(np.cumsum(count) - count, count)
        rows_of_owner = n_rows[owner]
        col = (col_lo[owner] + local // rows_of_owner) % lidar.columns
        row = row_lo[owner] + local % rows_of_owner
        pairs[kind] = (row * lidar.columns + col, ids[owner])
    return pairs


def render_scan(
    scene: Scene,
    pose: np.ndarray,
    lidar: LidarConfig,
    rng: np.random.Generator,
    weather: WeatherEffects | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render one scan from ``pose`` (T_world_lidar, level or tilted by at most ``MAX_TILT_DEG``).

    Returns ``(points, labels, rings)``: (N, 4) float32 x, y, z, intensity in
    the sensor frame (misses and the blocked wedge dropped, intensity in [0, 1]), (N,) uint8
    :class:`~.geometry.Material` of each point, (N,) uint16 beam index. A
    tilted pose is rendered through a widened level sensor (module docstring).
    """
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"pose must be a finite 4x4 matrix, got shape {pose.shape}")
    rotation, origin = pose[:3, :3], pose[:3, 3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6) or np.linalg.det(rotation) < 0:
        raise ValueError("pose rotation must be a proper rotation matrix")
    tilt = tilt_angle(rotation)
    if tilt > math.radians(MAX_TILT_DEG) + 1e-9:
        raise ValueError(f"pose tilts the sensor by {math.degrees(tilt):.1f} degrees; "
                         f"the renderer supports at most {MAX_TILT_DEG:g}")
    weather = weather or WeatherEffects()
    if tilt <= _LEVEL_TILT_RAD:
        xyz, intensity, labels, rows = _render_level(scene, origin, rotation, lidar, rng, weather)
        points, rings = _assemble(xyz, intensity), rows.astype(np.uint16)
    else:
        points, labels, rings = _render_tilted(scene, origin, rotation, tilt, lidar, rng, weather)
    if lidar.blocked_azimuth_deg is None:
        return points, labels, rings
    # Dropped after rendering: every ray still draws its noise, so the visible part is the unblocked scan.
    seen = lidar.sees(points)
    return points[seen], labels[seen], rings[seen]


def tilt_angle(rotation: np.ndarray) -> float:
    """Angle (rad) between the sensor's z axis (column 2 of ``rotation``) and the world's."""
    return math.atan2(math.hypot(rotation[0, 2], rotation[1, 2]), rotation[2, 2])


def _beam_step_deg(lidar: LidarConfig) -> float:
    low, high = lidar.vertical_fov_deg  # type: ignore[misc]
    return (high - low) / (lidar.beams - 1) if lidar.beams > 1 else _SINGLE_BEAM_STEP_DEG


def level_cover(lidar: LidarConfig, tilt: float) -> LidarConfig:
    """The level sensor that covers ``lidar`` tilted by ``tilt`` rad: same beam spacing and
    columns, its own beams among the rows, the field of view widened by whole beam steps."""
    low, high = lidar.vertical_fov_deg  # type: ignore[misc]
    high = high if lidar.beams > 1 else low  # one beam fires at ``low`` only
    step = _beam_step_deg(lidar)
    extra = math.ceil(math.degrees(tilt) / step - 1e-9)
    below = min(extra, math.ceil((low + 90.0) / step) - 1)  # stay inside (-90, 90)
    above = min(extra, math.ceil((90.0 - high) / step) - 1)
    if below + above == 0:  # a field of view already reaching +-90 degrees
        return lidar
    beams = lidar.beams + below + above
    if beams > _MAX_BEAMS:
        raise ValueError(f"a {lidar.beams}-beam sensor tilted by {math.degrees(tilt):.1f} degrees needs a "
                         f"{beams}-beam level render (at most {_MAX_BEAMS}): use fewer beams or less tilt")
    return replace(lidar, beams=beams, vertical_fov_deg=(low - below * step, high + above * step))


def _render_tilted(scene: Scene, origin: np.ndarray, rotation: np.ndarray, tilt: float, lidar: LidarConfig,
                   rng: np.random.Generator, weather: WeatherEffects) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render through the level cover, rotate into the tilted frame, crop to its field of view."""
    yaw = math.atan2(rotation[1, 0], rotation[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    level = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    xyz_level, intensity, labels, _ = _render_level(scene, origin, level, level_cover(lidar, tilt), rng, weather)
    # p_sensor = R^T L p_level; row vectors: p_level^T (L^T R).
    tilt_rotation = level.T @ rotation
    xyz = (xyz_level[:, 0:1] * tilt_rotation[0] + xyz_level[:, 1:2] * tilt_rotation[1]
           + xyz_level[:, 2:3] * tilt_rotation[2])
    elevation = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
    low = lidar.vertical_fov_deg[0]  # type: ignore[index]
    ring = np.rint((elevation - low) / _beam_step_deg(lidar)).astype(np.int64)
    inside = (ring >= 0) & (ring < lidar.beams)
    xyz, intensity, labels, ring = xyz[inside], intensity[inside], labels[inside], ring[inside]
    # Ring-major, then the sensor's own azimuth: the row-major order of a level scan.
    column = np.floor((np.arctan2(xyz[:, 1], xyz[:, 0]) + math.pi) * (lidar.columns / (2 * math.pi)))
    order = np.argsort(ring * (lidar.columns + 1) + column.astype(np.int64), kind="stable")
    return _assemble(xyz[order], intensity[order]), labels[order], ring[order].astype(np.uint16)


def _assemble(xyz: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    points = np.empty((len(xyz), 4), dtype=np.float32)
    points[:, :3] = xyz
    points[:, 3] = intensity
    return points


def _render_level(scene: Scene, origin: np.ndarray, rotation: np.ndarray, lidar: LidarConfig,
                  rng: np.random.Generator, weather: WeatherEffects
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(xyz float64 sensor frame, intensity in [0, 1], material, beam row) of a level sensor's returns."""
    yaw = math.atan2(rotation[1, 0], rotation[0, 0])
    dirs_sensor = lidar.directions()
    # Column-wise rotation: (n, 3) @ (3, 3) through BLAS is pathologically slow on some builds.
    dirs_world = (dirs_sensor[:, 0:1] * rotation[:, 0] + dirs_sensor[:, 1:2] * rotation[:, 1]
                  + dirs_sensor[:, 2:3] * rotation[:, 2])
    pairs = candidate_pairs(scene, lidar, origin, yaw)
    hits: Hits = scene.cast(origin, dirs_world, lidar.max_range_m, pairs, rng)
    n_rays = lidar.n_rays

    ranges = hits.range.copy()
    material = hits.material.copy()
    returned = np.isfinite(ranges)
    if weather.extinction_per_m > 0:
        returned &= rng.random(n_rays) < np.exp(-2 * weather.extinction_per_m * np.where(returned, ranges, 0.0))
    if weather.dropout_prob > 0:
        returned &= rng.random(n_rays) >= weather.dropout_prob
    cosine = np.abs(np.einsum("ij,ij->i", hits.normal, dirs_world))
    intensity = REFLECTIVITY[material] * (0.25 + 0.75 * cosine) / (1.0 + (ranges / _RANGE_FALLOFF_M) ** 2)
    if weather.clutter_prob > 0:
        clutter_range = lidar.min_range_m + rng.exponential(weather.clutter_scale_m, n_rays)
        clutter = (rng.random(n_rays) < weather.clutter_prob) & (
            clutter_range < np.where(returned, ranges, lidar.max_range_m))
        ranges[clutter] = clutter_range[clutter]
        material[clutter] = Material.CLUTTER
        intensity[clutter] = rng.uniform(*weather.clutter_intensity, int(clutter.sum()))
        returned |= clutter
    if weather.extinction_per_m > 0:
        intensity = intensity * np.exp(-2 * weather.extinction_per_m * np.where(returned, ranges, 0.0))

    keep = np.flatnonzero(returned)
    noise_std = math.hypot(lidar.range_noise_std_m, weather.extra_noise_m)
    measured = ranges[keep] + rng.normal(0.0, noise_std, len(keep)) if noise_std > 0 else ranges[keep]
    in_range = (measured >= lidar.min_range_m) & (measured <= lidar.max_range_m)
    keep, measured = keep[in_range], measured[in_range]
    value = intensity[keep]
    if lidar.intensity_noise_std > 0:
        value = value + rng.normal(0.0, lidar.intensity_noise_std, len(keep))
    return dirs_sensor[keep] * measured[:, None], np.clip(value, 0.0, 1.0), material[keep], keep // lidar.columns
