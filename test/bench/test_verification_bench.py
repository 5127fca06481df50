"""The verification benchmark: real simulated revisits, real verification, a table that adds up."""

from __future__ import annotations

import numpy as np
import pytest

from vbrl_ros.bench.verification import (
    REVISIT_M,
    UNRELATED_M,
    format_table,
    keyframe_pairs,
    measure,
)


@pytest.fixture(scope="module")
def pairs():
    return keyframe_pairs(revisits=2, unrelated=1)


def test_pairs_are_revisits_one_of_them_reversed_and_an_unrelated_place(pairs):
    assert [p.revisit for p in pairs] == [True, True, False]
    assert pairs[0].reversed  # the other way round comes first: it is the hard case
    for p in pairs:
        gap = np.linalg.norm(p.truth[:2, 3])
        assert (REVISIT_M[0] < gap < REVISIT_M[1]) if p.revisit else gap > UNRELATED_M
        assert 3000 < len(p.query) < 10000 and p.query.dtype == np.float32  # one point per voxel


def test_stages_add_up_and_the_decisions_are_right(pairs):
    results = measure(pairs, repeats=1)
    cpu = results["cpu_ms"]
    for column in ("revisits", "unrelated", "all", "all, query shared"):
        stages = {k: v for k, v in cpu[column].items() if k != "total"}
        assert {"prepare", "heading search", "icp fine", "agreement"} <= set(stages)
        assert all(v >= 0 for v in stages.values())
        # the stages cover verify_loop from its first line to its result
        assert sum(stages.values()) == pytest.approx(cpu[column]["total"], rel=0.15, abs=2.0)
    accuracy = results["accuracy"]
    assert accuracy["revisits_accepted"] == 2 and accuracy["unrelated_accepted"] == 0
    assert accuracy["translation_error_m"]["max"] < 0.1 and accuracy["rotation_error_deg"]["max"] < 0.5
    table = format_table(results)
    assert "heading search" in table and "2/2 revisits (1 reversed)" in table
