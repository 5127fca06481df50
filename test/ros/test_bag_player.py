"""``vbrl replay`` over real DDS: the player runs in a subprocess, this process subscribes with rclpy.

Every test gets its own ROS domain (vbrl_ros.ros.testing), so tests and
xdist workers never hear each other. The player waits for our subscriptions
(``--wait-for-subscribers``) instead of the tests sleeping for discovery.
"""

from __future__ import annotations

import itertools
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from geometry_msgs.msg import PoseStamped  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402

from vbrl_ros.io.bag_writer import write_scan_bag  # noqa: E402
from vbrl_ros.io.pointcloud2 import read_xyz_intensity, split_stamp  # noqa: E402
from vbrl_ros.ros import testing as ros_testing  # noqa: E402
from vbrl_ros.ros.bag_player import BagPlayer, ReplayError  # noqa: E402
from vbrl_ros.ros.testing import (  # noqa: E402
    MessageCollector,
    collect_messages,
    isolated_ros_env,
    ros_context,
    unique_domain_id,
)
from vbrl_ros.tools.replay import main as replay_main  # noqa: E402
from vbrl_ros.tools.replay import parse_remap  # noqa: E402

FORMATS = {"mcap": ({}, "bag"), "sqlite3": ({"storage": "sqlite3"}, "bag"), "ros1": ({"ros1": True}, "run.bag")}
T0 = 1_700_000_000.0
TIMEOUT = 20.0  # generous: only reached when something is broken


def make_bag(path: Path, count: int, spacing: float, **options: Any) -> tuple[Path, list[np.ndarray], np.ndarray,
                                                                             np.ndarray]:
    rng = np.random.default_rng(count)
    scans = [rng.normal(0.0, 10.0, size=(100 + 7 * i, 4)).astype(np.float32) for i in range(count)]
    stamps = T0 + spacing * np.arange(count)
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, :3, 3] = np.column_stack([np.arange(count) * 1.5, np.cos(np.arange(count)), np.zeros(count)])
    return write_scan_bag(path, scans, stamps, poses, **options), scans, stamps, poses


@pytest.fixture
def ros() -> Iterator[tuple[Any, dict[str, str]]]:
    """(node in a private context on a fresh domain, environment for a player on the same domain)."""
    with ros_context() as context:
        node = rclpy.create_node("replay_probe", context=context)
        try:
            yield node, isolated_ros_env(context.get_domain_id())
        finally:
            node.destroy_node()


def start_replay(bag: Path, env: dict[str, str], *args: str) -> subprocess.Popen:
    # --wait-for-subscribers sees the writer match our reader; the reader may match the writer
    # later, and samples sent in between then arrive in one burst (eleven clouds within 6 ms at
    # 1x, once, on a loaded machine), or not before the replay exits. Half a second covers that.
    return subprocess.Popen([sys.executable, "-m", "vbrl_ros.tools.replay", str(bag), "--quiet", "--delay", "0.5",
                             *args], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(process: subprocess.Popen, expected_code: int = 0) -> tuple[str, str]:
    stdout, stderr = process.communicate(timeout=TIMEOUT)
    assert process.returncode == expected_code, stderr
    return stdout, stderr


def stamp_of(msg: Any) -> tuple[int, int]:
    return msg.header.stamp.sec, msg.header.stamp.nanosec


# --------------------------------------------------------------------------- end to end, real DDS


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_replays_every_message_in_order(fmt: str, tmp_path: Path, ros) -> None:
    node, env = ros
    options, name = FORMATS[fmt]
    bag, scans, stamps, poses = make_bag(tmp_path / name, 8, 0.05, **options)
    topics = {"/points": PointCloud2, "/odom": Odometry, "/ground_truth": PoseStamped, "/clock": Clock}
    last_ns = sum(split_stamp(float(stamps[-1])) * np.array([1_000_000_000, 1]))

    def clock_ns(collector: MessageCollector) -> list[int]:
        return [msg.clock.sec * 1_000_000_000 + msg.clock.nanosec for msg in collector.messages["/clock"]]

    with MessageCollector(node, topics) as collector:
        process = start_replay(bag, env, "--wait-for-subscribers", "1")
        done = collector.spin_until(lambda: all(collector.count(t) == 8 for t in ("/points", "/odom", "/ground_truth"))
                                    and last_ns in clock_ns(collector), TIMEOUT)
        stdout, _ = finish(process)
        assert done, {topic: collector.count(topic) for topic in topics}
        assert "published 24 messages" in stdout and "1 pass(es)" in stdout

        clouds = collector.messages["/points"]
        assert [stamp_of(msg) for msg in clouds] == [split_stamp(float(s)) for s in stamps]  # all, in order
        for msg, scan in zip(clouds, scans):
            assert msg.header.frame_id == "lidar"
            points, intensity = read_xyz_intensity(msg)
            np.testing.assert_array_equal(points, scan[:, :3].astype(np.float64))
            np.testing.assert_array_equal(intensity, scan[:, 3].astype(np.float64))

        odometry = collector.messages["/odom"]
        assert [stamp_of(msg) for msg in odometry] == [split_stamp(float(s)) for s in stamps]
        assert {(msg.header.frame_id, msg.child_frame_id) for msg in odometry} == {("odom", "lidar")}
        positions = [(m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z) for m in odometry]
        np.testing.assert_allclose(positions, poses[:, :3, 3])
        truth = collector.messages["/ground_truth"]
        np.testing.assert_allclose([(m.pose.position.x, m.pose.position.y) for m in truth], poses[:, :2, 3])

        # /clock is the bag time: never backwards, and it reaches each message's stamp.
        clock = clock_ns(collector)
        assert clock == sorted(clock) and len(clock) >= 8
        stamps_ns = {sec * 1_000_000_000 + nanosec for sec, nanosec in (split_stamp(float(s)) for s in stamps)}
        assert stamps_ns <= set(clock)


def test_rate_scales_the_wall_time(tmp_path: Path, ros) -> None:
    node, env = ros
    bag, *_ = make_bag(tmp_path / "bag", 11, 0.1)  # 1 s of bag time
    spans = {}
    for rate in ("1", "5"):
        with MessageCollector(node, {"/points": PointCloud2}) as collector:
            process = start_replay(bag, env, "--rate", rate, "--topics", "/points", "--wait-for-subscribers", "1")
            assert collector.wait_for({"/points": 11}, TIMEOUT)
            finish(process)
            sent = collector.sent["/points"]  # the replay's pacing, whatever delivery did
            spans[rate] = sent[-1] - sent[0]
    # Same machine, same run: only the ratio is asserted, with a wide margin for a loaded CI.
    assert 3.0 < spans["1"] / spans["5"] < 8.0, spans  # 5 expected


def test_window_remap_and_sensor_qos(tmp_path: Path, ros) -> None:
    node, env = ros
    bag, scans, stamps, _ = make_bag(tmp_path / "bag", 10, 0.1)
    process = start_replay(bag, env, "--start-offset", "0.25", "--duration", "0.4", "--topics", "/points",
                           "--remap", "/points:=/velodyne_points", "--qos", "sensor", "--no-clock",
                           "--wait-for-subscribers", "1", "--delay", "0.3")  # best effort: let both ends match
    clouds = collect_messages(node, "/velodyne_points", PointCloud2, 4, TIMEOUT, qos=qos_profile_sensor_data)
    stdout, _ = finish(process)
    assert "published 4 messages" in stdout
    assert [stamp_of(msg) for msg in clouds] == [split_stamp(float(s)) for s in stamps[3:7]]  # bag t in [0.25, 0.65)
    np.testing.assert_array_equal(read_xyz_intensity(clouds[0])[0], scans[3][:, :3].astype(np.float64))


def test_sigint_during_a_loop_shuts_down_cleanly(tmp_path: Path, ros) -> None:
    node, env = ros
    bag, *_ = make_bag(tmp_path / "bag", 4, 0.05)
    with MessageCollector(node, {"/points": PointCloud2}) as collector:
        process = start_replay(bag, env, "--loop", "--rate", "4", "--wait-for-subscribers", "1",
                               "--wait-topics", "/points")
        assert collector.wait_for({"/points": 10}, TIMEOUT), "--loop must play the 4 clouds again and again"
        process.send_signal(signal.SIGINT)
        stdout, stderr = finish(process, 130)
    assert stdout.startswith("interrupted: published") and "Traceback" not in stderr


@pytest.mark.parametrize(("args", "message"), [
    (["{missing}"], "no such bag file or directory"),
    (["{bag}", "--topics", "/nope"], "no topic /nope in the bag (topics: /ground_truth"),
])
def test_bad_input_is_one_line_and_exit_code_2(args: list[str], message: str, tmp_path: Path) -> None:
    bag, *_ = make_bag(tmp_path / "bag", 3, 0.1)
    argv = [arg.format(bag=bag, missing=tmp_path / "missing") for arg in args]
    result = subprocess.run([sys.executable, "-m", "vbrl_ros.tools.replay", *argv, "--quiet"], env=isolated_ros_env(),
                            capture_output=True, text=True, timeout=TIMEOUT)
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.startswith("vbrl replay: error: ") and result.stderr.count("\n") == 1, result.stderr
    assert message in result.stderr


@pytest.mark.parametrize(("args", "message"), [
    (["--remap", "/nope:=/x"], "cannot remap /nope: not a replayed topic"),
    (["--remap", "/points"], "remap must look like /from:=/to"),
    (["--start-offset", "5"], "is past the bag's end"),
    (["--wait-for-subscribers", "1", "--wait-timeout", "0.3"], "timed out after 0.3 s waiting for 1 subscriber"),
])
def test_more_bad_input_in_process(args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture,
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    for key, value in isolated_ros_env().items():  # the wait-timeout case really starts DDS
        monkeypatch.setenv(key, value)
    bag, *_ = make_bag(tmp_path / "bag", 3, 0.1)
    try:
        code = replay_main([str(bag), "--quiet", *args])
    except SystemExit as exit:  # argparse's own errors
        code = exit.code
    assert code == 2
    assert message in capsys.readouterr().err.strip().splitlines()[-1]


# --------------------------------------------------------------------------- library API, in process


def test_player_in_a_thread_stops_on_event(tmp_path: Path, ros) -> None:
    node, _ = ros
    bag, *_ = make_bag(tmp_path / "bag", 3, 0.02)
    stop = threading.Event()
    with BagPlayer(bag, loop=True, rate=2.0, clock=False) as player, \
            MessageCollector(node, {"/odom": Odometry}) as collector:
        thread = threading.Thread(target=player.play, kwargs={"context": node.context, "stop": stop,
                                                                "wait_for_subscribers": 1, "wait_topics": ["/odom"]})
        thread.start()
        try:
            assert collector.wait_for({"/odom": 7}, TIMEOUT)
        finally:
            stop.set()
            thread.join(TIMEOUT)
        assert not thread.is_alive() and player.stats.passes >= 3 and player.stats.per_topic["/odom"] >= 7
        assert node.context.ok()  # a caller's context is left running


def test_options_are_checked_before_any_dds(tmp_path: Path) -> None:
    bag, *_ = make_bag(tmp_path / "bag", 3, 0.1)
    for kwargs, message in [({"rate": 0}, "rate must be"), ({"duration": -1}, "duration must be"),
                            ({"cloud_qos": "fast"}, "cloud QoS"),
                            ({"remaps": {"/points": "bad name"}}, "invalid topic"),
                            ({"remaps": {"/odom": "/points"}}, "two message types"),
                            ({"remaps": {"/clock": "/odom"}}, "also a replayed topic")]:
        with pytest.raises(ReplayError, match=message):
            BagPlayer(bag, **kwargs)
    assert parse_remap("/points:=/velodyne_points") == ("/points", "/velodyne_points")
    with BagPlayer(bag, topics=["/odom", "/points", "/odom"], duration=0.15) as player:
        assert player.topics == ["/odom", "/points"] and player.total == 4  # two stamps in [0, 0.15)


def test_domain_ids_are_distinct_per_call_and_per_xdist_worker(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(ros_testing, "_calls", itertools.count())  # as in a fresh worker process
    ids = [unique_domain_id() for _ in range(20)]
    assert len(set(ids)) == 20 and all(1 <= i <= 101 for i in ids)
    monkeypatch.setenv("PYTEST_XDIST_TESTRUNUID", "run")
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "4")
    by_worker = {}
    for worker in range(4):
        monkeypatch.setenv("PYTEST_XDIST_WORKER", f"gw{worker}")
        by_worker[worker] = {unique_domain_id() for _ in range(5)}
    assert sum(len(ids) for ids in by_worker.values()) == len(set().union(*by_worker.values())) == 20
    # two workers running many DDS tests each: their ids never meet, however many they draw
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "2")
    drawn = []
    for worker in range(2):
        monkeypatch.setenv("PYTEST_XDIST_WORKER", f"gw{worker}")
        drawn.append({unique_domain_id() for _ in range(200)})
    assert not drawn[0] & drawn[1] and len(drawn[0]) == len(drawn[1]) == 50
    env = isolated_ros_env(7, base={"ROS_LOCALHOST_ONLY": "1", "PATH": "/bin"})
    assert env == {"PATH": "/bin", "ROS_DOMAIN_ID": "7", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                   "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp"}
