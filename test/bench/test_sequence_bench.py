"""The sequence-matching benchmark times both ways of matching on one walk and prints them as rows."""

import numpy as np

from vbrl_ros.bench import sequence
from vbrl_ros.bench.speed_targets import sequence_rows


def test_the_walk_keeps_its_spacing_inside_the_area():
    positions = sequence.walk(500)
    steps = np.linalg.norm(np.diff(positions[:, :2], axis=0), axis=1)
    unfolded = steps < sequence.AREA_M / 2  # the fold jumps across the square
    np.testing.assert_allclose(steps[unfolded], sequence.SPACING_M)
    assert positions.min() >= 0 and positions.max() < sequence.AREA_M


def test_both_ways_are_timed_and_tabled():
    results = sequence.measure(keyframes=2_000, repeats=20)
    assert results["keyframes"] == 2_000
    for key in ("by_id_ms", "by_id_p95_ms", "by_place_ms", "by_place_p95_ms", "add_place_ms"):
        assert results[key] > 0
    rows = sequence_rows(results)
    assert [r[0] for r in rows] == ["sequence matching by id", "sequence matching by place (odometry)",
                                    "a keyframe's place stored"]
    assert "2,000 stored" in rows[1][1]
