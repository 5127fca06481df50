"""The node's output messages, built only from common_interfaces types.

Loop closures (``~/loop_closures``, ``std_msgs/Float64MultiArray``): one row
per accepted closure of a keyframe, ``len(CLOSURE_COLUMNS)`` columns in the
order below. ``layout.dim[0]`` is ``closure`` (rows), ``layout.dim[1]`` is
labelled with the comma-separated column names, so a message describes
itself. Unverified closures have NaN pose, fitness and covariance.

    query_stamp, match_stamp        seconds (float64)
    query_keyframe_id, match_keyframe_id
    query_session, match_session    integer session ids
    distance                        Eq. 4, lower = more similar
    fitness                         KISS-ICP inlier fraction in [0, 1]
    x, y, z, qx, qy, qz, qw         T_query<-match: maps match-frame points into the query frame
    cov_00 ... cov_55               6x6 row-major covariance of [x, y, z, roll, pitch, yaw]
    descriptor_yaw                  the recogniser's yaw of T_query<-match, radians (polar
                                    grid; 0 for the Cartesian grid), before verification

A verified closure's match is the stored keyframe nearest where the registration put the
query, along the path of the keyframe registered; ``distance`` and ``descriptor_yaw`` are
the recogniser's, of the keyframe it retrieved.

LIO-SAM convention (``lio_sam_topic``): ``Float64MultiArray`` data =
``[t_query, t_match]`` per closure.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from vbrl_ros.detection.candidate_verification import LoopClosure

CLOSURE_COLUMNS: tuple[str, ...] = (
    "query_stamp", "match_stamp", "query_keyframe_id", "match_keyframe_id",
    "query_session", "match_session", "distance", "fitness",
    "x", "y", "z", "qx", "qy", "qz", "qw",
    *(f"cov_{i}{j}" for i in range(6) for j in range(6)),
    "descriptor_yaw",  # appended last: consumers index columns by name, older ones by position
)


def closure_row(closure: LoopClosure) -> np.ndarray:
    row = np.full(len(CLOSURE_COLUMNS), np.nan)
    row[:8] = [
        closure.query_stamp, closure.match_stamp, closure.query_id, closure.match_id,
        int(closure.query_session), int(closure.match_session), closure.distance, closure.fitness,
    ]
    if closure.T_query_match is not None:
        T = np.asarray(closure.T_query_match)
        row[8:11] = T[:3, 3]
        row[11:15] = Rotation.from_matrix(T[:3, :3]).as_quat()  # x, y, z, w
    if closure.covariance is not None:
        row[15:51] = np.asarray(closure.covariance).ravel()
    row[51] = closure.yaw
    return row


def closures_message(closures: Sequence[LoopClosure]) -> Float64MultiArray:
    rows = np.array([closure_row(c) for c in closures]).reshape(-1, len(CLOSURE_COLUMNS))
    msg = Float64MultiArray()
    width = len(CLOSURE_COLUMNS)
    msg.layout.dim = [
        MultiArrayDimension(label="closure", size=len(rows), stride=len(rows) * width),
        MultiArrayDimension(label=",".join(CLOSURE_COLUMNS), size=width, stride=width),
    ]
    msg.data = rows.ravel().tolist()
    return msg


def parse_closures(msg: Float64MultiArray) -> list[dict[str, float]]:
    """Rows of a loop-closure message as dicts keyed by column name (what a consumer does)."""
    if len(msg.layout.dim) != 2:
        raise ValueError("loop-closure message must have a 2-D layout")
    columns = msg.layout.dim[1].label.split(",")
    data = np.asarray(msg.data, dtype=np.float64).reshape(-1, len(columns))
    return [dict(zip(columns, row.tolist())) for row in data]


def lio_sam_message(closure: LoopClosure) -> Float64MultiArray:
    msg = Float64MultiArray()
    msg.data = [float(closure.query_stamp), float(closure.match_stamp)]
    return msg
