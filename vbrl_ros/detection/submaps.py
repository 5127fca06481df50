"""Local submaps for verification: a keyframe's cloud with its neighbours' merged in by odometry.

A sparse keyframe (a 16-32-beam scan, a voxel-thinned cloud of a few thousand points, a
partly blind mount) often holds too little structure for a registration to be trusted, and a
revisit on the other side of the path sees other faces of the same place. The same place seen
from the keyframes just before (and, for a stored keyframe, just after) holds more: odometry
is accurate to centimetres over a few metres, so their clouds are merged into the keyframe's
own frame and the registration compares two small local maps instead of two single scans.

The query keyframe has only its past; a stored keyframe has both sides. Neighbours are taken
only where the merge can be trusted: same session, known poses, close in space, and less than
half the detector's ``exclude_recent_s`` away in time — so a query's submap and its candidate's
never share a keyframe (a candidate is at least ``exclude_recent_s`` older), and a registration
never finds a keyframe aligned with itself.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from kiss_icp.voxelization import voxel_down_sample

#: Neighbours farther than this from the keyframe (m) are not merged: odometry drifts with travel,
#: and what they see is another place.
MAX_NEIGHBOUR_DISTANCE_M = 6.0
#: The wider submaps a registration that slid is retried with (candidate_verification.WIDER_RETRY_FITNESS) reach
#: this far: four times the neighbours of keyframes a couple of metres apart.
WIDER_NEIGHBOUR_DISTANCE_M = 12.0


@dataclass(frozen=True)
class KeyframeView:
    """What a merge needs of one keyframe: its stored cloud in its grid ``frame`` (4x4 sensor ->
    grid), its odometry ``pose`` (T_world_lidar, NaN when unknown), its ``stamp`` and ``session``."""

    cloud: np.ndarray
    frame: np.ndarray
    pose: np.ndarray
    stamp: float
    session: str = ""


def neighbour_steps(count: int, *, both_sides: bool) -> list[int]:
    """Row steps of the neighbours merged into a keyframe, nearest first: ``-1, -2, …`` for a
    query (it has only its past), ``-1, +1, -2, +2, …`` for a stored keyframe."""
    if both_sides:
        return [sign * (k // 2 + 1) for k, sign in zip(range(count), [-1, 1] * count)]
    return [-(k + 1) for k in range(count)]


def can_merge(centre: KeyframeView, other: KeyframeView, max_gap_s: float,
              reach_m: float = MAX_NEIGHBOUR_DISTANCE_M) -> bool:
    """Whether ``other``'s cloud may be merged into ``centre``'s, at most ``max_gap_s`` (exclusive)
    before or after it and ``reach_m`` away (see the module docstring)."""
    if other.session != centre.session or not abs(other.stamp - centre.stamp) < max_gap_s:
        return False
    if not (np.all(np.isfinite(centre.pose)) and np.all(np.isfinite(other.pose))):
        return False
    return float(np.linalg.norm(other.pose[:3, 3] - centre.pose[:3, 3])) <= reach_m


def merged_cloud(centre: KeyframeView, neighbours: Sequence[KeyframeView], voxel: float,
                 max_gap_s: float, reach_m: float = MAX_NEIGHBOUR_DISTANCE_M) -> np.ndarray:
    """``centre``'s cloud with every mergeable neighbour's (:func:`can_merge` within ``reach_m``), in
    ``centre``'s grid frame, float32 (M, 3).

    Thinned to one point per ``voxel`` on the grid of the centre's *sensor* frame, the grid its
    own cloud was thinned on, with its own points first: they are all kept, and the neighbours
    only fill the voxels it left empty (on another grid the centre would lose its own points)."""
    usable = [n for n in neighbours if can_merge(centre, n, max_gap_s, reach_m) and len(n.cloud)]
    if not usable:
        return np.asarray(centre.cloud, np.float32)
    grid_to_sensor = np.linalg.inv(centre.frame)
    world_to_sensor = np.linalg.inv(centre.pose)
    parts = [_moved(centre.cloud, grid_to_sensor)]
    for other in usable:
        # other grid -> other sensor -> world -> centre sensor
        parts.append(_moved(other.cloud, world_to_sensor @ other.pose @ np.linalg.inv(other.frame)))
    in_sensor = voxel_down_sample(np.ascontiguousarray(np.concatenate(parts)), float(voxel))
    return _moved(in_sensor, centre.frame).astype(np.float32)


def _moved(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    points = np.asarray(points, np.float64)
    return points @ T[:3, :3].T + T[:3, 3]
