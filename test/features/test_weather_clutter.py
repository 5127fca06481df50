"""Lone returns from rain or snow near the sensor leave the height map; real structure stays."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from vbrl_ros.detection.registration import downsample_for_storage
from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.features.height_map import CELL_M, map_side
from vbrl_ros.features.weather_clutter import CLUTTER_RANGE_M, drop_lone_tops
from vbrl_ros.training.presets import recognition_config

sim = pytest.importorskip("vbrl_ros.simulator")

REACH = 20.0
SIDE = map_side(REACH, CELL_M)


def ground_map(every: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """(top, second) of a flat ground the sensor sampled in every ``every``-th column."""
    top = np.full(SIDE * SIDE, -1.0)
    iy, ix = np.divmod(np.arange(SIDE * SIDE), SIDE)
    sampled = (iy % every == 0) & (ix % every == 0)
    top[sampled] = 0.05
    return top, np.full(SIDE * SIDE, -1.0)


def column(x: float, y: float) -> int:
    return int((y + REACH) / CELL_M) * SIDE + int((x + REACH) / CELL_M)


def after(top: np.ndarray, second: np.ndarray) -> np.ndarray:
    return drop_lone_tops(top, second, SIDE, 1, CELL_M, REACH)


def test_a_lone_point_in_the_air_over_densely_sampled_ground_is_dropped():
    top, second = ground_map()
    drop = column(4.0, 1.0)
    top[drop] = 1.7  # a rain return above a ground column
    second[drop] = 0.05
    out = after(top, second)
    assert out[drop] == 0.05  # the column keeps the ground below it
    unchanged = np.ones(len(top), bool)
    unchanged[drop] = False
    assert np.array_equal(out[unchanged], top[unchanged])


def test_a_lone_point_with_nothing_below_it_empties_its_column():
    top, second = ground_map()
    drop = column(-3.0, 5.0)
    top[drop] = 2.2
    assert after(top, second)[drop] < 0


def test_structure_stays():
    top, second = ground_map()
    pole, wall, far = column(3.0, -2.0), [column(-6.0, y) for y in np.arange(-2, 2, CELL_M)], column(15.0, 0.0)
    top[pole], second[pole] = 3.0, 2.8  # a pole: its column holds points below its top
    top[wall] = 2.5  # a wall: each top has neighbours as high
    top[far] = 1.5  # beyond the range where airborne returns come from
    out = after(top, second)
    assert out[pole] == 3.0 and np.all(out[wall] == 2.5) and out[far] == 1.5
    assert 15.0 > CLUTTER_RANGE_M


def test_a_lone_point_where_the_sensor_sampled_sparsely_stays():
    # a sparse sensor or a keyframe thinned to a voxel leaves real structure as alone as a
    # rain return; there the ground around it is sparse too
    top, second = ground_map(every=5)
    keep = column(4.0, 1.0)
    top[keep] = 1.7
    assert after(top, second)[keep] == 1.7


# -- on ray-cast scans ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def clear_and_rain():
    """The same five places ray-cast by a 64-beam sensor in clear weather and in rain."""
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)
    route = sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=20.0))
    lidar = sim.LidarConfig(beams=64, columns=1024)
    clear, rain = (sim.simulate_run(town, route, lidar, scenario, seed=1) for scenario in ("summer_clear", "summer_rain"))
    return [(clear.scan(i).points[:, :3].astype(np.float64), rain.scan(i).points[:, :3].astype(np.float64))
            for i in range(5)]


def recognition(drop_clutter: bool) -> Featurizer:
    config = recognition_config()
    return Featurizer(dataclasses.replace(config, features=dataclasses.replace(config.features,
                                                                                drop_weather_clutter=drop_clutter)))


def l1(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).sum())


def test_rain_moves_a_descriptor_less_once_its_clutter_is_dropped(clear_and_rain):
    kept, dropped = recognition(False), recognition(True)
    before = [l1(kept.describe(clear), kept.describe(rain)) for clear, rain in clear_and_rain]
    after_dropping = [l1(dropped.describe(clear), dropped.describe(rain)) for clear, rain in clear_and_rain]
    # rain also drops and blurs returns, which stays; the clutter was a fifth of the change
    assert all(a < b for a, b in zip(after_dropping, before))
    assert np.mean(after_dropping) < 0.85 * np.mean(before)


def test_the_compiled_map_drops_what_the_numpy_reference_drops(clear_and_rain):
    dropped, kept = recognition(True), recognition(False)
    for _, rain in clear_and_rain[:2]:
        points = dropped.frame(rain).apply(rain)
        compiled, reference = dropped.modalities(points), dropped.modalities_numpy(points)
        assert all(np.array_equal(a, b) for a, b in zip(compiled, reference))
        assert not np.array_equal(compiled[0], kept.modalities(points)[0])  # something was dropped


def test_a_thinned_keyframe_is_left_as_it_is(clear_and_rain):
    # one point per metre: the ground around any lone top is sparse, so nothing counts as clutter
    for _, rain in clear_and_rain:
        thinned = downsample_for_storage(rain, 1.0).astype(np.float64)
        assert np.array_equal(recognition(True).describe(thinned), recognition(False).describe(thinned))
