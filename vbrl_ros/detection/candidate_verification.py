"""Verifying one keyframe's candidates: what the detector hands over (:class:`Retrieval`), the
rule a registration passes, and what comes back (:class:`KeyframeResult`).

It needs no database, so the node runs :func:`verify_candidates` in another process
(:mod:`~vbrl_ros.detection.verifier_process`) while the next keyframe is described and searched,
and ``vbrl eval --verify`` applies the same rule to every method's candidates.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from vbrl_ros.detection.database import Candidate
from vbrl_ros.detection.registration import QueryVerifier, Verification
from vbrl_ros.detection.settings import DetectorSettings


@dataclass(frozen=True)
class LoopClosure:
    """One accepted candidate. ``T_query_match`` maps match-frame points into the query frame.

    Verified, the match is the stored keyframe nearest where the registration put the query, along
    the path of the keyframe registered (:mod:`~vbrl_ros.detection.nearest_keyframe`); ``distance``
    and ``yaw`` stay the recogniser's, of the keyframe it retrieved."""

    query_id: int
    match_id: int
    query_stamp: float
    match_stamp: float
    query_session: str
    match_session: str
    distance: float  # Eq. 4, lower = more similar
    yaw: float = 0.0  # recogniser's yaw of T_query_match in the grid frame, radians (0 for Cartesian)
    T_query_match: np.ndarray | None = None
    fitness: float = float("nan")
    covariance: np.ndarray | None = None  # 6x6 over [x, y, z, roll, pitch, yaw]


@dataclass
class KeyframeResult:
    keyframe_id: int
    closures: list[LoopClosure]
    candidates_scored: int
    timings_ms: dict[str, float] = field(default_factory=dict)
    rejections: dict[str, int] = field(default_factory=dict)  # reason -> candidates rejected for it
    # positions in the retrieval's candidates of registrations worth a wider submap (see WIDER_RETRY_FITNESS)
    degenerate: list[int] = field(default_factory=list)
    # registrations short of min_fitness but at least corroborated_fitness, in candidate order: published
    # when an earlier keyframe corroborates them (detection.corroboration)
    weak: list[LoopClosure] = field(default_factory=list)
    corroborated: int = 0  # of the closures, how many were accepted so
    handed_on: int = 0  # of the closures, how many went to a keyframe nearer the query (detection.nearest_keyframe)

    @property
    def rejected_by_verification(self) -> int:
        return sum(self.rejections.values())


@dataclass
class Retrieval:
    """A keyframe described, searched and stored, with everything its candidates' verification needs
    (copies: the database may change while they are verified elsewhere)."""

    keyframe_id: int
    stamp: float
    session: str
    # within the distance threshold, best (lowest distance) first: top_k of them, and with the odometry
    # gate the ones it ruled out before the top_k-th it allows
    candidates: list[Candidate]
    candidates_scored: int
    frame: np.ndarray  # 4x4 sensor -> grid frame of the query
    cloud: np.ndarray | None = None  # the query's verification cloud, in its grid frame
    candidate_clouds: list[np.ndarray] = field(default_factory=list)
    candidate_frames: list[np.ndarray] = field(default_factory=list)
    timings_ms: dict[str, float] = field(default_factory=dict)


#: The cloud of a candidate that odometry rules out: it is rejected without being registered.
NOT_REGISTERED = np.zeros((0, 3), np.float32)

#: A registration that slid along a street or corridor ("degenerate") but overlapped at least this
#: share of ``min_fitness`` is registered once more with submaps of WIDER_RETRY_NEIGHBOURS times as
#: many neighbours, reaching up to WIDER_NEIGHBOUR_DISTANCE_M: where a partly blind sensor's passes
#: share only side facades, the wider maps reach the structure along the street that fixes the
#: position there. On the simulated low robot with 90 degrees hidden, four times the neighbours
#: within 12 m published more closures than twice within 6 m (docs/results/recordings.md); on the shared
#: recordings neither changed anything.
WIDER_RETRY_FITNESS = 0.7
WIDER_RETRY_NEIGHBOURS = 4


def wants_wider_retry(result: KeyframeResult, settings: DetectorSettings) -> bool:
    """Whether ``result`` has degenerate registrations to retry and room for another closure."""
    return bool(result.degenerate) and settings.submap_keyframes > 0 and len(result.closures) < settings.max_closures


def with_wider_retry(first: KeyframeResult, retried: KeyframeResult, settings: DetectorSettings) -> KeyframeResult:
    """``first`` with the closures its wider retry accepted, after its own, up to ``max_closures``."""
    accepted = retried.closures[: settings.max_closures - len(first.closures)]
    rejections = dict(first.rejections)
    rejections["degenerate"] = rejections.get("degenerate", 0) - len(accepted)
    if rejections["degenerate"] <= 0:
        del rejections["degenerate"]
    timings = {**first.timings_ms, "wider_retry": retried.timings_ms.get("verify", 0.0)}
    return replace(first, closures=first.closures + accepted, rejections=rejections, timings_ms=timings,
                   degenerate=[])


def verify_candidates(retrieval: Retrieval, settings: DetectorSettings) -> KeyframeResult:
    """The retrieval's loop closures: its candidates best first, each verified when ``settings``
    say so, until ``max_closures`` pass. Needs no database: it runs where the clouds are sent."""
    start = time.perf_counter()
    closures: list[LoopClosure] = []
    rejections: dict[str, int] = {}
    degenerate: list[int] = []
    weak: list[LoopClosure] = []
    # the query's thinning, ground, KD-tree and heading image are prepared once for all candidates
    verifier = (query_verifier(retrieval.cloud, settings, sensor=retrieval.frame)
                if settings.verify and retrieval.candidates else None)
    for k, candidate in enumerate(retrieval.candidates):
        if len(closures) >= settings.max_closures:
            break
        if candidate.too_far_by_odometry:  # not one place, however well it would register
            rejections["odometry"] = rejections.get("odometry", 0) + 1
            continue
        closure = LoopClosure(
            query_id=retrieval.keyframe_id, match_id=candidate.keyframe_id,
            query_stamp=retrieval.stamp, match_stamp=candidate.stamp, query_session=retrieval.session,
            match_session=candidate.session, distance=float(candidate.distance),
            yaw=float(candidate.yaw),
        )
        if settings.verify:
            # no initial guess: the verification searches every heading itself, as the
            # recogniser's yaw is often a symmetric place's other heading
            check = verifier.verify(retrieval.candidate_clouds[k], expected_yaw=candidate.odometry_yaw,
                                   sensor=retrieval.candidate_frames[k])
            T, covariance = to_sensor_frames(check, retrieval.frame, retrieval.candidate_frames[k])
            reason = closure_rejection(check, T, settings)
            closure = LoopClosure(
                **{**closure.__dict__, "T_query_match": T, "fitness": check.fitness,
                   "covariance": covariance}
            )
            if reason is not None:
                rejections[reason] = rejections.get(reason, 0) + 1
                if reason == "degenerate" and check.fitness >= WIDER_RETRY_FITNESS * settings.min_fitness:
                    degenerate.append(k)
                if reason == "low fitness" and is_weak(check.fitness, T, settings):
                    weak.append(closure)
                continue
        closures.append(closure)
    timings = {**retrieval.timings_ms, "verify": 1e3 * (time.perf_counter() - start)}
    return KeyframeResult(retrieval.keyframe_id, closures, retrieval.candidates_scored, timings, rejections,
                          degenerate, weak)


def is_weak(fitness: float, T_query_match: np.ndarray, settings: DetectorSettings) -> bool:
    """Whether a registration refused only for its fitness may still be corroborated: at least
    ``corroborated_fitness`` and no farther than a closure may be."""
    return (settings.corroborated_fitness <= fitness < settings.min_fitness
            and float(np.linalg.norm(T_query_match[:3, 3])) <= settings.max_closure_distance)


def query_verifier(cloud: np.ndarray, settings: DetectorSettings, max_threads: int = 0,
                   sensor: np.ndarray | None = None) -> QueryVerifier:
    """The verifier of one query's candidates under ``settings``: at their voxel, its heading search
    no farther than a closure they accept; ``sensor``: the query's frame (sensor -> grid)."""
    return QueryVerifier(cloud, voxel_size=settings.verification_voxel, max_threads=max_threads,
                         max_closure_distance=settings.max_closure_distance, sensor=sensor)


def closure_rejection(check: Verification, T_query_match: np.ndarray,
                      settings: DetectorSettings) -> str | None:
    """Why a verified candidate is not published (None: it is). ``T_query_match``: between
    the sensors. Beyond ``max_closure_distance`` the registration may be right, but the two
    keyframes are not the same place."""
    reason = check.rejection(settings.min_fitness)
    if reason is None and np.linalg.norm(T_query_match[:3, 3]) > settings.max_closure_distance:
        return "too far"
    return reason


def to_sensor_frames(check: Verification, query_frame: np.ndarray,
                     match_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A registration between two grid frames as ``T_query_match`` between the sensors, with its
    covariance (left perturbation in the query frame) carried into the query sensor's frame."""
    F_q_inv = np.linalg.inv(query_frame)
    T = F_q_inv @ check.T_query_match @ match_frame
    R, t = F_q_inv[:3, :3], F_q_inv[:3, 3]
    adjoint = np.zeros((6, 6))  # of F_q_inv, for xi = [translation, rotation]
    adjoint[:3, :3] = adjoint[3:, 3:] = R
    adjoint[:3, 3:] = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ R
    return T, adjoint @ check.covariance @ adjoint.T
