"""A keyframe's trail: earlier keyframes merged in where odometry puts them, and only when that helps."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vbrl_ros.features.blind_wedges import BINS, azimuth_bins, blind_bins, empty_bins, sees_all_round
from vbrl_ros.features.session_trails import with_trail
from vbrl_ros.features.trail import (
    CONFIRM_RANGE_M,
    MAX_TRAIL_KEYFRAMES,
    TRAIL_POINTS,
    Trail,
    confirmed,
)


def pose_at(x: float, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T[:2, :2] = [[c, -s], [s, c]]
    T[:2, 3] = x, y
    return T


def walls(rng: np.random.Generator, count: int = 4000) -> np.ndarray:
    """(n, 3) world points: a ring of wall 12 m round the origin, 0–3 m high."""
    angle = rng.uniform(-np.pi, np.pi, count)
    return np.column_stack([12.0 * np.cos(angle), 12.0 * np.sin(angle), rng.uniform(0.0, 3.0, count)])


def seen_from(world: np.ndarray, pose: np.ndarray, without: tuple[float, float] | None = None) -> np.ndarray:
    """``world`` in the sensor frame of ``pose``; ``without``: an azimuth wedge (degrees) it misses."""
    inv = np.linalg.inv(pose)
    points = world @ inv[:3, :3].T + inv[:3, 3]
    if without is not None:
        azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
        points = points[~((azimuth >= without[0]) & (azimuth <= without[1]))]
    return points


def in_world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return points @ pose[:3, :3].T + pose[:3, 3]


def test_an_earlier_keyframe_lands_where_odometry_puts_it():
    rng = np.random.default_rng(0)
    world = walls(rng)
    # only the first keyframe sees it; beyond CONFIRM_RANGE_M, where nothing needs confirming
    post = np.array([[16.0, -8.0, z] for z in np.arange(0.0, 2.0, 0.25)])
    first, second = pose_at(0.0), pose_at(1.5, 0.2, yaw_deg=30.0)
    trail = Trail(3.0)
    trail.cloud(seen_from(np.vstack([world, post]), first), first)
    merged = trail.cloud(seen_from(world, second), second)
    placed = in_world(merged, second)
    gap = np.linalg.norm(placed[:, None, :2] - post[None, :, :2], axis=2).min(axis=0)
    assert gap.max() < 1e-4  # every post point, where it stands
    assert len(trail) == 2


def test_without_a_reach_pose_or_session_a_keyframe_is_described_alone():
    rng = np.random.default_rng(1)
    world = walls(rng)
    scans = [seen_from(world, pose_at(x)) for x in (0.0, 1.0)]
    alone = Trail(0.0)
    assert all(alone.cloud(s, pose_at(0.0)) is s for s in scans)
    unposed = Trail(3.0)
    unposed.cloud(scans[0], pose_at(0.0))
    assert unposed.cloud(scans[1], None) is scans[1] and len(unposed) == 0  # and the trail starts anew
    sessions = Trail(3.0)
    sessions.cloud(scans[0], pose_at(0.0), session="monday")
    assert sessions.cloud(scans[1], pose_at(1.0), session="tuesday") is scans[1]
    nan_pose = np.full((4, 4), np.nan)
    assert Trail(3.0).cloud(scans[0], nan_pose) is scans[0]


def test_keyframes_beyond_the_reach_are_forgotten_along_the_path_and_across_a_jump():
    rng = np.random.default_rng(2)
    world = walls(rng)
    trail = Trail(3.0)
    for x in (0.0, 1.0, 2.0, 3.0, 4.0):
        trail.cloud(seen_from(world, pose_at(x)), pose_at(x))
    assert len(trail) == 4  # 0 m is 4 m back
    # back and forth within a metre: little apart in a straight line, but far along the path
    wiggle = Trail(3.0)
    for x in (0.0, 1.0, 0.0, 1.0, 0.0):
        wiggle.cloud(seen_from(world, pose_at(x)), pose_at(x))
    assert len(wiggle) == 4
    # odometry reset: 50 m away without travelling between
    trail.cloud(seen_from(world, pose_at(50.0)), pose_at(50.0))
    assert len(trail) == 1


def test_no_more_than_the_cap_is_merged_however_short_the_spacing():
    rng = np.random.default_rng(3)
    world = walls(rng, 500)
    trail = Trail(3.0)
    for k in range(MAX_TRAIL_KEYFRAMES + 10):
        trail.cloud(seen_from(world, pose_at(0.01 * k)), pose_at(0.01 * k))
    assert len(trail) == MAX_TRAIL_KEYFRAMES


def test_a_forward_looking_scan_is_described_alone():
    rng = np.random.default_rng(4)
    world = walls(rng)
    cone = (-35.0, 35.0)
    trail = Trail(3.0)
    trail.cloud(seen_from(world, pose_at(0.0)), pose_at(0.0))
    ahead = seen_from(world, pose_at(1.0))
    azimuth = np.degrees(np.arctan2(ahead[:, 1], ahead[:, 0]))
    ahead = ahead[(azimuth >= cone[0]) & (azimuth <= cone[1])]
    assert trail.cloud(ahead, pose_at(1.0)) is ahead


def test_the_keyframes_blind_wedge_and_its_mirror_stay_empty_after_the_merge():
    rng = np.random.default_rng(5)
    world = walls(rng)
    trail = Trail(3.0)
    trail.cloud(seen_from(world, pose_at(0.0)), pose_at(0.0))  # saw all round
    blind = seen_from(world, pose_at(1.0), without=(135.0, 180.0))
    merged = trail.cloud(blind, pose_at(1.0))
    hidden = blind_bins(blind[:, :2])
    assert hidden.any()
    occupied = np.zeros_like(hidden)
    occupied[azimuth_bins(merged[:, :2])] = True
    assert not (occupied & hidden).any()
    assert not (occupied & np.roll(hidden, len(hidden) // 2)).any()
    assert len(merged) > 0 and occupied.sum() == (~(hidden | np.roll(hidden, len(hidden) // 2))).sum()


def test_with_trail_pairs_each_scan_with_the_cloud_it_is_described_by():
    rng = np.random.default_rng(6)
    world = walls(rng)
    poses = np.stack([pose_at(x) for x in (0.0, 1.0, 2.0)])
    scans = [seen_from(world, p) for p in poses]
    pairs = list(with_trail(scans, poses, 3.0))
    assert [p[0] is s for p, s in zip(pairs, scans)] == [True] * 3
    assert pairs[0][1] is scans[0] and all(len(c) != len(s) for (s, c) in pairs[1:])
    assert all(c is s for s, c in with_trail(scans, None, 3.0))  # no poses, no trail


@pytest.mark.parametrize("reach", [-1.0, float("nan"), float("inf")])
def test_a_bad_reach_is_refused(reach):
    with pytest.raises(ValueError, match="trail reach"):
        Trail(reach)


def test_a_dense_keyframe_is_described_alone_and_a_sparse_one_takes_what_it_lacks():
    rng = np.random.default_rng(7)
    dense_world = walls(rng, TRAIL_POINTS)
    trail = Trail(3.0)
    trail.cloud(seen_from(dense_world, pose_at(0.0)), pose_at(0.0))
    dense = seen_from(dense_world, pose_at(1.0))
    assert trail.cloud(dense, pose_at(1.0)) is dense
    assert len(trail) == 0  # and neither is kept
    sparse_trail = Trail(3.0)
    part = TRAIL_POINTS * 3 // 8
    shared = walls(rng, part)  # the same wall points from every pose: each confirms the others
    for x in (0.0, 0.5, 1.0, 1.5):
        sparse_trail.cloud(seen_from(shared, pose_at(x)), pose_at(x))
    sparse = seen_from(walls(rng, 1000), pose_at(2.0))
    # nearest first: two earlier keyframes whole, every second point of the third, then what fits of the fourth
    third = len(range(0, part, 2))
    room = TRAIL_POINTS - 1000 - 2 * part - third
    fourth = len(range(0, part, -(-part // room)))
    assert len(sparse_trail.cloud(sparse, pose_at(2.0))) == 1000 + 2 * part + third + fourth <= TRAIL_POINTS


def test_an_empty_keyframe_in_the_trail_adds_nothing_and_breaks_nothing():
    rng = np.random.default_rng(9)
    world = walls(rng)
    trail = Trail(3.0)
    trail.cloud(seen_from(world, pose_at(0.0)), pose_at(0.0))
    trail.cloud(np.zeros((0, 3), np.float32), pose_at(0.5))  # e.g. every return filtered out
    scan = seen_from(world, pose_at(1.0))
    assert len(trail.cloud(scan, pose_at(1.0))) == 2 * len(scan)


def test_a_keyframe_just_below_the_fill_takes_only_a_few_earlier_points():
    rng = np.random.default_rng(8)
    trail = Trail(3.0)
    trail.cloud(seen_from(walls(rng, TRAIL_POINTS - 10), pose_at(0.0)), pose_at(0.0))
    almost = seen_from(walls(rng, TRAIL_POINTS - 100), pose_at(1.0))
    assert TRAIL_POINTS - 100 < len(trail.cloud(almost, pose_at(1.0))) <= TRAIL_POINTS


@pytest.mark.parametrize(("beams", "scenario", "alone"),
                         [(32, "summer_clear", True), (32, "winter_snow", True), (16, "summer_clear", False)])
def test_a_spinning_scan_of_32_beams_is_dense_enough_to_be_described_alone(beams, scenario, alone):
    # merged, 32-beam scans in snow kept the flakes of earlier scans (docs/results/trail.md)
    sim = pytest.importorskip("vbrl_ros.simulator")
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=5)
    run = sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=1.0, max_scans=2)),
                           sim.LidarConfig(beams=beams, columns=1024), scenario, seed=1)
    first, second = run[0].points, run[1].points  # a run renders a scan each time it is read
    trail = Trail(3.0)
    trail.cloud(first, run.poses[0])
    described = trail.cloud(second, run.poses[1])
    assert (described is second) == alone
    assert alone or len(second) < len(described) <= TRAIL_POINTS


def test_an_earlier_keyframes_flakes_near_the_sensor_are_dropped_its_structure_kept():
    """Snow returns from new places in every scan: an earlier keyframe's lone points within
    CONFIRM_RANGE_M are dropped, its points beside another keyframe's kept, and the keyframe's
    own points and everything farther away kept as they are."""
    rng = np.random.default_rng(11)
    structure = walls(rng, 3000) * [0.7, 0.7, 1.0]  # a ring 8.4 m round: within the range
    far = walls(rng, 500) * [1.5, 1.5, 1.0]  # 18 m round: beyond it

    def flakes(count: int) -> np.ndarray:  # in the air, 2-8 m from the sensor
        r, a = np.sqrt(rng.uniform(4.0, 64.0, count)), rng.uniform(-np.pi, np.pi, count)
        return np.column_stack([r * np.cos(a), r * np.sin(a), rng.uniform(0.5, 3.0, count)])

    trail = Trail(3.0)
    earlier_flakes = flakes(40)  # light snow: ~0.06 flakes per cubic metre a scan
    trail.cloud(seen_from(np.vstack([structure, far, earlier_flakes]), pose_at(0.0)), pose_at(0.0))
    own = seen_from(np.vstack([structure, flakes(40)]), pose_at(0.5))
    placed = cKDTree(in_world(trail.cloud(own, pose_at(0.5)), pose_at(0.5)))

    def kept(points: np.ndarray) -> np.ndarray:
        return placed.query(points)[0] < 1e-4

    assert kept(in_world(own, pose_at(0.5))).all()  # its own points, flakes too
    assert kept(earlier_flakes).mean() < 0.2  # a few share a voxel with the keyframe's own flakes
    assert kept(far).all()  # seen once, but farther than the range
    assert kept(structure).all()  # what both saw


def test_confirmed_keeps_everything_without_earlier_points_near():
    points = np.array([[1.0, 2.0, 0.5], [30.0, 0.0, 1.0], [0.0, 20.0, 2.0]])
    assert confirmed(points, np.array([0, 0, 1])).all()
    assert confirmed(points[:0], np.zeros(0, np.int64)).shape == (0,)
    lone = confirmed(np.array([[1.0, 2.0, 0.5], [1.2, 2.1, 0.7], [5.0, 5.0, 1.0]]), np.array([0, 1, 1]))
    assert lone.tolist() == [True, True, False]  # beside the keyframe's own point / alone
    assert CONFIRM_RANGE_M > 6.0


def street(rng: np.random.Generator) -> np.ndarray:
    """(n, 3) world points: a 60 m street, walls 5 m either side (0–3 m high), ground between."""
    wall_x = rng.uniform(-40.0, 20.0, 3000)
    walls_ = np.column_stack([wall_x, rng.choice([-5.0, 5.0], 3000), rng.uniform(0.0, 3.0, 3000)])
    ground = np.column_stack([rng.uniform(-40.0, 20.0, 3000), rng.uniform(-5.0, 5.0, 3000), np.full(3000, -0.8)])
    return np.vstack([walls_, ground])


def behind_hidden(points: np.ndarray) -> np.ndarray:
    """``points`` without the 90° wedge behind the sensor that a mast hides."""
    return points[np.abs(np.degrees(np.arctan2(points[:, 1], points[:, 0]))) < 135.0]


def drive(trail: Trail, world: np.ndarray, xs: np.ndarray, blind: bool = True) -> list:
    """(hidden cloud, all-round cloud or None) of each keyframe driven down the street at ``xs``."""
    out = []
    for x in xs:
        scan = seen_from(world, pose_at(float(x)))
        out.append(trail.clouds(behind_hidden(scan) if blind else scan, pose_at(float(x)))[:2])
    return out


def test_a_wedge_the_forward_trail_fills_whole_is_described_all_round_as_well():
    world = street(np.random.default_rng(5))
    xs = np.arange(-30.0, 0.5, 1.0)
    filled = drive(Trail(3.0, 60.0, fill_blind_wedges=True), world, xs)
    plain = drive(Trail(3.0, 60.0), world, xs)
    hidden, all_round = filled[-1]
    assert all_round is not None
    wedge = np.abs(np.degrees(np.arange(BINS) * 2 * np.pi / BINS - np.pi) + 2.5) > 137.5  # the bins behind
    assert empty_bins(hidden[:, :2])[wedge].all() and not empty_bins(all_round[:, :2])[wedge].any()
    # what fills the wedge is the street behind, where odometry puts it
    behind = all_round[np.abs(np.degrees(np.arctan2(all_round[:, 1], all_round[:, 0]))) > 150.0]
    assert len(behind) > 100
    gap, _ = cKDTree(world).query(in_world(behind, pose_at(0.0)))
    assert gap.max() < 1e-3
    # the described cloud is the one it always was; without the option nothing is described all round
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(filled, plain))
    assert all(c is None for _, c in plain)
    assert filled[0][1] is None  # the first keyframe has nothing to fill its wedge from


def test_no_all_round_cloud_for_a_keyframe_that_sees_all_round_or_a_wedge_left_open():
    world = street(np.random.default_rng(6))
    xs = np.arange(-30.0, 0.5, 1.0)
    assert all(c is None for _, c in drive(Trail(3.0, 60.0, fill_blind_wedges=True), world, xs, blind=False))
    # standing still, as a session starts: the keyframes before saw what it sees, its wedge stays open
    standing = drive(Trail(3.0, 60.0, fill_blind_wedges=True), world, np.full(5, -30.0))
    assert all(c is None for _, c in standing)


def test_a_wedge_the_trail_fills_in_part_is_described_all_round_with_the_rest_left_open():
    # no ground, and beside the street behind the sensor an open lot on its right: nothing there
    # for any keyframe to see, so half the wedge stays empty whatever the trail holds
    world = street(np.random.default_rng(9))
    world = world[(world[:, 2] > -0.5) & ~((world[:, 1] < 0.0) & (world[:, 0] < -3.0))]
    xs = np.arange(-30.0, 0.5, 1.0)
    hidden, all_round = drive(Trail(3.0, 60.0, fill_blind_wedges=True), world, xs)[-1]
    assert all_round is not None
    azimuth = np.degrees(np.arange(BINS) * 2 * np.pi / BINS - np.pi) + 2.5  # bin centres
    left_half, right_half = (azimuth > 137.5) & (azimuth < 172.5), (azimuth < -137.5) & (azimuth > -172.5)
    assert empty_bins(hidden[:, :2])[left_half].all()
    assert not empty_bins(all_round[:, :2])[left_half].any()  # the wall behind on the left, filled
    assert empty_bins(all_round[:, :2])[right_half].all()  # the open lot: nothing to fill it with
    assert blind_bins(all_round[:, :2])[right_half].all()  # a blind run is left: the featurizer hides it


def test_points_above_the_keyframes_own_field_of_view_do_not_fill_it():
    rng = np.random.default_rng(7)
    world = street(rng)
    tower = np.column_stack([np.full(400, -12.0), rng.uniform(-1.0, 1.0, 400), rng.uniform(0.0, 30.0, 400)])
    xs = np.arange(-30.0, 0.5, 1.0)
    hidden, all_round = drive(Trail(3.0, 60.0, fill_blind_wedges=True), world, xs)[-1]
    _, with_tower = drive(Trail(3.0, 60.0, fill_blind_wedges=True), np.vstack([world, tower]), xs)[-1]
    assert all_round is not None and with_tower is not None
    top = np.arctan2(hidden[:, 2], np.hypot(hidden[:, 0], hidden[:, 1])).max()
    elevation = np.arctan2(with_tower[:, 2], np.hypot(with_tower[:, 0], with_tower[:, 1]))
    assert elevation.max() <= top + 1e-3


def test_a_dense_keyframe_is_described_alone_but_still_fills_its_wedge():
    rng = np.random.default_rng(8)
    world = street(rng)
    dense = np.vstack([world, *(world + rng.normal(0.0, 0.05, world.shape) for _ in range(11))])  # ~28k seen
    xs = np.arange(-30.0, 0.5, 1.0)
    filled = drive(Trail(3.0, 60.0, fill_blind_wedges=True), dense, xs)
    plain = drive(Trail(3.0, 60.0), dense, xs)
    scan = behind_hidden(seen_from(dense, pose_at(0.0)))
    assert len(scan) >= TRAIL_POINTS
    hidden, all_round = filled[-1]
    assert hidden is not None and np.array_equal(hidden, scan)  # described alone, as always
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(filled, plain))
    assert all_round is not None and len(all_round) > len(scan)
    wedge = np.abs(np.degrees(np.arange(BINS) * 2 * np.pi / BINS - np.pi) + 2.5) > 137.5
    assert not empty_bins(all_round[:, :2])[wedge].any()


def test_whether_a_described_cloud_sees_all_round_is_told_as_counting_its_bins_would():
    rng = np.random.default_rng(10)
    world = street(rng)
    dense = np.vstack([world, *(world + rng.normal(0.0, 0.05, world.shape) for _ in range(11))])
    cone = lambda points: points[np.abs(np.degrees(np.arctan2(points[:, 1], points[:, 0]))) < 35.0]  # noqa: E731
    told = []
    for scene, view in ((world, behind_hidden), (world, lambda p: p), (dense, lambda p: p), (dense, behind_hidden),
                        (world, cone)):
        trail = Trail(3.0, 60.0, fill_blind_wedges=True)
        for x in np.arange(-30.0, 0.5, 2.0):
            described, _, sees = trail.clouds(view(seen_from(scene, pose_at(float(x)))), pose_at(float(x)))
            assert sees is None or sees == sees_all_round(described)
            told.append(sees)
    # the trail knows it for every keyframe that sees around, either way; not for a forward-looking one
    assert told.count(True) >= 30 and told.count(False) >= 30 and 0 < told.count(None) <= 16
    assert Trail(3.0, 60.0, fill_blind_wedges=True).clouds(world, None).sees_all_round is None  # no pose
