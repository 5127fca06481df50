"""The core library can be used without ROS: importing it loads no ROS package."""

import subprocess
import sys

CORE = ["config", "grids.kinds", "features.hog", "features.kernels", "features.featurizer", "model.solver", "model.scoring",
        "model.model_file", "model.builtin", "detection.database", "detection.registration", "detection.detector", "evaluation.baselines.scan_context", "training",
        "evaluation", "simulator"]


def test_core_modules_import_no_ros_package():
    code = (
        "import sys\n"
        + "".join(f"import vbrl_ros.{name}\n" for name in CORE)
        + "ros = sorted(m for m in sys.modules if m.split('.')[0] in "
        "('rclpy', 'sensor_msgs', 'std_msgs', 'nav_msgs', 'geometry_msgs', 'rosidl_runtime_py'))\n"
        "print(','.join(ros))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == ""
