"""The evaluation's query stream keeps sequence matching aligned when early queries have no database."""

import numpy as np
import pytest

from vbrl_ros.evaluation.methods import QueryStream


def test_queries_without_a_database_still_take_their_place_in_the_sequence():
    stream = QueryStream(3)
    stream.reach(0)
    stream.history.rescore(np.array([7, 50]), np.array([1.0, 6.0]))  # query 0 matched keyframe 7
    stream.reach(2)  # query 1 had no database: its place is kept, empty
    # query 2's candidate 10 driven the same way: query 0, two steps back, matched 8 +- 1
    scored = stream.history.rescore(np.array([10]), np.array([4.0]))[0]
    assert scored == pytest.approx((2 * 4.0 + 4.0 + 1.0) / 4)  # misaligned: (8 + 6 + 4) / 4
