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
  around a point (reach 1-2 map voxels), so from an initial guess the same
  registration runs on maps of voxel 8v, 2v, then v (v = ``voxel_size``), each
  from the previous result. The heading search starts within a metre and a few
  degrees (sub-step and sub-cell): a short 2v stage on a few hundred points, then
  the v stage;
* the ground is thinned in the source (:mod:`~vbrl_ros.detection.ground`): otherwise its
  sensor-centric sampling (rings, the blind disc) locks the translation;
* points are shuffled before voxel downsampling
  (:func:`~vbrl_ros.detection.prepared_cloud.shuffled`).

Everything derived from one cloud is computed once
(:class:`~vbrl_ros.detection.prepared_cloud.PreparedCloud`); :class:`QueryVerifier`
keeps the query's for all its candidates.

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
* ``fitness`` is the two clouds' structure overlap after alignment, ``constraint`` and
  ``facing_area`` how well their surfaces fix the horizontal position
  (:mod:`vbrl_ros.detection.overlap`, which says why); :meth:`Verification.rejection`
  is the acceptance rule. ``n_inliers`` / ``n_query_points`` is KISS-ICP's own inlier
  fraction at ``max_correspondence_distance``, over structure (non-ground) points.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from kiss_icp.mapping import VoxelHashMap
from kiss_icp.registration import Registration

from vbrl_ros.detection.coarse_alignment import MAX_SHIFT_M
from vbrl_ros.detection.overlap import agreement_of, covisible_overlap, is_constrained
from vbrl_ros.detection.pose_covariance import inlier_statistics
from vbrl_ros.detection.prepared_cloud import MAX_POINT_RANGE_M, PreparedCloud, thinned
from vbrl_ros.model.sector_shift import wrap_angle

__all__ = ["COARSE_TO_FINE", "EXPECTED_YAW_TOLERANCE_DEG", "MAX_POINT_RANGE_M", "SEARCH_MARGIN_M", "QueryVerifier",
           "Verification", "downsample_for_storage", "verify_loop", "yaw_guess"]

# Map voxel size of each stage as a multiple of ``voxel_size`` (coarse to fine), from an initial guess.
COARSE_TO_FINE = (8.0, 2.0, 1.0)
# The same after the heading search, whose coarse stage runs at most SEARCHED_COARSE_ITERATIONS
# on at most SEARCHED_COARSE_STRUCTURE structure points: on simulated revisits it had nothing
# left to do after 5 iterations (the fine stage alone ended at the same pose), but on the
# hand-held recording's sparse clouds, without it, a few more true closures ended unsettled.
SEARCHED_COARSE_TO_FINE = (2.0, 1.0)
SEARCHED_COARSE_ITERATIONS = 10
SEARCHED_COARSE_STRUCTURE = 400
# Registration source structure points beyond this are left out (a seeded random subset; all
# the ground stays): ICP's cost grows with them, and its pose did not improve beyond 1200 on
# simulated 64-beam revisits (~2200 at a 1 m voxel); sparser sensors never reach it.
FINE_SOURCE_STRUCTURE = 1200
# The heading search's best overlays (one per heading whose peak beats its neighbours') that are
# compared by what both sensors saw before one is refined: in a square courtyard or at a
# crossing the overlay turned by 90 degrees correlates almost as well, and with part of the
# circle hidden (a mast, a hand-held sensor's operator) it often correlated better.
HEADING_HYPOTHESES = 4
# ... compared by their co-visible overlap seen from above (overlap.covisible_overlap); another
# heading replaces the best peak's only when its overlap is at least this much higher (0.05
# refused right headings in a square courtyard; 0 cost a forward-looking sensor a few closures
# in rain).
HYPOTHESIS_MARGIN = 0.02
#: With an expected yaw (odometry's, for a candidate of the same session), only overlays within
#: this of it are compared: half the quarter turn that a symmetric place is confused by, and far
#: more than odometry's heading drifts over a loop. With none that close, all are compared.
EXPECTED_YAW_TOLERANCE_DEG = 45.0
#: The heading search looks this far beyond the farthest closure the caller accepts: its peak is
#: a cell off at worst, and ICP may still pull a registration back inside.
SEARCH_MARGIN_M = 2.0
# Fewer inliers than this cannot constrain 6 DoF robustly (nor give a variance).
_MIN_POINTS = 20
_CONVERGENCE_CRITERION = 1e-4  # KISS-ICP default: stop when |dx| < 1e-4
_CHECK_ITERATIONS = 3  # of the final stage again, to see that it has settled
_TOLERANCE_RAD = math.radians(EXPECTED_YAW_TOLERANCE_DEG)


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
    facing_area: float = 0.0  # m^2 of planar surface facing along the weakest horizontal direction

    def rejection(self, min_fitness: float) -> str | None:
        """Why this registration is not a loop closure (None: it is one)."""
        if not self.converged:
            return "not converged"
        if not is_constrained(self.constraint, self.facing_area):
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
    return thinned(points, voxel_size).astype(np.float32)


def verify_loop(
    query_points: np.ndarray,
    match_points: np.ndarray,
    *,
    initial_guess: np.ndarray | None = None,
    voxel_size: float = 1.0,
    max_correspondence_distance: float | None = None,
    max_iterations: int = 500,
    max_threads: int = 0,
    max_closure_distance: float | None = None,
    timings: dict[str, float] | None = None,
    query_sensor: np.ndarray | None = None,
    match_sensor: np.ndarray | None = None,
) -> Verification:
    """Register ``query_points`` (N, 3) onto ``match_points`` (M, 3) with KISS-ICP.

    ``initial_guess`` is a guess of ``T_query_match``; the basin is about +-10 degrees of
    yaw with metres of translation. Without one, a search over every heading finds it
    (:mod:`~vbrl_ros.detection.coarse_alignment`; both clouds levelled, z up). ``max_correspondence_distance``
    (default ``voxel_size``) gates the final ICP stage and defines inliers and
    fitness. ``max_threads=0`` lets KISS-ICP (TBB) use every core. ``max_closure_distance``: the
    caller rejects registrations farther than this (m), so the heading search looks only that far
    (plus ``SEARCH_MARGIN_M``; default: ``MAX_SHIFT_M``). Empty or tiny
    clouds give ``converged=False`` and ``fitness=0`` instead of raising. ``timings``, when
    given, accumulates the CPU milliseconds each stage took (``vbrl bench --verification``).
    ``query_sensor``, ``match_sensor``: each keyframe's sensor -> its cloud's frame (4x4), which
    tells the band of elevations it saw (:class:`PreparedCloud`); None: unknown.
    Several candidates of one query: :class:`QueryVerifier` prepares the query once.
    """
    laps = _Laps(timings)
    verifier = QueryVerifier(query_points, voxel_size=voxel_size,
                             max_correspondence_distance=max_correspondence_distance,
                             max_iterations=max_iterations, max_threads=max_threads,
                             max_closure_distance=max_closure_distance, sensor=query_sensor)
    laps.lap("prepare")
    return verifier.verify(match_points, initial_guess=initial_guess, timings=timings, sensor=match_sensor)


class QueryVerifier:
    """:func:`verify_loop` of one query against any number of candidates: the query's thinning,
    ground, registration source, KD-tree and heading-search image are computed once (on first
    use), not per candidate. Arguments as :func:`verify_loop`'s; ``sensor``: the query's, as
    :class:`PreparedCloud` takes it."""

    def __init__(self, query_points: np.ndarray, *, voxel_size: float = 1.0,
                 max_correspondence_distance: float | None = None, max_iterations: int = 500,
                 max_threads: int = 0, max_closure_distance: float | None = None,
                 sensor: np.ndarray | None = None) -> None:
        if voxel_size <= 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        threshold = voxel_size if max_correspondence_distance is None else max_correspondence_distance
        if float(threshold) <= 0:
            raise ValueError(f"max_correspondence_distance must be positive, got {threshold}")
        if max_closure_distance is not None and not (np.isfinite(max_closure_distance) and max_closure_distance > 0):
            raise ValueError(f"max_closure_distance must be positive, got {max_closure_distance}")
        self.voxel, self.threshold = float(voxel_size), float(threshold)
        # the heading search looks as far as a closure may be, and a margin beyond
        self.search_radius = MAX_SHIFT_M if max_closure_distance is None else (
            float(max_closure_distance) + SEARCH_MARGIN_M)
        self.query = PreparedCloud(query_points, self.voxel, sensor)
        self.registration = Registration(max_num_iterations=int(max_iterations),
                                         convergence_criterion=_CONVERGENCE_CRITERION,
                                         max_num_threads=int(max_threads))
        self.coarse = Registration(max_num_iterations=min(int(max_iterations), SEARCHED_COARSE_ITERATIONS),
                                   convergence_criterion=_CONVERGENCE_CRITERION, max_num_threads=int(max_threads))
        self.check = Registration(max_num_iterations=_CHECK_ITERATIONS,
                                  convergence_criterion=_CONVERGENCE_CRITERION, max_num_threads=int(max_threads))

    def verify(self, match: np.ndarray | PreparedCloud, *, initial_guess: np.ndarray | None = None,
               expected_yaw: float | None = None, timings: dict[str, float] | None = None,
               sensor: np.ndarray | None = None) -> Verification:
        """Register the query onto ``match`` ((M, 3) points, or a :class:`PreparedCloud` at this
        verifier's voxel that a caller keeps for a keyframe it verifies often). ``expected_yaw``
        (radians; None or NaN: unknown): roughly the yaw of ``T_query_match``, as odometry knows it
        (:func:`~vbrl_ros.detection.odometry_gate.odometry_heading`); the heading search then
        keeps to overlays within :data:`EXPECTED_YAW_TOLERANCE_DEG` of it. ``sensor``: the match's
        sensor pose when ``match`` is points, as :class:`PreparedCloud` takes it."""
        laps = _Laps(timings)
        guess = None if initial_guess is None else np.asarray(initial_guess, dtype=np.float64)
        if guess is not None and (guess.shape != (4, 4) or not np.all(np.isfinite(guess))):
            raise ValueError("initial_guess must be a finite 4x4 matrix")
        if not isinstance(match, PreparedCloud):
            match = PreparedCloud(match, self.voxel, sensor)
        elif match.voxel != self.voxel:
            raise ValueError(f"the match was prepared at voxel {match.voxel}, the query at {self.voxel}")
        query = self.query
        source, n_structure = query.source
        laps.lap("prepare")
        if len(match.points) < _MIN_POINTS or len(source) < _MIN_POINTS:
            return _failure(np.eye(4) if guess is None else guess, n_query=n_structure)
        if guess is not None:
            return self._register(match, guess, searched=False, laps=laps)
        overlays = query.heading_search(self.search_radius).alignments(match.structure, HEADING_HYPOTHESES)
        if expected_yaw is not None and math.isfinite(expected_yaw):
            overlays = [o for o in overlays if _yaw_apart(o.T_query_match, expected_yaw) <= _TOLERANCE_RAD] or overlays
        laps.lap("heading search")
        overlay = overlays[0]
        if len(overlays) > 1:
            scores = [covisible_overlap(query, match, o.T_query_match) for o in overlays]
            best = int(np.argmax(scores))
            if scores[best] >= scores[0] + HYPOTHESIS_MARGIN:
                overlay = overlays[best]
            laps.lap("heading hypotheses")
        return self._register(match, overlay.T_query_match, searched=True, laps=laps)

    def _register(self, match: PreparedCloud, guess: np.ndarray, *, searched: bool, laps: _Laps) -> Verification:
        """KISS-ICP from ``guess``, then the evidence; ``searched``: the guess came from the heading
        search (a metre and a few degrees off), else from a caller (metres and 10 degrees)."""
        query, voxel, threshold = self.query, self.voxel, self.threshold
        source, n_structure = query.source
        icp_source = query.sampled_source(FINE_SOURCE_STRUCTURE)
        if searched:  # within a metre and a few degrees (see SEARCHED_COARSE_TO_FINE): a short coarse stage
            stages, coarse = SEARCHED_COARSE_TO_FINE[:-1], self.coarse
            coarse_source = query.sampled_source(SEARCHED_COARSE_STRUCTURE)
        else:  # metres and 10 degrees to go: full stages
            stages, coarse, coarse_source = COARSE_TO_FINE[:-1], self.registration, icp_source
        # KISS-ICP solves for T_match_query (query points into the match map).
        T_mq = np.linalg.inv(_rigid(guess))
        for factor in stages:
            # A coarse stage: the map voxel sets the reach of the neighbour search;
            # the source stays the fine one (a coarser source lost the basin in our
            # tests). sigma = 2 map voxels ~ the error this stage must remove; as in
            # KISS-ICP's pipeline we gate at 3 sigma and pass sigma as the kernel.
            # Its Geman-McClure weight is k^2 / (k + r^2)^2, i.e. half weight at
            # r = 0.64 sqrt(k): 2.6 m on the 8 m map, 1.3 m on the 2 m map (v = 1).
            sigma = 2.0 * factor * voxel
            T_mq = _align(coarse, coarse_source, match.voxel_map(factor * voxel), T_mq, 3.0 * sigma, sigma)
            laps.lap("icp coarse")
        # The final stage only polishes: gate at the inlier threshold, kernel
        # threshold / 3 (half weight at 0.37 m for the default 1 m threshold).
        fine = match.voxel_map(voxel)
        T_mq = _align(self.registration, icp_source, fine, T_mq, threshold, threshold / 3.0)
        laps.lap("icp fine")

        # Convergence = the final stage is a fixed point: a few more of its iterations from its
        # own result barely move (the bindings do not report iterations).
        T_again = _align(self.check, icp_source, fine, T_mq, threshold, threshold / 3.0)
        step = np.linalg.inv(T_mq) @ T_again
        settled = bool(np.linalg.norm(step[:3, 3]) < 0.01 * voxel and _angle(step) < 1e-3)
        laps.lap("convergence check")
        # Fitness over structure only: ground overlaps at almost any two places,
        # and far ground rings are too sparse to overlap even at the right one.
        T_qm = np.linalg.inv(T_mq)
        scored = n_structure if n_structure >= _MIN_POINTS else len(source)
        inliers = inlier_statistics(source, match, T_qm, threshold, _MIN_POINTS)
        n_in = int(inliers.inlier.sum())
        laps.lap("evaluate")
        evidence = agreement_of(query, match, T_qm)
        laps.lap("agreement")
        ok = inliers.covariance is not None
        return Verification(
            T_query_match=T_qm,
            fitness=evidence.overlap,
            rmse=inliers.rmse,
            covariance=inliers.covariance if ok else np.full((6, 6), np.nan),
            converged=bool(settled and ok),
            n_query_points=scored,
            n_inliers=n_in,
            constraint=evidence.constraint,
            facing_area=evidence.facing_area,
        )


class _Laps:
    """CPU milliseconds between successive :meth:`lap` calls, summed per stage into ``timings``
    (CPU time: when other processes share the cores it is what the stage costs; wall-clock also
    counts the wait)."""

    def __init__(self, timings: dict[str, float] | None) -> None:
        self.timings, self.start = timings, time.process_time()

    def lap(self, stage: str) -> None:
        if self.timings is None:
            return
        now = time.process_time()
        self.timings[stage] = self.timings.get(stage, 0.0) + 1e3 * (now - self.start)
        self.start = now


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


def _yaw_apart(T: np.ndarray, yaw: float) -> float:
    """|yaw of ``T`` - ``yaw``| in radians, wrapped to [0, pi]."""
    return abs(float(wrap_angle(math.atan2(T[1, 0], T[0, 0]) - yaw)))


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


def _failure(T_qm: np.ndarray, *, n_query: int) -> Verification:
    return Verification(
        T_query_match=np.array(T_qm, dtype=np.float64),
        fitness=0.0,
        rmse=float("inf"),
        covariance=np.full((6, 6), np.nan),
        converged=False,
        n_query_points=n_query,
        n_inliers=0,
    )
