"""Corroborated closures: a registration a little short of ``min_fitness`` is believed when the
keyframe before it registered to the same place.

A sparse hand-held sensor overlaps less after registration than a dense one, so some right
closures score just under ``min_fitness`` (the Mid-360 walk: .14-.19 along a whole stretch; another
sensor's keyframes and a thinned robot's reversed revisits: .12-.2);
lowering the threshold for all of them publishes wrong ones elsewhere. A wrong registration,
though, rarely lands twice in a row where the path leads. Each registration says where the
query sensor stood in the match's session: the match keyframe's pose times the registered
transform. A candidate whose fitness reaches ``corroborated_fitness`` is accepted when, in
:data:`CORROBORATIONS_NEEDED` of the :data:`CORROBORATING_KEYFRAMES` keyframes before, a
registration at least that good (published or not) put that keyframe, in the same session,
within the distance odometry moved since plus :data:`CORROBORATION_SLACK_M` of where this one
puts the query: three registrations in a row agree. Two were not enough: in a small courtyard
two consecutive keyframes registered 4.5 m off the same way. Poses are odometry's, each in its
own session's frame, so it works across sessions too; without poses it never applies.

Three in a row can still slide together along a corridor or a facade that repeats. Within the
query's own session odometry knows where the sensor was, up to its drift: there a weak
registration must also put the sensor within :data:`CORROBORATION_SLACK_M` plus
``odometry_drift`` times the path driven since the match of where odometry does
(:func:`agrees_with_odometry`; the forward-looking hand-held recording with drifting odometry:
three keyframes registered 7 m along a corridor from where its poses put them).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

#: How many keyframes back a registration may corroborate one (keyframe ids, consecutive per session) ...
CORROBORATING_KEYFRAMES = 3
#: ... and how many of them must.
CORROBORATIONS_NEEDED = 2
#: Metres two registrations of nearby keyframes may disagree by beyond the query's own step: a right
#: registration is off by a few decimetres, and odometry a little over a few metres.
CORROBORATION_SLACK_M = 1.0


def registered_position(match_pose: np.ndarray, T_query_match: np.ndarray) -> np.ndarray:
    """Where a registration puts the query sensor in the match's session: ``match_pose`` (4x4
    T_world_lidar of the match) times the registered sensor-to-sensor transform (which maps
    match-frame points into the query frame), (3,)."""
    return (np.asarray(match_pose, float) @ np.linalg.inv(np.asarray(T_query_match, float)))[:3, 3]


def agrees_with_odometry(registered: np.ndarray, position: np.ndarray, path_m: float, odometry_drift: float) -> bool:
    """Whether a registration to the query's own session, which put the query sensor at
    ``registered``, agrees with odometry, which puts it at ``position`` ``path_m`` metres of driving
    after the match: within :data:`CORROBORATION_SLACK_M` plus ``odometry_drift`` times the path.
    True where odometry cannot say (``odometry_drift`` 0, unknown positions or path)."""
    apart = float(np.linalg.norm(np.asarray(registered, float) - np.asarray(position, float)))
    if odometry_drift <= 0 or not (np.isfinite(apart) and np.isfinite(path_m)):
        return True
    return bool(apart <= CORROBORATION_SLACK_M + odometry_drift * abs(path_m))


def corroborates(position: np.ndarray, query_step_m: float, earlier_position: np.ndarray) -> bool:
    """Whether an earlier keyframe's registration, which put it at ``earlier_position``, agrees with
    one that puts a query that has moved ``query_step_m`` since at ``position`` (both in one
    session's frame); False when a position is unknown (NaN)."""
    apart = float(np.linalg.norm(np.asarray(position, float) - np.asarray(earlier_position, float)))
    return bool(apart <= query_step_m + CORROBORATION_SLACK_M)  # NaN compares False


@dataclass(frozen=True)
class _Registered:
    keyframe_id: int
    session: str
    position: np.ndarray  # (3,) where the query was, its session's odometry
    registered: tuple[tuple[str, np.ndarray], ...]  # (session, where a registration put it there)


class RecentRegistrations:
    """The registrations of the last few verified keyframes, to corroborate a weak one with."""

    def __init__(self, keyframes: int = CORROBORATING_KEYFRAMES, needed: int = CORROBORATIONS_NEEDED) -> None:
        self.keyframes, self.needed = keyframes, needed
        self._recent: deque[_Registered] = deque(maxlen=keyframes)

    def corroborated(self, keyframe_id: int, session: str, position: np.ndarray | None,
                     match_session: str, registered: np.ndarray | None) -> bool:
        """Whether registrations of ``needed`` of the last ``keyframes`` keyframes of ``session``
        before ``keyframe_id`` agree with this keyframe's to ``match_session``, which put it at
        ``registered`` (:func:`corroborates`); ``position``: the keyframe's own, by its session's
        odometry."""
        if position is None or registered is None:
            return False
        agreeing = 0
        for earlier in self._recent:
            if earlier.session != session or not 0 < keyframe_id - earlier.keyframe_id <= self.keyframes:
                continue
            step = float(np.linalg.norm(np.asarray(position, float) - earlier.position))
            agreeing += any(s == match_session and corroborates(registered, step, p) for s, p in earlier.registered)
        return agreeing >= self.needed

    def remember(self, keyframe_id: int, session: str, position: np.ndarray | None,
                 registered: list[tuple[str, np.ndarray | None]]) -> None:
        """Keyframe ``keyframe_id``, at ``position`` by odometry, was registered (at least
        ``corroborated_fitness``) into these sessions at these positions."""
        if position is None:
            return
        known = tuple((s, np.asarray(p, float)) for s, p in registered if p is not None)
        self._recent.append(_Registered(keyframe_id, session, np.asarray(position, float), known))

    def __len__(self) -> int:
        return len(self._recent)

    def clear(self) -> None:
        self._recent.clear()
