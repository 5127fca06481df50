"""A forward-looking keyframe described with the earlier keyframes that looked at where it stands.

Through a 70° field of view two passes in opposite directions see opposite halves of their
surroundings, and a reversed revisit shares almost nothing with the scan it returns to. But a
forward-looking sensor looks ahead at the place it is about to reach: the keyframes of the
last tens of metres saw the walls beside and behind where it now stands, which is what the
other pass looked at. Merged in by odometry, they describe the place all round, and two passes
either way describe the same place.

Only the earlier keyframes that saw through the keyframe's position are merged: the keyframe
lies in a direction where they have a point at least as far away (``VISIBLE_SLACK_M``). Around a
corner, an earlier keyframe looked down another street or corridor, which a pass from the other
side never sees. The earlier keyframes are kept one per ``STEP_M`` of travel and thinned to one
point per ``VOXEL_M`` voxel, so a 60 m trail holds about thirty small clouds. Like every trail
it stops short of the keyframes a query may close a loop with (``Trail.max_age``): a loop closed
through its own trail would be odometry's, not recognition's.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from vbrl_ros.features.blind_wedges import BINS, azimuth_bins

#: One earlier keyframe is kept per this much travel.
STEP_M = 2.0
#: Kept keyframes are thinned to one point per voxel of this size (the height map's tops move by
#: less than a voxel).
VOXEL_M = 0.5
#: An earlier keyframe saw the keyframe's position when, in that direction (its azimuth bin or one
#: beside it), it has a point no nearer than the position less this.
VISIBLE_SLACK_M = 1.0
#: Earlier keyframes nearer than this are merged whatever they saw (the position is in their
#: near field, below the lowest beam).
NEAR_M = 2.0
#: Merged points beyond this horizontal range of the keyframe are left out: the recognition
#: grid reaches 40 m and its bird's-eye image 40 m each way.
RANGE_M = 40.0
#: At most this many points of earlier keyframes are merged, nearest keyframe first.
MAX_POINTS = 150_000


@dataclass(frozen=True)
class _Looked:
    points: np.ndarray  # (n, 3) float32 in its own sensor frame, voxel-thinned
    pose: np.ndarray  # T_world_lidar
    travelled: float  # metres of odometry driven up to it
    stamp: float  # when it was taken
    reach: np.ndarray  # (BINS,) the farthest horizontal range it saw in each azimuth bin


class ForwardTrail:
    """The forward-looking keyframes of one session within ``reach_m`` metres of travel."""

    def __init__(self, reach_m: float, max_age: float = math.inf) -> None:
        self.reach_m = float(reach_m)
        self.max_age = float(max_age)
        self._kept: deque[_Looked] = deque()

    def __len__(self) -> int:
        return len(self._kept)

    def clear(self) -> None:
        self._kept.clear()

    def merged(self, xyz: np.ndarray, pose: np.ndarray, travelled: float,
               stamp: float = math.nan) -> list[np.ndarray]:
        """The earlier keyframes' points that describe ``xyz``'s place, in its frame: one array per
        earlier keyframe that saw its position, nearest first (empty: none did). Those ``max_age``
        or more before ``stamp`` are forgotten (NaN: no limit)."""
        self._kept = deque(k for k in self._kept
                           if within_reach(k, travelled, pose, stamp, self.reach_m, self.max_age))
        to_keyframe = np.linalg.inv(pose)
        parts: list[np.ndarray] = []
        total = 0
        for kept in reversed(self._kept):  # nearest first
            if total >= MAX_POINTS:
                break
            T = to_keyframe @ kept.pose
            if not saw(kept, np.linalg.inv(T)[:3, 3]):
                continue
            points = kept.points @ T[:3, :3].T.astype(np.float32) + T[:3, 3].astype(np.float32)
            points = points[np.einsum("ij,ij->i", points[:, :2], points[:, :2]) <= RANGE_M ** 2]
            room = MAX_POINTS - total
            if len(points) > room:  # the last one tops the budget up with every k-th point
                points = points[::-(-len(points) // room)]
            parts.append(points)
            total += len(points)
        return parts

    def add(self, xyz: np.ndarray, pose: np.ndarray, travelled: float, stamp: float = math.nan) -> None:
        """Keep ``xyz`` (its own frame) for the keyframes after it, one per ``STEP_M`` of travel."""
        if self._kept and travelled - self._kept[-1].travelled < STEP_M:
            return
        reach = np.zeros(BINS, np.float32)
        if len(xyz):
            np.maximum.at(reach, azimuth_bins(xyz[:, :2]), np.hypot(xyz[:, 0], xyz[:, 1]))
        self._kept.append(_Looked(thinned(xyz), pose, travelled, stamp, reach))


def within_reach(earlier: Any, travelled: float, pose: np.ndarray, stamp: float,
                 reach_m: float, max_age: float) -> bool:
    """Whether a trail still holds ``earlier`` (with ``pose``, ``travelled`` and ``stamp``) for a
    keyframe at ``pose``, ``travelled`` and ``stamp``: within ``reach_m`` along the path and in a
    straight line (an odometry reset jumps without travelling), and younger than ``max_age``
    (NaN stamps: no limit)."""
    return (travelled - earlier.travelled <= reach_m
            and float(np.linalg.norm(earlier.pose[:3, 3] - pose[:3, 3])) <= reach_m
            and not stamp - earlier.stamp >= max_age)


def saw(kept: _Looked, position: np.ndarray) -> bool:
    """Whether ``kept`` saw ``position`` (in ``kept``'s frame): it is near, or ``kept`` has a point
    at least that far (less ``VISIBLE_SLACK_M``) in its direction or a direction beside it."""
    distance = float(np.hypot(position[0], position[1]))
    if distance < NEAR_M:
        return True
    b = int(azimuth_bins(position[None, :2])[0])
    farthest = max(kept.reach[(b - 1) % BINS], kept.reach[b], kept.reach[(b + 1) % BINS])
    return bool(farthest >= distance - VISIBLE_SLACK_M)


def thinned(xyz: np.ndarray) -> np.ndarray:
    """One point of ``xyz`` per ``VOXEL_M`` voxel, the first in scan order."""
    if not len(xyz):
        return xyz
    # one int64 key per voxel (21 bits an axis, +-500 km): a 1-D unique is ~10x a row-wise one
    cell = np.clip(np.floor(xyz / VOXEL_M).astype(np.int64) + (1 << 20), 0, (1 << 21) - 1)
    key = (cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2]
    _, first = np.unique(key, return_index=True)
    return xyz[np.sort(first)]
