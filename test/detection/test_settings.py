import pytest

from vbrl_ros.detection.settings import DetectorSettings, SettingsError


@pytest.mark.parametrize("name, value", [("session", ""), ("distance_threshold", float("nan")),
                                         ("distance_threshold", -1.0), ("exclude_recent_s", -1.0),
                                         ("top_k", 0), ("max_closures", 0), ("min_fitness", 1.5),
                                         ("verification_voxel", 0.0), ("verification_voxel", 1e-9),
                                         ("verification_voxel", 20.0), ("verification_voxel", float("inf")),
                                         ("sequence_length", 0), ("sequence_length", 2.0),
                                         ("sequence_length", 21)])
def test_bad_values_name_the_setting(name, value):
    with pytest.raises(SettingsError, match=f"'{name}' must be"):
        DetectorSettings(**{name: value})


def test_zero_threshold_means_the_models_own():
    assert DetectorSettings().distance_threshold == 0.0
