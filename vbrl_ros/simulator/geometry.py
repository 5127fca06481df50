"""Vectorised ray-primitive intersection for the LiDAR simulator.

A scene is a flat ground plane ``z = ground_z`` plus three batches of
primitives, each stored as arrays (structure of arrays, no Python objects per
primitive):

* :class:`Boxes` -- boxes rotated about the vertical axis (yaw only); buildings,
  walls, fences, cars. Rays are transformed into each box's frame and clipped
  with the slab test.
* :class:`Cylinders` -- vertical capped cylinders; tree trunks, poles,
  pedestrians. Quadratic in the horizontal plane plus the two cap planes.
* :class:`Ellipsoids` -- axis-aligned ellipsoids (a sphere is the special case
  of equal radii); tree crowns. Rays are scaled into the unit-sphere frame,
  where the ray parameter ``t`` keeps its meaning (world metres along a unit
  direction), so the quadratic gives world ranges directly.

Intersection kernels work on *pairs*: element ``k`` of every argument belongs
to the same (ray, primitive) pair. Who generates the pairs is the caller's
business -- :meth:`.scene.Scene.cast` tests all pairs by default (fine for a
few thousand rays), the spinning-LiDAR renderer in :mod:`.lidar` generates
only the pairs whose primitive covers the ray's azimuth/elevation cell.

Every primitive carries a ``density`` in (0, 1]: the probability that a ray
crossing it is returned (foliage, chain-link fences). Porosity is applied per
(ray, primitive) pair, so rays through a sparse crown reach what lies behind.

Only hits in front of the ray origin (``t > 0`` at entry) count: a ray starting
inside a primitive does not see that primitive.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from enum import IntEnum

import numpy as np

# Direction components smaller than this are nudged so the slab test never
# divides by zero (it then sees a huge but finite slab crossing parameter).
_TINY = 1e-12


class Material(IntEnum):
    """What a point hit; also the per-point label of a rendered scan."""

    NONE = 0
    GROUND = 1
    BUILDING = 2
    WALL = 3
    FENCE = 4
    TRUNK = 5
    FOLIAGE = 6  # deciduous crown: sparse in winter
    CONIFER = 7  # evergreen crown: kept all year
    POLE = 8
    PARKED_CAR = 9
    MOVING_CAR = 10
    PEDESTRIAN = 11
    CLUTTER = 12  # fog / snow / rain backscatter, no geometry behind it
    SNOW_GROUND = 13  # ground covered with snow


# Diffuse reflectivity per material in [0, 1] (indexed by Material value).
# Rough orders of magnitude for a 905 nm sensor: asphalt dark, plaster and
# car paint medium, vegetation fairly bright, fresh snow very bright.
REFLECTIVITY = np.array(
    [0.0, 0.12, 0.35, 0.45, 0.25, 0.30, 0.50, 0.40, 0.55, 0.60, 0.60, 0.30, 0.08, 0.85],
    dtype=np.float64,
)


class PrimitiveKind(IntEnum):
    """Which batch a hit came from (``Hits.kind``)."""

    NONE = 0
    GROUND = 1
    BOX = 2
    CYLINDER = 3
    ELLIPSOID = 4


def _as_float_array(value: np.ndarray, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim != 1 + len(shape_tail) or array.shape[1:] != shape_tail:
        raise ValueError(f"{name} must have shape (n, {', '.join(map(str, shape_tail))}), got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite")
    return array


class _PrimitiveBatch:
    """Shared helpers: length, subsetting and concatenation of a batch."""

    def __len__(self) -> int:
        return len(self.material)  # type: ignore[attr-defined]

    def take(self, selector: np.ndarray):
        """The sub-batch selected by a boolean mask or an index array."""
        return type(self)(**{f.name: getattr(self, f.name)[selector] for f in fields(self)})  # type: ignore[arg-type]

    @classmethod
    def concat(cls, batches: list):
        """One batch holding all primitives of ``batches`` in order."""
        if not batches:
            return cls.empty()
        return cls(**{f.name: np.concatenate([getattr(b, f.name) for b in batches]) for f in fields(cls)})  # type: ignore[arg-type]

    @classmethod
    def empty(cls):
        """A batch with no primitives."""
        widths = {"center": 3, "half_size": 3, "radii": 3, "center_xy": 2}
        return cls(**{f.name: np.zeros((0, widths[f.name]) if f.name in widths else 0) for f in fields(cls)})  # type: ignore[arg-type]

    def _finish(self, n: int) -> None:
        material = np.asarray(self.material, dtype=np.uint8).reshape(-1)  # type: ignore[attr-defined]
        density = np.ones(n) if self.density is None else np.asarray(self.density, dtype=np.float64).reshape(-1)  # type: ignore[attr-defined]
        if material.shape != (n,) or density.shape != (n,):
            raise ValueError(f"material and density must have shape ({n},)")
        if np.any((density <= 0) | (density > 1)):
            raise ValueError("density must lie in (0, 1]")
        object.__setattr__(self, "material", material)
        object.__setattr__(self, "density", density)


@dataclass(frozen=True, eq=False)
class Boxes(_PrimitiveBatch):
    """Boxes rotated by ``yaw`` (radians, about +z) around their ``center``."""

    center: np.ndarray  # (n, 3) geometric centre, world frame
    half_size: np.ndarray  # (n, 3) half extents along the box's own x, y, z
    yaw: np.ndarray  # (n,)
    material: np.ndarray  # (n,) uint8 Material
    density: np.ndarray | None = None  # (n,) return probability, default 1

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _as_float_array(self.center, (3,), "Boxes.center"))
        n = len(self.center)
        object.__setattr__(self, "half_size", _as_float_array(self.half_size, (3,), "Boxes.half_size"))
        object.__setattr__(self, "yaw", np.asarray(self.yaw, dtype=np.float64).reshape(-1))
        if self.half_size.shape[0] != n or self.yaw.shape != (n,):
            raise ValueError("Boxes arrays must all have length n")
        if np.any(self.half_size <= 0):
            raise ValueError("Boxes.half_size must be positive")
        self._finish(n)
        # Not a dataclass field (take/concat rebuild it): cached for the kernel.
        object.__setattr__(self, "cos_sin_yaw", (np.cos(self.yaw), np.sin(self.yaw)))


@dataclass(frozen=True, eq=False)
class Cylinders(_PrimitiveBatch):
    """Vertical capped cylinders: axis through ``center_xy``, z in [z_min, z_max]."""

    center_xy: np.ndarray  # (n, 2)
    radius: np.ndarray  # (n,)
    z_min: np.ndarray  # (n,)
    z_max: np.ndarray  # (n,)
    material: np.ndarray
    density: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "center_xy", _as_float_array(self.center_xy, (2,), "Cylinders.center_xy"))
        n = len(self.center_xy)
        for name in ("radius", "z_min", "z_max"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64).reshape(-1))
            if getattr(self, name).shape != (n,):
                raise ValueError(f"Cylinders.{name} must have shape ({n},)")
        if np.any(self.radius <= 0) or np.any(self.z_max <= self.z_min):
            raise ValueError("Cylinders need radius > 0 and z_max > z_min")
        self._finish(n)


@dataclass(frozen=True, eq=False)
class Ellipsoids(_PrimitiveBatch):
    """Axis-aligned ellipsoids with semi-axes ``radii`` around ``center``."""

    center: np.ndarray  # (n, 3)
    radii: np.ndarray  # (n, 3)
    material: np.ndarray
    density: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _as_float_array(self.center, (3,), "Ellipsoids.center"))
        object.__setattr__(self, "radii", _as_float_array(self.radii, (3,), "Ellipsoids.radii"))
        if self.radii.shape[0] != len(self.center) or np.any(self.radii <= 0):
            raise ValueError("Ellipsoids.radii must be positive, one row per centre")
        self._finish(len(self.center))


# --------------------------------------------------------------------------
# Pairwise kernels. Each returns (t, normal): t = entry range along the unit
# direction (np.inf for a miss), normal = outward unit surface normal there.
# --------------------------------------------------------------------------


def intersect_ground(origins: np.ndarray, directions: np.ndarray, ground_z: float = 0.0) -> np.ndarray:
    """Range to the plane ``z = ground_z`` from above (inf when not hit)."""
    dz = directions[..., 2]
    oz = np.broadcast_to(np.asarray(origins)[..., 2], dz.shape)
    t = np.full(dz.shape, np.inf)
    downward = (dz < -_TINY) & (oz > ground_z)
    t[downward] = (ground_z - oz[downward]) / dz[downward]
    return t


def intersect_boxes(
    origins: np.ndarray, directions: np.ndarray, center: np.ndarray, half_size: np.ndarray, yaw: np.ndarray,
    with_normal: bool = True,
    cos_sin_yaw: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Slab test of rays against yaw-rotated boxes, one box per ray.

    ``cos_sin_yaw`` may pass precomputed cos(yaw), sin(yaw) (saves two
    transcendental functions per pair).
    """
    cos_yaw, sin_yaw = cos_sin_yaw if cos_sin_yaw is not None else (np.cos(yaw), np.sin(yaw))
    rel = origins - center
    # Rotate by -yaw into the box frame (only x, y change); one 1-D array per axis.
    o_local = (cos_yaw * rel[:, 0] + sin_yaw * rel[:, 1], cos_yaw * rel[:, 1] - sin_yaw * rel[:, 0], rel[:, 2])
    d_local = (cos_yaw * directions[:, 0] + sin_yaw * directions[:, 1],
               cos_yaw * directions[:, 1] - sin_yaw * directions[:, 0], directions[:, 2])
    near, far, slopes = [], [], []
    for axis in range(3):
        d = np.copysign(np.maximum(np.abs(d_local[axis]), _TINY), d_local[axis])
        inv = 1.0 / d
        t_a = (-half_size[:, axis] - o_local[axis]) * inv
        t_b = (half_size[:, axis] - o_local[axis]) * inv
        near.append(np.minimum(t_a, t_b))
        far.append(np.maximum(t_a, t_b))
        slopes.append(d)
    t_enter = np.maximum(np.maximum(near[0], near[1]), near[2])
    t_exit = np.minimum(np.minimum(far[0], far[1]), far[2])
    hit = (t_enter <= t_exit) & (t_enter > 0.0)
    t = np.where(hit, t_enter, np.inf)
    if not with_normal:
        return t, None
    # Entry face normal in the box frame: -sign(d) along the axis that set t_enter.
    on_x = near[0] == t_enter
    on_y = ~on_x & (near[1] == t_enter)
    on_z = ~on_x & ~on_y
    sign_x, sign_y, sign_z = (-np.sign(d) for d in slopes)
    normal = np.empty((len(t), 3))
    normal[:, 0] = np.where(on_x, sign_x * cos_yaw, np.where(on_y, -sign_y * sin_yaw, 0.0))
    normal[:, 1] = np.where(on_x, sign_x * sin_yaw, np.where(on_y, sign_y * cos_yaw, 0.0))
    normal[:, 2] = np.where(on_z, sign_z, 0.0)
    normal[~hit] = 0.0
    return t, normal


def intersect_cylinders(
    origins: np.ndarray,
    directions: np.ndarray,
    center_xy: np.ndarray,
    radius: np.ndarray,
    z_min: np.ndarray,
    z_max: np.ndarray,
    with_normal: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Rays against vertical capped cylinders, one cylinder per ray."""
    origins = np.broadcast_to(origins, directions.shape)
    o_x, o_y = origins[:, 0] - center_xy[:, 0], origins[:, 1] - center_xy[:, 1]
    d_x, d_y, d_z = directions[:, 0], directions[:, 1], directions[:, 2]
    a = d_x * d_x + d_y * d_y
    b = o_x * d_x + o_y * d_y  # half of the usual b
    c = o_x * o_x + o_y * o_y - radius * radius
    disc = b * b - a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t_side = (-b - np.sqrt(disc)) / a
    z_side = origins[:, 2] + t_side * d_z
    side_ok = (disc >= 0) & (a > _TINY) & (t_side > 0) & (z_side >= z_min) & (z_side <= z_max)
    t_side = np.where(side_ok, t_side, np.inf)

    safe_dz = np.where(np.abs(d_z) < _TINY, _TINY, d_z)
    t_top = (z_max - origins[:, 2]) / safe_dz
    t_bottom = (z_min - origins[:, 2]) / safe_dz
    t_cap = np.where(d_z < 0, t_top, t_bottom)  # the cap facing the ray
    cap_x, cap_y = o_x + t_cap * d_x, o_y + t_cap * d_y
    cap_ok = (np.abs(d_z) >= _TINY) & (t_cap > 0) & (cap_x * cap_x + cap_y * cap_y <= radius * radius)
    t_cap = np.where(cap_ok, t_cap, np.inf)

    use_cap = t_cap < t_side
    t = np.minimum(t_side, t_cap)
    if not with_normal:
        return t, None
    normal = np.zeros_like(directions)
    inv_r = 1.0 / radius
    t_side = np.where(np.isfinite(t_side), t_side, 0.0)  # no inf * 0 for rays that only hit a cap
    normal[:, 0] = np.where(use_cap, 0.0, (o_x + t_side * d_x) * inv_r)
    normal[:, 1] = np.where(use_cap, 0.0, (o_y + t_side * d_y) * inv_r)
    normal[:, 2] = np.where(use_cap, -np.sign(safe_dz), 0.0)
    normal[~np.isfinite(t)] = 0.0
    return t, normal


def intersect_ellipsoids(
    origins: np.ndarray, directions: np.ndarray, center: np.ndarray, radii: np.ndarray,
    with_normal: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Rays against axis-aligned ellipsoids, one ellipsoid per ray."""
    o_scaled = (origins - center) / radii
    d_scaled = directions / radii
    a = np.einsum("ij,ij->i", d_scaled, d_scaled)
    b = np.einsum("ij,ij->i", o_scaled, d_scaled)  # half of the usual b
    c = np.einsum("ij,ij->i", o_scaled, o_scaled) - 1.0
    disc = b * b - a * c
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / a
    hit = (disc >= 0) & (t > 0)
    t = np.where(hit, t, np.inf)
    if not with_normal:
        return t, None
    t_finite = np.where(hit, t, 0.0)
    # Gradient of |(p - c) / r|^2 is 2 (p - c) / r^2.
    gradient = (o_scaled + t_finite[:, None] * d_scaled) / radii
    norm = np.linalg.norm(gradient, axis=1, keepdims=True)
    normal = np.where(hit[:, None], gradient / np.maximum(norm, _TINY), 0.0)
    return t, normal
