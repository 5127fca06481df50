"""Scenarios: determinism, weather, seasons, traffic and parking differ per run."""

import numpy as np
import pytest

from vbrl_ros.simulator.geometry import Material
from vbrl_ros.simulator.lidar import LidarConfig
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.run import simulate_run
from vbrl_ros.simulator.scenarios import SCENARIO_PRESETS, Scenario
from vbrl_ros.simulator.town import TownConfig, generate_town

LIDAR = LidarConfig(beams=32, columns=900)
QUIET = dict(moving_cars_per_km=0.0, pedestrians_per_km=0.0, parked_turnover=0.0)


@pytest.fixture(scope="module")
def town_and_route():
    town = generate_town(TownConfig(blocks_x=3, blocks_y=3), 21)
    return town, make_route(town, RouteConfig(loops=2, spacing_m=10.0))


def _scans(town, route, scenario, seed, indices):
    run = simulate_run(town, route, LIDAR, scenario, seed)
    return [run.scan(i) for i in indices]


def test_same_seeds_give_bit_identical_scans_in_any_order(town_and_route):
    town, route = town_and_route
    forward = _scans(town, route, "winter_snow", 5, [2, 7])
    # A fresh town and run, scans read in the other order.
    town_again = generate_town(TownConfig(blocks_x=3, blocks_y=3), 21)
    backward = _scans(town_again, make_route(town_again, RouteConfig(loops=2, spacing_m=10.0)), "winter_snow", 5,
                      [7, 2])[::-1]
    for a, b in zip(forward, backward):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.labels, b.labels)
        assert a.stamp == b.stamp
    other = _scans(town, route, "winter_snow", 6, [2])[0]
    assert len(other.points) != len(forward[0].points) or not np.array_equal(other.points, forward[0].points)


def test_iteration_matches_random_access(town_and_route):
    town, route = town_and_route
    short = make_route(town, RouteConfig(loops=1, spacing_m=10.0, max_scans=3))
    run = simulate_run(town, short, LIDAR, "autumn_fog", 1)
    iterated = list(run)
    assert len(iterated) == len(run) == 3
    np.testing.assert_array_equal(iterated[1].points, run[1].points)
    np.testing.assert_array_equal(run.point_clouds()[2], run.scan(-1).points)
    np.testing.assert_array_equal(run.poses, short.poses)


def _pooled(town, route, scenario, seed=3, indices=(1, 5, 9, 13)):
    scans = _scans(town, route, scenario, seed, indices)
    return np.concatenate([s.points for s in scans]), np.concatenate([s.labels for s in scans])


@pytest.mark.parametrize("weather", ["fog", "snow"])
def test_bad_weather_adds_near_returns_and_drops_far_ones(town_and_route, weather):
    town, route = town_and_route
    clear_pts, clear_labels = _pooled(town, route, Scenario("summer", "clear", **QUIET))
    bad_pts, bad_labels = _pooled(town, route, Scenario("summer", weather, **QUIET))
    assert not np.any(clear_labels == Material.CLUTTER)
    clear_range = np.linalg.norm(clear_pts[:, :3], axis=1)
    bad_range = np.linalg.norm(bad_pts[:, :3], axis=1)
    # Spurious returns in the air near the sensor (within 3 m, above the ground at z = -1.8).
    near_clear = np.sum((clear_range < 3) & (clear_pts[:, 2] > -1.6))
    near_bad = np.sum((bad_range < 3) & (bad_pts[:, 2] > -1.6))
    assert near_bad > 1.3 * near_clear
    assert np.sum(bad_labels == Material.CLUTTER) > 1000
    # Dropouts and extinction: fewer returns from far away.
    assert np.sum(bad_range > 30) < 0.9 * np.sum(clear_range > 30)


def test_snow_covers_the_ground(town_and_route):
    town, route = town_and_route
    clear_pts, clear_labels = _pooled(town, route, Scenario("winter", "clear", **QUIET))
    snow_pts, snow_labels = _pooled(town, route, Scenario("winter", "snow", **QUIET))
    assert not np.any(clear_labels == Material.SNOW_GROUND)
    assert not np.any(snow_labels == Material.GROUND)
    assert snow_pts[snow_labels == Material.SNOW_GROUND, 3].mean() > 3 * clear_pts[clear_labels == Material.GROUND,
                                                                                   3].mean()


def test_winter_removes_deciduous_foliage_but_keeps_evergreens(town_and_route):
    town, route = town_and_route
    _, summer = _pooled(town, route, Scenario("summer", "clear", **QUIET))
    _, winter = _pooled(town, route, Scenario("winter", "clear", **QUIET))
    foliage_summer, foliage_winter = np.sum(summer == Material.FOLIAGE), np.sum(winter == Material.FOLIAGE)
    assert foliage_summer > 1000
    assert foliage_winter < 0.15 * foliage_summer
    conifer_summer, conifer_winter = np.sum(summer == Material.CONIFER), np.sum(winter == Material.CONIFER)
    assert conifer_winter > 0.9 * conifer_summer  # (even more: no deciduous crowns in front of them)
    # Bare crowns uncover trunks and what stands behind the trees.
    assert np.sum(winter == Material.TRUNK) > np.sum(summer == Material.TRUNK)


def test_traffic_and_parking_differ_between_runs_and_move_in_time(town_and_route):
    town, route = town_and_route
    run_a = simulate_run(town, route, LIDAR, "summer_clear", 1)
    run_b = simulate_run(town, route, LIDAR, "summer_clear", 2)
    assert len(run_a.moving_cars.speed) > 5 and len(run_a.pedestrians.speed) > 5
    xy_a, _ = run_a.moving_cars.positions(0.0)
    xy_b, _ = run_b.moving_cars.positions(0.0)
    assert xy_a.shape != xy_b.shape or not np.allclose(xy_a, xy_b)
    later, _ = run_a.moving_cars.positions(1.0)
    moved = np.linalg.norm(later - xy_a, axis=1)
    wrapped = moved > 20  # reappeared at the other end of its street
    assert np.all((moved[~wrapped] > 3.9) & (moved[~wrapped] < 12.1)) and wrapped.mean() < 0.3  # 4-12 m/s
    parked_a = run_a.scene_at(0).boxes.material == Material.PARKED_CAR
    parked_b = run_b.scene_at(0).boxes.material == Material.PARKED_CAR
    centres_a = run_a.scene_at(0).boxes.center[parked_a]
    centres_b = run_b.scene_at(0).boxes.center[parked_b]
    assert centres_a.shape != centres_b.shape or not np.allclose(centres_a, centres_b)
    # Dynamic objects show up in the scans, with different points per run.
    dynamic = [Material.MOVING_CAR, Material.PEDESTRIAN]
    seen_a = sum(np.sum(np.isin(run_a.scan(i).labels, dynamic)) for i in range(0, len(run_a), 12))
    seen_b = sum(np.sum(np.isin(run_b.scan(i).labels, dynamic)) for i in range(0, len(run_b), 12))
    assert seen_a > 0 and seen_b > 0 and seen_a != seen_b


def test_static_preset_reproduces_the_reference_parking(town_and_route):
    town, route = town_and_route
    run = simulate_run(town, route, LIDAR, "static", 9)
    boxes = run.scene_at(0).boxes
    reference = town.parked_cars.take(town.parked_occupied)
    np.testing.assert_array_equal(boxes.center[boxes.material == Material.PARKED_CAR], reference.center)
    assert not np.any(boxes.material == Material.MOVING_CAR)


def test_presets_and_free_combinations():
    assert {"summer_clear", "winter_snow", "autumn_fog", "static"} <= set(SCENARIO_PRESETS)
    assert Scenario.from_name("winter_snow") is SCENARIO_PRESETS["winter_snow"]
    free = Scenario.from_name("spring_fog")
    assert (free.season, free.weather, free.name) == ("spring", "fog", "spring_fog")
    assert Scenario.from_name("summer_clear").seed_salt != Scenario.from_name("winter_snow").seed_salt
    with pytest.raises(ValueError, match="unknown scenario"):
        Scenario.from_name("monsoon")


@pytest.mark.parametrize(
    ("changes", "field"),
    [({"season": "monsoon"}, "season"), ({"weather": "hail"}, "weather"),
     ({"moving_cars_per_km": -1.0}, "moving_cars_per_km"), ({"parked_turnover": 2.0}, "parked_turnover"),
     ({"name": "a/b"}, "name")],
)
def test_bad_scenario_names_the_field(changes, field):
    with pytest.raises(ValueError, match=field):
        Scenario(**changes)


def test_bad_run_seed_is_rejected(town_and_route):
    town, route = town_and_route
    with pytest.raises(ValueError, match="seed"):
        simulate_run(town, route, LIDAR, "summer_clear", -3)
    with pytest.raises(IndexError):
        simulate_run(town, route, LIDAR, "summer_clear", 0).scan(len(route))
