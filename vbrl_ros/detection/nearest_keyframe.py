"""A verified closure goes to the stored keyframe nearest the query along its match's path.

Retrieval finds a place, not the nearest keyframe of it: translation search, sequences matched
by place and submaps all tolerate a few metres between a revisit and the keyframe ranked first,
on purpose. The registration then says where the query sensor stood in the match's odometry
frame, so the closure is handed to the stored keyframe of the match's session nearest that
place, among those within :data:`REACH_M` of driving of the match, with ``T_query_match``
composed through odometry between the two (good to centimetres over a few metres). A back-end
gets the shortest edge, to the keyframe whose cloud overlaps the query most, and a revisit
2.6 m from a keyframe is no longer published onto its neighbour 3.4 m away.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vbrl_ros.detection.corroboration import registered_position

#: Metres of driving either side of the registered keyframe a closure may move along: odometry
#: over that stretch is good to centimetres, and a registration within ``max_closure_distance``
#: (5 m by default) of its keyframe is never nearer to one farther along.
REACH_M = 5.0


class PathNeighbours(NamedTuple):
    """Stored keyframes along a stretch of one session's path, in order."""

    rows: np.ndarray  # (k,) database rows
    keyframe_ids: np.ndarray  # (k,)
    stamps: np.ndarray  # (k,) seconds
    poses: np.ndarray  # (k, 4, 4) T_world_lidar, NaN where unknown


def rows_along_path(row: int, sessions: np.ndarray, paths: np.ndarray, reach_m: float = REACH_M) -> np.ndarray:
    """Rows next to ``row``, in order, of its session (``sessions`` (n,)) and within ``reach_m`` of
    its metres driven (``paths`` (n,)), ``row`` included; only ``row`` where its path is unknown."""
    here = paths[row]
    if not np.isfinite(here):
        return np.array([row])

    def near(r: int) -> bool:
        return bool(sessions[r] == sessions[row] and abs(paths[r] - here) <= reach_m)  # NaN: False

    first, last = row, row
    while first > 0 and near(first - 1):
        first -= 1
    while last + 1 < len(paths) and near(last + 1):
        last += 1
    return np.arange(first, last + 1)


def nearest_along_path(T_query_match: np.ndarray, match_pose: np.ndarray, rows: np.ndarray,
                       poses: np.ndarray, match_row: int) -> tuple[int, np.ndarray]:
    """(row, T_query_row): of ``rows`` (with ``poses`` (k, 4, 4) T_world_lidar, ``match_row`` among
    them at ``match_pose``) the one nearest where the registration ``T_query_match`` put the query
    sensor, and the closure's transform to it. The match itself, unchanged, where it is nearest or
    its pose is unknown."""
    at = registered_position(match_pose, T_query_match)
    if not np.isfinite(at).all() or len(rows) == 0:
        return match_row, T_query_match
    apart = np.linalg.norm(poses[:, :3, 3] - at, axis=1)
    apart[~np.isfinite(apart)] = np.inf
    mine = np.flatnonzero(rows == match_row)
    best = int(np.argmin(apart))
    if len(mine) and apart[best] >= apart[mine[0]]:  # ties keep the keyframe registered
        return match_row, T_query_match
    return int(rows[best]), retargeted(T_query_match, match_pose, poses[best])


def retargeted(T_query_match: np.ndarray, match_pose: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """T_query_other from a registration ``T_query_match`` and both keyframes' odometry poses
    (T_world_lidar): the registration composed with odometry between them."""
    return np.asarray(T_query_match, float) @ np.linalg.inv(np.asarray(match_pose, float)) @ np.asarray(pose, float)
