import pytest

from vbrl_ros.config import FeatureConfig, VBRLConfig, VoxelGridConfig


def test_defaults_match_the_paper_scale():
    config = VBRLConfig()
    assert config.grid.n_layers == 3  # bottom / middle / top
    assert config.grid.n_voxels == 8 * 8 * 3


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"extent_xy": 0.0}, "grid.extent_xy"),
        ({"extent_xy": float("nan")}, "grid.extent_xy"),
        ({"cells_xy": 0}, "grid.cells_xy"),
        ({"cells_xy": 2.5}, "grid.cells_xy"),
        ({"z_edges": (1.0,)}, "grid.z_edges"),
        ({"z_edges": (0.0, 2.0, 1.0)}, "grid.z_edges"),
    ],
)
def test_bad_grid_values_name_the_field(kwargs, name):
    with pytest.raises(ValueError, match=name):
        VoxelGridConfig(**kwargs)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"raster_size": 6}, "features.raster_size"),
        ({"hog_orientations": 0}, "features.hog_orientations"),
        ({"hog_cells": 3}, "features.hog_cells"),
        ({"min_points": 0}, "features.min_points"),
    ],
)
def test_bad_feature_values_name_the_field(kwargs, name):
    with pytest.raises(ValueError, match=name):
        FeatureConfig(**kwargs)


def test_dict_round_trip_and_differences():
    config = VBRLConfig(grid=VoxelGridConfig(cells_xy=10, z_edges=(-2, 0, 3)))
    again = VBRLConfig.from_dict(config.to_dict())
    assert again == config
    assert VBRLConfig().differences(config) == [
        "grid.cells_xy: 8 != 10",
        "grid.z_edges: [-3.0, -1.0, 1.0, 6.0] != [-2.0, 0.0, 3.0]",
    ]


def test_unknown_keys_are_refused():
    with pytest.raises(ValueError, match="grid.cell"):
        VBRLConfig.from_dict({"grid": {"cell": 3}})
    with pytest.raises(ValueError, match="unknown section"):
        VBRLConfig.from_dict({"solver": {}})
