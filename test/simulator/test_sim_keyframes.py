"""Keyframe clouds: voxel thinning keeps one real return per voxel; ground removal drops exactly the ground."""

import math

import numpy as np
import pytest

from vbrl_ros.simulator.geometry import Material
from vbrl_ros.simulator.keyframes import KeyframeFilter
from vbrl_ros.simulator.lidar import LidarConfig
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.run import simulate_run
from vbrl_ros.simulator.town import TownConfig, generate_town

LOW_ROBOT = LidarConfig(beams=32, columns=1024)
INDICES = (3, 20)


@pytest.fixture(scope="module")
def town_and_route():
    town = generate_town(TownConfig(blocks_x=2, blocks_y=2), 0)
    return town, make_route(town, RouteConfig(loops=1, spacing_m=4.0, sensor_height_m=0.8))


def _run(town_and_route, keyframes=None, scenario="summer_clear"):
    town, route = town_and_route
    return simulate_run(town, route, LOW_ROBOT, scenario, seed=1, keyframes=keyframes)


def _voxels(points: np.ndarray, size: float) -> np.ndarray:
    return np.floor(points[:, :3].astype(np.float64) / size).astype(np.int64)


def _rows(points: np.ndarray) -> list[bytes]:
    return [row.tobytes() for row in points]


@pytest.mark.parametrize("voxel", [0.5, 1.0])
def test_thinning_keeps_the_return_nearest_each_voxels_centroid(town_and_route, voxel):
    raw_run, thin_run = _run(town_and_route), _run(town_and_route, KeyframeFilter(thin_voxel_m=voxel))
    for index in INDICES:
        raw, thin = raw_run.scan(index), thin_run.scan(index)
        kept = _voxels(thin.points, voxel)
        assert len(np.unique(kept, axis=0)) == len(kept)  # at most one point per voxel
        assert {tuple(v) for v in kept} == {tuple(v) for v in _voxels(raw.points, voxel)}  # no voxel lost
        assert len(thin.points) < len(raw.points) / (4 if voxel == 0.5 else 8)  # much smaller
        # Each kept point is a real return, with its own label and beam, in scan order.
        position = {row: k for k, row in enumerate(_rows(raw.points))}
        source = np.array([position[row] for row in _rows(thin.points)])
        assert np.all(np.diff(source) > 0)
        np.testing.assert_array_equal(thin.labels, raw.labels[source])
        np.testing.assert_array_equal(thin.rings, raw.rings[source])
        # ... and the one nearest its voxel's centroid, whatever the order of the points.
        raw_voxels, xyz = _voxels(raw.points, voxel), raw.points[:, :3].astype(np.float64)
        for k in source[:: max(1, len(source) // 50)]:
            members = xyz[np.all(raw_voxels == raw_voxels[k], axis=1)]
            gap = np.linalg.norm(members - members.mean(axis=0), axis=1)
            assert np.linalg.norm(xyz[k] - members.mean(axis=0)) == pytest.approx(gap.min(), abs=1e-9)
    shuffled = np.random.default_rng(0).permutation(len(raw.points))
    again = KeyframeFilter(thin_voxel_m=voxel).keep(raw.points[shuffled], raw.labels[shuffled])
    assert sorted(_rows(raw.points[shuffled][again])) == sorted(_rows(thin.points))


@pytest.mark.parametrize("scenario", ["summer_clear", "winter_snow"])
def test_ground_removal_drops_exactly_the_ground_surface(town_and_route, scenario):
    raw_run = _run(town_and_route, scenario=scenario)
    bare_run = _run(town_and_route, KeyframeFilter(remove_ground=True), scenario)
    for index in INDICES:
        raw, bare = raw_run.scan(index), bare_run.scan(index)
        ground_z = raw_run.scene_at(index).ground_z
        is_ground = np.isin(raw.labels, (Material.GROUND, Material.SNOW_GROUND))
        raw_height = raw.points_world()[:, 2] - ground_z
        # The labelled ground is the ground surface (within the range noise) and most of a low robot's scan.
        assert is_ground.mean() > 0.3 and np.abs(raw_height[is_ground]).max() < 0.15
        np.testing.assert_array_equal(bare.points, raw.points[~is_ground])
        np.testing.assert_array_equal(bare.labels, raw.labels[~is_ground])
        # Measured against the ground height, not the labels: what is left near it is the foot of walls,
        # poles and cars, a sliver of what was there.
        near_ground = np.abs(bare.points_world()[:, 2] - ground_z) < 0.05
        assert near_ground.sum() < 0.02 * (np.abs(raw_height) < 0.05).sum()
        assert len(bare.points) > 0.1 * len(raw.points)  # the scene above the ground stays


def test_ground_goes_before_thinning(town_and_route):
    raw_run = _run(town_and_route)
    both_run = _run(town_and_route, KeyframeFilter(thin_voxel_m=0.5, remove_ground=True))
    thin_only = _run(town_and_route, KeyframeFilter(thin_voxel_m=0.5))
    for index in INDICES:
        raw, both = raw_run.scan(index), both_run.scan(index)
        not_ground = ~np.isin(raw.labels, (Material.GROUND, Material.SNOW_GROUND))
        assert not np.isin(both.labels, (Material.GROUND, Material.SNOW_GROUND)).any()
        # Every voxel with anything above the ground keeps a point: thinning first would lose the
        # voxels whose first return was the road.
        expected = {tuple(v) for v in _voxels(raw.points[not_ground], 0.5)}
        assert {tuple(v) for v in _voxels(both.points, 0.5)} == expected
        kept_by_thin_only = thin_only.scan(index).labels
        assert (~np.isin(kept_by_thin_only, (Material.GROUND, Material.SNOW_GROUND))).sum() < len(both.points)


def test_the_default_filter_keeps_every_point(town_and_route):
    raw, kept = _run(town_and_route).scan(7), _run(town_and_route, KeyframeFilter()).scan(7)
    np.testing.assert_array_equal(kept.points, raw.points)
    np.testing.assert_array_equal(kept.labels, raw.labels)
    assert KeyframeFilter().keeps_everything and not KeyframeFilter(remove_ground=True).keeps_everything
    assert len(KeyframeFilter(thin_voxel_m=1.0, remove_ground=True).keep(np.zeros((0, 4), np.float32),
                                                                         np.zeros(0, np.uint8))) == 0


@pytest.mark.parametrize(("changes", "field"), [({"thin_voxel_m": 0.0}, "thin_voxel_m"),
                                                ({"thin_voxel_m": -1.0}, "thin_voxel_m"),
                                                ({"thin_voxel_m": math.inf}, "thin_voxel_m"),
                                                ({"thin_voxel_m": "0.5"}, "thin_voxel_m"),
                                                ({"remove_ground": 1}, "remove_ground")])
def test_bad_filters_name_the_field(changes, field):
    with pytest.raises(ValueError, match=field):
        KeyframeFilter(**changes)
