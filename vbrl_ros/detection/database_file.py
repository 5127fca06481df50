"""The keyframe database on disk: one versioned ``.npz``, and every check made on loading it.

``format="vbrl_ros.keyframes"``, ``format_version=3``: the per-keyframe
columns plus the index's arrays under ``index_*``, written atomically and
loaded with ``allow_pickle=False``. The file records the ``model_id`` and the
scorer's active rows, because descriptors compacted or standardised for one
model are meaningless under another. ``frames`` (n, 4, 4) is each keyframe's
sensor -> grid-frame transform (its cloud is stored in the grid frame); version 2
files, which have none, load with identity frames (their clouds are in the sensor
frame, which is what an identity frame says). Version 1 files are refused. The all-round
descriptors of partly blind keyframes (:mod:`vbrl_ros.index.all_round`) are stored under
``all_round_*`` with ``all_round_sees``, the keyframes described all round by themselves; a file
without them has none.
Members other than :data:`DATABASE_MEMBERS` are never read.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vbrl_ros.index.all_round import AllRoundIndex
from vbrl_ros.index.keyframe_index import KeyframeIndex
from vbrl_ros.index.state import STATE_MEMBERS
from vbrl_ros.io.atomic import atomic_write
from vbrl_ros.io.npz import INTEGER, TEXT, Member, one_line, read_npz
from vbrl_ros.model.scoring import WeightedL1Scorer

DATABASE_FORMAT = "vbrl_ros.keyframes"
DATABASE_FORMAT_VERSION = 3
READABLE_VERSIONS = (2, 3)
COLUMNS = (
    "stamps", "session_index", "keyframe_ids", "poses", "frames", "cloud_offsets", "cloud_points",
)  # fmt: skip
_INDEX_PREFIX = "index_"
_ALL_ROUND_PREFIX = "all_round_"
#: Every member a database file may hold; others are never read.
DATABASE_MEMBERS = {
    "format": TEXT, "format_version": INTEGER, "model_id": TEXT, "dimension": INTEGER,
    "active_rows": Member("iu", 1), "sectors": INTEGER, "sessions_json": TEXT, "next_keyframe_id": INTEGER,
    "stamps": Member("f", 1), "session_index": Member("i", 1), "keyframe_ids": Member("i", 1),
    "poses": Member("f", 3), "frames": Member("f", 3), "cloud_offsets": Member("i", 1),
    "cloud_points": Member("f", 2),
    **{f"{_INDEX_PREFIX}{name}": member for name, member in STATE_MEMBERS.items()},
    **{f"{_ALL_ROUND_PREFIX}{name}": member for name, member in STATE_MEMBERS.items()},
    f"{_ALL_ROUND_PREFIX}rows": Member("i", 1), f"{_ALL_ROUND_PREFIX}sees": Member("b", 1),
}
#: Keyframe ids go out as float64 in the closure messages: exact up to 2**53.
MAX_KEYFRAME_ID = 2**53


class DatabaseFileError(ValueError):
    """A keyframe database file that cannot be used; one-line message naming the problem."""


@dataclass(frozen=True)
class SavedDatabase:
    """What a database file holds: ``columns`` are the :data:`COLUMNS` arrays, n keyframes long
    (``cloud_offsets`` n + 1, ``cloud_points`` (P, 3))."""

    model_id: str
    sessions: list[str]
    next_keyframe_id: int
    columns: dict[str, np.ndarray]
    index: KeyframeIndex
    all_round: AllRoundIndex


def write_database(path: str | Path, saved: SavedDatabase, scorer: WeightedL1Scorer) -> Path:
    """Write one versioned ``.npz`` atomically (temp file + rename)."""
    payload = dict(
        format=np.array(DATABASE_FORMAT),
        format_version=np.array(DATABASE_FORMAT_VERSION),
        model_id=np.array(saved.model_id),
        dimension=np.array(scorer.dimension, dtype=np.int64),
        active_rows=np.asarray(scorer.active_rows, dtype=np.int64),
        sectors=np.array(scorer.sectors, dtype=np.int64),
        sessions_json=np.array(json.dumps(saved.sessions)),
        next_keyframe_id=np.array(saved.next_keyframe_id, dtype=np.int64),
        **{name: saved.columns[name] for name in COLUMNS},
        **saved.index.state(_INDEX_PREFIX),
        **saved.all_round.state(_ALL_ROUND_PREFIX),
    )
    return atomic_write(path, lambda handle: np.savez(handle, **payload))


def read_database(path: str | Path, scorer: WeightedL1Scorer, model_id: str) -> SavedDatabase:
    """Load and validate; any problem raises :class:`DatabaseFileError` (one line).

    The file must have been written for ``model_id`` and the scorer's active rows.
    """
    path = Path(path)
    contents = read_npz(path, DatabaseFileError, "keyframe database", DATABASE_FORMAT, DATABASE_MEMBERS)
    version = _scalar_int(contents.get("format_version"))
    if version not in READABLE_VERSIONS:
        raise DatabaseFileError(
            f"{path} has keyframe database format version {version}; this vbrl_ros reads "
            f"versions {', '.join(map(str, READABLE_VERSIONS))} (rebuild the database by replaying the data)"
        )
    required = ("model_id", "dimension", "active_rows", "sectors", "sessions_json",
                "next_keyframe_id")
    if version == 2:  # before frames: clouds are in the sensor frame
        contents = {**contents, "frames": np.tile(np.eye(4), (len(contents.get("stamps", ())), 1, 1))}
    missing = [key for key in (*required, *COLUMNS) if key not in contents]
    if missing:
        raise DatabaseFileError(f"{path} lacks {', '.join(missing)}")
    stored_model = _scalar_str(contents["model_id"])
    if stored_model != str(model_id):
        raise DatabaseFileError(
            f"{path} was built with model '{stored_model}', not the running model '{model_id}'"
        )
    active = contents["active_rows"]
    dimension = _scalar_int(contents["dimension"])
    sectors = _scalar_int(contents["sectors"])
    if (dimension != scorer.dimension or sectors != scorer.sectors
            or not np.array_equal(active, scorer.active_rows)):
        raise DatabaseFileError(
            f"{path} stores {active.size} active rows in {sectors} sector(s) of a "
            f"{dimension}-row descriptor; the scorer uses {len(scorer.active_rows)} in "
            f"{scorer.sectors} of {scorer.dimension} (different pruning or grid?)"
        )
    try:
        sessions = json.loads(_scalar_str(contents["sessions_json"]))
        if not isinstance(sessions, list):
            raise ValueError("sessions_json is not a list")
        return _checked(contents, [str(s) for s in sessions], scorer, str(model_id))
    except (ValueError, TypeError, RecursionError) as error:  # RecursionError: JSON nested too deeply
        raise DatabaseFileError(f"{path} is inconsistent: {one_line(error)}") from None


def _checked(c: dict[str, np.ndarray], sessions: list[str], scorer: WeightedL1Scorer,
             model_id: str) -> SavedDatabase:
    """The loaded arrays, once their shapes and invariants hold (``ValueError`` otherwise)."""
    n = len(c["stamps"])
    expected = {
        "stamps": ((n,), "f"),
        "session_index": ((n,), "i"),
        "keyframe_ids": ((n,), "i"),
        "poses": ((n, 4, 4), "f"),
        "frames": ((n, 4, 4), "f"),
        "cloud_offsets": ((n + 1,), "i"),
    }
    for key, (shape, kind) in expected.items():
        if c[key].shape != shape or c[key].dtype.kind != kind:
            raise ValueError(f"{key} has shape {c[key].shape} {c[key].dtype}, expected {shape}")
    points, offsets, ids = c["cloud_points"], c["cloud_offsets"], c["keyframe_ids"]
    if points.ndim != 2 or points.shape[1] != 3 or points.dtype.kind != "f":
        raise ValueError(f"cloud_points has shape {points.shape}, expected (P, 3)")
    if offsets[0] != 0 or offsets[-1] != len(points) or np.any(np.diff(offsets) < 0):
        raise ValueError("cloud_offsets do not partition cloud_points")
    if n and (np.any(np.diff(ids) <= 0) or ids[0] < 0):
        raise ValueError("keyframe ids are not strictly increasing")
    next_id = _scalar_int(c["next_keyframe_id"])
    if next_id < 0 or (n and next_id <= ids[-1]):
        raise ValueError("next_keyframe_id would reuse an id")
    if next_id > MAX_KEYFRAME_ID:
        raise ValueError(f"next_keyframe_id {next_id} is beyond 2**53, the largest id a closure message "
                         "carries exactly")
    if n and (c["session_index"].min() < 0 or c["session_index"].max() >= len(sessions)):
        raise ValueError("session index outside the session table")
    if not np.all(np.isfinite(c["stamps"])):
        raise ValueError("stamps contain NaN or inf")
    if not np.all(np.isfinite(c["frames"])):
        raise ValueError("frames contain NaN or inf")
    index = KeyframeIndex.from_state(c, _INDEX_PREFIX)
    if len(index) != n:
        raise ValueError(f"the index holds {len(index)} descriptors for {n} keyframes")
    if index.sectors != scorer.sectors or not np.array_equal(index.weights, scorer.active_weights):
        raise ValueError("the index was built with other weights than the scorer's")
    all_round = AllRoundIndex.from_state(c, index, _ALL_ROUND_PREFIX)
    if not np.array_equal(all_round.index.weights, index.weights):
        raise ValueError("the all-round index was built with other weights than the scorer's")
    return SavedDatabase(model_id, sessions, next_id, {name: c[name] for name in COLUMNS}, index, all_round)


def _scalar_str(value: np.ndarray | None) -> str:
    if value is None or value.shape != () or value.dtype.kind not in "US":
        return ""
    return str(value)


def _scalar_int(value: np.ndarray | None) -> int:
    if value is None or value.shape != () or value.dtype.kind not in "iu":
        return -1
    return int(value)
