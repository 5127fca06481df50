"""Online loop-closure detection without ROS: keyframes in, verified candidates out.

The node is a thin adapter around :class:`LoopClosureDetector`; tests and
offline tools drive it directly with numpy scans.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.registration import downsample_for_storage, verify_loop, yaw_guess
from vbrl_ros.detection.settings import DetectorSettings
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
    yaw: float = 0.0  # recogniser's yaw of T_query_match, radians (polar grid; 0 for Cartesian)
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
        self.featurizer = model.featurizer()
        self.scorer = database.scorer

    def process_keyframe(
        self, points: np.ndarray, stamp: float, pose: np.ndarray | None = None
    ) -> KeyframeResult:
        cfg = self.settings
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        descriptor = self.scorer.compact(self.model.standardize(self.featurizer.describe(points)))
        t1 = time.perf_counter()
        candidates = self.database.query(
            descriptor, top_k=cfg.top_k, session=cfg.session, stamp=stamp,
            exclude_recent_s=cfg.exclude_recent_s,
        )
        t2 = time.perf_counter()
        cloud = downsample_for_storage(points, cfg.verification_voxel) if cfg.verify else None
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
                match_cloud = self.database.cloud(candidate.index)
                # The polar grid's yaw puts KISS-ICP inside its +-10 degree basin
                # for revisits in any direction (Cartesian: yaw 0, identity guess).
                check = verify_loop(cloud, match_cloud, initial_guess=yaw_guess(candidate.yaw),
                                    voxel_size=cfg.verification_voxel)
                if not check.converged or check.fitness < cfg.min_fitness:
                    rejected += 1
                    continue
                closure = LoopClosure(
                    **{**closure.__dict__, "T_query_match": check.T_query_match,
                       "fitness": check.fitness, "covariance": check.covariance}
                )
            closures.append(closure)
        t3 = time.perf_counter()
        keyframe_id = self.database.add(descriptor, stamp, cfg.session, pose=pose, cloud=cloud)
        t4 = time.perf_counter()
        timings.update(describe=1e3 * (t1 - t0), query=1e3 * (t2 - t1),
                       verify=1e3 * (t3 - t2), insert=1e3 * (t4 - t3))
        return KeyframeResult(keyframe_id, closures, len(candidates), rejected, timings)
