"""What a tilted sensor would see facing the other way: the top of its field of view, mirrored.

A sensor tilted on its mount (a bracket pitched down, a hand-held unit, a robot on a slope)
looks higher on one side than on the other. Levelling (:mod:`vbrl_ros.grids.ground_frame`)
puts its points where they belong but cannot add what it did not see: driven back the other
way, the side that looked up now looks down, the tops of walls one pass saw the other did not,
and the height map, which keeps each column's top, describes another place (simulated, a
32-beam sensor tilted by 10° and 20°: Recall@1 of reversed revisits 1 of 166). A point is
kept only where the sensor, turned half a turn about the vertical, would still see it below
the top of its field of view, so both passes keep the same band of the world, as mirrored
blind wedges keep the same directions (:mod:`.blind_wedges`).

Mirroring sets in gradually: over the first :data:`MIRROR_RAMP_DEG` beyond :data:`MIN_TILT_DEG`
the top edge the turned sensor is held to is raised by up to twice the threshold, as much as
the tilt would cut at the threshold, so a sensor swaying about it (a two-wheeled robot
pitching, a hand-held one) is not cut by 6 degrees in one keyframe and not at all in the next
(simulated, 32 beams swaying by 3 degrees: Recall@1 .930 with a sudden start, .963 gradual).

Left alone: level sensors (under :data:`MIN_TILT_DEG`, nothing to mirror) and those whose
field of view reaches :data:`WIDE_TOP_DEG` or higher (hand-held dome units): they see the
tops of nearly everything beyond a few metres either way, and on such a recording, held
tilted by up to 20°, cutting them cost retrieval (docs/results/tilt_and_sway.md).
"""

from __future__ import annotations

import math

import numpy as np

MIN_TILT_DEG = 3.0
MIRROR_RAMP_DEG = 3.0
WIDE_TOP_DEG = 40.0
#: The top edge is read as this percentile of the scan's elevations: a stray return above
#: the top beam does not raise it.
TOP_PERCENTILE = 99.9
MIN_RANGE_M = 1.0  # returns from the robot or the person carrying it say nothing of the field
MIN_POINTS = 100
SAMPLE_POINTS = 20_000  # read from every k-th point of a denser scan: as good, and cheap
#: A half turn about the vertical of the levelled frame.
HALF_TURN = np.diag([-1.0, -1.0, 1.0])


def field_top(points: np.ndarray) -> float:
    """The elevation (radians, the sensor's own frame) of the top of the field of view that
    saw ``points`` (N, 3+), sensor frame; NaN with fewer than :data:`MIN_POINTS` returns."""
    xyz = np.asarray(points)[:: max(1, len(points) // SAMPLE_POINTS), :3].astype(np.float64)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    xyz = xyz[np.einsum("ij,ij->i", xyz, xyz) > MIN_RANGE_M ** 2]
    if len(xyz) < MIN_POINTS:
        return math.nan
    return float(np.percentile(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])), TOP_PERCENTILE))


def tilt_deg(rotation: np.ndarray) -> float:
    """How far (degrees) ``rotation`` (sensor -> levelled) tips the sensor's z axis."""
    return math.degrees(math.acos(float(np.clip(np.asarray(rotation, np.float64)[2, 2], -1.0, 1.0))))


def tilted(rotation: np.ndarray) -> bool:
    """Whether a sensor levelled by ``rotation`` is tilted enough for its field to be mirrored."""
    return tilt_deg(rotation) >= MIN_TILT_DEG


def mirrors(rotation: np.ndarray, top: float) -> bool:
    """Whether a sensor levelled by ``rotation`` whose field of view tops out at ``top``
    (radians, :func:`field_top`) has its field mirrored: tilted, and not a wide one."""
    return bool(np.isfinite(top) and math.degrees(top) < WIDE_TOP_DEG and tilted(rotation))


def mirrored_top(rotation: np.ndarray, top: float) -> float:
    """The top edge (radians) a sensor levelled by ``rotation`` whose field of view tops out at ``top``
    is held to turned half a turn: ``top`` itself from :data:`MIN_TILT_DEG` + :data:`MIRROR_RAMP_DEG`
    of tilt on, raised towards ``top`` + 2 :data:`MIN_TILT_DEG` (which cuts nothing a sensor tilted
    that much saw) as the tilt falls to :data:`MIN_TILT_DEG`."""
    excess = tilt_deg(rotation) - MIN_TILT_DEG
    return top + math.radians(2.0 * MIN_TILT_DEG * min(1.0, max(0.0, 1.0 - excess / MIRROR_RAMP_DEG)))


def half_turn_in_sensor(rotation: np.ndarray) -> np.ndarray:
    """(3, 3): a sensor-frame point's direction as the sensor would see it turned half a turn about
    the levelled vertical (``R^T M R``, ``R`` = ``rotation`` sensor -> levelled)."""
    R = np.asarray(rotation, dtype=np.float64)
    return R.T @ HALF_TURN @ R


def seen_both_ways(points: np.ndarray, rotation: np.ndarray, top: float) -> np.ndarray:
    """(N,) bool: the points of ``points`` (sensor frame) that the sensor turned half a turn would
    see below :func:`mirrored_top`; all True where :func:`mirrors` says no. The compiled height map applies the
    same test point by point (:func:`~.height_map.height_cells`)."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    if not mirrors(rotation, top):
        return np.ones(len(xyz), dtype=bool)
    turned = xyz @ half_turn_in_sensor(rotation).T
    return turned[:, 2] <= math.tan(mirrored_top(rotation, top)) * np.hypot(turned[:, 0], turned[:, 1])
