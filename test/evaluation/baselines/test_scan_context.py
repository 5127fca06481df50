"""Scan Context baseline: descriptor, distance/yaw, database prefilter."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from vbrl_ros.evaluation.baselines.scan_context import (
    ScanContextConfig,
    ScanContextDatabase,
    ring_key,
    scan_context,
    scan_context_distance,
    scan_context_distances,
    sector_key,
    sector_key_shift,
)

CFG = ScanContextConfig()  # 20 x 60, 80 m -> rings 4 m, sectors 6 deg
DATA = (Path(__file__).resolve().parents[3] / ".." / "shared" / "data").resolve()


def _polar(r: float, deg: float, z: float) -> list[float]:
    return [r * math.cos(math.radians(deg)), r * math.sin(math.radians(deg)), z]


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _scene(seed: int, n_objects: int = 40) -> np.ndarray:
    """Ground plus random boxes ("buildings", "poles") of random heights."""
    rng = np.random.default_rng(seed)
    ground = np.column_stack([rng.uniform(-60, 60, (4000, 2)), np.full(4000, -2.0)])
    parts = [ground]
    for _ in range(n_objects):
        centre = rng.uniform(-60, 60, 2)
        size = rng.uniform(1, 8, 2)
        height = rng.uniform(0.5, 12)
        pts = rng.uniform(0, 1, (150, 3)) * [*size, height] + [*(centre - size / 2), -2.0]
        parts.append(pts)
    return np.vstack(parts)


def test_hand_made_descriptor() -> None:
    pts = np.array(
        [
            _polar(6.0, 3.0, 1.0),  # ring 1, sector 0, height 3
            _polar(6.0, 3.0, 0.5),  # same bin, lower: the max wins
            _polar(10.0, 93.0, -0.5),  # ring 2, sector 15, height 1.5
            _polar(78.0, 357.0, 4.0),  # ring 19, sector 59 (azimuth -3 deg), height 6
            _polar(30.0, 183.0, -3.0),  # below ground: clipped to 0
            _polar(85.0, 45.0, 1.0),  # beyond max range: dropped
        ]
    )
    d = scan_context(pts)
    assert d.shape == (20, 60) and d.dtype == np.float32
    expected = np.zeros((20, 60), dtype=np.float32)
    expected[1, 0] = 3.0
    expected[2, 15] = 1.5
    expected[19, 59] = 6.0
    np.testing.assert_allclose(d, expected, atol=1e-6)
    np.testing.assert_allclose(ring_key(d)[[1, 2, 19]], [3 / 60, 1.5 / 60, 6 / 60], rtol=1e-6)
    assert sector_key(d).shape == (60,)


def test_config_is_configurable_and_validated() -> None:
    cfg = ScanContextConfig(num_rings=4, num_sectors=8, max_range=10.0, lidar_height=0.0)
    d = scan_context(np.array([_polar(9.0, 100.0, 2.0)]), cfg)
    assert d.shape == (4, 8) and d[3, 2] == pytest.approx(2.0)
    for bad in (
        dict(num_rings=0),
        dict(num_sectors=2.5),
        dict(max_range=-1.0),
        dict(max_range=math.inf),
        dict(lidar_height=math.nan),
    ):
        with pytest.raises(ValueError):
            ScanContextConfig(**bad)
    with pytest.raises(ValueError):
        scan_context(np.zeros((5, 2)))


def test_empty_and_nonfinite_clouds() -> None:
    d = scan_context(np.zeros((0, 3)))
    assert d.shape == (20, 60) and not d.any()
    d_nan = scan_context(np.array([[np.nan, 1.0, 0.0], [1.0, np.inf, 0.0], [1.0, 1.0, np.nan]]))
    assert not d_nan.any()
    # Distances involving empty descriptors are defined (1 = no evidence).
    full = scan_context(_scene(0))
    for a, b in ((d, d), (d, full), (full, d)):
        dist, yaw = scan_context_distance(a, b)
        assert dist == 1.0 and yaw == 0.0
    assert np.isfinite(ring_key(d)).all()


def test_extra_columns_ignored() -> None:
    pts = _scene(1)
    with_intensity = np.column_stack([pts, np.full(len(pts), 7.0)]).astype(np.float32)
    np.testing.assert_allclose(scan_context(with_intensity), scan_context(pts), atol=1e-5)


@pytest.mark.parametrize("k", [0, 1, 7, 29, 30, 31, 45, 59])
def test_rotation_by_k_sectors(k: int) -> None:
    pts = _scene(2)
    yaw = k * CFG.sector_angle
    base = scan_context(pts)
    rotated = scan_context(pts @ _rot_z(yaw).T)
    dist, est = scan_context_distance(rotated, base)
    assert dist < 0.01
    # yaw maps the candidate onto the query, wrapped to (-pi, pi]
    expected = math.atan2(math.sin(yaw), math.cos(yaw))
    if k == 30:
        expected = math.pi
    assert est == pytest.approx(expected, abs=1e-9)
    # The sector-key coarse alignment agrees, and the restricted search too.
    assert sector_key_shift(sector_key(rotated), sector_key(base)) == k
    assert scan_context_distance(rotated, base, search_radius=2) == pytest.approx((dist, est))


def test_different_places_are_far() -> None:
    a, b = scan_context(_scene(3)), scan_context(_scene(4))
    same = scan_context_distance(scan_context(_scene(3) @ _rot_z(0.8).T), a)[0]
    other = scan_context_distance(a, b)[0]
    assert other > 0.1 and other > 5 * same


def test_vectorised_distance_matches_loop() -> None:
    rng = np.random.default_rng(6)
    q = rng.uniform(0, 5, (20, 60)) * (rng.uniform(size=(20, 60)) < 0.4)
    cands = rng.uniform(0, 5, (7, 20, 60)) * (rng.uniform(size=(7, 20, 60)) < 0.4)
    cands[3][:, ::2] = 0  # half the columns empty
    dists, yaws = scan_context_distances(q, cands)
    for m, c in enumerate(cands):
        per_shift = []
        for k in range(60):  # reference: literal definition, one shift at a time
            shifted = np.roll(c, k, axis=1)  # column j <- candidate column j - k
            terms = [
                1 - q[:, j] @ shifted[:, j] / (np.linalg.norm(q[:, j]) * np.linalg.norm(shifted[:, j]))
                for j in range(60)
                if q[:, j].any() and shifted[:, j].any()
            ]
            per_shift.append(np.mean(terms) if terms else 1.0)
        k_best = int(np.argmin(per_shift))
        assert dists[m] == pytest.approx(per_shift[k_best], abs=1e-9)
        assert yaws[m] == pytest.approx(math.remainder(k_best * CFG.sector_angle, 2 * math.pi))


def test_database_finds_the_place() -> None:
    db = ScanContextDatabase(rebuild_min=4)
    scenes = [_scene(100 + i, n_objects=25) for i in range(30)]
    for s in scenes:
        db.add_points(s)
    assert len(db) == 30
    rng = np.random.default_rng(7)
    for target in (0, 17, 29):
        yaw = 1.3
        query_pts = scenes[target] @ _rot_z(yaw).T + rng.normal(0, 0.05, scenes[target].shape)
        match = db.query(scan_context(query_pts), num_candidates=5)
        assert match.index == target
        # An off-grid yaw moves points across sector borders: not 0, but
        # well separated from the other places.
        _, dist, _ = db.query_top_k(scan_context(query_pts), k=2, num_candidates=30)
        assert match.distance == pytest.approx(dist[0]) and dist[0] < 0.5 * dist[1]
        assert abs(math.remainder(match.yaw - yaw, 2 * math.pi)) <= CFG.sector_angle
    # Excluding the target (recent entries / upper index) finds something else.
    assert db.query(db.descriptors[29], exclude_last=1).index != 29
    assert db.query(db.descriptors[17], max_index=17).index < 17
    idx, dist, _ = db.query_top_k(db.descriptors[5], k=3)
    assert idx[0] == 5 and dist[0] == pytest.approx(0.0) and np.all(np.diff(dist) >= 0)


def test_empty_database_and_validation() -> None:
    db = ScanContextDatabase()
    m = db.query(np.zeros((20, 60), np.float32))
    assert m.index == -1 and math.isinf(m.distance)
    db.add(np.ones((20, 60)))
    assert db.query(np.ones((20, 60)), exclude_last=1).index == -1
    with pytest.raises(ValueError):
        db.add(np.ones((20, 59)))
    with pytest.raises(ValueError):
        db.add(np.full((20, 60), np.nan))


def test_prefilter_is_exact_knn_across_rebuilds() -> None:
    """Tree + brute-force tail must equal brute-force kNN on ring keys, whatever the tree state."""
    rng = np.random.default_rng(8)
    db = ScanContextDatabase(rebuild_min=8, rebuild_fraction=0.25)
    keys: list[np.ndarray] = []
    for n in range(1, 120):
        d = (rng.uniform(0, 3, (20, 60)) * (rng.uniform(size=(20, 60)) < 0.3)).astype(np.float32)
        db.add(d)
        keys.append(ring_key(d))
        q = ring_key(rng.uniform(0, 3, (20, 60)).astype(np.float32) * 0.3)
        for limit in {n, max(n - 10, 0), n // 3}:
            got = db.ring_key_candidates(q, 6, limit)
            ref_d = np.linalg.norm(np.array(keys[:limit]) - q, axis=1) if limit else np.empty(0)
            ref = np.lexsort((np.arange(limit), ref_d))[:6]
            np.testing.assert_allclose(ref_d[got], ref_d[ref], rtol=1e-5)
    assert 3 <= db.tree_builds < 40  # lazy, geometric rebuilds - not one per insert


@pytest.mark.skipif(not (DATA / "balm_realworld" / "velodyne").is_dir(), reason="shared data absent")
def test_real_scans_describe_and_self_match() -> None:
    files = sorted((DATA / "balm_realworld" / "velodyne").glob("*.bin"))[:60:6]
    db = ScanContextDatabase()
    for f in files:
        pts = np.fromfile(f, dtype="<f4").reshape(-1, 4)
        d = scan_context(pts, CFG)
        assert np.isfinite(d).all() and d.any()
        db.add(d)
    for i in range(len(files)):
        assert db.query(db.descriptors[i]).index == i
