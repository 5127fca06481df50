"""KITTI odometry sequences: camera-frame ground truth becomes T_world_lidar = Tr^-1 . P . Tr."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vbrl_ros.datasets import detect_source_kind, open_source
from vbrl_ros.datasets.base import ScanSourceError
from vbrl_ros.datasets.kitti_odometry import KittiOdometrySource, read_calib_tr
from vbrl_ros.datasets.poses import write_poses_txt

# Velodyne -> camera 0 of KITTI sequence 00 (rounded): the axes swap x-forward to z-forward.
TR_CAM_VELO = np.array([[0.000428, -0.999967, -0.008084, -0.011985],
                        [-0.007211, 0.008081, -0.999941, -0.054040],
                        [0.999974, 0.000486, -0.007207, -0.292197],
                        [0.0, 0.0, 0.0, 1.0]])


def lidar_trajectory(count: int) -> np.ndarray:
    """A drive in the LiDAR's own convention: x forward, z up, turning left, starting at identity."""
    poses = np.tile(np.eye(4), (count, 1, 1))
    yaw = np.linspace(0.0, 0.8, count)
    poses[:, :3, :3] = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    poses[:, :3, 3] = np.column_stack([np.arange(count) * 1.2, np.arange(count) ** 2 * 0.05, np.zeros(count)])
    return poses


def make_sequence(root: Path, sequence: str, count: int, with_poses: bool = True) -> np.ndarray:
    folder = root / "sequences" / sequence
    (folder / "velodyne").mkdir(parents=True)
    rng = np.random.default_rng(int(sequence))
    for index in range(count):
        rng.normal(0, 10, size=(100, 4)).astype("<f4").tofile(folder / "velodyne" / f"{index:06d}.bin")
    projection = " ".join(["0.0"] * 12)
    tr_line = " ".join(f"{v:.6e}" for v in TR_CAM_VELO[:3].reshape(-1))
    (folder / "calib.txt").write_text("".join(f"P{i}: {projection}\n" for i in range(4)) + f"Tr: {tr_line}\n")
    np.savetxt(folder / "times.txt", np.arange(count) * 0.103, fmt="%e")
    lidar_poses = lidar_trajectory(count)
    if with_poses:
        (root / "poses").mkdir(exist_ok=True)
        camera_poses = TR_CAM_VELO @ lidar_poses @ np.linalg.inv(TR_CAM_VELO)  # what KITTI publishes
        write_poses_txt(root / "poses" / f"{sequence}.txt", camera_poses)
    return lidar_poses


def test_camera_poses_become_lidar_poses(tmp_path: Path) -> None:
    truth = make_sequence(tmp_path, "03", 8)
    camera = np.loadtxt(tmp_path / "poses" / "03.txt").reshape(-1, 3, 4)
    assert abs(camera[-1, 2, 3]) > 5.0  # KITTI's camera frame: forward motion is along +z
    for source in (KittiOdometrySource(tmp_path / "sequences" / "03"), KittiOdometrySource(tmp_path, sequence=3),
                   open_source(tmp_path, sequence="03"), open_source(tmp_path / "sequences" / "03")):
        assert source.name == "kitti_03" and len(source) == 8
        np.testing.assert_allclose(source.poses, truth, atol=1e-6)
        np.testing.assert_allclose(source.stamps, np.arange(8) * 0.103)
        scan = source[7]
        raw = np.fromfile(tmp_path / "sequences" / "03" / "velodyne" / "000007.bin", dtype="<f4").reshape(-1, 4)
        np.testing.assert_array_equal(scan.points, raw[:, :3])
        np.testing.assert_array_equal(scan.intensity, raw[:, 3])
    assert detect_source_kind(tmp_path / "sequences" / "03") == "kitti_odometry"


def test_sequences_without_ground_truth_and_root_errors(tmp_path: Path) -> None:
    make_sequence(tmp_path, "03", 2)
    make_sequence(tmp_path, "11", 3, with_poses=False)
    assert KittiOdometrySource(tmp_path, sequence=11).poses is None
    with pytest.raises(ScanSourceError, match="pass sequence= one of: 03, 11"):
        open_source(tmp_path)
    with pytest.raises(ScanSourceError, match="no sequence 07 .sequences: 03, 11."):
        KittiOdometrySource(tmp_path, sequence=7)


def test_calibration_errors(tmp_path: Path) -> None:
    make_sequence(tmp_path, "00", 2)
    calib = tmp_path / "sequences" / "00" / "calib.txt"
    np.testing.assert_allclose(read_calib_tr(calib), TR_CAM_VELO, atol=1e-9)
    calib.write_text("P0: 1 2 3\n")
    with pytest.raises(ScanSourceError, match="no 'Tr:' line"):
        KittiOdometrySource(tmp_path, sequence=0)
    calib.write_text("Tr: 1 2 3\n")
    with pytest.raises(ScanSourceError, match="Tr has 3 numbers"):
        KittiOdometrySource(tmp_path, sequence=0)
