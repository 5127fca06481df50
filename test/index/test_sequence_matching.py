"""Sequence matching: a candidate is scored by the keyframes before the query too, driven either way."""

import numpy as np
import pytest

from vbrl_ros.index.keyframe_places import KeyframePlaces
from vbrl_ros.index.sequence_matching import CURRENT_WEIGHT, PLACE_SLACK_M, SLACK, SequenceHistory


def feed(history: SequenceHistory, pools: list[dict[int, float]]) -> None:
    """Earlier keyframes' pools, oldest first: {keyframe id: distance}."""
    for pool in pools:
        history.rescore(np.array(list(pool), np.int64), np.array(list(pool.values()), float))


def mean(current: float, earlier: list[float]) -> float:
    return (CURRENT_WEIGHT * current + sum(earlier)) / (CURRENT_WEIGHT + len(earlier))


def test_length_one_is_the_keyframe_alone_and_remembers_nothing():
    history = SequenceHistory(1)
    feed(history, [{5: 1.0}, {6: 1.0}])
    distances = np.array([3.0, 2.0])
    np.testing.assert_array_equal(history.rescore(np.array([10, 20]), distances), distances)
    assert len(history) == 0


def test_without_earlier_keyframes_a_candidate_keeps_its_own_distance():
    np.testing.assert_allclose(SequenceHistory(4).rescore(np.array([3, 9]), np.array([2.0, 5.0])), [2.0, 5.0])


@pytest.mark.parametrize("direction", [-1, 1], ids=["same way", "reversed"])
def test_a_run_of_keyframes_outranks_a_lookalike_that_only_the_query_matches(direction):
    # candidate 100 is the revisit: the three keyframes before the query matched its neighbours
    # 100 + direction * step; candidate 500 looks a little closer to the query alone
    earlier = [{100 + direction * step: 4.0, 700: 9.0} for step in (3, 2, 1)]
    history = SequenceHistory(4)
    feed(history, earlier)
    scored = history.rescore(np.array([100, 500]), np.array([5.0, 4.5]))
    assert scored[0] == pytest.approx(mean(5.0, [4.0, 4.0, 4.0]))
    farthest = 9.0  # 500's neighbours were in no earlier pool: each counts as that pool's farthest
    assert scored[1] == pytest.approx(mean(4.5, [farthest] * 3))
    assert scored[0] < scored[1]


def test_passes_keyframed_at_other_spots_still_line_up_within_the_slack():
    history = SequenceHistory(3)
    # the keyframes before the query matched 102 and 103, not 101 and 102: one keyframe of slack
    feed(history, [{98: 9.0, 103: 2.0}, {102: 2.0, 98: 9.0}])
    scored = history.rescore(np.array([100]), np.array([5.0]))[0]
    assert SLACK >= 1
    assert scored == pytest.approx(mean(5.0, [2.0, 2.0]))


def test_the_better_direction_is_taken():
    history = SequenceHistory(2)
    feed(history, [{49: 8.0, 51: 1.0, 60: 10.0}])
    assert history.rescore(np.array([50]), np.array([4.0]))[0] == pytest.approx(mean(4.0, [1.0]))


def test_a_keyframe_that_found_nothing_keeps_the_later_ones_in_their_places():
    history = SequenceHistory(3)
    feed(history, [{102: 1.0, 90: 9.0}, {}])  # the keyframe just before found no candidate
    # step 1 (nothing found) falls back to the query's own distance; step 2 reads 102
    assert history.rescore(np.array([100]), np.array([5.0]))[0] == pytest.approx(mean(5.0, [5.0, 1.0]))


def test_only_the_last_length_minus_one_keyframes_count():
    history = SequenceHistory(2)
    feed(history, [{101: 0.0, 90: 9.0}, {300: 1.0, 301: 7.0}])  # the older pool is forgotten
    assert len(history) == 1
    assert history.rescore(np.array([100]), np.array([5.0]))[0] == pytest.approx(mean(5.0, [7.0]))


def test_clear_forgets_the_stream():
    history = SequenceHistory(3)
    feed(history, [{101: 0.0}, {102: 0.0}])
    history.clear()
    assert history.rescore(np.array([100]), np.array([5.0]))[0] == pytest.approx(5.0)


@pytest.mark.parametrize("length", [0, -1, 2.5, "4"])
def test_a_bad_length_is_refused(length):
    with pytest.raises(ValueError, match="sequence length"):
        SequenceHistory(length)


def test_ids_and_distances_must_pair_up():
    with pytest.raises(ValueError, match="must be equal"):
        SequenceHistory(3).rescore(np.array([1, 2]), np.array([1.0]))


# -- by place: with odometry, earlier keyframes are compared where the query was then ------------

def street(places: KeyframePlaces, ids: range, start: tuple[float, float], step: tuple[float, float]) -> None:
    """Keyframes ``ids`` of an earlier pass, ``step`` metres apart from ``start``."""
    for k, keyframe_id in enumerate(ids):
        places.add(keyframe_id, np.array([start[0] + k * step[0], start[1] + k * step[1], 0.0]))


def feed_at(history: SequenceHistory, places: KeyframePlaces, pools: list[tuple[tuple[float, float], dict]]) -> None:
    """Earlier keyframes' pools, oldest first, each with where the query was then."""
    for (x, y), pool in pools:
        history.rescore(np.array(list(pool), np.int64), np.array(list(pool.values()), float),
                        here=np.array([x, y, 0.0]), places=places)


def test_a_turn_onto_a_street_driven_across_is_judged_on_what_can_be_compared():
    # the earlier pass drove along x (ids 0-9, 2 m apart); the query came down a street along y
    # that no keyframe was taken on and stands at the crossing, on keyframe 5; keyframe 40 of
    # another street (ids 35-45) looks almost as close, and the query's last keyframes matched
    # its id-neighbours moderately (passers-by of no note)
    places = KeyframePlaces(PLACE_SLACK_M)
    street(places, range(10), (0.0, 0.0), (2.0, 0.0))
    street(places, range(35, 46), (90.0, 100.0), (2.0, 0.0))
    pool = {4: 9.0, 6: 9.0, **dict.fromkeys((37, 38, 39, 41, 42, 43), 6.0)}
    ids, own = np.array([5, 40]), np.array([3.0, 3.5])

    by_id = SequenceHistory(4)
    feed(by_id, [pool] * 3)
    assert np.argmin(by_id.rescore(ids, own)) == 1  # by id the turn loses to the lookalike

    by_place = SequenceHistory(4)
    feed_at(by_place, places, [((10.0, 9.0), pool), ((10.0, 6.0), pool), ((10.0, 3.0), pool)])
    scored = by_place.rescore(ids, own, here=np.array([10.0, 0.0, 0.0]), places=places)
    typical = 6.0  # where no keyframe was ever taken, an earlier term is the pool's median
    np.testing.assert_allclose(scored, [mean(3.0, [typical] * 3), mean(3.5, [typical] * 3)])
    assert np.argmin(scored) == 0


def test_a_reversed_revisit_on_the_other_lane_is_matched_place_by_place():
    # the earlier pass along x (ids 0-9, 2 m apart); the query drives back 2 m to the side,
    # keyframed every 1.5 m: its last keyframes stood beside keyframes 6 and 7
    places = KeyframePlaces(PLACE_SLACK_M)
    street(places, range(10), (0.0, 0.0), (2.0, 0.0))
    pools = [((14.5, 2.0), {7: 2.0, 1: 8.0}), ((13.0, 2.0), {6: 3.0, 7: 2.5, 1: 8.0}),
             ((11.5, 2.0), {6: 2.0, 2: 8.0})]
    history = SequenceHistory(4)
    feed_at(history, places, pools)
    scored = history.rescore(np.array([5, 1]), np.array([4.0, 4.0]), here=np.array([10.0, 2.0, 0.0]),
                             places=places)
    # 5: 1.5 m on is 6 (2.0), 3 m on 6 or 7 (2.5), 4.5 m on 7 (2.0); 1: stored there, not retrieved
    np.testing.assert_allclose(scored, [mean(4.0, [2.0, 2.5, 2.0]), mean(4.0, [8.0, 8.0, 8.0])])


def test_without_a_position_candidates_are_matched_by_id():
    # another session's keyframes (not among these places) and a query without odometry
    pools = [{97: 4.0, 700: 9.0}, {98: 4.0, 700: 9.0}, {99: 4.0, 700: 9.0}]
    places = KeyframePlaces(PLACE_SLACK_M)
    street(places, range(10), (0.0, 0.0), (2.0, 0.0))
    ids, own = np.array([100, 500]), np.array([5.0, 4.5])
    expected = SequenceHistory(4)
    feed(expected, pools)
    want = expected.rescore(ids, own)
    for here in (np.array([1.0, 2.0, 0.0]), None, np.array([np.nan, 0.0, 0.0])):
        history = SequenceHistory(4)
        feed_at(history, places, [((0.0, 0.0), pool) for pool in pools])
        np.testing.assert_allclose(history.rescore(ids, own, here=here, places=places), want)
