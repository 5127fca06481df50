"""All-round descriptors: compared only with each other, and a keyframe counts at its nearer distance."""

import numpy as np
import pytest

from vbrl_ros.index.all_round import ALL_ROUND_SCALE, AllRoundIndex, search_all_round
from vbrl_ros.index.keyframe_index import KeyframeIndex
from vbrl_ros.index.parameters import IndexParameters
from vbrl_ros.index.translation_search import search_views

SECTORS, WIDTH = 6, 8


def new_index() -> KeyframeIndex:
    return KeyframeIndex(np.ones(SECTORS * WIDTH, np.float32), IndexParameters(sectors=SECTORS))


@pytest.fixture()
def stored():
    """(index, all_round, hidden, round): 40 keyframes; every third also has an all-round descriptor."""
    rng = np.random.default_rng(3)
    hidden = rng.random((40, SECTORS * WIDTH), dtype=np.float32)
    round_ = rng.random((40, SECTORS * WIDTH), dtype=np.float32)
    index, all_round = new_index(), AllRoundIndex.like(new_index())
    for row in range(40):
        index.add(hidden[row])
        all_round.note(sees_all_round=False)
        if row % 3 == 0:
            all_round.add(row, round_[row])
    return index, all_round, hidden, round_


def test_without_an_all_round_query_it_is_the_view_search(stored):
    index, all_round, hidden, _ = stored
    query = hidden[7][None] + 0.01
    plain = search_views(index, query, np.zeros((1, 2)), 5)
    found = search_all_round(index, query, np.zeros((1, 2)), 5, all_round=all_round, all_round_views=None)
    np.testing.assert_array_equal(found.indices, plain.indices)
    np.testing.assert_array_equal(found.distances, plain.distances)


def test_a_keyframe_far_by_its_hidden_descriptor_is_found_all_round(stored):
    index, all_round, hidden, round_ = stored
    # hidden, the query is nowhere near keyframe 9; all round it is keyframe 9 turned by one sector
    query = np.roll(round_[9].reshape(SECTORS, WIDTH), 1, axis=0).reshape(1, -1)
    plain = search_views(index, hidden[20][None], np.zeros((1, 2)), 3)
    found = search_all_round(index, hidden[20][None], np.zeros((1, 2)), 3, all_round=all_round,
                             all_round_views=query)
    assert found.indices[0] == 9 and found.distances[0] == pytest.approx(0.0, abs=1e-5)
    assert found.shifts[0] in (1, SECTORS - 1)  # the all-round match's own turn
    assert 20 in found.indices and 20 == plain.indices[0]  # the hidden match still counts


def test_the_all_round_distance_counts_scaled_and_the_nearer_wins(stored):
    index, all_round, hidden, round_ = stored
    query_hidden, query_round = hidden[12][None] + 0.2, round_[12][None] + 0.2
    found = search_all_round(index, query_hidden, np.zeros((1, 2)), 40, all_round=all_round,
                             all_round_views=query_round, pool=40)
    for row, distance in zip(found.indices, found.distances):
        rolled = [np.abs(np.roll(query_hidden[0].reshape(SECTORS, WIDTH), k, axis=0)
                         - hidden[row].reshape(SECTORS, WIDTH)).sum() for k in range(SECTORS)]
        expected = min(rolled)
        if row % 3 == 0:
            rolled_round = [np.abs(np.roll(query_round[0].reshape(SECTORS, WIDTH), k, axis=0)
                                   - round_[row].reshape(SECTORS, WIDTH)).sum() for k in range(SECTORS)]
            expected = min(expected, ALL_ROUND_SCALE * min(rolled_round))
        assert distance == pytest.approx(expected, rel=1e-4)
    assert list(found.distances) == sorted(found.distances)


def test_an_excluded_keyframe_is_not_found_all_round_either(stored):
    index, all_round, hidden, round_ = stored
    allowed = np.ones(len(index), dtype=bool)
    allowed[9] = False
    found = search_all_round(index, hidden[20][None], np.zeros((1, 2)), 5, allowed, all_round=all_round,
                             all_round_views=round_[9][None])
    assert 9 not in found.indices
    by_callable = search_all_round(index, hidden[20][None], np.zeros((1, 2)), 5, lambda rows: rows != 9,
                                   all_round=all_round, all_round_views=round_[9][None])
    np.testing.assert_array_equal(by_callable.indices, found.indices)


def test_the_all_round_index_is_saved_and_restored(stored):
    index, all_round, _, round_ = stored
    restored = AllRoundIndex.from_state(all_round.state(), index)
    np.testing.assert_array_equal(restored.rows, np.arange(0, 40, 3))
    np.testing.assert_array_equal(restored.index.descriptors(), all_round.index.descriptors())
    assert len(AllRoundIndex.from_state({}, index)) == 0  # a file from before: none


def test_rows_beyond_the_keyframes_are_refused(stored):
    index, all_round, *_ = stored
    state = all_round.state()
    state["all_round_rows"] = state["all_round_rows"] + 100
    with pytest.raises(ValueError, match="all_round_rows"):
        AllRoundIndex.from_state(state, index)


def test_keyframes_that_saw_all_round_by_themselves_meet_all_round_queries_both_ways():
    """A car's keyframes see all round; a robot whose mast hides a wedge queries them all round,
    and the car's query meets the robot's all-round descriptors."""
    rng = np.random.default_rng(4)
    car = rng.random((20, SECTORS * WIDTH), dtype=np.float32)
    robot_hidden = rng.random((20, SECTORS * WIDTH), dtype=np.float32)
    robot_round = rng.random((20, SECTORS * WIDTH), dtype=np.float32)
    index, all_round = new_index(), AllRoundIndex.like(new_index())
    for row in range(20):  # the car's keyframes: rows 0-19, all round by themselves
        index.add(car[row])
        all_round.note(sees_all_round=True)
    for row in range(20):  # the robot's: rows 20-39, described all round by filling
        index.add(robot_hidden[row])
        all_round.note(sees_all_round=False)
        all_round.add(20 + row, robot_round[row])
    far = np.full((1, SECTORS * WIDTH), 5.0, np.float32)
    # the robot's query, hidden far from everything, all round the car's keyframe 7
    found = search_all_round(index, far, np.zeros((1, 2)), 3, all_round=all_round, all_round_views=car[7][None])
    assert found.indices[0] == 7 and found.distances[0] == pytest.approx(0.0, abs=1e-5)
    # the car's query is all round by itself and meets the robot's all-round descriptor of keyframe 25
    found = search_all_round(index, robot_round[5][None], np.zeros((1, 2)), 3, all_round=all_round,
                             sees_all_round=True)
    assert found.indices[0] == 25 and found.distances[0] == pytest.approx(0.0, abs=1e-5)
    # a query that is neither meets only the main descriptors
    plain = search_all_round(index, robot_round[5][None], np.zeros((1, 2)), 3, all_round=all_round)
    assert 25 not in plain.indices
    # and an excluded car keyframe is not found all round either
    allowed = np.ones(40, dtype=bool)
    allowed[7] = False
    found = search_all_round(index, far, np.zeros((1, 2)), 3, allowed, all_round=all_round,
                             all_round_views=car[7][None])
    assert 7 not in found.indices
