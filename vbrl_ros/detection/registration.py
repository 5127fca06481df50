"""Geometric verification of a loop-closure candidate with KISS-ICP.

The place recogniser says "the current scan (query) looks like keyframe j
(match)"; this module checks it geometrically and measures the relative pose.
The match cloud becomes a KISS-ICP ``VoxelHashMap`` and the query is registered
against it with KISS-ICP's own point-to-point, robust-kernel ICP
(``Registration.align_points_to_map``), starting from an initial guess or, without
one, from a search over every heading (:mod:`~vbrl_ros.detection.coarse_alignment`).

Unlike odometry, a loop closure compares two *single* scans with no
constant-velocity prediction, so the initial error can be metres and degrees.
Three adaptations, each measured on ray-cast scenes (test_registration.py):

* coarse-to-fine: KISS-ICP's neighbour search only looks in the 27 voxels
  around a point (reach 1-2 map voxels), so the same registration runs on maps
  of voxel 8v, 2v, then v (v = ``voxel_size``), each from the previous result;
* the ground is thinned in the source (:func:`_ground_mask`): otherwise its
  sensor-centric sampling (rings, the blind disc) locks the translation;
* points are shuffled before voxel downsampling (:func:`_shuffled`).

Conventions
-----------
* ``T_query_match`` (4x4) maps match-frame points into the query frame:
  ``p_query = T_query_match @ p_match``. ``initial_guess`` uses the same convention.
* ``covariance`` (6x6) is of the perturbation ``xi = [rho, phi]`` (translation
  in m, then rotation vector in rad, the ROS ``PoseWithCovariance`` order)
  applied on the *left*, in the query frame: ``T_true = exp(xi) @ T_query_match``.
  It is ``sigma^2 * (sum J_i^T J_i)^-1`` with ``J_i = [I, -hat(T p_i)]`` the
  point-to-point Jacobian at the solution over inlier correspondences and
  ``sigma^2`` the per-coordinate inlier residual variance. It treats residuals
  as independent, which sampling-induced (not noise-induced) residuals are
  not: on the test scenes the true error was ~3-5x the reported standard
  deviation, and degenerate places (corridors) are worse. A lower bound.
* ``fitness`` is the two clouds' structure overlap after alignment and
  ``constraint`` how well their surfaces fix the horizontal position
  (:mod:`vbrl_ros.detection.overlap`, which says why); :meth:`Verification.rejection`
  is the acceptance rule. ``n_inliers`` / ``n_query_points`` is KISS-ICP's own inlier
  fraction at ``max_correspondence_distance``, over structure (non-ground) points.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from kiss_icp.mapping import VoxelHashMap
from kiss_icp.registration import Registration
from kiss_icp.voxelization import voxel_down_sample
from scipy.spatial import cKDTree

from vbrl_ros.detection.coarse_alignment import coarse_alignment
from vbrl_ros.detection.overlap import MIN_CONSTRAINT, agreement

# Map voxel size of each stage as a multiple of ``voxel_size`` (coarse to fine).
COARSE_TO_FINE = (8.0, 2.0, 1.0)
# KISS-ICP's default: at most 20 points per map voxel (with a minimum spacing of
# voxel/sqrt(20) between them), enough for sub-voxel nearest neighbours.
_MAX_POINTS_PER_VOXEL = 20
# Fewer inliers than this cannot constrain 6 DoF robustly (nor give a variance).
_MIN_POINTS = 20
_CONVERGENCE_CRITERION = 1e-4  # KISS-ICP default: stop when |dx| < 1e-4
_CHECK_ITERATIONS = 3  # of the final stage again, to see that it has settled
# Ground source points are kept at this many voxels (structure at 1.5), see _ground_mask.
_GROUND_THINNING = 4.0
# No LiDAR measures farther than this along any axis (the longest-range ones reach ~500 m);
# points beyond are corrupt and are dropped before storage and verification.
MAX_POINT_RANGE_M = 1000.0


@dataclass(frozen=True)
class Verification:
    """Result of :func:`verify_loop` (see the module docstring for conventions)."""

    T_query_match: np.ndarray  # (4, 4), p_query = T @ p_match
    fitness: float  # in [0, 1], structure overlap, higher = the clouds coincide more
    rmse: float  # metres, over inlier correspondences (inf without any)
    covariance: np.ndarray  # (6, 6) [translation, rotation]; all-NaN when unknown
    converged: bool
    n_query_points: int = 0  # downsampled query structure points the inliers are counted over
    n_inliers: int = 0
    constraint: float = 0.0  # in [0, 1]; 0: some horizontal direction is unconstrained

    def rejection(self, min_fitness: float) -> str | None:
        """Why this registration is not a loop closure (None: it is one)."""
        if not self.converged:
            return "not converged"
        if self.constraint < MIN_CONSTRAINT:
            return "degenerate"
        if self.fitness < min_fitness:
            return "low fitness"
        return None


def yaw_guess(yaw_rad: float) -> np.ndarray:
    """4x4 rotation by ``yaw_rad`` about z: an ``initial_guess`` from a yaw-only recogniser."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def downsample_for_storage(points: np.ndarray, voxel_size: float = 1.0) -> np.ndarray:
    """What the keyframe database stores per keyframe: one point per voxel, (M, 3) float32."""
    points = _shuffled(_clean(points))
    if len(points) == 0:
        return np.empty((0, 3), dtype=np.float32)
    return voxel_down_sample(points, float(voxel_size)).astype(np.float32)


def _shuffled(points: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random permutation of the points.

    KISS-ICP's voxel_down_sample keeps the *first* point of each voxel; in scan
    order that is always the lowest beam / earliest azimuth, a systematic
    offset of up to a voxel that differs between two viewpoints and biases
    scan-to-scan ICP (~10 cm -> ~6 cm with 1 m stored clouds).
    Seeded, so results are reproducible.
    """
    return points[np.random.default_rng(0).permutation(len(points))]


def verify_loop(
    query_points: np.ndarray,
    match_points: np.ndarray,
    *,
    initial_guess: np.ndarray | None = None,
    voxel_size: float = 1.0,
    max_correspondence_distance: float | None = None,
    max_iterations: int = 500,
    max_threads: int = 0,
    timings: dict[str, float] | None = None,
) -> Verification:
    """Register ``query_points`` (N, 3) onto ``match_points`` (M, 3) with KISS-ICP.

    ``initial_guess`` is a guess of ``T_query_match``; the basin is about +-10 degrees of
    yaw with metres of translation. Without one, a search over every heading finds it
    (:mod:`~vbrl_ros.detection.coarse_alignment`; both clouds levelled, z up). ``max_correspondence_distance``
    (default ``voxel_size``) gates the final ICP stage and defines inliers and
    fitness. ``max_threads=0`` lets KISS-ICP (TBB) use every core. Empty or tiny
    clouds give ``converged=False`` and ``fitness=0`` instead of raising. ``timings``, when
    given, accumulates the CPU milliseconds each stage took (``vbrl bench --verification``).
    """
    laps = _Laps(timings)
    if voxel_size <= 0:
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    guess = None if initial_guess is None else np.asarray(initial_guess, dtype=np.float64)
    if guess is not None and (guess.shape != (4, 4) or not np.all(np.isfinite(guess))):
        raise ValueError("initial_guess must be a finite 4x4 matrix")
    threshold = voxel_size if max_correspondence_distance is None else max_correspondence_distance
    threshold = float(threshold)
    if threshold <= 0:
        raise ValueError(f"max_correspondence_distance must be positive, got {threshold}")

    # KISS-ICP's preprocessing: the map keeps the scan at voxel/2 (a no-op for a
    # cloud from downsample_for_storage), the source is sparser (see _source).
    match = _shuffled(_clean(match_points))
    query = _shuffled(_clean(query_points))
    match = voxel_down_sample(match, 0.5 * voxel_size) if len(match) else match
    query = voxel_down_sample(query, 0.5 * voxel_size) if len(query) else query
    source, n_structure = _source(query, voxel_size)
    if len(match) < _MIN_POINTS or len(source) < _MIN_POINTS:
        return _failure(np.eye(4) if guess is None else guess, n_query=n_structure)
    stages = COARSE_TO_FINE[:-1]
    match_structure = match[~_ground_mask(match)] if guess is None else None
    laps.lap("prepare")
    if guess is None:
        guess = coarse_alignment(source[:n_structure], match_structure).T_query_match
        stages = stages[1:]  # the search is within a cell and a few degrees: no 8-voxel stage
        laps.lap("heading search")
    guess = _rigid(guess)

    registration = Registration(
        max_num_iterations=int(max_iterations),
        convergence_criterion=_CONVERGENCE_CRITERION,
        max_num_threads=int(max_threads),
    )
    maps = _MapsOf(match)
    # KISS-ICP solves for T_match_query (query points into the match map).
    T_mq = np.linalg.inv(guess)
    for factor in stages:
        # A coarse stage: the map voxel sets the reach of the neighbour search;
        # the source stays the fine one (a coarser source lost the basin in our
        # tests). sigma = 2 map voxels ~ the error this stage must remove; as in
        # KISS-ICP's pipeline we gate at 3 sigma and pass sigma as the kernel.
        # Its Geman-McClure weight is k^2 / (k + r^2)^2, i.e. half weight at
        # r = 0.64 sqrt(k): 2.6 m on the 8 m map, 1.3 m on the 2 m map (v = 1).
        stage_voxel = factor * voxel_size
        sigma = 2.0 * stage_voxel
        T_mq = _align(registration, source, maps.at(stage_voxel), T_mq, 3.0 * sigma, sigma)
        laps.lap("icp coarse")
    # The final stage only polishes: gate at the inlier threshold, kernel
    # threshold / 3 (half weight at 0.37 m for the default 1 m threshold).
    T_mq = _align(registration, source, maps.at(voxel_size), T_mq, threshold, threshold / 3.0)
    laps.lap("icp fine")

    # Convergence = the final stage is a fixed point: a few more of its iterations from its
    # own result barely move (the bindings do not report iterations).
    check = Registration(max_num_iterations=_CHECK_ITERATIONS, convergence_criterion=_CONVERGENCE_CRITERION,
                         max_num_threads=int(max_threads))
    T_again = _align(check, source, maps.at(voxel_size), T_mq, threshold, threshold / 3.0)
    step = np.linalg.inv(T_mq) @ T_again
    settled = bool(np.linalg.norm(step[:3, 3]) < 0.01 * voxel_size and _angle(step) < 1e-3)
    laps.lap("convergence check")
    # Fitness over structure only: ground overlaps at almost any two places,
    # and far ground rings are too sparse to overlap even at the right one.
    scored = n_structure if n_structure >= _MIN_POINTS else len(source)
    check = _evaluate(source, scored, match, np.linalg.inv(T_mq), threshold, settled)
    laps.lap("evaluate")
    evidence = agreement(query, match, check.T_query_match, voxel_size, _ground_mask)
    laps.lap("agreement")
    return replace(check, fitness=evidence.overlap, constraint=evidence.constraint)


class _Laps:
    """CPU milliseconds between successive :meth:`lap` calls, summed per stage into ``timings``
    (CPU time: on a shared machine it is what the stage costs, wall-clock is also the wait)."""

    def __init__(self, timings: dict[str, float] | None) -> None:
        self.timings, self.start = timings, time.process_time()

    def lap(self, stage: str) -> None:
        if self.timings is None:
            return
        now = time.process_time()
        self.timings[stage] = self.timings.get(stage, 0.0) + 1e3 * (now - self.start)
        self.start = now


class _MapsOf:
    """KISS-ICP maps of one cloud, one per voxel size, each built once."""

    def __init__(self, points: np.ndarray) -> None:
        self.points, self.maps = points, {}

    def at(self, voxel: float) -> VoxelHashMap:
        if voxel not in self.maps:
            # max_distance only prunes the map in update(); add_points keeps everything.
            self.maps[voxel] = VoxelHashMap(voxel, np.inf, max_points_per_voxel=_MAX_POINTS_PER_VOXEL)
            self.maps[voxel].add_points(self.points)
        return self.maps[voxel]


def _align(
    registration: Registration,
    source: np.ndarray,
    voxel_map: VoxelHashMap,
    T_mq: np.ndarray,
    max_distance: float,
    kernel: float,
) -> np.ndarray:
    """One KISS-ICP registration of ``source`` against ``voxel_map``."""
    T = registration.align_points_to_map(
        points=source,
        voxel_map=voxel_map,
        initial_guess=T_mq,
        max_correspondance_distance=max_distance,
        kernel=kernel,
    )
    return np.asarray(T, dtype=np.float64)


def _source(query: np.ndarray, voxel: float) -> tuple[np.ndarray, int]:
    """(points, n_structure): the registration source, structure points first.

    Structure (non-ground) at KISS-ICP's 1.5-voxel downsampling; ground thinned
    to one point per ``_GROUND_THINNING`` voxels (see :func:`_ground_mask`).
    """
    ground = _ground_mask(query)
    structure = voxel_down_sample(query[~ground], 1.5 * voxel) if (~ground).any() else query[:0]
    flat = voxel_down_sample(query[ground], _GROUND_THINNING * voxel) if ground.any() else query[:0]
    return np.ascontiguousarray(np.concatenate([structure, flat])), len(structure)


def _ground_mask(points: np.ndarray, cell: float = 2.0, tolerance: float = 0.3) -> np.ndarray:
    """True for points on the ground (sensor roughly upright, z up, as for Scan Context).

    Why: at KISS-ICP's 1.5-voxel downsampling, ground is 60-80 % of a single
    scan, and its sampling is sensor-centric (rings, the blind disc under the
    sensor). Scan-to-scan, those artefacts pull the solution towards "both
    sensors at the same place" and make unrelated places overlap on the
    ground alone. KISS-ICP odometry avoids this because its map accumulates
    many scans; a loop closure compares two single scans. Ground is kept (it
    fixes z, roll, pitch) but thinned so structure decides x, y, yaw.

    A point is ground if it lies within ``tolerance`` of its grid cell's lowest
    point and that cell's lowest point is within 0.5 m of the lowest point of
    the 3x3 neighbouring cells (so car roofs and wall tops are not ground).
    """
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    ij = np.floor(points[:, :2] / cell).astype(np.int64)
    ij -= ij.min(axis=0) - 1  # non-negative, with a free border for neighbour lookups
    width = int(ij[:, 1].max()) + 2
    keys, inverse = np.unique(ij[:, 0] * width + ij[:, 1], return_inverse=True)
    lowest = np.full(len(keys), np.inf)
    np.minimum.at(lowest, inverse, points[:, 2])
    reference = lowest.copy()
    for offset in (-width - 1, -width, -width + 1, -1, 1, width - 1, width, width + 1):
        position = np.minimum(np.searchsorted(keys, keys + offset), len(keys) - 1)
        found = keys[position] == keys + offset
        reference[found] = np.minimum(reference[found], lowest[position[found]])
    ground_cell = lowest - reference < 0.5
    return (points[:, 2] - lowest[inverse] < tolerance) & ground_cell[inverse]


def _evaluate(
    query: np.ndarray,
    n_scored: int,
    match: np.ndarray,
    T_qm: np.ndarray,
    threshold: float,
    settled: bool,
) -> Verification:
    """Fitness (over ``query[:n_scored]``), RMSE and covariance (over all inliers)."""
    match_in_query = match @ T_qm[:3, :3].T + T_qm[:3, 3]
    distances, nearest = cKDTree(match_in_query).query(query, distance_upper_bound=threshold)
    inlier = np.isfinite(distances)
    n_in = int(inlier.sum())
    fitness = float(inlier[:n_scored].mean())
    if n_in < _MIN_POINTS:
        return _failure(T_qm, n_query=n_scored, fitness=fitness, n_inliers=n_in)
    q, p = query[inlier], match_in_query[nearest[inlier]]
    residuals = q - p
    rmse = float(np.sqrt(np.mean(np.einsum("ij,ij->i", residuals, residuals))))
    # Per-coordinate residual variance, with 6 degrees of freedom used by the fit.
    sigma2 = float(np.sum(residuals**2) / max(3 * n_in - 6, 1))
    covariance = _covariance(p, sigma2)
    ok = covariance is not None
    return Verification(
        T_query_match=T_qm,
        fitness=float(fitness),
        rmse=rmse,
        covariance=covariance if ok else np.full((6, 6), np.nan),
        converged=bool(settled and ok),
        n_query_points=n_scored,
        n_inliers=n_in,
    )


def _covariance(p: np.ndarray, sigma2: float) -> np.ndarray | None:
    """sigma^2 (sum J^T J)^-1 with J = [I, -hat(p)] for each aligned match point p."""
    n = len(p)
    # sum J^T J = [[n I, -sum hat(p)], [sum hat(p), -sum hat(p)^2]], in closed form
    s = p.sum(axis=0)
    hat_s = _hat(s)
    second = (p.T @ p)  # sum p p^T
    minus_hat2 = np.trace(second) * np.eye(3) - second  # -sum hat(p)^2
    H = np.block([[n * np.eye(3), -hat_s], [hat_s, minus_hat2]])
    try:
        L = np.linalg.cholesky(H)
    except np.linalg.LinAlgError:
        return None
    L_inv = np.linalg.inv(L)
    covariance = sigma2 * (L_inv.T @ L_inv)
    covariance = 0.5 * (covariance + covariance.T)
    return covariance if np.all(np.isfinite(covariance)) else None


def _hat(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _angle(T: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))


def _rigid(T: np.ndarray) -> np.ndarray:
    """T with its rotation replaced by the nearest rotation matrix: KISS-ICP (Sophus) aborts the
    whole process on a rotation that is orthogonal only to float precision, as products of
    poses are."""
    u, _, vt = np.linalg.svd(T[:3, :3])
    rigid = np.eye(4)
    rigid[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    rigid[:3, 3] = T[:3, 3]
    return rigid


def _clean(points: np.ndarray) -> np.ndarray:
    """(N, 3) float64 C-contiguous points within :data:`MAX_POINT_RANGE_M` (what the KISS-ICP bindings
    need: far beyond it, voxel and grid indices overflow)."""
    points = np.asarray(points, dtype=np.float64)
    if points.size == 0:
        return np.empty((0, 3))
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    points = points[:, :3]
    # NaN and inf compare False: dropped too
    return np.ascontiguousarray(points[np.all(np.abs(points) <= MAX_POINT_RANGE_M, axis=1)])


def _failure(
    T_qm: np.ndarray, *, n_query: int, fitness: float = 0.0, n_inliers: int = 0
) -> Verification:
    return Verification(
        T_query_match=np.array(T_qm, dtype=np.float64),
        fitness=float(fitness),
        rmse=float("inf"),
        covariance=np.full((6, 6), np.nan),
        converged=False,
        n_query_points=n_query,
        n_inliers=n_inliers,
    )
