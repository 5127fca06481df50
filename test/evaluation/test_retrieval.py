"""Descriptor-agnostic retrieval drivers (P1 / P2)."""

from __future__ import annotations

import numpy as np
import pytest

from vbrl_ros.evaluation import (
    cross_session_retrieval,
    evaluate_cross_session,
    evaluate_online,
    online_retrieval,
    select_top_k,
)


def test_online_sees_only_prefix_and_pads() -> None:
    seen: dict[int, np.ndarray] = {}

    def fn(i: int, cand: np.ndarray) -> np.ndarray:
        seen[i] = cand.copy()
        return np.abs(cand - 0.4 * i).astype(float)

    res = online_retrieval(8, exclude=3, top_k=4, distances_fn=fn)
    assert sorted(seen) == [3, 4, 5, 6, 7]  # queries without a database are not called
    for i, cand in seen.items():
        np.testing.assert_array_equal(cand, np.arange(i - 3 + 1))
    np.testing.assert_array_equal(res.database_limit, [0, 0, 0, 1, 2, 3, 4, 5])
    assert (res.indices[:3] == -1).all() and np.isinf(res.distances[:3]).all()
    np.testing.assert_array_equal(res.indices[3], [0, -1, -1, -1])
    # query 7: |j - 2.8| for j = 0..4 -> 3, 2, 4, 1, 0
    np.testing.assert_array_equal(res.indices[7], [3, 2, 4, 1])
    np.testing.assert_allclose(res.distances[7], [0.2, 0.8, 1.2, 1.8])


def test_select_top_k_ties_inf_nan() -> None:
    idx, dist = select_top_k(np.arange(6), np.array([0.5, 0.1, np.inf, 0.1, 0.1, 0.2]), 2)
    np.testing.assert_array_equal(idx, [1, 3])  # ties: lower index first
    idx, dist = select_top_k(np.arange(3), np.array([np.inf, 0.3, np.inf]), 2)
    np.testing.assert_array_equal(idx, [1, -1])  # inf = not scored, never retrieved
    assert np.isinf(dist[1])
    with pytest.raises(ValueError):
        select_top_k(np.arange(3), np.array([0.1, np.nan, 0.2]), 1)
    with pytest.raises(ValueError):
        select_top_k(np.arange(3), np.array([0.1, 0.2]), 1)


def test_cross_session_driver() -> None:
    rng = np.random.default_rng(5)
    a = rng.uniform(0, 100, (40, 3))
    b = a[::2] + rng.normal(0, 0.3, (20, 3))

    def fn(i: int, cand: np.ndarray) -> np.ndarray:
        return np.linalg.norm(a[cand] - b[i], axis=1)

    res = cross_session_retrieval(20, 40, 5, fn)
    np.testing.assert_array_equal(res.indices[:, 0], np.arange(0, 40, 2))
    m = evaluate_cross_session(b, a, res.indices, res.distances, radius=3.0)
    assert m.recall_at_1 == 1.0 and m.recall_at_5 == 1.0 and m.max_f1 == pytest.approx(1.0)


def test_online_end_to_end_on_a_loop() -> None:
    # Two laps of a 40-scan circle: an oracle on positions is perfect under P1.
    t = np.arange(80) * 2 * np.pi / 40
    p = np.stack([30 * np.cos(t), 30 * np.sin(t), np.zeros_like(t)], axis=1)

    def fn(i: int, cand: np.ndarray) -> np.ndarray:
        return np.linalg.norm(p[cand] - p[i], axis=1)

    res = online_retrieval(80, exclude=10, top_k=5, distances_fn=fn, progress=False)
    m = evaluate_online(p, res.indices, res.distances, radius=3.0, exclude=10)
    assert m.num_queries == 70 and m.num_revisits == 40
    assert m.max_f1 == pytest.approx(1.0) and m.average_precision == pytest.approx(1.0)
