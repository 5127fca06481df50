"""Diagnostics and RViz markers of the node: what an operator looks at."""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point
from visualization_msgs.msg import Marker, MarkerArray

from vbrl_ros.ros.node_stats import StatsSnapshot


def diagnostics_status(stats: StatsSnapshot, database_size: int, session: int,
                       keyframes_waiting: int = 0) -> DiagnosticStatus:
    p50, p90, p99 = stats.latency_ms
    r50, r90, r99 = stats.retrieval_latency_ms
    values = {
        "input_rate_hz": f"{stats.input_rate_hz:.2f}",
        "scans_received": stats.scans,
        "scans_lost": stats.lost,
        "scans_between_keyframes": stats.between_keyframes,
        "keyframes_processed": stats.keyframes,
        "keyframes_waiting": keyframes_waiting,
        "loop_closures": stats.closures,
        "corroborated_closures": stats.corroborated,
        "closures_to_nearer_keyframe": stats.handed_on,
        "rejected_by_verification": stats.rejected_by_verification,
        "dropped_scans": stats.dropped,
        "unverified_keyframes": stats.unverified,
        "verification_errors": stats.verification_errors,
        "malformed_scans": stats.malformed,
        "empty_scans": stats.empty,
        "processing_errors": stats.errors,
        "failed_saves": stats.failed_saves,
        "odometry_received": stats.odometry,
        "bad_odometry": stats.bad_odometry,
        "late_odometry": stats.late_odometry,
        "latency_p50_ms": f"{p50:.1f}",
        "latency_p90_ms": f"{p90:.1f}",
        "latency_p99_ms": f"{p99:.1f}",
        "retrieval_latency_p50_ms": f"{r50:.1f}",
        "retrieval_latency_p90_ms": f"{r90:.1f}",
        "retrieval_latency_p99_ms": f"{r99:.1f}",
        "database_size": database_size,
        "session_id": session,
    }
    problems = stats.problems
    status = DiagnosticStatus(
        name="vbrl_node: loop closure",
        hardware_id="vbrl",
        level=DiagnosticStatus.WARN if problems else DiagnosticStatus.OK,
        message="lost, dropped or skipped scans or odometry, or failed saves (see values)" if problems else "ok",
    )
    status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
    return status


def keyframe_markers(poses: np.ndarray, keyframe_ids: np.ndarray, edges: np.ndarray, frame: str,
                     stamp: Time) -> MarkerArray | None:
    """Keyframe positions (spheres) and loop edges (lines); None when no pose is known.

    ``poses`` (n, 4, 4) and increasing ``keyframe_ids`` (n,) of the database's keyframes,
    ``edges`` (m, 2) keyframe ids of the query and match of each loop closure: copies, so
    that the worker may go on changing the originals meanwhile.
    """
    positions = poses[:, :3, 3]
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
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if len(keyframe_ids) and len(edges):
        rows = np.minimum(np.searchsorted(keyframe_ids, edges), len(keyframe_ids) - 1)
        # both ends still stored (a clear or another session's database drops them) and placed
        kept = (keyframe_ids[rows] == edges).all(axis=1) & known[rows].all(axis=1)
        ends = positions[rows[kept]].reshape(-1, 3)
        lines.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in ends]
    return MarkerArray(markers=[nodes, lines])
