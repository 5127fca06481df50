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
from typing import Any, NamedTuple

import numpy as np
from numba import njit

from vbrl_ros.features.blind_wedges import BINS, azimuth_bin, azimuth_bins

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


class Merged(NamedTuple):
    """Points merged into a keyframe's frame: ``keyframe_of`` each point's keyframe (0 its own,
    1 the nearest earlier one merged, 2 the next...), each keyframe's points together."""

    points: np.ndarray  # (n, 3) float32
    keyframe_of: np.ndarray  # (n,) int64
    keyframes: int  # how many earlier keyframes were merged


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
        self._stacked: tuple[np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return len(self._kept)

    def clear(self) -> None:
        self._kept.clear()
        self._stacked = None

    def merged(self, pose: np.ndarray, travelled: float, stamp: float = math.nan,
               own: np.ndarray | None = None) -> Merged:
        """The earlier keyframes' points that describe the place of a keyframe at ``pose``, in its
        frame, nearest keyframe first, after its points ``own`` (keyframe 0) when given. Those
        ``max_age`` or more before ``stamp`` are forgotten (NaN: no limit)."""
        kept = len(self._kept)
        self._kept = deque(k for k in self._kept
                           if within_reach(k, travelled, pose, stamp, self.reach_m, self.max_age))
        if len(self._kept) != kept:
            self._stacked = None
        own = np.zeros((0, 3), np.float32) if own is None else np.ascontiguousarray(own, np.float32)
        to_keyframe = np.linalg.inv(pose)
        chosen = []  # (index into kept, its transform into the keyframe's frame), nearest first
        for i in range(len(self._kept) - 1, -1, -1):
            earlier = self._kept[i].pose
            # the keyframe's position in the earlier one's frame, without inverting a 4x4 per keyframe
            if saw(self._kept[i], earlier[:3, :3].T @ (pose[:3, 3] - earlier[:3, 3])):
                chosen.append((i, to_keyframe @ earlier))
        if not chosen:
            return Merged(own, np.zeros(len(own), np.int64), 0)
        points, starts = self._stacked_points()
        index = np.array([i for i, _ in chosen], np.int64)
        transforms = np.array([T for _, T in chosen], np.float32)
        merged, keyframe_of = _placed(own, points, starts[index], starts[index + 1], transforms,
                                      np.float32(RANGE_M ** 2), MAX_POINTS)
        return Merged(merged, keyframe_of, len(chosen))

    def _stacked_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Every kept keyframe's points in one array (each in its own frame) and where each
        starts (one more: the end); stacked again only when the kept ones change."""
        if self._stacked is None:
            counts = [len(k.points) for k in self._kept]
            starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
            points = (np.concatenate([k.points for k in self._kept]) if self._kept
                      else np.zeros((0, 3), np.float32))
            self._stacked = (np.ascontiguousarray(points, np.float32), starts)
        return self._stacked

    def add(self, xyz: np.ndarray, pose: np.ndarray, travelled: float, stamp: float = math.nan) -> None:
        """Keep ``xyz`` (its own frame) for the keyframes after it, one per ``STEP_M`` of travel."""
        if self._kept and travelled - self._kept[-1].travelled < STEP_M:
            return
        reach = np.zeros(BINS, np.float32)
        if len(xyz):
            np.maximum.at(reach, azimuth_bins(xyz[:, :2]), np.hypot(xyz[:, 0], xyz[:, 1]))
        self._kept.append(_Looked(thinned(xyz), pose, travelled, stamp, reach))
        self._stacked = None


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
    b = azimuth_bin(position[0], position[1])  # thirty calls a keyframe
    farthest = max(kept.reach[(b - 1) % BINS], kept.reach[b], kept.reach[(b + 1) % BINS])
    return bool(farthest >= distance - VISIBLE_SLACK_M)


def thinned(xyz: np.ndarray) -> np.ndarray:
    """One point of ``xyz`` per ``VOXEL_M`` voxel, the first in scan order."""
    if not len(xyz):
        return xyz
    # one int64 key per voxel (21 bits an axis, +-500 km)
    cell = np.clip(np.floor(xyz / VOXEL_M).astype(np.int64) + (1 << 20), 0, (1 << 21) - 1)
    key = (cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2]
    return np.compress(_first_of_each(key), xyz, axis=0)


@njit(cache=True, nogil=True)
def _first_of_each(keys):
    """(n,) bool: the first of each distinct key, by an open-addressing hash set (a sort-based
    unique took a millisecond of each kept keyframe)."""
    size = 1
    while size < 2 * keys.shape[0]:
        size *= 2
    table = np.full(size, -1, np.int64)  # keys are >= 0
    first = np.zeros(keys.shape[0], np.bool_)
    for i in range(keys.shape[0]):
        k = keys[i]
        slot = ((k * 0x5851F42D4C957F2D) >> 29) & (size - 1)  # multiplicative hashing, int64 wraps
        while table[slot] != -1 and table[slot] != k:
            slot = (slot + 1) & (size - 1)
        if table[slot] == -1:
            table[slot] = k
            first[i] = True
    return first


@njit(cache=True, nogil=True)
def _placed(own, points, starts, ends, transforms, range_sq, max_points):
    """``own`` then, for each chosen keyframe (its rows ``starts[k]:ends[k]`` of ``points``), its
    points moved by ``transforms[k]`` within the horizontal range, until ``max_points`` earlier
    points: the last keyframe tops the budget up with every j-th of its points. One pass with no
    per-keyframe arrays: merging thirty earlier clouds was a third of a forward-looking keyframe's
    describe time."""
    n_own = own.shape[0]
    total = 0
    for k in range(starts.shape[0]):
        total += ends[k] - starts[k]
    out = np.empty((n_own + total, 3), np.float32)
    keyframe_of = np.empty(n_own + total, np.int64)
    out[:n_own] = own
    keyframe_of[:n_own] = 0
    at = n_own
    for k in range(starts.shape[0]):
        if at - n_own >= max_points:
            break
        T = transforms[k]
        first = at
        for i in range(starts[k], ends[k]):
            x, y, z = points[i, 0], points[i, 1], points[i, 2]
            px = x * T[0, 0] + y * T[0, 1] + z * T[0, 2] + T[0, 3]
            py = x * T[1, 0] + y * T[1, 1] + z * T[1, 2] + T[1, 3]
            if px * px + py * py > range_sq:
                continue
            out[at, 0] = px
            out[at, 1] = py
            out[at, 2] = x * T[2, 0] + y * T[2, 1] + z * T[2, 2] + T[2, 3]
            keyframe_of[at] = k + 1
            at += 1
        room = max_points - (first - n_own)
        count = at - first
        if count > room:  # every step-th point, in place (it reads ahead of where it writes)
            step = -(-count // room)
            kept = 0
            for j in range(first, at, step):
                out[first + kept] = out[j]
                kept += 1
            at = first + kept
    return out[:at], keyframe_of[:at]
