"""Recorded scans turned as a sensor held tilted would give them: the world stays where it was."""

import numpy as np
import pytest

from vbrl_ros.datasets.mount_tilt import checked_tilt, mount_rotation, tilted_points, tilted_poses


def test_tilted_points_and_poses_put_every_point_where_it_was_in_the_world():
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-20, 20, (500, 3)), rng.uniform(0, 255, 500)]).astype(np.float32)
    yaw = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = yaw, [5.0, -3.0, 1.2]
    mount = mount_rotation(10.0, 35.0)
    turned, turned_pose = tilted_points(points, mount), tilted_poses(pose[None], mount)[0]
    assert turned.dtype == np.float32 and turned.shape == points.shape
    np.testing.assert_array_equal(turned[:, 3], points[:, 3])  # intensity kept
    assert np.abs(turned[:, :3] - points[:, :3]).max() > 1.0  # the frame did turn
    world = points[:, :3].astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    np.testing.assert_allclose(turned[:, :3].astype(np.float64) @ turned_pose[:3, :3].T + turned_pose[:3, 3], world,
                               atol=1e-4)
    np.testing.assert_array_equal(turned_pose[:3, 3], pose[:3, 3])


def test_positive_pitch_tips_the_front_down():
    """Pitched down by the angle under which a level sensor sees a point on the ground ahead, the
    sensor's x axis points straight at that point (the simulator's --tilt convention)."""
    ground_ahead = np.array([[10.0, 0.0, -1.5]])
    pitched = tilted_points(ground_ahead, mount_rotation(0.0, 8.53))  # atan(1.5 / 10) degrees
    assert abs(pitched[0, 2]) < 1e-3 and pitched[0, 0] > 10.0


@pytest.mark.parametrize("bad", [(0.0, 46.0), (-50.0, 0.0), (float("nan"), 0.0), (1.0,), ("a", "b")])
def test_a_tilt_beyond_the_mount_limit_is_refused_in_one_line(bad):
    with pytest.raises(ValueError, match=r"^--mount-tilt must be \(roll, pitch\) in \[-45, 45\] degrees"):
        checked_tilt(bad, "--mount-tilt")
    assert checked_tilt((-45, 45.0), "--mount-tilt") == (-45.0, 45.0)
