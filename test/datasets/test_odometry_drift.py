"""Drifting odometry: steps re-integrated with a heading random walk and a scale error."""

import numpy as np
import pytest

from vbrl_ros.datasets.odometry_drift import SCALE_ERROR, checked_drift, drifted_poses


def square_loop(side: float = 100.0, step: float = 2.0) -> np.ndarray:
    """Poses driving a square and back to the start, heading along the path."""
    poses, heading, position = [], 0.0, np.zeros(3)
    for _ in range(4):
        for _ in range(int(side / step)):
            pose = np.eye(4)
            pose[:2, :2] = [[np.cos(heading), -np.sin(heading)], [np.sin(heading), np.cos(heading)]]
            pose[:3, 3] = position
            poses.append(pose)
            position = position + step * np.array([np.cos(heading), np.sin(heading), 0.0])
        heading += np.pi / 2
    return np.array(poses)


def test_without_drift_only_the_scale_error_stretches_the_path():
    poses = square_loop()
    got = drifted_poses(poses, 0.0)
    np.testing.assert_array_equal(got, poses)  # 0: the poses as recorded
    stretched = drifted_poses(poses, 1e-12)
    np.testing.assert_allclose(stretched[:, :3, 3], poses[:, :3, 3] * (1 + SCALE_ERROR), atol=1e-6)


def test_drift_grows_along_the_path_and_keeps_the_steps_locally_right():
    poses = square_loop()
    drifted = drifted_poses(poses, 2.0, seed=3)
    error = np.linalg.norm(drifted[:, :3, 3] - poses[:, :3, 3], axis=1)
    assert error[0] == 0.0 and error[-1] > 1.0  # 400 m on: metres off
    assert error[: len(error) // 8].max() < error[len(error) // 2:].max()
    steps = np.linalg.norm(np.diff(drifted[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, 2.0 * (1 + SCALE_ERROR))  # each step's length as odometry measured it
    np.testing.assert_allclose(drifted[:, 2, 3], 0.0, atol=1e-9)  # the heading error turns about gravity
    np.testing.assert_array_equal(drifted_poses(poses, 2.0, seed=3), drifted)  # repeatable


@pytest.mark.parametrize("bad", [-1.0, float("nan"), 90.0])
def test_a_drift_out_of_range_is_refused(bad):
    with pytest.raises(ValueError, match="--drift"):
        checked_drift(bad, "--drift")
