"""Odometry for the node: poses from ``nav_msgs/Odometry``, checked, keyframe spacing by travel,
and the pose at a cloud's own stamp.

A pose the node cannot use (a NaN or infinite component, a quaternion that is
not a rotation) raises :class:`OdometryError`; the node counts and skips that
message, so one bad message neither stops the node nor poisons the travel
that spaces later keyframes.
"""

from __future__ import annotations

import bisect
import math
import threading
from collections import deque

import numpy as np
from nav_msgs.msg import Odometry
from scipy.spatial.transform import Rotation

#: How far |q|^2 may be from 1, as tf2 allows before it refuses a transform.
QUATERNION_TOLERANCE = 0.01


class OdometryError(ValueError):
    """An odometry message whose pose cannot be used; the message says why in one line."""


def pose_matrix(odom: Odometry) -> np.ndarray:
    """T_world_lidar (4x4) of an odometry message; :class:`OdometryError` when it is not a pose."""
    p, q = odom.pose.pose.position, odom.pose.pose.orientation
    position, quaternion = (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)
    if not all(math.isfinite(v) for v in position):
        raise OdometryError(f"position ({', '.join(map(str, position))}) is not finite")
    if not all(math.isfinite(v) for v in quaternion):
        raise OdometryError(f"orientation ({', '.join(map(str, quaternion))}) is not finite")
    squared_norm = math.fsum(v * v for v in quaternion)
    if abs(squared_norm - 1.0) > QUATERNION_TOLERANCE:
        raise OdometryError(f"orientation ({', '.join(map(str, quaternion))}) is not a unit quaternion "
                            f"(|q|^2 = {squared_norm:.3g})")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(quaternion).as_matrix()
    T[:3, 3] = position
    return T


def mounting_matrix(pose: tuple[float, ...]) -> np.ndarray:
    """4x4 T_child_lidar of ``[x, y, z, roll, pitch, yaw]`` (metres, radians; fixed-axis roll, then
    pitch, then yaw, as a URDF joint's origin): odometry's pose times it is the LiDAR's."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", pose[3:]).as_matrix()
    T[:3, 3] = pose[:3]
    return T


class KeyframeSpacing:
    """Decides which scans become keyframes: every ``distance`` metres of odometry travel, or,
    while no pose is known (no odometry yet, or none at the last keyframe), every ``interval`` s."""

    def __init__(self, distance: float, interval: float) -> None:
        self.distance, self.interval = distance, interval
        self.latest_pose: np.ndarray | None = None
        self._last_keyframe: tuple[float, np.ndarray | None] | None = None  # (stamp, pose)
        self._travel = 0.0

    def moved_to(self, pose: np.ndarray) -> None:
        """A new (checked) odometry pose: travel grows by the step from the previous one."""
        if self.latest_pose is not None:
            # math.dist scales, so even steps near 1e300 m stay finite
            self._travel += math.dist(pose[:3, 3], self.latest_pose[:3, 3])
        self.latest_pose = pose

    def is_keyframe(self, stamp: float) -> bool:
        last = self._last_keyframe
        if last is None:
            return True
        if self.latest_pose is not None and last[1] is not None:
            return self._travel >= self.distance
        return stamp - last[0] >= self.interval or stamp < last[0]

    def mark(self, stamp: float) -> None:
        """A valid scan became a keyframe: spacing now counts from it."""
        self._last_keyframe = (stamp, self.latest_pose)
        self._travel = 0.0


class PoseHistory:
    """The last ``span_s`` seconds of odometry, by stamp: the pose at a cloud's stamp, interpolated.

    A LiDAR odometry publishes a scan's pose *after* the scan, so when a keyframe's cloud
    arrives the newest pose is usually the previous scan's, up to a metre behind at speed:
    submaps merged with it would be smeared. :meth:`at` waits (briefly) for odometry to reach
    the stamp, then interpolates between the poses around it. Thread-safe: odometry is added on
    the executor's thread and read on the worker's.
    """

    def __init__(self, span_s: float = 10.0) -> None:
        self.span_s = float(span_s)
        self._stamps: deque[float] = deque()
        self._poses: deque[np.ndarray] = deque()
        self._changed = threading.Condition()

    def add(self, stamp: float, pose: np.ndarray) -> None:
        """A checked pose. A stamp older than the newest (time jumped back: a bag started again)
        starts the history afresh; one equal to it replaces it."""
        with self._changed:
            if self._stamps and stamp < self._stamps[-1]:
                self._stamps.clear(), self._poses.clear()
            elif self._stamps and stamp == self._stamps[-1]:
                self._stamps.pop(), self._poses.pop()
            self._stamps.append(float(stamp))
            self._poses.append(pose)
            while self._stamps[0] < stamp - self.span_s:
                self._stamps.popleft(), self._poses.popleft()
            self._changed.notify_all()

    def at(self, stamp: float, wait_s: float = 0.0) -> tuple[np.ndarray | None, bool]:
        """(T_world_lidar at ``stamp``, whether odometry covered it). Waits up to ``wait_s`` for a pose
        at or after ``stamp`` (not when odometry has been silent for longer than ``wait_s`` of stamps
        before it); without one, or for a stamp older than the history, the newest pose, not
        covered. (None, False) without any pose."""
        with self._changed:
            if self._stamps and self._stamps[-1] >= stamp - max(wait_s, 1.0):
                self._changed.wait_for(lambda: bool(self._stamps) and self._stamps[-1] >= stamp, wait_s)
            if not self._stamps:
                return None, False
            stamps, poses = list(self._stamps), list(self._poses)
        if stamp >= stamps[-1]:
            return poses[-1], stamp == stamps[-1]
        after = bisect.bisect_right(stamps, stamp)
        if after == 0:  # older than the whole history: another time base, or a cloud very late
            return poses[-1], False
        t0, t1 = stamps[after - 1], stamps[after]
        return interpolated_pose(poses[after - 1], poses[after], (stamp - t0) / (t1 - t0)), True


def interpolated_pose(A: np.ndarray, B: np.ndarray, fraction: float) -> np.ndarray:
    """The pose ``fraction`` of the way from ``A`` to ``B``: positions linearly, rotations along
    the shortest arc."""
    T = np.eye(4)
    turn = Rotation.from_matrix(A[:3, :3].T @ B[:3, :3]).as_rotvec()
    T[:3, :3] = A[:3, :3] @ Rotation.from_rotvec(fraction * turn).as_matrix()
    T[:3, 3] = (1.0 - fraction) * A[:3, 3] + fraction * B[:3, 3]
    return T
