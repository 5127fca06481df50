"""One keyframe's cloud as verification uses it, with everything derived from it computed once.

Verifying a candidate needs, per cloud, the same few things several times over: the
thinned points, their ground, a KD-tree (registration's fitness and the agreement
both search it), the KISS-ICP map of the match, the registration source and the
heading search of the query. Computed per use, the same tree or mask was built two or
three times per candidate; here each is computed on first use and kept, so a query verified
against several candidates (:class:`~vbrl_ros.detection.registration.QueryVerifier`)
prepares itself once, and a caller may keep a database keyframe's too.

Search structures stay in the cloud's own frame: distances do not change under a
rigid transform, so the other cloud is carried into this one instead of rebuilding
a tree for every relative pose.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
from kiss_icp.mapping import VoxelHashMap
from kiss_icp.voxelization import voxel_down_sample
from scipy.spatial import cKDTree

from vbrl_ros.detection.coarse_alignment import HeadingSearch
from vbrl_ros.detection.ground import ground_mask
from vbrl_ros.detection.plan_view import PlanView
from vbrl_ros.detection.surface_normals import surfaces
from vbrl_ros.detection.visibility import Horizon

# No LiDAR measures farther than this along any axis (the longest-range ones reach ~500 m);
# points beyond are corrupt and are dropped before storage and verification.
MAX_POINT_RANGE_M = 1000.0
# KISS-ICP's default: at most 20 points per map voxel (with a minimum spacing of
# voxel/sqrt(20) between them), enough for sub-voxel nearest neighbours.
MAX_POINTS_PER_VOXEL = 20
# Ground source points are kept at this many voxels (structure at 1.5), see PreparedCloud.source.
GROUND_THINNING = 4.0
# Cells of the plan view that compares a heading search's overlays, in voxels: with whole voxels
# (a neighbour then counts up to 1.5 voxels away) the overlay turned by 90 degrees in a square
# courtyard won more often.
PLAN_CELL = 0.5
#: Neighbours of a point that define its surface normal.
NORMAL_NEIGHBOURS = 8


def clean_points(points: np.ndarray) -> np.ndarray:
    """(N, 3) float64 C-contiguous points within :data:`MAX_POINT_RANGE_M` (what the KISS-ICP bindings
    need: far beyond it, voxel and grid indices overflow)."""
    points = np.asarray(points, dtype=np.float64)
    if points.size == 0:
        return np.empty((0, 3))
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    points = points[:, :3]
    # NaN and inf compare False: dropped too
    return np.ascontiguousarray(points[np.all(np.abs(points) <= MAX_POINT_RANGE_M, axis=1)])


def shuffled(points: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random permutation of the points.

    KISS-ICP's voxel_down_sample keeps the *first* point of each voxel; in scan
    order that is always the lowest beam / earliest azimuth, a systematic
    offset of up to a voxel that differs between two viewpoints and biases
    scan-to-scan ICP (~10 cm -> ~6 cm with 1 m stored clouds).
    Seeded, so results are reproducible.
    """
    return points[np.random.default_rng(0).permutation(len(points))]


def thinned(points: np.ndarray, voxel: float) -> np.ndarray:
    """Cleaned, shuffled points, at most one per ``voxel``."""
    points = shuffled(clean_points(points))
    return voxel_down_sample(points, float(voxel)) if len(points) else points


class PreparedCloud:
    """A cloud for verification at ``voxel`` (KISS-ICP keeps the scan at voxel / 2: a no-op for a
    cloud from :func:`~vbrl_ros.detection.registration.downsample_for_storage`). ``sensor``: 4x4,
    the keyframe's sensor -> the cloud's frame (its levelling frame), which tells the band of
    elevations it saw (:class:`~vbrl_ros.detection.visibility.FieldOfView`); None: unknown."""

    def __init__(self, points: np.ndarray, voxel: float, sensor: np.ndarray | None = None) -> None:
        self.voxel = float(voxel)
        self.sensor = sensor
        self.points = thinned(points, 0.5 * self.voxel)
        self.ground = ground_mask(self.points)

    @classmethod
    def of_thinned(cls, points: np.ndarray, voxel: float, ground: np.ndarray) -> PreparedCloud:
        """(N, 3) float64 finite points taken as they are, with their ``ground`` (bool (N,)); the
        sensor's pose unknown."""
        cloud = cls.__new__(cls)
        cloud.voxel = float(voxel)
        cloud.sensor = None
        cloud.points = np.ascontiguousarray(points, dtype=np.float64)
        cloud.ground = np.asarray(ground, dtype=bool)
        return cloud

    @cached_property
    def structure(self) -> np.ndarray:
        """The non-ground points."""
        return self.points[~self.ground]

    @cached_property
    def source(self) -> tuple[np.ndarray, int]:
        """(points, n_structure): the registration source when this cloud is the query,
        structure first: structure at KISS-ICP's 1.5-voxel downsampling, ground thinned to one
        point per ``GROUND_THINNING`` voxels (ground fixes z, roll and pitch; structure
        should decide x, y and yaw)."""
        structure = voxel_down_sample(self.structure, 1.5 * self.voxel) if len(self.structure) else self.structure
        ground = self.points[self.ground]
        flat = voxel_down_sample(ground, GROUND_THINNING * self.voxel) if len(ground) else ground
        return np.ascontiguousarray(np.concatenate([structure, flat])), len(structure)

    def sampled_source(self, max_structure: int) -> np.ndarray:
        """:attr:`source` with at most ``max_structure`` structure points (a seeded random subset;
        all the ground), computed once per limit."""
        samples = self.__dict__.setdefault("_samples", {})
        if max_structure not in samples:
            source, n_structure = self.source
            if n_structure <= max_structure:
                samples[max_structure] = source
            else:
                keep = np.sort(np.random.default_rng(0).choice(n_structure, max_structure, replace=False))
                samples[max_structure] = np.ascontiguousarray(np.concatenate([source[keep], source[n_structure:]]))
        return samples[max_structure]

    @cached_property
    def horizon(self) -> Horizon:
        """How far this cloud's sensor saw in each direction (and, with its pose, between which
        elevations), to a voxel."""
        return Horizon(self.points, self.voxel, self.sensor)

    @cached_property
    def plan(self) -> PlanView:
        """The structure seen from above, in cells of ``PLAN_CELL`` voxels."""
        return PlanView(self.structure, PLAN_CELL * self.voxel)

    @cached_property
    def tree(self) -> cKDTree:
        return cKDTree(self.points)

    def heading_search(self, max_shift_m: float) -> HeadingSearch:
        """The query side of the heading search over the registration source's structure, for
        translations up to ``max_shift_m``; built once per radius."""
        searches = self.__dict__.setdefault("_searches", {})
        if max_shift_m not in searches:
            source, n_structure = self.source
            searches[max_shift_m] = HeadingSearch(source[:n_structure], max_shift_m)
        return searches[max_shift_m]

    def voxel_map(self, voxel: float) -> VoxelHashMap:
        """KISS-ICP's map of the points at ``voxel``, built once per voxel size."""
        maps = self.__dict__.setdefault("_maps", {})
        if voxel not in maps:
            # max_distance only prunes the map in update(); add_points keeps everything.
            maps[voxel] = VoxelHashMap(voxel, np.inf, max_points_per_voxel=MAX_POINTS_PER_VOXEL)
            maps[voxel].add_points(self.points)
        return maps[voxel]

    @cached_property
    def point_surfaces(self) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`surfaces` of every point, computed once (a query is checked against each candidate)."""
        return self.surfaces(np.arange(len(self.points)))

    def surfaces(self, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(normals (n, 3), planarity (n,)) of the points at ``indices``, in this cloud's frame:
        the smallest principal axis of each point's ``NORMAL_NEIGHBOURS`` nearest points, and
        (l2 - l1) / l3 of their spread (1 on a plane, 0 for scattered clutter)."""
        _, neighbours = self.tree.query(self.points[indices], k=NORMAL_NEIGHBOURS)
        return surfaces(self.points, neighbours)
