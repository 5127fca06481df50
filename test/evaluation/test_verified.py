"""The verified output's two readings, and verification of every candidate as the node does it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vbrl_ros.detection.settings import DetectorSettings
from vbrl_ros.evaluation.metrics import evaluate_online
from vbrl_ros.evaluation.verified import (
    Candidates,
    Corroboration,
    KeyframeClouds,
    OdometryTrack,
    VerifiedCandidates,
    best_verified,
    node_decision,
    operating_point,
    plausible_candidates,
    submap_clouds,
    verify_candidates,
)

INF = math.inf


def checked(fitness, rejection) -> VerifiedCandidates:
    fitness = np.array(fitness, dtype=float)
    return VerifiedCandidates(fitness, np.array(rejection, dtype=object),
                              np.full((*fitness.shape, 4, 4), np.nan))


# three queries, three candidates each: distance order, the rule's verdict and fitness
CANDIDATES = Candidates(np.array([[4, 7, 9], [5, 6, -1], [2, 3, 1]]),
                        np.array([[1.0, 2.0, 3.0], [1.5, 2.5, INF], [0.5, 0.6, 0.7]]))
VERIFIED = checked([[0.15, 0.40, 0.30], [0.50, 0.10, np.nan], [0.60, 0.90, 0.80]],
                   [[None, None, "degenerate"], [None, None, "no candidate"],
                    ["not converged", "too far", "low fitness"]])


def test_swept_reading_keeps_the_accepted_candidate_of_highest_fitness():
    indices, distances = best_verified(CANDIDATES, VERIFIED)
    # query 0: 7 (0.40) beats 4 (0.15); 9 is degenerate however fit. query 2: nothing accepted
    np.testing.assert_array_equal(indices[:, 0], [7, 5, -1])
    np.testing.assert_allclose(distances[:, 0], [0.60, 0.50, INF])


def test_node_reading_takes_the_first_accepted_in_distance_order():
    indices, decided = node_decision(CANDIDATES, VERIFIED, INF, min_fitness=0.2, top_k=3)
    np.testing.assert_array_equal(indices[:, 0], [7, 5, -1])  # 4 is below 0.2
    indices, _ = node_decision(CANDIDATES, VERIFIED, INF, min_fitness=0.1, top_k=3)
    np.testing.assert_array_equal(indices[:, 0], [4, 5, -1])  # first, not fittest
    indices, _ = node_decision(CANDIDATES, VERIFIED, 1.2, min_fitness=0.2, top_k=3)
    np.testing.assert_array_equal(indices[:, 0], [-1, -1, -1])  # 7 and 5 beyond the distance
    indices, decided = node_decision(CANDIDATES, VERIFIED, INF, min_fitness=0.2, top_k=1)
    np.testing.assert_array_equal(indices[:, 0], [-1, 5, -1])
    np.testing.assert_array_equal(decided[:, 0], [INF, 0.0, INF])


def test_the_verified_candidates_are_the_first_top_k_odometry_allows_as_the_node_retrieves_them():
    # keyframes 0-3 at the origin, 4-9 far along a straight 1 km drive; queries 10 and 11 back home
    positions = np.zeros((12, 3))
    positions[4:10, 0] = np.linspace(200.0, 1000.0, 6)
    positions[10:, 0] = [1.0, 2.0]
    poses = np.tile(np.eye(4), (12, 1, 1))
    poses[:, :3, 3] = positions
    ranked = np.full((12, 10), -1)
    ranked[10, :6] = [5, 0, 6, 7, 1, 2]  # lookalikes far away (5, 6, 7) before the true places
    ranked[11, :4] = [8, 9, 3, -1]
    rule = DetectorSettings(top_k=2, odometry_drift=0.1)
    chosen = plausible_candidates(ranked, np.where(ranked >= 0, 1.0, INF), rule, OdometryTrack.of(poses))
    # query 10: 0 and 1 are the two allowed, with the ruled-out 5, 6 and 7 before 1 (counted, not
    # registered); query 11: its spares hold only one allowed
    assert chosen.indices[10].tolist() == [5, 0, 6, 7, 1] and chosen.indices[11].tolist() == [8, 9, 3, -1, -1]
    assert np.isinf(chosen.distances[11, 3:]).all()
    for no_gate in (plausible_candidates(ranked, ranked * 1.0, rule, None),
                    plausible_candidates(ranked, ranked * 1.0, DetectorSettings(top_k=2, odometry_drift=0.0),
                                         OdometryTrack.of(poses))):
        assert no_gate.indices.shape == (12, 2) and no_gate.indices[10].tolist() == [5, 0]


def test_operating_point_counts_what_was_published():
    positions = np.c_[np.arange(8) * 10.0, np.zeros(8), np.zeros(8)]
    positions[6] = positions[0] + [1, 0, 0]  # query 6 revisits 0
    positions[7] = positions[2] + [1, 0, 0]  # query 7 revisits 2
    indices = np.array([[-1]] * 6 + [[0], [3]])  # 6 right, 7 wrong
    decided = np.where(indices >= 0, 0.0, INF)
    metrics = evaluate_online(positions, indices, decided, radius=3.0, exclude=3)
    point = operating_point(metrics, accepted=2)
    assert point.precision == 0.5 and point.recall == 0.5 and point.f1 == 0.5
    nothing = operating_point(evaluate_online(positions, np.full((8, 1), -1), np.full((8, 1), INF), 3.0, 3), 0)
    assert math.isnan(nothing.precision) and nothing.recall == 0.0


sim = pytest.importorskip("vbrl_ros.simulator")


@pytest.fixture(scope="module")
def drive() -> tuple[KeyframeClouds, np.ndarray]:
    """Levelled 1 m clouds of a simulated drive that comes back the other way."""
    from vbrl_ros.detection.detector import verification_cloud
    from vbrl_ros.model.builtin import load_default_model

    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=2)
    run = sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=2, spacing_m=6.0)),
                           sim.LidarConfig(beams=32, columns=512), "summer_clear", seed=1)
    featurizer = load_default_model().featurizer()
    clouds, frames = [], []
    for scan in run:
        frame = featurizer.frame(scan.points).matrix
        clouds.append(verification_cloud(scan.points, frame, 1.0))
        frames.append(frame)
    return KeyframeClouds(clouds, frames), run.poses


def test_verifying_every_candidate_finds_the_revisits_and_rejects_the_rest(drive):
    clouds, poses = drive
    n = len(poses)
    gaps = np.linalg.norm(poses[:, None, :2, 3] - poses[None, :, :2, 3], axis=2)
    queries = [q for q in range(n) if (gaps[q, : max(q - 5, 0)] < 3.0).any()][:6]
    assert len(queries) >= 4
    indices = np.full((n, 2), -1)
    for q in queries:  # the true revisit first, a far place second
        indices[q] = [int(np.argmin(gaps[q, : q - 5])), int(np.argmax(gaps[q, : q - 5]))]
    candidates = Candidates(indices, np.where(indices >= 0, 1.0, INF))
    settings = DetectorSettings()
    one = verify_candidates(clouds, None, candidates, settings, workers=1, progress=False)
    two = verify_candidates(clouds, None, candidates, settings, workers=2, progress=False)
    np.testing.assert_array_equal(one.fitness, two.fitness)  # deterministic, whatever the processes
    accepted = one.accepted_at(settings.min_fitness)
    assert accepted[queries, 0].all() and not accepted[queries, 1].any()
    for q in queries:  # the published transform is the true one between the sensors
        truth = np.linalg.inv(poses[q]) @ poses[indices[q, 0]]
        assert np.linalg.norm(one.T_query_match[q, 0][:3, 3] - truth[:3, 3]) < 0.3
    assert np.isnan(one.fitness[indices < 0]).all() and (one.rejection[indices < 0] == "no candidate").all()


def test_evaluation_rejects_what_the_sources_odometry_places_too_far_away_as_the_node_does(drive):
    clouds, poses = drive
    gaps = np.linalg.norm(poses[:, None, :2, 3] - poses[None, :, :2, 3], axis=2)
    q = next(q for q in range(len(poses)) if (gaps[q, : max(q - 5, 0)] < 3.0).any())
    revisit, far = int(np.argmin(gaps[q, : q - 5])), int(np.argmax(gaps[q, : q - 5]))
    candidates = Candidates(np.full((len(poses), 2), -1), np.full((len(poses), 2), INF))
    candidates.indices[q] = [revisit, far]
    track = OdometryTrack.of(poses)
    # odometry that drifts not at all: the far place is out of reach, the revisit within it
    strict = DetectorSettings(odometry_drift=1e-9)
    checked = verify_candidates(clouds, None, candidates, strict, odometry=track, workers=1, progress=False)
    assert checked.rejection[q, 1] == "odometry" and np.isnan(checked.fitness[q, 1])  # never registered
    assert checked.accepted_at(strict.min_fitness)[q, 0]
    # across sessions, or with the gate off, the far place is registered (and rejected on its own)
    for odometry, settings in ((None, strict), (track, DetectorSettings(odometry_drift=0.0))):
        plain = verify_candidates(clouds, None, candidates, settings, odometry=odometry, workers=1, progress=False)
        assert plain.rejection[q, 1] != "odometry" and np.isfinite(plain.fitness[q, 1])
    assert OdometryTrack.of(None) is None


def test_evaluation_tells_the_verification_the_heading_odometry_expects_as_the_node_does(drive, expected_yaws):
    from vbrl_ros.detection.odometry_gate import odometry_heading

    clouds, poses = drive
    gaps = np.linalg.norm(poses[:, None, :2, 3] - poses[None, :, :2, 3], axis=2)
    q = next(q for q in range(len(poses)) if (gaps[q, : max(q - 5, 0)] < 3.0).any())
    revisit = int(np.argmin(gaps[q, : q - 5]))
    candidates = Candidates(np.full((len(poses), 1), -1), np.full((len(poses), 1), INF))
    candidates.indices[q] = revisit
    told = expected_yaws
    track = OdometryTrack.of(poses)
    checked = verify_candidates(clouds, None, candidates, DetectorSettings(), odometry=track, workers=1, progress=False)
    expected = odometry_heading(poses[q], poses[revisit], clouds.frames[q], clouds.frames[revisit], 0.1)
    assert told == [expected] and math.isfinite(expected)
    assert checked.accepted_at(0.2)[q, 0]
    # the gate off, or no odometry (P2): no expectation, as at the node
    for odometry, settings in ((track, DetectorSettings(odometry_drift=0.0)), (None, DetectorSettings())):
        told.clear()
        verify_candidates(clouds, None, candidates, settings, odometry=odometry, workers=1, progress=False)
        assert len(told) == 1 and math.isnan(told[0])


def test_evaluation_verifies_the_submaps_the_node_would():
    """Each keyframe sees a patch of its own; a query's submap holds its past, a stored keyframe's
    both sides, and nothing merges without poses, with 0 neighbours or beyond the time gap."""
    patches = [np.random.default_rng(k).uniform(-3, 3, (200, 3)).astype(np.float32) + [20.0 * k, 0, 0]
               for k in range(6)]
    poses = np.stack([np.eye(4)] * 6)
    poses[:, 0, 3] = np.arange(6.0)  # 1 m apart; each patch given in its sensor's frame
    clouds = KeyframeClouds([p - [float(k), 0, 0] for k, p in enumerate(patches)], [np.eye(4)] * 6)
    stamps = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 40.0])
    rule = DetectorSettings(submap_keyframes=2, verification_voxel=0.05)

    def holders(merged: KeyframeClouds, k: int) -> set[int]:
        return set(np.unique(np.round((merged.clouds[k][:, 0] + k) / 20.0).astype(int)).tolist())

    queries = submap_clouds(clouds, poses, stamps, rule, both_sides=False)
    stored = submap_clouds(clouds, poses, stamps, rule, both_sides=True)
    assert [holders(queries, k) for k in range(6)] == [{0}, {0, 1}, {0, 1, 2}, {1, 2, 3}, {2, 3, 4}, {5}]
    assert [holders(stored, k) for k in range(6)] == [{0, 1}, {0, 1, 2}, {1, 2, 3}, {2, 3, 4}, {3, 4}, {5}]
    assert submap_clouds(clouds, None, stamps, rule, both_sides=True) is clouds
    assert submap_clouds(clouds, poses, stamps, DetectorSettings(submap_keyframes=0), both_sides=True) is clouds


def test_the_node_reading_takes_a_wider_retry_only_when_nothing_passed_as_it_was():
    """As the node: it retries degenerate registrations with wider submaps only after none of its
    candidates passed, so a retried acceptance never comes before a plain one."""
    retried = checked([[0.30, 0.40], [0.30, 0.10]], [[None, None], [None, "low fitness"]])
    retried = VerifiedCandidates(retried.fitness, retried.rejection, retried.T_query_match,
                                 np.array([[0.20, np.nan], [0.20, np.nan]]))  # first fitness of the retried
    candidates = Candidates(np.array([[4, 7], [5, 6]]), np.array([[1.0, 2.0], [1.5, 2.5]]))
    indices, _ = node_decision(candidates, retried, INF, min_fitness=0.2, top_k=2)
    np.testing.assert_array_equal(indices[:, 0], [7, 5])


def test_a_sweep_over_min_fitness_counts_a_wider_retry_only_where_the_node_would_have_retried():
    """The node retries a registration that slid only from WIDER_RETRY_FITNESS times its own
    min_fitness: one whose first overlap was 0.13 is retried at 0.16 (from 0.112), not at 0.2."""
    candidates = Candidates(np.array([[4], [5]]), np.ones((2, 1)))
    verified = VerifiedCandidates(np.array([[0.30], [0.30]]), np.full((2, 1), None, dtype=object),
                                  np.full((2, 1, 4, 4), np.nan), np.array([[0.13], [0.15]]))
    assert node_decision(candidates, verified, INF, 0.2, 1)[0][:, 0].tolist() == [-1, 5]
    assert node_decision(candidates, verified, INF, 0.16, 1)[0][:, 0].tolist() == [4, 5]


def corridor(rng: np.random.Generator, end_wall: bool) -> np.ndarray:
    """18 m of a 6 m wide corridor seen from its middle, 1 m up; ``end_wall``: closed at x = -6."""
    def plane(n, xs, ys, zs):
        return np.c_[rng.uniform(*xs, n), rng.uniform(*ys, n), rng.uniform(*zs, n)]
    parts = [plane(3000, (-6, 12), (3, 3), (-1, 4)), plane(3000, (-6, 12), (-3, -3), (-1, 4)),
             plane(2000, (-6, 12), (-3, 3), (-1, -1))]
    return np.vstack(parts + ([plane(600, (-6, -6), (-3, 3), (-1, 4))] if end_wall else [])).astype(np.float32)


def test_evaluation_retries_a_degenerate_registration_with_the_wider_clouds_as_the_node_does():
    rng = np.random.default_rng(4)
    narrow = KeyframeClouds([corridor(rng, False), corridor(rng, False)], [np.eye(4)] * 2)
    wider = KeyframeClouds([corridor(rng, True), corridor(rng, True)], [np.eye(4)] * 2)
    candidates = Candidates(np.array([[0]]), np.array([[1.0]]))
    rule = DetectorSettings()
    plain = verify_candidates(narrow, None, candidates, rule, workers=1, progress=False)
    assert plain.rejection[0, 0] == "degenerate" and plain.fitness[0, 0] >= 0.2 and not plain.retried.any()
    again = verify_candidates(narrow, None, candidates, rule, wider=(wider, None), workers=1, progress=False)
    assert again.rejection[0, 0] is None and again.retried[0, 0]
    assert np.linalg.norm(again.T_query_match[0, 0][:3, 3]) < 0.5


def test_the_node_reading_publishes_weak_registrations_the_queries_before_corroborate():
    # database keyframes a metre apart along x, keyframe 20 100 m off; queries 0-2 revisit 10-12 m
    # weakly, 3 registers weakly to 20, 4 passes outright; every registration puts the query sensor
    # 0.2 m to the side of its match
    database = np.tile(np.eye(4), (30, 1, 1))
    database[:, 0, 3] = np.arange(30.0)
    database[20, 0, 3] = 100.0
    queries = np.c_[np.arange(5.0) + 500.0, np.zeros(5), np.zeros(5)]  # its own frame, a metre a keyframe
    candidates = Candidates(np.array([[10, 3], [11, 4], [12, 5], [20, 6], [13, 7]]), np.ones((5, 2)))
    aside = np.eye(4)
    aside[1, 3] = -0.2  # match-frame points into the query frame: the query sensor at +0.2 m in y
    fitness = np.array([[0.17, 0.05], [0.18, 0.10], [0.19, 0.10], [0.19, 0.10], [0.50, 0.30]])
    verified = VerifiedCandidates(fitness, np.full((5, 2), None, dtype=object), np.tile(aside, (5, 2, 1, 1)))
    corroboration = Corroboration(queries, database, fitness=0.16)
    indices, decided = node_decision(candidates, verified, INF, 0.2, 2, corroboration)
    # 0, 1: not two before them; 2: 0 and 1 were registered 2 m and 1 m back; 3: 88 m from where
    # they were; 4: plainly
    np.testing.assert_array_equal(indices[:, 0], [-1, -1, 12, -1, 13])
    np.testing.assert_array_equal(decided[:, 0], [INF, INF, 0.0, INF, 0.0])
    assert node_decision(candidates, verified, INF, 0.2, 2)[0][:, 0].tolist() == [-1, -1, -1, -1, 13]
    off = Corroboration(queries, database, fitness=0.2)  # at min_fitness: off
    assert node_decision(candidates, verified, INF, 0.2, 2, off)[0][:, 0].tolist() == [-1, -1, -1, -1, 13]
    # registered only if not refused: with 10 sliding, query 2 has one agreeing keyframe before it
    slid = VerifiedCandidates(fitness, np.array([["degenerate", None]] + [[None, None]] * 4, dtype=object),
                              verified.T_query_match)
    assert node_decision(candidates, slid, INF, 0.2, 2, corroboration)[0][:, 0].tolist() == [-1, -1, -1, -1, 13]
    # where the registration puts the query counts, not the keyframe it matched: query 2's registration
    # says it stood 4 m from its match, 3 m farther than odometry allows
    moved = verified.T_query_match.copy()
    moved[2, 0, 0, 3] = -4.0
    wrong = VerifiedCandidates(fitness, verified.rejection, moved)
    assert node_decision(candidates, wrong, INF, 0.2, 2, corroboration)[0][:, 0].tolist() == [-1, -1, -1, -1, 13]


def test_within_one_session_a_weak_registration_must_also_agree_with_odometry():
    # P1 along a corridor, a keyframe a metre: keyframes 10-12 register weakly, consistently, onto 3-5,
    # as if the sensor stood there; odometry says 7 m on, after 7 m of walking: 1 m + 10 % of it allowed
    poses = np.tile(np.eye(4), (13, 1, 1))
    poses[:, 0, 3] = np.arange(13.0)
    indices = np.zeros((13, 1), dtype=np.int64)
    indices[10:, 0] = [3, 4, 5]
    fitness = np.zeros((13, 1))
    fitness[10:, 0] = 0.18
    verified = VerifiedCandidates(fitness, np.full((13, 1), None, dtype=object), np.tile(np.eye(4), (13, 1, 1, 1)))
    candidates = Candidates(indices, np.ones((13, 1)))

    def published(**odometry):
        corroboration = Corroboration(poses[:, :3, 3], poses, 0.16, **odometry)
        return node_decision(candidates, verified, INF, 0.2, 1, corroboration)[0][10:, 0].tolist()

    assert published() == [-1, -1, 5]  # across sessions (no paths) odometry cannot say
    assert published(paths=np.arange(13.0), odometry_drift=0.1) == [-1, -1, -1]
    assert published(paths=np.arange(13.0), odometry_drift=0.0) == [-1, -1, 5]  # the gate off
    assert published(paths=np.arange(13.0) * 10, odometry_drift=0.1) == [-1, -1, 5]  # 70 m of walking: 8 m
