"""vbrl_node as a real process over real DDS: start-up checks, bad input, load, services, signals."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from vbrl_ros.ros.detector_node import stamp_seconds  # noqa: E402
from vbrl_ros.ros.message_conversion import to_ros_msg  # noqa: E402
from vbrl_ros.ros.testing import MessageCollector, diagnostics_values, isolated_ros_env, ros_context  # noqa: E402

NODE = [sys.executable, "-m", "vbrl_ros.ros.node"]


def node_command(*params: str) -> list[str]:
    return [*NODE, "--ros-args", *[arg for p in params for arg in ("-p", p)]]


def test_help_lists_every_parameter_with_its_default_and_meaning():
    from vbrl_ros.ros.settings import DESCRIPTIONS, NodeSettings, yaml_value

    result = subprocess.run([*NODE, "--help"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0
    text = " ".join(result.stdout.split())  # the descriptions are wrapped
    for name, default in NodeSettings.defaults().items():
        assert f"{name} = {yaml_value(default)} {DESCRIPTIONS[name]}" in text, name


def start_fails(*args: str, cwd: Path | None = None) -> str:
    """Start the node with ``args``; it must exit 2 with one line of stderr, which is returned."""
    result = subprocess.run([*NODE, *args], env=isolated_ros_env(), cwd=cwd, capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    # rcl itself logs one "[ERROR] [...] [rcl]: Failed to parse global arguments" on a broken YAML
    lines = [line for line in result.stderr.splitlines() if "] [rcl]: " not in line]
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    return lines[0]


def test_a_missing_params_file_is_one_line_naming_it(tmp_path):
    line = start_fails("--ros-args", "--params-file", "config/vbrl.yaml", cwd=tmp_path)
    assert "--params-file config/vbrl.yaml does not exist" in line
    assert str(tmp_path) in line  # where a relative path was looked for
    assert str(Path(__file__).resolve().parents[2] / "config" / "vbrl.yaml") in line  # the shipped one
    (tmp_path / "broken.yaml").write_text("/**:\n  ros__parameters:\n    top_k: [1,\n")
    line = start_fails("--ros-args", "--params-file", str(tmp_path / "broken.yaml"))
    assert "cannot start" in line and "broken.yaml" in line and ".c:" not in line


def test_an_unknown_parameter_in_a_params_file_stops_the_start(tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("/**:\n  ros__parameters:\n    keyframe_distanse: 2.0\n")
    line = start_fails("--ros-args", "--params-file", str(params))
    assert "unknown parameter 'keyframe_distanse' (did you mean 'keyframe_distance'?)" in line


def test_the_shipped_params_file_starts_the_node_and_a_bad_mounting_stops_the_start():
    """The one array parameter (odometry_lidar_pose) goes through rcl's YAML and -p parsing."""
    config = Path(__file__).resolve().parents[2] / "config" / "vbrl.yaml"
    node = subprocess.Popen([*NODE, "--ros-args", "--params-file", str(config)], env=isolated_ros_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    watchdog = threading.Timer(60.0, node.kill)
    watchdog.start()
    try:
        started = any("listening on /points" in line for line in iter(node.stdout.readline, ""))
    finally:
        node.send_signal(signal.SIGINT)
        node.communicate(timeout=60)
        watchdog.cancel()
    assert started and node.returncode == 0
    line = start_fails("--ros-args", "-p", "odometry_lidar_pose:=[0.1, 0.0]")
    assert "parameter 'odometry_lidar_pose' must be six finite numbers [x, y, z, roll, pitch, yaw]" in line


def model_with_text_weights(path: Path) -> Path:
    from vbrl_ros.model.builtin import load_default_model

    saved = load_default_model().save(path)
    with np.load(saved) as archive:
        contents = dict(archive)
    np.savez(saved, **{**contents, "W": np.array("W")})
    return saved


@pytest.mark.parametrize("param, line", [
    ("keyframe_distance:=-1.0", "parameter 'keyframe_distance' must be a positive number, got -1.0"),
    ("top_k:=abc", "parameter 'top_k' must be int, got str 'abc'"),
    ("min_fitness:=2.0", "parameter 'min_fitness' must be in [0, 1], got 2.0"),
    ("sequence_length:=0", "parameter 'sequence_length' must be an integer in [1, 20], got 0"),
    ("verification_voxel:=1e-9", "parameter 'verification_voxel' must be in [0.05, 10.0] m, got 1e-09"),
    ("cloud_topics:=/velodyne_points", "unknown parameter 'cloud_topics' (did you mean 'cloud_topic'?); "
                                       "vbrl_node --help lists them"),
    ("cloud_topic:=bad topic", "parameter 'cloud_topic' is not a valid topic name: 'bad topic' (topic name must "
                               "not contain characters other than alphanumerics, '_', '~', '{', or '}')"),
    ("markers_topic:=//x", "parameter 'markers_topic' is not a valid topic name: '//x' (topic name must not "
                           "contain repeated '/')"),
    ("lio_sam_topic:=''", "parameter 'lio_sam_topic' is not a valid topic name: '' (topic name must not be "
                          "empty string)"),
    ("database_path:={tmp}/afile/keyframes.npz", "parameter 'database_path': cannot write "
                                                 "{tmp}/afile/keyframes.npz (a file where a folder should be: {tmp}/afile)"),
    ("index_refine_dim:=99999", "parameter 'index_refine_dim' for this model: refine_dim must be an integer in "
                                "[0, 640], got 99999"),
    ("model_path:=/nonexistent/model.npz", "model file /nonexistent/model.npz does not exist"),
    ("model_path:={tmp}", "model file {tmp} is a directory"),
    ("model_path:={tmp}/text_weights.npz", "{tmp}/text_weights.npz has a bad 'W': it holds a single <U1 value, "
                                           "where the model format stores a 2-d float array"),
])
def test_a_bad_parameter_stops_the_start_in_one_line_naming_it(tmp_path, param, line):
    (tmp_path / "afile").write_text("a file, not a folder")
    if "text_weights" in param:
        model_with_text_weights(tmp_path / "text_weights.npz")
    param, line = (text.replace("{tmp}", str(tmp_path)) for text in (param, line))
    assert start_fails("--ros-args", "-p", param) == f"vbrl_node: cannot start: {line}"


@pytest.mark.parametrize("delay", [0.2, 0.5, 1.0])
def test_ctrl_c_during_start_up_stops_without_a_traceback(delay):
    node = subprocess.Popen(node_command(), env=isolated_ros_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    time.sleep(delay)  # importing numpy, rclpy, numba and loading the model take a second or two
    node.send_signal(signal.SIGINT)
    output, _ = node.communicate(timeout=60)
    assert node.returncode == 0 and "Traceback" not in output, output


def test_a_ctrl_c_before_rclpy_handles_signals_is_recorded_not_raised():
    # raised inside some library's import, a KeyboardInterrupt can be swallowed there: the
    # node then started and never stopped
    from vbrl_ros.ros.node import record_interrupts

    previous = signal.getsignal(signal.SIGINT)
    try:
        interrupted = record_interrupts()
        signal.raise_signal(signal.SIGINT)
        assert interrupted.is_set()
    finally:
        signal.signal(signal.SIGINT, previous)


def test_a_recorded_ctrl_c_stops_the_start_before_rclpy_starts():
    import threading

    from vbrl_ros.ros.node import run

    interrupted = threading.Event()
    interrupted.set()
    with pytest.raises(KeyboardInterrupt):
        run(["vbrl_node", "--ros-args"], interrupted)
    assert not rclpy.ok()  # the default context was never initialised


def test_a_failed_final_save_is_one_line_and_exit_1(tmp_path):
    folder = tmp_path / "db"
    with ros_context() as context:
        env = isolated_ros_env(context.get_domain_id())
        probe = rclpy.create_node("probe", context=context)
        collector = MessageCollector(probe, {"/diagnostics": DiagnosticArray})
        node = subprocess.Popen(node_command(f"database_path:={folder / 'keyframes.npz'}", "diagnostics_period:=0.2"),
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            assert collector.wait_for({"/diagnostics": 1}, timeout=30), "node did not come up"
            folder.rmdir()  # the start made it (and checked it); now a file takes its place
            folder.write_text("not a folder")
            response = call(collector, "/vbrl_node/save_database")
            assert not response.success and response.message.startswith("save failed: ")
            assert collector.spin_until(lambda: stats(collector)["failed_saves"] == 1, 10)
        finally:
            node.send_signal(signal.SIGTERM)
            output, _ = node.communicate(timeout=60)
        probe.destroy_node()
    assert node.returncode == 1 and "Traceback" not in output, output
    assert f"[vbrl_node] database not saved: [Errno 17] File exists: '{folder}'" in output


def test_a_session_id_the_database_already_has_is_said_once_at_start(tmp_path):
    """One session is one odometry frame: reusing one after odometry restarted would compare
    positions across two frames, so the node says so; a new session (the default -1) says nothing."""
    database = tmp_path / "keyframes.npz"
    large_database(database, keyframes=3)
    warning = "session_id 0 already has keyframes in the database"
    outputs = {}
    with ros_context() as context:
        env = isolated_ros_env(context.get_domain_id())
        probe = rclpy.create_node("probe", context=context)
        collector = MessageCollector(probe, {"/diagnostics": DiagnosticArray})
        for session in ("0", "-1"):
            started = time.time()
            node = subprocess.Popen(node_command(f"database_path:={database}", f"session_id:={session}",
                                                 "save_every:=0", "diagnostics_period:=0.2"),
                                    env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            try:
                assert collector.spin_until(lambda: collector.count("/diagnostics") and stamp_seconds(
                    collector.messages["/diagnostics"][-1].header.stamp) > started, 60), "node did not come up"
            finally:
                node.send_signal(signal.SIGTERM)
                outputs[session], _ = node.communicate(timeout=60)
            assert node.returncode == 0, outputs[session]
        probe.destroy_node()
    assert outputs["0"].count(warning) == 1, outputs["0"]
    assert "already has keyframes" not in outputs["-1"], outputs["-1"]


def scan(stamp: float, seed: int) -> PointCloud2:
    rng = np.random.default_rng(seed)
    points = np.concatenate([rng.uniform(-30, 30, (20000, 2)), rng.uniform(-2, 4, (20000, 1)),
                             rng.random((20000, 1))], axis=1).astype(np.float32)
    return to_ros_msg(points, ["x", "y", "z", "intensity"], stamp=stamp, frame_id="lidar")


def malformed(stamp: float) -> list[PointCloud2]:
    no_z = to_ros_msg(np.zeros((10, 2), np.float32), ["x", "y"], stamp=stamp)
    short = scan(stamp, 0)
    short.data = bytes(short.data)[:100]
    zero_step = scan(stamp, 0)
    zero_step.point_step = 0
    beyond = scan(stamp, 0)
    beyond.fields = [PointField(name=n, offset=o, datatype=PointField.FLOAT32, count=1)
                     for n, o in (("x", 0), ("y", 4), ("z", 400))]
    empty = to_ros_msg(np.zeros((0, 3), np.float32), ["x", "y", "z"], stamp=stamp)
    nan_only = to_ros_msg(np.full((50, 3), np.nan, np.float32), ["x", "y", "z"], stamp=stamp)
    return [no_z, short, zero_step, beyond, empty, nan_only]


def stats(collector: MessageCollector) -> dict[str, float]:
    return diagnostics_values(collector.messages["/diagnostics"][-1])


def latest(collector: MessageCollector) -> dict[str, int]:
    """The node's current stats: drain what queued while the test was not spinning first."""
    collector.spin_until(lambda: False, 1.0)  # > 3 diagnostics periods
    return stats(collector)


def settle(collector: MessageCollector, timeout: float = 60.0) -> dict[str, int]:
    """Wait until the node's processed-keyframe count stops moving; return the last stats."""
    previous = None
    for _ in range(int(timeout)):
        current = latest(collector)
        if previous is not None and current["keyframes_processed"] == previous["keyframes_processed"]:
            return current
        previous = current
    raise AssertionError("node never went idle")


def call(collector: MessageCollector, service: str, timeout: float = 20.0) -> Trigger.Response:
    """Call a Trigger service, spinning the collector's executor (a node lives in one executor)."""
    client = collector.node.create_client(Trigger, service)
    assert client.wait_for_service(timeout_sec=timeout)
    future = client.call_async(Trigger.Request())
    assert collector.spin_until(future.done, timeout)
    return future.result()


def test_bad_input_load_services_and_sigterm(tmp_path: Path):
    database = tmp_path / "db" / "keyframes.npz"
    with ros_context() as context:
        env = isolated_ros_env(context.get_domain_id())
        probe = rclpy.create_node("probe", context=context)
        collector = MessageCollector(probe, {"/diagnostics": DiagnosticArray})
        publisher = probe.create_publisher(PointCloud2, "/points", 100)
        node = subprocess.Popen(
            node_command(f"database_path:={database}", "keyframe_interval:=0.05",
                         "diagnostics_period:=0.3", "save_every:=0"),
            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )
        try:
            assert collector.wait_for({"/diagnostics": 1}, timeout=30), "node did not come up"
            assert collector.spin_until(lambda: publisher.get_subscription_count() > 0, 20)

            # malformed and empty clouds: counted, skipped, the node goes on
            # (one at a time: the node's sensor-data QoS keeps only the last 5 of a burst)
            for k, msg in enumerate(malformed(100.0)):
                msg.header.stamp.sec = 100 + k
                publisher.publish(msg)
                assert collector.spin_until(lambda: stats(collector)["scans_received"] >= k + 1, 20)
            publisher.publish(scan(200.0, 1))
            assert collector.spin_until(lambda: stats(collector)["keyframes_processed"] >= 1, 20)
            s = latest(collector)
            assert (s["malformed_scans"], s["empty_scans"]) == (4, 2)
            assert s["processing_errors"] == 0 and node.poll() is None

            # a burst faster than processing: the newest is kept, the rest counted as dropped
            for k in range(40):
                publisher.publish(scan(300.0 + 0.1 * k, k))
            collector.spin_until(lambda: stats(collector)["scans_received"] >= 47, 30)
            s = settle(collector)
            assert s["dropped_scans"] > 0
            assert s["keyframes_processed"] + s["dropped_scans"] <= s["scans_received"]
            assert s["database_size"] == s["keyframes_processed"]

            # services
            saved = call(collector, "/vbrl_node/save_database")
            assert saved.success and database.is_file()
            cleared = call(collector, "/vbrl_node/clear_database")
            assert cleared.success and "cleared" in cleared.message
            assert latest(collector)["database_size"] == 0
            publisher.publish(scan(400.0, 99))
            assert collector.spin_until(lambda: stats(collector)["database_size"] == 1, 20)
        finally:
            node.send_signal(signal.SIGTERM)
            output, _ = node.communicate(timeout=60)
        probe.destroy_node()
    assert node.returncode == 0, output
    assert "saved 1 keyframes" in output  # SIGTERM saved the database


def odometry(x: float, quaternion=(0.0, 0.0, 0.0, 1.0)) -> Odometry:
    msg = Odometry()
    msg.pose.pose.position.x = x
    o = msg.pose.pose.orientation
    o.x, o.y, o.z, o.w = quaternion
    return msg


def test_bad_odometry_is_counted_and_skipped_and_keyframing_goes_on():
    with ros_context() as context:
        env = isolated_ros_env(context.get_domain_id())
        probe = rclpy.create_node("probe", context=context)
        collector = MessageCollector(probe, {"/diagnostics": DiagnosticArray})
        clouds = probe.create_publisher(PointCloud2, "/points", 10)
        odom = probe.create_publisher(Odometry, "/odom", 10)
        node = subprocess.Popen(node_command("odom_topic:=/odom", "keyframe_distance:=1.0", "diagnostics_period:=0.2"),
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        sent = {"odometry": 0}

        def move(msg: Odometry) -> None:
            odom.publish(msg)
            sent["odometry"] += 1
            assert collector.spin_until(lambda: stats(collector)["odometry_received"] >= sent["odometry"], 20), \
                "odometry not taken in (node dead?)"

        def keyframe(stamp: float, expected: int) -> None:
            clouds.publish(scan(stamp, int(stamp)))
            assert collector.spin_until(lambda: stats(collector)["keyframes_processed"] >= expected, 30), \
                f"no keyframe {expected} at {stamp} s: {stats(collector)}"

        try:
            assert collector.wait_for({"/diagnostics": 1}, timeout=30), "node did not come up"
            assert collector.spin_until(lambda: odom.get_subscription_count() > 0
                                        and clouds.get_subscription_count() > 0, 20)
            move(odometry(0.0))
            keyframe(1.0, 1)
            move(odometry(float("nan")))  # a NaN position must not stop every later keyframe
            move(odometry(2.0))
            keyframe(2.0, 2)
            move(odometry(3.0, (0.0, 0.0, 0.0, 0.0)))  # zero quaternion
            move(odometry(3.0, (0.0, float("nan"), 0.0, 1.0)))
            move(odometry(4.0))
            keyframe(3.0, 3)
            s = latest(collector)
            assert (s["odometry_received"], s["bad_odometry"]) == (6, 3)
            assert s["scans_between_keyframes"] == s["processing_errors"] == 0
            assert node.poll() is None
        finally:
            node.send_signal(signal.SIGTERM)
            output, _ = node.communicate(timeout=60)
        probe.destroy_node()
    assert node.returncode == 0, output
    assert "odometry skipped: position (nan, 0.0, 0.0) is not finite" in output


def large_database(path: Path, keyframes: int = 1000):
    """A database of the built-in model big enough (~25 MB) that a save takes a while; a loader of it."""
    from vbrl_ros.detection.database import KeyframeDatabase
    from vbrl_ros.model.builtin import load_default_model
    from vbrl_ros.ros.settings import NodeSettings

    model = load_default_model()
    scorer = model.scorer(prune=NodeSettings().weight_prune)
    db = KeyframeDatabase(scorer, model.identity())
    rng = np.random.default_rng(0)
    for k in range(keyframes):
        db.add(rng.normal(size=db.n_active).astype(np.float32), float(k), "0",
               cloud=rng.uniform(-40, 40, (2000, 3)))
    db.save(path)
    return lambda: KeyframeDatabase.load(path, scorer, model.identity())


def test_kill_9_mid_save_keeps_the_database_and_the_next_start_removes_the_leftovers(tmp_path):
    database = tmp_path / "keyframes.npz"
    load = large_database(database)
    count = len(load())
    leftovers = lambda: sorted(tmp_path.glob(".keyframes.npz.*.tmp"))  # noqa: E731
    with ros_context() as context:
        env = isolated_ros_env(context.get_domain_id())
        probe = rclpy.create_node("probe", context=context)
        collector = MessageCollector(probe, {"/diagnostics": DiagnosticArray})
        for attempt in range(3):
            started = time.time()
            node = subprocess.Popen(node_command(f"database_path:={database}", "save_every:=0",
                                                 "diagnostics_period:=0.2"),
                                    env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            try:
                # this node's diagnostics, not a late one of the node killed before
                assert collector.spin_until(lambda: collector.count("/diagnostics") and stamp_seconds(
                    collector.messages["/diagnostics"][-1].header.stamp) > started, 60), "node did not come up"
                assert stats(collector)["database_size"] == count
                assert leftovers() == []  # the start removed what the last kill left
                if attempt == 2:
                    break
                # one acknowledged save first: the client has then found this node's service
                # (a killed node's can linger in the graph, and a request to it is lost)
                client = probe.create_client(Trigger, "/vbrl_node/save_database")
                assert client.wait_for_service(timeout_sec=20)
                for _ in range(10):
                    future = client.call_async(Trigger.Request())
                    if collector.spin_until(future.done, 3):
                        break
                assert future.done() and future.result().success
                client.call_async(Trigger.Request())  # the request goes out now; the reply never comes
                deadline = time.monotonic() + 20
                while not leftovers() and time.monotonic() < deadline:
                    time.sleep(0.001)
                node.send_signal(signal.SIGKILL)  # mid-save
                node.wait(timeout=20)
                probe.destroy_client(client)
                assert leftovers(), "the save was not caught mid-write"
                assert len(load()) == count  # the last complete file, as acknowledged
            finally:
                if node.poll() is None:
                    node.send_signal(signal.SIGTERM)
                output, _ = node.communicate(timeout=60)
        probe.destroy_node()
    assert node.returncode == 0, output
    assert "removed 1 temporary file(s) that interrupted saves of" in output and f"saved {count} keyframes" in output
