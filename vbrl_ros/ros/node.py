"""``vbrl_node``: the online loop-closure detector as a ROS 2 node.

A thin adapter around :class:`~vbrl_ros.detection.detector.LoopClosureDetector`:
the subscription callback only decides whether a scan is a keyframe and
drops it into a one-slot mailbox; a worker thread decodes, scores, verifies,
inserts and publishes. When the worker falls behind, the newest keyframe
replaces the waiting one and the replaced one is counted as dropped, so no
queue grows without bound. A bad message is logged, counted and skipped.
"""

from __future__ import annotations

import os
import re
import sys
import textwrap
import threading
import time
from collections import deque
from dataclasses import replace
from pathlib import Path

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.database_file import DatabaseFileError
from vbrl_ros.detection.detector import LoopClosureDetector
from vbrl_ros.detection.settings import SettingsError
from vbrl_ros.grids.ground_frame import gravity_rotation
from vbrl_ros.index.parameters import IndexParameters
from vbrl_ros.io.atomic import remove_stale_temporaries
from vbrl_ros.io.pointcloud2 import PointCloud2Error, read_xyz_intensity
from vbrl_ros.model.builtin import load_default_model
from vbrl_ros.model.model_file import ModelFileError, load_model
from vbrl_ros.ros.messages import closures_message, lio_sam_message
from vbrl_ros.ros.odometry import KeyframeSpacing, OdometryError, pose_matrix
from vbrl_ros.ros.outputs import NodeStats, diagnostics_status, keyframe_markers
from vbrl_ros.ros.settings import DESCRIPTIONS, NodeSettings, unknown_parameters, yaml_value


def stamp_seconds(stamp) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


class VbrlNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("vbrl_node", **kwargs)
        self.settings = self._read_settings()
        s = self.settings
        self.model = load_model(s.model_path) if s.model_path else load_default_model()
        self.database = self._open_database()
        session = s.session_id if s.session_id >= 0 else self.database.next_session()
        self.detector = LoopClosureDetector(self.model, self.database,
                                            replace(s.detector, session=str(session)))
        self.session = session
        # compile (or load from cache) the featurizer kernel now, not on the first keyframe
        self.detector.featurizer.describe(np.zeros((1, 3)))
        self.stats = NodeStats()
        self._db_lock = threading.Lock()
        self._mailbox = threading.Condition()
        self._pending: tuple[np.ndarray, float, np.ndarray | None, float] | None = None
        self._stopping = False
        self._spacing = KeyframeSpacing(s.keyframe_distance, s.keyframe_interval)
        self._edges: deque[tuple[int, int]] = deque(maxlen=10_000)
        self._keyframes_since_save = 0

        self.closure_pub = self.create_publisher(Float64MultiArray, s.loop_closure_topic, 10)
        self.lio_sam_pub = self.create_publisher(Float64MultiArray, s.lio_sam_topic, 10)
        self.marker_pub = self.create_publisher(MarkerArray, s.markers_topic, 1)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(PointCloud2, s.cloud_topic, self._on_cloud, qos_profile_sensor_data)
        if s.odom_topic:
            self.create_subscription(Odometry, s.odom_topic, self._on_odom, 50)
        self.create_service(Trigger, "~/save_database", self._on_save)
        self.create_service(Trigger, "~/clear_database", self._on_clear)
        self.create_timer(s.diagnostics_period, self._publish_status)
        self._worker = threading.Thread(target=self._work, name="vbrl-worker", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"listening on {s.cloud_topic}; session {session}; {len(self.database)} keyframes in "
            f"memory; distance threshold {self.detector.distance_threshold:.3f} (lower = more similar)"
        )

    # -- start-up ------------------------------------------------------------

    def _read_settings(self) -> NodeSettings:
        values = {}
        for name, default in NodeSettings.defaults().items():
            # dynamic typing: a wrongly typed value reaches our validation,
            # which names the parameter, instead of an rclpy type exception
            descriptor = ParameterDescriptor(description=DESCRIPTIONS[name], dynamic_typing=True)
            self.declare_parameter(name, default, descriptor)
            values[name] = self.get_parameter(name).value
        self._refuse_unknown_overrides()
        return NodeSettings.from_values(values)

    def _refuse_unknown_overrides(self) -> None:
        """Stop on a -p or parameter-file name that no one declared.

        rclpy drops such overrides silently, so a misspelled ``cloud_topics``
        would leave a robot running on the default topic with nothing said.
        What rclpy declares itself (use_sim_time, ...) counts as known. The
        overrides are rclpy's protected ``Node._parameter_overrides``: it has
        no public way to list them without declaring them all.
        """
        unknown = [name for name in self._parameter_overrides if not self.has_parameter(name)]
        if unknown:
            raise SettingsError(unknown_parameters(sorted(unknown)))

    def _open_database(self) -> KeyframeDatabase:
        scorer = self.model.scorer(prune=self.settings.weight_prune)
        model_id = self.model.identity()
        path = self.settings.database_path
        if path:
            removed = remove_stale_temporaries(path)
            if removed:
                self.get_logger().info(f"removed {len(removed)} temporary file(s) that interrupted saves of "
                                       f"{path} left")
        if path and Path(path).exists():
            # a saved database keeps its own storage type (and refuses another prune)
            return KeyframeDatabase.load(path, scorer, model_id)
        return KeyframeDatabase(scorer, model_id, IndexParameters(storage=self.settings.descriptor_storage))

    # -- callbacks (executor thread): cheap ------------------------------------

    def _on_odom(self, msg: Odometry) -> None:
        self.stats.odometry += 1
        try:
            pose = pose_matrix(msg)
        except OdometryError as error:
            self.stats.bad_odometry += 1
            self.get_logger().warning(f"odometry skipped: {error}", throttle_duration_sec=5.0)
            return
        self._spacing.moved_to(pose)

    def _on_cloud(self, msg: PointCloud2) -> None:
        now = time.monotonic()
        self.stats.received(now)
        stamp = stamp_seconds(msg.header.stamp)
        if not self._spacing.is_keyframe(stamp):
            self.stats.between_keyframes += 1
            return
        # Decode here, not in the worker: every bad message is then counted as
        # what it is (instead of vanishing as a "drop" from the mailbox) and
        # never takes a keyframe slot. Decoding is a few ms; scoring is not.
        try:
            points, _ = read_xyz_intensity(msg)
        except PointCloud2Error as error:
            self.stats.malformed += 1
            self.get_logger().warning(f"malformed PointCloud2 skipped: {error}", throttle_duration_sec=5.0)
            return
        if len(points) == 0:
            self.stats.empty += 1
            self.get_logger().warning("PointCloud2 without finite points skipped", throttle_duration_sec=5.0)
            return
        self._spacing.mark(stamp)
        with self._mailbox:
            if self._pending is not None:
                self.stats.dropped += 1  # the worker is behind: keep the newest keyframe only
            self._pending = (points, stamp, self._spacing.latest_pose, now)
            self._mailbox.notify()

    # -- worker thread: the real work ------------------------------------------

    def _work(self) -> None:
        while True:
            with self._mailbox:
                while self._pending is None and not self._stopping:
                    self._mailbox.wait()
                if self._stopping:
                    return
                points, stamp, pose, arrived = self._pending
                self._pending = None
            try:
                self._process(points, stamp, pose, arrived)
            except Exception as error:  # never let one scan kill the node
                self.stats.errors += 1
                self.get_logger().error(f"keyframe skipped after an unexpected error: {error!r}")

    def _process(self, points: np.ndarray, stamp: float, pose: np.ndarray | None, arrived: float) -> None:
        with self._db_lock:
            gravity = (gravity_rotation(pose) if self.settings.level_from_odometry and pose is not None
                       else None)
            result = self.detector.process_keyframe(points, stamp, pose, gravity)
        self.stats.keyframe(1e3 * (time.monotonic() - arrived), result)
        for closure in result.closures:
            self._edges.append((closure.query_id, closure.match_id))
        if result.closures:
            self.closure_pub.publish(closures_message(result.closures))
            for closure in result.closures:
                self.lio_sam_pub.publish(lio_sam_message(closure))
        self._keyframes_since_save += 1
        if self.settings.save_every and self._keyframes_since_save >= self.settings.save_every:
            self.save_database()

    # -- persistence ----------------------------------------------------------

    def save_database(self) -> str:
        if not self.settings.database_path:
            return "no database_path set: nothing saved"
        with self._db_lock:
            self.database.save(self.settings.database_path)
            self._keyframes_since_save = 0
            return f"saved {len(self.database)} keyframes to {self.settings.database_path}"

    def _on_save(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        try:
            response.message = self.save_database()
            response.success = bool(self.settings.database_path)
        except OSError as error:
            response.success, response.message = False, f"save failed: {error}"
        return response

    def _on_clear(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._db_lock:
            count = len(self.database)
            self.database.clear()
            self._edges.clear()
        response.success, response.message = True, f"cleared {count} keyframes"
        return response

    def _publish_status(self) -> None:
        with self._db_lock:
            size = len(self.database)
            markers = keyframe_markers(self.database, self._edges, self.settings.map_frame,
                                       self.get_clock().now().to_msg())
        status = diagnostics_status(self.stats, size, self.session)
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self.diag_pub.publish(array)
        if markers is not None:
            self.marker_pub.publish(markers)

    def shutdown(self) -> None:
        """Stop the worker (finishing the keyframe in hand) and save the database."""
        with self._mailbox:
            self._stopping = True
            self._mailbox.notify_all()
        self._worker.join(timeout=30.0)
        if self.settings.database_path:
            # stderr, not the ROS logger: after SIGINT/SIGTERM the context
            # (and with it /rosout) is already shut down
            print(f"[vbrl_node] {self.save_database()}", file=sys.stderr)


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


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else argv)
    user_args = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if "-h" in user_args or "--help" in user_args:
        print(usage())
        return 0
    problem = params_file_problem(argv)
    if problem is not None:
        print(f"vbrl_node: cannot start: {problem}", file=sys.stderr)
        return 2
    try:
        rclpy.init(args=argv)
    except RuntimeError as error:  # rcl's RCLError, e.g. a parameter file that is not valid YAML
        print(f"vbrl_node: cannot start: {rcl_error_line(error)}", file=sys.stderr)
        return 2
    node = None
    try:
        node = VbrlNode()
        rclpy.spin(node)
    except (SettingsError, ModelFileError, DatabaseFileError) as error:
        print(f"vbrl_node: cannot start: {error}", file=sys.stderr)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass  # SIGINT / SIGTERM: fall through to a clean shutdown
    except Exception:
        if rclpy.ok():
            raise
        # a signal shut the context down while the executor was mid-wait;
        # rclpy then raises whatever that wait hit: still a clean shutdown
    finally:
        if node is not None:
            node.shutdown()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
