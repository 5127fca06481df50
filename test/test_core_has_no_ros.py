"""The library outside vbrl_ros/ros/ can be used without ROS: importing it loads no ROS package."""

import subprocess
import sys


def test_modules_outside_ros_import_no_ros_package(package_modules, ros_packages):
    core = [name for name in package_modules if name.split(".")[:2] != ["vbrl_ros", "ros"]]
    assert "vbrl_ros.detection.detector" in core and "vbrl_ros.tools.cli" in core
    code = (
        "import sys\n"
        + "".join(f"import {name}\n" for name in core)
        + f"ros = sorted(m for m in sys.modules if m.split('.')[0] in {tuple(ros_packages)!r})\n"
        "print(','.join(ros))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == ""
