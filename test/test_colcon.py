"""The package builds with colcon in a ROS 2 workspace, where `ros2 run` would find it.

ros2cli is not installable from PyPI, so instead of `ros2 run vbrl_ros vbrl_node`
this checks what `ros2 run` relies on: ament_index resolves the package
prefix, and lib/vbrl_ros/vbrl_node exists and runs.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
COLCON = Path(sys.executable).with_name("colcon")


@pytest.mark.skipif(not COLCON.exists(), reason="colcon-core/colcon-ros not installed (test extras)")
def test_colcon_build_installs_executables_where_ros2_run_looks(tmp_path):
    source = tmp_path / "ws" / "src" / "vbrl_ros"
    shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(
        ".venv", ".git", "build", "install", "log", "runs", "*.egg-info", "__pycache__", ".pytest_cache"))
    workspace = source.parents[1]
    result = subprocess.run([str(COLCON), "build"], cwd=workspace, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stdout + result.stderr
    prefix = workspace / "install" / "vbrl_ros"
    for executable in ("vbrl_node", "vbrl"):
        path = prefix / "lib" / "vbrl_ros" / executable
        assert path.is_file() and os.access(path, os.X_OK), executable

    env = {**os.environ, "AMENT_PREFIX_PATH": str(prefix)}
    resolve = ("from ament_index_python.packages import get_package_prefix, get_package_share_directory;"
               "print(get_package_prefix('vbrl_ros')); print(get_package_share_directory('vbrl_ros'))")
    found = subprocess.run([sys.executable, "-c", resolve], env=env, capture_output=True, text=True,
                           timeout=60)
    assert found.returncode == 0, found.stderr
    assert found.stdout.splitlines()[0] == str(prefix)
    share = Path(found.stdout.splitlines()[1])
    assert (share / "package.xml").is_file() and (share / "config" / "vbrl.yaml").is_file()

    # what `ros2 run vbrl_ros vbrl_node --help` executes
    python_path = next((prefix / "lib").glob("python3*/site-packages"))
    env["PYTHONPATH"] = f"{python_path}{os.pathsep}{env.get('PYTHONPATH', '')}"
    ran = subprocess.run([str(prefix / "lib" / "vbrl_ros" / "vbrl_node"), "--help"], env=env,
                         capture_output=True, text=True, timeout=120)
    assert ran.returncode == 0, ran.stderr
    assert "keyframe_distance" in ran.stdout
