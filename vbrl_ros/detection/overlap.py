"""Evidence that a registered loop closure is real: do the two clouds agree, and does their
structure pin the position down at all?

KISS-ICP's inlier fraction at its final gate (one voxel) is a weak test: one-voxel clouds of
unrelated places lie within a voxel of each other almost everywhere, so on real recordings
many false candidates scored as high as true revisits. Two measurements separate them far
better (measured on real recordings, candidates of the recogniser and of Scan Context alike):

* **overlap** — after alignment, the share of each cloud's structure (ground left out) that
  lies within ``OVERLAP_DISTANCE`` voxels of the other cloud; the smaller of the two shares.
  Each share counts only the points the other sensor could have seen
  (:mod:`~vbrl_ros.detection.visibility`): what lay in its hidden wedge, outside its field
  of view or beyond anything it saw that way cannot overlap, and counted against the
  overlap it held true revisits seen from the other side under the threshold.
  Both clouds come thinned (at most one point per half voxel, as registration keeps them; the
  database stores one per voxel), so the figure hardly depends on the sensor's density. A
  tight distance rewards surfaces that coincide, not clutter that happens to be near; taking
  both directions refuses a place where either sensor saw structure the other should have
  seen and did not.
* **constraint** — how well the matched surfaces fix the horizontal position: the weakest
  over the strongest eigenvalue of the point-to-plane information of the inliers in x, y.
  In a corridor or along a uniform facade every normal is across the axis, ICP slides freely
  along it and lands wherever the initial guess was, with an excellent overlap: 0.01-0.03 on
  such false closures, 0.2-0.6 on true ones.

Each cloud's ground is told in its own frame and its KD-tree is built there once
(:class:`~vbrl_ros.detection.prepared_cloud.PreparedCloud`); the other cloud's points are
carried into it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vbrl_ros.detection.prepared_cloud import NORMAL_NEIGHBOURS, PreparedCloud

#: Points closer than this many voxels to the other cloud overlap it.
OVERLAP_DISTANCE = 0.3
#: Below this constraint a registration cannot fix the position along some horizontal axis.
MIN_CONSTRAINT = 0.1
_MIN_STRUCTURE = 10


@dataclass(frozen=True)
class Agreement:
    overlap: float  # in [0, 1], higher = the clouds coincide more
    constraint: float  # in [0, 1], 0 = one horizontal direction is unconstrained


def agreement(query: np.ndarray, match: np.ndarray, T_query_match: np.ndarray, voxel: float,
              ground_mask) -> Agreement:
    """Overlap and constraint of ``match`` carried into the query frame by ``T_query_match``.

    ``query``, ``match``: (N, 3) float64 finite points, thinned; ``ground_mask(points) -> bool
    array`` tells ground points, which overlap at almost any two places and are left out.
    """
    return agreement_of(PreparedCloud.of_thinned(query, voxel, ground_mask(query)),
                        PreparedCloud.of_thinned(match, voxel, ground_mask(match)), T_query_match)


def agreement_of(query: PreparedCloud, match: PreparedCloud, T_query_match: np.ndarray) -> Agreement:
    """:func:`agreement` of two prepared clouds (their voxel: the query's)."""
    R, t = T_query_match[:3, :3], T_query_match[:3, 3]
    q_structure, m_structure = query.structure, match.structure
    if min(len(q_structure), len(m_structure)) < _MIN_STRUCTURE:
        return Agreement(0.0, 0.0)
    voxel = query.voxel
    near = OVERLAP_DISTANCE * voxel
    # beyond the bound a distance is inf: it counts neither as near nor as an inlier
    q_in_match, m_in_query = (q_structure - t) @ R, m_structure @ R.T + t
    to_match, nearest = match.tree.query(q_in_match, distance_upper_bound=voxel)
    to_query, _ = query.tree.query(m_in_query, distance_upper_bound=near)
    overlap = min(_share(to_match < near, match.horizon.sees(q_in_match)),
                  _share(to_query < near, query.horizon.sees(m_in_query)))
    inlier = to_match < voxel
    return Agreement(overlap, _constraint(match, nearest[inlier], R))


def _share(near: np.ndarray, visible: np.ndarray) -> float:
    """The share of the visible points that are near the other cloud; 0 when too few are visible."""
    n = int(visible.sum())
    return float(np.count_nonzero(near & visible)) / n if n >= _MIN_STRUCTURE else 0.0


def _constraint(surface: PreparedCloud, nearest: np.ndarray, R: np.ndarray) -> float:
    """Weakest / strongest eigenvalue of sum(w n_xy n_xy^T) over the query points matched to
    ``surface``'s points ``nearest``; ``R`` turns ``surface``'s frame into the query's.

    n: the normal of the matched surface point, w: how planar its neighbourhood is, so
    scattered clutter counts less.
    """
    if len(nearest) < _MIN_STRUCTURE or len(surface.points) < NORMAL_NEIGHBOURS:
        return 0.0
    used, where = np.unique(nearest, return_inverse=True)
    normals, planarity = surface.surfaces(used)
    normal_xy = (normals @ R.T)[:, :2][where]
    weight = planarity[where]
    information = np.einsum("n,ni,nj->ij", weight, normal_xy, normal_xy)
    low, high = np.linalg.eigvalsh(information)
    return float(low / high) if high > 0 else 0.0
