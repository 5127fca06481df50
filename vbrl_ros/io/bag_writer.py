"""Write LiDAR scans (and their poses) to a real ROS bag with rosbags.

ROS 2 bags (mcap or sqlite3 storage) are directories; ROS 1 bags are single
``.bag`` files. Scans are streamed: ``scans`` may be a generator and only one
scan is held at a time. If anything goes wrong (bad scan, count mismatch,
interruption) the partly written output is removed, so a path either holds a
complete bag or nothing that this function created.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from vbrl_ros.io.pointcloud2 import FLOAT32, split_stamp, to_rosbags_msg

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"
POSE_STAMPED_TYPE = "geometry_msgs/msg/PoseStamped"
CLOUD_FIELDS = ("x", "y", "z", "intensity")


def _validated_poses(poses: np.ndarray | None, count: int) -> np.ndarray | None:
    if poses is None:
        return None
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (count, 4, 4):
        raise ValueError(f"poses must have shape ({count}, 4, 4) (one per stamp), got {poses.shape}")
    if not np.isfinite(poses).all():
        raise ValueError("poses contain non-finite values")
    return poses


class _MessageFactory:
    """Builds the header-carrying rosbags messages for one typestore (ROS 1 or ROS 2)."""

    def __init__(self, typestore: Any) -> None:
        self.types = typestore.types
        self.typestore = typestore
        self.with_seq = "seq" in self.types["std_msgs/msg/Header"].__dataclass_fields__
        self.seq: dict[str, int] = {}

    def header(self, topic: str, stamp: tuple[int, int], frame_id: str) -> Any:
        extra = {}
        if self.with_seq:  # ROS 1 headers count messages per topic
            extra["seq"] = self.seq[topic] = self.seq.get(topic, -1) + 1
        time = self.types["builtin_interfaces/msg/Time"](sec=stamp[0], nanosec=stamp[1])
        return self.types["std_msgs/msg/Header"](stamp=time, frame_id=frame_id, **extra)

    def pose(self, transform: np.ndarray, quaternion_xyzw: np.ndarray) -> Any:
        position = self.types["geometry_msgs/msg/Point"](*(float(v) for v in transform[:3, 3]))
        orientation = self.types["geometry_msgs/msg/Quaternion"](*(float(v) for v in quaternion_xyzw))
        return self.types["geometry_msgs/msg/Pose"](position=position, orientation=orientation)

    def odometry(self, topic: str, stamp: tuple[int, int], frame: str, child: str, pose: Any) -> Any:
        covariance = np.zeros(36, dtype=np.float64)
        vector3 = self.types["geometry_msgs/msg/Vector3"]
        twist = self.types["geometry_msgs/msg/Twist"](linear=vector3(0.0, 0.0, 0.0), angular=vector3(0.0, 0.0, 0.0))
        return self.types[ODOMETRY_TYPE](
            header=self.header(topic, stamp, frame),
            child_frame_id=child,
            pose=self.types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=covariance),
            twist=self.types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=covariance.copy()),
        )

    def pose_stamped(self, topic: str, stamp: tuple[int, int], frame: str, pose: Any) -> Any:
        return self.types[POSE_STAMPED_TYPE](header=self.header(topic, stamp, frame), pose=pose)


def _open_writer(path: Path, storage: str, ros1: bool) -> tuple[Any, Any]:
    from rosbags.typesys import Stores, get_typestore

    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        if path.suffix != ".bag":
            raise ValueError(f"a ROS 1 bag path must end in .bag (readers detect ROS 1 by it): {path}")
        return Writer1(path), get_typestore(Stores.ROS1_NOETIC)
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2

    plugins = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
    if storage not in plugins:
        raise ValueError(f"storage must be one of {sorted(plugins)}, got {storage!r}")
    return Writer2(path, version=Writer2.VERSION_LATEST, storage_plugin=plugins[storage]), get_typestore(
        Stores.ROS2_JAZZY
    )


def write_scan_bag(
    path: str | Path,
    scans: Iterable[np.ndarray],
    stamps: Sequence[float] | np.ndarray,
    poses: np.ndarray | None = None,
    *,
    storage: str = "mcap",
    cloud_topic: str = "/points",
    odom_topic: str = "/odom",
    ground_truth_topic: str = "/ground_truth",
    frame_id: str = "lidar",
    odom_frame: str = "odom",
    ros1: bool = False,
    progress: bool = False,
) -> Path:
    """Write one PointCloud2 per scan (+ Odometry and PoseStamped per pose) and return the bag path.

    ``scans``: iterable of (N, 4) arrays (x, y, z, intensity; sensor frame),
    written as FLOAT32 fields. ``stamps``: seconds, one per scan; each
    message's header stamp and bag log time are this stamp. ``poses``:
    optional (n, 4, 4) T_world_lidar; each becomes a ``nav_msgs/Odometry``
    on ``odom_topic`` (frame ``odom_frame``, child ``frame_id``) and a
    ``geometry_msgs/PoseStamped`` on ``ground_truth_topic`` (frame
    ``odom_frame``). ROS 2 (``storage`` "mcap" or "sqlite3") writes a bag
    directory at ``path``; ``ros1=True`` writes a ``.bag`` file (``storage``
    is then ignored). ``path`` must not exist.
    """
    path = Path(path)
    stamp_values = np.asarray(stamps, dtype=np.float64).reshape(-1)
    if not np.isfinite(stamp_values).all():
        raise ValueError("stamps contain non-finite values")
    count = len(stamp_values)
    poses = _validated_poses(poses, count)
    if path.exists():
        raise FileExistsError(f"{path} exists already; not overwriting")
    quaternions = Rotation.from_matrix(poses[:, :3, :3]).as_quat() if poses is not None else None
    writer, typestore = _open_writer(path, storage, ros1)
    serialize = typestore.serialize_ros1 if ros1 else typestore.serialize_cdr
    factory = _MessageFactory(typestore)
    try:
        with writer, tqdm(total=count, desc=f"writing {path.name}", unit="scan", disable=not progress) as bar:
            clouds = writer.add_connection(cloud_topic, CLOUD_TYPE, typestore=typestore)
            if poses is not None:
                odometry = writer.add_connection(odom_topic, ODOMETRY_TYPE, typestore=typestore)
                ground_truth = writer.add_connection(ground_truth_topic, POSE_STAMPED_TYPE, typestore=typestore)
            written = 0
            for index, scan in enumerate(scans):
                if index >= count:
                    raise ValueError(f"more scans than stamps ({count})")
                scan = np.asarray(scan)
                if scan.ndim != 2 or scan.shape[1] != 4:
                    raise ValueError(f"scan {index} has shape {scan.shape}, expected (N, 4) x, y, z, intensity")
                stamp = split_stamp(float(stamp_values[index]))
                log_time = stamp[0] * 1_000_000_000 + stamp[1]
                cloud = to_rosbags_msg(scan, CLOUD_FIELDS, typestore=typestore, stamp=stamp, frame_id=frame_id,
                                       datatypes=FLOAT32)
                if factory.with_seq:
                    cloud.header.seq = index
                writer.write(clouds, log_time, serialize(cloud, CLOUD_TYPE))
                if poses is not None:
                    pose = factory.pose(poses[index], quaternions[index])
                    odom = factory.odometry(odom_topic, stamp, odom_frame, frame_id, pose)
                    writer.write(odometry, log_time, serialize(odom, ODOMETRY_TYPE))
                    truth = factory.pose_stamped(ground_truth_topic, stamp, odom_frame, pose)
                    writer.write(ground_truth, log_time, serialize(truth, POSE_STAMPED_TYPE))
                written += 1
                bar.update()
            if written != count:
                raise ValueError(f"got {written} scans for {count} stamps")
    except BaseException:
        # The writer has aborted; remove what it left so no half bag survives.
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        elif path.exists():
            path.unlink()
        raise
    return path
