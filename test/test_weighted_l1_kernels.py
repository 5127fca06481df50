"""The compiled Eq. 4 kernels: float16 widening and float16/float32 stores agreeing."""

import numpy as np
from numba import njit

from vbrl_ros import weighted_l1_kernels as wk


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
