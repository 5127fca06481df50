"""The first, cheap look at a serialized PointCloud2: its stamp, its frame, and the clouds missing before it.

The node subscribes to clouds serialized (``raw=True``) and reads only the
header here (a few hundred nanoseconds); the whole message (~1 ms for 120k
points) is deserialized only when the cloud becomes a keyframe.

Clouds lost on the way (DDS dropped them: the subscription's queue was full, or
the transport lost a fragment) are counted from the gaps in each publisher's
sequence numbers, which rclpy hands every callback. rclpy does not say which
publisher sent a message, so publishers are told apart by the cloud's
``frame_id``: one sensor, one frame. A sequence number that goes back (a
restarted driver) starts the count afresh.
"""

from __future__ import annotations

import struct

from vbrl_ros.io.pointcloud2 import PointCloud2Error

#: CDR encapsulation kinds (second byte of the serialized message) -> struct byte order.
BYTE_ORDERS = {0: ">", 1: "<"}
# encapsulation (4 bytes), stamp sec (4) and nanosec (4), frame_id length (4)
_HEADER = struct.Struct("iII")
_HEADER_END = 4 + _HEADER.size
#: Distinct frames followed at once; more (a fuzzer, a misconfigured driver) start afresh.
MAX_STREAMS = 64


def cloud_header(raw: bytes) -> tuple[float, bytes]:
    """(stamp in seconds, frame_id as bytes) of a serialized ``sensor_msgs/PointCloud2``."""
    if len(raw) < _HEADER_END or raw[1] not in BYTE_ORDERS:
        raise PointCloud2Error(f"serialized PointCloud2 of {len(raw)} bytes has no CDR header")
    sec, nanosec, length = struct.unpack_from(BYTE_ORDERS[raw[1]] + _HEADER.format, raw, 4)
    frame = bytes(raw[_HEADER_END:_HEADER_END + max(length - 1, 0)])  # without the terminating NUL
    return sec + 1e-9 * nanosec, frame


class SequenceGaps:
    """Counts the messages missing between consecutive publication sequence numbers, per stream."""

    def __init__(self) -> None:
        self._last: dict[bytes, int] = {}

    def missing_before(self, stream: bytes, sequence: int | None) -> int:
        """How many of ``stream``'s messages never arrived between the last one seen and this one."""
        if sequence is None or sequence <= 0:  # an RMW that does not number its messages
            return 0
        last = self._last.get(stream)
        if last is None and len(self._last) >= MAX_STREAMS:
            self._last.clear()
        self._last[stream] = sequence
        return sequence - last - 1 if last is not None and sequence > last else 0
