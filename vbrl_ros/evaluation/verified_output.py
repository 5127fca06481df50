"""One method's verified output, scored: select, verify, sweep and decide as ``vbrl eval --verify``
and ``vbrl loo`` both do, so that the two report the same figures for the same ranking.

From a method's ranking, the candidates the node would verify
(:func:`~vbrl_ros.evaluation.verified.plausible_candidates`) are registered as the node registers
them, from the clouds it would hold (:class:`VerificationInputs`, built once per source and shared
by every method); the result is scored swept over fitness and at the node's settings
(:mod:`vbrl_ros.evaluation.verified`), each closure handed on to the stored keyframe nearest the
query as the node hands it on (:func:`nearest_published`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from vbrl_ros.detection.candidate_verification import WIDER_RETRY_NEIGHBOURS
from vbrl_ros.detection.nearest_keyframe import nearest_along_path, rows_along_path
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.detection.submaps import MAX_NEIGHBOUR_DISTANCE_M, WIDER_NEIGHBOUR_DISTANCE_M
from vbrl_ros.evaluation.methods import SourceDescriptors
from vbrl_ros.evaluation.metrics import RetrievalMetrics
from vbrl_ros.evaluation.retrieval import RetrievalResults
from vbrl_ros.evaluation.verified import (
    Candidates,
    Corroboration,
    KeyframeClouds,
    OdometryTrack,
    OperatingPoint,
    VerifiedCandidates,
    best_verified,
    node_decision,
    operating_point,
    plausible_candidates,
    submap_clouds,
    verify_candidates,
)

__all__ = ["Score", "VerificationInputs", "VerifiedOutput", "odometry_track", "verified_clouds", "verified_output",
           "wider_clouds"]

#: The protocol's metrics of a ranking, by radius.
Score = Callable[[RetrievalResults], dict[float, RetrievalMetrics]]


def odometry_track(queries: SourceDescriptors, database: SourceDescriptors) -> OdometryTrack | None:
    """P1's one session as the node's odometry sees it (the source's poses); None for P2, whose two
    sessions odometry does not relate, and without poses."""
    return OdometryTrack.of(queries.poses) if database is queries else None


def verified_clouds(queries: SourceDescriptors, database: SourceDescriptors, rule: DetectorSettings, *,
                    neighbours: int | None = None,
                    reach_m: float = MAX_NEIGHBOUR_DISTANCE_M) -> tuple[KeyframeClouds, KeyframeClouds]:
    """The queries' and the database's clouds as the node verifies them under ``rule``: submaps
    of the queries' past and of the stored keyframes' both sides (the same source for P1), of
    ``neighbours`` (default: the rule's ``submap_keyframes``) within ``reach_m``."""
    def submaps(source: SourceDescriptors, both_sides: bool) -> KeyframeClouds:
        return submap_clouds(source.clouds, source.poses, source.stamps, rule, both_sides=both_sides,
                             neighbours=neighbours, reach_m=reach_m)
    return submaps(queries, False), submaps(database, True)


def wider_clouds(queries: SourceDescriptors, database: SourceDescriptors,
                 rule: DetectorSettings) -> tuple[KeyframeClouds, KeyframeClouds] | None:
    """The clouds a degenerate registration is retried with, as the node retries it: submaps of
    ``WIDER_RETRY_NEIGHBOURS`` times the rule's neighbours within ``WIDER_NEIGHBOUR_DISTANCE_M``; None
    without submaps (no poses, or ``submap_keyframes`` 0)."""
    if rule.submap_keyframes == 0 or queries.poses is None or database.poses is None:
        return None
    return verified_clouds(queries, database, rule, neighbours=WIDER_RETRY_NEIGHBOURS * rule.submap_keyframes,
                           reach_m=WIDER_NEIGHBOUR_DISTANCE_M)


@dataclass(frozen=True)
class VerificationInputs:
    """What verification reads of the sources under one rule: the clouds, the wider ones a
    degenerate registration is retried with, and P1's odometry."""

    clouds: tuple[KeyframeClouds, KeyframeClouds]
    wider: tuple[KeyframeClouds, KeyframeClouds] | None
    odometry: OdometryTrack | None
    # where odometry places the queries (n, 3) and the stored keyframes (m, 4, 4), each in its session's
    # frame (None without)
    poses: tuple[np.ndarray, np.ndarray] | None = None
    # the stored keyframes' session as odometry knows it, along which a closure moves to the nearest
    # keyframe (detection.nearest_keyframe); None without poses
    database_track: OdometryTrack | None = None

    @classmethod
    def of(cls, queries: SourceDescriptors, database: SourceDescriptors,
           rule: DetectorSettings) -> VerificationInputs:
        """``database`` is ``queries`` for P1."""
        poses = None if queries.poses is None or database.poses is None else (queries.poses[:, :3, 3], database.poses)
        return cls(verified_clouds(queries, database, rule), wider_clouds(queries, database, rule),
                   odometry_track(queries, database), poses, OdometryTrack.of(database.poses))


@dataclass(frozen=True)
class VerifiedOutput:
    """A method's candidates and what verification said of each; the best verified candidate per
    query (:func:`~vbrl_ros.evaluation.verified.best_verified`) and its metrics swept over fitness (by
    radius); the operating points at the node's settings (by min_fitness, then radius)."""

    candidates: Candidates
    verified: VerifiedCandidates
    best: tuple[np.ndarray, np.ndarray]
    best_nearest: np.ndarray  # (n, 1) the keyframe the best verified closure is published to (-1: none)
    swept: dict[float, RetrievalMetrics]
    points: dict[float, dict[float, OperatingPoint]]
    published: dict[float, np.ndarray]  # by min_fitness: (n, 1) the keyframe each query's closure went to (-1: none)


def verified_output(inputs: VerificationInputs, results: RetrievalResults, rule: DetectorSettings, score: Score, *,
                    min_fitness: Sequence[float] | None = None, distance_threshold: float = math.inf,
                    workers: int | None = None, progress: bool = True,
                    description: str = "verifying") -> VerifiedOutput:
    """Verify the candidates the node would take from ``results`` under ``rule`` and score them:
    swept, and what it publishes at each ``min_fitness`` (default: the rule's) with candidates
    beyond ``distance_threshold`` unverified."""
    candidates = plausible_candidates(results.indices, results.distances, rule, inputs.odometry)
    k = candidates.indices.shape[1]  # at most top_k of them the odometry gate allows
    fitnesses = (rule.min_fitness,) if min_fitness is None else tuple(min_fitness)
    # retried from the lowest min_fitness's threshold on; node_decision keeps what each would retry
    lowest = replace(rule, min_fitness=min(fitnesses))
    verified = verify_candidates(*inputs.clouds, candidates, lowest, wider=inputs.wider, odometry=inputs.odometry,
                                 workers=workers, progress=progress, description=description)
    best = best_verified(candidates, verified)
    limits = results.database_limit
    best_nearest = nearest_published(best[0], candidates, verified, inputs.database_track, limits)
    swept = score(RetrievalResults(best_nearest, best[1], limits))
    points, published = {}, {}
    corroboration = None if inputs.poses is None else Corroboration(
        *inputs.poses, rule.corroborated_fitness, None if inputs.odometry is None else inputs.odometry.paths,
        rule.odometry_drift)
    for fitness in fitnesses:
        decided, decision = node_decision(candidates, verified, distance_threshold, fitness, k, corroboration)
        decided = nearest_published(decided, candidates, verified, inputs.database_track, limits)
        accepted = int(np.isfinite(decision).sum())
        points[fitness] = {r: operating_point(m, accepted)
                           for r, m in score(RetrievalResults(decided, decision, limits)).items()}
        published[fitness] = decided
    return VerifiedOutput(candidates, verified, best, best_nearest, swept, points, published)


def nearest_published(indices: np.ndarray, candidates: Candidates, verified: VerifiedCandidates,
                      track: OdometryTrack | None, limits: np.ndarray) -> np.ndarray:
    """``indices`` (n, 1) of verified candidates (-1: none), each handed to the stored keyframe nearest
    where its registration put the query along its path, as the node hands its closures on
    (:mod:`~vbrl_ros.detection.nearest_keyframe`); ``track``: the stored keyframes' odometry (None:
    unchanged), ``limits`` (n,): the database prefix each query saw."""
    if track is None:
        return indices
    out = indices.copy()
    sessions = np.zeros(len(track.paths), np.int64)
    for q in np.flatnonzero(indices[:, 0] >= 0):
        match = int(indices[q, 0])
        T = verified.T_query_match[q, int(np.flatnonzero(candidates.indices[q] == match)[0])]
        rows = rows_along_path(match, sessions, track.paths)
        rows = rows[rows < limits[q]]
        out[q, 0] = nearest_along_path(T, track.poses[match], rows, track.poses[rows], match)[0]
    return out
