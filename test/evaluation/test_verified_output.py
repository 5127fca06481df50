"""The evaluation hands a verified closure on to the nearest keyframe as the node does, within the
database prefix each query saw."""

import numpy as np

from vbrl_ros.evaluation.verified import Candidates, OdometryTrack, VerifiedCandidates
from vbrl_ros.evaluation.verified_output import nearest_published


def line_poses(n: int) -> np.ndarray:
    """Keyframes 1 m apart along x."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n)
    return poses


def test_a_closure_moves_to_the_nearest_keyframe_the_query_saw():
    poses = line_poses(12)
    track = OdometryTrack.of(poses)
    query_at = np.eye(4)
    query_at[0, 3] = 3.1  # registered next to keyframe 3
    indices = np.array([[6], [1], [-1]])
    candidates = Candidates(np.array([[6, 9], [0, 1], [0, 1]]), np.zeros((3, 2)))
    T = np.full((3, 2, 4, 4), np.nan)
    T[0, 0] = np.linalg.inv(query_at) @ poses[6]
    T[1, 1] = np.linalg.inv(query_at) @ poses[1]
    verified = VerifiedCandidates(np.full((3, 2), 0.5), np.full((3, 2), None, dtype=object), T)
    limits = np.array([12, 3, 12])  # the second query saw keyframes 0-2 only
    moved = nearest_published(indices, candidates, verified, track, limits)
    assert moved[:, 0].tolist() == [3, 2, -1]
    assert nearest_published(indices, candidates, verified, None, limits) is indices  # no odometry: as registered
