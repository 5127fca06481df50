"""Online loop-closure detection without ROS: keyframes in, verified candidates out.

The node is a thin adapter around :class:`LoopClosureDetector`; tests and
offline tools drive it directly with numpy scans.

Frames: a model whose grid is in the ground frame levels each scan; its descriptor,
its stored cloud and the verification live in that levelled frame, and the published
``T_query_match`` is converted back to the two sensor frames.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from vbrl_ros.detection.database import Candidate, KeyframeDatabase
from vbrl_ros.detection.registration import Verification, downsample_for_storage, verify_loop
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.index.translation_search import view_offsets
from vbrl_ros.model.model_file import VBRLModel


@dataclass(frozen=True)
class LoopClosure:
    """One accepted candidate. ``T_query_match`` maps match-frame points into the query frame."""

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
    rejected_by_verification: int
    timings_ms: dict[str, float] = field(default_factory=dict)


class LoopClosureDetector:
    """Featurize a keyframe, find it in the database, verify, then remember it.

    ``distance_threshold``: the settings' one; where they say 0, none with verification (every one
    of the ``top_k`` is verified) and the model's own without.
    """

    def __init__(self, model: VBRLModel, database: KeyframeDatabase, settings: DetectorSettings) -> None:
        self.model = model
        self.database = database
        self.settings = settings
        # with verification every one of the top_k is checked: a distance threshold calibrated on
        # one sensor is far too strict on another, the geometry is not
        self.distance_threshold = settings.distance_threshold or (
            math.inf if settings.verify else model.distance_threshold())
        step = model.translation_search() if settings.translation_search < 0 else settings.translation_search
        self.view_offsets = view_offsets(step)
        self.featurizer = model.featurizer()
        self.scorer = database.scorer

    def process_keyframe(
        self, points: np.ndarray, stamp: float, pose: np.ndarray | None = None,
        gravity: np.ndarray | None = None,
    ) -> KeyframeResult:
        """``pose``: T_world_lidar (stored); ``gravity``: 3x3 sensor -> gravity-aligned rotation
        (odometry's roll and pitch) to level by instead of the scan's own ground."""
        cfg = self.settings
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        frame = self.featurizer.frame(points, gravity)
        views = self.scorer.compact(self.model.standardize(
            self.featurizer.describe_views(points, self.view_offsets, frame)))
        t1 = time.perf_counter()
        candidates = self.database.query_views(
            views, self.view_offsets, top_k=cfg.top_k, session=cfg.session, stamp=stamp,
            exclude_recent_s=cfg.exclude_recent_s,
        )
        t2 = time.perf_counter()
        cloud = verification_cloud(points, frame.matrix, cfg.verification_voxel) if cfg.verify else None
        closures: list[LoopClosure] = []
        rejected = 0
        for candidate in candidates:
            if candidate.distance > self.distance_threshold or len(closures) >= cfg.max_closures:
                break  # sorted by distance: nothing further can pass
            closure = LoopClosure(
                query_id=self.database.next_keyframe_id, match_id=candidate.keyframe_id,
                query_stamp=stamp, match_stamp=candidate.stamp, query_session=cfg.session,
                match_session=candidate.session, distance=float(candidate.distance),
                yaw=float(candidate.yaw),
            )
            if cfg.verify:
                check = self._verify(cloud, candidate)
                T, covariance = to_sensor_frames(check, frame.matrix, self.database.frame(candidate.index))
                if closure_rejection(check, T, cfg) is not None:
                    rejected += 1
                    continue
                closure = LoopClosure(
                    **{**closure.__dict__, "T_query_match": T, "fitness": check.fitness,
                       "covariance": covariance}
                )
            closures.append(closure)
        t3 = time.perf_counter()
        keyframe_id = self.database.add(views[0], stamp, cfg.session, pose=pose, cloud=cloud,
                                        frame=frame.matrix)
        t4 = time.perf_counter()
        timings.update(describe=1e3 * (t1 - t0), query=1e3 * (t2 - t1),
                       verify=1e3 * (t3 - t2), insert=1e3 * (t4 - t3))
        return KeyframeResult(keyframe_id, closures, len(candidates), rejected, timings)

    def _verify(self, cloud: np.ndarray, candidate: Candidate) -> Verification:
        # no initial guess: the verification searches every heading itself, as the
        # recogniser's yaw is often a symmetric place's other heading
        return verify_loop(cloud, self.database.cloud(candidate.index),
                           voxel_size=self.settings.verification_voxel)


def verification_cloud(points: np.ndarray, frame: np.ndarray, voxel: float) -> np.ndarray:
    """What a keyframe keeps for verification: one point per ``voxel``, in its levelled ``frame``
    (4x4 sensor -> grid), float32 (M, 3). Thinned first, then levelled: the same cloud for a
    fraction of the rotations."""
    thinned = downsample_for_storage(points, voxel).astype(np.float64)
    return (thinned @ frame[:3, :3].T + frame[:3, 3]).astype(np.float32)


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
