"""The index's key kernels against plain numpy references."""

import numpy as np
import pytest

from vbrl_ros import index_keys as kk


def _blocks(keys: np.ndarray) -> np.ndarray:
    """Row-major uint8 keys (n, key_dim) in the scan's block layout."""
    n, key_dim = keys.shape
    padded = np.zeros((-(-n // kk.BLOCK) * kk.BLOCK, key_dim), np.uint8)
    padded[:n] = keys
    return np.ascontiguousarray(padded.reshape(-1, kk.BLOCK, key_dim).transpose(0, 2, 1))


@pytest.mark.parametrize("n, key_dim, want, levels", [
    (1000, 256, 37, 256),  # full range: |a - q| up to 255 per entry
    (5000, 64, 300, 3),  # few levels: many tied scores, ties go to the lower row
    (130, 8, 500, 256),  # want > n: everything, in any order
    (20000, 32, 1, 256),
])
def test_scan_top_is_the_want_smallest_with_lower_rows_on_ties(n, key_dim, want, levels):
    rng = np.random.default_rng(n)
    keys = rng.integers(0, levels, (n, key_dim)).astype(np.uint8)
    query = rng.integers(0, levels, key_dim).astype(np.uint8)
    for allowed in (np.empty(0, np.bool_), rng.random(n) < 0.3):
        rows = np.empty(want, np.int64)
        scores = np.empty(want, np.int32)
        found = kk.scan_top(_blocks(keys), query, n, allowed, want, rows, scores)
        reference = np.abs(keys.astype(np.int32) - query).sum(axis=1)
        candidates = np.arange(n) if len(allowed) == 0 else np.flatnonzero(allowed)
        expected = candidates[np.lexsort((candidates, reference[candidates]))][:want]
        assert found == len(expected)
        assert np.array_equal(np.sort(rows[:found]), np.sort(expected))
        assert np.array_equal(scores[:found], reference[rows[:found]])


def test_scan_top_reads_only_the_first_n_keyframes():
    rng = np.random.default_rng(3)
    keys = rng.integers(0, 256, (300, 16)).astype(np.uint8)
    query = keys[250].copy()  # distance 0, but beyond n
    rows = np.empty(5, np.int64)
    scores = np.empty(5, np.int32)
    found = kk.scan_top(_blocks(keys), query, 200, np.empty(0, np.bool_), 5, rows, scores)
    assert found == 5 and rows.max() < 200
