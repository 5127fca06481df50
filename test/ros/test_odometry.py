"""Odometry poses are checked before they move anything; keyframes are spaced by travel or by time."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rclpy")
from nav_msgs.msg import Odometry  # noqa: E402

from vbrl_ros.ros.odometry import KeyframeSpacing, OdometryError, pose_matrix  # noqa: E402


def odometry(position=(0.0, 0.0, 0.0), quaternion=(0.0, 0.0, 0.0, 1.0)) -> Odometry:
    msg = Odometry()
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    p.x, p.y, p.z = position
    q.x, q.y, q.z, q.w = quaternion
    return msg


def test_a_pose_is_the_rotation_and_the_position():
    half = math.sqrt(0.5)
    T = pose_matrix(odometry((1.0, 2.0, 3.0), (0.0, 0.0, half, half)))  # 90 degrees about z
    np.testing.assert_allclose(T, [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], atol=1e-12)


def test_a_slightly_denormalised_quaternion_is_a_rotation():
    T = pose_matrix(odometry(quaternion=(0.0, 0.0, 0.0, 1.004)))  # |q|^2 = 1.008, within tf2's 0.01
    np.testing.assert_allclose(T, np.eye(4), atol=1e-12)


@pytest.mark.parametrize("position, quaternion, reason", [
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), r"orientation \(0.0, 0.0, 0.0, 0.0\) is not a unit quaternion"),
    ((0.0, 0.0, 0.0), (0.0, math.nan, 0.0, 1.0), r"orientation \(0.0, nan, 0.0, 1.0\) is not finite"),
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, math.inf), "is not finite"),
    ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 2.0), r"\|q\|\^2 = 4\)"),
    ((0.0, 0.0, 0.0), (1e-300, 0.0, 0.0, 0.0), "is not a unit quaternion"),
    ((math.nan, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), r"position \(nan, 0.0, 0.0\) is not finite"),
    ((0.0, -math.inf, 0.0), (0.0, 0.0, 0.0, 1.0), "position .* is not finite"),
])
def test_an_unusable_pose_raises_one_line(position, quaternion, reason):
    with pytest.raises(OdometryError, match=reason) as error:
        pose_matrix(odometry(position, quaternion))
    assert "\n" not in str(error.value)


def at(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_keyframes_come_every_distance_of_travel_once_poses_are_known():
    spacing = KeyframeSpacing(distance=1.0, interval=1.0)
    assert spacing.is_keyframe(0.0)  # the first scan always is one
    spacing.mark(0.0)
    assert not spacing.is_keyframe(0.5) and spacing.is_keyframe(1.0)  # no pose yet: by time
    spacing.moved_to(at(0.0))
    spacing.mark(1.0)
    spacing.moved_to(at(0.6))
    assert not spacing.is_keyframe(9.0)  # poses known: by travel, not time
    spacing.moved_to(at(0.1))
    assert spacing.is_keyframe(9.0)  # travel is the path: 0.6 m out and 0.5 m back
    spacing.mark(9.0)
    assert not spacing.is_keyframe(9.5)


def test_a_step_of_1e300_metres_is_still_a_finite_travel():
    spacing = KeyframeSpacing(distance=1.0, interval=1.0)
    spacing.moved_to(at(-1e300))
    spacing.mark(0.0)
    spacing.moved_to(at(1e300))
    assert spacing.is_keyframe(1.0)
    spacing.mark(1.0)
    spacing.moved_to(at(1e300 + 0.5))
    assert not spacing.is_keyframe(2.0)  # travel restarted from 0, not inf or NaN
