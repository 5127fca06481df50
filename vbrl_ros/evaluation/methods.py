"""Method adapters for offline evaluation: VBRL models and the Scan Context baseline.

Every source is described ONCE (:func:`describe_source`): the raw VBRL
descriptor and the Scan Context descriptor of each keyframe, computed together
in worker processes; with translation search also the VBRL descriptors from the
other viewpoints, as the node describes its queries. All VBRL variants (full model,
ablations) share the raw descriptors; only their standardisation and row weights differ.

A method turns (query descriptors, database descriptors) into a
``distances_fn(query_index, candidate_indices) -> distances`` for
:mod:`vbrl_ros.evaluation.retrieval` (lower = more similar). Matching uses the
descriptors, and poses only as the node uses odometry: a keyframe's trail, and in P1
the earlier keyframes of a sequence matched by place; otherwise poses are carried
alongside for the ground truth.
"""

from __future__ import annotations

from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from vbrl_ros.config import VBRLConfig
from vbrl_ros.datasets.base import ScanSource
from vbrl_ros.datasets.blocked_wedge import outside_wedge
from vbrl_ros.datasets.keyframe_selection import keyframe_poses, select_keyframes, source_points
from vbrl_ros.datasets.mount_tilt import mount_rotation, tilted_points, tilted_poses
from vbrl_ros.datasets.odometry_drift import drifted_poses
from vbrl_ros.datasets.registry import open_source
from vbrl_ros.detection.detector import submap_gap_s, verification_cloud, verified_by
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.evaluation.baselines.scan_context import (
    ScanContextConfig,
    ScanContextDatabase,
    scan_context,
)
from vbrl_ros.evaluation.metrics import DEFAULT_EXCLUDE
from vbrl_ros.evaluation.retrieval import DistancesFn
from vbrl_ros.evaluation.verified import TOP_K_RETRIEVED, KeyframeClouds
from vbrl_ros.features.blind_wedges import all_round_by_itself
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.features.parallel import bounded_map, default_workers, worker_pool
from vbrl_ros.features.session_trails import trail_clouds
from vbrl_ros.index.all_round import AllRoundIndex, search_all_round
from vbrl_ros.index.keyframe_index import KeyframeIndex
from vbrl_ros.index.keyframe_places import KeyframePlaces
from vbrl_ros.index.parameters import IndexParameters
from vbrl_ros.index.sequence_matching import DEFAULT_LENGTH, PLACE_SLACK_M, SequenceHistory
from vbrl_ros.index.translation_search import Rescore, view_offsets
from vbrl_ros.model.model_file import VBRLModel
from vbrl_ros.model.scoring import WeightedL1Scorer

__all__ = ["ScanContextMethod", "SourceDescriptors", "VBRLMethod", "describe_source", "scorer_top_k"]


@dataclass
class SourceDescriptors:
    """Descriptors of one source's keyframes, in source order."""

    name: str
    vbrl: np.ndarray  # (n, d) float32 raw (unstandardised) VBRL descriptors
    scan_context: np.ndarray  # (n, rings, sectors) float32
    keyframe_index: np.ndarray  # (n,) scan index of each keyframe in its source
    positions: np.ndarray | None  # (n, 3) ground truth only; None without poses
    views: np.ndarray | None = None  # (n, V, d) raw descriptors from view_offsets; [:, 0] = vbrl
    view_offsets: np.ndarray | None = None  # (V, 2) metres, the first (0, 0)
    clouds: KeyframeClouds | None = None  # what the node keeps for verification, when asked for
    poses: np.ndarray | None = None  # (n, 4, 4) T_world_lidar as the node's odometry reads it; None without
    truth: np.ndarray | None = None  # (n, 4, 4) the recorded poses, for the ground truth (None: ``poses``)
    stamps: np.ndarray | None = None  # (n,) seconds
    # (n, V, d) raw descriptors all round of the keyframes with one (has_all_round), zeros elsewhere
    all_round: np.ndarray | None = None
    has_all_round: np.ndarray | None = None  # (n,) bool
    sees_all_round: np.ndarray | None = None  # (n,) bool: described all round by themselves (index.all_round)

    def __len__(self) -> int:
        return len(self.keyframe_index)

    def all_round_summary(self) -> str | None:
        """How many keyframes are compared all round (:mod:`vbrl_ros.index.all_round`), by filling
        their blind wedge and by themselves; None when none is."""
        filled = 0 if self.has_all_round is None else int(self.has_all_round.sum())
        itself = 0 if self.sees_all_round is None else int(self.sees_all_round.sum())
        if not filled and not itself:
            return None
        return (f"{self.name}: {filled} of {len(self)} keyframes also described all round where their trail "
                f"saw into a blind wedge, {itself} all round by themselves")

    @property
    def recorded_poses(self) -> np.ndarray | None:
        """The poses as recorded, the ground truth, whatever odometry reads."""
        return self.poses if self.truth is None else self.truth


_worker: tuple[Featurizer, ScanContextConfig, np.ndarray, float | None, bool] | None = None


def _init_worker(config_dict: dict, sc_dict: dict, offsets: np.ndarray, voxel: float | None,
                 sc_trail: bool) -> None:
    global _worker
    _worker = (Featurizer(VBRLConfig.from_dict(config_dict)), ScanContextConfig(**sc_dict), offsets, voxel,
               sc_trail)


def _describe(scan: tuple[np.ndarray, np.ndarray | None, np.ndarray | None, bool | None]) -> tuple[
        np.ndarray, np.ndarray, np.ndarray | None, np.ndarray, np.ndarray | None, bool]:
    """(views (V, d), Scan Context, verification cloud or None, levelled frame 4x4, views all round
    or None, whether the views are all round by themselves) of (points, the cloud VBRL describes
    them by or None for the points themselves, the cloud it describes them by all round or None,
    whether the first sees all round or None when not known: :meth:`~vbrl_ros.features.trail.Trail.clouds`):
    the VBRL views and the cloud as the node computes them; Scan Context reads the scan alone, as
    published, unless told to read the same cloud as VBRL."""
    assert _worker is not None
    featurizer, sc_config, offsets, voxel, sc_trail = _worker
    points, described, all_round, sees = scan
    described = points if described is None else described
    frame = featurizer.frame(described, scan=points)
    views = featurizer.describe_views(described, offsets, frame)
    all_round_views = None if all_round is None else featurizer.describe_views(all_round, offsets, frame)
    cloud = None if voxel is None else verification_cloud(verified_by(points, described), frame.matrix, voxel)
    whole = all_round_by_itself(described, all_round, featurizer.config.features.fill_blind_wedges, sees)
    return (views, scan_context(described if sc_trail else points, sc_config), cloud, frame.matrix,
            all_round_views, whole)


def trail_horizon(source: ScanSource, indices: Sequence[int], exclude: int | None) -> dict[str, Any]:
    """``with_trail``'s stamps and max_age: half ``exclude`` in scans, or (None) half the node's
    ``exclude_recent_s`` in the source's seconds, as a submap reaches (detection/submaps.py)."""
    if exclude is not None:
        return scan_trail_horizon(indices, exclude)
    return {"stamps": np.asarray(source.stamps, np.float64)[np.asarray(indices, np.int64)],
            "max_age": submap_gap_s(DetectorSettings())}


def scan_trail_horizon(indices: Sequence[int], exclude: int = DEFAULT_EXCLUDE) -> dict[str, Any]:
    """``with_trail``'s stamps and max_age counted in scans: less than half ``exclude`` back, so a
    trail never holds a scan a candidate, or its submap, holds."""
    return {"stamps": np.asarray(indices), "max_age": 0.5 * exclude}


def describe_source(
    path: Path,
    config: VBRLConfig,
    sc_config: ScanContextConfig,
    *,
    topic: str | None = None,
    poses: str = "auto",
    keyframe_distance: float | None = None,
    every: int | None = None,
    workers: int | None = None,
    progress: bool = True,
    translation_search: float = 0.0,
    verification_voxel: float | None = None,
    blocked_azimuth: tuple[float, float] | None = None,
    mount_tilt: tuple[float, float] | None = None,
    sc_trail: bool = False,
    odometry_drift_deg: float = 0.0,
    exclude: int | None = DEFAULT_EXCLUDE,
) -> SourceDescriptors:
    """Read the keyframes of ``path`` once and compute both descriptors of each (and the VBRL
    views of :func:`~vbrl_ros.index.translation_search.view_offsets` for ``translation_search`` > 0;
    with ``verification_voxel`` also the clouds the node would keep for verification).
    ``blocked_azimuth``: a wedge of every scan (sensor frame, degrees) hidden first, as a mast
    would hide it. ``mount_tilt``: (roll, pitch) degrees every scan and pose is turned by first, as
    if the sensor had been held so (:mod:`vbrl_ros.datasets.mount_tilt`). ``sc_trail``: Scan Context
    reads each keyframe with its trail too, as VBRL does. ``odometry_drift_deg``: what reads
    odometry reads the poses drifted so (:mod:`vbrl_ros.datasets.odometry_drift`). A keyframe's
    trail reaches back less than half ``exclude`` scans (P1: it never holds a keyframe a
    candidate, or a candidate's submap, holds); ``exclude`` None: less than half the node's
    default ``exclude_recent_s``, by the source's stamps, as the node's does (P2)."""
    workers = default_workers() if workers is None else workers
    offsets = view_offsets(translation_search)
    init = (config.to_dict(), asdict(sc_config), offsets, verification_voxel, sc_trail)
    with open_source(path, topic=topic, poses=poses, progress=progress) as source:
        indices = select_keyframes(source, distance=keyframe_distance, every=every)
        scans = source_points(source, indices)
        poses = keyframe_poses(source, indices)
        if mount_tilt is not None:
            mount = mount_rotation(*mount_tilt)
            scans = (tilted_points(points, mount) for points in scans)
            poses = None if poses is None else tilted_poses(poses, mount)
        truth = poses
        if poses is not None and odometry_drift_deg > 0:
            poses = drifted_poses(poses, odometry_drift_deg)
        if blocked_azimuth is not None:  # the mast turns with the sensor: hidden in its tilted frame
            scans = (points[outside_wedge(points, blocked_azimuth)] for points in scans)
        # None where the scan is described alone: the worker is not sent the same points twice
        pairs = ((points, None if cloud is points else cloud, all_round, sees) for points, cloud, all_round, sees in
                 trail_clouds(scans, poses, config.features.trail_m, config.features.forward_trail_m,
                              **trail_horizon(source, indices, exclude),
                              fill_blind_wedges=config.features.fill_blind_wedges,
                              ahead_m=config.features.trail_ahead_m))
        bar = tqdm(total=len(indices), desc=f"describing {source.name}", unit="scan",
                   disable=not progress, leave=False)
        vbrl, sc, clouds, frames, all_round, whole = [], [], [], [], [], []
        with ExitStack() as stack:
            stack.callback(bar.close)
            if workers <= 1:
                _init_worker(*init)
                rows = map(_describe, pairs)
            else:
                pool = stack.enter_context(worker_pool(workers, _init_worker, init))
                rows = bounded_map(pool, _describe, pairs, 4 * workers)
            for views_of_scan, context, cloud, frame, round_views, sees in rows:
                vbrl.append(views_of_scan), sc.append(context), clouds.append(cloud), frames.append(frame)
                all_round.append(round_views), whole.append(sees)
                bar.update()
        positions = None if source.poses is None else source.poses[indices, :3, 3].copy()
        d = Featurizer(config).dimension
        views = np.stack(vbrl) if vbrl else np.zeros((0, len(offsets), d), np.float32)
        has_all_round = np.array([v is not None for v in all_round], dtype=bool)
        return SourceDescriptors(
            name=source.name,
            vbrl=views[:, 0],
            scan_context=np.stack(sc) if sc else np.zeros((0, *sc_config.shape), np.float32),
            keyframe_index=np.asarray(indices, dtype=np.int64),
            positions=positions,
            views=views if len(offsets) > 1 else None,
            view_offsets=offsets,
            clouds=None if verification_voxel is None else KeyframeClouds(clouds, frames),
            poses=poses,  # a selection (and its turn) of the source's poses: already a copy
            truth=None if truth is poses else truth,
            stamps=np.asarray(source.stamps, np.float64)[indices].copy(),
            all_round=np.stack([np.zeros_like(v) if a is None else a for v, a in zip(vbrl, all_round)])
            if has_all_round.any() else None,
            has_all_round=has_all_round if has_all_round.any() else None,
            sees_all_round=np.array(whole, dtype=bool) if any(whole) else None,
        )


def scorer_top_k(
    queries: np.ndarray,
    templates: np.ndarray,
    scorer: WeightedL1Scorer,
    k: int = 1,
    limits: Sequence[int] | np.ndarray | None = None,
    *,
    exact: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Top-k (indices, distances, yaws) of the scorer's Eq. 4 for every query; (n_q, k) each.

    Query q sees ``templates[:limits[q]]`` (None = all). Inputs are standardised
    and compacted by ``scorer``; with a polar scorer distances are minimised over
    sector shifts and yaws say how the query is rotated from its match.
    ``exact=False`` retrieves through :class:`KeyframeIndex` as the node does
    (exact distances for what it returns). Ties go to the lower index; padding
    is index -1, distance inf.
    """
    Q = np.asarray(queries, dtype=np.float32)
    T = np.asarray(templates, dtype=np.float32)
    lim = np.full(len(Q), len(T)) if limits is None else np.asarray(limits, dtype=np.int64)
    out_i = np.full((len(Q), k), -1, dtype=np.int64)
    out_d = np.full((len(Q), k), np.inf)
    out_y = np.zeros((len(Q), k))
    if len(T) == 0 or len(Q) == 0:
        return out_i, out_d, out_y
    index = KeyframeIndex(scorer.active_weights, IndexParameters(sectors=scorer.sectors))
    # queries in increasing database prefix: the index only ever grows
    for q in np.argsort(lim, kind="stable"):
        if lim[q] <= 0:
            continue
        if len(index) < lim[q]:
            index.add_batch(T[len(index): lim[q]])
        found = index.search_with_yaw(Q[q], k, exact=exact)
        n = len(found.indices)
        out_i[q, :n], out_d[q, :n], out_y[q, :n] = found.indices, found.distances, found.yaws
    return out_i, out_d, out_y


class VBRLMethod:
    """Eq. 4 distances with one model's standardisation and importances.

    Retrieval goes through :class:`KeyframeIndex` like the online node's
    (``exact=False``), or brute force over every template (and every sector
    shift of a polar grid) with ``exact=True``. ``prune`` is the node's
    ``weight_prune``: rows weighing less than that share of the largest row
    weight are neither stored nor scored. ``top_k``: keyframes retrieved per
    query, at least the driver's (:func:`~vbrl_ros.evaluation.verified.retrieval_width`).
    """

    def __init__(self, name: str, model: VBRLModel, *, exact: bool = False,
                 prune: float = 0.0, sequence_length: int = DEFAULT_LENGTH, top_k: int = TOP_K_RETRIEVED) -> None:
        self.name, self.model, self.exact, self.top_k = name, model, exact, top_k
        self.scorer = model.scorer(prune=prune)
        self.sequence_length = sequence_length

    def compact(self, raw: np.ndarray) -> np.ndarray:
        """Standardised active rows of raw descriptors (n, d): what the index stores."""
        rows = self.scorer.active_rows
        # Standardise only the rows that score: the others have zero weight.
        out = (raw[:, rows].astype(np.float64) - self.model.feature_mean[rows]) / self.model.feature_scale[rows]
        return out.astype(np.float32)

    def new_index(self) -> KeyframeIndex:
        """An empty index for this method's scorer, as the node builds it."""
        return KeyframeIndex(self.scorer.active_weights, IndexParameters(sectors=self.scorer.sectors))

    def distances_fn(self, queries: SourceDescriptors, database: SourceDescriptors) -> DistancesFn:
        Q = self.compact(queries.vbrl)
        T = Q if database is queries else self.compact(database.vbrl)
        index = self.new_index()
        all_round = AllRoundIndex.like(index)
        raw_views = queries.views
        offsets = np.zeros((1, 2)) if raw_views is None else queries.view_offsets
        # in P1 the poses stand in for the node's odometry: earlier keyframes are matched by place;
        # across sources (P2) the frames differ, as across the node's sessions
        positions = None if database is not queries or queries.poses is None else queries.poses[:, :3, 3]
        stream = QueryStream(self.sequence_length, places=None if positions is None else KeyframePlaces(PLACE_SLACK_M))

        def fn(i: int, candidates: np.ndarray) -> np.ndarray:
            stream.reach(i)
            # The drivers ask for database prefixes 0..limit-1 in increasing
            # limit (P1 grows it with i, P2 keeps it): insert lazily, like online.
            limit = int(candidates[-1]) + 1 if len(candidates) else 0
            if len(index) < limit:
                for row in range(len(index), limit):
                    if positions is not None:
                        stream.places.add(row, positions[row])
                    all_round.note(database.sees_all_round is not None and database.sees_all_round[row])
                    if database.has_all_round is not None and database.has_all_round[row]:
                        all_round.add(row, self.compact(database.all_round[row, :1])[0])
                index.add_batch(T[len(index): limit])
            rescore = None if self.sequence_length == 1 else stream.rescorer(
                None if positions is None else positions[i])
            allowed = None if len(index) == limit else np.arange(len(index)) < limit
            round_views = (self.compact(queries.all_round[i, :len(offsets)])
                           if queries.has_all_round is not None and queries.has_all_round[i] else None)
            # as the node: the query from every viewpoint
            views = Q[i][None] if raw_views is None else self.compact(raw_views[i])
            found = search_all_round(index, views, offsets, self.top_k, allowed,
                                     all_round=all_round, all_round_views=round_views, exact=self.exact,
                                     rescore=rescore, sees_all_round=queries.sees_all_round is not None
                                     and bool(queries.sees_all_round[i]))
            out = np.full(len(candidates), np.inf)  # not retrieved: never a match
            out[found.indices] = found.distances
            return out

        return fn


class QueryStream:
    """The sequence history of a driver's queries, which come in order; rows of one source
    are its keyframes in order, so they serve as the sequence's ids."""

    def __init__(self, length: int, places: KeyframePlaces | None = None) -> None:
        self.history = SequenceHistory(length)
        self.places = places  # where the database's rows were taken, for matching by place
        self._next = 0

    def rescorer(self, here: np.ndarray | None) -> Rescore:
        """The current query's rescoring of (rows, distances), taken at ``here`` (None: unknown)."""
        return lambda rows, distances: self.history.rescore(rows, distances, here=here, places=self.places)

    def reach(self, i: int) -> None:
        """Query ``i`` comes next: the queries skipped (no database yet) still take their place."""
        for _ in range(self._next, i):
            self.history.rescore(np.zeros(0, np.int64), np.zeros(0))
        self._next = i + 1


class ScanContextMethod:
    """Scan Context (Kim & Kim 2018): ring-key k-d tree prefilter, then the exact
    column-shift distance over all shifts on the ``num_candidates`` nearest ring keys.
    Candidates the prefilter drops get distance inf (never retrieved). ``sequence_length``
    > 1 ranks them with VBRL's sequence matching (its prefilter's candidates are the pool),
    for a like-for-like comparison; 1 is Scan Context as published."""

    name = "Scan Context"

    def __init__(self, config: ScanContextConfig, num_candidates: int = 10, sequence_length: int = 1) -> None:
        self.config, self.num_candidates, self.sequence_length = config, num_candidates, sequence_length

    def distances_fn(self, queries: SourceDescriptors, database: SourceDescriptors) -> DistancesFn:
        db = ScanContextDatabase(self.config)
        for descriptor in database.scan_context:
            db.add(descriptor)
        Q = queries.scan_context
        stream = QueryStream(self.sequence_length)

        def fn(i: int, candidates: np.ndarray) -> np.ndarray:
            out = np.full(len(candidates), np.inf)
            # Candidates are always a database prefix 0..limit-1 (P1 and P2 drivers).
            limit = int(candidates.max()) + 1 if len(candidates) else 0
            idx, dist, _ = db.query_top_k(Q[i], k=self.num_candidates,
                                          num_candidates=self.num_candidates, max_index=limit)
            if self.sequence_length > 1:
                stream.reach(i)
                dist = stream.history.rescore(idx, dist)
            out[idx] = dist
            return out

        return fn
