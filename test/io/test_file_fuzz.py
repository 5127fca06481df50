"""Seeded mutation fuzz of model and keyframe-database files through their real loaders.

Every mutated file must either load into something the node can use (score,
threshold, add a keyframe, save again) or be refused with the project's own
file error: one line naming the file. Anything else — another exception, a
warning, a file that loads and then fails on first use — is a failure, listed
with the seed that reproduces it. ``--long`` runs 1000 mutations per format.
"""

from __future__ import annotations

import json
import math
import struct
import tracemalloc
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from vbrl_ros.config import FeatureConfig, VBRLConfig, VoxelGridConfig
from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.database_file import DatabaseFileError
from vbrl_ros.detection.detector import LoopClosureDetector
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.model.model_file import ModelFileError, VBRLModel, load_model

pytestmark = pytest.mark.filterwarnings("error")  # a node would print each warning per file

CONFIG = VBRLConfig(
    grid=VoxelGridConfig(kind="polar", rings=4, sectors=6, max_range=20.0, z_edges=(0.0, 20.0), frame="ground"),
    features=FeatureConfig(modalities=("height",), normalise=True, min_points=1),
)
PRUNE = 0.0001  # the node's default weight_prune

#: Replacement values for a whole member: each kind of thing a hand-edited or corrupted file could hold.
MEMBER_VALUES: list[Callable[[], np.ndarray]] = [
    lambda: np.array(5), lambda: np.array(-1), lambda: np.array(0), lambda: np.array(2**63 - 1),
    lambda: np.array(np.nan), lambda: np.array(np.inf), lambda: np.array(1e308), lambda: np.array(True),
    lambda: np.array("abc"), lambda: np.array(""), lambda: np.array("[1, 2]"), lambda: np.array("{}"),
    lambda: np.array("null"), lambda: np.array("5"), lambda: np.array([1, 1]), lambda: np.zeros(3),
    lambda: np.zeros((2, 2)), lambda: np.zeros(0), lambda: np.zeros((0, 3)), lambda: np.array(1 + 2j),
    lambda: np.array(b"bytes"), lambda: np.zeros(3, np.float16), lambda: np.zeros(3, np.uint8),
    lambda: np.array(["a", "b"]), lambda: np.array([{"pickled": 1}], dtype=object),
]
#: Replacement values inside a JSON member.
JSON_VALUES = [5, -1, 0, 0.5, 2**63 - 1, 10**30, 1e308, float("nan"), float("inf"), -float("inf"), "low", "",
               "\u0663", "\u00b2", [], [1, 2], ["a", 3], {}, {"a": 1}, None, True, False]
ELEMENT_VALUES = [np.nan, np.inf, -np.inf, -1.0, 0.0, 1e30, 3.4e38, 2.0**62, -(2.0**62)]


def make_model() -> VBRLModel:
    d = Featurizer(CONFIG).dimension
    rng = np.random.default_rng(0)
    scenarios = [f"place_{k}" for k in range(5)]
    return VBRLModel(config=CONFIG, W=rng.normal(size=(d, len(scenarios))), feature_mean=rng.normal(size=d),
                     feature_scale=rng.uniform(0.5, 2.0, size=d), lambda1=10.0, lambda2=0.1, scenarios=scenarios,
                     metadata={"scans": 40, "distance_threshold": 0.3, "translation_search": 1.5,
                               "sources": ["town_0.mcap"]})


def make_database(model: VBRLModel) -> KeyframeDatabase:
    scorer = model.scorer(prune=PRUNE)
    db = KeyframeDatabase(scorer, model.identity())
    rng = np.random.default_rng(1)
    for k in range(12):
        pose = np.eye(4) if k % 3 else None
        db.add(rng.normal(size=db.n_active).astype(np.float32), float(k), str(k // 6),
               pose=pose, cloud=rng.uniform(-20, 20, (rng.integers(0, 30), 3)))
    return db


def contents_of(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as archive:
        return {key: archive[key] for key in archive.files}


# -- mutations: each takes the original arrays and writes a mutated file ------------------


def replace_member(contents, rng, path):
    key = str(rng.choice(sorted(contents)))
    value = MEMBER_VALUES[rng.integers(len(MEMBER_VALUES))]()
    np.savez(path, **{**contents, key: value}, allow_pickle=True)
    return f"{key} = {value!r}"


def remove_member(contents, rng, path):
    key = str(rng.choice(sorted(contents)))
    np.savez(path, **{k: v for k, v in contents.items() if k != key})
    return f"without {key}"


def add_member(contents, rng, path):
    name = str(rng.choice(["extra", "W_old", "index_extra", "notes"]))
    value = MEMBER_VALUES[rng.integers(len(MEMBER_VALUES))]()
    np.savez(path, **contents, **{name: value}, allow_pickle=True)
    return f"extra member {name} = {value!r}"


def mutate_json(contents, rng, path):
    keys = sorted(k for k, v in contents.items() if k.endswith("_json"))
    key = str(rng.choice(keys))
    document = json.loads(str(contents[key]))
    value = JSON_VALUES[rng.integers(len(JSON_VALUES))]
    where = _json_container(document, rng)
    if where is None:
        document, what = value, "the whole document"
    else:
        container, slot = where
        if rng.random() < 0.2:
            del container[slot]
            value, what = "(deleted)", f"[{slot!r}]"
        else:
            container[slot], what = value, f"[{slot!r}]"
    np.savez(path, **{**contents, key: np.array(json.dumps(document))})
    return f"{key}{what} = {value!r}"


def _json_container(document, rng):
    """A random (container, key or index) inside a JSON document, or None for the document itself."""
    container = None
    node = document
    while isinstance(node, (dict, list)) and len(node) and rng.random() < 0.8:
        slot = str(rng.choice(sorted(node))) if isinstance(node, dict) else int(rng.integers(len(node)))
        container, node = (node, slot), node[slot]
    return container


def mutate_elements(contents, rng, path):
    keys = sorted(k for k, v in contents.items() if v.dtype.kind in "fiu" and v.size)
    key = str(rng.choice(keys))
    value = contents[key].copy()
    how = rng.integers(4)
    if how == 0 and value.dtype.kind == "f":
        flat = value.reshape(-1)
        picked = rng.integers(value.size, size=rng.integers(1, 4))
        flat[picked] = ELEMENT_VALUES[rng.integers(len(ELEMENT_VALUES))]
        what = f"elements {picked.tolist()} = {flat[picked[0]]}"
    elif how == 0 or how == 1:
        info = np.iinfo(value.dtype) if value.dtype.kind in "iu" else None
        flat = value.reshape(-1)
        picked = rng.integers(value.size)
        new = int(rng.choice([info.max, info.min, -1, 0, value.size, 2**31])) if info else float(
            rng.choice(ELEMENT_VALUES))
        flat[picked] = np.clip(new, info.min, info.max) if info else new
        what = f"element {picked} = {flat[picked]}"
    elif how == 2:
        dtype = np.dtype(str(rng.choice(["float16", "float32", "int8", "uint64", "int32", "bool"])))
        with np.errstate(all="ignore"):
            value = value.astype(dtype)
        what = f"as {dtype}"
    else:
        value = value.reshape(-1)[: max(value.size - int(rng.integers(1, 4)), 0)] if rng.random() < 0.5 \
            else value[..., None]
        what = f"shape {value.shape}"
    np.savez(path, **{**contents, key: value})
    return f"{key} {what}"


def claim_huge_shape(contents, rng, path):
    """A member whose npy header claims 10**12 elements while the data is as before."""
    key = str(rng.choice(sorted(contents)))
    np.savez(path, **contents)
    dtype = "<f8" if rng.random() < 0.5 else contents[key].dtype.str
    header = {"descr": dtype, "fortran_order": False, "shape": (10**12,)}
    _rewrite_member(path, key, _npy_header(header) + contents[key].tobytes())
    return f"{key} claims shape (10**12,) {dtype}"


def compressed_zeros(contents, key, path):
    """240 MB of zeros deflated into a quarter of a MB, under ``key`` (a defined member or not)."""
    np.savez(path, **{k: v for k, v in contents.items() if k != key})
    rows = 10_000_000
    header = _npy_header({"descr": "<f8", "fortran_order": False, "shape": (rows, 3)})
    with zipfile.ZipFile(path, "a", compression=zipfile.ZIP_DEFLATED) as archive:
        with archive.open(f"{key}.npy", "w", force_zip64=True) as out:
            out.write(header)
            block = bytes(1 << 20)
            for _ in range(rows * 24 >> 20):
                out.write(block)
    return f"{key}: 240 MB of compressed zeros"


def flip_bytes(contents, rng, path):
    np.savez(path, **contents)
    data = bytearray(path.read_bytes())
    picked = rng.integers(len(data), size=rng.integers(1, 8))
    for i in picked:
        data[i] = int(rng.integers(256))
    path.write_bytes(bytes(data))
    return f"bytes {sorted(picked.tolist())} changed"


def truncate(contents, rng, path):
    np.savez(path, **contents)
    data = path.read_bytes()
    cut = int(rng.integers(len(data)))
    path.write_bytes(data[:cut])
    return f"cut at byte {cut} of {len(data)}"


def _npy_header(header: dict) -> bytes:
    text = repr(header).encode("latin1")
    text += b" " * (-(len(text) + 11) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text


def _rewrite_member(path: Path, key: str, payload: bytes) -> None:
    with zipfile.ZipFile(path) as archive:
        members = {name: archive.read(name) for name in archive.namelist()}
    members[f"{key}.npy"] = payload
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)


MUTATIONS = [replace_member, remove_member, add_member, mutate_json, mutate_elements, claim_huge_shape,
             flip_bytes, truncate]
WEIGHTS = np.array([5, 1, 2, 5, 5, 1, 2, 1], dtype=float)


def mutated_files(original: Path, count: int, tmp_path: Path, bombed: str):
    """(seed, description, path) of ``count`` seeded mutations of ``original``; first two compressed
    bombs (seeds -2 and -1), under the defined member ``bombed`` and under a name no format defines."""
    contents = contents_of(original)
    path = tmp_path / f"mutated_{original.name}"
    yield -2, compressed_zeros(contents, bombed, path), path
    yield -1, compressed_zeros(contents, "extra", path), path
    for seed in range(count - 2):
        rng = np.random.default_rng(seed)
        mutation = MUTATIONS[rng.choice(len(MUTATIONS), p=WEIGHTS / WEIGHTS.sum())]
        yield seed, f"{mutation.__name__}: {mutation(contents, rng, path)}", path


def outcome(path: Path, error_type: type[Exception], load_and_use: Callable[[Path], None]) -> str | None:
    """None when the file was used or refused as it should be; else what went wrong."""
    try:
        load_and_use(path)
    except error_type as error:
        message = str(error)
        if "\n" in message or str(path) not in message:
            return f"{type(error).__name__} not one line naming the file: {message!r}"
    except BaseException as error:  # noqa: BLE001 - anything else is the finding
        if isinstance(error, KeyboardInterrupt):
            raise
        return f"{type(error).__name__}: {' '.join(str(error).split())[:200]}"
    return None


def fuzz(original: Path, error_type, load_and_use, count: int, tmp_path: Path, bombed: str) -> None:
    failures = []
    for seed, description, path in mutated_files(original, count, tmp_path, bombed):
        tracemalloc.start()
        try:
            problem = outcome(path, error_type, load_and_use)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        if problem is None and seed < 0 and peak > 50e6:  # the bombs: refused or left unread
            problem = f"{peak / 1e6:.0f} MB allocated"
        if problem is not None:
            failures.append(f"seed {seed} ({description}): {problem}")
    assert not failures, f"{len(failures)} of {count} mutations:\n" + "\n".join(failures[:40])


@pytest.fixture(scope="module")
def model() -> VBRLModel:
    return make_model()


def test_mutated_model_files_load_usable_or_fail_in_one_line(model, tmp_path, long_run):
    original = model.save(tmp_path / "model.npz")
    points = np.random.default_rng(2).uniform(-15, 15, (500, 3))

    def load_and_use(path: Path) -> None:
        loaded = load_model(path, expected_config=CONFIG)
        assert math.isfinite(loaded.distance_threshold()) and loaded.distance_threshold() >= 0
        assert 0 <= loaded.translation_search() <= 10
        scorer = loaded.scorer(prune=PRUNE)
        detector = LoopClosureDetector(loaded, KeyframeDatabase(scorer, loaded.identity()), DetectorSettings())
        detector.process_keyframe(points, 0.0)
        detector.process_keyframe(points, 100.0)

    fuzz(original, ModelFileError, load_and_use, 1000 if long_run else 150, tmp_path, bombed="W")


def test_mutated_database_files_load_usable_or_fail_in_one_line(model, tmp_path, long_run):
    original = make_database(model).save(tmp_path / "keyframes.npz")
    scorer, model_id = model.scorer(prune=PRUNE), model.identity()
    descriptor = np.random.default_rng(3).normal(size=len(scorer.active_rows)).astype(np.float32)

    def load_and_use(path: Path) -> None:
        db = KeyframeDatabase.load(path, scorer, model_id)
        db.query(descriptor, top_k=3, session="0", stamp=50.0, exclude_recent_s=1.0)
        db.add(descriptor, 50.0, "0", cloud=np.ones((3, 3)))
        db.next_session()
        KeyframeDatabase.load(db.save(tmp_path / "saved_again.npz"), scorer, model_id)

    fuzz(original, DatabaseFileError, load_and_use, 1000 if long_run else 150, tmp_path, bombed="cloud_points")
