"""rclpy messages from rosbags messages (replay) and from numpy points (tests, tools).

Message packages are imported where used: ``vbrl --help`` imports this module.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from vbrl_ros.io.pointcloud2 import Stamp, encode_cloud, split_stamp

CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"


class MessageTypeError(ValueError):
    """A message type whose package is not installed (one line)."""


def message_class(msgtype: str) -> type:
    """``"nav_msgs/msg/Odometry"`` -> the rclpy class, or a MessageTypeError if its package is missing."""
    package, _, name = msgtype.rpartition("/")
    try:
        return getattr(importlib.import_module(package.replace("/", ".")), name)
    except (ImportError, AttributeError):
        raise MessageTypeError(f"message type {msgtype} is not installed in this Python environment") from None


def copy_into(dst: Any, src: Any) -> Any:
    """Copy a rosbags message into an rclpy message field by field (ROS 1 ``seq`` and other extras are dropped)."""
    from rosidl_parser.definition import AbstractNestedType, NamespacedType

    for name, slot in zip(dst.get_fields_and_field_types(), dst.SLOT_TYPES):
        value = getattr(src, name)
        if isinstance(slot, NamespacedType):
            copy_into(getattr(dst, name), value)
        elif isinstance(slot, AbstractNestedType) and isinstance(slot.value_type, NamespacedType):
            element = message_class("/".join((*slot.value_type.namespaces, slot.value_type.name)))
            setattr(dst, name, [copy_into(element(), item) for item in value])
        elif isinstance(value, np.ndarray) and value.dtype == np.uint8:
            setattr(dst, name, value.tobytes())  # bytes: numpy into rclpy uint8[] is ~200x slower
        else:
            setattr(dst, name, value)
    return dst


def cloud_to_rclpy(src: Any) -> Any:
    """The hot path: PointCloud2 without per-field introspection, ``data`` as one bytes copy."""
    from sensor_msgs.msg import PointCloud2, PointField

    msg = PointCloud2()
    msg.header.stamp.sec, msg.header.stamp.nanosec = int(src.header.stamp.sec), int(src.header.stamp.nanosec)
    msg.header.frame_id = src.header.frame_id
    msg.height, msg.width = int(src.height), int(src.width)
    msg.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in src.fields]
    msg.is_bigendian, msg.is_dense = bool(src.is_bigendian), bool(src.is_dense)
    msg.point_step, msg.row_step = int(src.point_step), int(src.row_step)
    msg.data = np.asarray(src.data, dtype=np.uint8).tobytes()
    return msg


def converter_for(msgtype: str) -> Callable[[Any], Any]:
    """A function turning a rosbags-deserialised ``msgtype`` into the matching rclpy message."""
    if msgtype == CLOUD_TYPE:
        return cloud_to_rclpy
    cls = message_class(msgtype)
    return lambda src: copy_into(cls(), src)


def to_ros_msg(points: np.ndarray, field_names: Sequence[str] | None = None, *, stamp: Stamp = 0.0,
               frame_id: str = "", **encode_options: Any) -> Any:
    """Build an rclpy ``sensor_msgs.msg.PointCloud2`` (see :func:`encode_cloud`)."""
    from sensor_msgs.msg import PointCloud2, PointField

    cloud = encode_cloud(points, field_names, **encode_options)
    msg = PointCloud2()
    msg.header.stamp.sec, msg.header.stamp.nanosec = split_stamp(stamp)
    msg.header.frame_id = frame_id
    msg.height, msg.width = cloud.height, cloud.width
    msg.fields = [PointField(name=f.name, offset=f.offset, datatype=f.datatype, count=f.count) for f in cloud.fields]
    msg.is_bigendian = cloud.is_bigendian
    msg.point_step, msg.row_step = cloud.point_step, cloud.row_step
    msg.data = cloud.data  # bytes: assigning a numpy array here is ~100x slower in rclpy
    msg.is_dense = cloud.is_dense
    return msg
