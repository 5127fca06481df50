"""Odometry for the node: poses from ``nav_msgs/Odometry``, checked, and keyframe spacing by travel.

A pose the node cannot use (a NaN or infinite component, a quaternion that is
not a rotation) raises :class:`OdometryError`; the node counts and skips that
message, so one bad message neither stops the node nor poisons the travel
that spaces later keyframes.
"""

from __future__ import annotations

import math

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
