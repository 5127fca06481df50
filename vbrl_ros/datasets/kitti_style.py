"""KITTI-style recording folders (docs/design.md §3): read them as a ScanSource, and write them.

Layout: ``velodyne/NNNNNN.bin`` (float32 little-endian, N x 4: x, y, z,
intensity, sensor frame), optional ``poses.txt`` (one line per scan, 12
numbers: row-major 3x4 T_world_lidar), optional ``times.txt`` (seconds, one
per scan). Without ``times.txt`` a scan's stamp is its index (in seconds).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterable

import numpy as np
from tqdm import tqdm

from vbrl_ros.datasets.base import Scan, ScanSource, ScanSourceError
from vbrl_ros.datasets.poses import read_poses_txt, write_poses_txt
from vbrl_ros.io.pointcloud2 import returns_mask


def read_kitti_bin(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read one ``.bin`` scan: (points (N, 3) float64, intensity (N,) float64), returns only
    (:func:`~vbrl_ros.io.pointcloud2.returns_mask`: finite, not the no-return origin)."""
    raw = np.fromfile(path, dtype="<f4")
    if raw.size % 4:
        raise ScanSourceError(f"{path}: {raw.size * 4} bytes is not a whole number of 16-byte x,y,z,i points")
    values = raw.reshape(-1, 4).astype(np.float64)
    values = values[returns_mask(values)]
    return np.ascontiguousarray(values[:, :3]), np.ascontiguousarray(values[:, 3])


def scan_files(velodyne: Path) -> list[Path]:
    """The ``.bin`` files of a velodyne folder in numeric order (000010 after 000009)."""
    files = [p for p in velodyne.iterdir() if p.suffix == ".bin" and p.is_file()]
    return sorted(files, key=lambda p: (int(p.stem), p.stem) if p.stem.isdigit() else (float("inf"), p.stem))


def read_times_txt(path: Path, count: int) -> np.ndarray:
    try:
        times = np.loadtxt(path, dtype=np.float64, ndmin=1).reshape(-1)
    except ValueError as error:
        raise ScanSourceError(f"{path}: not one number per line ({error})") from None
    if len(times) != count:
        raise ScanSourceError(f"{path}: {len(times)} stamps for {count} scans")
    return times


class BinFolderSource(ScanSource):
    """A source whose scans are ``self._files`` (KITTI .bin) stamped by ``self._stamps``."""

    _files: list[Path]
    _stamps: np.ndarray

    def __len__(self) -> int:
        return len(self._files)

    @property
    def stamps(self) -> np.ndarray:
        return self._stamps

    def read_scan(self, index: int) -> Scan:
        points, intensity = read_kitti_bin(self._files[index])
        return Scan(points, intensity, float(self._stamps[index]), index)


class KittiStyleSource(BinFolderSource):
    """A KITTI-style folder. Every access reads one small file: random access is as cheap as iteration."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        super().__init__(self.folder.name)
        velodyne = self.folder / "velodyne"
        if not velodyne.is_dir():
            raise ScanSourceError(f"{self.folder}: no velodyne/ folder of .bin scans")
        self._files = scan_files(velodyne)
        if not self._files:
            raise ScanSourceError(f"{velodyne}: no .bin scans")
        times = self.folder / "times.txt"
        self._stamps = (
            read_times_txt(times, len(self._files)) if times.exists() else np.arange(len(self._files), dtype=float)
        )
        poses = self.folder / "poses.txt"
        if poses.exists():
            self.set_poses(read_poses_txt(poses), origin="poses.txt")



def _scan_rows(scan: np.ndarray | Scan, index: int) -> np.ndarray:
    """(N, 4) float32 x, y, z, intensity from an (N, 4) or (N, 3) array (intensity 0) or a Scan."""
    if isinstance(scan, Scan):
        intensity = scan.intensity if scan.intensity is not None else np.zeros(len(scan.points))
        scan = np.column_stack([scan.points, intensity])
    scan = np.asarray(scan)
    if scan.ndim != 2 or scan.shape[1] not in (3, 4):
        raise ValueError(f"scan {index} has shape {scan.shape}, expected (N, 4) or (N, 3)")
    if scan.shape[1] == 3:
        scan = np.column_stack([scan, np.zeros(len(scan))])
    return np.ascontiguousarray(scan, dtype="<f4")


def write_kitti_style(
    folder: str | Path,
    scans: Iterable[np.ndarray | Scan],
    poses: np.ndarray | None,
    stamps: np.ndarray | None = None,
    *,
    progress: bool = False,
) -> Path:
    """Write scans (+ poses.txt, + times.txt when ``stamps`` given) as a KITTI-style folder.

    ``scans`` may be a generator of (N, 4)/(N, 3) arrays or Scans; only one is
    held at a time. The folder is built beside ``folder`` and renamed into
    place at the end, so ``folder`` ends up complete or untouched; it must not
    exist or be an empty directory. Scan, pose and stamp counts must agree.
    """
    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise FileExistsError(f"{folder} exists and is not an empty directory; not overwriting")
    if poses is not None:
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ValueError(f"poses must have shape (n, 4, 4), got {poses.shape}")
    if stamps is not None:
        stamps = np.asarray(stamps, dtype=np.float64).reshape(-1)
    expected = len(poses) if poses is not None else (len(stamps) if stamps is not None else None)
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".partial", dir=folder.parent))
    staging.chmod(0o755)  # mkdtemp makes it private; the result is an ordinary data folder
    try:
        (staging / "velodyne").mkdir()
        count = 0
        for index, scan in enumerate(tqdm(scans, total=expected, desc=f"writing {folder.name}", unit="scan",
                                          disable=not progress)):
            _scan_rows(scan, index).tofile(staging / "velodyne" / f"{index:06d}.bin")
            count += 1
        for label, values in (("poses", poses), ("stamps", stamps)):
            if values is not None and len(values) != count:
                raise ValueError(f"got {count} scans but {len(values)} {label}")
        if poses is not None:
            write_poses_txt(staging / "poses.txt", poses)
        if stamps is not None:
            np.savetxt(staging / "times.txt", stamps, fmt="%.9f")
        if folder.exists():
            folder.rmdir()  # empty, checked above; os.replace needs it gone or empty
        os.replace(staging, folder)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return folder
