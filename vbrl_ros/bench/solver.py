"""Solver timings for ``vbrl bench``: the fast paths against the literal Algorithm 1.

Random data on the paper's layout (192 voxels x 41 features when d = 7872),
with labels that depend on a few voxels so IRLS has real sparsity to find.
"""

from __future__ import annotations

import time

import numpy as np

from vbrl_ros.model.gram import GramAccumulator, GramStats, GramStepper
from vbrl_ros.model.solver import (RowGroups, default_eps, irls_weights, least_squares_x, solve_vbrl,
                                   woodbury_step)
from vbrl_ros.model.solver_reference import literal_step


def _random_problem(n: int, d: int, c: int, seed: int):
    """Random benchmark data on the paper-like layout (192 voxels × 41 features when d = 7872);
    labels depend on a few voxels so that IRLS has real sparsity to find."""
    rng = np.random.default_rng(seed)
    per_voxel = np.repeat(np.arange(5), (6, 9, 9, 9, 8))
    groups = RowGroups(np.arange(d) // 41, per_voxel[np.arange(d) % 41])
    X = rng.standard_normal((d, n))
    W_true = rng.standard_normal((d, c)) * (groups.voxel_of_row < 8)[:, None]
    Y = np.eye(c)[np.argmax(X.T @ W_true + 0.5 * rng.standard_normal((n, c)), axis=1)]
    return X, Y, groups


def time_one_iteration(n: int = 700, d: int = 7872, c: int = 2, seed: int = 0) -> dict:
    """Seconds for one IRLS step: fast path (Woodbury if n < d, else Gram-Cholesky) vs the
    literal generic d×d solve of (XXᵀ + Λ)W = XY (XXᵀ precomputed for both, not timed)."""
    X, Y, groups = _random_problem(n, d, c, seed)
    W = least_squares_x(X, Y)
    lam = irls_weights(W, groups, 10.0, 0.1, default_eps(W))
    t = time.perf_counter()
    W_fast = woodbury_step(X, Y, lam) if n < d else None
    t_fast = time.perf_counter() - t
    XXt, XY = X @ X.T, X @ Y
    t = time.perf_counter()
    W_gram = GramStepper(GramStats(XXt, XY, float(np.sum(Y * Y)), n), "cholesky", 0, 0)(lam, W)
    t_gram = time.perf_counter() - t
    t = time.perf_counter()
    W_lit = literal_step(XXt, XY, lam)
    t_lit = time.perf_counter() - t
    if W_fast is None:
        W_fast, t_fast = W_gram, t_gram
    scale = np.abs(W_lit).max()
    return {"n": n, "d": d, "c": c, "fast_path": "woodbury" if n < d else "gram",
            "fast_s": t_fast, "gram_cholesky_s": t_gram, "literal_s": t_lit,
            "speedup": t_lit / t_fast, "max_rel_diff": float(np.abs(W_fast - W_lit).max() / scale)}


def time_gram_training(n: int = 10_000, d: int = 7872, c: int = 2, seed: int = 0,
                       linear_solver: str = "auto", chunk: int = 2000, **kw) -> dict:
    """End-to-end Gram-path training time: accumulate G, B in chunks, then IRLS."""
    X, Y, groups = _random_problem(n, d, c, seed)
    t = time.perf_counter()
    acc = GramAccumulator(d, c)
    for k in range(0, n, chunk):
        acc.add(X[:, k:k + chunk], Y[k:k + chunk])
    stats = acc.stats()
    t_gram = time.perf_counter() - t
    del X
    res = solve_vbrl(groups=groups, gram=stats, linear_solver=linear_solver, **kw)
    return {"n": n, "d": d, "gram_s": t_gram, "solve_s": res.seconds, "total_s": t_gram + res.seconds,
            "iterations": res.iterations, "converged": res.converged,
            "objective": res.objective_history[-1], "result": res}
