"""Rotation-invariant column features: the DFT over the sectors, its magnitudes and their bound."""

import numpy as np
import pytest

from vbrl_ros.index import harmonics as hm
from vbrl_ros.index.keyframe_index import KeyframeIndex
from vbrl_ros.index.parameters import IndexParameters


def _features(x: np.ndarray, sectors: int, width: int, harmonics: int) -> np.ndarray:
    cosines, sines = hm.dft_tables(sectors, harmonics)
    out = np.empty(width * (harmonics + 1), np.float32)
    hm.column_features(x, sectors, width, cosines, sines, np.empty((harmonics, width)),
                       np.empty((harmonics, width)), out)
    return out.reshape(harmonics + 1, width)


@pytest.mark.parametrize("sectors", [6, 7, 30])
def test_features_are_the_column_sums_and_the_dft_magnitudes(sectors):
    width, harmonics = 9, sectors // 2
    x = np.random.default_rng(sectors).standard_normal(sectors * width).astype(np.float32)
    spectrum = np.fft.rfft(x.reshape(sectors, width).astype(np.float64), axis=0)
    got = _features(x, sectors, width, harmonics)
    np.testing.assert_allclose(got[0], x.reshape(sectors, width).sum(axis=0), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(got[1:], np.abs(spectrum[1 : harmonics + 1]), rtol=1e-5, atol=1e-5)


def test_features_do_not_change_when_the_scan_turns_by_whole_sectors():
    sectors, width = 12, 5
    x = np.random.default_rng(1).standard_normal(sectors * width).astype(np.float32)
    turned = np.roll(x.reshape(sectors, width), 5, axis=0).ravel()
    a, b = _features(x, sectors, width, 6), _features(turned, sectors, width, 6)
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-5)


def test_each_feature_bounds_the_column_l1_distance_at_every_shift():
    # | |A[m]| - |B[m]| | <= min over shifts of the column's L1 distance, also for near
    # matches (a turned copy with a little noise), where the bound is tightest
    sectors, width = 10, 4
    rng = np.random.default_rng(2)
    for trial in range(50):
        a = rng.standard_normal(sectors * width).astype(np.float32)
        b = (np.roll(a.reshape(sectors, width), trial % sectors, axis=0).ravel()
             + (0.05 if trial % 2 else 2.0) * rng.standard_normal(sectors * width)).astype(np.float32)
        fa, fb = _features(a, sectors, width, 5), _features(b, sectors, width, 5)
        columns_a, columns_b = a.reshape(sectors, width), b.reshape(sectors, width)
        closest = np.min([np.abs(np.roll(columns_a, k, axis=0) - columns_b).sum(axis=0)
                          for k in range(sectors)], axis=0)  # per column, its own best shift
        assert np.all(np.abs(fa - fb) <= closest * (1 + 1e-5) + 1e-5)


def test_a_key_takes_harmonics_only_when_the_columns_do_not_fill_it():
    assert hm.harmonics_for(256, 7872, 1) == 0  # Cartesian: column sums, as always
    assert hm.harmonics_for(256, 400, 24) == 0  # a wide polar descriptor too
    assert hm.harmonics_for(256, 40, 30) == 6  # 280 features for 256 entries
    assert hm.harmonics_for(1024, 40, 30) == 15  # at most S / 2: the rest mirror them
    assert hm.feature_count(40, 30) == 40 * 16 and hm.feature_count(50, 1) == 50


def test_coefficients_of_a_column_sum_to_its_weight():
    weights = np.array([0.5, 0.2, 0.3])
    coefficients, means = hm.feature_coefficients(weights, 24, 4)
    np.testing.assert_allclose(coefficients.reshape(5, 3).sum(axis=0), weights)
    assert np.all(means.reshape(5, 3)[0] == 0) and np.all(means.reshape(5, 3)[1:] > 0)
    # every feature gets the column sum's nominal spread
    _, spread = hm.nominal_statistics(24, 4)
    scaled = coefficients.reshape(5, 3) * spread[:, None]
    np.testing.assert_allclose(scaled, np.broadcast_to(scaled[0], scaled.shape))


def test_a_narrow_descriptor_tells_places_apart_by_their_harmonics():
    # 150 places whose columns have the same sums: only where things are around the
    # sensor tells them apart, which the column sums alone (key_dim = R) cannot see
    sectors, columns = 24, 8
    rng = np.random.default_rng(11)
    centres = rng.standard_normal((150, sectors, columns))
    centres += 3.0 * rng.standard_normal(columns) - centres.mean(axis=1, keepdims=True)
    places = rng.integers(0, 150, 3000)
    noisy = centres[places] + 0.3 * rng.standard_normal((3000, sectors, columns))
    x = np.stack([np.roll(v, int(k), axis=0) for v, k in zip(noisy, rng.integers(0, sectors, 3000))])
    x = x.reshape(3000, -1).astype(np.float32)
    weights = np.tile(rng.uniform(0.5, 1.0, columns) / columns, sectors).astype(np.float32)
    queries = [np.roll(x[i].reshape(sectors, -1), int(rng.integers(0, sectors)), axis=0).ravel()
               + 0.2 * rng.standard_normal(x.shape[1]).astype(np.float32)
               for i in rng.integers(0, 3000, 60)]
    options = {"sectors": sectors, "candidates": 64, "rerank": 64}
    harmonics = KeyframeIndex(weights, IndexParameters(**options))
    sums = KeyframeIndex(weights, IndexParameters(key_dim=columns, refine_dim=0, **options))
    assert harmonics.parameters.key_dim == columns * (1 + sectors // 2)  # every feature its own entry
    harmonics.add_batch(x), sums.add_batch(x)
    for q in queries:  # top 3 as brute force has them, distances to the bit
        found, exact = harmonics.search_with_yaw(q, 3), harmonics.search_with_yaw(q, 3, exact=True)
        for field in ("indices", "distances", "shifts"):
            np.testing.assert_array_equal(getattr(found, field), getattr(exact, field))
    agree = np.mean([sums.search(q, 1)[0][0] == sums.exact_search(q, 1)[0][0] for q in queries])
    assert agree < 0.5  # what the harmonics are for
