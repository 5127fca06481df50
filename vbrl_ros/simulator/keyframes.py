"""Keyframe clouds as SLAM front-ends publish them: ground removed, voxel-thinned.

A place-recognition node subscribed to a SLAM system rarely sees the raw
scan. Front-ends hand on sparse keyframes: one point per voxel, often with
the ground stripped first. :class:`KeyframeFilter` turns a rendered scan into
such a keyframe. The ground is removed by the simulator's own labels (every
point that hit the ground surface, nothing else), not by a heuristic fit, so
what remains is known exactly. Thinning keeps, in each voxel of the sensor
frame, the return nearest the voxel's centroid: close to the centroid PCL's
voxel grid publishes (what most LiDAR-inertial front-ends use), independent of
the order a driver lists the points in, and still a real return with its own
intensity, label and beam.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .geometry import Material

GROUND_MATERIALS = (Material.GROUND, Material.SNOW_GROUND)


@dataclass(frozen=True)
class KeyframeFilter:
    """``remove_ground`` drops every ground return; ``thin_voxel_m`` keeps at most one point per cube of
    that edge length (sensor frame). Ground goes first, so a voxel holding a wall's foot and the road keeps
    the wall. The default filter keeps every point."""

    thin_voxel_m: float | None = None
    remove_ground: bool = False

    def __post_init__(self) -> None:
        voxel = self.thin_voxel_m
        if voxel is not None and (not isinstance(voxel, (int, float)) or not math.isfinite(voxel) or voxel <= 0):
            raise ValueError(f"KeyframeFilter.thin_voxel_m must be a positive number or None, got {voxel!r}")
        if not isinstance(self.remove_ground, bool):
            raise ValueError(f"KeyframeFilter.remove_ground must be a bool, got {self.remove_ground!r}")

    @property
    def keeps_everything(self) -> bool:
        return self.thin_voxel_m is None and not self.remove_ground

    def keep(self, points: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """Indices (ascending, so scan order is kept) of the points of ``points`` / ``labels`` that remain."""
        index = np.arange(len(points))
        if self.remove_ground:
            index = index[~np.isin(labels, GROUND_MATERIALS)]
        if self.thin_voxel_m is None or len(index) == 0:
            return index
        xyz = points[index, :3].astype(np.float64)
        _, voxel = np.unique(np.floor(xyz / self.thin_voxel_m).astype(np.int64), axis=0, return_inverse=True)
        voxel = voxel.ravel()
        count = np.bincount(voxel)
        centroid = np.stack([np.bincount(voxel, xyz[:, k]) / count for k in range(3)], axis=1)
        # Nanometres, so that equal distances (both points of a two-point voxel) are equal whatever order the
        # centroid was summed in; ties then go to the lowest point, not to whichever was listed first.
        gap = np.rint(np.linalg.norm(xyz - centroid[voxel], axis=1) * 1e9).astype(np.int64)
        order = np.lexsort((xyz[:, 0], xyz[:, 1], xyz[:, 2], gap, voxel))  # by voxel, nearest the centroid first
        first = np.ones(len(order), dtype=bool)
        first[1:] = voxel[order[1:]] != voxel[order[:-1]]
        return index[np.sort(order[first])]
