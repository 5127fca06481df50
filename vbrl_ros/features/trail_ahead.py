"""A keyframe described with the keyframes on both sides of it: its trail, and the next few metres.

A revisit driven the other way comes along the far side of a place: its trail lies where the
first pass went on to, not where it came from, and the two trails share little (the open
campus of docs/results/trail.md lost reversed revisits as the trail grew). A describer that
waits until it has passed a keyframe by ``ahead_m`` metres can merge the keyframes after it
as well, the same way as those before it; both passes then hold both sides of the place.
Only evaluation does this (``vbrl eval --trail-ahead``): ``vbrl_node`` describes a keyframe
when it arrives.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator

import numpy as np

from vbrl_ros.features.blind_wedges import BINS
from vbrl_ros.features.trail import Trail, merged_confirmed, trail_clouds


def trail_clouds_both_ways(scans: Iterable[np.ndarray], poses: np.ndarray | None, reach_m: float,
                           ahead_m: float, forward_reach_m: float = 0.0, stamps: np.ndarray | None = None,
                           max_age: float = math.inf, fill_blind_wedges: bool = False,
                           ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray | None, bool | None]]:
    """:func:`~vbrl_ros.features.trail.trail_clouds`, with each keyframe that has a near trail also
    merged with the keyframes of the next ``ahead_m`` metres (nearest first, filled up as the trail
    is, no nearer than ``max_age`` after it); a keyframe described without a trail behind it (``reach_m``
    0, a dense or forward-looking scan) is described as before. Holds every scan in memory."""
    if poses is None or ahead_m <= 0.0 or reach_m <= 0.0:
        yield from trail_clouds(scans, poses, reach_m, forward_reach_m, stamps, max_age, fill_blind_wedges)
        return
    scans = list(scans)
    # the keyframes after each one are its trail when the session is read backwards
    ahead = Trail(ahead_m, 0.0, max_age)
    later: list[list[np.ndarray]] = []
    for k in reversed(range(len(scans))):
        ahead.clouds(scans[k], poses[k], stamp=math.nan if stamps is None else -float(stamps[k]))
        later.append([] if ahead.near_parts is None else ahead.near_parts[0][1:])
    later.reverse()
    behind = Trail(reach_m, forward_reach_m, max_age, fill_blind_wedges)
    for k, points in enumerate(scans):
        described, all_round, sees = behind.clouds(points, poses[k],
                                                   stamp=math.nan if stamps is None else float(stamps[k]))
        if behind.near_parts is None or not later[k]:
            yield points, described, all_round, sees
            continue
        parts, blind = behind.near_parts
        yield points, merged_confirmed([*parts, *later[k]], blind | np.roll(blind, BINS // 2)), all_round, sees
