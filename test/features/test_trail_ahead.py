"""A keyframe's trail both ways: the keyframes after it merged in as those before it are."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vbrl_ros.features.session_trails import trail_clouds
from vbrl_ros.features.trail import MAX_TRAIL_KEYFRAMES, TRAIL_POINTS, Trail
from vbrl_ros.features.trail_ahead import TrailAhead


def trail_clouds_both_ways(scans, poses, reach_m, ahead_m, **kwargs):
    return trail_clouds(scans, poses, reach_m, ahead_m=ahead_m, **kwargs)


def pose_at(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def drive(count: int = 6, spacing: float = 1.0, points: int = 2000):
    """A straight drive along a ring of wall; a post 20 m out beside each keyframe, seen only from it."""
    rng = np.random.default_rng(4)
    angle = rng.uniform(-np.pi, np.pi, points)
    ring = np.column_stack([15.0 * np.cos(angle), 15.0 * np.sin(angle), rng.uniform(0.0, 3.0, points)])
    poses = np.stack([pose_at(spacing * k) for k in range(count)])
    scans, posts = [], []
    for k, pose in enumerate(poses):
        post = np.array([[pose[0, 3], 20.0, z] for z in np.arange(0.0, 2.0, 0.25)])
        scans.append((np.vstack([ring, post]) - pose[:3, 3]).astype(np.float32))
        posts.append(post)
    return scans, poses, posts


def holds(cloud: np.ndarray, pose: np.ndarray, post: np.ndarray) -> bool:
    placed = cloud + pose[:3, 3]
    return bool(np.linalg.norm(placed[:, None] - post[None], axis=2).min(axis=0).max() < 1e-4)


def test_a_keyframe_holds_the_keyframes_on_both_sides_within_reach():
    scans, poses, posts = drive()
    clouds = [cloud for _, cloud, _, _ in trail_clouds_both_ways(scans, poses, 2.0, 2.0)]
    k = 3
    assert all(holds(clouds[k], poses[k], posts[j]) for j in (1, 2, 3, 4, 5))  # 2 m either way
    assert not holds(clouds[k], poses[k], posts[0])  # 3 m back: beyond the reach
    # the last keyframe has none after it; the first none before it
    assert holds(clouds[-1], poses[-1], posts[3]) and not holds(clouds[-1], poses[-1], posts[2])
    assert holds(clouds[0], poses[0], posts[2]) and not holds(clouds[0], poses[0], posts[3])


def test_without_reaching_ahead_without_poses_or_without_a_trail_behind_it_is_the_trail():
    scans, poses, _ = drive()
    for reach, ahead, with_poses in ((2.0, 0.0, poses), (2.0, 2.0, None), (0.0, 2.0, poses)):
        both = list(trail_clouds_both_ways(scans, with_poses, reach, ahead, forward_reach_m=60.0))
        trail = list(trail_clouds(scans, with_poses, reach, forward_reach_m=60.0))
        assert all(np.array_equal(a[1], b[1]) for a, b in zip(both, trail))


def test_a_dense_keyframe_is_still_described_alone():
    scans, poses, _ = drive(points=TRAIL_POINTS)
    for points, cloud, _, _ in trail_clouds_both_ways(scans, poses, 2.0, 2.0):
        assert cloud is points


def test_the_keyframes_after_one_respect_the_age_limit_as_those_before_it():
    scans, poses, posts = drive()
    stamps = np.arange(len(scans), dtype=float)
    clouds = [cloud for _, cloud, _, _ in trail_clouds_both_ways(scans, poses, 2.0, 2.0, stamps=stamps,
                                                                 max_age=2.0)]
    k = 3  # one scan either way is younger than 2, two are not
    assert holds(clouds[k], poses[k], posts[2]) and holds(clouds[k], poses[k], posts[4])
    assert not holds(clouds[k], poses[k], posts[1]) and not holds(clouds[k], poses[k], posts[5])


def test_a_keyframe_waits_until_the_sensor_has_passed_it_and_comes_with_what_lies_ahead():
    scans, poses, posts = drive()
    ahead = TrailAhead(2.0)
    assert [ahead.add(k, scans[k], poses[k]) for k in range(3)] == [[], [], []]  # 2 m on: within reach
    assert len(ahead) == 3
    (item, parts), = ahead.add(3, scans[3], poses[3])  # 3 m past the first
    assert item == 0 and len(parts) == 2 and len(ahead) == 3
    assert all(holds(np.vstack(parts), poses[0], posts[j]) for j in (1, 2))
    assert not holds(np.vstack(parts), poses[0], posts[3])
    # the rest, oldest first, each with what came after it; the last with nothing
    flushed = ahead.flush()
    assert [item for item, _ in flushed] == [1, 2, 3] and [len(p) for _, p in flushed] == [2, 1, 0]
    assert len(ahead) == 0 and ahead.flush() == []


def test_a_break_in_the_chain_releases_every_waiting_keyframe_first_in_order():
    scans, poses, _ = drive()
    dense = np.zeros((TRAIL_POINTS, 3), np.float32)
    dense[:, 0] = np.linspace(-30, 30, TRAIL_POINTS)
    for breaker, pose, session in ((scans[2], None, ""), (scans[2], np.full((4, 4), np.nan), ""),
                                   (dense, poses[2], ""), (scans[2], poses[2], "another")):
        ahead = TrailAhead(5.0)
        assert ahead.add(0, scans[0], poses[0]) == [] and ahead.add(1, scans[1], poses[1]) == []
        due = ahead.add(2, breaker, pose, session=session)
        if session:  # another session's first keyframe waits for its own
            assert [(item, len(parts)) for item, parts in due] == [(0, 1), (1, 0)] and len(ahead) == 1
        else:
            assert [(item, len(parts)) for item, parts in due] == [(0, 1), (1, 0), (2, 0)] and len(ahead) == 0


def test_none_later_than_the_age_limit_joins_and_its_arrival_releases():
    scans, poses, _ = drive()
    ahead = TrailAhead(10.0, max_age=2.0)
    assert ahead.add(0, scans[0], poses[0], stamp=0.0) == [] and ahead.add(1, scans[1], poses[1], stamp=1.0) == []
    assert [(item, len(parts)) for item, parts in ahead.add(2, scans[2], poses[2], stamp=2.0)] == [(0, 1)]


def test_a_keyframe_that_does_not_see_all_round_does_not_wait_but_keeps_its_turn():
    scans, poses, _ = drive()
    forward = scans[1][scans[1][:, 0] > 5.0]  # a 70-degree view ahead
    ahead = TrailAhead(2.0)
    assert ahead.add(0, scans[0], poses[0]) == []
    assert ahead.add(1, forward, poses[1]) == []  # behind the one still waiting
    assert [(item, len(parts)) for item, parts in ahead.add(2, scans[2], poses[2])] == []
    due = ahead.add(3, scans[3], poses[3])
    assert [(item, len(parts)) for item, parts in due] == [(0, 2), (1, 0)]


def test_a_standing_sensor_releases_once_those_after_it_fill_its_cloud():
    scans, poses, _ = drive(count=1)
    ahead, due, count = TrailAhead(2.0), [], 0
    while not due:
        due = ahead.add(count, scans[0], poses[0])
        count += 1
    (item, parts), = due
    # the keyframe that filled it came last: nothing after it could have added a point
    assert item == 0 and len(parts) == count - 1 and len(scans[0]) + sum(map(len, parts)) == TRAIL_POINTS
    assert len(scans[0]) + sum(map(len, parts[:-1])) < TRAIL_POINTS
    # as many keyframes as a trail holds release the oldest whatever their points
    angle = np.linspace(-np.pi, np.pi, 200, endpoint=False)
    ahead, few = TrailAhead(2.0), np.column_stack([10 * np.cos(angle), 10 * np.sin(angle), np.ones(200)])
    assert all(ahead.add(k, few, poses[0]) == [] for k in range(MAX_TRAIL_KEYFRAMES))
    assert [item for item, _ in ahead.add(MAX_TRAIL_KEYFRAMES, few, poses[0])] == [0]


def test_bad_reaches_are_refused():
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="trail ahead must be a finite number of metres"):
            TrailAhead(bad)
    with pytest.raises(ValueError, match="max_age"):
        TrailAhead(1.0, max_age=math.nan)


def test_a_caller_that_moves_one_pose_array_along_gets_what_fresh_poses_give():
    """A driver loop that updates one 4x4 in place: the trails keep copies, not its buffer."""
    scans, poses, _ = drive()
    clouds = []
    for moves_its_buffer in (False, True):
        trail, ahead, out = Trail(2.0, 60.0), TrailAhead(2.0), []
        buffers = np.eye(4), np.eye(4)

        def pose_of(j: int, buffer: np.ndarray) -> np.ndarray:
            if not moves_its_buffer:
                return poses[j].copy()
            buffer[:] = poses[j]
            return buffer

        for k, scan in enumerate(scans):
            due = ahead.add(k, scan, pose_of(k, buffers[0]))
            out += [trail.cloud(scans[j], pose_of(j, buffers[1]), ahead=later) for j, later in due]
        out += [trail.cloud(scans[j], pose_of(j, buffers[1]), ahead=later) for j, later in ahead.flush()]
        clouds.append(out)
    assert len(clouds[0]) == len(scans)
    assert all(np.array_equal(a, b) for a, b in zip(*clouds))
