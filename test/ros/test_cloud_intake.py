"""The node's cheap first look at serialized clouds, and its count of the clouds DDS never delivered."""

from __future__ import annotations

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

from vbrl_ros.io.pointcloud2 import PointCloud2Error  # noqa: E402
from vbrl_ros.ros.cloud_intake import SequenceGaps, cloud_header  # noqa: E402
from vbrl_ros.ros.detector_node import CLOUD_QOS, VbrlNode  # noqa: E402
from vbrl_ros.ros.message_conversion import to_ros_msg  # noqa: E402
from vbrl_ros.ros.testing import MessageCollector, diagnostics_values, ros_context  # noqa: E402


def cloud(stamp: float, frame: str = "lidar", n: int = 500) -> PointCloud2:
    points = np.random.default_rng(0).uniform(-20, 20, (n, 3)).astype(np.float32)
    return to_ros_msg(points, ["x", "y", "z"], stamp=stamp, frame_id=frame)


@pytest.mark.parametrize("stamp, frame", [(0.0, ""), (1712345678.123456789, "os_sensor"), (-3.25, "ü")])
def test_the_header_read_from_serialized_bytes_is_the_message_s(stamp, frame):
    msg = cloud(stamp, frame)
    read_stamp, read_frame = cloud_header(serialize_message(msg))
    assert read_stamp == msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
    assert read_frame == frame.encode()


@pytest.mark.parametrize("raw", [b"", b"\x00\x01\x00\x00\x01\x00", b"\x00\x07" + bytes(30)])
def test_bytes_without_a_cdr_header_are_a_pointcloud2_error(raw):
    with pytest.raises(PointCloud2Error):
        cloud_header(raw)


def test_sequence_gaps_are_counted_per_stream_and_restart_on_a_step_back():
    gaps = SequenceGaps()
    assert [gaps.missing_before(b"a", n) for n in (5, 6, 9, 10)] == [0, 0, 2, 0]
    assert gaps.missing_before(b"b", 100) == 0 and gaps.missing_before(b"b", 104) == 3
    assert gaps.missing_before(b"a", 2) == 0 and gaps.missing_before(b"a", 4) == 1  # a restarted driver
    assert gaps.missing_before(b"a", None) == 0


def test_clouds_pushed_out_of_the_node_s_queue_are_counted_as_lost():
    burst = 3 * CLOUD_QOS.depth
    with ros_context() as context:
        node = VbrlNode(context=context, parameter_overrides=[Parameter("keyframe_interval", value=1000.0),
                                                              Parameter("diagnostics_period", value=0.1)])
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        probe = rclpy.create_node("publisher", context=context)
        collector = MessageCollector(probe, {"/diagnostics": DiagnosticArray})
        publisher = probe.create_publisher(PointCloud2, "/points", 10)
        stats = lambda: diagnostics_values(collector.messages["/diagnostics"][-1])  # noqa: E731
        spin = lambda seconds: [executor.spin_once(0.01) or collector.spin_until(lambda: False, 0.01)  # noqa: E731
                                for _ in range(int(seconds / 0.02))]
        try:
            assert collector.spin_until(lambda: publisher.get_subscription_count() > 0, 20)
            publisher.publish(cloud(1.0))  # the node's first: no gap can be seen before it
            for _ in range(500):
                spin(0.02)
                if collector.count("/diagnostics") and stats()["scans_received"] == 1:
                    break
            for k in range(burst):  # the node does not take any meanwhile: its queue overflows
                publisher.publish(cloud(2.0 + k))
            collector.spin_until(lambda: False, 0.5)
            spin(1.0)
            s = stats()
        finally:
            node.shutdown()
            executor.shutdown()
            node.destroy_node()
            collector.close()
            probe.destroy_node()
    assert s["scans_received"] == 1 + CLOUD_QOS.depth
    assert s["scans_lost"] == burst - CLOUD_QOS.depth
    assert s["scans_between_keyframes"] == CLOUD_QOS.depth
