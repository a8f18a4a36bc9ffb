"""Tests of robust_imdp.bounds.gp_cells: certified bounds of GP posterior mean/std over boxes.

Independent checks: dense uniform samples per box (10^4), closed-form extrema of a one-point
GP, exhaustive grids for the relaxation alone (hypothesis), the joint affine+mean image.
Tolerances: a certified bound may not be crossed at all by sampled values (no slack); "close
to the optimum" checks use ``tol`` plus 1e-9 for the float error of the sampled values.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robust_imdp.bounds.gp_cells import (
    ImageBounds,
    PosteriorBounds,
    _kernel_sum_lower,
    bound_image,
    bound_posterior,
)
from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.bounds.gp import GaussianProcess

from soundness_checks import check_posterior_bounds


class StandInGP:
    """Minimal fitted-GP stand-in with the attribute contract of gp.GaussianProcess."""

    def __init__(self, X, alpha, lengthscale, sf2=1.0, lam=1.0):
        self.X_train_ = np.atleast_2d(np.asarray(X, float))
        m, d = self.X_train_.shape
        self.alpha_ = np.asarray(alpha, float)
        self.lengthscale_ = np.broadcast_to(np.asarray(lengthscale, float), (d,)).copy()
        self.signal_variance_ = float(sf2)
        self.noise_variance_ = float(lam)
        self.jitter_ = 0.0
        K = self.kernel(self.X_train_, self.X_train_) + lam * np.eye(m)
        self.L_ = np.linalg.cholesky(K)

    def kernel(self, A, B):
        z = (((A[:, None, :] - B[None, :, :]) / self.lengthscale_) ** 2).sum(-1)
        return self.signal_variance_ * np.exp(-0.5 * z)

    def predict(self, X, return_std=False):
        Ks = self.kernel(X, self.X_train_)
        mu = Ks @ self.alpha_
        v = np.linalg.solve(self.L_, Ks.T)
        return mu, np.sqrt(np.maximum(self.signal_variance_ - (v * v).sum(0), 0.0))


def random_gp(d, seed, m=None):
    rng = np.random.default_rng(seed)
    m = m or int(rng.integers(5, 30))
    X = rng.uniform(-2, 2, (m, d))
    y = np.sin(2 * X).sum(1) + rng.normal(0, 0.3, m)
    ls = rng.uniform(0.4, 1.5, d)
    return GaussianProcess(ls, float(rng.uniform(0.5, 2.0)), "chowdhury").fit(X, y), rng


def random_boxes(rng, k, d, wmax=0.8):
    lo = rng.uniform(-2.5, 2.0, (k, d))
    return lo, lo + rng.uniform(0.0, wmax, (k, d))


def dense(rng, lo, hi, n=10_000):
    """(k, n, d) uniform samples per box, with the box corners included."""
    k, d = lo.shape
    pts = lo[:, None, :] + rng.uniform(size=(k, n, d)) * (hi - lo)[:, None, :]
    corners = np.array(np.meshgrid(*[[0, 1]] * d)).reshape(d, -1).T  # (2^d, d)
    pts[:, : 2**d] = lo[:, None, :] + corners[None] * (hi - lo)[:, None, :]
    return pts


def assert_contains(gp, r, lo, hi, rng, n=10_000):
    k, d = lo.shape
    pts = dense(rng, lo, hi, n)
    mu, sd = gp.predict(pts.reshape(-1, d), return_std=True)
    mu, sd = mu.reshape(k, n), sd.reshape(k, n)
    assert np.all(r.mean_lower <= mu.min(1))
    assert np.all(r.mean_upper >= mu.max(1))
    assert np.all(r.std_upper >= sd.max(1))
    # the same against polished extrema (samples + corners + L-BFGS-B), the check whose power
    # test_sensitivity.py shows (a 1e-3 shrink of a tight bound is flagged)
    assert check_posterior_bounds(r.mean_lower, r.mean_upper, r.std_upper, gp, lo, hi, rng, n=2000) == 0
    # achieved values are values at points of the box, so they lie between the bounds
    assert np.all(r.mean_lower <= r.mean_min_achieved)
    assert np.all(r.mean_max_achieved <= r.mean_upper)
    assert np.all(r.std_max_achieved <= r.std_upper)
    return mu, sd


@pytest.mark.parametrize("d", [1, 2, 3])
@pytest.mark.parametrize("seed", range(6))
def test_bounds_contain_dense_samples(d, seed):
    gp, rng = random_gp(d, seed)
    lo, hi = random_boxes(rng, 6, d)
    r = bound_posterior(gp, lo, hi, tol=1e-3, local_solver=None)
    assert isinstance(r, PosteriorBounds)
    mu, sd = assert_contains(gp, r, lo, hi, rng)
    ok = ~r.budget_exhausted
    # gap <= tol where the budget allowed; the sampled extremes are within the gap too
    # (1e-9: float error of the sampled values themselves)
    assert np.all(r.mean_lower_gap[ok] <= 1e-3 + 1e-9)
    assert np.all(r.mean_upper_gap[ok] <= 1e-3 + 1e-9)
    assert np.all(r.std_upper_gap[ok] <= 1e-3 + 1e-9)


def test_casadi_local_solver_sound_and_at_least_as_good():
    gp, rng = random_gp(2, 11, m=40)
    lo, hi = random_boxes(rng, 5, 2)
    r0 = bound_posterior(gp, lo, hi, tol=1e-4, local_solver=None)
    r1 = bound_posterior(gp, lo, hi, tol=1e-4, local_solver="casadi")
    assert_contains(gp, r1, lo, hi, rng)
    # both certified within tol of each other's achieved values (same true extremum)
    assert np.all(r1.mean_lower <= r0.mean_min_achieved)
    assert np.all(r0.mean_lower <= r1.mean_min_achieved)
    assert np.all(np.abs(r1.std_upper - r0.std_upper) <= 2e-4)


def test_one_point_gp_closed_form():
    # mu(x) = a sf2 exp(-|x|^2 / (2 l^2)); sigma^2(x) = sf2 - k(x)^2 / (sf2 + lam)
    a, sf2, lam, l = 1.7, 2.0, 0.5, 0.8
    gp = StandInGP([[0.0, 0.0]], [a], l, sf2, lam)
    lo, hi = np.array([[0.5, -0.2]]), np.array([[1.0, 0.3]])
    near, far = np.array([0.5, 0.0]), np.array([1.0, 0.3])  # closest / farthest points to 0
    k_near = sf2 * np.exp(-0.5 * (near**2).sum() / l**2)
    k_far = sf2 * np.exp(-0.5 * (far**2).sum() / l**2)
    r = bound_posterior(gp, lo, hi, tol=1e-6, local_solver=None)
    assert not r.budget_exhausted.any()
    assert a * k_far - 1e-6 - 1e-12 <= r.mean_lower[0] <= a * k_far
    assert a * k_near <= r.mean_upper[0] <= a * k_near + 1e-6 + 1e-12
    s_far = np.sqrt(sf2 - k_far**2 / (sf2 + lam))
    assert s_far <= r.std_upper[0] <= s_far + 1e-6 + 1e-12
    # negative weight: extrema swap
    neg = StandInGP([[0.0, 0.0]], [-a], l, sf2, lam)
    r = bound_posterior(neg, lo, hi, tol=1e-6, local_solver=None)
    assert -a * k_near - 1e-6 - 1e-12 <= r.mean_lower[0] <= -a * k_near


def test_zero_width_box_is_tight():
    # lower == upper: z_L == z_U guard; bound within padding of the point value
    gp, rng = random_gp(2, 3)
    x = rng.uniform(-1, 1, (4, 2))
    r = bound_posterior(gp, x, x, tol=1e-3, local_solver=None)
    mu, sd = gp.predict(x, return_std=True)
    assert np.all(r.mean_lower <= mu) and np.all(mu <= r.mean_upper)
    assert np.all(r.std_upper >= sd)
    np.testing.assert_allclose(r.mean_upper - r.mean_lower, 0.0, atol=1e-10)


def test_far_from_origin_is_still_sound():
    # shifting everything by 1e3 stresses the cancellation in the expanded quadratic
    gp0, rng = random_gp(2, 5)
    gp = StandInGP(gp0.X_train_ + 1e3, gp0.alpha_, gp0.lengthscale_, gp0.signal_variance_,
                   gp0.noise_variance_)
    lo, hi = random_boxes(rng, 4, 2)
    r = bound_posterior(gp, lo + 1e3, hi + 1e3, tol=1e-3, local_solver=None)
    assert_contains(gp, r, lo + 1e3, hi + 1e3, rng)


def test_budget_exhausted_still_sound():
    gp, rng = random_gp(2, 7, m=25)
    lo, hi = random_boxes(rng, 5, 2, wmax=2.0)
    r = bound_posterior(gp, lo, hi, tol=1e-9, max_boxes=3, local_solver=None)
    assert r.budget_exhausted.all()
    assert_contains(gp, r, lo, hi, rng)


@settings(deadline=None, max_examples=25)
@given(
    seed=st.integers(0, 10_000),
    d=st.integers(1, 2),
    width=st.floats(0.0, 3.0),
)
def test_relaxation_alone_never_crosses_the_optimum(seed, d, width):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 8))
    X = rng.uniform(-2, 2, (m, d))
    W = rng.normal(0, 2, (1, m))  # mixed signs: tangent and chord terms
    ls = rng.uniform(0.3, 2.0, d)
    lo = rng.uniform(-2, 2, (1, d))
    hi = lo + width * rng.uniform(0, 1, (1, d))
    lin = rng.normal(0, 1, (1, d))
    const = rng.normal(0, 1, 1)
    lb, xstar = _kernel_sum_lower(X, ls, W, lo, hi, lin, const)
    # exhaustive grid of the box (41^d points incl. corners) and random points
    g = np.meshgrid(*[np.linspace(lo[0, j], hi[0, j], 41) for j in range(d)])
    pts = np.vstack([np.column_stack([a.ravel() for a in g]), dense(rng, lo, hi, 2000)[0]])
    z = (((pts[:, None, :] - X[None]) / ls) ** 2).sum(-1)
    F = np.exp(-0.5 * z) @ W[0] + pts @ lin[0] + const[0]
    assert lb[0] <= F.min()
    assert np.all((xstar >= lo) & (xstar <= hi))


@settings(deadline=None, max_examples=15)
@given(seed=st.integers(0, 10_000), width=st.floats(0.0, 4.0))
def test_root_relaxation_of_mean_and_std_never_crosses(seed, width):
    # max_boxes=1: no branching, the bounds are the relaxations of the root box alone
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 10))
    gp = StandInGP(rng.uniform(-2, 2, (m, 1)), rng.normal(0, 2, m), rng.uniform(0.3, 2.0),
                   rng.uniform(0.5, 2.0), rng.uniform(0.01, 2.0))
    lo = rng.uniform(-2, 2, (1, 1))
    hi = lo + width
    r = bound_posterior(gp, lo, hi, max_boxes=1)
    x = np.linspace(lo[0, 0], hi[0, 0], 4001)[:, None]  # exhaustive 1-D grid incl. ends
    mu, sd = gp.predict(x, return_std=True)
    assert r.mean_lower[0] <= mu.min() and mu.max() <= r.mean_upper[0]
    assert sd.max() <= r.std_upper[0]


def test_root_only_is_looser_but_sound():
    gp, rng = random_gp(2, 9)
    lo, hi = random_boxes(rng, 5, 2)
    r_bb = bound_posterior(gp, lo, hi, tol=1e-4, local_solver=None)
    r_root = bound_posterior(gp, lo, hi, tol=1e-4, max_boxes=1, local_solver=None)
    assert_contains(gp, r_root, lo, hi, rng, n=2000)
    assert np.all(r_root.mean_lower <= r_bb.mean_min_achieved)
    assert np.all(r_root.std_upper >= r_bb.std_max_achieved)


def test_image_bound_is_joint_and_sound():
    # GP ~ identity in 1-D; image x - mu(x) ~ 0: the joint bound is much narrower than the
    # sum of separate bounds of -x and mu(x).
    rng = np.random.default_rng(0)
    X = np.linspace(-2, 2, 30)[:, None]
    gps = [
        GaussianProcess(1.0, 1.0, 0.01).fit(X, X[:, 0]),
        GaussianProcess(0.7, 1.0, 0.5).fit(X, np.cos(X[:, 0])),
    ]
    A = np.array([[-1.0], [0.5]])
    b = np.array([0.3, -0.2])
    lo = np.array([[-1.0], [0.2]])
    hi = np.array([[-0.5], [1.0]])
    r = bound_image(gps, A, b, lo, hi, tol=1e-4, local_solver=None)
    assert isinstance(r, ImageBounds) and r.lower.shape == (2, 2)
    pts = dense(rng, lo, hi)
    for i, gp in enumerate(gps):
        mu, sd = gp.predict(pts.reshape(-1, 1), return_std=True)
        img = (pts.reshape(-1, 1) @ A[i] + b[i] + mu).reshape(2, -1)
        assert np.all(r.lower[:, i] <= img.min(1)) and np.all(r.upper[:, i] >= img.max(1))
        assert np.all(r.std_upper[:, i] >= sd.reshape(2, -1).max(1))
    assert not r.budget_exhausted.any()
    assert np.all(r.lower_gap <= 1e-4) and np.all(r.upper_gap <= 1e-4)
    assert np.all(r.std_upper_gap <= 1e-4 + 1e-12)  # + one ulp of the rounded-up sqrt
    sep = bound_posterior(gps[0], lo, hi, tol=1e-4, local_solver=None)
    sep_width = (sep.mean_upper - sep.mean_lower) + (hi - lo)[:, 0]
    assert np.all(r.upper[:, 0] - r.lower[:, 0] < 0.2 * sep_width)


def test_bad_input_messages():
    gp, _ = random_gp(2, 0)
    lo = np.zeros((2, 2))
    with pytest.raises(InvalidInputError, match="box 1 has lower"):
        bound_posterior(gp, lo, np.array([[1.0, 1.0], [-1.0, 1.0]]))
    with pytest.raises(DimensionError, match=r"lower must have shape \(k, 2\)"):
        bound_posterior(gp, np.zeros((2, 3)), np.ones((2, 3)))
    with pytest.raises(DimensionError, match="lower must have shape"):
        bound_posterior(gp, np.zeros(2), np.ones(2))
    with pytest.raises(DimensionError, match="upper must have the same shape"):
        bound_posterior(gp, lo, np.ones((3, 2)))
    with pytest.raises(InvalidInputError, match="upper must contain only finite"):
        bound_posterior(gp, lo, np.array([[1.0, np.nan], [1.0, 1.0]]))
    with pytest.raises(InvalidInputError, match="tol must be a positive"):
        bound_posterior(gp, lo, lo + 1, tol=0.0)
    with pytest.raises(InvalidInputError, match="max_boxes must be a positive integer"):
        bound_posterior(gp, lo, lo + 1, max_boxes=0)
    with pytest.raises(InvalidInputError, match="per_iter must be a positive integer"):
        bound_posterior(gp, lo, lo + 1, per_iter=0)
    with pytest.raises(InvalidInputError, match="local_solver must be"):
        bound_posterior(gp, lo, lo + 1, local_solver="ipopt")
    with pytest.raises(InvalidInputError, match="gp must be a fitted GaussianProcess"):
        bound_posterior(GaussianProcess(), lo, lo + 1)
    stale = random_gp(2, 0)[0]
    stale.noise_variance_ = 0.0  # L_ was computed with lambda = 1 + 2/m
    with pytest.raises(InvalidInputError, match="L_ must be the Cholesky factor"):
        bound_posterior(stale, lo, lo + 1)
    with pytest.raises(DimensionError, match=r"A must have shape \(n, d\) = \(1, 2\)"):
        bound_image([gp], np.zeros((2, 2)), np.zeros(1), lo, lo + 1)
    with pytest.raises(DimensionError, match=r"b must have shape"):
        bound_image([gp], np.zeros((1, 2)), np.zeros(2), lo, lo + 1)
    with pytest.raises(InvalidInputError, match="A and b must contain only finite"):
        bound_image([gp], np.full((1, 2), np.inf), np.zeros(1), lo, lo + 1)
    with pytest.raises(InvalidInputError, match="gps must be a non-empty"):
        bound_image([], np.zeros((0, 2)), np.zeros(0), lo, lo + 1)


def test_mean_bounds_cover_the_exact_posterior_despite_an_inexact_alpha():
    """The error lemma is about mu = k^T (K + lambda I)^{-1} y; bounds.py certifies k^T alpha_ and
    widens by a bound of |k^T (alpha - alpha_)| from the residual. Perturb alpha_ by 1e-3 (far
    above float error) and check the bounds still contain the exact posterior mean at dense
    samples, while the widening stays tiny for an unperturbed GP."""
    from robust_imdp.bounds.gp import GaussianProcess

    rng = np.random.default_rng(11)
    X = rng.uniform(-1, 1, (40, 2))
    y = np.sin(3 * X[:, 0]) + 0.1 * rng.standard_normal(40)
    gp = GaussianProcess(0.5, 1.0, "chowdhury").fit(X, y)
    from robust_imdp.bounds.gp_cells import _GPTerms

    assert 0.0 < _GPTerms(gp).alpha_err < 1e-10  # unperturbed: only float error
    K = gp.kernel(X, X) + gp.noise_variance_ * np.eye(40)
    alpha_exact = np.linalg.solve(K, y)
    gp.alpha_ = gp.alpha_ + 1e-3 * rng.standard_normal(40)
    lo = np.array([[-1.0, -1.0], [0.0, -0.5], [0.5, 0.5]])
    hi = lo + 0.25
    pb = bound_posterior(gp, lo, hi, tol=1e-4)
    for b in range(len(lo)):
        pts = lo[b] + rng.random((5000, 2)) * (hi[b] - lo[b])
        mu = gp.kernel(pts, X) @ alpha_exact
        assert np.all(pb.mean_lower[b] <= mu) and np.all(mu <= pb.mean_upper[b])
