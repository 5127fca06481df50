"""Odometry poses are checked before they move anything; keyframes are spaced by travel or by time;
a keyframe gets the pose at its own stamp."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
from scipy.spatial.transform import Rotation
import pytest

pytest.importorskip("rclpy")
from nav_msgs.msg import Odometry  # noqa: E402

from vbrl_ros.ros.odometry import KeyframeSpacing, OdometryError, PoseHistory, mounting_matrix, pose_matrix  # noqa: E402


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


def turned(x: float, yaw_deg: float) -> np.ndarray:
    T = at(x)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    return T


def test_the_pose_between_two_odometry_stamps_is_interpolated():
    history = PoseHistory()
    history.add(10.0, turned(0.0, 170.0))
    history.add(11.0, turned(2.0, -170.0))  # 20 degrees on, across +-180
    pose, covered = history.at(10.25)
    assert covered
    np.testing.assert_allclose(pose[:3, 3], [0.5, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(pose[:3, :3], turned(0.0, 175.0)[:3, :3], atol=1e-12)
    assert history.at(11.0) == (history.at(11.0)[0], True)


def test_a_keyframe_waits_for_the_odometry_of_its_own_stamp():
    """LiDAR odometry publishes a scan's pose after the scan: the keyframe must not take the
    previous scan's pose."""
    history = PoseHistory()
    history.add(10.0, at(0.0))
    later = threading.Timer(0.05, history.add, (10.2, at(2.0)))
    later.start()
    pose, covered = history.at(10.1, wait_s=2.0)
    later.join()
    assert covered and pose[0, 3] == pytest.approx(1.0)


def test_without_odometry_at_the_stamp_the_newest_pose_is_used_and_said_so():
    history = PoseHistory()
    assert history.at(5.0, wait_s=0.01) == (None, False)
    history.add(10.0, at(3.0))
    start = time.monotonic()
    pose, covered = history.at(10.1, wait_s=0.1)
    assert not covered and pose[0, 3] == 3.0 and time.monotonic() - start >= 0.09
    start = time.monotonic()
    pose, covered = history.at(60.0, wait_s=5.0)  # odometry silent for 50 s: no wait
    assert not covered and time.monotonic() - start < 1.0
    history.add(11.0, at(4.0))
    pose, covered = history.at(9.0)  # older than the history (another time base?): the newest
    assert not covered and pose[0, 3] == 4.0


def test_time_going_back_starts_the_history_afresh_and_old_poses_are_forgotten():
    history = PoseHistory(span_s=10.0)
    for stamp in range(100):
        history.add(float(stamp), at(float(stamp)))
    assert history.at(50.0) == (history.at(50.0)[0], False)  # older than the last 10 s
    history.add(3.0, at(-7.0))  # a bag played again
    pose, covered = history.at(3.0)
    assert covered and pose[0, 3] == -7.0


def test_a_mounting_is_read_as_a_urdf_joint_origin():
    """Fixed-axis roll, then pitch, then yaw (R = Rz Ry Rx), then the offset: a LiDAR 0.5 m ahead of
    base_link, turned to look back, sees base_link's forward axis as its -x."""
    T = mounting_matrix((0.5, 0.0, 0.3, 0.0, 0.0, math.pi))
    np.testing.assert_allclose(T[:3, 3], [0.5, 0.0, 0.3])
    np.testing.assert_allclose(T[:3, :3].T @ [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], atol=1e-12)
    roll, pitch, yaw = 0.1, -0.2, 0.7

    def about(axis: int, angle: float) -> np.ndarray:
        return Rotation.from_rotvec(angle * np.eye(3)[axis]).as_matrix()

    np.testing.assert_allclose(mounting_matrix((0, 0, 0, roll, pitch, yaw))[:3, :3],
                               about(2, yaw) @ about(1, pitch) @ about(0, roll), atol=1e-12)
    np.testing.assert_array_equal(mounting_matrix((0.0,) * 6), np.eye(4))
