"""The height modality, normalised blocks, views from shifted viewpoints and the frame setting.

The compiled height map (:mod:`vbrl_ros.features.height_map`) is held to the numpy reference
bit for bit; the new settings must leave the paper's configuration (its dict and every model
identity hash built from it) exactly as it was.
"""

import hashlib
import json

import numpy as np
import pytest

from vbrl_ros.config import MODALITY_NAMES, FeatureConfig, VBRLConfig, VoxelGridConfig
from vbrl_ros.features.blind_wedges import mirrored_blind_bins
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.index.translation_search import view_offsets
from vbrl_ros.model.model_file import VBRLModel
from vbrl_ros.training.presets import recognition_config

sim = pytest.importorskip("vbrl_ros.simulator")

POLAR = VoxelGridConfig(kind="polar", rings=20, sectors=30, max_range=40.0, z_edges=(-3.0, -1.0, 1.0, 6.0))
CARTESIAN = VoxelGridConfig(extent_xy=40.0, cells_xy=8, z_edges=(-3.0, -1.0, 1.0, 6.0))
GROUND_POLAR = VoxelGridConfig(kind="polar", rings=20, sectors=30, max_range=40.0, z_edges=(0.0, 20.0),
                               frame="ground")
GROUND_CARTESIAN = VoxelGridConfig(extent_xy=40.0, cells_xy=20, z_edges=(0.0, 20.0), frame="ground")


@pytest.fixture(scope="module")
def run():
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)
    route = sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=2.0))
    return sim.simulate_run(town, route, sim.LidarConfig(beams=32, columns=512), "summer_clear", seed=1)


def featurizer(grid: VoxelGridConfig, modalities=("height",), min_points: int = 1,
               normalise: bool = False) -> Featurizer:
    return Featurizer(VBRLConfig(grid=grid, features=FeatureConfig(modalities=modalities, min_points=min_points,
                                                                   normalise=normalise)))


def framed(f: Featurizer, points: np.ndarray) -> np.ndarray:
    """The points in the featurizer's grid frame."""
    return f.frame(points).apply(points)


def distance(a: np.ndarray, b: np.ndarray) -> float:
    """L1 distance normalised to [0, 1]."""
    return float(np.abs(a - b).sum() / (np.abs(a).sum() + np.abs(b).sum()))


# -- the compiled path equals the numpy reference ---------------------------------------------


@pytest.mark.parametrize("grid", [POLAR, CARTESIAN, GROUND_POLAR], ids=["polar", "cartesian", "ground-polar"])
@pytest.mark.parametrize("modalities", [("height",), ("covariance", "height"), ("height", "occupancy", "hog_xy")])
def test_compiled_height_blocks_equal_the_numpy_reference(run, grid, modalities):
    """Every block, bit for bit, on three scans and three min_points; the height block is
    not trivially empty and min_points does thin it."""
    for min_points in (1, 3, 10):
        f = featurizer(grid, modalities, min_points)
        for k in (0, 40, 80):
            points = framed(f, run.scan(k).points)
            compiled, reference = f.modalities(points), f.modalities_numpy(points)
            assert [b.shape for b in compiled] == [(f.grid.n_voxels, n) for n in f.layout.features_per_modality]
            for a, b in zip(compiled, reference):
                np.testing.assert_array_equal(a, b)
    height = modalities.index("height")
    points = framed(f, run.scan(40).points)
    occupied = {m: int((featurizer(grid, modalities, m).modalities(points)[height] > 0).sum()) for m in (1, 10)}
    assert occupied[1] > 50 and occupied[10] < occupied[1]


def test_height_is_the_top_of_each_voxel_above_its_floor():
    """A hand-made cloud: the block holds each voxel's highest point above its layer's floor."""
    grid = VoxelGridConfig(extent_xy=8.0, cells_xy=4, z_edges=(-2.0, 0.0, 2.0))
    f = featurizer(grid)
    # voxel (layer 1, iy 2, ix 1): x [-4, 0), y [0, 4), z [0, 2)
    points = np.array([[-2.0, 1.0, 0.3], [-3.0, 2.5, 1.7], [-1.0, 3.0, 0.9], [5.0, -5.0, -1.5]])
    block = f.modalities(points)[0][:, 0]
    expected = np.zeros(grid.n_voxels)
    expected[(1 * 4 + 2) * 4 + 1] = 1.7
    expected[(0 * 4 + 0) * 4 + 3] = 0.5  # x [4, 8), y [-8, -4), z [-2, 0): 0.5 above -2
    np.testing.assert_allclose(block, expected, atol=1e-12)


# -- normalise -----------------------------------------------------------------------------------


@pytest.mark.parametrize("grid", [POLAR, CARTESIAN], ids=["polar", "cartesian"])
def test_normalise_gives_every_modality_block_unit_l1_norm(run, grid):
    f = featurizer(grid, ("covariance", "height", "occupancy"), 3, normalise=True)
    raw = featurizer(grid, ("covariance", "height", "occupancy"), 3)
    points = run.scan(60).points
    descriptor, unnormalised = f.describe(points), raw.describe(points)
    for m in range(f.layout.n_modalities):
        rows = f.layout.modality_slice(m)
        assert np.abs(descriptor[rows]).sum() == pytest.approx(1.0, rel=1e-5)
        assert np.abs(unnormalised[rows]).sum() > 2.0  # normalising did something
        np.testing.assert_allclose(descriptor[rows] * np.abs(unnormalised[rows]).sum(), unnormalised[rows],
                                   rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("grid", [POLAR, GROUND_POLAR], ids=["polar", "ground-polar"])
def test_an_empty_scan_stays_all_zero_when_normalised(grid):
    f = featurizer(grid, ("covariance", "height"), 3, normalise=True)
    for points in (np.zeros((0, 3)), np.full((5, 3), np.nan)):
        descriptor = f.describe(points)
        assert descriptor.shape == (f.dimension,) and np.isfinite(descriptor).all()
        assert not descriptor.any()


# -- views from shifted viewpoints --------------------------------------------------------------


@pytest.mark.parametrize("modalities", [("height",), ("covariance", "height")])
def test_the_view_from_the_sensor_is_the_descriptor(run, modalities):
    f = Featurizer(VBRLConfig(grid=GROUND_POLAR, features=FeatureConfig(modalities=modalities, min_points=1,
                                                                        normalise=True)))
    points = framed(f, run.scan(30).points)
    views = f.describe_views(points, [(0.0, 0.0)])
    assert views.shape == (1, f.dimension) and views.dtype == np.float32
    np.testing.assert_array_equal(views[0], f.describe_framed(points))
    assert f.describe_views(points, np.zeros((0, 2))).shape == (0, f.dimension)


def test_views_of_other_modalities_describe_the_shifted_points_exactly(run):
    f = featurizer(GROUND_POLAR, ("covariance", "height"), 3, normalise=True)
    points = framed(f, run.scan(30).points)
    views = f.describe_views(points, [(1.5, -0.5), (0.0, 3.0)])
    np.testing.assert_array_equal(views[0], f.describe_framed(points - [1.5, -0.5, 0.0]))
    np.testing.assert_array_equal(views[1], f.describe_framed(points - [0.0, 3.0, 0.0]))


@pytest.mark.parametrize("grid", [GROUND_POLAR, GROUND_CARTESIAN, POLAR], ids=["polar", "cartesian", "3-layer"])
@pytest.mark.parametrize("mirror", [False, True])
def test_every_view_equals_the_numpy_reference_from_its_viewpoint(run, grid, mirror):
    """Bit for bit: translation search's viewpoints, off-cell ones and one beyond the map's margin."""
    modalities = ("height", "spectrum") if grid.kind == "polar" else ("height",)
    f = Featurizer(VBRLConfig(grid=grid, features=FeatureConfig(modalities=modalities, min_points=2,
                                                                mirror_blind_wedges=mirror)))
    offsets = np.vstack([view_offsets(1.5), [(0.3, -0.1), (-2.75, 1.05), (0.0, 6.0)]])
    for k in (10, 60):
        points = framed(f, run.scan(k).points)
        if mirror:  # the sensor did not see behind it: there is a wedge to hide
            points = points[points[:, 0] > -np.abs(points[:, 1])]
            assert mirrored_blind_bins(points[:, :2]).any()
        views = f.describe_views(points, offsets)
        for view, offset in zip(views, offsets):
            reference = np.concatenate([b.ravel() for b in f.modalities_numpy(points, tuple(offset))])
            np.testing.assert_array_equal(view, reference.astype(np.float32))
        assert len({v.tobytes() for v in views}) == len(offsets)  # every view differs


@pytest.mark.parametrize("grid", [GROUND_POLAR, GROUND_CARTESIAN], ids=["polar", "cartesian"])
def test_a_view_is_close_to_describing_the_shifted_points(run, grid):
    """The view from (dx, dy) is the scan moved by (-dx, -dy) up to the 0.2 m map cells: far
    closer to it than the unshifted scan is, and than a place 20-30 m away."""
    f = featurizer(grid, normalise=True)
    offsets = np.array([(1.5, 0.0), (0.0, -3.0), (-1.5, 1.5), (0.3, 0.1)])
    for k in (10, 60, 120):
        points = framed(f, run.scan(k).points)
        views = f.describe_views(points, offsets)
        here = f.describe_framed(points)
        elsewhere = f.describe_framed(framed(f, run.scan(k + 15).points))
        far = distance(here, elsewhere)
        assert far > 0.6
        for view, (dx, dy) in zip(views, offsets):
            moved = f.describe_framed(points - [dx, dy, 0.0])
            d = distance(view, moved)
            assert d < 0.1 and d < 0.15 * far, (k, dx, dy, d, far)
            if abs(dx) + abs(dy) > 1.0:
                assert distance(here, moved) > max(0.1, 3 * d), (k, dx, dy, d)  # the view really moved
        # a whole number of map cells: the same map, moved
        assert distance(views[1], f.describe_framed(points - [0.0, -3.0, 0.0])) < 0.02


# -- configuration: the paper's unchanged, bad values refused --------------------------------


def test_the_paper_configuration_dict_is_unchanged():
    """No modalities / normalise / frame keys at their defaults: the dict models were hashed by."""
    assert VBRLConfig().to_dict() == {
        "grid": {"extent_xy": 40.0, "cells_xy": 8, "z_edges": [-3.0, -1.0, 1.0, 6.0]},
        "features": {"raster_size": 8, "hog_orientations": 9, "hog_cells": 1, "min_points": 3},
    }
    polar = VBRLConfig(grid=VoxelGridConfig(kind="polar")).to_dict()
    assert set(polar["grid"]) == {"z_edges", "kind", "rings", "sectors", "max_range"}
    assert set(polar["features"]) == {"raster_size", "hog_orientations", "hog_cells", "min_points"}


#: identity() of the deterministic model below, as computed before the height modality,
#: normalisation and the ground frame existed.
PINNED_IDENTITY = {"cartesian": "ab184285d932fb51", "polar": "923da0c6339bb786"}


@pytest.mark.parametrize("kind", ["cartesian", "polar"])
def test_the_identity_of_a_paper_configuration_model_is_stable(kind):
    config = VBRLConfig() if kind == "cartesian" else VBRLConfig(grid=VoxelGridConfig(kind="polar"))
    d = Featurizer(config).dimension
    model = VBRLModel(config, np.linspace(0.0, 1.0, 2 * d).reshape(d, 2), np.zeros(d), np.ones(d), 10.0, 0.1,
                      ["a", "b"])
    assert model.identity() == PINNED_IDENTITY[kind]
    digest = hashlib.sha256(json.dumps(config.to_dict(), sort_keys=True).encode()).hexdigest()
    assert digest != hashlib.sha256(json.dumps(recognition_config().to_dict(), sort_keys=True).encode()).hexdigest()


def test_new_settings_appear_in_the_dict_and_round_trip():
    config = recognition_config()
    data = config.to_dict()
    assert data["grid"]["frame"] == "ground"
    assert data["features"]["modalities"] == ["height", "spectrum"] and data["features"]["normalise"] is True
    assert VBRLConfig.from_dict(json.loads(json.dumps(data))) == config
    mixed = VBRLConfig(features=FeatureConfig(modalities=("height", "covariance")))
    assert VBRLConfig.from_dict(mixed.to_dict()) == mixed
    assert Featurizer(mixed).layout.features_per_modality == (1, 6)


@pytest.mark.parametrize("modalities", [("covariance", "bogus"), ("height", "height"), ()])
def test_invalid_modalities_are_refused_by_name(modalities):
    with pytest.raises(ValueError, match=r"features\.modalities"):
        FeatureConfig(modalities=modalities)
    with pytest.raises(ValueError, match=r"features\.modalities"):
        VBRLConfig.from_dict({"features": {"modalities": list(modalities)}})


def test_every_modality_name_is_accepted_alone():
    for name in MODALITY_NAMES:
        assert FeatureConfig(modalities=(name,)).modalities == (name,)


def test_an_unknown_frame_and_a_non_boolean_normalise_are_refused():
    with pytest.raises(ValueError, match=r"grid\.frame"):
        VoxelGridConfig(frame="bad")
    with pytest.raises(ValueError, match=r"features\.normalise"):
        FeatureConfig(normalise="yes")
