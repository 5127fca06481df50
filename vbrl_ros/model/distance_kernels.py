"""Compiled Eq. 4 distances under circular sector shifts (the exact part of retrieval).

A compact descriptor is sector-major: ``x.reshape(S, R)`` holds the same R
active columns for each of the S sectors (S = 1 for the Cartesian grid), and
the column weights ``w`` (R,) are tied across sectors. The distance at shift
``k`` is

    D_k(q, t) = sum_s sum_r w_r |q[(s + k) % S, r] - t[s, r]|

and the rotation-minimised distance is ``min_k D_k``. Every kernel here sums a
given (template, shift) pair in the same order (template sector by template
sector, each a vectorised sum over r), so the brute-force scan and the index's
re-rank at chosen shifts return bitwise-identical float32 values — equality
between the two is meaningful, not "up to rounding".

float16 storage: numba has no float16 type, so such stores are passed as
their ``uint16`` bit patterns and :func:`as_float32` widens each entry inside
the sums (one ``fpext half`` in LLVM: exact, and vectorised to the CPU's
half-to-float conversion where it has one). Every kernel compiles once per
store dtype, so float32 and float16 stores run the same code. All kernels are
single-threaded and release the GIL.
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic


@intrinsic
def as_float32(typingctx, value):
    """float32 of a float32 (itself) or of a uint16 holding float16 bits (exact widening)."""
    if value == types.float32:
        return types.float32(value), lambda context, builder, signature, args: args[0]
    if value == types.uint16:
        def widen(context, builder, signature, args):
            return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())
        return types.float32(value), widen
    return None


@intrinsic
def as_half_bits(typingctx, value):
    """The float16 bit pattern (uint16) of a float32, rounded to nearest even like numpy."""
    if value != types.float32:
        return None

    def narrow(context, builder, signature, args):
        return builder.bitcast(builder.fptrunc(args[0], ir.HalfType()), ir.IntType(16))
    return types.uint16(value), narrow


@njit(cache=True, nogil=True)
def store_half(src: np.ndarray, out_bits: np.ndarray) -> None:
    """out_bits[i, j] = float16 bits of src[i, j] ((m, d) float32 -> (m, d) uint16 view).

    numpy's float32 -> float16 cast is a scalar loop (~0.2 ms per 23k-value
    descriptor here); this one is vectorised by the CPU's conversion.
    """
    for i in range(src.shape[0]):
        row, out = src[i], out_bits[i]
        for j in range(len(row)):
            out[j] = as_half_bits(row[j])


@njit(cache=True, nogil=True, fastmath=True)
def _sector_l1(q: np.ndarray, q_start: int, t: np.ndarray, t_start: int,
               w: np.ndarray) -> np.float32:
    """sum_r w[r] |q[q_start + r] - t[t_start + r]| (float32; t float32 or float16 bits).

    Deliberately not inlined: a separate fastmath function is vectorised the
    same way whoever calls it (inlined into a non-fastmath caller it is not
    vectorised at all, ~8x slower), and every caller gets the same rounding.
    """
    n = len(w)
    a = q[q_start : q_start + n]
    b = t[t_start : t_start + n]
    total = np.float32(0.0)
    for r in range(n):
        total += w[r] * abs(a[r] - as_float32(b[r]))
    return total


@njit(cache=True, nogil=True, inline="always")
def _argmin_first(values: np.ndarray) -> int:
    best = 0
    for k in range(1, len(values)):
        if values[k] < values[best]:  # strict: the smallest shift wins a tie
            best = k
    return best


@njit(cache=True, nogil=True)
def min_over_shifts(store: np.ndarray, rows: np.ndarray, q: np.ndarray, w: np.ndarray,
                    sectors: int, out_distance: np.ndarray, out_shift: np.ndarray) -> None:
    """Brute force: min_k D_k and its k for each stored row ``store[rows[i]]``.

    ``store``: (n, S*R) float32, or the uint16 view of a float16 store (as every kernel here).
    """
    per_shift = np.empty(sectors, np.float32)
    every_shift = np.arange(sectors)
    for i in range(len(rows)):
        best = _nearest_row(store[rows[i]], q, w, sectors, np.inf, every_shift, per_shift)
        out_distance[i] = per_shift[best]
        out_shift[i] = best


@njit(cache=True, nogil=True, inline="always")
def _keep_best(best: np.ndarray, count: int, value: np.float32) -> int:
    """Insert ``value`` into the ascending ``best[:count]`` (capacity len(best)); new count."""
    pos = min(count, len(best) - 1)
    if count == len(best) and value >= best[pos]:
        return count
    while pos > 0 and best[pos - 1] > value:
        best[pos] = best[pos - 1]
        pos -= 1
    best[pos] = value
    return min(count + 1, len(best))


@njit(cache=True, nogil=True, inline="always")
def _row_at_shifts(t: np.ndarray, q: np.ndarray, w: np.ndarray, sectors: int,
                   shifts: np.ndarray, threshold: float, out: np.ndarray) -> None:
    """out[j] = D_{shifts[j]}(q, t); +inf for a negative shift or one above ``threshold``.

    Sector-major, so each stored sector is read once for all the shifts; each
    shift's sum still runs sector by sector, in the order every kernel here
    uses. A shift whose partial sum exceeds ``threshold`` is dropped: partial
    sums only grow, so it cannot end at or below it; the row stops once every
    shift is dropped.
    """
    width = len(w)
    for j in range(len(shifts)):
        out[j] = 0.0 if shifts[j] >= 0 else np.inf
    for s in range(sectors):
        alive = 0
        for j in range(len(shifts)):
            k = shifts[j]
            if k >= 0 and out[j] <= threshold:
                out[j] += _sector_l1(q, ((s + k) % sectors) * width, t, s * width, w)
                alive += 1
        if alive == 0:
            break
    for j in range(len(shifts)):
        if out[j] > threshold:
            out[j] = np.inf


@njit(cache=True, nogil=True, inline="always")
def _nearest_row(t: np.ndarray, q: np.ndarray, w: np.ndarray, sectors: int, threshold: float,
                 every_shift: np.ndarray, per_shift: np.ndarray) -> int:
    """Fill per_shift with D_k (``every_shift`` = 0..S-1) and return the best k; -1 if every
    D_k > ``threshold`` (those are +inf, see :func:`_row_at_shifts`)."""
    _row_at_shifts(t, q, w, sectors, every_shift, threshold, per_shift)
    best = _argmin_first(per_shift)
    return best if per_shift[best] <= threshold else -1


@njit(cache=True, nogil=True)
def nearest(store: np.ndarray, rows: np.ndarray, q: np.ndarray, w: np.ndarray, sectors: int,
            top_k: int, row_limits: np.ndarray, out_distance: np.ndarray,
            out_shift: np.ndarray) -> None:
    """:func:`min_over_shifts` that skips what cannot be among the ``top_k`` or improve a row.

    Each row's shifts are dropped once their partial sums exceed the k-th best
    distance found so far or ``row_limits[i]`` (e.g. the row's distance at a
    shift already scored; +inf for none): partial sums only grow, so it is
    exact. A row with no shift left is abandoned (distance +inf, shift -1);
    with a clear nearest keyframe most rows stop after a few sectors. Rows and
    shifts it completes have the same sums as every kernel here.
    """
    per_shift = np.empty(sectors, np.float32)
    every_shift = np.arange(sectors)
    best = np.empty(top_k, np.float32)
    count = 0
    for i in range(len(rows)):
        threshold = best[top_k - 1] if count == top_k else np.inf
        k = _nearest_row(store[rows[i]], q, w, sectors, min(threshold, row_limits[i]),
                         every_shift, per_shift)
        out_shift[i] = k
        out_distance[i] = per_shift[k] if k >= 0 else np.inf
        if k >= 0:
            count = _keep_best(best, count, per_shift[k])


@njit(cache=True, nogil=True)
def at_shifts(store: np.ndarray, rows: np.ndarray, shifts: np.ndarray, q: np.ndarray,
              w: np.ndarray, sectors: int, out: np.ndarray, keep: int = 0) -> None:
    """out[i, j] = D_{shifts[i, j]}(q, store[rows[i]]); a negative shift leaves +inf.

    Sector-major over a row, so each stored sector is read from memory once for
    all of the row's shifts (:func:`_row_at_shifts`).

    ``keep`` > 0: only the ``keep`` rows with the smallest distance (over their
    shifts) are wanted. Once ``keep`` rows are done, a shift is dropped (+inf)
    as soon as its partial sum exceeds the keep-th smallest row distance so
    far: it cannot make its row one of them. Exact for the rows that are; pass
    the most promising rows first so the cut-off tightens early.
    """
    best = np.empty(max(keep, 1), np.float32)
    count = 0
    for i in range(len(rows)):
        threshold = best[keep - 1] if keep > 0 and count == keep else np.inf
        _row_at_shifts(store[rows[i]], q, w, sectors, shifts[i], threshold, out[i])
        nearest = out[i].min()
        if keep > 0 and nearest < np.inf:
            count = _keep_best(best, count, nearest)
