"""A scene (ground plane + primitive batches) and its nearest-hit ray cast.

:meth:`Scene.cast` runs the pairwise kernels of :mod:`.geometry` on the
(ray, primitive) pairs it is given, keeps the nearest hit per ray with an
unbuffered ``np.minimum.at`` reduction, and computes normals and materials
only for the winning pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import (Boxes, Cylinders, Ellipsoids, Material, PrimitiveKind, intersect_boxes,
                       intersect_cylinders, intersect_ellipsoids, intersect_ground)


@dataclass(frozen=True)
class Hits:
    """Nearest hit per ray; ``range`` is inf (and kind NONE) for misses."""

    range: np.ndarray  # (R,) metres along the unit direction
    normal: np.ndarray  # (R, 3) world-frame unit normal (zeros for misses)
    material: np.ndarray  # (R,) uint8 Material
    kind: np.ndarray  # (R,) uint8 PrimitiveKind
    index: np.ndarray  # (R,) index into the batch named by kind, -1 for misses/ground


PairLists = dict[PrimitiveKind, tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True, eq=False)
class Scene:
    """Ground plane plus primitive batches; the input of every ray cast."""

    boxes: Boxes
    cylinders: Cylinders
    ellipsoids: Ellipsoids
    ground_z: float = 0.0
    ground_material: Material = Material.GROUND

    def batch(self, kind: PrimitiveKind):
        return {PrimitiveKind.BOX: self.boxes, PrimitiveKind.CYLINDER: self.cylinders,
                PrimitiveKind.ELLIPSOID: self.ellipsoids}[kind]

    def all_pairs(self, n_rays: int) -> PairLists:
        """Every (ray, primitive) pair -- brute force, for small ray sets."""
        pairs: PairLists = {}
        for kind in (PrimitiveKind.BOX, PrimitiveKind.CYLINDER, PrimitiveKind.ELLIPSOID):
            n_prims = len(self.batch(kind))
            pairs[kind] = (np.repeat(np.arange(n_rays), n_prims), np.tile(np.arange(n_prims), n_rays))
        return pairs

    def _intersect(self, kind: PrimitiveKind, origins: np.ndarray, directions: np.ndarray,
                   ray_ids: np.ndarray, prim_ids: np.ndarray, with_normal: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """Run the kernel of ``kind`` on the given (ray, primitive) pairs."""
        batch = self.batch(kind)
        ray_origins = origins if origins.ndim == 1 else np.take(origins, ray_ids, axis=0)
        ray_dirs = np.take(directions, ray_ids, axis=0)
        if kind == PrimitiveKind.BOX:
            cos_yaw, sin_yaw = batch.cos_sin_yaw
            return intersect_boxes(ray_origins, ray_dirs, np.take(batch.center, prim_ids, axis=0),
                                   np.take(batch.half_size, prim_ids, axis=0), np.take(batch.yaw, prim_ids),
                                   with_normal, (np.take(cos_yaw, prim_ids), np.take(sin_yaw, prim_ids)))
        if kind == PrimitiveKind.CYLINDER:
            return intersect_cylinders(ray_origins, ray_dirs, np.take(batch.center_xy, prim_ids, axis=0),
                                       np.take(batch.radius, prim_ids), np.take(batch.z_min, prim_ids),
                                       np.take(batch.z_max, prim_ids), with_normal)
        return intersect_ellipsoids(ray_origins, ray_dirs, np.take(batch.center, prim_ids, axis=0),
                                    np.take(batch.radii, prim_ids, axis=0), with_normal)

    def cast(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        max_range: float = np.inf,
        pairs: PairLists | None = None,
        rng: np.random.Generator | None = None,
    ) -> Hits:
        """Nearest hit of each ray.

        ``origins`` is (R, 3) or a single (3,) origin shared by all rays,
        ``directions`` (R, 3) unit vectors, both world frame. ``pairs`` limits
        the tests to the given (ray index, primitive index) lists per kind
        (default: all pairs). ``rng`` draws porosity for primitives with
        density < 1; without it every primitive is solid.
        """
        directions = np.asarray(directions, dtype=np.float64)
        origins = np.asarray(origins, dtype=np.float64)
        n_rays = len(directions)
        if pairs is None:
            pairs = self.all_pairs(n_rays)

        best = intersect_ground(origins, directions, self.ground_z)
        best[best > max_range] = np.inf
        ground_hit = np.isfinite(best)
        kind = np.where(ground_hit, PrimitiveKind.GROUND, PrimitiveKind.NONE).astype(np.uint8)
        material = np.where(ground_hit, int(self.ground_material), Material.NONE).astype(np.uint8)
        index = np.full(n_rays, -1, dtype=np.int64)
        normal = np.zeros((n_rays, 3))
        normal[ground_hit, 2] = 1.0

        for prim_kind, (ray_ids, prim_ids) in pairs.items():
            if len(ray_ids) == 0:
                continue
            batch = self.batch(prim_kind)
            t, _ = self._intersect(prim_kind, origins, directions, ray_ids, prim_ids, with_normal=False)
            if rng is not None:
                density = np.take(batch.density, prim_ids)
                porous = density < 1.0
                if np.any(porous):
                    passes = np.zeros(len(t), dtype=bool)
                    passes[porous] = rng.random(int(porous.sum())) >= density[porous]
                    t[passes] = np.inf
            candidate = np.flatnonzero(t < np.minimum(np.take(best, ray_ids), max_range))
            if len(candidate) == 0:
                continue
            ray_c, t_c = np.take(ray_ids, candidate), np.take(t, candidate)
            np.minimum.at(best, ray_c, t_c)
            winner = t_c == np.take(best, ray_c)
            ray_w, prim_w = ray_c[winner], np.take(prim_ids, candidate)[winner]
            kind[ray_w] = prim_kind
            index[ray_w] = prim_w
        # Normals and materials only for the final winners, not for every pair.
        for prim_kind in (PrimitiveKind.BOX, PrimitiveKind.CYLINDER, PrimitiveKind.ELLIPSOID):
            ray_w = np.flatnonzero(kind == prim_kind)
            if len(ray_w):
                prim_w = index[ray_w]
                _, normal[ray_w] = self._intersect(prim_kind, origins, directions, ray_w, prim_w, with_normal=True)
                material[ray_w] = self.batch(prim_kind).material[prim_w]
        index[kind == PrimitiveKind.GROUND] = -1
        return Hits(range=best, normal=normal, material=material, kind=kind, index=index)
