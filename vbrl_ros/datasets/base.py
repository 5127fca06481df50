"""The one interface every scan source (bag, KITTI-style folder, KITTI odometry) offers."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Iterator

import numpy as np


class ScanSourceError(ValueError):
    """A scan source cannot be opened or read as asked (bad path, topic, layout, index)."""


@dataclass(frozen=True)
class Scan:
    """One LiDAR scan in the sensor frame.

    points: (N, 3) float64, finite rows only. intensity: (N,) float64 or None
    when the source has none. stamp: seconds (Unix time for recordings).
    index: position of the scan in its source.
    """

    points: np.ndarray
    intensity: np.ndarray | None
    stamp: float
    index: int


def validate_poses(poses: np.ndarray | None, count: int, origin: str) -> np.ndarray | None:
    """Return poses as (count, 4, 4) float64 or raise ScanSourceError naming ``origin``.

    Rows may be NaN (a scan outside the pose time range); anything else must
    be a proper transform with last row 0 0 0 1.
    """
    if poses is None:
        return None
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (count, 4, 4):
        raise ScanSourceError(f"{origin}: expected {count} poses of shape (4, 4), got array of shape {poses.shape}")
    known = ~np.isnan(poses).any(axis=(1, 2))
    if not np.isfinite(poses[known]).all() or not np.allclose(poses[known, 3], [0.0, 0.0, 0.0, 1.0]):
        raise ScanSourceError(f"{origin}: poses must be finite 4x4 transforms with last row 0 0 0 1")
    return poses


class ScanSource(ABC):
    """A finite, indexable sequence of scans with stamps and optional poses.

    ``src[i]`` reads scan i lazily (negative indices count from the end);
    ``iter(src)`` yields every scan in order and may be cheaper than indexing
    (see each reader). ``src.poses`` are (n, 4, 4) T_world_lidar or None;
    a pose row is NaN where the pose is unknown for that scan.
    """

    name: str

    def __init__(self, name: str) -> None:
        self.name = name
        self._poses: np.ndarray | None = None

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def read_scan(self, index: int) -> Scan:
        """Read scan ``index`` (0 <= index < len(self))."""

    @property
    @abstractmethod
    def stamps(self) -> np.ndarray:
        """(n,) float64 seconds, one per scan."""

    @property
    def poses(self) -> np.ndarray | None:
        return self._poses

    def set_poses(self, poses: np.ndarray | None, origin: str = "poses") -> None:
        """Attach per-scan poses T_world_lidar (validated) or None."""
        self._poses = validate_poses(poses, len(self), f"{self.name}: {origin}")

    def __getitem__(self, index: int) -> Scan:
        if isinstance(index, slice) or not isinstance(index, (int, np.integer)):
            raise TypeError(f"scan index must be an integer, got {type(index).__name__}")
        count = len(self)
        position = int(index) + count if index < 0 else int(index)
        if not 0 <= position < count:
            raise IndexError(f"{self.name}: scan index {index} out of range for {count} scans")
        return self.read_scan(position)

    def __iter__(self) -> Iterator[Scan]:
        for index in range(len(self)):
            yield self.read_scan(index)

    def close(self) -> None:
        """Release open files (a no-op for sources that hold none)."""

    def __enter__(self) -> "ScanSource":
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, scans={len(self)}, poses={self.poses is not None})"
