"""The online loop-closure detector as a ROS 2 node (:class:`VbrlNode`; ``vbrl_node`` runs it).

A thin adapter around :class:`~vbrl_ros.detection.detector.LoopClosureDetector`,
in three threads and a process. The subscription callback (executor thread)
reads a serialized cloud's stamp, decides whether it is a keyframe and only
then decodes it into a short queue; the worker thread describes,
searches and stores the keyframe (with a model that describes a keyframe with the metres
after it too, once the sensor has passed it: after as long a silence as the trail ahead
reaches in time, or at shutdown, with what came); a child process
(:class:`~vbrl_ros.detection.verifier_process.VerifierProcess`) verifies its
candidates meanwhile, and the verification thread publishes what passes. No
hand-over grows: a keyframe pushed out of the worker's queue (5 long) is
counted as dropped, one whose candidates a newer keyframe's replaced before
verification (a single place) as unverified. Clouds DDS never delivered are
counted as lost. A bad message is logged, counted and skipped; a failed save is
logged and counted, and tried again at the next keyframe.

Before anything is loaded, every topic parameter must be a name rclpy accepts and
``database_path`` must be writable: either stops the start with a line naming it.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from dataclasses import replace

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from vbrl_ros.detection.candidate_verification import KeyframeResult, Retrieval, verify_candidates
from vbrl_ros.detection.detector import Keyframe, LoopClosureDetector, submap_gap_s
from vbrl_ros.detection.verifier_process import VerifierError, VerifierProcess
from vbrl_ros.grids.ground_frame import gravity_rotation
from vbrl_ros.io.pointcloud2 import PointCloud2Error, read_xyz_intensity
from vbrl_ros.model.builtin import load_default_model
from vbrl_ros.model.model_file import load_model
from vbrl_ros.ros.cloud_intake import SequenceGaps, cloud_header
from vbrl_ros.ros.messages import closures_message, lio_sam_message
from vbrl_ros.ros.newest_queue import NewestQueue
from vbrl_ros.ros.node_setup import check_database_path, check_topics, open_database, read_settings
from vbrl_ros.ros.node_stats import NodeStats
from vbrl_ros.ros.odometry import KeyframeSpacing, OdometryError, PoseHistory, mounting_matrix, pose_matrix
from vbrl_ros.ros.outputs import diagnostics_status, keyframe_markers

#: Keyframes waiting for the worker before the oldest is dropped: half a second at 10 keyframes/s,
#: what a save of ~800 keyframes (~55 MB) holds the worker for; more would only add latency.
KEYFRAME_QUEUE = 5
#: Retrievals waiting for verification before the oldest is left unverified: the keyframes of one
#: place that come due together when the sensor stops (features.trail_ahead_m), no more.
RETRIEVAL_QUEUE = 4
#: Sensor-data QoS (best effort), with a queue of a second of a 10 Hz sensor instead of 5 messages:
#: a cloud waiting there costs memory only until the callback takes it, a cloud pushed out is lost.
#: How long a keyframe waits for odometry to reach its stamp (a LiDAR odometry publishes a scan's
#: pose after the scan): three scans of a 10 Hz sensor. Beyond it the newest pose is used, counted.
ODOMETRY_WAIT_S = 0.3
CLOUD_QOS = QoSProfile(history=qos_profile_sensor_data.history, depth=10,
                       reliability=qos_profile_sensor_data.reliability,
                       durability=qos_profile_sensor_data.durability)


def stamp_seconds(stamp) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


class VbrlNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__("vbrl_node", **kwargs)
        self.settings = read_settings(self)
        s = self.settings
        check_topics(self, s)
        check_database_path(s)
        self.model = load_model(s.model_path) if s.model_path else load_default_model()
        self.database = open_database(self.model, s, self.get_logger().info)
        session = s.session_id if s.session_id >= 0 else self.database.next_session()
        if s.session_id >= 0 and str(session) in self.database.sessions:
            # one session is one odometry frame: the gate and matching by place compare its positions
            self.get_logger().warning(
                f"session_id {session} already has keyframes in the database: this run's odometry is taken "
                f"to be in their frame (odometry_drift, sequences matched by place); after odometry "
                f"restarts, give a new session_id or -1")
        self.detector = LoopClosureDetector(self.model, self.database,
                                            replace(s.detector, session=str(session)))
        self.session = session
        # compile (or load from cache) the featurizer kernel now, not on the first keyframe
        self.detector.featurizer.describe(np.zeros((1, 3)))
        self.stats = NodeStats()  # thread-safe itself
        # guards the database, the detector (it appends to the database), the loop edges
        # and the keyframe count since the last save: the worker writes them, the
        # diagnostics timer and the services read or reset them
        self._db_lock = threading.Lock()
        # (points, stamp, pose, arrival) for the worker; (retrieval, arrival) for verification
        self._keyframes: NewestQueue[tuple[np.ndarray, float, np.ndarray | None, float]] = \
            NewestQueue(KEYFRAME_QUEUE)
        self._retrievals: NewestQueue[tuple[Retrieval, float]] = NewestQueue(RETRIEVAL_QUEUE)
        self._verifier = VerifierProcess(self.detector.settings) if s.detector.verify else None
        self._spacing = KeyframeSpacing(s.keyframe_distance, s.keyframe_interval)
        self._pose_history = PoseHistory()
        self._odometry_to_lidar = mounting_matrix(s.odometry_lidar_pose)
        self._odometry_frame: str | None = None  # child_frame_id of the first good odometry
        self._frames_compared = False
        self._gaps = SequenceGaps()
        self._edges: deque[tuple[int, int]] = deque(maxlen=10_000)
        self._keyframes_since_save = 0

        self.closure_pub = self.create_publisher(Float64MultiArray, s.loop_closure_topic, 10)
        self.lio_sam_pub = self.create_publisher(Float64MultiArray, s.lio_sam_topic, 10)
        self.marker_pub = self.create_publisher(MarkerArray, s.markers_topic, 1)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        # serialized: only a keyframe's cloud is deserialized (cloud_intake)
        self.create_subscription(PointCloud2, s.cloud_topic, self._on_cloud, CLOUD_QOS, raw=True)
        if s.odom_topic:
            self.create_subscription(Odometry, s.odom_topic, self._on_odom, 50)
        self.create_service(Trigger, "~/save_database", self._on_save)
        self.create_service(Trigger, "~/clear_database", self._on_clear)
        self.create_timer(s.diagnostics_period, self._publish_status)
        if self._verifier is not None:
            try:
                self._verifier.start()  # before any keyframe: a second or two
            except VerifierError as error:  # tried again at the first keyframe with candidates
                self.get_logger().error(f"verification process not started: {error}")
        self._worker = threading.Thread(target=self._work, name="vbrl-worker", daemon=True)
        self._worker.start()
        self._verification = threading.Thread(target=self._verify, name="vbrl-verification", daemon=True)
        self._verification.start()
        self.get_logger().info(
            f"listening on {s.cloud_topic}; session {session}; {len(self.database)} keyframes in "
            f"memory; distance threshold {self.detector.distance_threshold:.3f} (lower = more similar)"
        )

    # -- callbacks (executor thread): cheap ------------------------------------

    def _on_odom(self, msg: Odometry) -> None:
        self.stats.count("odometry")
        try:
            pose = pose_matrix(msg) @ self._odometry_to_lidar
        except OdometryError as error:
            self.stats.count("bad_odometry")
            self.get_logger().warning(f"odometry skipped: {error}", throttle_duration_sec=5.0)
            return
        self._spacing.moved_to(pose)
        self._pose_history.add(stamp_seconds(msg.header.stamp), pose)
        if self._odometry_frame is None:
            self._odometry_frame = msg.child_frame_id

    def _on_cloud(self, raw: bytes, info: dict) -> None:
        now = time.monotonic()
        self.stats.received(now)
        try:
            stamp, frame = cloud_header(raw)
        except PointCloud2Error as error:
            self.stats.count("malformed")
            self.get_logger().warning(f"malformed PointCloud2 skipped: {error}", throttle_duration_sec=5.0)
            return
        lost = self._gaps.missing_before(frame, info.get("publication_sequence_number"))
        if lost:
            self.stats.count("lost", lost)
        if not self._spacing.is_keyframe(stamp):
            self.stats.count("between_keyframes")
            return
        # Decode here, not in the worker: every bad message is then counted as
        # what it is (instead of vanishing as a "drop" from the mailbox) and
        # never takes a keyframe slot. Decoding takes ~2 ms per 120k points; scoring far more.
        try:
            msg = deserialize_message(raw, PointCloud2)
            points, _ = read_xyz_intensity(msg)
        except (PointCloud2Error, RuntimeError, TypeError) as error:  # rclpy's own failures included
            self.stats.count("malformed")
            self.get_logger().warning(f"malformed PointCloud2 skipped: {error}", throttle_duration_sec=5.0)
            return
        if len(points) == 0:
            self.stats.count("empty")
            self.get_logger().warning("PointCloud2 without finite points skipped", throttle_duration_sec=5.0)
            return
        self._compare_frames(frame)
        self._spacing.mark(stamp)
        if self._keyframes.put((points, stamp, self._spacing.latest_pose, now)):
            self.stats.count("dropped")  # the worker is far behind: the oldest waiting one goes

    def _compare_frames(self, cloud_frame: bytes) -> None:
        """Once odometry and a keyframe have both come: warn if the odometry moves another frame than
        the clouds' (a robot's base_link, say) and no ``odometry_lidar_pose`` says where the LiDAR
        sits on it. Without tf the node cannot look it up, and a LiDAR mounted turned against that
        frame would smear every submap."""
        if self._frames_compared or self._odometry_frame is None:
            return
        self._frames_compared = True
        cloud = cloud_frame.decode(errors="replace")
        uses = [name for name, on in (("submap_keyframes", self.settings.detector.submap_keyframes > 0),
                                      ("level_from_odometry", self.settings.level_from_odometry)) if on]
        mounted = any(self.settings.odometry_lidar_pose)
        if self._odometry_frame and self._odometry_frame != cloud and uses and not mounted:
            self.get_logger().warning(
                f"odometry moves frame '{self._odometry_frame}', the clouds are in '{cloud}': "
                f"{' and '.join(uses)} take odometry as the LiDAR's own motion; set odometry_lidar_pose "
                f"to where the LiDAR sits in '{self._odometry_frame}', or publish odometry of the LiDAR frame")

    # -- worker thread: describe, search, store ----------------------------------

    def _work(self) -> None:
        # a keyframe waiting for the metres after it goes once no keyframe came for as long as
        # the trail ahead reaches in time (none later could join it): the robot stopped, the bag ended
        silence = submap_gap_s(self.detector.settings)
        while True:
            try:
                keyframe = self._keyframes.take(timeout=silence if len(self.detector.trail_ahead) else None)
            except TimeoutError:
                self._process_waiting()
                continue
            if keyframe is None:
                break
            try:
                self._process_due(self._due(*keyframe), arrived=keyframe[-1])
            except Exception as error:  # never let one scan kill the node
                self.stats.count("errors")
                self.get_logger().error(f"keyframe skipped after an unexpected error: {error!r}")
        # stopping: the waiting keyframes are stored (and saved), too late to publish their closures
        self._process_waiting(publish=False)

    def _process_waiting(self, publish: bool = True) -> None:
        try:
            keyframes = self.detector.keyframes_waiting()
        except Exception as error:  # the worker goes on: the next keyframe starts the wait anew
            self.stats.count("errors")
            self.get_logger().error(f"waiting keyframes skipped after an unexpected error: {error!r}")
            return
        self._process_due(keyframes, publish)

    def _due(self, points: np.ndarray, stamp: float, pose: np.ndarray | None, arrived: float) -> list[Keyframe]:
        if pose is not None:  # odometry runs: the pose at the cloud's own stamp, not the newest
            pose, covered = self._pose_history.at(stamp, ODOMETRY_WAIT_S)
            if not covered:
                self.stats.count("late_odometry")
        gravity = gravity_rotation(pose) if self.settings.level_from_odometry and pose is not None else None
        # the keyframes waiting are the worker's alone: no lock
        return self.detector.keyframes_due(points, stamp, pose, gravity, tag=arrived)

    def _process_due(self, keyframes: list[Keyframe], publish: bool = True, arrived: float | None = None) -> None:
        """Describe, search and store ``keyframes``; ``arrived``: when the one just taken came."""
        due = time.monotonic()
        for keyframe in keyframes:
            # its retrieval latency counts from when it was due, not from the metres it waited for;
            # when its closures are decided counts from when it came
            start = keyframe.tag if keyframe.tag == arrived else due
            try:
                self._process(keyframe, start, publish)
            except Exception as error:  # never let one keyframe cost the others
                self.stats.count("errors")
                self.get_logger().error(f"keyframe skipped after an unexpected error: {error!r}")

    def _process(self, keyframe: Keyframe, start: float, publish: bool) -> None:
        arrived = keyframe.tag
        with self._db_lock:
            retrieval = self.detector.retrieve_keyframe(keyframe)
            self._keyframes_since_save += 1
            save_due = bool(self.settings.save_every) and self._keyframes_since_save >= self.settings.save_every
        self.stats.keyframe(1e3 * (time.monotonic() - start))
        if not publish:
            return
        if self._verifier is not None and retrieval.candidates:
            # verified in the other process while this thread takes the next keyframe
            if self._retrievals.put((retrieval, arrived)):
                self.stats.count("unverified")
        else:  # nothing to register: decided here
            self._publish(verify_candidates(retrieval, self.detector.settings), arrived)
        if save_due:
            try:
                self.save_database()
            except OSError as error:  # e.g. a full disk: the keyframe is kept, the save tried again
                self.stats.count("failed_saves")
                self.get_logger().error(f"database not saved: {error}", throttle_duration_sec=5.0)

    # -- verification thread: waits for the verification process ----------------

    def _verify(self) -> None:
        while (item := self._retrievals.take()) is not None:
            retrieval, arrived = item
            try:
                result = self.detector.verified(retrieval, self._verifier.verify, self._db_lock)
            except VerifierError as error:  # the process is started again for the next keyframe
                self.stats.count("verification_errors")
                self.get_logger().error(f"keyframe {retrieval.keyframe_id} not verified: {error}")
                continue
            try:
                self._publish(result, arrived)
            except Exception as error:  # never let one keyframe end verification
                self.stats.count("verification_errors")
                self.get_logger().error(f"closures of keyframe {retrieval.keyframe_id} lost: {error!r}")

    def _publish(self, result: KeyframeResult, arrived: float) -> None:
        with self._db_lock:
            self._edges.extend((closure.query_id, closure.match_id) for closure in result.closures)
        self.stats.decided(1e3 * (time.monotonic() - arrived), len(result.closures),
                           result.rejected_by_verification, result.corroborated, result.handed_on)
        if result.closures:
            self.closure_pub.publish(closures_message(result.closures))
            for closure in result.closures:
                self.lio_sam_pub.publish(lio_sam_message(closure))

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
            self.stats.count("failed_saves")
            response.success, response.message = False, f"save failed: {error}"
        return response

    def _on_clear(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._db_lock:
            count = len(self.database)
            self.detector.clear_database()
            self._edges.clear()
        response.success, response.message = True, f"cleared {count} keyframes"
        return response

    def _publish_status(self) -> None:
        with self._db_lock:  # copies: the markers are built without holding up the worker
            size, waiting = len(self.database), len(self.detector.trail_ahead)
            poses, ids = self.database.poses, self.database.keyframe_ids
            edges = np.array(self._edges, dtype=np.int64).reshape(-1, 2)
        markers = keyframe_markers(poses, ids, edges, self.settings.map_frame, self.get_clock().now().to_msg())
        status = diagnostics_status(self.stats.snapshot(), size, self.session, waiting)
        array = DiagnosticArray()
        array.header.stamp = self.get_clock().now().to_msg()
        array.status = [status]
        self.diag_pub.publish(array)
        if markers is not None:
            self.marker_pub.publish(markers)

    def shutdown(self) -> bool:
        """Stop the worker and verification (finishing the keyframe in hand, storing those waiting
        for the metres after them) and save the database; False if that failed."""
        self._keyframes.close()
        self._worker.join(timeout=30.0)
        self._retrievals.close()
        self._verification.join(timeout=30.0)
        if self._verifier is not None:
            self._verifier.stop()
        if not self.settings.database_path:
            return True
        # stderr, not the ROS logger: after SIGINT/SIGTERM the context
        # (and with it /rosout) is already shut down
        try:
            print(f"[vbrl_node] {self.save_database()}", file=sys.stderr)
        except OSError as error:
            print(f"[vbrl_node] database not saved: {error}", file=sys.stderr)
            return False
        return True
