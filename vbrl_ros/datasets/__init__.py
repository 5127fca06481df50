"""Scan sources behind one interface (``ScanSource``), and ``open_source`` to pick one from a path.

:mod:`.registry` (the readers by kind, and ``open_source``), :mod:`.base`
(``Scan``, ``ScanSource``), :mod:`.rosbag`, :mod:`.kitti_style`,
:mod:`.kitti_odometry` (the readers), :mod:`.poses` (per-scan poses from the
data, a file or KISS-ICP), :mod:`.keyframe_selection`.
"""

from vbrl_ros.datasets.base import Scan, ScanSource, ScanSourceError
from vbrl_ros.datasets.registry import SOURCE_TYPES, available_sources, detect_source_kind, open_source

__all__ = ["Scan", "ScanSource", "ScanSourceError", "SOURCE_TYPES", "available_sources", "detect_source_kind",
           "open_source"]
