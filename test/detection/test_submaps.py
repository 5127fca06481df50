"""Submaps: a keyframe's cloud with its neighbours' merged in by odometry, in its own levelled frame;
what may be merged, and that a query's submap never shares a keyframe with its candidate's."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from vbrl_ros.detection.database import KeyframeDatabase
from vbrl_ros.detection.detector import LoopClosureDetector, verification_cloud
from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.detection.submaps import (
    MAX_NEIGHBOUR_DISTANCE_M,
    WIDER_NEIGHBOUR_DISTANCE_M,
    KeyframeView,
    can_merge,
    merged_cloud,
    neighbour_steps,
)
from vbrl_ros.model.builtin import load_default_model

WORLD = np.random.default_rng(0).uniform([-40, -40, -1], [40, 40, 5], (60000, 3))


def transform(x: float, y: float, yaw: float, roll: float = 0.0, pitch: float = 0.0, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [roll, pitch, yaw], degrees=True).as_matrix()
    T[:3, 3] = x, y, z
    return T


def keyframe(pose: np.ndarray, stamp: float, *, frame: np.ndarray | None = None, session: str = "0",
             radius: float = 15.0) -> KeyframeView:
    """What the node stores of a sensor at ``pose`` seeing WORLD within ``radius``: its cloud, thinned
    and levelled into ``frame`` (a tilt and a height: levelled grid frames are not the sensor's)."""
    frame = transform(0.1, -0.2, 0.0, roll=4.0, pitch=-3.0, z=1.7) if frame is None else frame
    seen = WORLD[np.linalg.norm(WORLD[:, :2] - pose[:2, 3], axis=1) < radius]
    in_sensor = (seen - pose[:3, 3]) @ pose[:3, :3]
    return KeyframeView(verification_cloud(in_sensor, frame, 1.0), frame, pose, stamp, session)


def in_world(points: np.ndarray, view: KeyframeView) -> np.ndarray:
    T = view.pose @ np.linalg.inv(view.frame)
    return np.asarray(points, np.float64) @ T[:3, :3].T + T[:3, 3]


def test_the_neighbours_are_the_past_for_a_query_and_both_sides_for_a_stored_keyframe():
    assert neighbour_steps(3, both_sides=False) == [-1, -2, -3]
    assert neighbour_steps(4, both_sides=True) == [-1, 1, -2, 2]
    assert neighbour_steps(0, both_sides=True) == []


def test_neighbours_land_where_they_are_in_the_world_and_the_keyframe_keeps_every_own_point():
    centre = keyframe(transform(0.0, 0.0, 30.0), 10.0)
    before = keyframe(transform(-5.5, 1.0, 20.0), 9.0, frame=transform(0.0, 0.0, 0.0, roll=-5.0, z=1.2))
    merged = merged_cloud(centre, [before], voxel=1.0, max_gap_s=15.0)
    assert merged.dtype == np.float32 and len(merged) > 1.15 * len(centre.cloud)
    distance, _ = cKDTree(WORLD).query(in_world(merged, centre))
    assert distance.max() < 1e-4  # every merged point is a world point, wherever it came from
    own, _ = cKDTree(merged).query(centre.cloud)
    assert own.max() < 1e-4
    # one point per voxel of the centre's sensor frame
    in_sensor = in_world(merged, centre) - centre.pose[:3, 3]
    voxels = np.floor(in_sensor @ centre.pose[:3, :3]).astype(int)
    assert len(np.unique(voxels, axis=0)) == len(voxels)


@pytest.mark.parametrize("change, merges", [
    ({}, True),
    ({"session": "1"}, False),
    ({"stamp": 25.0}, False),  # 15 s after: the gap is exclusive
    ({"stamp": 24.9}, True),
    ({"pose": np.full((4, 4), np.nan)}, False),
    ({"pose": transform(MAX_NEIGHBOUR_DISTANCE_M + 0.1, 0.0, 0.0)}, False),
])
def test_only_a_trusted_neighbour_is_merged(change, merges):
    centre = keyframe(transform(0.0, 0.0, 0.0), 10.0)
    other = KeyframeView(**{**keyframe(transform(2.0, 0.0, 0.0), 11.0).__dict__, **change})
    assert can_merge(centre, other, max_gap_s=15.0) is merges
    merged = merged_cloud(centre, [other], voxel=1.0, max_gap_s=15.0)
    assert (len(merged) > len(centre.cloud)) is merges


def test_a_wider_submap_reaches_neighbours_farther_away():
    centre, other = keyframe(transform(0.0, 0.0, 0.0), 10.0), keyframe(transform(8.0, 0.0, 0.0), 11.0)
    assert not can_merge(centre, other, max_gap_s=15.0)
    assert can_merge(centre, other, max_gap_s=15.0, reach_m=WIDER_NEIGHBOUR_DISTANCE_M)
    wider = merged_cloud(centre, [other], voxel=1.0, max_gap_s=15.0, reach_m=WIDER_NEIGHBOUR_DISTANCE_M)
    assert len(wider) > len(merged_cloud(centre, [other], voxel=1.0, max_gap_s=15.0)) == len(centre.cloud)


def test_a_query_submap_never_shares_a_keyframe_with_its_candidates():
    """Each keyframe sees its own patch of the world: the verified clouds say which keyframes they hold."""
    model = load_default_model()
    database = KeyframeDatabase(model.scorer(), model.identity())
    settings = DetectorSettings(exclude_recent_s=4.0, top_k=20, submap_keyframes=4)
    detector = LoopClosureDetector(model, database, settings)
    patches = [np.random.default_rng(k).uniform([-8, -8, 0], [8, 8, 4], (1500, 3)) + [50.0 * k, 0, 0]
               for k in range(12)]
    for k, patch in enumerate(patches):  # a 1 m step a second, every keyframe seeing a distinct patch
        pose = transform(float(k), 0.0, 0.0)
        retrieval = detector.retrieve(patch - [float(k), 0.0, 0.0], float(k), pose)
        held = [holders(cloud, retrieval.frame if i == 0 else retrieval.candidate_frames[i - 1], pose_of)
                for i, (cloud, pose_of) in enumerate(
                    [(retrieval.cloud, pose)]
                    + [(c, database.pose(cand.index)) for c, cand in zip(retrieval.candidate_clouds,
                                                                        retrieval.candidates)])]
        query, candidates = held[0], held[1:]
        assert query == {j for j in range(max(0, k - 4), k + 1) if k - j < 2}  # within half of 4 s
        for candidate, found in zip(retrieval.candidates, candidates):
            assert candidate.stamp <= k - 4.0 and not found & query, (k, candidate.stamp, found, query)


def holders(cloud: np.ndarray, frame: np.ndarray, pose: np.ndarray) -> set[int]:
    """Which keyframes' patches the points of a verified cloud come from (patches lie 50 m apart)."""
    T = pose @ np.linalg.inv(frame)
    world = np.asarray(cloud, np.float64) @ T[:3, :3].T + T[:3, 3]
    return set(np.unique(np.round(world[:, 0] / 50.0).astype(int)).tolist())
