"""ROS 1 and ROS 2 bags as a ScanSource, through ``rosbags.highlevel.AnyReader``.

Accepted paths: a ROS 2 bag directory (``metadata.yaml`` + ``.db3``/``.mcap``),
one of its ``.db3``/``.mcap`` files, a ROS 1 ``.bag`` file, or a directory of
ROS 1 ``.bag`` files (a split recording, replayed in time order).

Cost model (the bag is never loaded at once; one scan is decoded at a time):

* opening reads only the bag's metadata / indexes;
* ``iter(src)`` is one sequential pass over the cloud topic;
* ``src.stamps`` and random access ``src[i]`` need an index of the cloud
  messages (bag log time + header stamp per message). It is built once, by
  one sequential pass that reads the cloud topic's bytes but deserialises
  nothing, or for free by a completed ``iter(src)``;
* ``src[i]`` then re-reads message i from the bag by its log time: for
  indexed mcap, sqlite3 and ROS 1 bags that touches one chunk / one row, not
  the whole bag.

A scan's stamp is its header stamp, or the bag log time when the header
stamp is zero (publishers that leave it unset).
"""

from __future__ import annotations

import contextlib
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from vbrl_ros.datasets.base import Scan, ScanSource, ScanSourceError
from vbrl_ros.io.pointcloud2 import PointCloud2Error, read_xyz_intensity

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
TF_TYPE = "tf2_msgs/msg/TFMessage"
# Pose message types -> how to reach their geometry_msgs/Pose.
POSE_GETTERS = {
    "nav_msgs/msg/Odometry": lambda msg: msg.pose.pose,
    "geometry_msgs/msg/PoseStamped": lambda msg: msg.pose,
    "geometry_msgs/msg/PoseWithCovarianceStamped": lambda msg: msg.pose.pose,
}


class BagTopicError(ScanSourceError):
    """The requested topic is missing, ambiguous or of the wrong type."""


def bag_paths(path: Path) -> list[Path]:
    """The paths AnyReader needs for ``path`` (see module docstring), or a clear error."""
    if not path.exists():
        raise ScanSourceError(f"{path}: no such bag file or directory")
    if path.is_file():
        if path.suffix == ".bag":
            return [path]
        if path.suffix in (".db3", ".mcap"):
            if (path.parent / "metadata.yaml").is_file():
                return [path.parent]
            raise ScanSourceError(f"{path}: a ROS 2 bag file needs the metadata.yaml of its bag directory beside it")
        raise ScanSourceError(f"{path}: not a bag (expected .bag, .db3, .mcap or a bag directory)")
    if (path / "metadata.yaml").is_file():
        return [path]
    if ros1_bags := sorted(path.glob("*.bag")):
        return ros1_bags
    raise ScanSourceError(f"{path}: directory holds neither a ROS 2 bag (metadata.yaml) nor ROS 1 .bag files")


def header_stamp_ns(rawdata: bytes | memoryview, ros1: bool) -> int:
    """Header stamp (ns) of a serialised message that starts with std_msgs/Header; 0 if unreadable.

    ROS 1: uint32 seq, uint32 sec, uint32 nsec (little-endian). ROS 2 CDR:
    4-byte encapsulation (byte 1 odd = little-endian), int32 sec, uint32 nanosec.
    Both put the stamp at bytes 4..12.
    """
    if len(rawdata) < 12:
        return 0
    order = "<" if ros1 or rawdata[1] & 1 else ">"
    sec, nanosec = struct.unpack_from(order + ("I" if ros1 else "i") + "I", rawdata, 4)
    return sec * 1_000_000_000 + nanosec


def _time_ns(stamp: Any) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def transforms_to_matrices(translations: np.ndarray, quaternions_xyzw: np.ndarray, where: str) -> np.ndarray:
    """(n, 3) translations + (n, 4) quaternions -> (n, 4, 4) transforms."""
    matrices = np.tile(np.eye(4), (len(translations), 1, 1))
    if len(translations) == 0:
        return matrices
    norms = np.linalg.norm(quaternions_xyzw, axis=1)
    if not (np.isfinite(norms).all() and (norms > 1e-6).all() and np.isfinite(translations).all()):
        raise ScanSourceError(f"{where}: a pose has a zero or non-finite quaternion or translation")
    matrices[:, :3, :3] = Rotation.from_quat(quaternions_xyzw).as_matrix()
    matrices[:, :3, 3] = translations
    return matrices


@dataclass(frozen=True)
class _CloudIndex:
    log_ns: np.ndarray  # (n,) int64 bag log time of each cloud message
    occurrence: np.ndarray  # (n,) int64 rank among messages sharing that log time
    stamps: np.ndarray  # (n,) float64 seconds


class _IndexBuilder:
    def __init__(self) -> None:
        self.log_ns: list[int] = []
        self.occurrence: list[int] = []
        self.stamps_ns: list[int] = []

    def add(self, log_ns: int, header_ns: int) -> int:
        repeated = self.occurrence[-1] + 1 if self.log_ns and self.log_ns[-1] == log_ns else 0
        self.log_ns.append(log_ns)
        self.occurrence.append(repeated)
        self.stamps_ns.append(header_ns if header_ns > 0 else log_ns)
        return self.stamps_ns[-1]

    def build(self) -> _CloudIndex:
        return _CloudIndex(np.array(self.log_ns, dtype=np.int64), np.array(self.occurrence, dtype=np.int64),
                           np.array(self.stamps_ns, dtype=np.int64) / 1e9)


class RosbagSource(ScanSource):
    """The PointCloud2 messages of one topic of a bag; see the module docstring for costs."""

    def __init__(self, path: str | Path, *, topic: str | None = None) -> None:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore

        self.path = Path(path)
        super().__init__(self.path.stem if self.path.is_file() else self.path.name)
        paths = bag_paths(self.path)
        try:
            self._reader = AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_JAZZY))
            self._reader.open()
        except (AnyReaderError, OSError) as error:
            raise ScanSourceError(f"{self.path}: cannot open bag: {error}") from None
        self.is_ros1 = not self._reader.is2
        self.topic = self._select_cloud_topic(topic)
        self._connections = [c for c in self._reader.connections if c.topic == self.topic]
        self._count = self._reader.topics[self.topic].msgcount
        self._index: _CloudIndex | None = None

    # ----------------------------------------------------------------------- topics

    def topics_of_type(self, *msgtypes: str) -> list[str]:
        return sorted(topic for topic, info in self._reader.topics.items() if info.msgtype in msgtypes)

    def _select_cloud_topic(self, topic: str | None) -> str:
        clouds = self.topics_of_type(CLOUD_TYPE)
        listing = ", ".join(clouds) or "none"
        if topic is None:
            if len(clouds) == 1:
                return clouds[0]
            if not clouds:
                raise BagTopicError(f"{self.path}: no {CLOUD_TYPE} topic in the bag (topics: "
                                    f"{', '.join(sorted(self._reader.topics)) or 'none'})")
            raise BagTopicError(f"{self.path}: several {CLOUD_TYPE} topics; choose one with topic=: {listing}")
        if topic not in clouds:
            info = self._reader.topics.get(topic)
            found = f"'{topic}' is a {info.msgtype} topic" if info else f"no topic '{topic}'"
            raise BagTopicError(f"{self.path}: {found}; {CLOUD_TYPE} topics: {listing}")
        return topic

    # ----------------------------------------------------------------------- scans

    def __len__(self) -> int:
        return len(self._index.log_ns) if self._index is not None else self._count

    @property
    def stamps(self) -> np.ndarray:
        return self._ensure_index().stamps

    def _ensure_index(self) -> _CloudIndex:
        if self._index is None:
            builder = _IndexBuilder()
            for _, log_ns, rawdata in self._reader.messages(self._connections):
                builder.add(log_ns, header_stamp_ns(rawdata, self.is_ros1))
            self._index = builder.build()
        return self._index

    def _decode(self, rawdata: bytes, msgtype: str, index: int, stamp: float) -> Scan:
        try:
            msg = self._reader.deserialize(rawdata, msgtype)
            points, intensity = read_xyz_intensity(msg)
        except PointCloud2Error as error:
            raise PointCloud2Error(f"{self.path} {self.topic} message {index}: {error}") from None
        except Exception as error:  # rosbags' deserialisation errors: corrupt message bytes
            raise ScanSourceError(f"{self.path} {self.topic} message {index}: cannot deserialise: {error}") from None
        return Scan(points, intensity, stamp, index)

    def read_scan(self, index: int) -> Scan:
        cloud_index = self._ensure_index()
        log_ns = int(cloud_index.log_ns[index])
        wanted = int(cloud_index.occurrence[index])
        messages = self._reader.messages(self._connections, start=log_ns, stop=log_ns + 1)
        for rank, (connection, _, rawdata) in enumerate(messages):
            if rank == wanted:
                return self._decode(rawdata, connection.msgtype, index, float(cloud_index.stamps[index]))
        raise ScanSourceError(f"{self.path} {self.topic}: message {index} vanished from the bag")

    def __iter__(self) -> Iterator[Scan]:
        builder = _IndexBuilder()
        for index, (connection, log_ns, rawdata) in enumerate(self._reader.messages(self._connections)):
            stamp_ns = builder.add(log_ns, header_stamp_ns(rawdata, self.is_ros1))
            yield self._decode(rawdata, connection.msgtype, index, stamp_ns / 1e9)
        if self._index is None:  # a full pass is a free index
            self._index = builder.build()

    # ----------------------------------------------------------------------- poses recorded in the bag

    def pose_samples(self, topic: str) -> tuple[np.ndarray, np.ndarray]:
        """(stamps (m,) seconds, poses (m, 4, 4)) of an Odometry / PoseStamped / PoseWithCovarianceStamped topic."""
        info = self._reader.topics.get(topic)
        if info is None or info.msgtype not in POSE_GETTERS:
            found = f"'{topic}' is a {info.msgtype} topic" if info else f"no topic '{topic}'"
            listing = ", ".join(self.topics_of_type(*POSE_GETTERS)) or "none"
            raise BagTopicError(f"{self.path}: {found}; pose topics: {listing}")
        get_pose = POSE_GETTERS[info.msgtype]
        connections = [c for c in self._reader.connections if c.topic == topic]
        stamps_ns, translations, quaternions = [], [], []
        for connection, log_ns, rawdata in self._reader.messages(connections):
            msg = self._reader.deserialize(rawdata, connection.msgtype)
            pose = get_pose(msg)
            stamps_ns.append(_time_ns(msg.header.stamp) or log_ns)
            translations.append((pose.position.x, pose.position.y, pose.position.z))
            quaternions.append((pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w))
        poses = transforms_to_matrices(np.array(translations).reshape(-1, 3), np.array(quaternions).reshape(-1, 4),
                                       f"{self.path} {topic}")
        return np.array(stamps_ns, dtype=np.int64) / 1e9, poses

    def _messages_of(self, connections: list) -> Iterator[tuple[Any, int, bytes]]:
        """The messages of ``connections``; none for none (rosbags reads every connection then)."""
        return self._reader.messages(connections) if connections else iter(())

    def cloud_frame(self) -> str:
        """The ``frame_id`` of the first cloud ('' when the bag has none or leaves it empty)."""
        for connection, _, rawdata in self._reader.messages(self._connections):
            return self._reader.deserialize(rawdata, connection.msgtype).header.frame_id.lstrip("/")
        return ""

    def moved_frame(self, topic: str) -> str:
        """The frame an Odometry topic moves (its first message's ``child_frame_id``); '' for the
        other pose types, which do not say."""
        for connection, _, rawdata in self._messages_of([c for c in self._reader.connections if c.topic == topic]):
            if connection.msgtype != "nav_msgs/msg/Odometry":
                return ""
            return self._reader.deserialize(rawdata, connection.msgtype).child_frame_id.lstrip("/")
        return ""

    def tf_samples(self, *, static_only: bool = False) -> dict[tuple[str, str], tuple[np.ndarray, np.ndarray, bool]]:
        """Every tf edge in the bag: (parent, child) -> (stamps (m,), T_parent_child (m, 4, 4), static).

        Reads every TFMessage topic (``static_only``: only ``.../tf_static``, a few messages where
        ``/tf`` may hold millions); an edge is static when it came on a topic named
        ``.../tf_static``. Leading '/' of ROS 1 frame ids is dropped.
        """
        topics = [t for t in self.topics_of_type(TF_TYPE) if not static_only or t.rstrip("/").endswith("tf_static")]
        connections = [c for c in self._reader.connections if c.topic in topics]
        raw: dict[tuple[str, str], tuple[list[int], list[tuple], list[tuple], bool]] = {}
        for connection, log_ns, rawdata in self._messages_of(connections):
            static = connection.topic.rstrip("/").endswith("tf_static")
            for transform in self._reader.deserialize(rawdata, connection.msgtype).transforms:
                edge = (transform.header.frame_id.lstrip("/"), transform.child_frame_id.lstrip("/"))
                stamps, translations, rotations, was_static = raw.setdefault(edge, ([], [], [], static))
                t, q = transform.transform.translation, transform.transform.rotation
                stamps.append(_time_ns(transform.header.stamp) or log_ns)
                translations.append((t.x, t.y, t.z))
                rotations.append((q.x, q.y, q.z, q.w))
                raw[edge] = (stamps, translations, rotations, was_static or static)
        return {
            edge: (np.array(stamps, dtype=np.int64) / 1e9,
                   transforms_to_matrices(np.array(translations), np.array(rotations), f"{self.path} tf {edge}"),
                   static)
            for edge, (stamps, translations, rotations, static) in raw.items()
        }

    # ----------------------------------------------------------------------- lifetime

    def close(self) -> None:
        reader = getattr(self, "_reader", None)
        if reader is not None and reader.stack is not None:
            reader.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # at interpreter exit rosbags may be half torn down
            self.close()
