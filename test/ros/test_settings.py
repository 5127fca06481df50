from pathlib import Path

import pytest
import yaml

from vbrl_ros.detection.settings import DetectorSettings, SettingsError
from vbrl_ros.ros.settings import DESCRIPTIONS, NodeSettings, parameter_file, unknown_parameters

CONFIG = Path(__file__).resolve().parents[2] / "config" / "vbrl.yaml"


def test_yaml_defaults_equal_the_code_defaults():
    params = yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"]
    assert params == NodeSettings.defaults()
    assert NodeSettings.from_values(params) == NodeSettings()


def test_every_parameter_has_one_description_and_the_yaml_is_generated_from_them():
    assert list(DESCRIPTIONS) == NodeSettings.names()
    assert all(text.strip() for text in DESCRIPTIONS.values())
    assert CONFIG.read_text() == parameter_file(), (
        "config/vbrl.yaml is out of date: python -m vbrl_ros.ros.settings > config/vbrl.yaml")


def test_unknown_names_come_with_the_closest_known_one():
    assert unknown_parameters(["cloud_topics"]) == (
        "unknown parameter 'cloud_topics' (did you mean 'cloud_topic'?); vbrl_node --help lists them")
    message = unknown_parameters(["topk", "zzz"])
    assert message.startswith("unknown parameters 'topk' (did you mean 'top_k'?), 'zzz';")


@pytest.mark.parametrize(
    "name, value, message",
    [
        ("keyframe_distance", 0.0, "keyframe_distance"),
        ("keyframe_interval", -1.0, "keyframe_interval"),
        ("min_fitness", 1.5, "min_fitness"),
        ("top_k", 0, "top_k"),
        ("save_every", -3, "save_every"),
        ("session_id", -2, "session_id"),
        ("cloud_topic", "", "cloud_topic"),
        ("top_k", "five", "top_k"),
        ("verify", 1, "verify"),
        ("distance_threshold", float("nan"), "distance_threshold"),
        ("diagnostics_period", 1e-6, r"'diagnostics_period' must be in \[0.1, 3600.0\] seconds, got 1e-06"),
        ("diagnostics_period", 1e5, "diagnostics_period"),
        ("diagnostics_period", float("nan"), "diagnostics_period"),
        ("verification_voxel", 1e-9, r"'verification_voxel' must be in \[0.05, 10.0\] m, got 1e-09"),
        ("no_such_parameter", 1, "no_such_parameter"),
        ("index_candidates", -2, r"'index_candidates' must be -1 \(the default\) or >= 0, got -2"),
        ("index_refine_dim", 1.5, "index_refine_dim"),
        ("index_bound_shifts", -5, "index_bound_shifts"),
    ],
)
def test_bad_values_name_the_parameter(name, value, message):
    with pytest.raises(SettingsError, match=message):
        NodeSettings.from_values({name: value})


def test_integers_are_accepted_for_floats():
    assert NodeSettings.from_values({"keyframe_distance": 2}).keyframe_distance == 2.0


def test_detector_parameters_are_the_detector_settings():
    settings = NodeSettings.from_values({"top_k": 5, "distance_threshold": 0.25, "odom_topic": "/odom"})
    assert settings.detector == DetectorSettings(top_k=5, distance_threshold=0.25)
    assert settings.odom_topic == "/odom"
    assert NodeSettings().detector == DetectorSettings()
    assert "session" not in NodeSettings.defaults()  # the node derives it from session_id


def test_index_parameters_reach_the_index_and_minus_one_is_the_model_s_default():
    from vbrl_ros.ros.settings import index_parameters

    given = index_parameters(NodeSettings.from_values({"index_candidates": 64, "index_refine_dim": 0,
                                                       "descriptor_storage": "float16"}))
    assert (given.candidates, given.refine_dim, given.bound_shifts, given.storage) == (64, 0, None, "float16")
    default = index_parameters(NodeSettings())
    assert (default.candidates, default.refine_dim, default.bound_shifts) == (None, None, None)


@pytest.mark.parametrize("value", [[0.0] * 5, [0.0] * 7, [0.0, 0.0, 0.0, 0.0, 0.0, float("nan")],
                                   [True] * 6, "0 0 0 0 0 0", 0.0, ["0"] * 6])
def test_a_mounting_that_is_not_six_finite_numbers_names_the_parameter(value):
    with pytest.raises(SettingsError, match=r"^parameter 'odometry_lidar_pose' must be six finite numbers "
                                            r"\[x, y, z, roll, pitch, yaw\], got "):
        NodeSettings.from_values({"odometry_lidar_pose": value})


def test_a_mounting_comes_as_a_ros_double_or_integer_array():
    import array

    assert NodeSettings.from_values({"odometry_lidar_pose": array.array("d", [0.5, 0, 0.3, 0, 0, 3.1])}) \
        .odometry_lidar_pose == (0.5, 0.0, 0.3, 0.0, 0.0, 3.1)
    assert NodeSettings.from_values({"odometry_lidar_pose": [1, 0, 0, 0, 0, 0]}).odometry_lidar_pose == \
        (1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
