"""Lane wander: a smooth, seeded lateral offset within its amplitude; the poses follow the driven line."""

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vbrl_ros.simulator.geometry import Material
from vbrl_ros.simulator.route import RouteConfig, make_route
from vbrl_ros.simulator.town import TownConfig, generate_town

AMPLITUDE = 1.5


@pytest.fixture(scope="module")
def town():
    return generate_town(TownConfig(blocks_x=3, blocks_y=3), 1)


def _lateral_offset(route, lane, max_turn_per_m=0.005):
    """Signed offset (right of travel) of each pose from the lane line ``lane`` (a densely sampled route
    without wander), and whether the lane is straight there (corners have no single lateral direction).
    Each pose is matched to the nearest lane point with the distance along the route as a third,
    down-weighted coordinate, so a street driven again (either way) is matched to the same pass."""
    expected_s = route.arc_length * lane.length_m / route.length_m
    _, nearest = cKDTree(np.column_stack([lane.positions[:, :2], 0.05 * lane.arc_length])).query(
        np.column_stack([route.positions[:, :2], 0.05 * expected_s]))
    yaw = lane.yaw[nearest]
    right = np.stack([np.sin(yaw), -np.cos(yaw)], axis=1)
    offset = np.einsum("ij,ij->i", route.positions[:, :2] - lane.positions[nearest, :2], right)
    turn = np.abs(np.gradient(np.unwrap(lane.yaw)) / np.gradient(lane.arc_length))
    straight = np.convolve(turn, np.ones(81) / 81, mode="same") < max_turn_per_m  # +-10 m of straight lane
    return offset, straight[nearest]


def test_two_seeds_wander_differently_within_the_amplitude(town):
    lane = make_route(town, RouteConfig(loops=3, spacing_m=0.25))
    offsets = {}
    for seed in (1, 2):
        route = make_route(town, RouteConfig(loops=3, spacing_m=1.0, lane_wander_m=AMPLITUDE, lane_wander_seed=seed))
        offset, straight = _lateral_offset(route, lane)
        assert straight.mean() > 0.6
        offset = offset[straight]
        assert np.abs(offset).max() < AMPLITUDE + 0.01
        assert np.abs(offset).max() > 0.6 * AMPLITUDE and np.std(offset) > 0.2 * AMPLITUDE  # it does wander
        offsets[seed] = np.interp(lane.arc_length, route.arc_length[straight], offset)
    difference = offsets[1] - offsets[2]
    assert 1.0 < np.abs(difference).max() < 2 * AMPLITUDE  # sessions differ laterally by up to ~1-3 m
    assert np.mean(np.abs(difference) > 0.5) > 0.2


def test_the_wander_is_smooth_over_tens_of_metres(town):
    lane = make_route(town, RouteConfig(loops=3, spacing_m=0.25))
    route = make_route(town, RouteConfig(loops=3, spacing_m=1.0, lane_wander_m=AMPLITUDE, lane_wander_seed=7))
    offset, straight = _lateral_offset(route, lane)
    runs = np.split(np.arange(len(offset)), np.flatnonzero(np.diff(straight.astype(int))) + 1)
    slopes, crossings, length = [], 0, 0.0
    for run in (r for r in runs if straight[r[0]] and len(r) > 40):
        o, s = offset[run], route.arc_length[run]
        slopes.append(np.abs(np.diff(o) / np.diff(s)).max())
        assert np.abs(np.diff(o, 2)).max() < 0.01  # no kinks at 1 m spacing
        crossings += int(np.sum(np.diff(np.sign(o - offset[straight].mean())) != 0))
        length += s[-1] - s[0]
        # Neighbouring metres are nearly the same offset, 5 m apart still closely related.
        if len(run) > 60:
            assert np.corrcoef(o[:-5], o[5:])[0, 1] > 0.8
    assert length > 500 and max(slopes) < 0.25  # never steering more than ~14 degrees off the lane
    # A correlation length of ~30 m: a few sign changes per hundred metres, not one per metre nor none.
    assert 2 <= crossings <= length / 15


def test_poses_follow_the_wandering_line(town):
    cfg = RouteConfig(loops=3, spacing_m=1.0, sensor_height_m=0.8, lane_wander_m=AMPLITUDE, lane_wander_seed=3)
    route = make_route(town, cfg)
    rotations = route.poses[:, :3, :3]
    np.testing.assert_allclose(rotations @ rotations.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rotations.shape),
                               atol=1e-12)
    np.testing.assert_allclose(route.positions[:, 2], 0.8)
    np.testing.assert_allclose(np.diff(route.arc_length), 1.0)
    step = np.diff(route.positions[:, :2], axis=0)
    assert np.all(np.linalg.norm(step, axis=1) <= 1.0 + 1e-9)  # chords of the line the poses lie on
    travel = np.arctan2(step[:, 1], step[:, 0])
    mid_yaw = np.arctan2(np.sin(route.yaw[:-1]) + np.sin(route.yaw[1:]), np.cos(route.yaw[:-1]) + np.cos(route.yaw[1:]))
    error = np.abs((travel - mid_yaw + np.pi) % (2 * np.pi) - np.pi)
    assert np.percentile(error, 99) < 0.01 and error.max() < 0.05  # the yaw is the wandering line's own
    assert np.abs(np.diff(np.unwrap(route.yaw))).max() < 0.5  # no yaw jumps, corners a little tighter
    # The sensor stays on the road and out of buildings and the town's parked cars.
    boxes = town.static.boxes
    solid = boxes.take(np.isin(boxes.material, (Material.BUILDING, Material.PARKED_CAR)))
    rel = route.positions[:, None, :2] - solid.center[None, :, :2]
    c, s = np.cos(solid.yaw), np.sin(solid.yaw)
    local = np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1]], axis=-1)
    assert not np.any(np.all(np.abs(local) < solid.half_size[None, :, :2], axis=-1))


def test_seeded_and_off_by_default(town):
    base = RouteConfig(loops=2, spacing_m=2.0)
    plain = make_route(town, base)
    # Without wander the seed is ignored: the lane is exactly today's.
    np.testing.assert_array_equal(make_route(town, RouteConfig(loops=2, spacing_m=2.0, lane_wander_seed=5)).poses,
                                  plain.poses)
    a = make_route(town, RouteConfig(loops=2, spacing_m=2.0, lane_wander_m=1.0, lane_wander_seed=5))
    b = make_route(town, RouteConfig(loops=2, spacing_m=2.0, lane_wander_m=1.0, lane_wander_seed=5))
    np.testing.assert_array_equal(a.poses, b.poses)
    assert a.loop_names == plain.loop_names and abs(a.length_m - plain.length_m) < 0.02 * plain.length_m


def test_the_lane_offset_sets_how_far_apart_opposite_passes_are(town):
    lane = make_route(town, RouteConfig(loops=3, spacing_m=0.25, lane_offset_m=0.0))
    for offset_m in (0.5, 2.0):
        route = make_route(town, RouteConfig(loops=3, spacing_m=1.0, lane_offset_m=offset_m))
        offset, straight = _lateral_offset(route, lane)
        np.testing.assert_allclose(offset[straight], offset_m, atol=0.02)


@pytest.mark.parametrize(("changes", "field"), [({"lane_wander_m": -0.1}, "lane_wander_m"),
                                                ({"lane_wander_m": 3.5}, "lane_wander_m"),
                                                ({"lane_wander_m": math.nan}, "lane_wander_m"),
                                                ({"lane_wander_seed": -1}, "lane_wander_seed"),
                                                ({"lane_wander_seed": 1.5}, "lane_wander_seed")])
def test_bad_wander_names_the_field(changes, field):
    with pytest.raises(ValueError, match=field):
        RouteConfig(**changes)
