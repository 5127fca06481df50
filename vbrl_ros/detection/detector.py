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
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np

from vbrl_ros.detection.candidate_verification import (
    NOT_REGISTERED,
    WIDER_RETRY_NEIGHBOURS,
    KeyframeResult,
    LoopClosure,
    Retrieval,
    verify_candidates,
    wants_wider_retry,
    with_wider_retry,
)
from vbrl_ros.detection.corroboration import RecentRegistrations, agrees_with_odometry, registered_position
from vbrl_ros.detection.database import Candidate, KeyframeDatabase
from vbrl_ros.detection.nearest_keyframe import REACH_M, nearest_along_path
from vbrl_ros.detection.odometry_gate import SPARE_FACTOR, kept_with_spares, odometry_heading, too_far_by_odometry
from vbrl_ros.detection.registration import downsample_for_storage
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.detection.submaps import WIDER_NEIGHBOUR_DISTANCE_M
from vbrl_ros.features.blind_wedges import all_round_by_itself, looks_forward
from vbrl_ros.features.trail import Trail
from vbrl_ros.features.trail_ahead import TrailAhead
from vbrl_ros.index.sequence_matching import SequenceHistory
from vbrl_ros.index.translation_search import view_offsets
from vbrl_ros.model.model_file import VBRLModel


class Keyframe(NamedTuple):
    """A keyframe due to be described (:meth:`LoopClosureDetector.keyframes_due`)."""

    points: np.ndarray
    stamp: float
    pose: np.ndarray | None
    gravity: np.ndarray | None
    ahead: list[np.ndarray]  # the points of the keyframes after it, in its frame (features.trail_ahead)
    tag: Any  # what the caller gave with it


class LoopClosureDetector:
    """Featurize a keyframe, find it in the database, remember it, verify its candidates.

    ``distance_threshold``: the settings' one; where they say 0, none with verification (every one
    of the ``top_k`` is verified) and the model's own without.

    :meth:`process_keyframe` does it all in one call; the node hands each keyframe to
    :meth:`keyframes_due`, calls :meth:`retrieve_keyframe` for each one due and verifies the
    :class:`Retrieval` with :func:`verify_candidates` in another process, while the next
    keyframe is described and searched.
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
        # the keyframes a keyframe is described with: as a submap, none a candidate's submap holds
        features = model.config.features
        self.trail = Trail(features.trail_m, features.forward_trail_m, max_age=submap_gap_s(settings),
                           fill_blind_wedges=features.fill_blind_wedges and settings.fill_blind_wedges)
        # keyframes waiting for the sensor to pass them, described in the order they came
        self.trail_ahead: TrailAhead[Keyframe] = TrailAhead(features.trail_ahead_m, max_age=submap_gap_s(settings))
        self.scorer = database.scorer
        self.sequence = SequenceHistory(settings.sequence_length)
        self.recent = RecentRegistrations()  # what the last keyframes registered to, to corroborate with

    def clear_database(self) -> None:
        """Forget every stored keyframe, and with them the earlier keyframes' candidate pools and
        registrations, which name keyframes that are gone. The trail stays: it is the live stream's."""
        self.database.clear()
        self.sequence.clear()
        self.recent.clear()

    def process_keyframe(
        self, points: np.ndarray, stamp: float, pose: np.ndarray | None = None,
        gravity: np.ndarray | None = None,
    ) -> KeyframeResult:
        """``pose``: T_world_lidar (stored); ``gravity``: 3x3 sensor -> gravity-aligned rotation
        (odometry's roll and pitch) to level by instead of the scan's own ground. Described at
        once, without the keyframes after it (:meth:`keyframes_due` waits for them)."""
        return self.verified(self.retrieve(points, stamp, pose, gravity),
                             lambda retrieval: verify_candidates(retrieval, self.settings))

    def verified(self, retrieval: Retrieval, verify: Callable[[Retrieval], KeyframeResult],
                 database_lock: AbstractContextManager | None = None) -> KeyframeResult:
        """``retrieval``'s closures by ``verify`` (:func:`verify_candidates`, here or in another
        process), degenerate registrations retried with wider submaps (:data:`WIDER_RETRY_FITNESS`),
        which are built from the database under ``database_lock``."""
        result = verify(retrieval)
        if wants_wider_retry(result, self.settings):
            with database_lock or nullcontext():
                wider = self.widened(retrieval, result.degenerate)
            if wider is not None:
                result = with_wider_retry(result, verify(wider), self.settings)
        if self.settings.verify and self.settings.corroborated_fitness < self.settings.min_fitness:
            with database_lock or nullcontext():
                result = self._corroborated(retrieval, result)
        if self.settings.verify and result.closures:
            with database_lock or nullcontext():
                nearest = [self._to_nearest(retrieval, c) for c in result.closures]
            moved = sum(a.match_id != b.match_id for a, b in zip(result.closures, nearest))
            result = replace(result, closures=nearest, handed_on=moved)
        return result

    def _to_nearest(self, retrieval: Retrieval, closure: LoopClosure) -> LoopClosure:
        """``closure`` handed to the stored keyframe nearest where it put the query, along its match's
        path (:mod:`~vbrl_ros.detection.nearest_keyframe`), among those the query may close a loop with."""
        try:
            row = self.database.index_of(closure.match_id)
        except KeyError:  # cleared since
            return closure
        along = self.database.along_path(row, REACH_M)
        allowed = along.keyframe_ids != retrieval.keyframe_id
        if closure.match_session == retrieval.session:  # the recent past is never a candidate
            allowed &= along.stamps <= retrieval.stamp - self.settings.exclude_recent_s
        allowed |= along.rows == row
        rows, poses = along.rows[allowed], along.poses[allowed]
        nearest, T = nearest_along_path(closure.T_query_match, self.database.pose(row), rows, poses, row)
        if nearest == row:
            return closure
        k = int(np.flatnonzero(rows == nearest)[0])
        return replace(closure, match_id=int(along.keyframe_ids[allowed][k]),
                       match_stamp=float(along.stamps[allowed][k]), T_query_match=T)

    def _corroborated(self, retrieval: Retrieval, result: KeyframeResult) -> KeyframeResult:
        """``result`` with its weak registrations that the last keyframes corroborate accepted, up to
        ``max_closures``; then this keyframe's registrations remembered."""
        def pose(keyframe_id: int) -> np.ndarray | None:
            try:
                T = self.database.pose(self.database.index_of(keyframe_id))
            except KeyError:  # cleared since
                return None
            return T if np.isfinite(T).all() else None

        def registered(closure: LoopClosure) -> np.ndarray | None:
            match = pose(closure.match_id)
            return None if match is None else registered_position(match, closure.T_query_match)

        here = pose(retrieval.keyframe_id)
        here = None if here is None else here[:3, 3]
        registrations = [(c, registered(c)) for c in result.closures + result.weak]
        accepted = []
        for weak, at in registrations[len(result.closures):]:
            if len(result.closures) + len(accepted) >= self.settings.max_closures:
                break
            if (self.recent.corroborated(retrieval.keyframe_id, retrieval.session, here, weak.match_session, at)
                    and self._agrees_with_odometry(retrieval, weak, at, here)):
                accepted.append(weak)
        self.recent.remember(retrieval.keyframe_id, retrieval.session, here,
                             [(c.match_session, at) for c, at in registrations])
        if not accepted:
            return result
        rejections = dict(result.rejections)
        rejections["low fitness"] -= len(accepted)
        if rejections["low fitness"] <= 0:
            del rejections["low fitness"]
        return replace(result, closures=result.closures + accepted, rejections=rejections,
                       corroborated=len(accepted))

    def _agrees_with_odometry(self, retrieval: Retrieval, weak: LoopClosure, at: np.ndarray,
                              here: np.ndarray) -> bool:
        """A weak registration to the query's own session also agrees with odometry (corroboration)."""
        if weak.match_session != retrieval.session:
            return True
        try:
            _, path = self.database.odometry_apart(self.database.index_of(retrieval.keyframe_id),
                                                   self.database.index_of(weak.match_id))
        except KeyError:  # cleared since
            return False
        return agrees_with_odometry(at, here, path, self.settings.odometry_drift)

    def keyframes_due(
        self, points: np.ndarray, stamp: float, pose: np.ndarray | None = None,
        gravity: np.ndarray | None = None, tag: Any = None,
    ) -> list[Keyframe]:
        """Take a keyframe (arguments as :meth:`process_keyframe`; ``tag`` comes back with it);
        the keyframes now due to be described, oldest first: with the model's
        ``features.trail_ahead_m`` one with a trail waits until odometry has carried the sensor
        that far past it (:class:`~vbrl_ros.features.trail_ahead.TrailAhead`), else it is due at once."""
        if self.trail_ahead.ahead_m > 0:  # it may wait: copies, the caller may reuse its buffers
            points = np.array(points)
            pose, gravity = (None if m is None else np.array(m, np.float64) for m in (pose, gravity))
        item = Keyframe(points, stamp, pose, gravity, [], tag)
        return [keyframe._replace(ahead=ahead) for keyframe, ahead in
                self.trail_ahead.add(item, points, pose, self.settings.session, stamp)]

    def keyframes_waiting(self) -> list[Keyframe]:
        """Every keyframe still waiting, now due with what came after it (the input fell silent, or stops)."""
        return [keyframe._replace(ahead=ahead) for keyframe, ahead in self.trail_ahead.flush()]

    def retrieve_keyframe(self, keyframe: Keyframe) -> Retrieval:
        """:meth:`retrieve` of a keyframe :meth:`keyframes_due` returned, in that order."""
        return self.retrieve(keyframe.points, keyframe.stamp, keyframe.pose, keyframe.gravity, keyframe.ahead)

    def retrieve(
        self, points: np.ndarray, stamp: float, pose: np.ndarray | None = None,
        gravity: np.ndarray | None = None, ahead: Sequence[np.ndarray] = (),
    ) -> Retrieval:
        """Describe the keyframe, find its candidates, store it (arguments as :meth:`process_keyframe`;
        ``ahead``: :attr:`Keyframe.ahead`)."""
        cfg = self.settings
        t0 = time.perf_counter()
        described, all_round, sees = self.trail.clouds(points, pose, cfg.session, stamp=stamp, ahead=ahead)
        frame = self.featurizer.frame(described, gravity, scan=points)
        views = self.scorer.compact(self.model.standardize(
            self.featurizer.describe_views(described, self.view_offsets, frame)))
        all_round_views = None if all_round is None else self.scorer.compact(self.model.standardize(
            self.featurizer.describe_views(all_round, self.view_offsets, frame)))
        whole = all_round_by_itself(described, all_round, self.trail.fill_blind_wedges, sees)
        t1 = time.perf_counter()
        # with the odometry gate and a pose, spares take the place of the candidates it rules out
        gated = cfg.odometry_drift > 0 and pose is not None
        found = self.database.query_views(
            views, self.view_offsets, top_k=cfg.top_k * (SPARE_FACTOR if gated else 1),
            session=cfg.session, stamp=stamp, exclude_recent_s=cfg.exclude_recent_s, sequence=self.sequence,
            position=None if pose is None else np.asarray(pose, np.float64)[:3, 3], all_round_views=all_round_views,
            sees_all_round=whole,
        )
        # sorted by distance: the first beyond the threshold ends the list
        candidates = [c for c in found if c.distance <= self.distance_threshold]
        t2 = time.perf_counter()
        cloud = verification_cloud(verified_by(points, described), frame.matrix,
                                   cfg.verification_voxel) if cfg.verify else None
        keyframe_id = self.database.add(views[0], stamp, cfg.session, pose=pose, cloud=cloud, frame=frame.matrix,
                                        all_round=None if all_round_views is None else all_round_views[0],
                                        sees_all_round=whole)
        candidates = [self._gated(c, len(self.database) - 1) for c in candidates]
        candidates = candidates[:kept_with_spares([c.too_far_by_odometry for c in candidates], cfg.top_k)]
        t3 = time.perf_counter()
        retrieval = Retrieval(  # rows of older keyframes stay where they were after an add
            keyframe_id=keyframe_id, stamp=stamp, session=cfg.session,
            candidates=candidates, candidates_scored=len(found), frame=frame.matrix,
            cloud=self._verified_cloud(len(self.database) - 1, both_sides=False) if cfg.verify else None,
            candidate_clouds=[NOT_REGISTERED if c.too_far_by_odometry else self._verified_cloud(c.index)
                              for c in candidates] if cfg.verify else [],
            candidate_frames=[self.database.frame(c.index) for c in candidates],
        )
        t4 = time.perf_counter()
        retrieval.timings_ms.update(describe=1e3 * (t1 - t0), query=1e3 * (t2 - t1), insert=1e3 * (t3 - t2),
                                    submaps=1e3 * (t4 - t3))
        return retrieval

    def _gated(self, candidate: Candidate, query_row: int) -> Candidate:
        """``candidate`` marked when odometry places it too far from the query, else given the yaw
        odometry expects its registration to find (odometry_gate), when the gate is on."""
        apart, path = self.database.odometry_apart(query_row, candidate.index)
        if too_far_by_odometry(apart, path, self.settings.max_closure_distance, self.settings.odometry_drift):
            return replace(candidate, too_far_by_odometry=True)
        if not math.isfinite(apart):  # another session, or a pose unknown: odometry says nothing
            return candidate
        db = self.database
        return replace(candidate, odometry_yaw=odometry_heading(
            db.pose(query_row), db.pose(candidate.index), db.frame(query_row), db.frame(candidate.index),
            self.settings.odometry_drift))

    def widened(self, retrieval: Retrieval, positions: list[int]) -> Retrieval | None:
        """``retrieval`` with only the candidates at ``positions``, its query's and their clouds merged
        from twice ``submap_keyframes`` neighbours (:data:`WIDER_RETRY_FITNESS`); None without
        submaps or when one of the keyframes is no longer stored (a cleared database)."""
        cfg = self.settings
        if cfg.submap_keyframes == 0 or not positions:
            return None
        try:
            query = self.database.index_of(retrieval.keyframe_id)
            rows = [self.database.index_of(retrieval.candidates[k].keyframe_id) for k in positions]
        except KeyError:
            return None
        return replace(retrieval, candidates=[retrieval.candidates[k] for k in positions],
                       cloud=self._verified_cloud(query, both_sides=False, wider=True),
                       candidate_clouds=[self._verified_cloud(row, wider=True) for row in rows],
                       candidate_frames=[retrieval.candidate_frames[k] for k in positions], timings_ms={})

    def _verified_cloud(self, index: int, *, both_sides: bool = True, wider: bool = False) -> np.ndarray:
        """The cloud a keyframe is verified with: its own, or its submap with odometry (within half
        ``exclude_recent_s``: a query's and its candidate's submaps never share a keyframe) of
        ``submap_keyframes`` neighbours, or ``wider``: a wider retry's (:data:`WIDER_RETRY_FITNESS`)."""
        cfg = self.settings
        if cfg.submap_keyframes == 0:
            return self.database.cloud(index)
        if wider:
            return self.database.submap_cloud(index, WIDER_RETRY_NEIGHBOURS * cfg.submap_keyframes,
                                              cfg.verification_voxel, submap_gap_s(cfg), both_sides=both_sides,
                                              reach_m=WIDER_NEIGHBOUR_DISTANCE_M)
        return self.database.submap_cloud(index, cfg.submap_keyframes, cfg.verification_voxel,
                                          submap_gap_s(cfg), both_sides=both_sides)


def submap_gap_s(settings: DetectorSettings) -> float:
    """How far in time (exclusive) a submap reaches on each side of its keyframe: half the recent
    past that is never a candidate, so no keyframe is in both a query's and its candidate's."""
    return 0.5 * settings.exclude_recent_s


def verified_by(points: np.ndarray, described: np.ndarray) -> np.ndarray:
    """The cloud a keyframe is verified with: a forward-looking keyframe's forward trail, which
    a pass from the other way shares (its own 70° does not: features/forward_trail.py), and
    otherwise the scan alone."""
    return described if described is not points and looks_forward(points) else points


def verification_cloud(points: np.ndarray, frame: np.ndarray, voxel: float) -> np.ndarray:
    """What a keyframe keeps for verification: one point per ``voxel``, in its levelled ``frame``
    (4x4 sensor -> grid), float32 (M, 3). Thinned first, then levelled: the same cloud for a
    fraction of the rotations."""
    thinned = downsample_for_storage(points, voxel).astype(np.float64)
    return (thinned @ frame[:3, :3].T + frame[:3, 3]).astype(np.float32)
