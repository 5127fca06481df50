"""Sequence matching: a candidate is scored by the keyframes before the query too, driven either way."""

import numpy as np
import pytest

from vbrl_ros.index.sequence_matching import CURRENT_WEIGHT, SLACK, SequenceHistory


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
