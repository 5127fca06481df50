"""The keyframe database: the online node's long-term memory of places.

Per keyframe: the *compact* standardised descriptor (only the scorer's active
rows — rows the learned sparsity switched off cost no memory), the stamp, the
session, a unique keyframe id, an optional pose, the keyframe's grid frame
(sensor -> levelled transform, identity for sensor-frame grids) and an optional
downsampled cloud for geometric verification, stored in that frame.

The descriptors live in one place, a :class:`~vbrl_ros.index.keyframe_index.KeyframeIndex`
(float32 or float16, next to its small search keys), which also answers
queries: candidate keys + exact Eq. 4 re-rank, or brute force with
``exact=True``. On a polar grid (``scorer.sectors`` > 1) distances are minimised
over circular sector shifts and each candidate carries the yaw of its best
shift (:attr:`Candidate.yaw`). The metadata are growable column arrays with
amortised doubling, so :meth:`KeyframeDatabase.add` is O(1) amortised besides
the index's O(d) keys; clouds live in one concatenated ``(P, 3)`` float32
array plus ``offsets`` (keyframe ``i`` owns ``points[offsets[i]:offsets[i + 1]]``).

Distances are Eq. 4 (:class:`~vbrl_ros.model.scoring.WeightedL1Scorer`):
**lower = more similar**. On disk: :mod:`vbrl_ros.detection.database_file`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from vbrl_ros.detection.database_file import MAX_KEYFRAME_ID, SavedDatabase, read_database, write_database
from vbrl_ros.detection.nearest_keyframe import PathNeighbours, rows_along_path
from vbrl_ros.detection.odometry_gate import DrivenPath, path_lengths
from vbrl_ros.detection.submaps import MAX_NEIGHBOUR_DISTANCE_M, KeyframeView, merged_cloud, neighbour_steps
from vbrl_ros.index.all_round import AllRoundIndex, search_all_round
from vbrl_ros.index.keyframe_index import KeyframeIndex
from vbrl_ros.index.keyframe_places import BYTES_PER_KEYFRAME as PLACE_BYTES_PER_KEYFRAME
from vbrl_ros.index.keyframe_places import KeyframePlaces
from vbrl_ros.index.keyframe_store import grown
from vbrl_ros.index.parameters import IndexParameters
from vbrl_ros.index.sequence_matching import PLACE_SLACK_M, SequenceHistory
from vbrl_ros.model.scoring import WeightedL1Scorer

_INITIAL_CAPACITY = 64
# Fixed per-keyframe metadata: stamp f64 + session index i32 + id i64
# + pose and frame 4x4 f64 + cloud offset i64 + metres driven f64 (odometry gate).
METADATA_BYTES_PER_KEYFRAME = 8 + 4 + 8 + 2 * 16 * 8 + 8 + 8


@dataclass(frozen=True)
class Candidate:
    """One retrieval result. ``distance`` is Eq. 4: lower = more similar.

    ``yaw`` (radians, (-pi, pi]): the query scan is this keyframe's scan rotated
    by +yaw about z, i.e. ``T_query_match`` has this yaw (the best sector shift;
    0.0 on the Cartesian grid) — a seed for geometric verification.
    """

    index: int  # row in the database (changes on clear(); keyframe_id does not repeat)
    keyframe_id: int
    distance: float
    stamp: float
    session: str
    yaw: float = 0.0
    offset: tuple[float, float] = (0.0, 0.0)  # the keyframe's position in the query's grid frame
    # odometry places it too far from the query to be one place (detection.odometry_gate)
    too_far_by_odometry: bool = False
    # T_query_match's yaw between the levelled frames as odometry gives it (odometry_heading); NaN: unknown
    odometry_yaw: float = math.nan


class KeyframeDatabase:
    """Keyframes scored with one model's :class:`WeightedL1Scorer` (lower distance = closer).

    ``parameters`` (storage, search; see
    :class:`~vbrl_ros.index.parameters.IndexParameters`) configure the index;
    its sectors are always the scorer's.
    """

    def __init__(self, scorer: WeightedL1Scorer, model_id: str,
                 parameters: IndexParameters | None = None) -> None:
        self.scorer = scorer
        self.model_id = str(model_id)
        self.index = KeyframeIndex(scorer.active_weights,
                                   replace(parameters or IndexParameters(), sectors=scorer.sectors))
        self.all_round = AllRoundIndex.like(self.index)
        self._next_id = 0
        self._reset_storage()

    def _reset_storage(self) -> None:
        self._size = 0
        self._n_points = 0
        self._sessions: list[str] = []
        self._session_lookup: dict[str, int] = {}
        c = _INITIAL_CAPACITY
        self._stamps = np.empty(c, dtype=np.float64)
        self._session_index = np.empty(c, dtype=np.int32)
        self._keyframe_ids = np.empty(c, dtype=np.int64)
        self._poses = np.empty((c, 4, 4), dtype=np.float64)
        self._frames = np.empty((c, 4, 4), dtype=np.float64)
        self._cloud_offsets = np.zeros(c + 1, dtype=np.int64)  # offsets[0] = 0 always
        self._cloud_points = np.empty((0, 3), dtype=np.float32)
        self._paths = np.empty(c, dtype=np.float64)  # metres driven in the session (odometry_gate)
        self._driven = DrivenPath()
        self._places: dict[int, KeyframePlaces] = {}  # by session: each its own odometry frame

    # -- size and accessors ---------------------------------------------------

    def __len__(self) -> int:
        return self._size

    @property
    def n_active(self) -> int:
        """Length of a compact descriptor (the scorer's active rows)."""
        return self.index.dimension

    @property
    def capacity(self) -> int:
        """Keyframes storable before the next (doubling) reallocation of the metadata."""
        return len(self._stamps)

    @property
    def next_keyframe_id(self) -> int:
        return self._next_id

    @property
    def sessions(self) -> list[str]:
        return list(self._sessions)

    @property
    def keyframe_ids(self) -> np.ndarray:
        return self._keyframe_ids[: self._size].copy()

    @property
    def stamps(self) -> np.ndarray:
        return self._stamps[: self._size].copy()

    @property
    def poses(self) -> np.ndarray:
        """(n, 4, 4) T_world_lidar of every keyframe; NaN where unknown."""
        return self._poses[: self._size].copy()

    def next_session(self) -> int:
        """One more than the largest session named by a number (0 without any): a new run's session.

        Other names (and numbers beyond int64, which no session_id parameter gives) do not count.
        """
        numeric = [int(name) for name in self._sessions if name.isdecimal() and len(name) <= 18]
        return max(numeric, default=-1) + 1

    def frame(self, index: int) -> np.ndarray:
        """The keyframe's 4x4 sensor -> grid-frame transform (its cloud is in the grid frame)."""
        return self._frames[self._check_index(index)].copy()

    def session_of(self, index: int) -> str:
        return self._sessions[self._session_index[self._check_index(index)]]

    def descriptor(self, index: int) -> np.ndarray:
        """The stored compact descriptor as float32 (float16-rounded with float16 storage)."""
        return self.index.descriptor(self._check_index(index))

    def pose(self, index: int) -> np.ndarray:
        """T_world_lidar (4x4); all-NaN when the pose was not given."""
        return self._poses[self._check_index(index)].copy()

    def cloud(self, index: int) -> np.ndarray:
        """The stored (M, 3) float32 cloud (M = 0 when none was given)."""
        i = self._check_index(index)
        return self._cloud_points[self._cloud_offsets[i] : self._cloud_offsets[i + 1]].copy()

    def submap_cloud(self, index: int, neighbours: int, voxel: float, max_gap_s: float, *,
                     both_sides: bool = True, reach_m: float = MAX_NEIGHBOUR_DISTANCE_M) -> np.ndarray:
        """The keyframe's cloud with up to ``neighbours`` adjacent keyframes' merged in by their poses
        (:func:`~vbrl_ros.detection.submaps.merged_cloud`, within ``reach_m``), in its grid frame;
        ``both_sides`` False: only earlier ones."""
        i = self._check_index(index)
        rows = [i + step for step in neighbour_steps(neighbours, both_sides=both_sides) if 0 <= i + step < self._size]
        return merged_cloud(self._view(i), [self._view(r) for r in rows], voxel, max_gap_s, reach_m)

    def _view(self, i: int) -> KeyframeView:
        return KeyframeView(self.cloud(i), self._frames[i], self._poses[i], float(self._stamps[i]),
                            self._sessions[self._session_index[i]])

    def odometry_apart(self, a: int, b: int) -> tuple[float, float]:
        """(metres between two keyframes by their poses, metres driven between them); NaN for
        keyframes of different sessions or without poses."""
        a, b = self._check_index(a), self._check_index(b)
        if self._session_index[a] != self._session_index[b]:
            return math.nan, math.nan
        apart = float(np.linalg.norm(self._poses[a, :3, 3] - self._poses[b, :3, 3]))
        return apart, float(abs(self._paths[a] - self._paths[b]))

    def along_path(self, index: int, reach_m: float) -> PathNeighbours:
        """The keyframes of this one's session next to it within ``reach_m`` metres driven, itself
        included (:func:`~vbrl_ros.detection.nearest_keyframe.rows_along_path`)."""
        i, n = self._check_index(index), self._size
        rows = rows_along_path(i, self._session_index[:n], self._paths[:n], reach_m)
        return PathNeighbours(rows, self._keyframe_ids[rows], self._stamps[rows], self._poses[rows])

    def index_of(self, keyframe_id: int) -> int:
        """Row of a keyframe id; ids are increasing, so a binary search."""
        ids = self._keyframe_ids[: self._size]
        i = int(np.searchsorted(ids, keyframe_id))
        if i == self._size or ids[i] != keyframe_id:
            raise KeyError(f"no keyframe with id {keyframe_id}")
        return i

    def _check_index(self, index: int) -> int:
        if not -self._size <= index < self._size:
            raise IndexError(f"keyframe index {index} out of range for {self._size} keyframes")
        return index % self._size

    # -- memory -------------------------------------------------------------

    def bytes_per_keyframe(self) -> int:
        """Fixed bytes per keyframe: descriptor + search keys + metadata + place, no cloud and no
        all-round descriptor (:meth:`all_round_bytes_per_keyframe`)."""
        return sum(self.bytes_breakdown().values())

    def bytes_breakdown(self) -> dict[str, int]:
        """Per-keyframe bytes: descriptor, key, yaw_key (index), metadata, place (where it was
        taken, for sequence matching by place) and whether it saw all round by itself."""
        return {**self.index.bytes_breakdown(), "metadata": METADATA_BYTES_PER_KEYFRAME,
                "place": PLACE_BYTES_PER_KEYFRAME, "sees_all_round": self.all_round.sees_all_round.itemsize}

    def all_round_bytes_per_keyframe(self) -> int:
        """What a keyframe also described all round adds to :meth:`bytes_per_keyframe` (a partly
        blind sensor's keyframes mostly are: :mod:`vbrl_ros.index.all_round`)."""
        return self.all_round.bytes_per_descriptor()

    def cloud_bytes_per_keyframe(self) -> float:
        """Mean bytes of stored cloud per keyframe (12 per point; 0 for an empty database)."""
        return 12.0 * self._n_points / self._size if self._size else 0.0

    # -- writing --------------------------------------------------------------

    def add(
        self,
        descriptor_compact: np.ndarray,
        stamp: float,
        session: str,
        *,
        pose: np.ndarray | None = None,
        cloud: np.ndarray | None = None,
        frame: np.ndarray | None = None,
        all_round: np.ndarray | None = None,
        sees_all_round: bool = False,
    ) -> int:
        """Append one keyframe; returns its new keyframe id (O(1) amortised + O(d) keys).

        ``frame``: 4x4 sensor -> grid frame of the keyframe (identity by default), the
        frame ``cloud`` is given in. ``all_round``: its compact all-round descriptor, when it
        has one; ``sees_all_round``: its descriptor is all round by itself (:mod:`vbrl_ros.index.all_round`)."""
        stamp = float(stamp)
        if not math.isfinite(stamp):
            raise ValueError(f"stamp must be finite, got {stamp}")
        if pose is None:
            pose_array = np.full((4, 4), np.nan)
        else:
            pose_array = np.asarray(pose, dtype=np.float64)
            if pose_array.shape != (4, 4):
                raise ValueError(f"pose must be 4x4, got shape {pose_array.shape}")
        frame_array = np.eye(4) if frame is None else np.asarray(frame, dtype=np.float64)
        if frame_array.shape != (4, 4) or not np.all(np.isfinite(frame_array)):
            raise ValueError(f"frame must be a finite 4x4 matrix, got shape {frame_array.shape}")
        points = np.empty((0, 3), np.float32) if cloud is None else np.asarray(cloud, np.float32)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"cloud must have shape (M, 3), got {points.shape}")
        if self._next_id >= MAX_KEYFRAME_ID:
            raise ValueError(f"no keyframe id left: ids end at 2**53, {self._next_id} is next")
        if all_round is not None:
            all_round = self.index.check(all_round)
        self.index.add(descriptor_compact)  # validates the descriptor before storing anything
        self.all_round.note(sees_all_round)
        if all_round is not None:
            self.all_round.add(self._size, all_round)

        n = self._size
        self._stamps = grown(self._stamps, n + 1)
        self._session_index = grown(self._session_index, n + 1)
        self._keyframe_ids = grown(self._keyframe_ids, n + 1)
        self._poses = grown(self._poses, n + 1)
        self._frames = grown(self._frames, n + 1)
        self._cloud_offsets = grown(self._cloud_offsets, n + 2)
        self._cloud_points = grown(self._cloud_points, self._n_points + len(points))
        self._paths = grown(self._paths, n + 1)

        self._stamps[n] = stamp
        self._session_index[n] = self._session_id(str(session))
        self._keyframe_ids[n] = self._next_id
        self._poses[n] = pose_array
        self._frames[n] = frame_array
        self._cloud_points[self._n_points : self._n_points + len(points)] = points
        self._n_points += len(points)
        self._cloud_offsets[n + 1] = self._n_points
        self._paths[n] = self._driven.step(int(self._session_index[n]), pose_array[:3, 3])
        self._place(n)
        self._size = n + 1
        self._next_id += 1
        return self._next_id - 1

    def _place(self, row: int) -> None:
        session = int(self._session_index[row])
        places = self._places.get(session)
        if places is None:
            places = self._places[session] = KeyframePlaces(PLACE_SLACK_M)
        places.add(int(self._keyframe_ids[row]), self._poses[row, :3, 3])

    def clear(self) -> None:
        """Forget every keyframe and free the memory. Ids keep increasing (never reused)."""
        self.index = self.index.empty_like()
        self.all_round = AllRoundIndex.like(self.index)
        self._reset_storage()

    def _session_id(self, session: str) -> int:
        index = self._session_lookup.get(session)
        if index is None:
            index = self._session_lookup[session] = len(self._sessions)
            self._sessions.append(session)
        return index

    # -- retrieval ------------------------------------------------------------

    def query(
        self,
        descriptor_compact: np.ndarray,
        *,
        top_k: int = 5,
        session: str | None = None,
        stamp: float | None = None,
        exclude_recent_s: float = 0.0,
        exact: bool = False,
    ) -> list[Candidate]:
        """The ``top_k`` closest keyframes, sorted by distance ascending (lower = more similar).

        Keyframes of the *same* ``session`` whose stamp is > ``stamp - exclude_recent_s``
        are excluded (the robot's own recent past is not a loop closure); keyframes
        of other sessions are never excluded by recency. Without ``session`` or
        ``stamp`` nothing is excluded. Ties are broken by insertion order.
        ``exact=True`` scans every keyframe (and every sector shift) instead of
        using the index's keys.
        """
        return self.query_views(np.asarray(descriptor_compact)[None], np.zeros((1, 2)), top_k=top_k,
                                session=session, stamp=stamp, exclude_recent_s=exclude_recent_s,
                                exact=exact)

    def query_views(
        self,
        views_compact: np.ndarray,
        offsets: np.ndarray,
        *,
        top_k: int = 5,
        session: str | None = None,
        stamp: float | None = None,
        exclude_recent_s: float = 0.0,
        exact: bool = False,
        sequence: SequenceHistory | None = None,
        position: np.ndarray | None = None,
        all_round_views: np.ndarray | None = None,
        sees_all_round: bool = False,
    ) -> list[Candidate]:
        """:meth:`query` for a query described from several viewpoints ``offsets`` (V, 2), the
        first the sensor itself (translation search, :mod:`vbrl_ros.index.translation_search`).

        ``sequence``: the stream's earlier keyframes; candidates are then ranked (and their
        ``distance`` is) the sequence distance of :mod:`vbrl_ros.index.sequence_matching`, by place
        for keyframes of ``session`` when ``position`` (3,), the query's by odometry, is given.
        ``all_round_views``: the query described all round from the same viewpoints, when it has
        been, or ``sees_all_round`` when ``views`` are all round by themselves; it is also compared
        with the keyframes described so (:mod:`vbrl_ros.index.all_round`)."""
        views = np.stack([self.index.check(v) for v in np.asarray(views_compact)])
        if all_round_views is not None:
            all_round_views = np.stack([self.index.check(v) for v in np.asarray(all_round_views)])
        if top_k <= 0 or self._size == 0:
            if sequence is not None:  # this keyframe still takes its place in the sequence
                sequence.rescore(np.zeros(0, np.int64), np.zeros(0))
            return []
        allowed = None
        session_id = None if session is None else self._session_lookup.get(str(session))
        if session_id is not None and stamp is not None:
            recent = (self._session_index[: self._size] == session_id) & (
                self._stamps[: self._size] > float(stamp) - float(exclude_recent_s)
            )
            allowed = ~recent
        places = self._places.get(session_id) if session_id is not None else None
        rescore = None if sequence is None else (
            lambda rows, distances: sequence.rescore(self._keyframe_ids[rows], distances, here=position,
                                                     places=places))
        found = search_all_round(self.index, views, offsets, top_k, allowed, all_round=self.all_round,
                                 all_round_views=all_round_views, sees_all_round=sees_all_round, exact=exact,
                                 rescore=rescore)
        return [
            Candidate(
                index=int(i),
                keyframe_id=int(self._keyframe_ids[i]),
                distance=float(distance),
                stamp=float(self._stamps[i]),
                session=self._sessions[self._session_index[i]],
                yaw=float(yaw),
                offset=(float(offset[0]), float(offset[1])),
            )
            for i, distance, yaw, offset in zip(found.indices, found.distances, found.yaws, found.offsets)
        ]

    # -- persistence ----------------------------------------------------------

    def save(self, path: str | Path) -> Path:
        """Write one versioned ``.npz`` atomically (temp file + rename)."""
        n, p = self._size, self._n_points
        columns = dict(
            stamps=self._stamps[:n],
            session_index=self._session_index[:n],
            keyframe_ids=self._keyframe_ids[:n],
            poses=self._poses[:n],
            frames=self._frames[:n],
            cloud_offsets=self._cloud_offsets[: n + 1],
            cloud_points=self._cloud_points[:p],
        )
        return write_database(path, SavedDatabase(self.model_id, self._sessions, self._next_id,
                                                  columns, self.index, self.all_round), self.scorer)

    @classmethod
    def load(cls, path: str | Path, scorer: WeightedL1Scorer, model_id: str) -> KeyframeDatabase:
        """Load and validate; any problem raises
        :class:`~vbrl_ros.detection.database_file.DatabaseFileError` (one line).

        The index parameters and storage are the saved ones.
        """
        saved = read_database(path, scorer, model_id)
        db, c = cls(scorer, model_id), saved.columns
        db.index, db.all_round = saved.index, saved.all_round
        db._size, db._n_points = len(c["stamps"]), len(c["cloud_points"])
        db._next_id = saved.next_keyframe_id
        db._sessions = list(saved.sessions)
        db._session_lookup = {name: i for i, name in enumerate(db._sessions)}
        db._stamps = c["stamps"].astype(np.float64, copy=False)
        db._session_index = c["session_index"].astype(np.int32, copy=False)
        db._keyframe_ids = c["keyframe_ids"].astype(np.int64, copy=False)
        db._poses = c["poses"].astype(np.float64, copy=False)
        db._frames = c["frames"].astype(np.float64, copy=False)
        db._cloud_offsets = c["cloud_offsets"].astype(np.int64, copy=False)
        db._cloud_points = c["cloud_points"].astype(np.float32, copy=False)
        db._paths = path_lengths(db._poses[:, :3, 3], db._session_index, db._driven)  # and it goes on from there
        for session in np.unique(db._session_index):
            rows = np.flatnonzero(db._session_index == session)
            db._places[int(session)] = KeyframePlaces.of(PLACE_SLACK_M, db._keyframe_ids[rows], db._poses[rows, :3, 3])
        return db
