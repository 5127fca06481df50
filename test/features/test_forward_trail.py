"""A forward-looking keyframe's trail: the earlier keyframes that looked at where it stands."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from vbrl_ros.features.blind_wedges import empty_bins, sees_around
from vbrl_ros.features.forward_trail import MAX_POINTS, RANGE_M, STEP_M, VOXEL_M, ForwardTrail, thinned
from vbrl_ros.features.session_trails import with_trail
from vbrl_ros.features.trail import TRAIL_POINTS, Trail

HALF_FIELD_DEG = 35.0  # a 70° forward-looking sensor


def pose_at(x: float, y: float = 0.0, yaw_deg: float = 0.0) -> np.ndarray:
    """T_world_lidar of a level sensor at (x, y) heading ``yaw_deg``."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    T[:2, 3] = x, y
    return T


def in_world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return points @ pose[:3, :3].T + pose[:3, 3]


def street(rng: np.random.Generator, count: int = 60_000) -> np.ndarray:
    """(n, 3) world points: facades 6 m either side of a street along x, 0–8 m high, with posts of
    random heights along both kerbs, so each stretch differs from the next."""
    x = rng.uniform(-120.0, 120.0, count)
    side = rng.choice([-6.0, 6.0], count)
    facades = np.column_stack([x, side, rng.uniform(0.0, 8.0, count)])
    posts_x = np.arange(-120.0, 120.0, 3.0)
    tops = rng.uniform(0.5, 4.0, len(posts_x))
    posts = np.concatenate([np.column_stack([np.full(20, px), np.full(20, py), np.linspace(0.0, top, 20)])
                            for px, top in zip(posts_x, tops) for py in (-3.5, 3.5)])
    return np.vstack([facades, posts])


def crossing(rng: np.random.Generator) -> np.ndarray:
    """:func:`street` with a side street 12 m wide leaving it along +y at x = 0."""
    main = street(rng)
    main = main[~((main[:, 1] > 5.0) & (np.abs(main[:, 0]) < 6.0))]  # the gap the side street leaves
    side = street(rng)[:, [1, 0, 2]]  # along y
    return np.vstack([main, side[side[:, 1] > 6.0]])


def seen_ahead(world: np.ndarray, pose: np.ndarray, max_range: float = 60.0) -> np.ndarray:
    """``world`` in the frame of a forward-looking sensor at ``pose``: what lies within its 70° and range."""
    inv = np.linalg.inv(pose)
    points = (world @ inv[:3, :3].T + inv[:3, 3]).astype(np.float32)
    azimuth = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    distance = np.hypot(points[:, 0], points[:, 1])
    return points[(np.abs(azimuth) <= HALF_FIELD_DEG) & (distance <= max_range) & (distance > 0.5)]


def drive(world: np.ndarray, xs: np.ndarray, y: float, yaw_deg: float, reach_m: float) -> np.ndarray:
    """The world points the last of the keyframes at ``xs`` is described by."""
    poses = [pose_at(x, y, yaw_deg) for x in xs]
    *_, (_, cloud) = with_trail((seen_ahead(world, p) for p in poses), np.array(poses), 3.0, reach_m)
    return in_world(cloud, poses[-1])


def shared(a: np.ndarray, b: np.ndarray) -> float:
    """The fraction of ``a``'s points that ``b`` holds too (both drawn from the same world points)."""
    return float((cKDTree(b).query(a)[0] < 1e-3).mean())


def test_two_passes_either_way_describe_the_same_place_with_the_forward_trail():
    rng = np.random.default_rng(0)
    world = street(rng)
    there = np.arange(-60.0, 0.5, 1.0)  # driven along +x to x = 0
    back = np.arange(60.0, -0.5, -1.0)  # driven back along -x, 1 m to the side
    alone = drive(world, there, 0.0, 0.0, 0.0), drive(world, back, 1.0, 180.0, 0.0)
    trailed = drive(world, there, 0.0, 0.0, 60.0), drive(world, back, 1.0, 180.0, 60.0)
    assert shared(*alone) < 0.1  # through 70° the two passes look at opposite halves
    assert shared(*trailed) > 0.5 and shared(trailed[1], trailed[0]) > 0.5
    assert not sees_around(empty_bins(in_world(alone[0], np.linalg.inv(pose_at(0.0)))[:, :2]))
    assert sees_around(empty_bins(in_world(trailed[0], np.linalg.inv(pose_at(0.0)))[:, :2]))


def test_merged_points_stay_within_range_of_the_keyframe_and_the_budget():
    rng = np.random.default_rng(1)
    world = street(rng, 200_000)
    cloud = drive(world, np.arange(-80.0, 0.5, 1.0), 0.0, 0.0, 60.0)
    own = seen_ahead(world, pose_at(0.0))
    assert len(cloud) <= len(own) + MAX_POINTS
    earlier = cloud[~(cKDTree(own).query(cloud)[0] < 1e-3)]
    assert np.hypot(earlier[:, 0], earlier[:, 1]).max() <= RANGE_M + 1e-3
    assert earlier[:, 0].min() < -RANGE_M + 5.0  # reaching back almost as far as the grid does


def test_the_keyframe_comes_first_then_the_earlier_ones_nearest_first_until_the_budget():
    """Each earlier keyframe's points are where odometry puts them, one keyframe after another,
    nearest first; the last one that tops the budget up gives every k-th of its points."""
    rng = np.random.default_rng(5)
    cloud = np.column_stack([rng.uniform(-30, 30, 40_000), rng.uniform(-30, 30, 40_000),
                             rng.uniform(0, 5, 40_000)]).astype(np.float32)
    kept = thinned(cloud)
    trail = ForwardTrail(60.0)
    xs = np.arange(0.0, 5 * STEP_M, STEP_M)
    for x in xs:
        trail.add(cloud, pose_at(x), float(x))
    here = pose_at(10.0, 0.0, 90.0)
    own = cloud[:100]
    merged = trail.merged(here, 10.0, own=own)
    assert merged.keyframes == len(xs) and np.array_equal(merged.points[:100], own)
    first = [np.flatnonzero(merged.keyframe_of == k)[0] for k in range(len(xs) + 1)]
    assert first == sorted(first)  # each keyframe's points together, in order
    total = 0
    for k, x in enumerate(xs[::-1], start=1):  # nearest (the last added) first
        world = in_world(merged.points[merged.keyframe_of == k], here)
        expected = in_world(kept, pose_at(x))
        expected = expected[np.hypot(*(expected[:, :2] - here[:2, 3]).T) <= RANGE_M]
        if k < len(xs):
            np.testing.assert_allclose(world, expected, atol=1e-3)
        else:  # the budget's last keyframe: every step-th point
            room = MAX_POINTS - total
            assert 0 < room < len(expected)
            np.testing.assert_allclose(world, expected[::-(-len(expected) // room)], atol=1e-3)
        total += len(world)
    assert total == len(merged.points) - len(own) <= MAX_POINTS


def test_thinning_keeps_the_first_point_of_each_voxel_in_scan_order():
    rng = np.random.default_rng(6)
    for scale in (3.0, 30.0, 3e4):  # dense, sparse, and far from the origin
        xyz = rng.normal(0.0, scale, (20_000, 3)).astype(np.float32)
        cell = np.floor(xyz / VOXEL_M).astype(np.int64)
        _, first = np.unique(cell, axis=0, return_index=True)
        np.testing.assert_array_equal(thinned(xyz), xyz[np.sort(first)])
    assert thinned(np.zeros((0, 3), np.float32)).shape == (0, 3)


def test_earlier_keyframes_that_did_not_see_the_place_are_left_out():
    """Around a corner: the keyframes down the first street looked past where the sensor now
    stands, those of the second street at it."""
    trail = ForwardTrail(60.0)
    rng = np.random.default_rng(2)
    world = crossing(rng)
    travelled = 0.0
    corner = [pose_at(x) for x in np.arange(-30.0, 0.5, STEP_M)]  # along +x to the crossing
    turned = [pose_at(0.0, y, 90.0) for y in np.arange(STEP_M, 10.5, STEP_M)]  # then along +y
    for previous, pose in zip([corner[0], *corner, *turned], [*corner, *turned]):
        travelled += float(np.linalg.norm(pose[:3, 3] - previous[:3, 3]))
        trail.add(seen_ahead(world, pose), pose, travelled)
    here = pose_at(0.0, 30.0, 90.0)
    assert len(trail) == len(corner) + len(turned)  # all within reach
    merged = trail.merged(here, travelled + 20.0)
    # 30 m up the side street lies 45° or more off the first street's axis from every keyframe on it
    assert merged.keyframes == len(turned)
    assert set(np.unique(merged.keyframe_of)) <= set(range(1, len(turned) + 1))


def test_a_keyframe_behind_a_wall_is_not_seen():
    trail = ForwardTrail(60.0)
    for wall_x, seen in ((5.0, False), (15.0, True)):
        trail.clear()
        y, z = np.meshgrid(np.linspace(-3.0, 3.0, 30), np.linspace(0.0, 3.0, 10))
        wall = np.column_stack([np.full(y.size, wall_x), y.ravel(), z.ravel()]).astype(np.float32)
        trail.add(wall, pose_at(0.0), 0.0)
        here = pose_at(10.0)
        assert trail.merged(here, 10.0).keyframes == int(seen)


def test_one_keyframe_is_kept_per_step_and_those_beyond_reach_are_forgotten():
    trail = ForwardTrail(10.0)
    scan = seen_ahead(street(np.random.default_rng(3)), pose_at(0.0))
    for x in np.arange(0.0, 12.5, 0.5):
        trail.add(scan, pose_at(x), float(x))
    assert len(trail) == int(12.0 // STEP_M) + 1
    trail.merged(pose_at(12.5), 12.5)
    assert len(trail) == 5  # those kept at 4, 6, .. 12 m: within 10 m of travel


def test_a_dense_forward_looking_scan_is_trailed_a_spinning_one_is_not():
    rng = np.random.default_rng(4)
    world = street(rng, 400_000)
    poses = [pose_at(x) for x in np.arange(-20.0, 0.5, 1.0)]
    scans = [seen_ahead(world, p) for p in poses]
    assert len(scans[-1]) >= TRAIL_POINTS
    *_, (last, described) = with_trail(scans, np.array(poses), 3.0, 60.0)
    assert len(described) > len(last)
    spinning = Trail(3.0, 60.0)
    around = world[np.linalg.norm(world[:, :2], axis=1) < 40.0].astype(np.float32)
    spinning.cloud(around, pose_at(0.0))
    moved = around - np.float32([1.0, 0.0, 0.0])
    assert spinning.cloud(moved, pose_at(1.0)) is moved


def test_without_a_forward_reach_a_forward_looking_scan_is_described_alone():
    rng = np.random.default_rng(5)
    world = street(rng)
    poses = [pose_at(x) for x in np.arange(-20.0, 0.5, 1.0)]
    *_, (last, described) = with_trail((seen_ahead(world, p) for p in poses), np.array(poses), 3.0, 0.0)
    assert described is last


@pytest.mark.parametrize("reach", [-1.0, float("nan"), float("inf")])
def test_a_bad_forward_reach_is_refused(reach):
    with pytest.raises(ValueError, match="forward trail reach"):
        Trail(3.0, reach)


def test_a_trail_never_holds_a_keyframe_the_query_may_be_matched_with():
    """Keyframes ``max_age`` or more before the keyframe are not merged (the node's
    ``exclude_recent_s``, evaluation's P1 exclusion): a short loop must be recognised, not
    carried round by odometry."""
    rng = np.random.default_rng(6)
    world = street(rng)
    poses = np.array([pose_at(x) for x in np.arange(-40.0, 0.5, STEP_M)])
    scans = [seen_ahead(world, p) for p in poses]
    stamps = np.arange(len(poses), dtype=float)
    *_, (_, bounded) = with_trail(scans, poses, 3.0, 60.0, stamps=stamps, max_age=5.0)
    # the same as a trail that began 4 keyframes back (stamps 16..19 are younger than 5)
    *_, (_, fresh) = with_trail(scans[-5:], poses[-5:], 3.0, 60.0)
    *_, (_, unbounded) = with_trail(scans, poses, 3.0, 60.0)
    assert np.array_equal(bounded, fresh)
    assert len(unbounded) > len(bounded)
