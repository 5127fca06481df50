"""The compiled Eq. 4 kernels: float16 widening and float16/float32 stores agreeing."""

import numpy as np
from numba import njit

from vbrl_ros.model import distance_kernels as wk


@njit
def _widen_all(bits: np.ndarray, out: np.ndarray) -> None:
    for i in range(len(bits)):
        out[i] = wk.as_float32(bits[i])


def test_as_float32_widens_every_finite_half_exactly():
    halves = np.arange(2**16, dtype=np.uint32).astype(np.uint16).view(np.float16)
    halves = halves[np.isfinite(halves)]  # zeros, subnormals, normals of both signs
    out = np.empty(len(halves), np.float32)
    _widen_all(halves.view(np.uint16), out)
    np.testing.assert_array_equal(out.view(np.uint32), halves.astype(np.float32).view(np.uint32))


def test_float16_store_gives_the_float32_sums_of_its_rounded_rows():
    rng = np.random.default_rng(0)
    sectors, width = 6, 37
    rounded = rng.standard_normal((20, sectors * width)).astype(np.float16)
    q = rng.standard_normal(sectors * width).astype(np.float32)
    w = rng.random(width).astype(np.float32)
    rows = np.arange(20, dtype=np.int64)
    results = []
    for store in (rounded.view(np.uint16), rounded.astype(np.float32)):
        d = np.empty(20, np.float32)
        k = np.empty(20, np.int64)
        wk.min_over_shifts(store, rows, q, w, sectors, d, k)
        at = np.empty((20, 1), np.float32)
        wk.at_shifts(store, rows, k[:, None], q, w, sectors, at)
        np.testing.assert_array_equal(at[:, 0], d)  # same sums, bit for bit
        results.append((d, k))
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[0][1], results[1][1])
    x = rounded.astype(np.float64).reshape(20, sectors, width)
    qs = q.astype(np.float64).reshape(sectors, width)
    exact = np.array([[(w * np.abs(np.roll(qs, -s, axis=0) - t)).sum() for s in range(sectors)]
                      for t in x])
    np.testing.assert_allclose(results[0][0], exact.min(axis=1), rtol=1e-5)
    np.testing.assert_array_equal(results[0][1], exact.argmin(axis=1))


def test_nearest_drops_only_what_cannot_win():
    rng = np.random.default_rng(1)
    sectors, width, n = 8, 29, 60
    store = rng.standard_normal((n, sectors * width)).astype(np.float32)
    q = rng.standard_normal(sectors * width).astype(np.float32)
    w = rng.random(width).astype(np.float32)
    rows = np.arange(n, dtype=np.int64)
    d_ref, k_ref = np.empty(n, np.float32), np.empty(n, np.int64)
    wk.min_over_shifts(store, rows, q, w, sectors, d_ref, k_ref)
    # per-row limits: half the rows at exactly their minimum (kept, bit for bit),
    # half just below it (nothing can reach the limit: abandoned)
    limits = np.where(rows % 2 == 0, d_ref, np.nextafter(d_ref, -np.inf)).astype(np.float32)
    d, k = np.empty(n, np.float32), np.empty(n, np.int64)
    wk.nearest(store, rows, q, w, sectors, n, limits, d, k)
    even = rows % 2 == 0
    np.testing.assert_array_equal(d[even], d_ref[even])
    np.testing.assert_array_equal(k[even], k_ref[even])
    assert np.all(k[~even] == -1) and np.all(np.isinf(d[~even]))
    # top-k pruning alone: the 5 nearest come out exact, the others may be abandoned
    inf = np.full(n, np.inf, np.float32)
    wk.nearest(store, rows, q, w, sectors, 5, inf, d, k)
    top = np.argsort(d_ref, kind="stable")[:5]
    np.testing.assert_array_equal(d[top], d_ref[top])
    assert np.all((k == -1) | (d == d_ref))


def test_store_half_rounds_like_numpy():
    rng = np.random.default_rng(2)
    values = np.concatenate([
        rng.standard_normal(5000) * 10.0 ** rng.integers(-9, 5, 5000),  # subnormal to large
        np.float16(rng.standard_normal(200)).astype(np.float64) + 2.0**-25,  # near ties
        [0.0, -0.0, 65504.0, -65504.0, 6.0e-8, 2.9e-8, 3.0e-8],
    ]).astype(np.float32).reshape(1, -1)
    bits = np.empty(values.shape, np.uint16)
    wk.store_half(values, bits)
    np.testing.assert_array_equal(bits, values.astype(np.float16).view(np.uint16))


def test_at_shifts_keeping_the_nearest_rows_drops_only_the_others():
    rng = np.random.default_rng(2)
    sectors, width, n, keep = 8, 29, 80, 5
    store = rng.standard_normal((n, sectors * width)).astype(np.float32)
    q = store[40] + 0.1 * rng.standard_normal(sectors * width).astype(np.float32)
    w = rng.random(width).astype(np.float32)
    rows = rng.permutation(n).astype(np.int64)
    shifts = rng.integers(-1, sectors, (n, 3))
    shifts[:, 0] = rng.integers(0, sectors, n)  # at least one shift per row
    full, kept = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    wk.at_shifts(store, rows, shifts, q, w, sectors, full)
    wk.at_shifts(store, rows, shifts, q, w, sectors, kept, keep)
    nearest = np.argsort(full.min(axis=1), kind="stable")[:keep]
    # the nearest rows keep their best shift and distance, bit for bit (a worse shift may go)
    np.testing.assert_array_equal(kept[nearest].min(axis=1), full[nearest].min(axis=1))
    np.testing.assert_array_equal(kept[nearest].argmin(axis=1), full[nearest].argmin(axis=1))
    finite = np.isfinite(kept)
    np.testing.assert_array_equal(kept[finite], full[finite])  # what is kept is exact
    assert finite.sum() < np.isfinite(full).sum() / 2  # and most of the rest was dropped
