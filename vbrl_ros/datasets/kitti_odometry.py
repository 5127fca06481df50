"""A KITTI odometry benchmark sequence as a ScanSource.

Layout of the benchmark (``data_odometry_velodyne`` + ``calib`` + ``poses``)::

    <root>/sequences/NN/velodyne/NNNNNN.bin
    <root>/sequences/NN/calib.txt    # "Tr: 12 numbers" = T_cam0_velo (3x4)
    <root>/sequences/NN/times.txt    # seconds since the sequence start
    <root>/poses/NN.txt              # T_cam0(first)_cam0(i), 3x4 per line; 00-10 only

Poses are converted to the LiDAR frame, T_world_lidar = Tr^-1 . P . Tr, so
the world frame is the LiDAR frame of the first scan. Sequences without a
poses file (11-21) have ``poses = None``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vbrl_ros.datasets.base import ScanSourceError
from vbrl_ros.datasets.kitti_style import BinFolderSource, read_times_txt, scan_files
from vbrl_ros.datasets.poses import read_poses_txt


def read_calib_tr(path: Path) -> np.ndarray:
    """The 4x4 T_cam0_velo from the ``Tr:`` line of a KITTI odometry ``calib.txt``."""
    for line in path.read_text().splitlines():
        key, _, values = line.partition(":")
        if key.strip() == "Tr":
            numbers = np.array(values.split(), dtype=np.float64)
            if numbers.size != 12:
                raise ScanSourceError(f"{path}: Tr has {numbers.size} numbers, expected 12")
            return np.vstack([numbers.reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    raise ScanSourceError(f"{path}: no 'Tr:' line (the velodyne-to-camera calibration)")


def camera_to_lidar_poses(camera_poses: np.ndarray, tr_cam_velo: np.ndarray) -> np.ndarray:
    """T_world_lidar = Tr^-1 . P . Tr for each camera pose P (world = first LiDAR frame)."""
    return np.linalg.inv(tr_cam_velo) @ camera_poses @ tr_cam_velo


def locate_sequence(path: Path, sequence: str | int | None) -> tuple[Path, Path | None]:
    """(sequence folder, poses file or None) from a sequence folder or the dataset root + id."""
    if sequence is not None:
        sequence_id = f"{int(sequence):02d}" if str(sequence).isdigit() else str(sequence)
        folder = path / "sequences" / sequence_id
        if not folder.is_dir():
            available = sorted(p.name for p in (path / "sequences").glob("*") if p.is_dir())
            raise ScanSourceError(f"{path}: no sequence {sequence_id} (sequences: {', '.join(available) or 'none'})")
    elif (path / "sequences").is_dir():
        available = sorted(p.name for p in (path / "sequences").glob("*") if p.is_dir())
        raise ScanSourceError(
            f"{path} is a KITTI odometry root; pass sequence= one of: {', '.join(available) or 'none'}"
        )
    else:
        folder = path
    poses = folder.parent.parent / "poses" / f"{folder.name}.txt"
    return folder, (poses if poses.is_file() else None)


class KittiOdometrySource(BinFolderSource):
    """One KITTI odometry sequence; one small file per scan, so random access is cheap."""

    def __init__(self, path: str | Path, sequence: str | int | None = None) -> None:
        folder, poses_file = locate_sequence(Path(path), sequence)
        super().__init__(f"kitti_{folder.name}")
        self.folder = folder
        velodyne, calib = folder / "velodyne", folder / "calib.txt"
        if not velodyne.is_dir():
            raise ScanSourceError(f"{folder}: no velodyne/ folder of .bin scans")
        self._files = scan_files(velodyne)
        if not self._files:
            raise ScanSourceError(f"{velodyne}: no .bin scans")
        times = folder / "times.txt"
        self._stamps = (
            read_times_txt(times, len(self._files)) if times.exists() else np.arange(len(self._files), dtype=float)
        )
        if poses_file is not None:
            if not calib.is_file():
                raise ScanSourceError(f"{folder}: poses need calib.txt (its Tr) to move them to the LiDAR frame")
            lidar_poses = camera_to_lidar_poses(read_poses_txt(poses_file), read_calib_tr(calib))
            self.set_poses(lidar_poses, origin=str(poses_file))

