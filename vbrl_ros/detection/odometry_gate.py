"""Same-session candidates that odometry places far away are not verified.

A place that looks like another — a repeated block of buildings, a second identical
corridor — can register well enough to pass every geometric test. Within one session the
node knows where it has been: odometry drifts, but by a share of the path travelled, not by
hundreds of metres. A candidate whose keyframe odometry places farther from the query than
``max_closure_distance`` plus :data:`SLACK_M` plus ``odometry_drift`` times the path driven
between the two cannot be the same place and is rejected before it is registered. Across
sessions odometry says nothing, and neither it does where a pose is unknown.

Odometry also says which way the candidate's keyframe faced. Its heading drifts by a few
degrees over a loop, while a symmetric place — a square courtyard, a crossing of two alike
streets — overlays almost as well turned by a quarter: :func:`odometry_heading` is the
registration's expected yaw, and the verification's heading search keeps to overlays within
:data:`~vbrl_ros.detection.registration.EXPECTED_YAW_TOLERANCE_DEG` of it.
"""

from __future__ import annotations

import numpy as np

#: Metres allowed beyond ``max_closure_distance`` however short the path between the two
#: keyframes: odometry that has just started may already be off by a little.
SLACK_M = 5.0


class DrivenPath:
    """Metres driven since each session began, keyframe by keyframe in order; a keyframe without a
    position has none, and the next one is bridged from the last known in a straight line."""

    def __init__(self) -> None:
        self._last: dict = {}  # session -> (its last known position, metres driven there)

    def step(self, session, position: np.ndarray) -> float:
        """Metres driven in ``session`` up to ``position`` (NaN where it is unknown)."""
        position = np.asarray(position, dtype=np.float64)
        if not np.all(np.isfinite(position)):
            return float("nan")
        before = self._last.get(session)
        path = 0.0 if before is None else before[1] + float(np.linalg.norm(position - before[0]))
        self._last[session] = (position.copy(), path)
        return path


def path_lengths(positions: np.ndarray, sessions: np.ndarray, driven: DrivenPath | None = None) -> np.ndarray:
    """(n,) :meth:`DrivenPath.step` of each keyframe in order (``driven``: the tracker to go on
    with afterwards; a new one by default)."""
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    driven = DrivenPath() if driven is None else driven
    return np.array([driven.step(s, p) for p, s in zip(positions, np.asarray(sessions).reshape(-1).tolist())],
                    dtype=np.float64)


def too_far_by_odometry(apart_m: float, path_m: float, max_closure_distance: float,
                        odometry_drift: float) -> bool:
    """Whether two keyframes ``apart_m`` metres apart by odometry, ``path_m`` metres of driving
    between them, are too far apart to be one place; never without both (NaN) or with
    ``odometry_drift`` 0 (the gate off)."""
    if odometry_drift <= 0 or not (np.isfinite(apart_m) and np.isfinite(path_m)):
        return False
    return apart_m > max_closure_distance + SLACK_M + odometry_drift * abs(path_m)


#: With the gate on, this many times ``top_k`` candidates are retrieved, so that those odometry
#: rules out leave their place to the next ones rather than an empty verification budget.
SPARE_FACTOR = 3


def kept_with_spares(too_far: list[bool], top_k: int) -> int:
    """How many of the candidates, best first (``too_far``: each ruled out by odometry), to keep:
    up to the ``top_k``-th one odometry allows, the ruled-out ones before it included (they are
    counted as rejected, not registered); all of them when fewer are allowed."""
    allowed = 0
    for position, far in enumerate(too_far):
        allowed += not far
        if allowed == top_k:
            return position + 1
    return len(too_far)


def odometry_heading(query_pose: np.ndarray, match_pose: np.ndarray, query_frame: np.ndarray,
                     match_frame: np.ndarray, odometry_drift: float) -> float:
    """The yaw (radians) of ``T_query_match`` between two keyframes' levelled frames (sensor -> grid,
    where verification registers them) as odometry gives it: ``query_pose`` and ``match_pose`` are
    T_world_lidar of one session. NaN where a pose is unknown, and with ``odometry_drift`` 0 (odometry
    trusted for neither, as by :func:`too_far_by_odometry`)."""
    if odometry_drift <= 0 or not (np.all(np.isfinite(query_pose)) and np.all(np.isfinite(match_pose))):
        return float("nan")
    T = query_frame @ np.linalg.solve(query_pose, match_pose) @ np.linalg.inv(match_frame)
    return float(np.arctan2(T[1, 0], T[0, 0]))
