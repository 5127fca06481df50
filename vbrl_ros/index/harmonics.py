"""Rotation-invariant column features of a polar descriptor: its spectrum over the sectors.

Turning a scan by whole sectors shifts every column ``x[:, r]`` (S values, one
per sector) circularly. Its discrete Fourier transform over the sectors,
``X_r[m] = sum_s x[s, r] exp(-2 pi i m s / S)``, only changes phase, so the
column sum ``X_r[0]`` (signed) and the magnitudes ``|X_r[m]|``, 1 <= m <= S/2,
are invariant. Each is also 1-Lipschitz in the column's L1 norm whatever the
shift: ``| |A[m]| - |B[m]| | <= |A[m] - B[m] e^{i theta}| <= sum_s |a_s - b_(s+k)|``
for every k. So any weighted sum ``sum_r w_r sum_m c_m |g_m(a_r) - g_m(b_r)|``
with ``sum_m c_m = 1`` is a lower bound of the Eq. 4 distance at every shift
(:mod:`vbrl_ros.index.keys` groups these features into its keys).

The 40 column sums of a narrow descriptor cannot rank a map of 10^5
keyframes; the first few harmonics say how each ring's content is spread
around the sensor, which tells places apart far better.

Feature ``f = m * R + r`` is harmonic m of column r: a key of more entries than
columns takes every column's first harmonics, lowest first (:func:`harmonics_for`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from vbrl_ros.model.distance_kernels import as_float32


def harmonics_for(entries: int, width: int, sectors: int) -> int:
    """Harmonics (beyond the column sum) a key of ``entries`` over ``width`` columns uses.

    None while the column sums alone fill the key (the key of a wide descriptor
    is then what it always was); otherwise as many as it takes to give every
    entry at least one feature, at most S / 2 (the rest mirror them).
    """
    if entries <= width or sectors < 2:
        return 0
    return min(-(-entries // width) - 1, sectors // 2)


def feature_count(width: int, sectors: int) -> int:
    """Distinct invariant features of R = ``width`` columns of S sectors: every harmonic."""
    return width * (1 + (sectors // 2 if sectors > 1 else 0))


def nominal_statistics(sectors: int, harmonics: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, standard deviation) of feature m = 0..harmonics for a column of S independent
    unit-variance values (standardised features): the column sum is N(0, S); a
    harmonic's magnitude is Rayleigh (|complex normal|, E|X|^2 = S), and at m = S/2
    (real) half-normal."""
    mean, std = np.zeros(harmonics + 1), np.full(harmonics + 1, math.sqrt(sectors))
    for m in range(1, harmonics + 1):
        if 2 * m == sectors:
            mean[m], std[m] = math.sqrt(2 * sectors / math.pi), math.sqrt(sectors * (1 - 2 / math.pi))
        else:
            mean[m], std[m] = math.sqrt(math.pi * sectors) / 2, math.sqrt(sectors * (1 - math.pi / 4))
    return mean, std


def feature_coefficients(column_weights: np.ndarray, sectors: int,
                         harmonics: int) -> tuple[np.ndarray, np.ndarray]:
    """(coefficients c_f >= 0, nominal means of c_f g_f), both (R * (harmonics + 1),).

    Harmonic m of column r weighs ``w_r beta_m / sum_m beta_m``: ``beta_m`` gives every
    feature the column sum's nominal spread (so one 4-bit scale fits them all) and
    dividing by the sum keeps ``sum_m c_m = w_r`` — the lower bound of the module
    docstring. With no harmonics the coefficients are the weights themselves.
    """
    mean, std = nominal_statistics(sectors, harmonics)
    beta = std[0] / std
    scaled = np.outer(beta / beta.sum(), np.asarray(column_weights, np.float64))  # (m, r)
    return scaled.ravel(), (scaled * mean[:, None]).ravel()


def dft_tables(sectors: int, harmonics: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of 2 pi m s / S, (harmonics, S) float64, for m = 1..harmonics."""
    angle = 2 * np.pi * np.outer(np.arange(1, harmonics + 1), np.arange(sectors)) / sectors
    return np.cos(angle), np.sin(angle)


@njit(cache=True, nogil=True)
def column_features(row: np.ndarray, sectors: int, width: int, cosines: np.ndarray,
                    sines: np.ndarray, re: np.ndarray, im: np.ndarray, out: np.ndarray) -> None:
    """out[m * R + r] = column r's sum (m = 0) or |X_r[m]| (m = 1..len(cosines)) of one
    sector-major descriptor (float32 or float16 bits); ``re``/``im``: (harmonics, R) scratch.

    The sums are float32 as they always were (keys without harmonics stay bitwise
    the same); the harmonics accumulate in float64, so a rotated scan's magnitudes
    agree to ~1e-15 and its 4-bit key is, in practice, exactly the same.
    """
    harmonics = cosines.shape[0]
    column = out[:width]
    column[:] = 0.0
    re[:, :] = 0.0
    im[:, :] = 0.0
    for s in range(sectors):  # contiguous, vectorised over the columns
        part = row[s * width : (s + 1) * width]
        for r in range(width):
            column[r] += as_float32(part[r])
        for m in range(harmonics):
            c, si = cosines[m, s], sines[m, s]
            real, imaginary = re[m], im[m]
            for r in range(width):
                value = np.float64(as_float32(part[r]))
                real[r] += c * value
                imaginary[r] += si * value
    for m in range(harmonics):
        for r in range(width):
            out[(m + 1) * width + r] = np.float32(math.sqrt(re[m, r] ** 2 + im[m, r] ** 2))
