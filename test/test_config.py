import json

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
        ({"mirror_blind_wedges": 1}, "features.mirror_blind_wedges"),
        ({"mirror_blind_wedges": True}, "features.mirror_blind_wedges"),  # the paper's modalities
        ({"trail_m": -1.0}, "features.trail_m"),
        ({"trail_m": float("nan")}, "features.trail_m"),
        ({"trail_m": 100.0}, "features.trail_m"),
        ({"trail_m": True}, "features.trail_m"),
        ({"fill_blind_wedges": True}, "features.fill_blind_wedges"),  # nothing mirrored, no forward trail
        ({"fill_blind_wedges": 1, "modalities": ("height",), "mirror_blind_wedges": True,
          "forward_trail_m": 60.0}, "features.fill_blind_wedges"),
        ({"fill_blind_wedges": True, "modalities": ("height",), "mirror_blind_wedges": True},
         "features.fill_blind_wedges"),
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


def test_mirrored_wedges_are_saved_only_when_on_so_older_models_keep_their_identity():
    plain = FeatureConfig(modalities=("height", "spectrum"), normalise=True)
    mirrored = FeatureConfig(modalities=("height", "spectrum"), normalise=True, mirror_blind_wedges=True)
    assert "mirror_blind_wedges" not in plain.to_dict()
    assert mirrored.to_dict()["mirror_blind_wedges"] is True
    assert FeatureConfig(**mirrored.to_dict()) == mirrored


def test_a_trail_is_saved_only_when_set_so_older_models_keep_their_identity():
    assert "trail_m" not in FeatureConfig().to_dict()
    trailed = FeatureConfig(trail_m=3.0)
    assert trailed.to_dict()["trail_m"] == 3.0
    assert FeatureConfig(**trailed.to_dict()) == trailed


def test_filled_wedges_are_saved_only_when_on_so_older_models_keep_their_identity():
    plain = FeatureConfig(modalities=("height",), mirror_blind_wedges=True, forward_trail_m=60.0)
    filled = FeatureConfig(modalities=("height",), mirror_blind_wedges=True, forward_trail_m=60.0,
                           fill_blind_wedges=True)
    assert "fill_blind_wedges" not in plain.to_dict()
    assert FeatureConfig(**filled.to_dict()) == filled


def test_unknown_keys_are_refused():
    with pytest.raises(ValueError, match="grid.cell"):
        VBRLConfig.from_dict({"grid": {"cell": 3}})
    with pytest.raises(ValueError, match="unknown section"):
        VBRLConfig.from_dict({"solver": {}})


# -- polar grid ------------------------------------------------------------------------

POLAR = VoxelGridConfig(kind="polar", rings=6, sectors=12, max_range=30.0, z_edges=(-2, 0, 4))


def test_polar_counts_rings_sectors_layers():
    assert POLAR.n_voxels == 6 * 12 * 2
    assert POLAR.ring_width == 5.0 and POLAR.n_sectors == 12
    assert VoxelGridConfig().n_sectors == 1  # Cartesian: one "sector"
    assert VoxelGridConfig(kind="polar").n_voxels == 8 * 24 * 3  # documented defaults


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"kind": "spherical"}, "grid.kind"),
        ({"kind": "polar", "sectors": 1}, "grid.sectors"),
        ({"kind": "polar", "sectors": 361}, "grid.sectors"),
        ({"kind": "polar", "sectors": 12.0}, "grid.sectors"),
        ({"kind": "polar", "rings": 0}, "grid.rings"),
        ({"kind": "polar", "rings": 257}, "grid.rings"),
        ({"kind": "polar", "max_range": 0.0}, "grid.max_range"),
        ({"kind": "polar", "max_range": float("inf")}, "grid.max_range"),
        ({"kind": "polar", "max_range": "40"}, "grid.max_range"),
        # settings the chosen grid does not read must stay at their defaults
        ({"kind": "polar", "cells_xy": 10}, "grid.cells_xy"),
        ({"kind": "polar", "extent_xy": 20.0}, "grid.extent_xy"),
        ({"rings": 4}, "grid.rings"),
        ({"max_range": 20.0}, "grid.max_range"),
    ],
)
def test_bad_polar_values_name_the_field(kwargs, name):
    with pytest.raises(ValueError, match=name):
        VoxelGridConfig(**kwargs)


def test_polar_round_trip_and_differences():
    config = VBRLConfig(grid=POLAR)
    data = config.to_dict()
    assert data["grid"] == {"z_edges": [-2.0, 0.0, 4.0], "kind": "polar", "rings": 6,
                            "sectors": 12, "max_range": 30.0}
    assert VBRLConfig.from_dict(json.loads(json.dumps(data))) == config
    assert VBRLConfig().differences(config) == [
        "grid.z_edges: [-3.0, -1.0, 1.0, 6.0] != [-2.0, 0.0, 4.0]",
        "grid.kind: 'cartesian' != 'polar'",
        "grid.rings: 8 != 6",
        "grid.sectors: 24 != 12",
        "grid.max_range: 40.0 != 30.0",
    ]


def test_cartesian_dict_is_unchanged_so_old_model_files_load_and_hash_alike():
    # exactly the keys written before polar grids existed (model identity hashes this dict)
    assert VBRLConfig().to_dict()["grid"] == {"extent_xy": 40.0, "cells_xy": 8,
                                              "z_edges": [-3.0, -1.0, 1.0, 6.0]}
    old = {"grid": {"extent_xy": 30.0, "cells_xy": 6, "z_edges": [-2.0, 1.0, 5.0]},
           "features": {"raster_size": 8, "hog_orientations": 9, "hog_cells": 1, "min_points": 3}}
    config = VBRLConfig.from_dict(old)
    assert config.grid.kind == "cartesian" and config.grid.n_voxels == 6 * 6 * 2
    assert config.to_dict() == old
