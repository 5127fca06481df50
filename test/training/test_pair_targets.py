"""Pair targets: Eq. 3 on revisit / non-revisit scan pairs, and the model ``fit_pairs`` builds.

Structure (gaps, sources, counts) is checked on synthetic descriptors that encode their own
keyframe: every feature of keyframe i is i, so a pair's X row is |i - j| in every column
whatever the sector shift. Content is checked on a simulated drive that revisits its streets.
"""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vbrl_ros.features.featurizer import Featurizer
from vbrl_ros.training.fit import fit_pairs, standardization
from vbrl_ros.training.pair_targets import DIFFERENT_PLACE_M, HARD_NEGATIVES, MIN_GAP, SAME_PLACE_M, pair_targets
from vbrl_ros.training.presets import recognition_config

sim = pytest.importorskip("vbrl_ros.simulator")

CONFIG = recognition_config(rings=10, sectors=12)
LAYOUT = Featurizer(CONFIG).layout


def two_laps(n_per_lap: int = 100, spacing: float = 2.0) -> np.ndarray:
    """(2 n, 3) positions: a circle driven twice, one keyframe every ``spacing`` metres."""
    radius = n_per_lap * spacing / (2 * np.pi)
    angle = np.tile(np.arange(n_per_lap) * 2 * np.pi / n_per_lap, 2)
    return np.column_stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(len(angle))])


def index_descriptors(n: int, base: float = 0.0) -> np.ndarray:
    """Keyframe i's descriptor is base + i in every feature."""
    return np.repeat(base + np.arange(n, dtype=np.float64)[:, None], LAYOUT.dimension, axis=1)


def revisits(positions: np.ndarray) -> set[tuple[int, int]]:
    """Every pair within SAME_PLACE_M and at least MIN_GAP keyframes apart, by brute force."""
    d = np.linalg.norm(positions[:, None, :2] - positions[None, :, :2], axis=2)
    return {(i, j) for i, j in zip(*np.nonzero(d < SAME_PLACE_M)) if j - i >= MIN_GAP}


def test_same_place_pairs_are_every_revisit_at_least_min_gap_keyframes_apart():
    """Neighbours on one pass (2 m apart, within SAME_PLACE_M) are not revisits; every pair
    across the laps is, exactly once."""
    positions = two_laps()
    pairs = pair_targets(index_descriptors(len(positions)), positions, np.zeros(len(positions), int), LAYOUT)
    same = pairs.Y[:, 0] == 1
    gaps = pairs.X[:, 0]
    np.testing.assert_array_equal(pairs.X, np.repeat(gaps[:, None], LAYOUT.dimension, axis=1))
    assert gaps[same].min() >= MIN_GAP
    expected = revisits(positions)
    assert len(expected) > 200
    assert np.linalg.norm(positions[1, :2] - positions[0, :2]) < SAME_PLACE_M  # neighbours are close
    assert pairs.n_same == len(expected)
    assert sorted(gaps[same]) == sorted(float(j - i) for i, j in expected)
    # each keyframe: its nearest far places and as many random far ones
    assert pairs.n_different == 2 * HARD_NEGATIVES * len(positions)
    far = np.linalg.norm(positions[:, None, :2] - positions[None, :, :2], axis=2) > DIFFERENT_PLACE_M
    assert far.any(axis=1).all()


def test_pairs_never_cross_sources():
    """Two sessions over the same positions (each in its own frame): no pair mixes them,
    though their positions coincide."""
    positions = two_laps()
    n = len(positions)
    descriptors = np.concatenate([index_descriptors(n), index_descriptors(n, base=10_000.0)])
    sources = np.repeat([0, 1], n)
    pairs = pair_targets(descriptors, np.concatenate([positions, positions]), sources, LAYOUT)
    assert pairs.X.max() < n  # a cross-source pair differs by ~10 000
    assert pairs.n_same == 2 * len(revisits(positions))
    assert pairs.n_different == 2 * 2 * HARD_NEGATIVES * n


def test_keyframes_without_a_pose_take_no_part():
    positions = two_laps()
    n = len(positions)
    positions[::3] = np.nan
    descriptors = index_descriptors(n)
    descriptors[::3] = 10_000.0  # a pair with one of them differs by ~10 000
    pairs = pair_targets(descriptors, positions, np.zeros(n, int), LAYOUT)
    assert np.isfinite(pairs.X).all() and pairs.X.max() < n
    assert pairs.n_same > 0 and pairs.n_different == 2 * HARD_NEGATIVES * (n - len(range(0, n, 3)))


@pytest.mark.parametrize("case", ["straight", "no poses", "one source too small"])
def test_no_revisits_is_an_error_naming_the_option(case):
    n = 60
    positions = np.column_stack([np.arange(n) * 2.0, np.zeros(n), np.zeros(n)])  # never back
    sources = np.zeros(n, int)
    if case == "no poses":
        positions = np.full((n, 3), np.nan)
    if case == "one source too small":
        positions, sources = two_laps(), np.arange(200)  # every keyframe its own source
        n = 200
    with pytest.raises(ValueError, match="--targets pairs needs revisits"):
        pair_targets(index_descriptors(n), positions, sources, LAYOUT)


@pytest.fixture(scope="module")
def drive():
    """Raw recognition descriptors and positions of a two-loop drive (3 m spacing)."""
    town = sim.generate_town(sim.TownConfig(blocks_x=2, blocks_y=2), seed=0)
    run = sim.simulate_run(town, sim.make_route(town, sim.RouteConfig(loops=2, spacing_m=3.0)),
                           sim.LidarConfig(beams=16, columns=360), "summer_clear", seed=1)
    featurizer = Featurizer(CONFIG)
    return np.stack([featurizer.describe(scan.points) for scan in run]), run.poses[:, :3, 3]


def test_pairs_of_a_simulated_drive_tell_revisits_from_other_places(drive):
    """X is non-negative, Y one-hot with both classes, and revisits differ less than other places."""
    descriptors, positions = drive
    mean, scale = standardization(descriptors, LAYOUT.tie_of_row)
    pairs = pair_targets((descriptors - mean) / scale, positions, np.zeros(len(positions), int), LAYOUT)
    assert pairs.X.shape == (pairs.n_same + pairs.n_different, LAYOUT.dimension)
    assert (pairs.X >= 0).all() and np.isfinite(pairs.X).all()
    np.testing.assert_array_equal(pairs.Y.sum(axis=1), 1.0)
    assert set(np.unique(pairs.Y)) == {0.0, 1.0}
    assert pairs.n_same == int(pairs.Y[:, 0].sum()) > 10 and pairs.n_different == int(pairs.Y[:, 1].sum()) > 100
    assert pairs.n_same == len(revisits(positions))
    same, different = pairs.X[pairs.Y[:, 0] == 1].mean(), pairs.X[pairs.Y[:, 1] == 1].mean()
    assert same < 0.8 * different, (same, different)


def test_the_pair_differences_take_each_pair_at_its_best_sector_shift(drive):
    """A revisit turned around (its descriptor rolled by half the sectors) gives the same X row."""
    descriptors, positions = drive
    mean, scale = standardization(descriptors, LAYOUT.tie_of_row)
    z = (descriptors - mean) / scale
    rows = LAYOUT.sector_rows
    turned = z.copy()
    half = LAYOUT.sectors // 2
    second = np.arange(len(z)) >= len(z) // 2
    turned[np.ix_(second, rows.ravel())] = np.roll(z[second][:, rows.ravel()].reshape(-1, *rows.shape),
                                                   half, axis=1).reshape(int(second.sum()), -1)
    sources = np.zeros(len(z), int)
    a, b = pair_targets(z, positions, sources, LAYOUT), pair_targets(turned, positions, sources, LAYOUT)
    same_a, same_b = a.X[a.Y[:, 0] == 1], b.X[b.Y[:, 0] == 1]
    np.testing.assert_allclose(np.sort(same_a.sum(axis=1)), np.sort(same_b.sum(axis=1)), rtol=1e-5)


def test_fit_pairs_builds_a_same_or_different_place_model(drive):
    descriptors, positions = drive
    result = fit_pairs(descriptors, positions, np.zeros(len(positions), int), CONFIG, metadata={"note": "x"})
    model = result.model
    assert model.scenarios == ["same_place", "different_place"]
    assert model.W.shape == (LAYOUT.dimension, 2) and np.isfinite(model.W).all()
    assert model.metadata["targets"] == "pairs" and model.metadata["note"] == "x"
    assert model.metadata["pairs"]["same_place"] == len(revisits(positions))
    assert model.metadata["pairs"]["different_place"] > 0 and model.metadata["scans"] == len(descriptors)
    assert model.config == CONFIG
    assert model.w_modality.sum() == pytest.approx(1.0) and model.w_voxel.sum() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="--targets pairs"):
        fit_pairs(descriptors[:40], positions[:40], np.zeros(40, int), CONFIG)
