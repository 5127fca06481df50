"""vbrl_node over real DDS stores each keyframe with the odometry pose at the cloud's own stamp,
carries a base_link odometry over to the LiDAR mounted on it, and says so when odometry moves
another frame than the clouds' with no mounting given."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

from vbrl_ros.ros.message_conversion import to_ros_msg  # noqa: E402
from vbrl_ros.ros.testing import MessageCollector, diagnostics_values, isolated_ros_env, ros_context  # noqa: E402


def cloud(stamp: float) -> PointCloud2:
    rng = np.random.default_rng(int(stamp))
    points = np.concatenate([rng.uniform(-30, 30, (20000, 2)), rng.uniform(-2, 4, (20000, 1))], axis=1)
    return to_ros_msg(points.astype(np.float32), ["x", "y", "z"], stamp=stamp, frame_id="lidar")


def odometry(stamp: float, x: float, child_frame: str = "lidar") -> Odometry:
    msg = Odometry()
    msg.child_frame_id = child_frame
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(stamp), round((stamp % 1) * 1e9)
    msg.pose.pose.position.x = x
    msg.pose.pose.orientation.w = 1.0
    return msg


def stored_poses(path: Path) -> np.ndarray:
    from vbrl_ros.detection.database import KeyframeDatabase
    from vbrl_ros.model.builtin import load_default_model
    from vbrl_ros.ros.settings import NodeSettings

    model = load_default_model()
    return KeyframeDatabase.load(path, model.scorer(prune=NodeSettings().weight_prune), model.identity()).poses


def stored_positions(path: Path) -> np.ndarray:
    return stored_poses(path)[:, :3, 3]


def values(collector: MessageCollector) -> dict:
    return diagnostics_values(collector.messages["/diagnostics"][-1])


def run_node(env: dict, *params: str) -> subprocess.Popen:
    args = [a for p in ("odom_topic:=/odom", "diagnostics_period:=0.2", *params) for a in ("-p", p)]
    return subprocess.Popen([sys.executable, "-m", "vbrl_ros.ros.node", "--ros-args", *args],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


@dataclass
class OdometrySession:
    """A probe publishing clouds and odometry to a running vbrl_node; its output once it stopped."""

    collector: MessageCollector
    clouds: Any
    odom: Any
    output: str = ""
    returncode: int | None = None


@contextmanager
def odometry_session(*params: str) -> Iterator[OdometrySession]:
    """vbrl_node (``params`` as :func:`run_node`'s) on its own domain, up and subscribed to the
    probe's clouds and odometry; stopped with SIGTERM on leaving."""
    with ros_context() as context:
        env = isolated_ros_env(context.get_domain_id())
        probe = rclpy.create_node("probe", context=context)
        session = OdometrySession(MessageCollector(probe, {"/diagnostics": DiagnosticArray}),
                                  probe.create_publisher(PointCloud2, "/points", 10),
                                  probe.create_publisher(Odometry, "/odom", 50))
        node = run_node(env, *params)
        try:
            assert session.collector.wait_for({"/diagnostics": 1}, timeout=30), "node did not come up"
            assert session.collector.spin_until(lambda: session.odom.get_subscription_count() > 0
                                                and session.clouds.get_subscription_count() > 0, 20)
            yield session
        finally:
            node.send_signal(signal.SIGTERM)
            session.output, _ = node.communicate(timeout=60)
            session.returncode = node.returncode
        probe.destroy_node()


def test_a_keyframe_is_stored_with_the_pose_at_its_stamp_even_when_odometry_comes_after_it(tmp_path):
    """As from a LiDAR odometry: each scan's pose is published just after the scan. A keyframe stored
    with the newest pose instead would sit a scan's travel behind, and submaps merged by it smear."""
    database = tmp_path / "keyframes.npz"
    with odometry_session(f"database_path:={database}", "save_every:=0") as session:
        collector, clouds, odom = session.collector, session.clouds, session.odom
        odom.publish(odometry(10.0, 0.0))
        assert collector.spin_until(lambda: values(collector)["odometry_received"] >= 1, 20)
        for k, stamp in enumerate((10.5, 12.5, 14.5)):  # odometry at 2 m/s, once a second
            clouds.publish(cloud(stamp))
            odom.publish(odometry(stamp + 0.5, 2.0 * (stamp + 0.5 - 10.0)))
            assert collector.spin_until(lambda: values(collector)["keyframes_processed"] >= k + 1, 30), \
                values(collector)
            odom.publish(odometry(stamp + 1.5, 2.0 * (stamp + 1.5 - 10.0)))
        collector.spin_until(lambda: False, 1.0)
        assert values(collector)["late_odometry"] == 0
    assert session.returncode == 0, session.output
    assert "odometry moves frame" not in session.output  # odometry of the LiDAR's own frame
    # halfway between the poses around each stamp; the newest pose at arrival was 1 m behind
    np.testing.assert_allclose(stored_positions(database), [[1.0, 0, 0], [5.0, 0, 0], [9.0, 0, 0]], atol=1e-6)


def base_link_run(*params: str) -> str:
    """Three keyframes with odometry of base_link, 2 m apart; the node's output."""
    with odometry_session(*params) as session:
        collector = session.collector
        for k in range(3):
            session.odom.publish(odometry(10.0 + k, 2.0 * k, child_frame="base_link"))
            assert collector.spin_until(lambda: values(collector)["odometry_received"] >= k + 1, 20)
            session.clouds.publish(cloud(10.0 + k))
            assert collector.spin_until(lambda: values(collector)["keyframes_processed"] >= k + 1, 30), \
                values(collector)
    assert session.returncode == 0, session.output
    return session.output


def test_odometry_of_another_frame_than_the_clouds_is_said_once():
    output = base_link_run()
    assert output.count("odometry moves frame 'base_link', the clouds are in 'lidar': submap_keyframes take "
                        "odometry as the LiDAR's own motion; set odometry_lidar_pose") == 1, output


def test_odometry_of_base_link_is_carried_over_to_a_lidar_mounted_on_it(tmp_path):
    """A LiDAR 0.5 m ahead of base_link and 0.3 m up, turned to look back: the keyframes are stored
    with the LiDAR's poses, and nothing is said."""
    database = tmp_path / "keyframes.npz"
    output = base_link_run(f"database_path:={database}", "save_every:=0",
                           f"odometry_lidar_pose:=[0.5, 0.0, 0.3, 0.0, 0.0, {np.pi!r}]")
    assert "odometry moves frame" not in output
    poses = stored_poses(database)
    np.testing.assert_allclose(poses[:, :3, 3], [[0.5, 0, 0.3], [2.5, 0, 0.3], [4.5, 0, 0.3]], atol=1e-9)
    np.testing.assert_allclose(poses[:, :3, :3], np.broadcast_to(np.diag([-1.0, -1.0, 1.0]), (3, 3, 3)), atol=1e-9)
