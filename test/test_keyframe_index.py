"""KeyframeIndex: candidate keys + exact Eq. 4 re-rank agree with brute force."""

from __future__ import annotations

import numpy as np
import pytest

from vbrl_ros.keyframe_index import KeyframeIndex
from vbrl_ros.scoring import WeightedL1Scorer


def _clustered(n: int, d: int, clusters: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    centres = rng.standard_normal((clusters, d)).astype(np.float32)
    labels = rng.integers(0, clusters, n)
    return centres[labels] + 0.5 * rng.standard_normal((n, d)).astype(np.float32), centres


def _weights(d: int, seed: int = 1) -> np.ndarray:
    w = np.random.default_rng(seed).gamma(0.5, size=d)
    w[::7] = 0.0  # switched-off rows
    return (w / w.sum()).astype(np.float32)


def _agreement(index: KeyframeIndex, queries: np.ndarray, masks=None) -> float:
    hits = 0
    for i, q in enumerate(queries):
        allowed = None if masks is None else masks[i]
        hits += index.search(q, 1, allowed)[0][0] == index.exact_search(q, 1, allowed)[0][0]
    return hits / len(queries)


@pytest.fixture(scope="module")
def real_descriptors() -> tuple[np.ndarray, np.ndarray]:
    """A 1-block town driven twice (summer, winter), 32 x 900 scans, default model."""
    import vbrl_ros.simulator as sim
    from vbrl_ros.default_model import load_default_model

    model = load_default_model()
    scorer, featurizer = model.scorer(), model.featurizer()
    town = sim.generate_town(sim.TownConfig(blocks_x=1, blocks_y=1), seed=3)
    rows = []
    for scenario, seed, offset in (("summer_clear", 1, 0.0), ("winter_snow", 2, 1.5)):
        route = sim.make_route(town, sim.RouteConfig(loops=1, spacing_m=2.0, sample_offset_m=offset))
        run = sim.simulate_run(town, route, sim.LidarConfig(beams=32, columns=900), scenario, seed=seed)
        for i in range(len(run)):
            raw = featurizer.describe(run.scan(i).points[:, :3])
            rows.append(scorer.compact(model.standardize(raw)))
    return np.asarray(rows, np.float32), scorer.active_weights


def test_distances_match_the_scorer():
    x, _ = _clustered(300, 500, 10, 0)
    w = _weights(500)
    index = KeyframeIndex(w, key_dim=64)
    index.add_batch(x)
    rows, dist = index.exact_search(x[0] + 0.1, top_k=300)
    reference = WeightedL1Scorer(w.astype(np.float64)).distances(x[0] + 0.1, x)
    np.testing.assert_allclose(dist, reference[rows], rtol=1e-5)
    assert np.all(np.diff(dist) >= 0)


def test_synthetic_clustered_top1_matches_exact():
    x, centres = _clustered(4000, 1024, 200, 2)
    index = KeyframeIndex(_weights(1024), key_dim=128, candidates=64)
    index.add_batch(x)
    rng = np.random.default_rng(3)
    queries = x[rng.integers(0, len(x), 200)] + 0.3 * rng.standard_normal((200, 1024)).astype(np.float32)
    rate = _agreement(index, queries)
    print(f"synthetic clustered Recall@1 vs exact: {rate:.3f}")
    assert rate >= 0.99


@pytest.mark.parametrize("storage", ["float32", "float16"])
def test_real_descriptors_top1_matches_exact(real_descriptors, storage):
    x, w = real_descriptors
    n = len(x)
    index = KeyframeIndex(w, storage=storage)
    index.add_batch(x)
    float32_exact = KeyframeIndex(w)
    float32_exact.add_batch(x)
    masks = []
    for i in range(n):  # leave-one-out and the neighbourhood of the query in its own drive
        mask = np.ones(n, bool)
        mask[max(0, i - 5) : i + 6] = False
        masks.append(mask)
    rate = _agreement(index, x, masks)
    vs32 = np.mean([index.search(q, 1, m)[0][0] == float32_exact.exact_search(q, 1, m)[0][0]
                    for q, m in zip(x, masks)])
    print(f"real descriptors ({storage}) Recall@1 vs exact: {rate:.3f}, vs float32 exact: {vs32:.3f}")
    assert rate >= 0.99
    assert vs32 >= 0.99


def test_exclusion_mask_and_callable_are_respected():
    x, _ = _clustered(2000, 256, 20, 4)
    index = KeyframeIndex(_weights(256), key_dim=32, candidates=32)
    index.add_batch(x)
    forbidden = np.zeros(len(x), bool)
    forbidden[:1500] = True  # excludes most of every cluster
    for q in x[:50]:
        rows, _ = index.search(q, 5, ~forbidden)
        assert len(rows) == 5 and not forbidden[rows].any()
        assert np.array_equal(rows, index.exact_search(q, 5, ~forbidden)[0])
        rows_c, _ = index.search(q, 5, lambda idx: ~forbidden[idx])
        assert np.array_equal(rows_c, rows)
    nothing = np.zeros(len(x), bool)
    assert len(index.search(x[0], 3, nothing)[0]) == 0
    assert len(index.search(x[0], 3, lambda idx: np.zeros(len(idx), bool))[0]) == 0


def test_incremental_add_after_queries():
    x, _ = _clustered(600, 128, 30, 5)
    index = KeyframeIndex(_weights(128), key_dim=32)
    assert len(index.search(x[0], 1)[0]) == 0
    for i, v in enumerate(x[:300]):
        assert index.add(v) == i
    index.search(x[0], 3)
    assert list(index.add_batch(x[300:])) == list(range(300, 600))
    assert len(index) == 600
    for i in (0, 299, 300, 599):
        rows, dist = index.search(x[i], 1)
        assert rows[0] == i and dist[0] == 0.0


def test_state_round_trip(tmp_path):
    x, _ = _clustered(500, 200, 10, 6)
    index = KeyframeIndex(_weights(200), key_dim=40, candidates=20, seed=7, storage="float16")
    index.add_batch(x)
    path = tmp_path / "db.npz"
    np.savez(path, other=np.arange(3), **index.state())
    with np.load(path, allow_pickle=False) as archive:
        restored = KeyframeIndex.from_state(archive)
    assert len(restored) == 500 and restored.storage == "float16" and restored.key_dim == 40
    for q in x[:20] + 0.05:
        a, b = index.search(q, 4), restored.search(q, 4)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    restored.add(x[0])
    assert len(restored) == 501
    with pytest.raises(ValueError, match="lacks"):
        KeyframeIndex.from_state({"index_format": np.array("vbrl_ros.keyframe_index")})


def test_rejects_bad_input():
    index = KeyframeIndex(_weights(50), key_dim=8)
    with pytest.raises(ValueError, match="shape"):
        index.add(np.zeros(49))
    with pytest.raises(ValueError, match="NaN"):
        index.add(np.full(50, np.nan))
    index.add(np.zeros(50))
    with pytest.raises(ValueError, match="boolean mask"):
        index.search(np.zeros(50), 1, np.ones(2, bool))
    assert index.bytes_per_keyframe() == 50 * 4 + 8
