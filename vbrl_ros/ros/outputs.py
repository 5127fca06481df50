"""Diagnostics and RViz markers of the node: what an operator looks at."""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point
from visualization_msgs.msg import Marker, MarkerArray

from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.detector import KeyframeResult

RATE_WINDOW_S = 5.0


@dataclass
class NodeStats:
    """Counters and recent timings; written by the callbacks and the worker."""

    scans: int = 0
    between_keyframes: int = 0  # valid or not, too close to the last keyframe to be one
    keyframes: int = 0
    closures: int = 0
    rejected_by_verification: int = 0
    dropped: int = 0
    malformed: int = 0
    empty: int = 0
    errors: int = 0
    failed_saves: int = 0
    odometry: int = 0
    bad_odometry: int = 0
    arrivals: deque = field(default_factory=lambda: deque(maxlen=2000))
    latencies_ms: deque = field(default_factory=lambda: deque(maxlen=1000))

    def received(self, now: float) -> None:
        self.scans += 1
        self.arrivals.append(now)

    def keyframe(self, latency_ms: float, result: KeyframeResult) -> None:
        self.keyframes += 1
        self.closures += len(result.closures)
        self.rejected_by_verification += result.rejected_by_verification
        self.latencies_ms.append(latency_ms)

    def input_rate(self, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        recent = [t for t in list(self.arrivals) if now - t <= RATE_WINDOW_S]
        return len(recent) / RATE_WINDOW_S

    def latency_percentiles(self) -> tuple[float, float, float]:
        values = np.array(list(self.latencies_ms))
        if len(values) == 0:
            return (float("nan"),) * 3
        p50, p90, p99 = np.percentile(values, [50, 90, 99])
        return float(p50), float(p90), float(p99)


def diagnostics_status(stats: NodeStats, database_size: int, session: int) -> DiagnosticStatus:
    p50, p90, p99 = stats.latency_percentiles()
    values = {
        "input_rate_hz": f"{stats.input_rate():.2f}",
        "scans_received": stats.scans,
        "scans_between_keyframes": stats.between_keyframes,
        "keyframes_processed": stats.keyframes,
        "loop_closures": stats.closures,
        "rejected_by_verification": stats.rejected_by_verification,
        "dropped_scans": stats.dropped,
        "malformed_scans": stats.malformed,
        "empty_scans": stats.empty,
        "processing_errors": stats.errors,
        "failed_saves": stats.failed_saves,
        "odometry_received": stats.odometry,
        "bad_odometry": stats.bad_odometry,
        "latency_p50_ms": f"{p50:.1f}",
        "latency_p90_ms": f"{p90:.1f}",
        "latency_p99_ms": f"{p99:.1f}",
        "database_size": database_size,
        "session_id": session,
    }
    problems = (stats.malformed + stats.empty + stats.errors + stats.dropped + stats.bad_odometry
                + stats.failed_saves)
    status = DiagnosticStatus(
        name="vbrl_node: loop closure",
        hardware_id="vbrl",
        level=DiagnosticStatus.WARN if problems else DiagnosticStatus.OK,
        message="dropped or skipped scans or odometry, or failed saves (see values)" if problems else "ok",
    )
    status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
    return status


def keyframe_markers(
    database: KeyframeDatabase, edges: Iterable[tuple[int, int]], frame: str, stamp: Time
) -> MarkerArray | None:
    """Keyframe positions (spheres) and loop edges (lines); None when no pose is known."""
    positions = database.poses[:, :3, 3]
    known = np.isfinite(positions).all(axis=1)
    if not known.any():
        return None
    nodes = Marker(ns="vbrl_keyframes", id=0, type=Marker.SPHERE_LIST, action=Marker.ADD)
    nodes.header.frame_id, nodes.header.stamp = frame, stamp
    nodes.scale.x = nodes.scale.y = nodes.scale.z = 0.4
    nodes.color.r, nodes.color.g, nodes.color.b, nodes.color.a = 0.2, 0.6, 1.0, 1.0
    nodes.pose.orientation.w = 1.0
    nodes.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in positions[known]]
    lines = Marker(ns="vbrl_loops", id=1, type=Marker.LINE_LIST, action=Marker.ADD)
    lines.header.frame_id, lines.header.stamp = frame, stamp
    lines.scale.x = 0.15
    lines.color.r, lines.color.g, lines.color.b, lines.color.a = 1.0, 0.3, 0.1, 1.0
    lines.pose.orientation.w = 1.0
    ids = database.keyframe_ids
    for query_id, match_id in edges:
        a, b = np.searchsorted(ids, [query_id, match_id])
        if a < len(ids) and b < len(ids) and ids[a] == query_id and ids[b] == match_id:
            if known[a] and known[b]:
                lines.points += [Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                                 for p in (positions[a], positions[b])]
    return MarkerArray(markers=[nodes, lines])
