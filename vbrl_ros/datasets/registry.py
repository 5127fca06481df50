"""The registry of scan-source readers, and ``open_source`` to pick one from a path.

In the spirit of kiss_icp.datasets: a small registry of readers, each
imported only when used.

================  ============================================================
kind              path
================  ============================================================
rosbag            ROS 2 bag directory or its .db3/.mcap, ROS 1 .bag (or a
                  directory of split .bag files)
kitti_style       folder with velodyne/*.bin (+ poses.txt, times.txt)
kitti_odometry    KITTI odometry sequence folder (velodyne/ + calib.txt), or
                  the dataset root with sequence=
================  ============================================================
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from vbrl_ros.datasets.base import ScanSource, ScanSourceError

# kind -> "module:class"
SOURCE_TYPES: dict[str, str] = {
    "rosbag": "vbrl_ros.datasets.rosbag:RosbagSource",
    "kitti_style": "vbrl_ros.datasets.kitti_style:KittiStyleSource",
    "kitti_odometry": "vbrl_ros.datasets.kitti_odometry:KittiOdometrySource",
}
BAG_SUFFIXES = (".bag", ".db3", ".mcap")


def available_sources() -> list[str]:
    return sorted(SOURCE_TYPES)


def source_class(kind: str) -> type[ScanSource]:
    if kind not in SOURCE_TYPES:
        raise ScanSourceError(f"unknown source kind {kind!r}; available: {', '.join(available_sources())}")
    module_name, class_name = SOURCE_TYPES[kind].split(":")
    return getattr(importlib.import_module(module_name), class_name)


def detect_source_kind(path: str | Path) -> str:
    """The registry kind that reads ``path``, from its suffix or folder layout."""
    path = Path(path)
    if not path.exists():
        raise ScanSourceError(f"{path}: no such file or directory")
    if path.is_file():
        if path.suffix in BAG_SUFFIXES:
            return "rosbag"
        raise ScanSourceError(f"{path}: not a bag file ({', '.join(BAG_SUFFIXES)})")
    if (path / "metadata.yaml").is_file() or any(path.glob("*.bag")):
        return "rosbag"
    if (path / "sequences").is_dir() or ((path / "velodyne").is_dir() and (path / "calib.txt").is_file()):
        return "kitti_odometry"
    if (path / "velodyne").is_dir():
        return "kitti_style"
    raise ScanSourceError(f"{path}: not a bag, a KITTI-style folder (velodyne/) or a KITTI odometry sequence")


def open_source(
    path: str | Path,
    *,
    kind: str | None = None,
    topic: str | None = None,
    sequence: str | int | None = None,
    poses: str | None = "auto",
    progress: bool = True,
    **kiss_icp_options: Any,
) -> ScanSource:
    """Open ``path`` as a ScanSource with poses attached per the ``poses`` spec.

    ``kind`` overrides detection. ``topic`` (bags) selects the PointCloud2
    topic; ``sequence`` (KITTI odometry root) the sequence. ``poses``:
    "auto" | "none" | "kiss-icp" | "odom:/topic" | "pose:/topic" |
    "tf:parent:child" | "file:/path/poses.txt" (see :mod:`vbrl_ros.datasets.poses`).
    ``kiss_icp_options`` (max_range, min_range, voxel_size, config) and
    ``progress`` apply to "kiss-icp".
    """
    from vbrl_ros.datasets.poses import resolve_poses

    kind = kind or ("kitti_odometry" if sequence is not None else detect_source_kind(path))
    if topic is not None and kind != "rosbag":
        raise ScanSourceError(f"topic= applies to bags only; {path} is {kind}")
    if sequence is not None and kind != "kitti_odometry":
        raise ScanSourceError(f"sequence= applies to KITTI odometry only; {path} is {kind}")
    if kiss_icp_options and poses != "kiss-icp":
        raise ScanSourceError(f"{', '.join(kiss_icp_options)} apply to poses='kiss-icp' only")
    cls = source_class(kind)
    if kind == "rosbag":
        source = cls(path, topic=topic)
    elif kind == "kitti_odometry":
        source = cls(path, sequence=sequence)
    else:
        source = cls(path)
    try:
        source.set_poses(resolve_poses(source, poses, progress=progress, **kiss_icp_options),
                         origin=f"poses={poses!r}")
    except BaseException:
        source.close()
        raise
    return source
