"""Tests for vbrl_ros.model.solver (docs/design.md §2: Eq. 3 and Algorithm 1)."""
import numpy as np
import pytest
import scipy.optimize
from hypothesis import given, settings, strategies as st

from vbrl_ros.model.gram import GramAccumulator, GramStats
from vbrl_ros.model.solver import RowGroups, default_eps, irls_weights, objective, solve_vbrl
from vbrl_ros.model.solver_reference import solve_literal

TIGHT = dict(tol=1e-14, max_iter=3000)


def make_problem(n, v=6, sizes=(2, 3, 1), c=3, seed=0, informative=None, noise_modality=None):
    """Voxel-major layout; Y = one-hot argmax of a linear model on the informative voxels
    (all voxels if None) and on all modalities except ``noise_modality``."""
    rng = np.random.default_rng(seed)
    groups = RowGroups.from_layout(v, sizes)
    X = rng.standard_normal((groups.d, n))
    mask = np.ones(groups.d, bool)
    if informative is not None:
        mask &= np.isin(groups.voxel_of_row, informative)
    if noise_modality is not None:
        mask &= groups.modality_of_row != noise_modality
    W_true = rng.standard_normal((groups.d, c)) * mask[:, None]
    Y = np.eye(c)[np.argmax(X.T @ W_true + 0.3 * rng.standard_normal((n, c)), axis=1)]
    return X, Y, groups


def gram_of(X, Y):
    return GramStats(X @ X.T, X @ Y, float(np.sum(Y ** 2)), X.shape[1])


def assert_monotone(hist, scale: float = 0.0):
    """Each objective at most the previous one, up to rounding: relative to the objective, or to
    ``scale`` (the objective at W = 0, ||Y||^2) where an exact fit leaves only rounding noise."""
    h = np.asarray(hist)
    assert np.all(np.diff(h) <= 1e-12 * np.maximum(np.abs(h[:-1]), scale)), np.diff(h).max()


# ---------------------------------------------------------------- groups, objective, Gram stats
def test_rowgroups_norms_match_loops_and_noncontiguous_groups():
    rng = np.random.default_rng(1)
    vox, mod = rng.integers(0, 7, 40), rng.integers(0, 3, 40)  # shuffled, non-contiguous rows
    g, W = RowGroups(vox, mod), rng.standard_normal((40, 2))
    assert (g.n_voxels, g.n_modalities, g.d) == (vox.max() + 1, mod.max() + 1, 40)
    np.testing.assert_allclose(g.voxel_norms(W), [np.linalg.norm(W[vox == j]) for j in range(g.n_voxels)])
    np.testing.assert_allclose(g.modality_norms(W), [np.linalg.norm(W[mod == i]) for i in range(3)])
    np.testing.assert_allclose(g.row_norms(W), np.linalg.norm(W, axis=1))
    assert RowGroups.from_layout(192).d == 7872


def test_objective_from_gram_equals_objective_from_x():
    X, Y, g = make_problem(30)
    W = np.random.default_rng(2).standard_normal((g.d, 3))
    fx = objective(W, Y, g, 10.0, 0.1, X=X)
    manual = (np.sum((X.T @ W - Y) ** 2) + 10 * g.voxel_norms(W).sum()
              + 0.1 * (g.modality_norms(W).sum() + g.row_norms(W).sum()))
    assert fx == pytest.approx(manual, rel=1e-12)
    assert objective(W, None, g, 10.0, 0.1, gram=gram_of(X, Y)) == pytest.approx(fx, rel=1e-10)


@pytest.mark.parametrize("dtype, order", [(np.float64, "C"), (np.float32, "F")])
def test_gram_accumulator_chunks_equal_full(dtype, order):
    rng = np.random.default_rng(3)
    X, Y = rng.standard_normal((37, 101)).astype(dtype), np.eye(4)[rng.integers(0, 4, 101)]
    acc = GramAccumulator(37, 4)
    for k in range(0, 101, 17):
        acc.add(np.asarray(X[:, k:k + 17], order=order), Y[k:k + 17])
    s, X64 = acc.stats(), X.astype(np.float64)
    np.testing.assert_allclose(s.G, X64 @ X64.T, rtol=1e-12, atol=1e-10)
    np.testing.assert_allclose(s.B, X64 @ Y, rtol=1e-12, atol=1e-12)
    assert (s.yy, s.n) == (101.0, 101) and np.array_equal(s.G, s.G.T)


# ---------------------------------------------------------------- Algorithm 1 properties
LAMBDAS = [(10.0, 0.1), (1.0, 0.0), (0.0, 0.1), (30.0, 1.0)]


@pytest.mark.parametrize("lam", LAMBDAS)
@pytest.mark.parametrize("n, kw", [(25, dict(path="woodbury")), (25, dict(path="gram")),
                                   (80, dict(path="gram", linear_solver="pcg"))])
def test_objective_decreases_monotonically(lam, n, kw):
    X, Y, g = make_problem(n, informative=[0, 2])
    r = solve_vbrl(X, Y, g, *lam, max_iter=200, tol=1e-12, **kw)
    assert r.path == kw["path"] and len(r.objective_history) == r.iterations + 1
    assert_monotone(r.objective_history)
    assert objective(r.W, Y, g, *lam, X=X) <= r.objective_history[-1] * (1 + 1e-12)


@pytest.mark.parametrize("path", ["woodbury", "gram"])
def test_on_iteration_reports_every_step_with_its_objective(path):
    X, Y, g = make_problem(25, informative=[0, 2])
    calls = []
    r = solve_vbrl(X, Y, g, 10.0, 0.1, path=path, on_iteration=lambda it, f: calls.append((it, f)))
    assert [it for it, _ in calls] == list(range(1, r.iterations + 1))
    assert [f for _, f in calls] == r.objective_history[1:]
    limited = solve_vbrl(X, Y, g, 10.0, 0.1, path=path, max_iter=2, tol=1e-14)
    assert not limited.converged and limited.iterations == 2


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(5, 60), l1=st.floats(0, 50), l2=st.floats(0, 5))
def test_objective_decreases_monotonically_random(seed, n, l1, l2):
    X, Y, g = make_problem(n, v=4, sizes=(2, 2), c=2, seed=seed)
    X *= np.random.default_rng(seed).uniform(0.01, 100)  # scale-free ε must cope with any units
    assert_monotone(solve_vbrl(X, Y, g, l1, l2, max_iter=100, tol=1e-12).objective_history, float(np.sum(Y ** 2)))


def test_a_vanishing_lambda_is_least_squares_not_an_overflow():
    """λ2 = 2.2e-308: Λ⁻¹ overflowed to inf and W jumped to 0 (objective 1e-29 -> 5)."""
    X, Y, g = make_problem(5, v=4, sizes=(2, 2), c=2, seed=0)
    r = solve_vbrl(X, Y, g, 0.0, float(np.finfo(float).tiny), max_iter=100, tol=1e-12)
    assert_monotone(r.objective_history, float(np.sum(Y ** 2)))
    assert r.objective_history[-1] < 1e-20 and np.isfinite(r.W).all()


def test_a_lambda_whose_half_underflows_is_least_squares_not_nan():
    """λ2 = 5e-324 (the smallest subnormal): λ/2 is 0, Λ = 0, and m Λ⁻¹ was 0/0."""
    X, Y, g = make_problem(5, v=4, sizes=(2, 2), c=2, seed=0)
    r = solve_vbrl(X, Y, g, 0.0, 5e-324, max_iter=100, tol=1e-12)
    assert_monotone(r.objective_history, float(np.sum(Y ** 2)))
    assert np.isfinite(r.W).all() and r.objective_history[-1] < 1e-20


def smooth_gradient(W, X, Y, g, l1, l2):
    """∇ of Eq. 3 where every group is non-zero: 2X(XᵀW − Y) + ΛW with Λ from exact norms."""
    return 2 * X @ (X.T @ W - Y) + 2 * irls_weights(W, g, l1, l2, 0.0)[:, None] * W


@pytest.mark.parametrize("lam", [(1.0, 0.1), (0.0, 0.5), (40.0, 0.1)])
def test_stationarity_at_convergence(lam):
    X, Y, g = make_problem(60, informative=[0, 1, 2])
    r = solve_vbrl(X, Y, g, *lam, **TIGHT)
    vn, mn, rn = g.voxel_norms(r.W), g.modality_norms(r.W), g.row_norms(r.W)
    scale = max(vn.max(), 1e-300)
    live = (vn[g.voxel_of_row] > 1e-4 * scale) & (rn > 1e-4 * scale)  # all three terms differentiable
    assert live.sum() >= g.d // 3
    grad = smooth_gradient(r.W, X, Y, g, *lam)[live]
    assert np.abs(grad).max() < 1e-5 * np.abs(2 * X @ Y).max()
    if lam[0] >= 40:  # zero voxel groups (noise voxels 4, 5): 0 ∈ ∇_g fit + λ1 ∂‖W_g‖ + λ2 Σ_r ∂‖w^r‖
        dead = np.flatnonzero(vn < 1e-4 * scale)
        assert set(dead) == {4, 5}
        fit_grad = 2 * X @ (X.T @ r.W - Y)
        for j in dead:
            rows = g.voxel_of_row == j
            assert np.linalg.norm(fit_grad[rows]) <= lam[0] + lam[1] * np.sqrt(rows.sum())


@pytest.mark.parametrize("lam", [(10.0, 0.1), (0.0, 0.1), (10.0, 0.0)])
def test_woodbury_gram_literal_and_cg_agree(lam):
    X, Y, g = make_problem(20)  # d = 36 > n = 20 → auto picks Woodbury
    AGREE = dict(tol=1e-12, max_iter=600)  # same start and ε → same iterates, converged or not
    ref = solve_literal(X, Y, g, *lam, **AGREE)
    runs = [solve_vbrl(X, Y, g, *lam, eps=ref.eps, **AGREE),
            solve_vbrl(X, Y, g, *lam, eps=ref.eps, path="gram", linear_solver="cholesky", **AGREE),
            solve_vbrl(groups=g, lambda1=lam[0], lambda2=lam[1], gram=gram_of(X, Y), eps=ref.eps,
                       linear_solver="pcg", **AGREE)]
    assert [r.path for r in runs] == ["woodbury", "gram", "gram"]
    assert len(runs[2].info["cg_iterations"]) > runs[2].info["factorisations"]  # PCG did most steps
    for r in runs:
        np.testing.assert_allclose(r.W, ref.W, rtol=0, atol=1e-7 * np.abs(ref.W).max())
        assert r.objective_history[-1] == pytest.approx(ref.objective_history[-1], rel=1e-9)
    # identical iterates, not just identical limits (same start, same ε)
    n_common = min(len(runs[0].objective_history), len(ref.objective_history), 20)
    np.testing.assert_allclose(runs[0].objective_history[:n_common], ref.objective_history[:n_common],
                               rtol=1e-9)


@pytest.mark.parametrize("lam", [(1.0, 0.1), (0.0, 0.3), (2.0, 0.0)])
def test_matches_generic_optimiser(lam):
    """BFGS on Eq. 3 itself (differentiable at an optimum with no zero group)."""
    X, Y, g = make_problem(30, v=3, sizes=(2, 1), c=2, seed=4)
    r = solve_vbrl(X, Y, g, *lam, **TIGHT)

    def fun(w):
        W = w.reshape(r.W.shape)
        return objective(W, Y, g, *lam, X=X), smooth_gradient(W, X, Y, g, *lam).ravel()

    opt = scipy.optimize.minimize(fun, r.W.ravel() + 0.1, jac=True, method="BFGS",
                                  options=dict(gtol=1e-10, maxiter=10_000))
    assert r.objective_history[-1] <= opt.fun * (1 + 1e-10)
    np.testing.assert_allclose(r.W.ravel(), opt.x, atol=1e-5 * np.abs(opt.x).max())


# ---------------------------------------------------------------- least squares and ablations
def test_lambda_zero_gives_min_norm_least_squares():
    X, Y, g = make_problem(15)  # d = 36 > n: infinitely many interpolants, take the min-norm one
    ref = np.linalg.pinv(X.T) @ Y
    for r in (solve_vbrl(X, Y, g, 0.0, 0.0),
              solve_vbrl(groups=g, lambda1=0, lambda2=0, gram=gram_of(X, Y))):  # singular G
        assert r.path == "least-squares" and r.iterations == 0
        np.testing.assert_allclose(r.W, ref, atol=1e-9 * np.abs(ref).max())
    X, Y, g = make_problem(90)  # n > d, G non-singular
    r = solve_vbrl(groups=g, lambda1=0, lambda2=0, gram=gram_of(X, Y))
    np.testing.assert_allclose(r.W, np.linalg.pinv(X.T) @ Y, atol=1e-10)


def test_ablations_selected_by_lambda_alone():
    X, Y, g = make_problem(120, v=8, informative=[0, 1, 2])
    for lam in [(0, 0), (10, 0), (0, 0.1), (10, 0.1)]:
        r = solve_vbrl(X, Y, g, *lam)
        assert r.path == ("least-squares" if lam == (0, 0) else "gram")
        assert (r.iterations == 0) == (lam == (0, 0))


def test_voxel_only_switches_off_noise_voxels():
    X, Y, g = make_problem(150, v=8, informative=[0, 1, 2], seed=5)
    noise_share = []
    for l1 in [0.0, 3.0, 10.0, 30.0, 100.0]:
        vn = g.voxel_norms(solve_vbrl(X, Y, g, l1, 0.0, **TIGHT).W)
        noise_share.append(vn[3:].sum() / vn.sum())
    assert np.all(np.diff(noise_share) < 0), noise_share
    assert noise_share[-1] < 1e-4 < 0.1 < noise_share[0]  # whole voxel groups ~0 ("zero" ≈ √ε)


def test_modality_only_downweights_noise_modality():
    X, Y, g = make_problem(150, v=5, sizes=(3, 3, 3), noise_modality=1, seed=6)
    shares = []
    for l2 in [0.0, 0.1, 3.0, 30.0]:
        mn = g.modality_norms(solve_vbrl(X, Y, g, 0.0, l2, **TIGHT).W)
        shares.append(mn[1] / mn.sum())
    assert np.all(np.diff(shares) < 0), shares
    assert shares[-1] < 0.2 * shares[0]


def test_scale_invariance_of_eps():
    """X → aX, λ → aλ is the same problem with W → W/a; the relative ε keeps that exact."""
    X, Y, g = make_problem(40, informative=[0, 1])
    r1 = solve_vbrl(X, Y, g, 10.0, 0.1, **TIGHT)
    r2 = solve_vbrl(1e4 * X, Y, g, 1e5, 1e3, **TIGHT)
    np.testing.assert_allclose(1e4 * r2.W, r1.W, atol=1e-7 * np.abs(r1.W).max())
    assert r2.eps == pytest.approx(r1.eps * 1e-8, rel=1e-6)
    assert default_eps(np.zeros((3, 2))) > 0


# ---------------------------------------------------------------- bad input and benchmark helper
@pytest.mark.parametrize("mutate, msg", [
    (lambda X, Y, g: (X[:, :-1], Y, g, 1.0, 0.1), "columns"),
    (lambda X, Y, g: (X[:-1], Y, g, 1.0, 0.1), "feature rows"),
    (lambda X, Y, g: (np.where(np.eye(*X.shape, dtype=bool), np.nan, X), Y, g, 1.0, 0.1), "NaN"),
    (lambda X, Y, g: (X, Y, g, -1.0, 0.1), "lambda1"),
    (lambda X, Y, g: (X, Y, g, 1.0, float("nan")), "lambda2"),
])
def test_bad_input_raises(mutate, msg):
    X, Y, g = make_problem(10)
    with pytest.raises(ValueError, match=msg):
        solve_vbrl(*mutate(X, Y, g))


def test_bad_groups_and_gram_raise():
    with pytest.raises(ValueError, match="non-negative"):
        RowGroups(np.array([0, -1]), np.array([0, 0]))
    with pytest.raises(ValueError, match="integer"):
        RowGroups(np.array([0.0, 1.0]), np.array([0, 0]))
    with pytest.raises(ValueError, match="rows"):
        RowGroups(np.array([0, 1]), np.array([0]))
    g = RowGroups(np.arange(4), np.zeros(4, int))
    with pytest.raises(ValueError, match="shape"):
        GramAccumulator(4, 2).add(np.ones((3, 5)), np.ones((5, 2)))
    with pytest.raises(ValueError, match="NaN"):
        GramAccumulator(4, 2).add(np.full((4, 5), np.nan), np.ones((5, 2)))
    with pytest.raises(ValueError, match="match"):
        solve_vbrl(groups=g, gram=(np.eye(3), np.ones((3, 2)), 1.0))
    with pytest.raises(ValueError, match="either"):
        solve_vbrl(groups=g)


def test_zero_labels_and_zero_feature_rows():
    """Y = 0 → W = 0 at once; all-zero feature rows (empty voxels) keep W rows at 0, no 1/0."""
    X, Y, g = make_problem(20)
    r = solve_vbrl(X, np.zeros_like(Y), g, 10.0, 0.1)
    assert r.converged and np.all(r.W == 0) and r.objective_history[-1] == 0
    X[g.voxel_of_row == 2] = 0.0
    for kw in (dict(), dict(path="gram"), dict(path="gram", linear_solver="pcg")):
        r = solve_vbrl(X, Y, g, 10.0, 0.1, **kw)
        assert np.all(np.isfinite(r.W)) and np.abs(r.W[g.voxel_of_row == 2]).max() < 1e-12
        assert_monotone(r.objective_history)
