"""Coarse alignment: every heading searched, yaw and translation found to a step and a cell,
on revisits the simulator drives the other way round."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vbrl_ros.detection.coarse_alignment import (
    CELL_M,
    YAW_STEP_DEG,
    HeadingSearch,
    coarse_alignment,
)

sim = pytest.importorskip("vbrl_ros.simulator")
SENSOR_HEIGHT_M = 1.8  # the route's default: the ground is flat at -1.8 m in the sensor frame


def structure(points: np.ndarray) -> np.ndarray:
    return points[points[:, 2] > 0.3 - SENSOR_HEIGHT_M]


def yaw_of(T: np.ndarray) -> float:
    return math.atan2(T[1, 0], T[0, 0])


@pytest.fixture(scope="module")
def run():
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=3)
    route = sim.make_route(town, sim.RouteConfig(loops=2, spacing_m=2.0))
    return sim.simulate_run(town, route, sim.LidarConfig(beams=32, columns=720), "summer_clear", seed=1)


def revisits(run, turned_deg: float, count: int) -> list[tuple[int, int]]:
    """``count`` (query, match) pairs 1-4 m apart whose headings differ by more than ``turned_deg``."""
    poses = run.poses
    pairs = []
    for q in range(len(run) - 1, 0, -7):
        gaps = np.linalg.norm(poses[:q - 10, :2, 3] - poses[q, :2, 3], axis=1)
        for m in np.flatnonzero((gaps > 1.0) & (gaps < 4.0)):
            turn = abs(math.degrees(math.remainder(yaw_of(poses[q]) - yaw_of(poses[m]), 2 * math.pi)))
            if turn > turned_deg:
                pairs.append((q, int(m)))
                break
        if len(pairs) == count:
            return pairs
    raise AssertionError(f"the route has fewer than {count} such revisits")


def test_finds_heading_and_offset_of_reversed_revisits_on_the_other_lane(run):
    for q, m in revisits(run, turned_deg=150.0, count=4):
        query, match = run.scan(q), run.scan(m)
        truth = np.linalg.inv(query.pose) @ match.pose
        found = coarse_alignment(structure(query.points), structure(match.points))
        yaw_error = math.degrees(abs(math.remainder(yaw_of(found.T_query_match) - yaw_of(truth), 2 * math.pi)))
        # KISS-ICP's basin is about +-10 degrees and metres: a step and a couple of cells are inside it
        assert yaw_error <= YAW_STEP_DEG / 2 + 1.0, (q, m, yaw_error)
        assert np.linalg.norm(found.T_query_match[:2, 3] - truth[:2, 3]) <= 2 * CELL_M, (q, m)
        np.testing.assert_allclose(found.T_query_match[2], [0, 0, 1, 0])  # horizontal only


def test_an_unrelated_place_correlates_less_than_the_same_place(run):
    (q, m), = revisits(run, turned_deg=150.0, count=1)
    far = int(np.argmax(np.linalg.norm(run.poses[:, :2, 3] - run.poses[q, :2, 3], axis=1)))
    query = structure(run.scan(q).points)
    same = coarse_alignment(query, structure(run.scan(m).points))
    other = coarse_alignment(query, structure(run.scan(far).points))
    assert other.score < 0.7 * same.score


def test_empty_structure_gives_a_zero_score():
    found = coarse_alignment(np.empty((0, 3)), np.empty((0, 3)))
    assert found.score == 0.0 and found.T_query_match.shape == (4, 4)


def test_between_the_steps_yaw_and_translation_are_interpolated(run):
    # halfway between two searched headings: the steps alone would be 5 degrees off
    turn = np.deg2rad(YAW_STEP_DEG / 2)
    c, s = math.cos(turn), math.sin(turn)
    errors = []
    for q, m in revisits(run, turned_deg=150.0, count=4):
        query, match = run.scan(q), run.scan(m)
        truth = np.linalg.inv(query.pose) @ match.pose
        turned = structure(match.points)[:, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])  # R(turn)^-1 p
        found = HeadingSearch(structure(query.points)).align(turned).T_query_match
        yaw = math.remainder(yaw_of(found) - turn - yaw_of(truth), 2 * math.pi)  # found = truth R(turn)
        errors.append((abs(math.degrees(yaw)), np.linalg.norm(found[:2, 3] - truth[:2, 3])))
    errors = np.array(errors)
    assert errors[:, 0].max() < 0.5 * YAW_STEP_DEG and np.median(errors[:, 0]) < 2.0, errors
    assert errors[:, 1].max() < 1.5 * CELL_M, errors


def test_one_query_searched_against_many_matches_as_one_pair_each(run):
    (q, m), = revisits(run, turned_deg=150.0, count=1)
    query, match = structure(run.scan(q).points), structure(run.scan(m).points)
    search = HeadingSearch(query)
    for other in (match, structure(run.scan(0).points)):
        np.testing.assert_array_equal(search.align(other).T_query_match,
                                      coarse_alignment(query, other).T_query_match)


def test_translations_beyond_the_search_radius_are_not_searched(run):
    (q, _), = revisits(run, turned_deg=150.0, count=1)
    query = structure(run.scan(q).points)[:, :3]
    moved = query - np.array([9.0, 0.0, 0.0])  # the same place, 9 m back: T_query_match moves it +9 m in x
    found = HeadingSearch(query, max_shift_m=12.0).align(moved).T_query_match
    np.testing.assert_allclose(found[:2, 3], [9.0, 0.0], atol=CELL_M)
    assert abs(math.degrees(yaw_of(found))) < YAW_STEP_DEG / 2
    near = HeadingSearch(query, max_shift_m=6.0).align(moved).T_query_match
    assert np.linalg.norm(near[:2, 3]) <= 6.0 + 1e-9
    with pytest.raises(ValueError, match="max_shift_m"):
        HeadingSearch(query, max_shift_m=0.0)



def test_the_first_overlay_is_the_best_peak_and_the_others_are_other_headings(run):
    (q, m), = revisits(run, turned_deg=150.0, count=1)
    query, match = structure(run.scan(q).points), structure(run.scan(m).points)
    search = HeadingSearch(query)
    overlays = search.alignments(match, 4)
    assert 2 <= len(overlays) <= 4
    np.testing.assert_array_equal(overlays[0].T_query_match, search.align(match).T_query_match)
    yaws = np.degrees([yaw_of(o.T_query_match) for o in overlays])
    gaps = np.abs((yaws[:, None] - yaws[None, :] + 180.0) % 360.0 - 180.0)[np.triu_indices(len(yaws), 1)]
    assert gaps.min() >= YAW_STEP_DEG  # one per summit of the peaks over headings
    assert all(o.score <= overlays[0].score + 1e-9 for o in overlays)
    assert len(search.alignments(np.empty((0, 3)), 4)) == 1
