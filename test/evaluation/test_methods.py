"""The evaluation's query stream keeps sequence matching aligned when early queries have no database."""

import numpy as np
import pytest

from vbrl_ros.evaluation.methods import QueryStream
from vbrl_ros.index.keyframe_places import KeyframePlaces
from vbrl_ros.index.sequence_matching import PLACE_SLACK_M


def test_queries_without_a_database_still_take_their_place_in_the_sequence():
    stream = QueryStream(3)
    stream.reach(0)
    stream.history.rescore(np.array([7, 50]), np.array([1.0, 6.0]))  # query 0 matched keyframe 7
    stream.reach(2)  # query 1 had no database: its place is kept, empty
    # query 2's candidate 10 driven the same way: query 0, two steps back, matched 8 +- 1
    scored = stream.history.rescore(np.array([10]), np.array([4.0]))[0]
    assert scored == pytest.approx((2 * 4.0 + 4.0 + 1.0) / 4)  # misaligned: (8 + 6 + 4) / 4


def test_with_places_the_stream_matches_earlier_queries_by_where_they_were():
    places = KeyframePlaces(PLACE_SLACK_M)
    for row in range(50):  # the database's rows along x, 2 m apart
        places.add(row, np.array([2.0 * row, 0.0, 0.0]))
    stream = QueryStream(2, places=places)
    stream.reach(0)  # query 0 stood 3 m off the street, where no keyframe was taken
    stream.rescorer(np.array([10.0, 3.0, 0.0]))(np.array([4, 6, 30, 40]), np.array([9.0, 9.0, 5.0, 6.0]))
    stream.reach(1)
    scored = stream.rescorer(np.array([10.0, 0.0, 0.0]))(np.array([5]), np.array([3.0]))[0]
    assert scored == pytest.approx((2 * 3.0 + 7.5) / 3)  # the earlier term: the pool's median, 7.5
    by_id = QueryStream(2)
    by_id.reach(0)
    by_id.history.rescore(np.array([4, 6, 30, 40]), np.array([9.0, 9.0, 5.0, 6.0]))
    by_id.reach(1)
    assert by_id.history.rescore(np.array([5]), np.array([3.0]))[0] == pytest.approx((2 * 3.0 + 9.0) / 3)


def test_a_trail_stops_at_p1s_exclusion_in_scans_and_p2s_at_the_nodes_seconds(tmp_path):
    """P1: a trail never holds a scan the protocol lets its query match, nor one of that scan's
    submap; P2 (another session's database): as the node's, younger than half
    ``exclude_recent_s`` by the recording's stamps."""
    from vbrl_ros.datasets.kitti_style import write_kitti_style
    from vbrl_ros.datasets.registry import open_source
    from vbrl_ros.detection.settings import DetectorSettings
    from vbrl_ros.evaluation.methods import trail_horizon

    stamps = 1_700_000_000.0 + 0.1 * np.arange(6)
    clouds = [np.ones((10, 4), np.float32) * k for k in range(6)]
    folder = write_kitti_style(tmp_path / "run", clouds, np.tile(np.eye(4), (6, 1, 1)), stamps)
    with open_source(folder, progress=False) as source:
        p1 = trail_horizon(source, [1, 3, 5], 50)
        p2 = trail_horizon(source, [1, 3, 5], None)
    np.testing.assert_array_equal(p1["stamps"], [1, 3, 5])
    assert p1["max_age"] == 25  # half: as far as a candidate's submap reaches
    np.testing.assert_allclose(p2["stamps"], stamps[[1, 3, 5]])
    assert p2["max_age"] == DetectorSettings().exclude_recent_s / 2
