"""The index's key kernels against plain numpy references."""

import numpy as np
import pytest

from vbrl_ros.index import keys as kk


def _blocks(codes: np.ndarray) -> np.ndarray:
    """Row-major nibble codes (n, key_dim) in the scan's packed block layout."""
    pairs = kk.packed(codes)
    n, width = pairs.shape
    padded = np.zeros((-(-n // kk.BLOCK) * kk.BLOCK, width), np.uint8)
    padded[:n] = pairs
    return np.ascontiguousarray(padded.reshape(-1, kk.BLOCK, width).transpose(0, 2, 1))


def test_packing_round_trips_odd_and_even_widths():
    rng = np.random.default_rng(0)
    for key_dim in (1, 7, 8, 255):
        codes = rng.integers(0, 16, (5, key_dim)).astype(np.uint8)
        assert kk.packed(codes).shape == (5, -(-key_dim // 2))
        np.testing.assert_array_equal(kk.unpacked(kk.packed(codes), key_dim), codes)


@pytest.mark.parametrize("n, key_dim, want, levels", [
    (1000, 1024, 37, 16),  # full range at the longest key: |a - q| up to 15 per entry
    (5000, 63, 300, 3),  # few levels: many tied scores, ties go to the lower row; odd width
    (130, 8, 500, 16),  # want > n: everything
    (20000, 32, 1, 16),
])
def test_scan_top_is_the_want_smallest_with_lower_rows_on_ties(n, key_dim, want, levels):
    rng = np.random.default_rng(n)
    keys = rng.integers(0, levels, (n, key_dim)).astype(np.uint8)
    query = rng.integers(0, levels, key_dim).astype(np.uint8)
    for allowed in (np.empty(0, np.bool_), rng.random(n) < 0.3):
        rows = np.empty(want, np.int64)
        scores = np.empty(want, np.int32)
        found = kk.scan_top(_blocks(keys), kk.padded(query), n, allowed, want, rows, scores)
        reference = np.abs(keys.astype(np.int32) - query).sum(axis=1)
        candidates = np.arange(n) if len(allowed) == 0 else np.flatnonzero(allowed)
        expected = candidates[np.lexsort((candidates, reference[candidates]))][:want]
        assert found == len(expected)
        assert np.array_equal(rows[:found], np.sort(expected))  # in ascending row order
        assert np.array_equal(scores[:found], reference[rows[:found]])


def test_scan_top_reads_only_the_first_n_keyframes():
    rng = np.random.default_rng(3)
    keys = rng.integers(0, 16, (300, 16)).astype(np.uint8)
    query = keys[250].copy()  # distance 0, but beyond n
    rows = np.empty(5, np.int64)
    scores = np.empty(5, np.int32)
    found = kk.scan_top(_blocks(keys), kk.padded(query), 200, np.empty(0, np.bool_), 5, rows, scores)
    assert found == 5 and rows.max() < 200


def test_refine_scores_are_nibble_l1_distances_of_the_chosen_rows():
    rng = np.random.default_rng(5)
    codes = rng.integers(1, 16, (300, 37)).astype(np.uint8)  # odd width: padded with 8
    query = rng.integers(1, 16, 37).astype(np.uint8)
    rows = np.sort(rng.choice(300, 50, replace=False)).astype(np.int64)
    out = np.empty(len(rows), np.int32)
    kk.refine_scores(kk.packed(codes), rows, kk.padded(query), out)
    expected = np.abs(codes[rows].astype(np.int32) - query).sum(axis=1)
    np.testing.assert_array_equal(out, expected)


def test_raw_keys_group_the_sector_sums():
    rng = np.random.default_rng(6)
    sectors, width, groups = 4, 30, 7
    x = rng.standard_normal((20, sectors * width)).astype(np.float32)
    group = rng.integers(0, groups, width)
    signed = rng.standard_normal(width).astype(np.float32)
    keys = np.empty((20, 3), np.float32)
    out = np.empty((20, groups), np.float32)
    none = np.empty((0, sectors))  # no harmonics: the features are the column sums
    kk.raw_keys(x, sectors, none, none, group % 3, signed, group, signed, np.zeros(width, np.int64),
                signed, keys, out, np.empty((20, sectors, 0), np.float32))
    columns = x.reshape(20, sectors, width).sum(axis=1) * signed
    expected = np.stack([columns[:, group == g].sum(axis=1) for g in range(groups)], axis=1)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-5)


def test_yaw_bounds_are_the_shifted_l1_distances_at_the_given_shifts():
    rng = np.random.default_rng(7)
    sectors, groups = 6, 5
    keys = rng.standard_normal((40, sectors, groups)).astype(np.float32)
    query = rng.standard_normal((sectors, groups)).astype(np.float32)
    rows = np.array([3, 17, 39], np.int64)
    for shifts in (np.broadcast_to(np.arange(sectors), (3, sectors)),  # every shift
                   np.array([[0, 5], [2, 3], [4, 4]], np.int64)):
        out = np.empty(shifts.shape, np.float32)
        kk.yaw_bounds(keys, rows, query, shifts, out)
        expected = [[np.abs(np.roll(query, -k, axis=0) - keys[row]).sum() for k in ks]
                    for row, ks in zip(rows, shifts)]
        np.testing.assert_allclose(out, expected, rtol=1e-5)
