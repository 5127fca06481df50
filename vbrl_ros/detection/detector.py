"""Online loop-closure detection without ROS: keyframes in, verified candidates out.

The node is a thin adapter around :class:`LoopClosureDetector`; tests and
offline tools drive it directly with numpy scans.

Frames: a model whose grid is in the ground frame levels each scan; its descriptor,
its stored cloud and the verification live in that levelled frame, and the published
``T_query_match`` is converted back to the two sensor frames.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from vbrl_ros.detection.database import Candidate, KeyframeDatabase
from vbrl_ros.detection.registration import Verification, downsample_for_storage, verify_loop, yaw_guess
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

    ``distance_threshold``: the settings' one, or the model's own where they say 0.
    """

    def __init__(self, model: VBRLModel, database: KeyframeDatabase, settings: DetectorSettings) -> None:
        self.model = model
        self.database = database
        self.settings = settings
        self.distance_threshold = settings.distance_threshold or model.distance_threshold()
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
        # thinned first, then levelled: the same cloud for a fraction of the rotations
        cloud = (frame.apply(downsample_for_storage(points, cfg.verification_voxel)).astype(np.float32)
                 if cfg.verify else None)
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
                if not check.converged or check.fitness < cfg.min_fitness:
                    rejected += 1
                    continue
                T, covariance = to_sensor_frames(check, frame.matrix, self.database.frame(candidate.index))
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
        # The recogniser's yaw (and, with translation search, the match's position) puts
        # KISS-ICP inside its +-10 degree basin for revisits in any direction.
        guess = yaw_guess(candidate.yaw)
        guess[:2, 3] = candidate.offset
        return verify_loop(cloud, self.database.cloud(candidate.index), initial_guess=guess,
                           voxel_size=self.settings.verification_voxel)


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
