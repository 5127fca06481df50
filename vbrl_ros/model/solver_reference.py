"""Algorithm 1 exactly as the paper writes it: the independent reference for the solver's tests.

Slow on purpose (a generic d×d solve per step, group norms group by group);
``vbrl bench`` times :func:`literal_step` against the fast paths.
"""

from __future__ import annotations

import time
from typing import Optional

import numpy as np

from vbrl_ros.model.solver import RowGroups, SolverResult, check_problem, default_eps, irls, objective


def literal_step(XXt: np.ndarray, XY: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """One IRLS step the textbook way: W = (XXᵀ + Λ)⁻¹XY by a generic LU solve."""
    return np.linalg.solve(XXt + np.diag(lam), XY)


def solve_literal(X: np.ndarray, Y: np.ndarray, groups: RowGroups, lambda1: float, lambda2: float,
                  *, tol: float = 1e-6, max_iter: int = 100, eps: Optional[float] = None) -> SolverResult:
    """Algorithm 1 exactly as written: W ← (XXᵀ + Λ)⁻¹XY by a generic d×d LU solve each step,
    with group norms computed group by group — an independent reference for the tests."""
    X, Y, _ = check_problem(X, Y, groups, lambda1, lambda2, None)
    t0 = time.perf_counter()
    W = np.linalg.pinv(X.T) @ Y
    eps = default_eps(W) if eps is None else float(eps)
    XXt, XY = X @ X.T, X @ Y
    vox, mod = groups.voxel_of_row, groups.modality_of_row

    def lam_of(W):
        lam = np.zeros(X.shape[0])
        for j in np.unique(vox):
            lam[vox == j] += lambda1 / (2 * np.sqrt(np.sum(W[vox == j] ** 2) + eps))
        for i in np.unique(mod):
            lam[mod == i] += lambda2 / (2 * np.sqrt(np.sum(W[mod == i] ** 2) + eps))
        return lam + lambda2 / (2 * np.sqrt(np.sum(W ** 2, axis=1) + eps))

    step = lambda W: literal_step(XXt, XY, lam_of(W))  # noqa: E731
    f = lambda W: objective(W, Y, groups, lambda1, lambda2, X=X)  # noqa: E731
    W, hist, it, conv = irls(W, step, f, tol, max_iter) \
        if (lambda1 or lambda2) else (W, [f(W)], 0, True)
    return SolverResult(W, hist, it, conv, "literal", eps, time.perf_counter() - t0, "lu")
