"""VBRL solver: group-sparse least squares by IRLS (docs/design.md §2, paper Eq. 3, Alg. 1).

Notation: X ∈ R^{d×n} (one column per scan), Y ∈ {0,1}^{n×c}, W ∈ R^{d×c}.
Row r of W belongs to voxel ``voxel_of_row[r]`` and modality ``modality_of_row[r]``.

Objective (Eq. 3)::

    f(W) = ‖XᵀW − Y‖²_F + λ1 Σ_j ‖W_voxel(j)‖_F + λ2 (Σ_i ‖W_modality(i)‖_F + Σ_r ‖w^r‖_2)

Algorithm 1 (IRLS) is a majorise–minimise scheme: with s_g = sqrt(‖W_g‖² + ε),
``λ s_g ≤ λ (‖W_g‖² + s_g'^2) / (2 s_g')`` at the previous iterate s_g', so each step minimises
the quadratic surrogate ``‖XᵀW − Y‖² + tr(WᵀΛW)``, whose minimiser solves

    (XXᵀ + Λ) W = XY,   Λ_rr = λ1/(2 s_voxel(r)) + λ2 (1/(2 s_modality(r)) + 1/(2 s_r)).

This decreases the ε-smoothed objective f_ε monotonically (f ≤ f_ε ≤ f + O(λ√ε)).
Three ways to evaluate the step, all giving the same iterates:

* ``"woodbury"`` (X in memory, n < d): W = Λ⁻¹X (I_n + XᵀΛ⁻¹X)⁻¹ Y — an n×n SPD solve.
* ``"gram"`` (n ≥ d, or only G = XXᵀ, B = XY, ‖Y‖² known): (G + Λ) W = B — a d×d SPD solve,
  by Cholesky, or (``linear_solver="pcg"``) by warm-started CG preconditioned with a lagged
  Cholesky factor (refactored only when Λ has drifted too far); both in :mod:`.gram`, where
  :class:`~vbrl_ros.model.gram.GramAccumulator` builds G and B without holding X.
* :func:`~vbrl_ros.model.solver_reference.solve_literal`: the textbook (XXᵀ + Λ)⁻¹XY with a
  generic d×d solve (tests, benchmark).

λ1 = λ2 = 0 is the "concatenation" ablation: the minimum-norm least-squares solution.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Literal, Optional

import numpy as np
import scipy.linalg as sla

from vbrl_ros.model.gram import (
    GramAccumulator,
    GramStats,
    GramStepper,
    as_gram_stats,
    check_finite,
    least_squares_gram,
    symmetric_product,
)

__all__ = ["RowGroups", "SolverResult", "objective", "irls_weights", "default_eps", "solve_vbrl"]

Path = Literal["auto", "woodbury", "gram", "least-squares"]
EPS_REL = 1e-6  # ε = (EPS_REL · rms row norm of the least-squares W0)²; see default_eps


@dataclass
class RowGroups:
    """Voxel and modality membership of every row of W (rows of a group need not be contiguous)."""

    voxel_of_row: np.ndarray
    modality_of_row: np.ndarray
    n_voxels: int = field(init=False)
    n_modalities: int = field(init=False)

    def __post_init__(self) -> None:
        arrs = []
        for name in ("voxel_of_row", "modality_of_row"):
            a = np.asarray(getattr(self, name))
            if a.ndim != 1 or a.size == 0:
                raise ValueError(f"RowGroups.{name} must be a non-empty 1-D array, got shape {a.shape}")
            if not np.issubdtype(a.dtype, np.integer):
                raise ValueError(f"RowGroups.{name} must have an integer dtype, got {a.dtype}")
            if a.min() < 0:
                raise ValueError(f"RowGroups.{name} must be non-negative (min is {a.min()})")
            a = a.astype(np.intp)
            a.setflags(write=False)  # cached counts below must stay valid
            arrs.append(a)
        if arrs[0].shape != arrs[1].shape:
            raise ValueError(f"voxel_of_row has {arrs[0].size} rows but modality_of_row has {arrs[1].size}")
        self.voxel_of_row, self.modality_of_row = arrs
        self.n_voxels = int(arrs[0].max()) + 1
        self.n_modalities = int(arrs[1].max()) + 1

    @property
    def d(self) -> int:
        return int(self.voxel_of_row.size)

    @classmethod
    def from_layout(cls, n_voxels: int, modality_sizes: tuple[int, ...] = (6, 9, 9, 9, 8)) -> "RowGroups":
        """Voxel-major layout: voxel 0's features (modality 0 block, modality 1 block, ...), voxel 1, ...

        The default (covariance 6, three 9-bin HOGs, 8 occupancy bits) with 192 voxels gives d = 7872.
        """
        per_voxel = np.repeat(np.arange(len(modality_sizes)), modality_sizes)
        return cls(np.repeat(np.arange(n_voxels), per_voxel.size), np.tile(per_voxel, n_voxels))

    def row_norms(self, W: np.ndarray) -> np.ndarray:
        """‖w^r‖_2 for every row r, shape (d,)."""
        return np.sqrt(_row_sq(W))

    def voxel_norms(self, W: np.ndarray) -> np.ndarray:
        """‖W_voxel(j)‖_F, shape (n_voxels,) (ids without rows give 0)."""
        return np.sqrt(np.bincount(self.voxel_of_row, _row_sq(W), minlength=self.n_voxels))

    def modality_norms(self, W: np.ndarray) -> np.ndarray:
        """‖W_modality(i)‖_F, shape (n_modalities,)."""
        return np.sqrt(np.bincount(self.modality_of_row, _row_sq(W), minlength=self.n_modalities))


def _row_sq(W: np.ndarray) -> np.ndarray:
    W = np.asarray(W, dtype=np.float64)
    return np.einsum("rc,rc->r", W, W)


@dataclass
class SolverResult:
    """W is the iterate with the lowest f; objective_history holds f (Eq. 3, ε = 0) of the
    initial W and after every iteration; eps is the ε used; seconds the wall time."""

    W: np.ndarray
    objective_history: list
    iterations: int
    converged: bool
    path: str  # "woodbury" | "gram" | "least-squares"
    eps: float = 0.0
    seconds: float = 0.0
    linear_solver: str = ""
    info: dict = field(default_factory=dict)  # Gram path: factorisations, CG iterations per step


def _penalty(W: np.ndarray, groups: RowGroups, lambda1: float, lambda2: float, eps: float) -> float:
    """λ1 Σ_j sqrt(‖W_vox j‖² + ε) + λ2 (Σ_i sqrt(‖W_mod i‖² + ε) + Σ_r sqrt(‖w^r‖² + ε))."""
    r2 = _row_sq(W)
    total = 0.0
    if lambda1:
        total += lambda1 * np.sqrt(np.bincount(groups.voxel_of_row, r2) + eps).sum()
    if lambda2:
        m2 = np.bincount(groups.modality_of_row, r2)
        total += lambda2 * (np.sqrt(m2 + eps).sum() + np.sqrt(r2 + eps).sum())
    return float(total)


def objective(W: np.ndarray, Y: Optional[np.ndarray], groups: RowGroups, lambda1: float,
              lambda2: float, *, X: Optional[np.ndarray] = None, gram=None, eps: float = 0.0) -> float:
    """Eq. 3 at W, from X (exact residual) or from Gram statistics.

    From Gram statistics: ‖XᵀW − Y‖² = tr(WᵀGW) − 2 tr(WᵀB) + ‖Y‖², clipped at 0 (the
    expansion cancels when the fit is near-perfect; absolute error ≈ 1e-16·‖Y‖²).
    ``eps`` > 0 gives the smoothed objective f_ε that IRLS decreases monotonically.
    """
    W = np.asarray(W, dtype=np.float64)
    if X is not None:
        fit = float(np.sum((np.asarray(X, dtype=np.float64).T @ W - Y) ** 2))
    elif gram is not None:
        s = as_gram_stats(gram)
        fit = max(float(np.sum(W * symmetric_product(s.G, W)) - 2.0 * np.sum(W * s.B) + s.yy), 0.0)
    else:
        raise ValueError("objective needs X (with Y) or gram statistics")
    return fit + _penalty(W, groups, lambda1, lambda2, eps)


def irls_weights(W: np.ndarray, groups: RowGroups, lambda1: float, lambda2: float,
                 eps: float) -> np.ndarray:
    """diag(Λ) = λ1 D + λ2 D̃ with D_rr = 1/(2 sqrt(‖W_voxel(r)‖² + ε)),
    D̃_rr = 1/(2 sqrt(‖W_modality(r)‖² + ε)) + 1/(2 sqrt(‖w^r‖² + ε)); shape (d,)."""
    r2 = _row_sq(W)
    lam = np.zeros(r2.size)
    if lambda1:
        v2 = np.bincount(groups.voxel_of_row, r2, minlength=groups.n_voxels)
        lam += (0.5 * lambda1) / np.sqrt(v2 + eps)[groups.voxel_of_row]
    if lambda2:
        m2 = np.bincount(groups.modality_of_row, r2, minlength=groups.n_modalities)
        lam += (0.5 * lambda2) * (1.0 / np.sqrt(m2 + eps)[groups.modality_of_row] + 1.0 / np.sqrt(r2 + eps))
    return lam


def default_eps(W0: np.ndarray) -> float:
    """ε = (1e-6 · rms row norm of W0)², W0 the least-squares start.

    Why relative: ε must not depend on the units of X. √ε is the level below which a group
    counts as "zero": a group the optimum switches off shrinks geometrically under IRLS until
    its norm is ~√ε, where its weight λ/(2√ε) stays finite (an absolute ε = 1e-12 would give
    1/0-like weights ~1e6·λ for data with large W, or no sparsity at all for tiny W).
    The bias on live groups is a relative ε/(2‖W_g‖²) ≲ 1e-8 in their subgradient.
    """
    rms = float(np.sqrt(np.sum(_row_sq(W0)) / max(W0.shape[0], 1)))
    return max((EPS_REL * rms) ** 2, np.finfo(float).tiny)


def least_squares_x(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Minimum-norm argmin ‖XᵀW − Y‖ = (Xᵀ)⁺Y, SVD-based; singular values below
    max(n, d)·eps_machine·σ_max are treated as zero (numpy's default rcond)."""
    return np.linalg.lstsq(X.T, Y, rcond=None)[0]


def woodbury_step(X: np.ndarray, Y: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """W = Λ⁻¹X (I_n + XᵀΛ⁻¹X)⁻¹ Y, computed as S X (m I_n + XᵀSX)⁻¹ Y with m = min λ and
    S = m Λ⁻¹ ≤ I: the same W, but a tiny λ (1e-308) no longer overflows Λ⁻¹ to inf. SPD →
    Cholesky, cost O(n²d); a Gram matrix singular to rounding (λ → 0 with dependent scans), or a
    Λ that underflowed to 0, falls back to least squares."""
    m = float(lam.min())
    if not m > 0.0:  # a λ so small (5e-324) that half of it underflows to 0: Λ = 0 is least squares
        return least_squares_x(X, Y)
    scale = m / lam
    Xs = X * np.sqrt(scale)[:, None]
    K = Xs.T @ Xs
    K.flat[:: K.shape[0] + 1] += m
    try:
        Z = sla.cho_solve(sla.cho_factor(K, check_finite=False), Y, check_finite=False)
    except np.linalg.LinAlgError:
        Z = np.linalg.lstsq(K, Y, rcond=None)[0]
    return scale[:, None] * (X @ Z)


def check_problem(X, Y, groups, lambda1, lambda2, gram):
    if not isinstance(groups, RowGroups):
        raise ValueError("groups must be a RowGroups")
    for name, lam in (("lambda1", lambda1), ("lambda2", lambda2)):
        if not np.isfinite(lam) or lam < 0:
            raise ValueError(f"{name} must be a finite number >= 0, got {lam}")
    if (X is None) == (gram is None):
        raise ValueError("give either X and Y, or gram statistics (not both, not neither)")
    if X is None:
        s = as_gram_stats(gram)
        if s.G.shape != (groups.d, groups.d) or s.B.ndim != 2 or s.B.shape[0] != groups.d:
            raise ValueError(f"gram shapes G {s.G.shape}, B {s.B.shape} do not match d={groups.d}")
        check_finite(s.G, "gram G"), check_finite(s.B, "gram B")
        return None, None, s
    X, Y = np.asarray(X, dtype=np.float64), np.asarray(Y, dtype=np.float64)
    if X.ndim != 2 or Y.ndim != 2:
        raise ValueError(f"X must be (d, n) and Y (n, c); got X {X.shape}, Y {Y.shape}")
    if X.shape[1] != Y.shape[0]:
        raise ValueError(f"X has {X.shape[1]} columns (scans) but Y has {Y.shape[0]} rows")
    if X.shape[0] != groups.d:
        raise ValueError(f"X has {X.shape[0]} feature rows but groups describe {groups.d}")
    check_finite(X, "X"), check_finite(Y, "Y")
    return X, Y, None


def solve_vbrl(X: Optional[np.ndarray] = None, Y: Optional[np.ndarray] = None,
               groups: Optional[RowGroups] = None, lambda1: float = 10.0, lambda2: float = 0.1, *,
               gram=None, tol: float = 1e-6, max_iter: int = 100, eps: Optional[float] = None,
               path: Path = "auto", linear_solver: str = "auto", cg_rtol: float = 1e-10,
               cg_maxiter: int = 30,
               on_iteration: Optional[Callable[[int, float], None]] = None) -> SolverResult:
    """Minimise Eq. 3 by Algorithm 1 (IRLS), stopping when the relative decrease of f is < tol.

    path="auto": λ1 = λ2 = 0 → "least-squares" (min-norm W = (Xᵀ)⁺Y, or G⁺B from gram);
    X given with n < d → "woodbury" (n×n solves); otherwise "gram" (d×d solves of
    (G + Λ)W = B; G is built from X in chunks if X was given). ``gram`` may be a
    GramAccumulator, GramStats or (G, B, ‖Y‖²[, n]). ``eps`` None → :func:`default_eps`.
    ``linear_solver`` ("auto" | "cholesky" | "pcg", Gram path only): "auto" = "pcg" for
    d > 2000. PCG stops at ‖r‖ ≤ cg_rtol·‖B‖ per column; if it needs more than ``cg_maxiter``
    iterations that step is redone by a fresh Cholesky.
    ``on_iteration(iteration, f)`` is called after every IRLS step: a d×d solve can take
    minutes, and a caller showing progress has nothing else to go by.
    """
    t0 = time.perf_counter()
    X, Y, stats = check_problem(X, Y, groups, lambda1, lambda2, gram)
    if path not in ("auto", "woodbury", "gram", "least-squares"):
        raise ValueError(f"unknown path {path!r}")
    if linear_solver not in ("auto", "cholesky", "pcg"):
        raise ValueError(f"unknown linear_solver {linear_solver!r}")
    if eps is not None and not eps > 0:
        raise ValueError(f"eps must be > 0, got {eps}")
    least_squares = lambda1 == 0 and lambda2 == 0  # then Λ = 0: "concatenation" ablation
    if path == "least-squares" and not least_squares:
        raise ValueError("path='least-squares' is what λ1 = λ2 = 0 selects; got non-zero λ")
    if path == "woodbury" and X is None:
        raise ValueError("the Woodbury path needs X")
    if path == "auto" and not least_squares:
        path = "woodbury" if X is not None and X.shape[1] < X.shape[0] else "gram"
    if stats is None and path == "gram" and not least_squares:
        acc = GramAccumulator(X.shape[0], Y.shape[1])
        for k in range(0, X.shape[1], 2048):  # chunks bound the float64 temporaries
            acc.add(X[:, k:k + 2048], Y[k:k + 2048])
        stats = acc.stats()

    def f(W: np.ndarray) -> float:  # residual from X when we have it: no cancellation
        return objective(W, Y, groups, lambda1, lambda2, X=X, gram=None if X is not None else stats)

    W0 = least_squares_x(X, Y) if X is not None and (path == "woodbury" or least_squares) else \
        least_squares_gram(stats, exact=least_squares)
    if least_squares:
        return SolverResult(W0, [f(W0)], 0, True, "least-squares", 0.0, time.perf_counter() - t0)
    eps = default_eps(W0) if eps is None else float(eps)
    if path == "woodbury":
        step, kind = (lambda lam, W: woodbury_step(X, Y, lam)), "cholesky"
    else:
        kind = linear_solver if linear_solver != "auto" else ("pcg" if groups.d > 2000 else "cholesky")
        step = GramStepper(stats, kind, cg_rtol, cg_maxiter)
    W, hist, it, conv = irls(W0, lambda W: step(irls_weights(W, groups, lambda1, lambda2, eps), W),
                              f, tol, max_iter, on_iteration)
    info = {"factorisations": step.factorisations, "cg_iterations": step.cg_iterations} \
        if path == "gram" else {}
    return SolverResult(W, hist, it, conv, path, eps, time.perf_counter() - t0, kind, info)


def irls(W, step, f, tol, max_iter, on_iteration=None):
    """Shared IRLS loop. Stops when (f_prev − f)/f_prev < tol; if a step *raised* f (only
    possible at round-off level, or from the ε-smoothing) the previous W is returned."""
    hist = [f(W)]
    for it in range(1, max_iter + 1):
        W_new = step(W)
        hist.append(f(W_new))
        if on_iteration is not None:
            on_iteration(it, hist[-1])
        if hist[-1] <= hist[-2]:
            W = W_new
        if hist[-2] - hist[-1] <= tol * abs(hist[-2]):  # "<=": f = 0 (Y = 0) stops too
            return W, hist, it, True
    return W, hist, max_iter, False


