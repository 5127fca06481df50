"""Gram statistics of the data term, and the d×d solves of the solver's Gram path.

G = XXᵀ, B = XY and ‖Y‖² are all the solver needs of X when n ≥ d (or when X
never fits in memory: :class:`GramAccumulator` sums them over chunks of
scans). Each IRLS step then solves (G + Λ)W = B, by Cholesky or by
preconditioned CG (:class:`GramStepper`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import numpy as np
import scipy.linalg as sla


@dataclass
class GramStats:
    """Sufficient statistics of the data term: G = XXᵀ (d×d, symmetric), B = XY (d×c), yy = ‖Y‖²_F."""

    G: np.ndarray
    B: np.ndarray
    yy: float
    n: int


class GramAccumulator:
    """Accumulate G = XXᵀ, B = XY, ‖Y‖², n over column chunks of X, so X is never held whole.

    Memory is one d×d float64 matrix (8k×8k ≈ 0.5 GB). Only the upper triangle is updated
    (symmetric rank-k update, BLAS dsyrk); :meth:`stats` mirrors it once at the end.
    """

    def __init__(self, d: int, c: int) -> None:
        if d < 1 or c < 1:
            raise ValueError(f"GramAccumulator needs d >= 1 and c >= 1, got d={d}, c={c}")
        self.d, self.c = int(d), int(c)
        self._G = np.zeros((self.d, self.d), order="F")  # dsyrk updates an F-ordered C in place
        self._B = np.zeros((self.d, self.c))
        self.yy, self.n = 0.0, 0

    def add(self, X_chunk: np.ndarray, Y_chunk: np.ndarray) -> None:
        """Add k scans: X_chunk (d, k), Y_chunk (k, c)."""
        X, Y = np.asarray(X_chunk, dtype=np.float64), np.asarray(Y_chunk, dtype=np.float64)
        if X.ndim != 2 or X.shape[0] != self.d:
            raise ValueError(f"X_chunk must have shape (d={self.d}, k), got {X.shape}")
        if Y.shape != (X.shape[1], self.c):
            raise ValueError(f"Y_chunk must have shape (k={X.shape[1]}, c={self.c}), got {Y.shape}")
        check_finite(X, "X_chunk"), check_finite(Y, "Y_chunk")
        # Pass whichever orientation is F-contiguous so dsyrk does not copy the chunk.
        a, trans = (X, 0) if X.flags.f_contiguous else (np.ascontiguousarray(X).T, 1)
        self._G = sla.blas.dsyrk(1.0, a, beta=1.0, c=self._G, trans=trans, lower=0, overwrite_c=1)
        self._B += X @ Y
        self.yy += float(np.sum(Y * Y))
        self.n += X.shape[1]

    def stats(self) -> GramStats:
        """Return a GramStats with the full symmetric G (a copy; the accumulator can keep adding)."""
        G = np.triu(self._G)
        G += np.triu(G, 1).T
        return GramStats(G, self._B.copy(), self.yy, self.n)


def check_finite(a: np.ndarray, name: str) -> None:
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contains NaN or inf")


def as_gram_stats(gram: Union[GramStats, GramAccumulator, tuple]) -> GramStats:
    if isinstance(gram, GramAccumulator):
        return gram.stats()
    if isinstance(gram, GramStats):
        return gram
    G, B, yy, *rest = gram
    return GramStats(np.asarray(G, dtype=np.float64), np.asarray(B, dtype=np.float64), float(yy),
                     int(rest[0]) if rest else -1)


def least_squares_gram(s: GramStats, exact: bool) -> np.ndarray:
    """Minimum-norm least squares from Gram statistics: W = G⁺B (= (Xᵀ)⁺Y since (XXᵀ)⁺X = (Xᵀ)⁺).

    First try a Cholesky of G; if G is numerically non-singular (LAPACK condition estimate)
    that *is* G⁺B. Otherwise ``exact`` → eigendecomposition with eigenvalues below
    d·eps_machine·λ_max dropped (that is the noise floor of a formed Gram matrix, so the
    Gram path cannot resolve directions with σ(X) < ~1e-6 σ_max); not ``exact`` (IRLS start
    only) → the ridge solution (G + δI)⁻¹B, δ = 1e-8·mean diag G, a much cheaper
    (one Cholesky, vs ~100 s eigh at d = 8k) approximation that IRLS then corrects.
    """
    G, B = s.G, s.B
    d = G.shape[0]
    try:
        cf = sla.cho_factor(G, check_finite=False)
        rcond = sla.lapack.dpocon(cf[0], np.abs(G).sum(axis=0).max(), b"L" if cf[1] else b"U")[0]
        if rcond > d * np.finfo(float).eps * 1e3:
            return sla.cho_solve(cf, B, check_finite=False)
    except np.linalg.LinAlgError:
        pass
    if exact:
        vals, vecs = sla.eigh(G, check_finite=False)
        keep = vals > max(d, s.n) * np.finfo(float).eps * max(vals[-1], 0.0)
        V = vecs[:, keep]
        return V @ ((V.T @ B) / vals[keep][:, None])
    A = np.array(G, order="F")
    A[np.diag_indices(d)] += 1e-8 * max(float(np.mean(np.diag(G))), np.finfo(float).tiny)
    return sla.cho_solve(sla.cho_factor(A, overwrite_a=True, check_finite=False), B)


class GramStepper:
    """Solve (G + Λ)W = B each IRLS step, reusing one d×d work buffer (G is 0.5 GB at d = 8k).

    "cholesky": factor G + Λ every step (d³/3 flops, ~3 s at d = 8k on 2 cores).
    "pcg": keep the Cholesky factor of G + Λ_ref from an earlier step and use it to precondition
    CG warm-started at the previous W. Since G ⪰ 0 and Λ, Λ_ref are positive diagonals,
    cond((G+Λ_ref)⁻¹(G+Λ)) ≤ max(1, max ρ) / min(1, min ρ) with ρ = Λ/Λ_ref — an O(d) bound.
    Refactor only when that bound exceeds KAPPA_MAX, when the last PCG needed more than
    cg_maxiter/2 iterations (one factorisation costs about 20–25 PCG iterations at d = 8k),
    or when CG misses cg_rtol within cg_maxiter. At n = 10k, d = 7872 that is 4–17 PCG
    iterations (~0.16 s each) per IRLS step instead of a ~3–4 s factorisation.
    """

    KAPPA_MAX = 100.0  # the bound is pessimistic: κ-bounds of 30–1e4 still took ~15 iterations

    def __init__(self, s: GramStats, linear_solver: str, cg_rtol: float, cg_maxiter: int) -> None:
        self.s, self.kind, self.rtol, self.maxiter = s, linear_solver, cg_rtol, cg_maxiter
        self.work: Optional[np.ndarray] = None
        self.lam_ref: Optional[np.ndarray] = None
        self.cg_iterations: list[int] = []
        self.factorisations, self.stale = 0, False

    def __call__(self, lam: np.ndarray, W_prev: np.ndarray) -> np.ndarray:
        if self.kind == "pcg" and self.lam_ref is not None:
            rho = lam / self.lam_ref
            if max(1.0, rho.max()) / min(1.0, rho.min()) <= self.KAPPA_MAX and not self.stale:
                W, k = _pcg(self.s.G, lam, self.s.B, W_prev, self._precond, self.rtol, self.maxiter)
                self.cg_iterations.append(k)
                self.stale = k > self.maxiter // 2  # refactor next step: cheaper than slow CG
                if k <= self.maxiter:
                    return W
        if self.work is None:
            self.work = np.empty_like(self.s.G, order="F")
        np.copyto(self.work, self.s.G)
        self.work[np.diag_indices_from(self.work)] += lam
        self.cf = sla.cho_factor(self.work, overwrite_a=True, check_finite=False)  # upper: UᵀU
        self.lam_ref, self.factorisations, self.stale = lam, self.factorisations + 1, False
        return sla.cho_solve(self.cf, self.s.B, check_finite=False)

    def _precond(self, R: np.ndarray) -> np.ndarray:
        """(G + Λ_ref)⁻¹R = U⁻¹U⁻ᵀR; per-column dtrsv is ~2x faster than dpotrs for c ≤ 8."""
        U, lower = self.cf
        if lower or R.shape[1] > 8:
            return sla.cho_solve(self.cf, R, check_finite=False)
        return np.stack([sla.blas.dtrsv(U, sla.blas.dtrsv(U, R[:, j], trans=1))
                         for j in range(R.shape[1])], axis=1)


def _pcg(G: np.ndarray, lam: np.ndarray, B: np.ndarray, W0: np.ndarray, precond, rtol: float,
         maxiter: int) -> tuple[np.ndarray, int]:
    """Preconditioned CG on (G + Λ)W = B, all c columns at once (one pass over G per iteration),
    warm-started at W0. CG from W0 only lowers the quadratic IRLS surrogate, so even a partial
    solve keeps IRLS monotone. Stops when every column has ‖r‖ ≤ rtol·‖b‖; returns the
    iteration count, or maxiter + 1 if it did not get there."""
    W = np.array(W0, dtype=np.float64)
    R = B - (symmetric_product(G, W) + lam[:, None] * W)
    bnorm = np.maximum(np.linalg.norm(B, axis=0), np.finfo(float).tiny)
    Z = precond(R)
    P = Z.copy()
    rz = np.sum(R * Z, axis=0)
    for k in range(maxiter + 1):
        if np.all(np.linalg.norm(R, axis=0) <= rtol * bnorm):
            return W, k
        if k == maxiter:
            break
        AP = symmetric_product(G, P) + lam[:, None] * P
        pap = np.sum(P * AP, axis=0)
        alpha = np.divide(rz, pap, out=np.zeros_like(rz), where=pap > 0)  # 0 for solved columns
        W += alpha * P
        R -= alpha * AP
        Z = precond(R)
        rz_new = np.sum(R * Z, axis=0)
        P = Z + np.divide(rz_new, rz, out=np.zeros_like(rz), where=rz > 0) * P
        rz = rz_new
    return W, maxiter + 1


def symmetric_product(G: np.ndarray, P: np.ndarray) -> np.ndarray:
    """G @ P for symmetric G and few columns: one dsymv per column reads half of G (≈2x faster
    than a thin gemm); G.T is the F-ordered view BLAS wants, equal to G."""
    Gf = G if G.flags.f_contiguous else G.T
    if not Gf.flags.f_contiguous or P.shape[1] > 8:
        return G @ P
    return np.stack([sla.blas.dsymv(1.0, Gf, P[:, j]) for j in range(P.shape[1])], axis=1)
