"""vbrl_node under concurrent load over real DDS: every thread busy at once, nothing shared unguarded.

Odometry and clouds arrive on the executor thread, the worker turns nearly every
cloud into a keyframe with loop closures (no recency window, each keyframe a
revisit of identical earlier ones), verified in the node's verification process
or not, and the diagnostics timer
rebuilds every keyframe's marker and loop edge ten times a second. The node runs
in this process so that the test can shrink the interpreter's thread switch
interval: an interleaving that takes minutes at the default 5 ms (the worker
adding loop edges while the timer reads them) then comes within seconds.
"""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

from vbrl_ros.ros.detector_node import VbrlNode  # noqa: E402
from vbrl_ros.ros.message_conversion import to_ros_msg  # noqa: E402
from vbrl_ros.ros.testing import MessageCollector, diagnostics_values, ros_context  # noqa: E402

PARAMS = {"odom_topic": "/odom", "keyframe_distance": 0.5, "keyframe_interval": 0.001, "diagnostics_period": 0.1,
          "verify": False, "exclude_recent_s": 0.0, "distance_threshold": 1000.0, "top_k": 20, "max_closures": 20,
          "save_every": 0,
          # the same four scans come back while odometry drives straight on: no place is revisited by
          # odometry, so its gate is off for this load
          "odometry_drift": 0.0}
SECONDS = 8.0


def place(seed: int) -> np.ndarray:
    """A small scan (fast to describe, so keyframes and loop edges pile up quickly)."""
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-30, 30, (1500, 2)), rng.uniform(-2, 4, 1500)].astype(np.float32)


def odometry(x: float) -> Odometry:
    msg = Odometry()
    msg.pose.pose.position.x = x
    msg.pose.pose.orientation.w = 1.0
    return msg


@pytest.fixture
def fast_thread_switches():
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-5)
    yield
    sys.setswitchinterval(interval)


@pytest.mark.parametrize("verify", [False, True])
def test_odometry_clouds_closures_and_fast_diagnostics_together(fast_thread_switches, verify):
    scans = [place(seed) for seed in range(4)]  # revisited over and over: closures at every keyframe
    failures: list[BaseException] = []
    with ros_context() as context:
        overrides = [Parameter(name, value=value) for name, value in {**PARAMS, "verify": verify}.items()]
        node = VbrlNode(context=context, parameter_overrides=overrides)
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)

        def spin() -> None:
            try:
                while context.ok() and not failures and not stop.is_set():
                    executor.spin_once(timeout_sec=0.05)
            except BaseException as error:  # what rclpy.spin would raise in vbrl_node: the node dies
                failures.append(error)

        stop = threading.Event()
        spinner = threading.Thread(target=spin)
        spinner.start()
        probe = rclpy.create_node("stress", context=context)
        collector = MessageCollector(probe, {"/diagnostics": DiagnosticArray, "/vbrl_node/loop_closures":
                                             Float64MultiArray, "/vbrl_node/markers": MarkerArray})
        clouds = probe.create_publisher(PointCloud2, "/points", 10)
        odom = probe.create_publisher(Odometry, "/odom", 10)
        try:
            assert collector.spin_until(lambda: clouds.get_subscription_count() and odom.get_subscription_count(), 20)
            sent, start = 0, time.monotonic()
            while time.monotonic() - start < SECONDS and not failures:
                odom.publish(odometry(float(sent)))
                clouds.publish(to_ros_msg(scans[sent % len(scans)], ["x", "y", "z"], stamp=1000.0 + 0.01 * sent))
                sent += 1
                collector.spin_until(lambda: False, 0.005)
            collector.spin_until(lambda: False, 1.0)
        finally:
            stop.set()
            spinner.join(timeout=30)
            node.shutdown()
            executor.shutdown()
            node.destroy_node()
            collector.close()
            probe.destroy_node()
    assert not failures, f"the node's executor raised {failures[0]!r}"
    s = diagnostics_values(collector.messages["/diagnostics"][-1])
    print(f"sent {sent} clouds; the node's counters: {s}")
    assert s["processing_errors"] == 0
    assert s["verification_errors"] == 0
    # the load did happen (verified: each keyframe's candidates until the first that passes)
    closures = 20 if verify else 500
    assert s["keyframes_processed"] > 50 and s["loop_closures"] > closures
    assert 0 <= s["corroborated_closures"] <= s["loop_closures"]
    assert 0 <= s["closures_to_nearer_keyframe"] <= s["loop_closures"]
    edges = collector.messages["/vbrl_node/markers"][-1].markers[1].points
    assert len(edges) > closures
