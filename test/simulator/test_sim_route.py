"""Route: loops with same- and opposite-direction revisits, smooth level poses, sampling modes."""

import numpy as np
import pytest

from vbrl_ros.simulator.geometry import Material
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.town import TownConfig, generate_town


@pytest.fixture(scope="module")
def town():
    return generate_town(TownConfig(blocks_x=4, blocks_y=4), 2)


def _revisit_pairs(route, radius=3.0, min_gap=50):
    p, yaw = route.positions[:, :2], route.yaw
    dist = np.linalg.norm(p[:, None] - p[None], axis=2)
    idx = np.arange(len(p))
    close = (dist < radius) & (np.abs(idx[:, None] - idx[None]) > min_gap)
    heading = np.abs((yaw[:, None] - yaw[None] + np.pi) % (2 * np.pi) - np.pi)
    return close, heading


def test_route_revisits_places_in_both_directions(town):
    route = make_route(town, RouteConfig(loops=4, spacing_m=2.0))
    close, heading = _revisit_pairs(route)
    opposite = close & (heading > np.radians(150))
    same = close & (heading < np.radians(30))
    assert opposite.any(axis=1).sum() > 50
    assert same.any(axis=1).sum() > 20
    # Some places are seen only once: not every scan has a revisit.
    assert (~close.any(axis=1)).sum() > 50
    assert len(set(route.loop_index.tolist())) == 4 and len(route.loop_names) == 4


def test_poses_are_level_rigid_at_sensor_height_and_on_the_road(town):
    cfg = RouteConfig(loops=3, spacing_m=1.0, sensor_height_m=1.73)
    route = make_route(town, cfg)
    rotations = route.poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rotations.shape),
                               atol=1e-12)
    np.testing.assert_allclose(rotations[:, 2, 2], 1.0)
    np.testing.assert_allclose(route.positions[:, 2], 1.73)
    np.testing.assert_array_equal(route.poses[:, 3], np.broadcast_to([0, 0, 0, 1], (len(route), 4)))
    a, b = town.street_endpoints()
    ab = b - a
    p = route.positions[:, :2]
    t = np.clip(np.einsum("pkj,kj->pk", p[:, None] - a[None], ab) / np.einsum("kj,kj->k", ab, ab), 0, 1)
    to_street = np.linalg.norm(p[:, None] - (a[None] + t[..., None] * ab[None]), axis=2).min(axis=1)
    assert to_street.max() < town.config.curb_offset_m - 1.0  # stays on the road, corners included
    # The sensor never sits inside a building.
    boxes = town.static.boxes
    buildings = boxes.take(boxes.material == Material.BUILDING)
    rel = p[:, None] - buildings.center[None, :, :2]
    c, s = np.cos(buildings.yaw), np.sin(buildings.yaw)
    local = np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1]], axis=-1)
    assert not np.any(np.all(np.abs(local) < buildings.half_size[None, :, :2], axis=-1))


def test_heading_follows_the_path_smoothly(town):
    route = make_route(town, RouteConfig(loops=2, spacing_m=1.0))
    step = np.diff(route.positions[:, :2], axis=0)
    travel = np.arctan2(step[:, 1], step[:, 0])
    mid_yaw = route.yaw[:-1]
    error = np.abs((travel - mid_yaw + np.pi) % (2 * np.pi) - np.pi)
    assert np.percentile(error, 99) < 0.15
    turn_per_scan = np.abs(np.diff(np.unwrap(route.yaw)))
    assert turn_per_scan.max() < 0.3  # rounded corners, no yaw jumps
    assert np.abs(np.unwrap(route.yaw)[-1] - route.yaw[0]) > np.pi  # it does turn around blocks


def test_spacing_mode_and_rate_mode(town):
    by_distance = make_route(town, RouteConfig(loops=1, spacing_m=2.5))
    np.testing.assert_allclose(np.diff(by_distance.arc_length), 2.5)
    np.testing.assert_array_less(np.linalg.norm(np.diff(by_distance.positions, axis=0), axis=1), 2.5 + 1e-9)
    assert np.all(np.diff(by_distance.stamps) > 0)

    by_time = make_route(town, RouteConfig(loops=1, spacing_m=None, rate_hz=10.0, speed_mps=8.0, start_stamp=100.0))
    np.testing.assert_allclose(np.diff(by_time.stamps), 0.1, atol=1e-9)
    assert by_time.stamps[0] == pytest.approx(100.0)
    steps = np.linalg.norm(np.diff(by_time.positions, axis=0), axis=1)
    assert steps.max() <= 0.8 + 1e-6  # never faster than the cruise speed
    assert steps.min() < 0.6  # slows down in corners
    assert by_time.length_m == pytest.approx(by_distance.length_m, rel=0.01)


def test_sample_offset_interleaves_sessions(town):
    base = make_route(town, RouteConfig(loops=1, spacing_m=2.0))
    shifted = make_route(town, RouteConfig(loops=1, spacing_m=2.0, sample_offset_m=1.0))
    np.testing.assert_allclose(shifted.arc_length[:3], [1.0, 3.0, 5.0])
    nearest = np.linalg.norm(shifted.positions[:, None, :2] - base.positions[None, :, :2], axis=2).min(axis=1)
    assert np.median(nearest) == pytest.approx(1.0, abs=0.05)  # halfway between the other session's scans


def test_max_scans_truncates(town):
    route = make_route(town, RouteConfig(loops=2, max_scans=17))
    assert len(route) == 17 and route.poses.shape == (17, 4, 4) and route.stamps.shape == (17,)


def test_small_town_still_gets_loops():
    tiny = generate_town(TownConfig(blocks_x=1, blocks_y=1), 0)
    route = make_route(tiny, RouteConfig(loops=3, spacing_m=2.0))
    close, _ = _revisit_pairs(route)
    assert close.any(axis=1).sum() > 50  # the same block driven three times


@pytest.mark.parametrize(
    ("changes", "field"),
    [({"loops": 0}, "loops"), ({"spacing_m": None}, "spacing_m"), ({"rate_hz": 10.0}, "rate_hz"),
     ({"speed_mps": 0.0}, "speed_mps"), ({"lane_offset_m": -1.0}, "lane_offset_m"), ({"max_scans": 0}, "max_scans"),
     ({"sample_offset_m": -1.0}, "sample_offset_m")],
)
def test_bad_config_names_the_field(changes, field):
    with pytest.raises(ValueError, match=field):
        RouteConfig(**changes)


def test_home_outside_the_grid_is_rejected(town):
    with pytest.raises(ValueError, match="home"):
        make_route(town, RouteConfig(home=(9, 9)))
