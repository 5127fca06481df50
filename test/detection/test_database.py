"""The keyframe database: Eq. 4 retrieval, recency exclusion, memory, crash-safe files."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import vbrl_ros.detection.database as database_module
from vbrl_ros.detection.database import METADATA_BYTES_PER_KEYFRAME, KeyframeDatabase
from vbrl_ros.detection.database_file import DATABASE_FORMAT_VERSION, DatabaseFileError
from vbrl_ros.index.parameters import IndexParameters
from vbrl_ros.index.sequence_matching import SequenceHistory
from vbrl_ros.model.scoring import WeightedL1Scorer

D = 40  # full descriptor length of the toy model


def make_weights(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    weights = rng.uniform(0.1, 1.0, D)
    weights[rng.choice(D, 15, replace=False)] = 0.0  # rows the sparsity norms switched off
    return weights / weights.sum()


WEIGHTS = make_weights()
SCORER = WeightedL1Scorer(WEIGHTS)


def make_db(n: int = 0, seed: int = 1, **add_kwargs) -> tuple[KeyframeDatabase, np.ndarray]:
    """A database of ``n`` random keyframes; also returns their full descriptors."""
    db = KeyframeDatabase(SCORER, model_id="model-A")
    full = np.random.default_rng(seed).normal(size=(n, D)).astype(np.float32)
    for i, x in enumerate(full):
        db.add(SCORER.compact(x), stamp=float(i), session="s0", **add_kwargs)
    return db, full


def eq4(query: np.ndarray, templates: np.ndarray) -> np.ndarray:
    """Paper Eq. 4 over *all* rows, straight from the definition (float64)."""
    return np.abs(templates.astype(np.float64) - query.astype(np.float64)) @ WEIGHTS


# -- retrieval ----------------------------------------------------------------------


def test_compact_storage_keeps_only_active_rows():
    db, full = make_db(3)
    assert db.n_active == D - 15
    np.testing.assert_array_equal(db.descriptor(1), full[1, SCORER.active_rows])
    assert db.descriptor(0).dtype == np.float32


def test_query_matches_a_direct_eq4_computation():
    db, full = make_db(300)
    query = np.random.default_rng(2).normal(size=D).astype(np.float32)
    expected = eq4(query, full)
    order = np.argsort(expected, kind="stable")[:10]
    result = db.query(SCORER.compact(query), top_k=10)
    assert [c.index for c in result] == list(order)
    assert [c.keyframe_id for c in result] == list(order)  # ids 0..n-1 in insertion order
    np.testing.assert_allclose([c.distance for c in result], expected[order], rtol=1e-5)
    assert all(a.distance <= b.distance for a, b in zip(result, result[1:]))  # lower = closer
    assert all(c.yaw == 0.0 for c in result)  # Cartesian: no rotation search
    # the index's answer equals brute force over every keyframe
    assert db.query(SCORER.compact(query), top_k=10, exact=True) == result


def test_a_stored_descriptor_finds_itself_at_distance_zero():
    db, full = make_db(50)
    best = db.query(SCORER.compact(full[17]), top_k=1)[0]
    assert best.index == 17 and best.distance == 0.0 and best.session == "s0"
    assert best.stamp == 17.0


def test_empty_database_and_non_positive_top_k_return_nothing():
    db, _ = make_db(0)
    assert db.query(np.zeros(db.n_active)) == []
    db, _ = make_db(5)
    assert db.query(np.zeros(db.n_active), top_k=0) == []
    assert len(db.query(np.zeros(db.n_active), top_k=50)) == 5


def test_recency_exclusion_is_same_session_only():
    db = KeyframeDatabase(SCORER, model_id="model-A")
    x = np.zeros(db.n_active, dtype=np.float32)
    for t in range(10):  # session A at t = 0..9, session B at the same stamps
        db.add(x, stamp=float(t), session="A")
        db.add(x, stamp=float(t), session="B")
    found = db.query(x, top_k=100, session="A", stamp=9.0, exclude_recent_s=5.0)
    a_stamps = sorted(c.stamp for c in found if c.session == "A")
    b_stamps = sorted(c.stamp for c in found if c.session == "B")
    assert a_stamps == [0.0, 1.0, 2.0, 3.0, 4.0]  # stamp > 9 - 5 excluded
    assert b_stamps == [float(t) for t in range(10)]  # other sessions: never by recency
    # an unknown session, or no stamp, excludes nothing
    assert len(db.query(x, top_k=100, session="C", stamp=9.0, exclude_recent_s=5.0)) == 20
    assert len(db.query(x, top_k=100, session="A", exclude_recent_s=5.0)) == 20


@settings(max_examples=40, deadline=None)
@given(
    keyframes=st.lists(
        st.tuples(st.floats(0, 100, allow_nan=False), st.sampled_from(["A", "B", "C"])),
        max_size=30,
    ),
    now=st.floats(0, 100, allow_nan=False),
    window=st.floats(0, 50, allow_nan=False),
)
def test_recency_filter_property(keyframes, now, window):
    db = KeyframeDatabase(SCORER, model_id="m")
    rng = np.random.default_rng(0)
    for stamp, session in keyframes:
        db.add(rng.normal(size=db.n_active), stamp=stamp, session=session)
    query = np.zeros(db.n_active)
    found = db.query(query, top_k=100, session="A", stamp=now, exclude_recent_s=window)
    recent = {i for i, (s, name) in enumerate(keyframes) if name == "A" and s > now - window}
    assert {c.index for c in found} == set(range(len(keyframes))) - recent


# -- ids, clouds, poses ---------------------------------------------------------------


def test_ids_increase_and_clear_never_reuses_them():
    db, _ = make_db(3)
    assert db.keyframe_ids.tolist() == [0, 1, 2] and db.index_of(2) == 2
    db.clear()
    assert len(db) == 0 and db.sessions == []
    assert db.add(np.zeros(db.n_active), 1.0, "s") == 3
    with pytest.raises(KeyError):
        db.index_of(0)


def test_clouds_are_one_concatenated_array_and_poses_default_to_nan():
    db = KeyframeDatabase(SCORER, model_id="m")
    rng = np.random.default_rng(0)
    clouds = [rng.normal(size=(n, 3)) for n in (5, 0, 7)]
    pose = np.eye(4)
    pose[:3, 3] = [1, 2, 3]
    db.add(np.zeros(db.n_active), 0.0, "s", cloud=clouds[0], pose=pose)
    db.add(np.zeros(db.n_active), 1.0, "s")  # no cloud, no pose
    db.add(np.zeros(db.n_active), 2.0, "s", cloud=clouds[2])
    np.testing.assert_allclose(db.cloud(0), clouds[0], rtol=1e-6)
    assert db.cloud(1).shape == (0, 3) and db.cloud(2).dtype == np.float32
    np.testing.assert_allclose(db.cloud(-1), clouds[2], rtol=1e-6)
    assert db._cloud_points.ndim == 2  # one array + offsets, not a list of arrays
    assert db._cloud_offsets[:4].tolist() == [0, 5, 5, 12]
    np.testing.assert_array_equal(db.pose(0), pose)
    assert np.isnan(db.pose(1)).all()
    assert db.cloud_bytes_per_keyframe() == pytest.approx(12 * 12 / 3)


def test_invalid_input_is_refused():
    db, _ = make_db(1)
    with pytest.raises(ValueError, match=r"scorer.compact"):
        db.add(np.zeros(D), 0.0, "s")  # a full descriptor: forgot to compact it
    with pytest.raises(ValueError, match="NaN"):
        db.add(np.full(db.n_active, np.nan), 0.0, "s")
    with pytest.raises(ValueError, match="stamp"):
        db.add(np.zeros(db.n_active), float("nan"), "s")
    with pytest.raises(ValueError, match="4x4"):
        db.add(np.zeros(db.n_active), 0.0, "s", pose=np.eye(3))
    with pytest.raises(ValueError, match=r"\(M, 3\)"):
        db.add(np.zeros(db.n_active), 0.0, "s", cloud=np.zeros((4, 2)))
    with pytest.raises(ValueError, match="compact descriptor"):
        db.query(np.zeros(3))
    assert len(db) == 1  # nothing half-added


# -- memory and growth -----------------------------------------------------------------


def test_bytes_per_keyframe_is_descriptor_key_metadata_and_place():
    db, _ = make_db(0)
    active = D - 15
    key = -(-min(256, active) // 2)  # 4-bit key entries, at most one per active row
    assert db.bytes_per_keyframe() == active * 4 + key + METADATA_BYTES_PER_KEYFRAME + 40 + 1
    assert db.bytes_breakdown() == {"descriptor": active * 4, "key": key, "yaw_key": 0,
                                    "metadata": METADATA_BYTES_PER_KEYFRAME, "place": 40, "sees_all_round": 1}
    # an all-round descriptor: another descriptor with its keys, and the main row it belongs to
    assert db.all_round_bytes_per_keyframe() == active * 4 + key + 8
    full = KeyframeDatabase(WeightedL1Scorer(np.ones(7872)), model_id="default")
    # 256 + 512 four-bit key entries (scan key, refine key)
    assert full.bytes_per_keyframe() == 7872 * 4 + 384 + METADATA_BYTES_PER_KEYFRAME + 40 + 1 == 32205
    half = KeyframeDatabase(WeightedL1Scorer(np.ones(7872)), "default", IndexParameters(storage="float16"))
    assert half.bytes_per_keyframe() == 7872 * 2 + 384 + METADATA_BYTES_PER_KEYFRAME + 40 + 1
    assert half.all_round_bytes_per_keyframe() == 7872 * 2 + 384 + 8
    assert full.cloud_bytes_per_keyframe() == 0.0


def test_the_metadata_and_place_figures_are_what_a_keyframe_adds_to_the_arrays():
    db = KeyframeDatabase(WeightedL1Scorer(np.ones(8)), model_id="m")
    rng = np.random.default_rng(0)
    for k in range(200):  # one session with odometry: every keyframe has a place
        pose = np.eye(4)
        pose[:2, 3] = rng.uniform(-500, 500, 2)
        db.add(rng.normal(size=8).astype(np.float32), float(k), "0", pose=pose)
    per_row = lambda arrays: sum(a.itemsize * int(np.prod(a.shape[1:])) for a in arrays)  # noqa: E731
    metadata = [db._stamps, db._session_index, db._keyframe_ids, db._poses, db._frames, db._cloud_offsets,
                db._paths]
    assert per_row(metadata) == METADATA_BYTES_PER_KEYFRAME
    places = db._places[0]
    assert per_row([places._ids, places._positions, places._chain]) == db.bytes_breakdown()["place"]
    assert per_row([db.all_round.sees_all_round]) == db.bytes_breakdown()["sees_all_round"]


def test_what_an_all_round_descriptor_adds_is_what_the_all_round_index_grows_by():
    db = KeyframeDatabase(WeightedL1Scorer(np.ones(8)), model_id="m")
    rng = np.random.default_rng(1)
    for k in range(300):
        db.add(rng.normal(size=8).astype(np.float32), float(k), "0", all_round=rng.normal(size=8).astype(np.float32))
    store = db.all_round.index.store  # what one more row of each of its arrays holds
    per_row = lambda arrays: sum(a.itemsize * int(np.prod(a.shape[1:])) for a in arrays)  # noqa: E731
    stored = (per_row([store._descriptors, store.refine_key_bytes, store.yaw_coarse, store.yaw_fine])
              + store.key_blocks.shape[1] + db.all_round.rows.itemsize)
    assert len(db.all_round) == 300 and db.all_round_bytes_per_keyframe() == stored


def test_add_is_amortised_constant_time():
    db = KeyframeDatabase(WeightedL1Scorer(np.ones(8)), model_id="m")
    x = np.zeros(8, dtype=np.float32)
    capacities = []
    for i in range(20_000):
        db.add(x, float(i), "s")
        if not capacities or db.capacity != capacities[-1]:
            capacities.append(db.capacity)
    # geometric growth: every reallocation at least doubles, so there are only
    # log2(20000 / 64) ~ 9 of them and each add copies O(1) rows on average
    assert all(b >= 2 * a for a, b in zip(capacities, capacities[1:]))
    assert len(capacities) <= 10 and db.capacity < 2 * 20_000 + 64
    assert len(db) == 20_000 and db.keyframe_ids[-1] == 19_999


# -- files -------------------------------------------------------------------------------


def test_save_load_round_trip_and_ids_continue(tmp_path):
    db, full = make_db(20, cloud=np.ones((4, 3)))
    db.add(SCORER.compact(full[0]), 99.0, "other", pose=np.eye(4))
    path = db.save(tmp_path / "kf.npz")
    loaded = KeyframeDatabase.load(path, SCORER, "model-A")
    assert len(loaded) == 21 and loaded.sessions == ["s0", "other"]
    np.testing.assert_array_equal(loaded.keyframe_ids, db.keyframe_ids)
    np.testing.assert_array_equal(loaded.stamps, db.stamps)
    for i in (0, 20):
        np.testing.assert_array_equal(loaded.descriptor(i), db.descriptor(i))
        np.testing.assert_array_equal(loaded.cloud(i), db.cloud(i))
        np.testing.assert_array_equal(loaded.pose(i), db.pose(i))
        assert loaded.session_of(i) == db.session_of(i)
    query = SCORER.compact(full[3])
    assert loaded.query(query, top_k=5) == db.query(query, top_k=5)
    assert loaded.add(query, 100.0, "s0") == 21  # ids continue, never restart
    assert not list(tmp_path.glob(".*tmp"))


def test_the_path_driven_between_keyframes_survives_a_restart(tmp_path):
    # odometry_gate: metres apart and metres driven between two keyframes of one session
    def at(x, y):
        T = np.eye(4)
        T[:2, 3] = x, y
        return T
    db, descriptor = make_db(0)[0], SCORER.compact(np.zeros(D, np.float32))
    for i, (session, xy) in enumerate([("s0", (0, 0)), ("s0", (3, 4)), ("s1", (0, 0)), ("s0", (3, 0))]):
        db.add(descriptor, float(i), session, pose=at(*xy))
    assert db.odometry_apart(3, 0) == (3.0, 9.0)
    assert all(np.isnan(db.odometry_apart(2, 0)))  # two sessions: odometry does not relate them
    loaded = KeyframeDatabase.load(db.save(tmp_path / "kf.npz"), SCORER, "model-A")
    assert loaded.odometry_apart(3, 0) == (3.0, 9.0)
    loaded.add(descriptor, 9.0, "s0", pose=at(3, 8))  # driving on after it
    assert loaded.odometry_apart(4, 0) == (np.hypot(3, 8), 17.0)


def test_ids_survive_clear_and_save(tmp_path):
    db, _ = make_db(5)
    db.clear()
    path = db.save(tmp_path / "kf.npz")
    loaded = KeyframeDatabase.load(path, SCORER, "model-A")
    assert len(loaded) == 0 and loaded.add(np.zeros(loaded.n_active), 0.0, "s") == 5


def test_crash_mid_save_keeps_the_last_good_file(tmp_path, monkeypatch):
    db, full = make_db(10)
    path = db.save(tmp_path / "kf.npz")
    db.add(SCORER.compact(full[0]), 50.0, "s0")
    real_savez = np.savez

    def crashing_savez(handle, **arrays):  # writes half an archive, then dies
        buffer = io.BytesIO()
        real_savez(buffer, **arrays)
        handle.write(buffer.getvalue()[: len(buffer.getvalue()) // 2])
        raise OSError("disk full")

    monkeypatch.setattr(database_module.np, "savez", crashing_savez)
    with pytest.raises(OSError, match="disk full"):
        db.save(path)
    monkeypatch.undo()
    assert len(KeyframeDatabase.load(path, SCORER, "model-A")) == 10
    assert not list(tmp_path.glob(".*tmp"))


def _assert_refused(path, match, model_id="model-A", scorer=SCORER):
    with pytest.raises(DatabaseFileError, match=match) as error:
        KeyframeDatabase.load(path, scorer, model_id)
    assert "\n" not in str(error.value)


def test_truncated_file_is_refused(tmp_path):
    path = make_db(10)[0].save(tmp_path / "kf.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    _assert_refused(path, "truncated")


def test_missing_and_foreign_files_are_refused(tmp_path):
    _assert_refused(tmp_path / "nothing.npz", "does not exist")
    (tmp_path / "text.npz").write_text("hello")
    _assert_refused(tmp_path / "text.npz", "not a vbrl_ros keyframe database file .it is a text file")
    np.savez(tmp_path / "foreign.npz", W=np.ones(3))
    _assert_refused(tmp_path / "foreign.npz", "not a vbrl_ros keyframe database")
    np.savez(tmp_path / "model.npz", format=np.array("vbrl_ros.model"), format_version=np.array(1))
    _assert_refused(tmp_path / "model.npz", "not a vbrl_ros keyframe database")


def _rewrite(path, **changes):
    with np.load(path, allow_pickle=False) as archive:
        contents = {key: archive[key] for key in archive.files}
    contents.update(changes)
    with open(path, "wb") as handle:
        np.savez(handle, **contents)


def test_pickled_object_arrays_are_refused(tmp_path):
    path = make_db(3)[0].save(tmp_path / "kf.npz")
    _rewrite(path, stamps=np.array([{"evil": 1}, None, 3], dtype=object))
    _assert_refused(path, "allow_pickle=False")


def test_other_version_model_and_pruning_are_refused(tmp_path):
    db, _ = make_db(3)
    path = db.save(tmp_path / "kf.npz")
    _assert_refused(path, "built with model 'model-A'", model_id="model-B")
    pruned = WeightedL1Scorer(WEIGHTS, prune=0.5)
    _assert_refused(path, "different pruning", scorer=pruned)
    _rewrite(path, format_version=np.array(1))  # before the index: no index arrays
    _assert_refused(path, "format version 1; this vbrl_ros reads versions 2, 3")
    _rewrite(path, format_version=np.array(4))
    _assert_refused(path, "format version 4")


def test_version_2_files_load_with_sensor_frames(tmp_path):
    """Files from before frames were stored: clouds in the sensor frame, identity frames."""
    db, _ = make_db(3)
    path = db.save(tmp_path / "kf.npz")
    with np.load(path) as archive:
        arrays = {k: archive[k] for k in archive.files if k != "frames"}
    arrays["format_version"] = np.array(2)
    np.savez(path, **arrays)
    loaded = KeyframeDatabase.load(path, WeightedL1Scorer(WEIGHTS), "model-A")
    assert len(loaded) == 3 and np.array_equal(loaded.frame(2), np.eye(4))
    _rewrite(path, format_version=np.array(3))  # a version 3 file must have them
    _assert_refused(path, "lacks frames")


def test_frames_round_trip(tmp_path):
    db, _ = make_db(0)
    frame = np.eye(4)
    frame[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    frame[2, 3] = 1.7
    db.add(np.ones(db.n_active, np.float32), 1.0, "s", frame=frame)
    loaded = KeyframeDatabase.load(db.save(tmp_path / "kf.npz"), WeightedL1Scorer(WEIGHTS), "model-A")
    assert np.array_equal(loaded.frame(0), frame)
    with pytest.raises(ValueError, match="frame must be a finite 4x4"):
        db.add(np.ones(db.n_active, np.float32), 2.0, "s", frame=np.full((4, 4), np.nan))


def test_inconsistent_contents_are_refused(tmp_path):
    path = make_db(3)[0].save(tmp_path / "kf.npz")
    _rewrite(path, keyframe_ids=np.array([0, 2, 1]))
    _assert_refused(path, "strictly increasing")
    path = make_db(3)[0].save(tmp_path / "kf.npz")
    _rewrite(path, stamps=np.zeros(2))
    _assert_refused(path, "inconsistent")
    path = make_db(3)[0].save(tmp_path / "kf.npz")
    with zipfile.ZipFile(path) as archive:
        names = [n for n in archive.namelist() if n != "poses.npy"]
        members = {n: archive.read(n) for n in names}
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    _assert_refused(path, "lacks poses")


def test_a_next_keyframe_id_no_closure_message_carries_is_refused(tmp_path):
    path = make_db(3)[0].save(tmp_path / "kf.npz")
    _rewrite(path, next_keyframe_id=np.array(2**63 - 1))
    _assert_refused(path, "next_keyframe_id 9223372036854775807 is beyond 2\\*\\*53")
    _rewrite(path, next_keyframe_id=np.array(2**53 - 1))
    db = KeyframeDatabase.load(path, SCORER, "model-A")
    assert db.add(np.zeros(db.n_active), 9.0, "s") == 2**53 - 1
    db = KeyframeDatabase.load(db.save(path), SCORER, "model-A")
    with pytest.raises(ValueError, match="no keyframe id left"):
        db.add(np.zeros(db.n_active), 10.0, "s")


def test_the_next_session_follows_the_largest_numbered_one():
    db, _ = make_db(0)
    assert db.next_session() == 0
    for session in ("3", "lab", "\u00b2", "\u0667", "9" * 40):  # superscript two; Arabic-Indic seven
        db.add(np.zeros(db.n_active), 0.0, session)
    assert db.next_session() == 8


def test_index_arrays_are_checked_on_load(tmp_path):
    db, full = make_db(30)
    path = db.save(tmp_path / "kf.npz")
    with np.load(path, allow_pickle=False) as archive:
        assert "index_descriptors" in archive.files and "descriptors" not in archive.files
        keys = archive["index_keys"].copy()
    keys[3] = np.clip(keys[3].astype(np.int16) + 5, -127, 127).astype(np.int8)
    _rewrite(path, index_keys=keys)
    _assert_refused(path, "inconsistent: stored keys do not match")
    path = db.save(tmp_path / "kf.npz")
    _rewrite(path, index_descriptors=np.zeros((29, db.n_active), np.float32))
    _assert_refused(path, "inconsistent")
    path = db.save(tmp_path / "kf.npz")
    _rewrite(path, index_format_version=np.array(1))
    _assert_refused(path, "keyframe index state version")
    assert DATABASE_FORMAT_VERSION == 3


# -- index delegation, float16, polar --------------------------------------------------


def test_one_copy_of_the_descriptors_lives_in_the_index():
    db, full = make_db(5)
    assert not hasattr(db, "_descriptors")
    np.testing.assert_array_equal(db.index.descriptors()[2], full[2, SCORER.active_rows])
    np.testing.assert_array_equal(db.descriptor(-1), full[4, SCORER.active_rows])


def test_float16_storage_round_trips_and_finds_itself(tmp_path):
    db = KeyframeDatabase(SCORER, "model-A", IndexParameters(storage="float16"))
    full = np.random.default_rng(5).normal(size=(200, D)).astype(np.float32)
    for i, x in enumerate(full):
        db.add(SCORER.compact(x), float(i), "s")
    assert db.index.descriptors().dtype == np.float16
    stored = full[:, SCORER.active_rows].astype(np.float16).astype(np.float32)
    np.testing.assert_array_equal(db.descriptor(7), stored[7])
    best = db.query(SCORER.compact(full[7]), top_k=3)
    assert best[0].index == 7
    expected = np.abs(stored - SCORER.compact(full[7])) @ SCORER.active_weights
    np.testing.assert_allclose([c.distance for c in best], np.sort(expected)[:3], rtol=1e-5)
    loaded = KeyframeDatabase.load(db.save(tmp_path / "kf.npz"), SCORER, "model-A")
    assert loaded.index.parameters.storage == "float16"
    assert loaded.query(SCORER.compact(full[7]), top_k=3) == best
    with pytest.raises(ValueError, match="float16 range"):
        db.add(np.full(db.n_active, 1e6), 0.0, "s")


SECTORS, COLUMNS = 8, 12


def polar_scorer(prune: float = 0.0) -> WeightedL1Scorer:
    """Sector-major toy layout: row s * COLUMNS + c is column c of sector s; 3 columns off."""
    column_weights = np.random.default_rng(3).uniform(0.1, 1.0, COLUMNS)
    column_weights[[1, 5, 9]] = 0.0
    sector_rows = np.arange(SECTORS * COLUMNS).reshape(SECTORS, COLUMNS)
    return WeightedL1Scorer(np.tile(column_weights, SECTORS), prune, sector_rows=sector_rows)


def test_polar_candidates_carry_the_yaw_of_the_best_shift(tmp_path):
    scorer = polar_scorer()
    db = KeyframeDatabase(scorer, "polar")
    assert db.index.sectors == SECTORS and db.n_active == SECTORS * (COLUMNS - 3)
    rng = np.random.default_rng(1)
    places = rng.normal(size=(40, SECTORS * COLUMNS))
    for i, x in enumerate(places):
        db.add(scorer.compact(x), float(i), "map")
    for k in (0, 1, 3, 4, 6, 7):
        rotated = np.roll(scorer.compact(places[11]).reshape(SECTORS, -1), k, axis=0).ravel()
        best = db.query(rotated, top_k=2)[0]
        signed = k if k <= SECTORS // 2 else k - SECTORS
        assert best.index == 11 and best.distance == 0.0
        assert best.yaw == pytest.approx(signed * 2 * np.pi / SECTORS)
        assert db.query(rotated, top_k=2, exact=True)[0] == best
    loaded = KeyframeDatabase.load(db.save(tmp_path / "kf.npz"), scorer, "polar")
    assert loaded.query(rotated, top_k=3) == db.query(rotated, top_k=3)
    cartesian = WeightedL1Scorer(np.tile(np.ones(COLUMNS), SECTORS))
    _assert_refused(tmp_path / "kf.npz", "different pruning or grid", "polar", cartesian)


def test_recency_exclusion_is_exact_in_a_large_database():
    db = KeyframeDatabase(SCORER, "m", IndexParameters(candidates=4))  # few candidates: mask must act first
    x = np.random.default_rng(0).normal(size=(3000, db.n_active)).astype(np.float32)
    for i, v in enumerate(x):
        db.add(v, stamp=float(i), session="B" if i % 3 == 0 else "A")
    kwargs = dict(top_k=20, session="A", stamp=2999.0, exclude_recent_s=100.0)
    for i in (2997, 2998):  # a recent keyframe of the other session / of the own session
        found = db.query(x[i] + 0.01, **kwargs)
        assert len(found) == 20
        assert all(c.session == "B" or c.stamp <= 2899.0 for c in found)
        assert (found[0].index == i) == (i == 2997)  # the own recent past is never returned
        assert found[0] == db.query(x[i] + 0.01, exact=True, **kwargs)[0]


def test_a_sequence_ranks_a_revisited_run_above_a_lookalike_of_the_last_keyframe_alone():
    db, full = make_db(30)
    rng = np.random.default_rng(7)
    path = [12, 11, 10, 9]  # keyframes 12..9 revisited the other way round
    queries = [SCORER.compact(full[j] + rng.normal(0, 0.3, D).astype(np.float32)) for j in path]
    lookalike = db.add(queries[-1] + rng.normal(0, 0.05, len(queries[-1])).astype(np.float32), 30.0, "s0")
    zero = np.zeros((1, 2))
    alone = db.query_views(queries[-1][None], zero, top_k=3)
    assert alone[0].keyframe_id == lookalike

    history = SequenceHistory(4)
    for query in queries:
        found = db.query_views(query[None], zero, top_k=3, sequence=history)
    assert found[0].keyframe_id == 9
    # the reported distance is the sequence's: the last keyframe's own distance to 9 counted
    # twice, and each earlier one's to the nearest of 10, 11, 12 (one keyframe of slack)
    def distance(query, row):
        return float(np.abs(db.descriptor(row) - query) @ SCORER.active_weights)

    earlier = [min(distance(queries[3 - step], 9 + step + s) for s in (-1, 0, 1)) for step in (1, 2, 3)]
    assert found[0].distance == pytest.approx((2 * distance(queries[-1], 9) + sum(earlier)) / 5, rel=1e-5)
    assert len(history) == 3


def test_a_keyframe_against_an_empty_database_still_takes_its_place_in_the_sequence():
    db = KeyframeDatabase(SCORER, model_id="model-A")
    history = SequenceHistory(3)
    assert db.query_views(np.zeros((1, SCORER.active_rows.size), np.float32), np.zeros((1, 2)),
                          sequence=history) == []
    assert len(history) == 1


def along_x(k: int) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = 2.0 * k
    return pose


def test_with_odometry_a_session_is_matched_by_place_and_the_places_survive_a_restart(tmp_path):
    db = KeyframeDatabase(SCORER, model_id="model-A")
    full = np.random.default_rng(1).normal(size=(30, D)).astype(np.float32)
    for i, x in enumerate(full):  # one street along x, a keyframe every 2 m
        db.add(SCORER.compact(x), stamp=float(i), session="s0", pose=along_x(i))
    rng = np.random.default_rng(3)
    # the query comes down a street along y that no keyframe was taken on, to keyframe 10's place
    queries = [SCORER.compact(rng.normal(size=D).astype(np.float32)) for _ in range(3)]
    queries.append(SCORER.compact(full[10] + rng.normal(0, 0.3, D).astype(np.float32)))
    positions = [np.array([20.0, y, 0.0]) for y in (9.0, 6.0, 3.0, 0.0)]

    def run(database, session, with_position):
        history = SequenceHistory(4)
        for query, position in zip(queries, positions):
            found = database.query_views(query[None], np.zeros((1, 2)), top_k=3, session=session, stamp=100.0,
                                         sequence=history, position=position if with_position else None)
        return [(c.keyframe_id, c.distance) for c in found]

    by_id = run(db, "s0", with_position=False)
    by_place = run(db, "s0", with_position=True)
    assert by_place[0][0] == 10
    assert by_place[0][1] != pytest.approx(by_id[0][1])  # the earlier terms are the places', not the ids'
    # another session's keyframes lie in another odometry frame: matched by id
    assert run(db, "other", with_position=True) == run(db, "other", with_position=False)
    db.save(tmp_path / "db.npz")
    assert run(KeyframeDatabase.load(tmp_path / "db.npz", SCORER, "model-A"), "s0", with_position=True) == by_place


# -- all-round descriptors ------------------------------------------------------------


def test_a_keyframe_described_all_round_is_found_all_round_and_kept_across_a_restart(tmp_path):
    db, full = make_db(30)
    rng = np.random.default_rng(9)
    round_ = SCORER.compact(rng.normal(size=D).astype(np.float32))
    kept = db.add(SCORER.compact(full[3]), stamp=30.0, session="s0", all_round=round_)
    far = SCORER.compact(rng.normal(size=D).astype(np.float32) * 10.0)
    assert kept not in [c.keyframe_id for c in db.query(far, top_k=3)]  # hidden, it is far
    found = db.query_views(far[None], np.zeros((1, 2)), top_k=3, all_round_views=round_[None])
    assert found[0].keyframe_id == kept and found[0].distance == 0.0
    whole = db.add(SCORER.compact(full[4]), stamp=31.0, session="s0", sees_all_round=True)
    restored = KeyframeDatabase.load(db.save(tmp_path / "db.npz"), SCORER, "model-A")
    assert restored.query_views(far[None], np.zeros((1, 2)), top_k=1,
                                all_round_views=round_[None])[0].keyframe_id == kept
    np.testing.assert_array_equal(np.flatnonzero(restored.all_round.sees_all_round), [restored.index_of(whole)])
    # an all-round query meets the keyframe described all round by itself, through its main descriptor
    assert restored.query_views(far[None], np.zeros((1, 2)), top_k=1,
                                all_round_views=SCORER.compact(full[4])[None])[0].keyframe_id == whole
    restored.clear()
    assert len(restored.all_round) == 0


def test_a_bad_all_round_descriptor_stores_nothing():
    db, _ = make_db(3)
    with pytest.raises(ValueError):
        db.add(np.zeros(db.n_active), 3.0, "s0", all_round=np.zeros(db.n_active + 1))
    assert len(db) == 3 and len(db.index) == 3 and len(db.all_round) == 0
