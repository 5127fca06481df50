"""What ``vbrl_node`` does before its node exists: ``--help``, the parameter file, rcl's errors in a line.

Standard library only at import: see :mod:`vbrl_ros.ros.node`.
"""

from __future__ import annotations

import os
import re
import textwrap
from pathlib import Path

USAGE = """usage: vbrl_node [-h] [--ros-args [--params-file FILE] [-p NAME:=VALUE] ...]

Online VBRL loop-closure detection: scans in, loop closures out.
Topics: subscribes cloud_topic (sensor_msgs/PointCloud2, sensor-data QoS) and
odom_topic (nav_msgs/Odometry); publishes loop_closure_topic and lio_sam_topic
(std_msgs/Float64MultiArray), markers_topic (visualization_msgs/MarkerArray),
/diagnostics. Services: ~/save_database, ~/clear_database (std_srvs/Trigger).
An unknown parameter name or a bad value stops the start with a message naming it.

parameters (NAME = DEFAULT):
{parameters}"""


def usage() -> str:
    """``vbrl_node --help``: every parameter with its default and what it means."""
    from vbrl_ros.ros.settings import DESCRIPTIONS, NodeSettings, yaml_value  # loads numpy and numba

    entries = []
    for name, default in NodeSettings.defaults().items():
        entries.append(f"  {name} = {yaml_value(default)}")
        entries += textwrap.wrap(DESCRIPTIONS[name], 78, initial_indent=" " * 6, subsequent_indent=" " * 6)
    return USAGE.format(parameters="\n".join(entries))


def params_file_problem(argv: list[str]) -> str | None:
    """What is wrong with a ``--params-file`` of the ROS arguments, in one line, or None.

    rcl reports a missing file as an RCLError traceback that names neither the
    directory a relative path was looked up in nor where the shipped file is.
    """
    in_ros_args = False
    for k, arg in enumerate(argv):
        if arg == "--ros-args":
            in_ros_args = True
        elif arg == "--":
            in_ros_args = False
        elif in_ros_args and arg == "--params-file":
            if k + 1 >= len(argv) or argv[k + 1].startswith("-"):
                return "--params-file needs a file name"
            path = Path(argv[k + 1])
            if path.is_file():
                continue
            where = "" if path.is_absolute() else f" (relative to the current directory {os.getcwd()})"
            problem = "is not a file" if path.exists() else "does not exist"
            shipped = shipped_parameter_file()
            hint = f"; the package's own is {shipped}" if shipped is not None else ""
            return f"--params-file {path} {problem}{where}{hint}"
    return None


def shipped_parameter_file() -> Path | None:
    """config/vbrl.yaml of the installed package (colcon share directory) or of this checkout."""
    candidates = [Path(__file__).resolve().parents[2] / "config" / "vbrl.yaml"]
    try:
        from ament_index_python.packages import get_package_share_directory

        candidates.insert(0, Path(get_package_share_directory("vbrl_ros")) / "config" / "vbrl.yaml")
    except Exception:  # not installed with colcon, or no ament_index: the checkout's copy
        pass
    return next((path for path in candidates if path.is_file()), None)


def rcl_error_line(error: Exception) -> str:
    """rcl's message without its C source locations (", at /project/src/parser.c:271")."""
    text = " ".join(str(error).split())
    return re.sub(r",? at \S+\.c:\d+", "", text)
