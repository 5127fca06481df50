import json
import zipfile

import numpy as np
import pytest

from vbrl_ros.config import VBRLConfig, VoxelGridConfig
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.model.model_file import ModelFileError, VBRLModel, load_model

CONFIG = VBRLConfig(grid=VoxelGridConfig(cells_xy=4))


def make_model(config=CONFIG, seed=0) -> VBRLModel:
    d = Featurizer(config).dimension
    rng = np.random.default_rng(seed)
    return VBRLModel(
        config=config,
        W=rng.normal(size=(d, 2)),
        feature_mean=rng.normal(size=d),
        feature_scale=rng.uniform(0.5, 2, size=d),
        lambda1=10.0,
        lambda2=0.1,
        scenarios=["summer_clear", "winter_snow"],
        metadata={"scans": 12},
    )


def test_round_trip(tmp_path):
    model = make_model()
    path = model.save(tmp_path / "model.npz")
    loaded = load_model(path, expected_config=CONFIG)
    assert loaded.config == CONFIG
    for name in ("W", "feature_mean", "feature_scale", "w_modality", "w_voxel"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(model, name))
    assert loaded.scenarios == ["summer_clear", "winter_snow"]
    assert (loaded.lambda1, loaded.lambda2) == (10.0, 0.1)
    assert loaded.metadata == {"scans": 12}
    assert loaded.w_modality.sum() == pytest.approx(1.0)
    assert not list(tmp_path.glob(".*tmp"))  # no temp file left behind


def test_standardize_and_score():
    model = make_model()
    x = np.random.default_rng(1).normal(size=(3, model.layout.dimension))
    z = model.standardize(x)
    np.testing.assert_allclose(z, (x - model.feature_mean) / model.feature_scale, rtol=1e-5)
    distances = model.scorer().distances(z[0], z)
    assert distances[0] == 0 and (distances[1:] > 0).all()


def test_truncated_file_is_one_clear_line(tmp_path):
    path = make_model().save(tmp_path / "model.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelFileError, match="truncated or corrupt") as error:
        load_model(path)
    assert "\n" not in str(error.value)


def test_missing_file(tmp_path):
    with pytest.raises(ModelFileError, match="does not exist"):
        load_model(tmp_path / "nope.npz")


def test_foreign_npz_is_refused(tmp_path):
    path = tmp_path / "foreign.npz"
    np.savez(path, weights=np.ones(3))
    with pytest.raises(ModelFileError, match="not a vbrl_ros model"):
        load_model(path)


def _zip_of_text(path):
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("readme.txt", "not arrays")


@pytest.mark.parametrize("name, write, reason", [
    ("notes.txt", lambda p: p.write_text("model_path: /data/model.npz\n"), "it is a text file"),
    ("noise.npz", lambda p: p.write_bytes(np.random.default_rng(0).bytes(4096)), "not an .npz archive"),
    ("plain.zip", _zip_of_text, "a zip archive, not an .npz"),
    ("array.npy", lambda p: np.save(p, np.ones(3)), "a single .npy array"),
    ("other.npz", lambda p: np.savez(p, weights=np.ones(3)),
     "without the format tag 'vbrl_ros.model'; it holds weights"),
    ("keyframes.npz", lambda p: np.savez(p, format=np.array("vbrl_ros.keyframes")),
     "its format tag is 'vbrl_ros.keyframes'"),
])
def test_a_file_that_is_not_a_model_says_so_in_one_line(tmp_path, name, write, reason):
    path = tmp_path / name
    write(path)
    with pytest.raises(ModelFileError) as error:
        load_model(path)
    message = str(error.value)
    assert message.startswith(f"{path} is not a vbrl_ros model file (") and reason in message
    assert "\n" not in message and "allow_pickle" not in message


def test_pickled_content_is_never_loaded(tmp_path):
    path = tmp_path / "pickled.npz"
    np.savez(path, format=np.array("vbrl_ros.model"), format_version=np.array(1),
             W=np.array([{"evil": 1}], dtype=object))
    with pytest.raises(ModelFileError, match="pickled object arrays, which are never loaded"):
        load_model(path)


def test_other_version_is_refused(tmp_path):
    path = make_model().save(tmp_path / "model.npz")
    with np.load(path) as archive:
        contents = dict(archive)
    contents["format_version"] = np.array(99)
    np.savez(path, **contents)
    with pytest.raises(ModelFileError, match="version 99"):
        load_model(path)


def test_config_mismatch_names_the_setting(tmp_path):
    path = make_model().save(tmp_path / "model.npz")
    running = VBRLConfig(grid=VoxelGridConfig(cells_xy=8))
    with pytest.raises(ModelFileError, match=r"grid.cells_xy: 4 != 8"):
        load_model(path, expected_config=running)


def test_shape_inconsistent_with_config_is_refused(tmp_path):
    path = make_model().save(tmp_path / "model.npz")
    with np.load(path) as archive:
        contents = dict(archive)
    contents["W"] = contents["W"][:-5]
    np.savez(path, **contents)
    with pytest.raises(ModelFileError, match="W has shape"):
        load_model(path)


def test_non_finite_weights_are_refused():
    model = make_model()
    W = model.W.copy()
    W[0, 0] = np.nan
    with pytest.raises(ModelFileError, match="NaN"):
        VBRLModel(config=CONFIG, W=W, feature_mean=model.feature_mean,
                  feature_scale=model.feature_scale, lambda1=1, lambda2=1, scenarios=["a", "b"])


def test_identity_follows_content_not_file(tmp_path):
    model = make_model()
    again = load_model(model.save(tmp_path / "a.npz"))
    assert again.identity() == model.identity()
    assert make_model(seed=1).identity() != model.identity()


POLAR = VBRLConfig(grid=VoxelGridConfig(kind="polar", rings=3, sectors=6, max_range=20.0))


def test_polar_model_ties_voxel_weights_across_sectors(tmp_path):
    model = make_model(POLAR)
    layout = model.layout
    assert model.w_voxel.shape == (3 * POLAR.grid.n_layers,)  # one per (layer, ring) column
    assert model.w_voxel.sum() == pytest.approx(1.0)
    weights = model.row_weights()
    rows = layout.sector_rows
    np.testing.assert_array_equal(weights[rows], np.broadcast_to(weights[rows[0]], rows.shape))
    loaded = load_model(model.save(tmp_path / "polar.npz"), expected_config=POLAR)
    assert loaded.config == POLAR
    np.testing.assert_array_equal(loaded.w_voxel, model.w_voxel)
    with pytest.raises(ModelFileError, match="w_voxel"):
        VBRLModel(config=POLAR, W=model.W, feature_mean=model.feature_mean,
                  feature_scale=model.feature_scale, lambda1=1.0, lambda2=0.1,
                  scenarios=model.scenarios, w_modality=model.w_modality,
                  w_voxel=np.full(POLAR.grid.n_voxels, 1.0 / POLAR.grid.n_voxels))
    with pytest.raises(ModelFileError, match="grid.kind"):
        load_model(tmp_path / "polar.npz", expected_config=CONFIG)


THRESHOLD_RULE = "metadata_json: distance_threshold must be a finite number >= 0, got"
STEP_RULE = "metadata_json: translation_search must be a finite number in [0, 10], got"


def _metadata_with(**fields):
    return np.array(json.dumps({"scans": 12, **fields}))


@pytest.mark.parametrize("member, value, named", [
    ("scenarios_json", np.array(5), "bad 'scenarios_json'"),
    ("scenarios_json", np.array('{"a": 1}'), "scenarios_json must be a JSON list of names"),
    ("format_version", np.array([1, 1]), "bad 'format_version'"),
    ("lambda1", np.array("abc"), "bad 'lambda1'"),
    ("W", np.array("W"), "bad 'W'"),
    ("metadata_json", np.array("[1, 2]"), "metadata_json must be a JSON object"),
    ("metadata_json", np.array("{"), "metadata_json is not valid JSON"),
    ("metadata_json", _metadata_with(distance_threshold="low"), THRESHOLD_RULE),
    ("metadata_json", _metadata_with(distance_threshold=float("nan")), THRESHOLD_RULE),
    ("metadata_json", _metadata_with(distance_threshold=-1), THRESHOLD_RULE),
    ("metadata_json", _metadata_with(translation_search=True), STEP_RULE),
    ("metadata_json", _metadata_with(translation_search=50.0), STEP_RULE),
    ("w_voxel", None, "w_voxel must be non-negative"),
])
def test_a_malformed_field_is_one_line_naming_the_file_and_the_field(tmp_path, member, value, named):
    path = make_model().save(tmp_path / "model.npz")
    with np.load(path) as archive:
        contents = dict(archive)
    contents[member] = -contents[member] if value is None else value
    np.savez(path, **contents)
    with pytest.raises(ModelFileError) as error:
        load_model(path)
    message = str(error.value)
    assert message.startswith(str(path)) and named in message and "\n" not in message, message


def test_usable_metadata_loads(tmp_path):
    model = make_model()
    model.metadata.update(distance_threshold=0.25, translation_search=1.5, sources=["a.mcap"])
    loaded = load_model(model.save(tmp_path / "model.npz"))
    assert (loaded.distance_threshold(), loaded.translation_search()) == (0.25, 1.5)
