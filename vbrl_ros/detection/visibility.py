"""What a keyframe's sensor could have seen: how far it saw in each direction, and between
which elevations.

Two scans of one place share only what both sensors saw. A robot's mast hides a wedge
behind it, a forward-looking Livox sees a 70 degree cone, and a revisit driven the other
way sees the other half of the street; the other scan's points in such directions cannot
overlap anything, and counted against the overlap they made true closures look like
unrelated places (measured on simulated reversed revisits behind a hidden wedge: the right
registration overlapped .13-.20, under the node's acceptance threshold).

A cloud's :class:`Horizon` is, per azimuth bin around its sensor, the farthest horizontal
range of any of its points (ground included: ground seen at 20 m means the sensor saw
20 m that way). A point of the other cloud, carried into this cloud's frame, was visible
to this sensor if it lies within that range (plus a voxel) in its bin or a neighbouring
one. Points behind a nearer surface in an otherwise open bin count as visible: the test
leaves out what the sensor could not have seen at all, not every occlusion.

Given the sensor's pose in the cloud's frame, a :class:`FieldOfView` also leaves out what lay
above or below the band of elevations the sensor scans. A 16-beam sensor sees 15 degrees up;
tilted on its mount, it looks higher on one side, and a pass driven the other way saw the
other band of every wall: counted against the overlap, those points held the right
registrations of such a sensor under the node's threshold (simulated, 16 beams pitched 10
degrees: the node published .781 of the revisits, and .935 with the band).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vbrl_ros.features.blind_wedges import azimuth_bins
from vbrl_ros.features.field_of_view import field_top

#: Azimuth bins around the sensor; a point is judged against its bin and the two beside it,
#: so a sparse (1 m thinned) cloud's far gaps between points do not read as blind directions.
AZIMUTH_BINS = 72


@dataclass(frozen=True)
class FieldOfView:
    """The band of elevations, in the sensor's own frame, that saw a cloud: its edges are read from
    the cloud (:func:`~vbrl_ros.features.field_of_view.field_top`, and the same for the bottom), so
    a stray return does not widen it."""

    rotation: np.ndarray  # (3, 3): the sensor's axes -> the cloud's
    origin: np.ndarray  # (3,): the sensor in the cloud's frame
    tan_bottom: float
    tan_top: float

    @classmethod
    def of(cls, points: np.ndarray, sensor: np.ndarray) -> FieldOfView | None:
        """The field of view of ``points`` ((N, 3), the cloud's frame) from a sensor at ``sensor``
        (4x4, sensor -> the cloud's frame); None when too few returns tell it."""
        sensor = np.asarray(sensor, np.float64)
        local = _in_sensor(np.asarray(points, np.float64), sensor[:3, :3], sensor[:3, 3])
        top, bottom = field_top(local), -field_top(local * (1.0, 1.0, -1.0))
        if not (np.isfinite(top) and np.isfinite(bottom)):
            return None
        return cls(sensor[:3, :3], sensor[:3, 3], float(np.tan(bottom)), float(np.tan(top)))

    def sees(self, points: np.ndarray, margin: float) -> np.ndarray:
        """(N,) bool: each point (the cloud's frame) lies in the band, to ``margin`` metres."""
        local = _in_sensor(points, self.rotation, self.origin)
        reach = np.hypot(local[:, 0], local[:, 1])
        return (local[:, 2] <= reach * self.tan_top + margin) & (local[:, 2] >= reach * self.tan_bottom - margin)


def _in_sensor(points: np.ndarray, rotation: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """(N, 3) points of a cloud's frame in the sensor's (``rotation``, ``origin``: sensor -> cloud)."""
    return (points - origin) @ rotation


class Horizon:
    """Per azimuth bin the farthest horizontal range of ``points`` ((N, 3), sensor above the
    origin of their frame, z up), widened by ``margin`` metres; with ``sensor`` (4x4, sensor ->
    the points' frame) also its :class:`FieldOfView`."""

    def __init__(self, points: np.ndarray, margin: float, sensor: np.ndarray | None = None) -> None:
        self.margin = float(margin)
        self.field = None if sensor is None else FieldOfView.of(points, sensor)
        farthest = np.full(AZIMUTH_BINS, -np.inf)
        if len(points):
            np.maximum.at(farthest, azimuth_bins(points, AZIMUTH_BINS), np.hypot(points[:, 0], points[:, 1]))
        # a bin reaches as far as it or either neighbour does
        self.reach = np.max([np.roll(farthest, -1), farthest, np.roll(farthest, 1)], axis=0) + margin

    def sees(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: each point (this cloud's frame) lies within what this sensor saw; (N, 2)
        points (a plan view) by their range alone."""
        seen = np.hypot(points[:, 0], points[:, 1]) <= self.reach[azimuth_bins(points, AZIMUTH_BINS)]
        if self.field is not None and points.shape[1] == 3:
            seen &= self.field.sees(points, self.margin)
        return seen

