"""A session's keyframes, each with the cloud it is described by, as the node describes them.

Evaluation and training read a recording's keyframes in order through :func:`trail_clouds`:
each keyframe's trail behind it (:class:`~vbrl_ros.features.trail.Trail`) and, with
``ahead_m``, the keyframes of the next metres (:class:`~vbrl_ros.features.trail_ahead.TrailAhead`),
held no longer than the node holds them, so a recording is streamed, not kept.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator

import numpy as np

from vbrl_ros.features.trail import Trail
from vbrl_ros.features.trail_ahead import TrailAhead


def with_trail(scans: Iterable[np.ndarray], poses: np.ndarray | None,
               reach_m: float, forward_reach_m: float = 0.0, stamps: np.ndarray | None = None,
               max_age: float = math.inf, ahead_m: float = 0.0) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(scan, the cloud it is described by) of each of ``scans`` in order, one session whose
    ``poses`` (n, 4, 4) are T_world_lidar (None: no trail); ``stamps`` and ``max_age`` as
    :meth:`~vbrl_ros.features.trail.Trail.cloud`'s; ``ahead_m``: the metres ahead it also takes."""
    for points, cloud, *_ in trail_clouds(scans, poses, reach_m, forward_reach_m, stamps, max_age,
                                          ahead_m=ahead_m):
        yield points, cloud


def trail_clouds(scans: Iterable[np.ndarray], poses: np.ndarray | None,
                 reach_m: float, forward_reach_m: float = 0.0, stamps: np.ndarray | None = None,
                 max_age: float = math.inf, fill_blind_wedges: bool = False, ahead_m: float = 0.0,
                 ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray | None, bool | None]]:
    """:func:`with_trail` with the rest of each scan's :meth:`~vbrl_ros.features.trail.Trail.clouds`
    (its all-round cloud and whether it sees all round) after it. A keyframe without a trail
    behind it (``reach_m`` 0) takes none ahead either."""
    if poses is None:
        reach_m, forward_reach_m = 0.0, 0.0
    trail = Trail(reach_m, forward_reach_m, max_age, fill_blind_wedges)
    ahead = TrailAhead(ahead_m if reach_m > 0.0 else 0.0, max_age)

    def due() -> Iterator[tuple[tuple[np.ndarray, np.ndarray | None, float], list[np.ndarray]]]:
        for k, points in enumerate(scans):
            pose = None if poses is None else poses[k]
            stamp = math.nan if stamps is None else float(stamps[k])
            yield from ahead.add((points, pose, stamp), points, pose, stamp=stamp)
        yield from ahead.flush()

    for (points, pose, stamp), later in due():
        yield points, *trail.clouds(points, pose, stamp=stamp, ahead=later)
