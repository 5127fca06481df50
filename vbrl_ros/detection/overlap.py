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
  Another sensor's rings cross the same wall at other heights, and its points then lie a
  ring's spacing from the other cloud's: between a 32-beam robot and a 64-beam car the right
  registrations overlapped half as much as between two passes of one sensor (median .175
  against .40, simulated), under ``min_fitness``. So the overlap is also counted with a point
  that lies on the other cloud's surface — within a voxel of a planar neighbourhood of it and
  within ``OVERLAP_DISTANCE`` voxels of its plane — as near, at ``SURFACE_CREDIT``: a plane
  met anywhere is weaker evidence than points that coincide (wrong registrations in a room
  reached it too), and the larger of the two counts.
* **constraint** — how well the matched surfaces fix the horizontal position: the weakest
  over the strongest eigenvalue of the point-to-plane information of the inliers in x, y.
  In a corridor or along a uniform facade every normal is across the axis, ICP slides freely
  along it and lands wherever the initial guess was, with an excellent overlap: 0.01-0.03 on
  such false closures, 0.2-0.6 on true ones.
* **facing area** — the same weakest direction's information in absolute terms: how many
  square metres of surface face along it, each weighed by how planar it is (inliers counted
  once per voxel: a sensor that samples every voxel of a wall counts its area, not its
  points). A ratio cannot tell a corridor from a street seen forwards: a forward-looking
  sensor sees thousands of facade points beside it and the few dozen square metres of a
  crossing or a far wall ahead, ratio 0.02-0.1, and the position along the street is fixed
  all the same (simulated: such registrations were at most 1 m off). A registration is
  constrained by either test.

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
#: The overlap counted on the other cloud's surfaces weighs this much against the one on its points.
#: At 0.6 no registration of the shared recordings as recorded changed its verdict, for either
#: method's candidates (with a wedge hidden, one wrong one of Scan Context's passed at .205); at 2/3
#: a wrong one of Scan Context's in a room passed as recorded.
SURFACE_CREDIT = 0.6
#: A neighbourhood at least this planar (``PreparedCloud.surfaces``) is a surface that another
#: sensor may have sampled elsewhere.
MIN_PLANARITY = 0.5
#: Below this constraint a registration cannot fix the position along some horizontal axis...
MIN_CONSTRAINT = 0.1
#: ... unless at least this much planar surface (m^2) faces along that axis. On simulated and
#: real revisits no registration with a smaller ratio but at least 16-32 m^2 was more than 2 m
#: off; at 6 m^2 some were.
MIN_FACING_AREA_M2 = 20.0
_MIN_STRUCTURE = 10


@dataclass(frozen=True)
class Agreement:
    overlap: float  # in [0, 1], higher = the clouds coincide more
    constraint: float  # in [0, 1], 0 = one horizontal direction is unconstrained
    facing_area: float = 0.0  # m^2 of planar surface facing along the weakest horizontal direction


def is_constrained(constraint: float, facing_area: float) -> bool:
    """A registration fixes the horizontal position: relative to its strongest direction, or by
    enough surface facing along its weakest."""
    return constraint >= MIN_CONSTRAINT or facing_area >= MIN_FACING_AREA_M2


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
    to_query, nearest_in_query = query.tree.query(m_in_query, distance_upper_bound=voxel)
    q_near, m_near = to_match < near, to_query < near
    inlier = to_match < voxel
    surfaces = _Surfaces.of(match, nearest[inlier])
    on_points = _covisible_share(query, match, q_in_match, q_near, m_in_query, m_near)
    q_on = q_near.copy()
    q_on[inlier] |= surfaces.holds(q_in_match[inlier], match.points[nearest[inlier]], near)
    m_inlier = to_query < voxel
    m_on = m_near.copy()
    m_on[m_inlier] |= _Surfaces.of(query, nearest_in_query[m_inlier], every_point=True).holds(
        m_in_query[m_inlier], query.points[nearest_in_query[m_inlier]], near)
    on_surfaces = _covisible_share(query, match, q_in_match, q_on, m_in_query, m_on)
    overlap = max(on_points, SURFACE_CREDIT * on_surfaces)
    return Agreement(overlap, *_constraint(surfaces, q_structure[inlier], R, voxel))


@dataclass(frozen=True)
class _Surfaces:
    """The surface normal and planarity at each of some points of a cloud (NaN-free; none when the
    cloud is too small to tell)."""

    normals: np.ndarray  # (n, 3)
    planarity: np.ndarray  # (n,)

    @classmethod
    def of(cls, cloud: PreparedCloud, indices: np.ndarray, every_point: bool = False) -> _Surfaces:
        """At ``cloud.points[indices]``: from the cloud's every-point table when ``every_point`` (a
        query, checked against each candidate, computes it once), else for those points alone."""
        if len(cloud.points) < NORMAL_NEIGHBOURS or len(indices) == 0:
            return cls(np.zeros((len(indices), 3)), np.zeros(len(indices)))
        if every_point:
            normals, planarity = cloud.point_surfaces
            return cls(normals[indices], planarity[indices])
        used, where = np.unique(indices, return_inverse=True)
        normals, planarity = cloud.surfaces(used)
        return cls(normals[where], planarity[where])

    def holds(self, points: np.ndarray, at: np.ndarray, near: float) -> np.ndarray:
        """Which ``points`` lie within ``near`` of the plane through ``at`` (one per point) where it is planar."""
        off_plane = np.abs(np.einsum("ij,ij->i", self.normals, points - at))
        return (self.planarity >= MIN_PLANARITY) & (off_plane < near)


def covisible_overlap(query: PreparedCloud, match: PreparedCloud, T_query_match: np.ndarray) -> float:
    """The overlap of :func:`agreement_of` seen from above, cell by cell (``PreparedCloud.plan``):
    the smaller share of each cloud's occupied cells that the other sensor could see and that
    land in or beside an occupied cell of the other. It tells apart the overlays of a heading
    search, which are a metre and a few degrees off, before any of them is refined."""
    R, t = T_query_match[:2, :2], T_query_match[:2, 3]
    q_cells, m_cells = query.plan.centres, match.plan.centres
    if min(len(q_cells), len(m_cells)) < _MIN_STRUCTURE:
        return 0.0
    q_in_match, m_in_query = (q_cells - t) @ R, m_cells @ R.T + t
    return _covisible_share(query, match, q_in_match, match.plan.near(q_in_match), m_in_query,
                            query.plan.near(m_in_query))


def _covisible_share(query: PreparedCloud, match: PreparedCloud, q_in_match: np.ndarray, q_near: np.ndarray,
                     m_in_query: np.ndarray, m_near: np.ndarray) -> float:
    """The smaller of the two clouds' shares of near points among those the other sensor could see."""
    return min(_share(q_near, match.horizon.sees(q_in_match)), _share(m_near, query.horizon.sees(m_in_query)))


def _share(near: np.ndarray, visible: np.ndarray) -> float:
    """The share of the visible points that are near the other cloud; 0 when too few are visible."""
    n = int(visible.sum())
    return float(np.count_nonzero(near & visible)) / n if n >= _MIN_STRUCTURE else 0.0


def _constraint(surfaces: _Surfaces, inliers: np.ndarray, R: np.ndarray, voxel: float) -> tuple[float, float]:
    """(constraint, facing area) of the query ``inliers`` (query frame) matched to points of the
    other cloud whose ``surfaces`` are given; ``R`` turns that cloud's frame into the query's.

    The information is sum(w n_xy n_xy^T): n the normal of the matched surface point, w how
    planar its neighbourhood is, so scattered clutter counts less. Constraint: its weakest over
    its strongest eigenvalue; facing area: its weakest eigenvalue over one inlier per voxel,
    in m^2.
    """
    if len(inliers) < _MIN_STRUCTURE or not surfaces.planarity.any():
        return 0.0, 0.0
    normal_xy = (surfaces.normals @ R.T)[:, :2]
    weight = surfaces.planarity
    low, high = _information_extremes(weight, normal_xy)
    # one inlier per voxel: a surface's area counts, not how densely the sensor sampled it
    _, once = np.unique(_voxel_keys(inliers, voxel), return_index=True)
    facing, _ = _information_extremes(weight[once], normal_xy[once])
    return (float(low / high) if high > 0 else 0.0), float(facing) * voxel ** 2


def _voxel_keys(points: np.ndarray, voxel: float) -> np.ndarray:
    """(N,) int64, equal for points in the same ``voxel``: 20 bits per axis reach 500k voxels
    either side, beyond any point that survives cleaning (1000 m) at any voxel over 2 mm."""
    index = np.floor(points / voxel).astype(np.int64) + (1 << 19)
    return (index[:, 0] << 40) | (index[:, 1] << 20) | index[:, 2]


def _information_extremes(weight: np.ndarray, normal_xy: np.ndarray) -> tuple[float, float]:
    """The (weakest, strongest) eigenvalue of sum(w n n^T)."""
    low, high = np.linalg.eigvalsh(np.einsum("n,ni,nj->ij", weight, normal_xy, normal_xy))
    return float(low), float(high)
