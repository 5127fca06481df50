"""What a keyframe's sensor could have seen: how far it saw in each direction.

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
"""

from __future__ import annotations

import numpy as np

from vbrl_ros.features.blind_wedges import azimuth_bins

#: Azimuth bins around the sensor; a point is judged against its bin and the two beside it,
#: so a sparse (1 m thinned) cloud's far gaps between points do not read as blind directions.
AZIMUTH_BINS = 72


class Horizon:
    """Per azimuth bin the farthest horizontal range of ``points`` ((N, 3), sensor at the
    origin of their frame, z up), widened by ``margin`` metres."""

    def __init__(self, points: np.ndarray, margin: float) -> None:
        farthest = np.full(AZIMUTH_BINS, -np.inf)
        if len(points):
            np.maximum.at(farthest, azimuth_bins(points, AZIMUTH_BINS), np.hypot(points[:, 0], points[:, 1]))
        # a bin reaches as far as it or either neighbour does
        self.reach = np.max([np.roll(farthest, -1), farthest, np.roll(farthest, 1)], axis=0) + margin

    def sees(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: each point (this cloud's frame) lies within what this sensor saw."""
        return np.hypot(points[:, 0], points[:, 1]) <= self.reach[azimuth_bins(points, AZIMUTH_BINS)]

