"""The verified output, evaluated: retrieval's top-k, each candidate registered with KISS-ICP as
the node registers it, and the closure the node would publish.

Every candidate of every query is verified once (:func:`verify_candidates`, in worker
processes); the two readings of the result are then cheap:

* **swept** (:func:`best_verified`): per query the accepted candidate with the highest fitness,
  its fitness swept as the acceptance threshold — the verified counterpart of retrieval's
  max F1, independent of any distance threshold;
* **at the node's settings** (:func:`node_decision`): the first candidate, in distance order
  within the distance threshold, that the detector's rule accepts — one operating point, what a
  robot running the node with those settings publishes.

Verification finds the relative pose itself (a search over every heading, then KISS-ICP), so
any method's top-k are verified by the same code: Scan Context's like the model's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from vbrl_ros.detection.candidate_verification import (
    WIDER_RETRY_FITNESS,
    closure_rejection,
    query_verifier,
    to_sensor_frames,
)
from vbrl_ros.detection.corroboration import RecentRegistrations, agrees_with_odometry, registered_position
from vbrl_ros.detection.detector import submap_gap_s
from vbrl_ros.detection.odometry_gate import (
    SPARE_FACTOR,
    kept_with_spares,
    odometry_heading,
    path_lengths,
    too_far_by_odometry,
)
from vbrl_ros.detection.registration import QueryVerifier
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.detection.submaps import MAX_NEIGHBOUR_DISTANCE_M, KeyframeView, merged_cloud, neighbour_steps
from vbrl_ros.evaluation.metrics import RetrievalMetrics
from vbrl_ros.features.parallel import bounded_map, default_workers, worker_pool

__all__ = ["TOP_K_RETRIEVED", "Candidates", "Corroboration", "KeyframeClouds", "OdometryTrack", "OperatingPoint",
           "VerifiedCandidates", "best_verified", "node_decision", "operating_point", "plausible_candidates",
           "retrieval_width", "submap_clouds", "verify_candidates"]


def retrieval_width(top_k: int) -> int:
    """Candidates retrieval keeps per query: the spares the odometry gate draws on when ``top_k`` are
    verified (:func:`plausible_candidates`), and at least 10, for Recall@5 and the matches dump's lists."""
    return max(10, top_k * SPARE_FACTOR)


#: :func:`retrieval_width` for the node's own ``top_k``.
TOP_K_RETRIEVED = retrieval_width(DetectorSettings().top_k)


@dataclass(frozen=True)
class Candidates:
    """Per query the top-k of a method, best first; padding: index -1, distance inf."""

    indices: np.ndarray  # (n, k) int64
    distances: np.ndarray  # (n, k)


@dataclass(frozen=True)
class VerifiedCandidates:
    """What verification said about each candidate of :class:`Candidates` (same shape)."""

    fitness: np.ndarray  # (n, k), NaN for padding
    rejection: np.ndarray  # (n, k) object: the rule's reason at fitness 0 (None: accepted)
    T_query_match: np.ndarray  # (n, k, 4, 4) between the sensors, NaN for padding
    # (n, k) of those accepted only when retried with wider submaps (candidate_verification.WIDER_RETRY_FITNESS), the
    # first registration's fitness, NaN for the others: the node retries only from WIDER_RETRY_FITNESS
    # times its min_fitness, so a sweep over min_fitness needs it
    retried_from: np.ndarray | None = None

    @property
    def retried(self) -> np.ndarray | None:
        """(n, k) bool: accepted only when retried with wider submaps; None when none were tried."""
        return None if self.retried_from is None else np.isfinite(self.retried_from)

    def accepted_at(self, min_fitness: float) -> np.ndarray:
        """(n, k) bool: converged, constrained, near enough and at least ``min_fitness``."""
        return np.equal(self.rejection, None) & (self.fitness >= min_fitness)  # elementwise


@dataclass(frozen=True)
class KeyframeClouds:
    """Per keyframe of a source what the node keeps for verification: its cloud in its levelled
    frame (see :func:`~vbrl_ros.detection.detector.verification_cloud`) and that frame (4x4)."""

    clouds: Sequence[np.ndarray]
    frames: Sequence[np.ndarray]


def submap_clouds(clouds: KeyframeClouds, poses: np.ndarray | None, stamps: np.ndarray,
                  settings: DetectorSettings, *, both_sides: bool, neighbours: int | None = None,
                  reach_m: float = MAX_NEIGHBOUR_DISTANCE_M) -> KeyframeClouds:
    """Every keyframe's cloud as the node verifies it under ``settings`` (``submap_keyframes``, or
    ``neighbours`` within ``reach_m`` for a wider retry; :mod:`~vbrl_ros.detection.submaps`): queries see only their
    past (``both_sides`` False), stored keyframes both sides. The source's poses stand for the
    node's odometry; without poses, or with ``submap_keyframes`` 0, the single clouds."""
    if poses is None or settings.submap_keyframes == 0:
        return clouds
    n, gap = len(clouds.clouds), submap_gap_s(settings)
    views = [KeyframeView(clouds.clouds[i], clouds.frames[i], poses[i], float(stamps[i])) for i in range(n)]
    steps = neighbour_steps(neighbours or settings.submap_keyframes, both_sides=both_sides)
    merged = [merged_cloud(views[i], [views[i + s] for s in steps if 0 <= i + s < n],
                           settings.verification_voxel, gap, reach_m) for i in range(n)]
    return KeyframeClouds(merged, clouds.frames)


@dataclass(frozen=True)
class _Work:
    queries: KeyframeClouds
    database: KeyframeClouds
    settings: DetectorSettings  # the rule without its fitness threshold: fitness is swept afterwards
    wider: tuple[KeyframeClouds, KeyframeClouds] | None
    retry_fitness: float  # a degenerate registration overlapping this much is retried wider
    odometry: OdometryTrack | None  # P1: where the node's odometry would place each keyframe


@dataclass(frozen=True)
class OdometryTrack:
    """One session's keyframes as the node's odometry knows them: the source's positions stand for
    it, as for submaps (:mod:`~vbrl_ros.detection.odometry_gate`)."""

    poses: np.ndarray  # (n, 4, 4) T_world_lidar, NaN where unknown
    paths: np.ndarray  # (n,) metres driven from the start

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]

    @classmethod
    def of(cls, poses: np.ndarray | None) -> OdometryTrack | None:
        """The track of a source's keyframe poses (n, 4, 4), in order; None without poses."""
        if poses is None:
            return None
        poses = np.asarray(poses, dtype=np.float64)
        return cls(poses, path_lengths(poses[:, :3, 3], np.zeros(len(poses), np.int64)))

    def too_far(self, query: int, match: int, settings: DetectorSettings) -> bool:
        apart = float(np.linalg.norm(self.positions[query] - self.positions[match]))
        return too_far_by_odometry(apart, float(self.paths[query] - self.paths[match]),
                                   settings.max_closure_distance, settings.odometry_drift)

    def heading(self, query: int, match: int, query_frame: np.ndarray, match_frame: np.ndarray,
                settings: DetectorSettings) -> float:
        """The yaw odometry expects the registration to find, as the node's (NaN with the gate off)."""
        return odometry_heading(self.poses[query], self.poses[match], query_frame, match_frame,
                                settings.odometry_drift)


_worker: _Work | None = None
# The last query's verifier: tasks come query by query, so a worker often gets several
# candidates of one query in a row and prepares the query once for them.
_last_query: tuple[int, QueryVerifier] | None = None


def _init_worker(queries: KeyframeClouds, database: KeyframeClouds | None, settings: DetectorSettings,
                 wider: tuple[KeyframeClouds, KeyframeClouds | None] | None,
                 odometry: OdometryTrack | None = None) -> None:
    global _worker, _last_query
    _worker = _Work(queries, database or queries, DetectorSettings(**{**settings.__dict__, "min_fitness": 0.0}),
                    None if wider is None else (wider[0], wider[1] or wider[0]),
                    WIDER_RETRY_FITNESS * settings.min_fitness, odometry)
    _last_query = None


def _verify(task: tuple[int, int]) -> tuple[float, str | None, np.ndarray, float]:
    global _last_query
    assert _worker is not None
    work, (query, match) = _worker, task
    if work.odometry is not None and work.odometry.too_far(query, match, work.settings):
        return math.nan, "odometry", np.full((4, 4), np.nan), math.nan  # as the node: not registered
    if _last_query is None or _last_query[0] != query:
        _last_query = (query, query_verifier(work.queries.clouds[query], work.settings, max_threads=1,
                                             sensor=work.queries.frames[query]))
    expected = math.nan if work.odometry is None else work.odometry.heading(
        query, match, work.queries.frames[query], work.database.frames[match], work.settings)
    check = _last_query[1].verify(work.database.clouds[match], expected_yaw=expected,
                                  sensor=work.database.frames[match])
    T, _ = to_sensor_frames(check, work.queries.frames[query], work.database.frames[match])
    reason = closure_rejection(check, T, work.settings)
    if reason == "degenerate" and work.wider is not None and check.fitness >= work.retry_fitness:
        # as the node: once more with submaps of twice the neighbours (detector.LoopClosureDetector.verified)
        wider_queries, wider_database = work.wider
        again = query_verifier(wider_queries.clouds[query], work.settings, max_threads=1,
                               sensor=work.queries.frames[query]).verify(
            wider_database.clouds[match], expected_yaw=expected, sensor=work.database.frames[match])
        T_again, _ = to_sensor_frames(again, work.queries.frames[query], work.database.frames[match])
        if closure_rejection(again, T_again, work.settings) is None:
            return again.fitness, None, T_again, check.fitness
    return check.fitness, reason, T, math.nan


def verify_candidates(queries: KeyframeClouds, database: KeyframeClouds | None, candidates: Candidates,
                      settings: DetectorSettings, *, wider: tuple[KeyframeClouds, KeyframeClouds | None] | None = None,
                      odometry: OdometryTrack | None = None, workers: int | None = None, progress: bool = True,
                      description: str = "verifying") -> VerifiedCandidates:
    """Register every candidate as the node does; ``database`` None: the queries' own (P1). With
    ``wider`` (the queries' and the database's clouds from submaps of twice the neighbours), a
    degenerate registration is retried with them, as the node retries it. With ``odometry`` (P1:
    one session) a candidate it places too far away is rejected unregistered, as by the node."""
    n, k = candidates.indices.shape
    fitness = np.full((n, k), np.nan)
    rejection = np.full((n, k), "no candidate", dtype=object)
    transforms = np.full((n, k, 4, 4), np.nan)
    retried_from = np.full((n, k), np.nan)
    slots = [(q, r) for q in range(n) for r in range(k) if candidates.indices[q, r] >= 0]
    tasks = [(q, int(candidates.indices[q, r])) for q, r in slots]
    workers = default_workers() if workers is None else workers
    bar = tqdm(total=len(tasks), desc=description, unit="pair", disable=not progress, leave=False)
    initargs = (queries, database, settings, wider, odometry)
    try:
        if workers <= 1:
            _init_worker(*initargs)
            results = map(_verify, tasks)
            for (q, r), (f, why, T, first) in zip(slots, results):
                fitness[q, r], rejection[q, r], transforms[q, r], retried_from[q, r] = f, why, T, first
                bar.update()
        else:
            with worker_pool(workers, _init_worker, initargs) as pool:
                for (q, r), (f, why, T, first) in zip(slots, bounded_map(pool, _verify, tasks, 8 * workers)):
                    fitness[q, r], rejection[q, r], transforms[q, r], retried_from[q, r] = f, why, T, first
                    bar.update()
    finally:
        bar.close()
    return VerifiedCandidates(fitness, rejection, transforms, retried_from)


def plausible_candidates(indices: np.ndarray, distances: np.ndarray, settings: DetectorSettings,
                         odometry: OdometryTrack | None) -> Candidates:
    """Per query the candidates the node verifies, from a method's ranking ``indices`` / ``distances``
    (n, K), best first: its first ``top_k``; with the odometry gate (``odometry`` and a positive
    ``odometry_drift``), the first ``top_k`` the gate allows among ``SPARE_FACTOR`` times as many,
    those it rules out before them included, as the detector retrieves them."""
    top_k = settings.top_k
    if odometry is None or settings.odometry_drift <= 0:
        return Candidates(indices[:, :top_k], distances[:, :top_k])
    pool_i, pool_d = indices[:, :top_k * SPARE_FACTOR], distances[:, :top_k * SPARE_FACTOR]
    kept = [kept_with_spares([int(j) >= 0 and odometry.too_far(q, int(j), settings) for j in row], top_k)
            for q, row in enumerate(pool_i)]
    width = max(kept, default=top_k)
    out_i, out_d = np.full((len(pool_i), width), -1, np.int64), np.full((len(pool_i), width), np.inf)
    for q, m in enumerate(kept):
        out_i[q, :m], out_d[q, :m] = pool_i[q, :m], pool_d[q, :m]
    return Candidates(out_i, out_d)


def best_verified(candidates: Candidates, verified: VerifiedCandidates) -> tuple[np.ndarray, np.ndarray]:
    """Per query the accepted candidate of highest fitness: ``(indices (n, 1), 1 - fitness (n, 1))``
    — a distance (lower = better) for the retrieval metrics; -1 / inf where none was accepted."""
    ok = verified.accepted_at(0.0)
    fitness = np.where(ok, verified.fitness, -np.inf)
    best = np.argmax(fitness, axis=1)
    rows = np.arange(len(best))
    found = np.isfinite(fitness[rows, best])
    indices = np.where(found, candidates.indices[rows, best], -1)[:, None]
    return indices, np.where(found, 1.0 - fitness[rows, best], np.inf)[:, None]


@dataclass(frozen=True)
class Corroboration:
    """Where the node's odometry places each query and each stored keyframe (each in its own session's
    frame; NaN where unknown), and the fitness from which a closure may be corroborated
    (:mod:`~vbrl_ros.detection.corroboration`)."""

    query_positions: np.ndarray  # (n_queries, 3)
    database_poses: np.ndarray  # (n_database, 4, 4) T_world_lidar
    fitness: float
    # P1, one session: metres driven up to each keyframe, for a weak registration to agree with odometry
    # within odometry_drift of the path (corroboration.agrees_with_odometry); None across sessions
    paths: np.ndarray | None = None
    odometry_drift: float = 0.0


def node_decision(candidates: Candidates, verified: VerifiedCandidates, distance_threshold: float,
                  min_fitness: float, top_k: int,
                  corroboration: Corroboration | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What the node publishes per query: the first of its ``top_k`` candidates within
    ``distance_threshold`` that the rule accepts at ``min_fitness``, else, with ``corroboration``, the
    first weak one the queries before corroborate; ``(indices (n, 1), 0 or inf)``."""
    within = candidates.distances[:, :top_k] <= distance_threshold
    ok = verified.accepted_at(min_fitness)[:, :top_k] & within
    plain = np.ones_like(ok)
    if verified.retried_from is not None:
        first_fitness = verified.retried_from[:, :top_k]
        plain = np.isnan(first_fitness)
        with np.errstate(invalid="ignore"):  # retried by the node only from this first fitness on
            ok &= plain | (first_fitness >= WIDER_RETRY_FITNESS * min_fitness)
        # the node retries wider only when no candidate passed as it was
        ok = np.where((ok & plain).any(axis=1, keepdims=True), ok & plain, ok)
    first = np.argmax(ok, axis=1)
    found = ok.any(axis=1)
    indices = np.where(found, candidates.indices[np.arange(len(first)), first], -1)
    if corroboration is not None and corroboration.fitness < min_fitness:
        fitness = verified.fitness[:, :top_k]
        weak = (verified.accepted_at(corroboration.fitness)[:, :top_k] & within & plain
                & (fitness < min_fitness))
        # the node registers candidates until one passes; one that passed only wider came after them all
        stop = np.where(found & plain[np.arange(len(first)), first], first, top_k)
        indices = _corroborated(indices, np.where(found, first, -1), stop, candidates.indices[:, :top_k], weak,
                                verified.T_query_match[:, :top_k], corroboration)
    return indices[:, None], np.where(indices >= 0, 0.0, np.inf)[:, None]


def _corroborated(published: np.ndarray, slot: np.ndarray, stop: np.ndarray, indices: np.ndarray, weak: np.ndarray,
                  transforms: np.ndarray, corroboration: Corroboration) -> np.ndarray:
    """``published`` (n,) with the weak candidates the queries before corroborate where it is -1, query by
    query as the node decides; ``slot`` (n,): where the published one is among the candidates (-1:
    none); ``stop`` (n,): how many the node registered before it (it stops at the one it publishes);
    ``transforms`` (n, k, 4, 4): each candidate's registration."""
    out = published.copy()
    recent = RecentRegistrations()
    queries, database = corroboration.query_positions, corroboration.database_poses

    for q in range(len(out)):
        weak_slots = [r for r in range(int(stop[q])) if weak[q, r]]
        slots = weak_slots + ([int(slot[q])] if slot[q] >= 0 else [])
        at = {r: registered_position(database[indices[q, r]], transforms[q, r]) for r in slots}
        if out[q] < 0:
            for r in weak_slots:
                if recent.corroborated(q, "query", queries[q], "database", at[r]) and (
                        corroboration.paths is None or agrees_with_odometry(
                            at[r], queries[q], corroboration.paths[q] - corroboration.paths[indices[q, r]],
                            corroboration.odometry_drift)):
                    out[q] = indices[q, r]
                    break
        recent.remember(q, "query", queries[q], [("database", at[r]) for r in slots])
    return out


@dataclass(frozen=True)
class OperatingPoint:
    """One acceptance rule's result: what was published and how much of it was right."""

    accepted: int
    precision: float  # NaN when nothing was accepted
    recall: float  # NaN without revisits

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        return 2 * p * r / (p + r) if p + r > 0 else 0.0

    def summary(self) -> dict[str, float]:
        return {"accepted": self.accepted, "precision": self.precision, "recall": self.recall,
                "f1": self.f1}


def operating_point(metrics: RetrievalMetrics, accepted: int) -> OperatingPoint:
    """The single point of ``metrics`` computed from a 0 / inf decision (:func:`node_decision`)."""
    curve = metrics.pr
    if len(curve.thresholds) == 0:
        return OperatingPoint(accepted, math.nan, 0.0 if metrics.num_revisits else math.nan)
    return OperatingPoint(accepted, float(curve.precision[-1]), float(curve.recall[-1]))
