"""Protocol metrics (docs/design.md section 3) on hand-computed cases."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from vbrl_ros.evaluation import (
    RetrievalResults,
    correct_mask,
    dump_matches,
    evaluate_cross_session,
    evaluate_matches_file,
    evaluate_online,
    evaluate_retrieval,
    load_matches,
    online_database_limits,
    revisit_mask,
)

# Database on a line, 10 m apart: only the scan a query stands on is within 3 m.
DB = np.array([[10.0 * j, 0.0, 0.0] for j in range(10)])


def _six_queries() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q0..q4 stand near DB[q] (revisits); q5 is far from everything.

    top-1 (distance): q0->0 (.1, right), q1->5 (.2, wrong), q2->2 (.3, right),
    q3->3 (.4, right), q4->7 (.5, wrong; its 2nd candidate 4 is right),
    q5->9 (.6, wrong, not a revisit).
    """
    queries = np.vstack([DB[:5] + [1.0, 0.5, 0.0], [[1000.0, 0.0, 0.0]]])
    idx = np.full((6, 5), -1)
    dist = np.full((6, 5), np.inf)
    idx[:, 0] = [0, 5, 2, 3, 7, 9]
    dist[:, 0] = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]
    idx[4, 1], dist[4, 1] = 4, 0.55
    return queries, idx, dist


def test_hand_computed_six_queries() -> None:
    q, idx, dist = _six_queries()
    m = evaluate_retrieval(q, DB, idx, dist, radius=3.0)
    # Sweep (TP, FP) with 5 revisits: .1:(1,0) .2:(1,1) .3:(2,1) .4:(3,1) .5:(3,2) .6:(3,3)
    # precision 1, 1/2, 2/3, 3/4, 3/5, 1/2; recall .2, .2, .4, .6, .6, .6
    # F1 = 1/3, 2/7, 1/2, 2/3, 3/5, 6/11 -> max 2/3 at threshold .4
    # AP = .2*1 + 0 + .2*(2/3) + .2*(3/4) + 0 + 0
    assert m.num_queries == 6
    assert m.num_revisits == 5
    assert m.max_f1 == pytest.approx(2 / 3)
    assert m.threshold_at_max_f1 == pytest.approx(0.4)
    assert m.average_precision == pytest.approx(0.2 + 0.2 * 2 / 3 + 0.2 * 3 / 4)
    assert m.recall_at_100_precision == pytest.approx(0.2)
    assert m.recall_at_1 == pytest.approx(3 / 5)
    assert m.recall_at_5 == pytest.approx(4 / 5)
    np.testing.assert_allclose(m.pr.precision, [1, 1 / 2, 2 / 3, 3 / 4, 3 / 5, 1 / 2])
    np.testing.assert_allclose(m.pr.recall, [0.2, 0.2, 0.4, 0.6, 0.6, 0.6])
    np.testing.assert_allclose(m.pr.thresholds, [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])


def test_recall_at_5_needs_five_columns() -> None:
    q, idx, dist = _six_queries()
    m = evaluate_retrieval(q, DB, idx[:, :2], dist[:, :2], radius=3.0)
    assert m.recall_at_5 is None
    assert m.recall_at_1 == pytest.approx(3 / 5)


def test_ties_are_accepted_together() -> None:
    q = DB[:3] + [0.5, 0.0, 0.0]
    idx = np.array([[0], [9], [2]])
    dist = np.array([[0.1], [0.1], [0.2]])
    m = evaluate_retrieval(q, DB, idx, dist, radius=3.0)
    # .1: TP1 FP1 -> P 1/2 R 1/3 ; .2: TP2 FP1 -> P 2/3 R 2/3
    assert len(m.pr.thresholds) == 2
    assert m.max_f1 == pytest.approx(2 / 3)
    assert m.average_precision == pytest.approx(1 / 3 * 1 / 2 + 1 / 3 * 2 / 3)
    assert m.recall_at_100_precision == 0.0


def test_perfect_retrieval() -> None:
    # Five correct revisits, plus two non-revisit queries whose wrong matches
    # are less confident than every correct one: still perfect.
    q = np.vstack([DB[:5] + [0.0, 1.0, 0.0], [[500.0, 0, 0], [600.0, 0, 0]]])
    idx = np.array([[0], [1], [2], [3], [4], [8], [9]])
    dist = np.array([[0.3], [0.1], [0.5], [0.2], [0.4], [0.8], [0.9]])
    m = evaluate_retrieval(q, DB, idx, dist, radius=3.0)
    assert m.max_f1 == pytest.approx(1.0)
    assert m.average_precision == pytest.approx(1.0)
    assert m.recall_at_100_precision == pytest.approx(1.0)
    assert m.recall_at_1 == pytest.approx(1.0)
    assert m.threshold_at_max_f1 == pytest.approx(0.5)


def test_nothing_correct_and_no_revisits() -> None:
    q, idx, dist = _six_queries()
    wrong = np.full_like(idx, 9)
    m = evaluate_retrieval(q, DB, wrong, dist, radius=3.0)
    assert (m.max_f1, m.average_precision, m.recall_at_100_precision, m.recall_at_1) == (0, 0, 0, 0)
    assert math.isinf(m.threshold_at_max_f1)
    far = q + 5000.0
    m = evaluate_retrieval(far, DB, idx, dist, radius=3.0)
    assert m.num_revisits == 0 and math.isnan(m.max_f1) and math.isnan(m.recall_at_1)


def test_missing_candidates_are_never_accepted() -> None:
    q, idx, dist = _six_queries()
    idx[0, 0] = -1  # q0's right answer withdrawn: recall drops, precision unaffected
    m = evaluate_retrieval(q, DB, idx, dist, radius=3.0)
    assert m.recall_at_1 == pytest.approx(2 / 5)
    assert m.pr.thresholds[0] == pytest.approx(0.2)


def _p1_path() -> np.ndarray:
    # Scans 10 m apart; scan 5 is 0.5 m from scan 4 (inside the window, E=3),
    # scan 9 is back at scan 0 (outside it).
    p = np.array([[10.0 * i, 0.0, 0.0] for i in range(10)])
    p[5] = p[4] + [0.5, 0, 0]
    p[9] = p[0] + [0.5, 0, 0]
    return p


def test_p1_database_limits() -> None:
    np.testing.assert_array_equal(online_database_limits(6, 3), [0, 0, 0, 1, 2, 3])
    with pytest.raises(ValueError):
        online_database_limits(6, 0)


def test_p1_exclusion_window() -> None:
    p = _p1_path()
    lim = online_database_limits(len(p), 3)
    expected = np.zeros(10, dtype=bool)
    expected[9] = True
    np.testing.assert_array_equal(revisit_mask(p, p, 3.0, lim), expected)
    # Without the window scan 5 would be a revisit of scan 4.
    assert revisit_mask(p, p, 3.0, np.arange(10))[5]

    idx = np.zeros((10, 1), dtype=int)  # everyone answers scan 0 ...
    dist = np.full((10, 1), 0.9)
    idx[5, 0], dist[5, 0] = 4, 0.01  # ... except 5, which answers inside its window
    idx[9, 0], dist[9, 0] = 0, 0.1
    m = evaluate_online(p, idx, dist, radius=3.0, exclude=3)
    assert m.num_queries == 7 and m.num_revisits == 1
    # .01: FP (in-window match is wrong, not dropped); .1: TP -> P 1/2 R 1
    assert m.max_f1 == pytest.approx(2 / 3)
    assert m.average_precision == pytest.approx(0.5)
    assert m.recall_at_100_precision == 0.0
    assert m.recall_at_1 == 1.0

    # Scan 8 moved next to scan 9: answering it is close but inside the
    # window, so never correct; queries 0..2 have no database and whatever
    # they return is ignored (never accepted).
    p8 = p.copy()
    p8[8] = p[9] + [0.2, 0, 0]
    answers = np.full((10, 1), 8)
    assert not correct_mask(p8, p8, answers, 3.0, lim)[9, 0]
    assert correct_mask(p8, p8, answers, 3.0, np.full(10, 10))[9, 0]
    idx[0, 0], dist[0, 0] = 9, 0.0
    m = evaluate_online(p, idx, dist, radius=3.0, exclude=3)
    assert m.num_queries == 7 and m.max_f1 == pytest.approx(2 / 3)


def test_revisit_mask_matches_brute_force() -> None:
    rng = np.random.default_rng(3)
    q = rng.uniform(0, 20, (80, 3))
    db = rng.uniform(0, 20, (60, 3))
    lim = rng.integers(0, 61, 80)
    d = np.linalg.norm(q[:, None] - db[None], axis=2)
    visible = np.arange(60)[None, :] < lim[:, None]
    np.testing.assert_array_equal(revisit_mask(q, db, 2.5, lim), ((d < 2.5) & visible).any(axis=1))


def test_p2_alignment_used_for_ground_truth() -> None:
    rng = np.random.default_rng(4)
    a = rng.uniform(-50, 50, (30, 3))
    yaw = 0.7
    t_ba = np.eye(4)
    t_ba[:3, :3] = [[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]]
    t_ba[:3, 3] = [100.0, -40.0, 2.0]
    b = a @ t_ba[:3, :3].T + t_ba[:3, 3]  # same places, session B's frame
    idx = np.arange(30)[:, None]
    dist = rng.uniform(0, 1, (30, 1))
    unaligned = evaluate_cross_session(b, a, idx, dist, radius=3.0)
    aligned = evaluate_cross_session(b, a, idx, dist, radius=3.0, query_alignment=np.linalg.inv(t_ba))
    assert unaligned.num_revisits == 0
    assert aligned.num_revisits == 30 and aligned.num_queries == 30
    assert aligned.max_f1 == pytest.approx(1.0) and aligned.average_precision == pytest.approx(1.0)


def test_shape_validation() -> None:
    q, idx, dist = _six_queries()
    with pytest.raises(ValueError):
        evaluate_retrieval(q, DB, idx, dist[:, :2], radius=3.0)
    with pytest.raises(ValueError):
        evaluate_retrieval(q[:, :2], DB, idx, dist, radius=3.0)
    with pytest.raises(ValueError):
        evaluate_retrieval(q, DB, idx, dist, radius=0.0)


def test_json_round_trip(tmp_path) -> None:
    p = _p1_path()
    lim = online_database_limits(10, 3)
    idx = np.full((10, 5), -1)
    dist = np.full((10, 5), np.inf)
    for i in range(3, 10):
        idx[i] = [0, 1, 2, 3, 4]
        dist[i] = 0.05 * i + np.arange(5) * 0.01
    idx[6, 0], dist[6, 0] = -1, np.inf  # a query whose method found nothing
    res = RetrievalResults(idx, dist, lim)
    path = tmp_path / "matches.json"
    dump_matches(path, res)
    entries = json.loads(path.read_text())
    assert [e["query"] for e in entries] == list(range(3, 10))  # no entry without a database
    assert entries[0] == {"query": 3, "match": 0, "distance": pytest.approx(0.15)}
    assert entries[3] == {"query": 6, "match": -1, "distance": None}

    loaded = load_matches(path, 10)
    np.testing.assert_array_equal(loaded.indices[:, 0], idx[:, 0])
    np.testing.assert_allclose(loaded.distances[:, 0], dist[:, 0])
    direct = evaluate_online(p, idx[:, :1], dist[:, :1], 3.0, 3).summary()
    assert evaluate_matches_file(path, p, 3.0, exclude=3).summary() == direct

    # Top-K lists survive too (Recall@5), and docs/design.md's "score" key is read.
    dump_matches(path, res, include_top_k=True)
    assert evaluate_matches_file(path, p, 3.0, exclude=3).summary() == evaluate_online(p, idx, dist, 3.0, 3).summary()
    path.write_text(json.dumps([{"query": 9, "match": 0, "score": 0.2}]))
    assert evaluate_matches_file(path, p, 3.0, exclude=3).recall_at_1 == 1.0


def test_json_p2_and_validation(tmp_path) -> None:
    q, idx, dist = _six_queries()
    res = RetrievalResults(idx, dist, np.full(6, len(DB)))
    path = tmp_path / "p2.json"
    dump_matches(path, res, include_top_k=True)
    # Padding is not written, so the top-K width is passed explicitly here.
    m = evaluate_matches_file(path, q, 3.0, database_positions=DB, top_k=5)
    assert m.summary() == evaluate_retrieval(q, DB, idx, dist, 3.0).summary()
    path.write_text(json.dumps([{"query": 1, "match": 0, "distance": 0.1}] * 2))
    with pytest.raises(ValueError, match="twice"):
        load_matches(path, 6)
    path.write_text(json.dumps([{"query": 7, "match": 0, "distance": 0.1}]))
    with pytest.raises(ValueError, match="out of range"):
        load_matches(path, 6)
