"""Seeded fuzz over real DDS: malformed PointCloud2 and Odometry messages into a running vbrl_node.

The node must stay alive and account for everything it took in: every scan it
received ends in exactly one counter of its diagnostics (between keyframes,
malformed, empty, dropped, processed) and none in processing errors; every
odometry message is counted, exactly the bad ones as bad. Clouds go out best
effort (the node's sensor-data QoS), so some may be lost on the way; the
balance is over what arrived. ``--long`` sends 10,000 messages instead of 400.
"""

from __future__ import annotations

import math
import signal
import subprocess
import sys

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402

from vbrl_ros.ros.message_conversion import to_ros_msg  # noqa: E402
from vbrl_ros.ros.testing import MessageCollector, diagnostics_values, isolated_ros_env, ros_context  # noqa: E402

NODE = [sys.executable, "-m", "vbrl_ros.ros.node", "--ros-args"]
# nearly every scan a keyframe (odometry moves between most), each scored and verified, levelled by
# the fuzzed odometry
PARAMS = ("odom_topic:=/odom", "keyframe_distance:=0.001", "keyframe_interval:=0.001", "diagnostics_period:=0.1",
          "save_every:=0", "exclude_recent_s:=0.0", "distance_threshold:=1000.0", "top_k:=1",
          "level_from_odometry:=true")
UINT32 = 2**32 - 1
EXTREMES = [np.nan, np.inf, -np.inf, 1e30, -1e30, 3.4e38, -3.4e38, 0.0, 5e3]
CLOUD_KINDS = ["valid", "extreme", "all_nan", "no_points", "short", "longer", "header", "field", "fields", "bytes",
               "stamp", "big"]
CLOUD_WEIGHTS = np.array([6, 4, 1, 1, 2, 1, 3, 3, 1, 2, 1, 0.1])
ODOMETRY_KINDS = ["good", "zero_quaternion", "nan_quaternion", "inf_quaternion", "nan_position", "inf_position",
                  "far", "denormalised", "tiny_quaternion"]
ODOMETRY_WEIGHTS = np.array([8, 1, 1, 1, 1, 1, 0.5, 1, 0.5])
BAD_ODOMETRY = {"zero_quaternion", "nan_quaternion", "inf_quaternion", "nan_position", "inf_position",
                "denormalised", "tiny_quaternion"}


def fuzzed_cloud(rng: np.random.Generator, stamp: float, big_points: int) -> tuple[str, PointCloud2]:
    """A cloud as a driver could send it, then broken one way (or not): its kind and the message."""
    kind = str(rng.choice(CLOUD_KINDS, p=CLOUD_WEIGHTS / CLOUD_WEIGHTS.sum()))
    n = {"no_points": 0, "big": big_points}.get(kind, int(rng.integers(1, 4000)))
    names = ["x", "y", "z"] + [name for name in ("intensity", "ring", "t") if rng.random() < 0.4]
    points = np.c_[rng.uniform(-40, 40, (n, 2)), rng.uniform(-3, 8, (n, 1)), rng.random((n, len(names) - 3))]
    if kind == "extreme":
        rows = rng.random(n) < rng.uniform(0.01, 0.5)
        points[rows, int(rng.integers(3))] = rng.choice(EXTREMES, int(rows.sum()))
    if kind == "all_nan":
        points[:, :3] = np.nan
    width = int(rng.choice([w for w in (1, 2, 16, 32) if n % w == 0]))
    shape = (width, n // width, len(names)) if rng.random() < 0.3 else (n, len(names))  # organised or not
    float_type = int(rng.choice([PointField.FLOAT32, PointField.FLOAT64]))
    with np.errstate(over="ignore"):  # 3.4e38 and 1e30 in float32 are what such a driver sends
        msg = to_ros_msg(points.reshape(shape), names, stamp=stamp, frame_id="lidar", datatypes=float_type,
                         point_step=8 * len(names) + int(rng.integers(0, 9)) if rng.random() < 0.5 else None,
                         row_padding=int(rng.integers(0, 8)), big_endian=bool(rng.random() < 0.3))
    data = bytes(msg.data)
    if kind == "short":
        msg.data = data[: int(rng.integers(0, max(len(data), 1)))]
    elif kind == "longer":
        msg.data = data + rng.bytes(int(rng.integers(1, 64)))
    elif kind == "bytes":
        msg.data = rng.bytes(len(data))
    elif kind == "header":
        name = str(rng.choice(["height", "width", "point_step", "row_step"]))
        setattr(msg, name, int(rng.choice([0, 1, 3, UINT32, int(rng.integers(0, UINT32))])))
    elif kind == "field":
        field = msg.fields[int(rng.integers(len(msg.fields)))]
        name = str(rng.choice(["offset", "datatype", "count", "name"]))
        value = {"offset": int(rng.choice([0, 3, 4096, UINT32])), "datatype": int(rng.integers(0, 256)),
                 "count": int(rng.choice([0, 2, 1000, UINT32])), "name": str(rng.choice(["", "x", "z\n", "ü"]))}
        setattr(field, name, value[name])
    elif kind == "fields":
        msg.fields = list(msg.fields)[: int(rng.integers(0, 3))]  # no z (or nothing)
    elif kind == "stamp":
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(rng.integers(-(2**31), 2**31)), int(rng.integers(0, UINT32))
    return kind, msg


def fuzzed_odometry(rng: np.random.Generator, position: np.ndarray, kind: str | None = None) -> tuple[str, Odometry]:
    """A step of a random walk with a random orientation, or one broken pose: its kind and the message."""
    kind = kind or str(rng.choice(ODOMETRY_KINDS, p=ODOMETRY_WEIGHTS / ODOMETRY_WEIGHTS.sum()))
    position += rng.normal(0.0, 1.0, 3) * [1.0, 1.0, 0.1]
    quaternion = rng.normal(size=4)
    quaternion /= np.linalg.norm(quaternion)
    quaternion *= 1.0 + rng.uniform(-0.004, 0.004)  # within tf2's tolerance
    p, q = position.copy(), quaternion.copy()
    if kind.endswith("_quaternion") or kind == "denormalised":
        value = {"zero_quaternion": 0.0, "nan_quaternion": math.nan, "inf_quaternion": -math.inf,
                 "denormalised": 2.0, "tiny_quaternion": 1e-300}[kind]
        if kind in ("zero_quaternion", "tiny_quaternion", "denormalised"):
            q[:] = [value, 0.0, 0.0, 0.0] if kind != "denormalised" else q * value
        else:
            q[int(rng.integers(4))] = value
    elif kind in ("nan_position", "inf_position"):
        p[int(rng.integers(3))] = math.nan if kind == "nan_position" else math.inf
    elif kind == "far":
        p = rng.choice([-1.0, 1.0], 3) * 1e300
    msg = Odometry()
    msg.header.frame_id, msg.child_frame_id = "odom", "lidar"
    pose = msg.pose.pose
    pose.position.x, pose.position.y, pose.position.z = map(float, p)
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = map(float, q)
    return kind, msg


def balance(s: dict[str, float]) -> float:
    """Scans received minus the scans in the counters; 0 once every scan has its outcome."""
    return s["scans_received"] - sum(s[key] for key in ("scans_between_keyframes", "malformed_scans", "empty_scans",
                                                        "dropped_scans", "keyframes_processed", "processing_errors"))


def test_fuzzed_clouds_and_odometry_over_dds_leave_the_node_alive_and_its_counters_balanced(long_run):
    total = 10_000 if long_run else 400
    rng = np.random.default_rng(15)
    with ros_context() as context:
        env = isolated_ros_env(context.get_domain_id())
        probe = rclpy.create_node("fuzzer", context=context)
        collector = MessageCollector(probe, {"/diagnostics": DiagnosticArray})
        clouds = probe.create_publisher(PointCloud2, "/points", qos_profile_sensor_data)
        odometry = probe.create_publisher(Odometry, "/odom", 100)
        node = subprocess.Popen([*NODE, *[arg for p in PARAMS for arg in ("-p", p)]], env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        latest = lambda: diagnostics_values(collector.messages["/diagnostics"][-1])  # noqa: E731
        sent = {"clouds": 0, "odometry": 0, "bad_odometry": 0}
        kinds: dict[str, int] = {}
        try:
            assert collector.wait_for({"/diagnostics": 1}, timeout=60), "node did not come up"
            assert collector.spin_until(lambda: clouds.get_subscription_count() and odometry.get_subscription_count(),
                                        20)
            position, stamp, lost = np.zeros(3), 1000.0, 0
            while sum(kinds.values()) < total:
                # a batch the node's queues hold (5 best-effort scans, 50 odometry) in random order,
                # most clouds after a good step (so that they are keyframes and decoded), then the
                # node's counters catch up
                batch = ["cloud"] * int(rng.integers(0, 5)) + ["odometry"] * int(rng.integers(0, 10))
                for what in rng.permutation(batch):
                    if what == "cloud":
                        if rng.random() < 0.7:
                            odometry.publish(fuzzed_odometry(rng, position, kind="good")[1])
                            sent["odometry"] += 1
                        stamp += float(rng.uniform(0.0, 0.5))
                        kind, msg = fuzzed_cloud(rng, stamp, big_points=2_000_000 if long_run else 100_000)
                        clouds.publish(msg)
                        sent["clouds"] += 1
                    else:
                        kind, msg = fuzzed_odometry(rng, position)
                        odometry.publish(msg)
                        sent["odometry"] += 1
                        sent["bad_odometry"] += kind in BAD_ODOMETRY
                    kinds[kind] = kinds.get(kind, 0) + 1
                collector.spin_until(lambda: latest()["scans_received"] + lost >= sent["clouds"]
                                     and latest()["odometry_received"] >= sent["odometry"], 2.0)
                lost = sent["clouds"] - int(latest()["scans_received"])  # best effort: those never come
                assert node.poll() is None, f"the node died after {kinds}"
            assert collector.spin_until(lambda: balance(latest()) == 0, 60), f"counters never balanced: {latest()}"
            s = latest()
        finally:
            node.send_signal(signal.SIGTERM)
            output, _ = node.communicate(timeout=60)
        probe.destroy_node()
    print(f"sent {sent}, by kind {kinds}; the node's counters: {s}")
    assert node.returncode == 0 and "Traceback" not in output, output[-3000:]
    assert s["processing_errors"] == 0, output[-3000:]
    assert (s["odometry_received"], s["bad_odometry"]) == (sent["odometry"], sent["bad_odometry"])
    assert s["scans_received"] >= 0.9 * sent["clouds"]  # best effort: nearly all arrive on one host
    assert min(s["malformed_scans"], s["empty_scans"], s["keyframes_processed"]) > 0
