"""A keyframe's trail both ways: the keyframes after it merged in as those before it are."""

from __future__ import annotations

import numpy as np

from vbrl_ros.features.trail import TRAIL_POINTS, trail_clouds
from vbrl_ros.features.trail_ahead import trail_clouds_both_ways


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
