"""Certified RKHS cell bounds (rkhs.py): every soundness claim is checked independently, and
every check is shown to have teeth (it fails on a bound shrunk by 0.1 % of its width).

Independent references used here:
* mpmath at 50 digits for the kernel, the certificate (eq. W) and the Taylor remainder (eq. T);
* finite kernel expansions ``h = sum_j c_j k(., z_j)`` whose RKHS norm is known exactly
  (``||h||^2 = c^T K_z c``), scaled to the assumed bound B, sampled densely in every cell;
* the extremal functions that attain the Taylor remainder and the optimal pointwise bound;
* cvxpy/clarabel SOCPs (``lp.rkhs_vertex_socp``, ``lp.rkhs_min_norm_socp``).
"""

from __future__ import annotations

import itertools
from fractions import Fraction

import mpmath as mp
import numpy as np
import pytest

from robust_imdp.bounds import rkhs
from robust_imdp.errors import AssumptionError, DimensionError, InvalidInputError
from robust_imdp.solvers.lp import rkhs_min_norm_socp, rkhs_vertex_socp
from robust_imdp.models.noise import GaussianNoise, TruncatedGaussianNoise, UniformNoise

mp.mp.dps = 50
SHRINK = 1e-3  # the "slightly unsound" bound of the sensitivity tests: 0.1 % of the width


# ----------------------------------------------------------------------------- helpers
def kern(A, B, ls):
    """Plain numpy SE kernel (an independent implementation from rkhs._kernel_matrix)."""
    A, B = np.atleast_2d(A), np.atleast_2d(B)
    z = np.sum(((A[:, None, :] - B[None, :, :]) / ls) ** 2, axis=-1)
    return np.exp(-0.5 * z)


def kernel_function(rng, d, n_centres, ls, norm, lo=-1.5, hi=1.5):
    """``h = sum_j c_j k(., z_j)`` with ``||h|| = norm`` (up to 1e-12 relative, scaled down)."""
    Z = rng.uniform(lo, hi, size=(n_centres, d))
    c = rng.standard_normal(n_centres)
    nrm = np.sqrt(c @ kern(Z, Z, ls) @ c)
    c *= norm * (1 - 1e-12) / nrm

    def h(X):
        return kern(X, Z, ls) @ c

    return h


def grid_cells(d, lo, hi, size):
    edges = np.arange(lo, hi - 1e-12, size)
    corners = np.array(list(itertools.product(edges, repeat=d)))
    return corners, corners + size


def samples_in_cells(rng, lower, upper, n_random):
    """Every vertex, the centre and n_random uniform points of each cell: (n_cells, k, d)."""
    d = lower.shape[1]
    signs = np.array(list(itertools.product((0.0, 1.0), repeat=d)))
    verts = lower[:, None, :] + signs[None] * (upper - lower)[:, None, :]
    cen = 0.5 * (lower + upper)[:, None, :]
    rnd = lower[:, None, :] + rng.random((lower.shape[0], n_random, d)) * (upper - lower)[:, None, :]
    return np.concatenate([verts, cen, rnd], axis=1)


def count_violations(values, lower, upper):
    """values (n_cells, k) against per-cell [lower, upper]: number of samples outside."""
    return int(np.sum(values > upper[:, None]) + np.sum(values < lower[:, None]))


def shrink(lower, upper, frac=SHRINK):
    w = upper - lower
    return lower + frac * w, upper - frac * w


# ----------------------------------------------------------------------------- Taylor remainder (eq. T)
def mp_R(t):
    t = mp.mpf(t)
    e = mp.e ** (-t / 2)
    return 2 * (1 - e) + t * (1 - 2 * e)


def test_taylor_remainder_closed_form_matches_feature_space_norm():
    # ||k_x - k_c - D.dk_c||^2 from kernel evaluations only: the derivative section is the limit
    # of (k_{c + hD} - k_{c - hD}) / (2h); at h = 1e-15 in 80-digit arithmetic the difference
    # quotient's error is O(h^2) and the cancellation costs 2 x 15 digits of the 80.
    # Independent of the inner-product identities used in rkhs.py.
    rng = np.random.default_rng(0)
    mp.mp.dps = 80
    for _ in range(5):
        d = int(rng.integers(1, 4))
        ls = [mp.mpf(v) for v in rng.uniform(0.5, 3.0, d)]
        c = [mp.mpf(v) for v in rng.uniform(-1, 1, d)]
        D = [mp.mpf(v) for v in rng.uniform(-0.4, 0.4, d)]
        x = [ci + di for ci, di in zip(c, D)]
        h = mp.mpf("1e-15")

        def k(a, b):
            return mp.e ** (-sum((ai - bi) ** 2 / (2 * li ** 2) for ai, bi, li in zip(a, b, ls)))

        pts = [x, c, [ci + h * di for ci, di in zip(c, D)], [ci - h * di for ci, di in zip(c, D)]]
        coef = [mp.mpf(1), mp.mpf(-1), -1 / (2 * h), 1 / (2 * h)]
        norm2 = sum(coef[i] * coef[j] * k(pts[i], pts[j]) for i in range(4) for j in range(4))
        t = sum(di ** 2 / li ** 2 for di, li in zip(D, ls))
        assert abs(norm2 - mp_R(t)) < mp.mpf("1e-25") * (1 + mp_R(t))
    mp.mp.dps = 50


@pytest.mark.parametrize("t", [0.0, 1e-12, 1e-8, 1e-5, 1e-3, 0.00195, 0.05, 0.3, 1.0, 2.5, 10.0, 100.0])
def test_taylor_remainder_bound_is_an_upper_bound_and_tight(t):
    got = float(rkhs.taylor_remainder_sqrt_up(t))
    exact = mp.sqrt(mp_R(t))
    assert mp.mpf(got) >= exact  # sound (no tolerance)
    # tight: 3t^2/4 is used for tiny t, whose relative excess is about 5t/36; else ~1e-13
    assert mp.mpf(got) <= exact * (1 + mp.mpf("1e-9") + mp.mpf(t) / 5) + mp.mpf("1e-150")


def test_taylor_remainder_check_has_teeth():
    # The same check on a bound 0.1 % too small fails for every t > 0.
    for t in (1e-6, 1e-3, 0.5, 5.0):
        got = float(rkhs.taylor_remainder_sqrt_up(t)) * (1 - SHRINK)
        assert mp.mpf(got) < mp.sqrt(mp_R(t))


def test_taylor_inequality_holds_for_known_norm_functions_and_is_attained():
    # h(x) <= h(c) + D.grad h(c) + ||h|| sqrt(R(t)) for random finite expansions (sound), and the
    # extremal function h* = B (k_x - k_c - D.dk_c) / sqrt(R) attains it (tight).
    rng = np.random.default_rng(1)
    worst = -np.inf
    for _ in range(200):
        d = int(rng.integers(1, 4))
        ls = rng.uniform(0.5, 2.0, d)
        Z = rng.uniform(-1, 1, (6, d))
        cc = rng.standard_normal(6)
        B = float(np.sqrt(cc @ kern(Z, Z, ls) @ cc))
        c = rng.uniform(-1, 1, d)
        D = rng.uniform(-0.3, 0.3, d)
        kc = kern(c, Z, ls)[0]
        grad = (kc * cc) @ ((Z - c) / ls ** 2)  # d/dc of k(c, z) = k (z - c)/l^2
        lin = kc @ cc + D @ grad
        val = kern(c + D, Z, ls)[0] @ cc
        t = float(np.sum(D ** 2 / ls ** 2))
        slack = val - lin - B * float(rkhs.taylor_remainder_sqrt_up(t))
        worst = max(worst, slack)
    assert worst <= 1e-12  # float evaluation of the random expansions only
    # Extremal function: h*(y) = (k(x,y) - k(c,y) - D.d_c k(c,y)) / sqrt(R); h*(x) - [h*(c) + D.grad h*(c)]
    # equals ||h* - ...|| = sqrt(R) in closed form: evaluate it with mpmath.
    d, ls = 2, [mp.mpf(1.3), mp.mpf(0.7)]
    c, D = [mp.mpf(0.1), mp.mpf(-0.2)], [mp.mpf(0.05), mp.mpf(0.03)]
    x = [c[0] + D[0], c[1] + D[1]]
    t = sum(D[a] ** 2 / ls[a] ** 2 for a in range(d))

    def k(a, b):
        return mp.e ** (-sum((a[i] - b[i]) ** 2 / (2 * ls[i] ** 2) for i in range(d)))

    def dk(a, b, i):  # d/db_i k(a, b)
        return k(a, b) * (a[i] - b[i]) / ls[i] ** 2

    def hstar(y):
        return (k(x, y) - k(c, y) - sum(D[i] * dk(y, c, i) for i in range(d))) / mp.sqrt(mp_R(t))

    h = mp.mpf("1e-25")
    grad = [(hstar([c[j] + (h if j == i else 0) for j in range(d)])
             - hstar([c[j] - (h if j == i else 0) for j in range(d)])) / (2 * h) for i in range(d)]
    gap = hstar(x) - hstar(c) - sum(D[i] * grad[i] for i in range(d))
    assert abs(gap - mp.sqrt(mp_R(t))) < mp.mpf("1e-20")
    # teeth: a remainder bound 0.1 % smaller would be violated by h*
    assert gap > mp.sqrt(mp_R(t)) * (1 - SHRINK)


def test_scaled_remainder_is_an_upper_bound_of_the_max_over_the_cell():
    # rho(a) >= max_{s in [0, t]} sqrt(f(s)) (dense grid in mpmath), and equal to the max of the ends.
    for t in (1e-4, 0.002, 0.1, 1.0, 1.38):
        a = float(np.exp(-0.5 * t))
        got = float(rkhs._scaled_remainder_sqrt_up(np.array([a]), np.array([t]))[0])
        am = mp.mpf(a)
        f = [1 + am ** 2 + am ** 2 * s - 2 * am * (1 + s) * mp.e ** (-s / 2) for s in mp.linspace(0, t, 201)]
        exact = mp.sqrt(max(f))
        assert mp.mpf(got) >= exact
        assert mp.mpf(got) <= exact * (1 + mp.mpf("1e-8")) + mp.mpf("1e-140")
        # the scaled remainder is smaller than the plain one (that is why it is used)
        assert got < float(rkhs.taylor_remainder_sqrt_up(t))
    assert np.isinf(rkhs._scaled_remainder_sqrt_up(np.array([0.9]), np.array([3.5]))[0])  # not convex there
    assert np.isinf(rkhs._scaled_remainder_sqrt_up(np.array([0.4]), np.array([1.0]))[0])  # 1 - a inexact


# ----------------------------------------------------------------------------- geometry and kernel
def test_cell_centres_contain_the_cell_exactly():
    rng = np.random.default_rng(2)
    lo = rng.uniform(-1e3, 1e3, (500, 3)) * rng.choice([1e-7, 1.0, 1e5], (500, 3))
    up = lo + np.abs(rng.standard_normal((500, 3))) * rng.choice([1e-12, 1e-3, 10.0], (500, 3))
    lo[0] = [0.1, 0.2, 0.3]
    up[0] = [0.1 + 1e-17, np.nextafter(0.2, 1), 0.7]
    c, r = rkhs.cell_centres(lo, up)
    for q in range(lo.shape[0]):
        for a in range(3):
            assert Fraction(c[q, a]) - Fraction(r[q, a]) <= Fraction(lo[q, a])
            assert Fraction(c[q, a]) + Fraction(r[q, a]) >= Fraction(up[q, a])


def test_inverse_squared_lengthscales_are_rounded_up():
    for ls in (0.1, 0.3, 1.0, 2.0, 3.0, 7.77, 123.456):
        inv = rkhs._inv_l2(ls, 1)[0]
        assert Fraction(inv) >= 1 / (Fraction(ls) * Fraction(ls))


def test_kernel_entries_within_the_stated_relative_error():
    rng = np.random.default_rng(3)
    X = rng.uniform(-3, 3, (25, 3))
    model = rkhs.KernelModel(X, np.zeros(25), [0.7, 1.9, 3.0])
    worst = 0.0
    for i in range(25):
        for j in range(25):
            z = sum((mp.mpf(X[i, a]) - mp.mpf(X[j, a])) ** 2 * mp.mpf(model.inv_l2[a]) for a in range(3))
            exact = mp.e ** (-z / 2)
            rel = abs((mp.mpf(model.K[i, j]) - exact) / exact)
            worst = max(worst, float(rel / model.K_err))
    assert worst <= 1.0
    assert worst > 1e-4  # the stated bound is not absurdly loose (teeth against a x1e4 over-claim)


# ----------------------------------------------------------------------------- the certificate (eq. W)
def mp_certificate(X, y, inv_l2, c, v, w, a1, a2, G, side):
    """Exact value of w.y + side (a1|w|_1 + a2|w|_2 + G ||phi_v - Phi* w||) in 50 digits."""
    d = X.shape[1]
    m = X.shape[0]
    L = [mp.mpf(v_) for v_ in inv_l2]

    def k(a, b):
        return mp.e ** (-sum((mp.mpf(a[i]) - mp.mpf(b[i])) ** 2 * L[i] for i in range(d)) / 2)

    b = [k(X[i], c) * (1 + sum(mp.mpf(v[a]) * (mp.mpf(X[i, a]) - mp.mpf(c[a])) * L[a] for a in range(d)))
         for i in range(m)]
    s0 = 1 + sum(mp.mpf(v[a]) ** 2 * L[a] for a in range(d))
    W = [mp.mpf(x) for x in w]
    q = s0 - 2 * sum(W[i] * b[i] for i in range(m)) + sum(W[i] * W[j] * k(X[i], X[j]) for i in range(m)
                                                           for j in range(m))
    rad = a1 * sum(abs(x) for x in W) + a2 * mp.sqrt(sum(x * x for x in W)) + G * mp.sqrt(max(q, 0))
    return sum(W[i] * mp.mpf(y[i]) for i in range(m)) + side * rad, q


def test_certificate_bounds_the_exact_value_including_cancellation():
    # Interpolation-like weights make ||phi - Phi* w|| tiny: the float quadratic form cancels
    # catastrophically. The certified value must still bound the 50-digit value, and the error
    # term must matter: without it (naive float) some cases fall on the wrong side.
    rng = np.random.default_rng(4)
    naive_wrong = 0
    for trial in range(30):
        d = 2
        X = rng.uniform(-1, 1, (12, d))
        y = rng.standard_normal(12)
        model = rkhs.KernelModel(X, y, 3.0)  # long lengthscale: ill-conditioned K, large weights
        c, r = rkhs.cell_centres(X[:1] - 1e-3, X[:1] + 1e-3)
        signs = rkhs.vertex_signs(d)
        vp = rkhs.vertex_problems(model, c, r, signs)
        j = trial % 4
        b, eb, s0 = vp["b"][0, j], vp["b_err"][0, j], vp["s0"][0, j]
        w = np.linalg.solve(model.K + 1e-13 * np.eye(12), b)  # near-interpolation weights
        if trial % 3 == 1:
            w = w + rng.standard_normal(12) * 1e-3
        for side in (1, -1):
            cert = rkhs.certify_weights(model, b[None], eb[None], np.array([s0]), w[None], noise_l1=0.01,
                                        noise_l2=0.0, rkhs_bound=2.0, side=side)[0]
            exact, q = mp_certificate(X, y, model.inv_l2, c[0], vp["v"][0, j], w, mp.mpf("0.01"), 0, 2, side)
            assert (mp.mpf(cert) - exact) * side >= 0  # sound, no tolerance
            assert abs(mp.mpf(cert) - exact) < mp.mpf("1e-4")  # and not vacuous
            s0_float = 1.0 + np.sum(vp["v"][0, j] ** 2 * model.inv_l2)  # not rounded up
            naive_q = s0_float - 2 * w @ b + w @ model.K @ w
            naive = w @ y + side * (0.01 * np.abs(w).sum() + 2.0 * np.sqrt(max(naive_q, 0.0)))
            naive_wrong += int((mp.mpf(naive) - exact) * side < 0)
    assert naive_wrong > 0  # the test can tell a missing error term


def test_certificate_is_sound_for_huge_cancelling_weights():
    # Weights t (e_i - e_j) with t = 1e5 on two points 1e-4 apart nearly cancel in feature space:
    # the float quadratic form ||phi - Phi* w||^2 sums terms of size t^2 ~ 1e10 to a value of
    # ~1e-3, losing ~1e-6 -- far more than the upward rounding of <phi, phi>, so only the explicit
    # error term (added before the square root) keeps the certificate on the safe side of the
    # 50-digit value. Both sides, 16 problems; the float error has either sign, so dropping the
    # error term fails here (benchmarks/mutations.py: rkhs-quadform-error-off).
    rng = np.random.default_rng(15)
    for trial in range(16):
        base = rng.uniform(-1, 1, (6, 1))
        X = np.concatenate([base, base + 1e-4])
        y = rng.uniform(-1, 1, 12)
        model = rkhs.KernelModel(X, y, 1.0)
        c, r = rkhs.cell_centres(np.array([[0.05]]), np.array([[0.07]]))
        vp = rkhs.vertex_problems(model, c, r)
        j = trial % 2
        b, eb, s0 = vp["b"][0, j], vp["b_err"][0, j], vp["s0"][0, j]
        w = rng.uniform(-0.1, 0.1, 12)
        i = trial % 6
        w[i] += 1e5 * (1 + trial / 7)
        w[i + 6] -= 1e5 * (1 + trial / 7)
        for side in (1, -1):
            cert = rkhs.certify_weights(model, b[None], eb[None], np.array([s0]), w[None], noise_l1=0.0,
                                        rkhs_bound=1.0, side=side)[0]
            exact, _ = mp_certificate(X, y, model.inv_l2, c[0], vp["v"][0, j], w, 0, 0, 1, side)
            assert (mp.mpf(cert) - exact) * side >= 0
            assert abs(mp.mpf(cert) - exact) < mp.mpf("1e-3")  # not vacuous


def test_certificate_with_l2_term_and_shrunk_version_fails():
    rng = np.random.default_rng(5)
    X = rng.uniform(-1, 1, (10, 1))
    y = rng.standard_normal(10)
    model = rkhs.KernelModel(X, y, 0.8)
    c, r = rkhs.cell_centres(np.array([[0.1]]), np.array([[0.2]]))
    vp = rkhs.vertex_problems(model, c, r)
    w = rng.standard_normal(10) * 0.1
    for side in (1, -1):
        cert = rkhs.certify_weights(model, vp["b"][0, 1][None], vp["b_err"][0, 1][None], vp["s0"][0, 1:2],
                                    w[None], noise_l1=0.02, noise_l2=0.3, rkhs_bound=1.5, side=side)[0]
        exact, _ = mp_certificate(X, y, model.inv_l2, c[0], vp["v"][0, 1], w, mp.mpf("0.02"), mp.mpf("0.3"),
                                  mp.mpf("1.5"), side)
        assert (mp.mpf(cert) - exact) * side >= 0
        radius = abs(float(exact) - float(w @ y))
        assert (mp.mpf(cert - side * SHRINK * radius) - exact) * side < 0  # teeth


# ----------------------------------------------------------------------------- Monte Carlo soundness
def _mc_case(rng, d, method, noise_kind, n_cells_side, known=False, tau=0.0):
    ls = rng.uniform(0.6, 2.0, d)
    B = rng.uniform(0.5, 3.0)
    dbar = rng.choice([0.005, 0.02, 0.1])
    h = kernel_function(rng, d, 8, ls, B)
    e = (lambda X: tau * np.sin(37 * X[:, 0] + 11 * X[:, -1])) if tau else (lambda X: 0.0)
    m = int(rng.integers(15, 60))
    X = rng.uniform(-1, 1, (m, d))
    g = h(X) + e(X)
    if noise_kind == "uniform":
        noise = rng.uniform(-dbar, dbar, m)
    elif noise_kind == "signs":
        noise = dbar * rng.choice([-1.0, 1.0], m)
    else:  # adversarial: push every sample away from a smooth fit of the clean values
        Kx = kern(X, X, ls)
        mu = Kx @ np.linalg.solve(Kx + 0.5 * np.eye(m), g)
        noise = dbar * np.where(g >= mu, 1.0, -1.0)
    y = g + noise
    A = rng.standard_normal(d) if known else np.zeros(d)
    b0 = float(rng.standard_normal()) if known else 0.0
    lo, up = grid_cells(d, -1.0, 1.0, 2.0 / n_cells_side)
    cr = rkhs.cell_ranges(rkhs.KernelModel(X, y, ls), lo, up, rkhs_bound=B, noise_bound=dbar,
                          misspecification=tau, known_row=A, known_offset=b0, method=method)
    P = samples_in_cells(rng, lo, up, 6)
    vals = np.stack([h(P[q]) + e(P[q]) + P[q] @ A + b0 for q in range(lo.shape[0])])
    return count_violations(vals, cr.lower, cr.upper), lo.shape[0], cr


def test_cell_bounds_contain_known_norm_functions_on_10000_cells():
    # Functions of exactly known norm B, noise uniform / random +-dbar / adversarial +-dbar, with and
    # without a known affine part and a misspecification term; d = 1, 2, 3; both weight methods.
    # Soundness claim: zero samples outside (no probability involved: the bound is deterministic).
    rng = np.random.default_rng(6)
    total_cells = total_viol = 0
    configs = []
    for noise_kind in ("uniform", "signs", "adversarial"):
        configs += [(1, "optimal", noise_kind, 60, False, 0.0)] * 8
        configs += [(2, "optimal", noise_kind, 16, True, 0.0)] * 8
        configs += [(2, "optimal", noise_kind, 12, False, 0.01)] * 3
        configs += [(3, "optimal", noise_kind, 5, True, 0.0)] * 3
        configs += [(2, "ridge", noise_kind, 10, True, 0.0)] * 2
    for d, method, nk, side, known, tau in configs:
        viol, n, _ = _mc_case(rng, d, method, nk, side, known, tau)
        total_viol += viol
        total_cells += n
    assert total_cells >= 10_000
    assert total_viol == 0


# ----------------------------------------------------------------------------- optimality and teeth
def _point_problem(seed, m=30, d=2):
    rng = np.random.default_rng(seed)
    ls = rng.uniform(0.7, 1.5, d)
    h = kernel_function(rng, d, 6, ls, 1.0)
    X = rng.uniform(-1, 1, (m, d))
    y = h(X) + rng.uniform(-0.02, 0.02, m)
    x = rng.uniform(-0.8, 0.8, (1, d))
    return rkhs.KernelModel(X, y, ls), x


@pytest.mark.parametrize("seed", range(6))
def test_optimal_bound_is_attained_by_an_admissible_function(seed):
    # Degenerate cell = one point x (no Taylor term). From the optimal weights w (our active set, whose
    # optimum is checked against the SOCP below), the extremal function h* = B (k_x - Phi* w) /
    # ||k_x - Phi* w|| has norm B and h*(x) = the optimum; it meets the data within dbar + eta (eta = its
    # measured violation, ~ the optimiser's tolerance). With the noise bound dbar + eta our certified
    # bound must contain h*(x) (hard check) and exceed it by no more than eta ||w||_1 (tight).
    model, x = _point_problem(seed)
    B, dbar = 2.0, 0.02
    c, r = rkhs.cell_centres(x, x)
    vp = rkhs.vertex_problems(model, c, r, np.zeros((1, model.d)))
    b, s0 = vp["b"][0, 0], vp["s0"][0, 0]
    for side in (1, -1):
        w, status = rkhs.optimal_weights(model, b, s0, noise=dbar, rkhs_bound=B, side=side)
        assert status == 0
        res = s0 - 2 * w @ b + w @ model.K @ w
        hstar_X = side * B * (b - model.K @ w) / np.sqrt(res)  # h*(x_i)
        hstar_x = side * B * (s0 - w @ b) / np.sqrt(res)  # h*(x) = <h*, k_x>
        eta = max(float(np.max(np.abs(hstar_X - model.y)) - dbar), 0.0) * 1.001 + 1e-15
        cr = rkhs.cell_ranges(model, x, x, rkhs_bound=B, noise_bound=dbar + eta)
        bound = cr.upper[0] if side > 0 else cr.lower[0]
        width = cr.upper[0] - cr.lower[0]
        assert side * (bound - hstar_x) >= 0  # sound: h* is admissible
        # optimal: the optimum moves by ||w||_1 per unit of noise bound (w is the dual), so the
        # inflated bound may exceed h*(x) by about eta ||w||_1, and by nothing else
        assert side * (bound - hstar_x) <= 4 * eta * np.abs(w).sum() + 1e-8 * width
        shrunk = bound - side * SHRINK * width
        assert side * (shrunk - hstar_x) < 0  # teeth: a 0.1 % shrink excludes an admissible function


def test_active_set_matches_the_socp_optimum():
    rng = np.random.default_rng(7)
    for seed in range(8):
        model, x = _point_problem(100 + seed, m=40)
        lo = x - rng.uniform(0.01, 0.1, x.shape)
        up = x + rng.uniform(0.01, 0.1, x.shape)
        c, r = rkhs.cell_centres(lo, up)
        signs = rkhs.vertex_signs(model.d)
        vp = rkhs.vertex_problems(model, c, r, signs)
        val, sup, stat = rkhs._optimal_cells(model.X, model.y, model.K, model.K_err, model.inv_l2, c, r, signs,
                                             0.02, 2.0, model.m, 2000, 1e-10, np.array([0, 1]),
                                             np.zeros((1, signs.shape[0])), False, np.zeros(1, dtype=np.int64))
        for j in range(signs.shape[0]):
            for side, col in ((1, 0), (-1, 1)):
                ref, _ = rkhs_vertex_socp(model.K, model.y, vp["b"][0, j], vp["s0"][0, j], 0.02, 2.0, side)
                ours = side * val[0, j, col]  # certified value of min_w side w.y + ...
                assert ours >= ref - 1e-7  # a certificate can never beat the optimum (solver tol)
                assert ours <= ref + 1e-6  # and ours is optimal


def test_ridge_certificates_are_sound_but_never_tighter_than_optimal():
    rng = np.random.default_rng(8)
    for seed in range(4):
        model, x = _point_problem(200 + seed, m=50)
        lo, up = grid_cells(2, -1.0, 1.0, 0.25)
        opt = rkhs.cell_ranges(model, lo, up, rkhs_bound=2.0, noise_bound=0.02, method="optimal", prune=False)
        rid = rkhs.cell_ranges(model, lo, up, rkhs_bound=2.0, noise_bound=0.02, method="ridge")
        assert np.all(rid.vertex_upper >= opt.vertex_upper - 1e-9)
        assert np.all(rid.vertex_lower <= opt.vertex_lower + 1e-9)
        assert np.median(rid.upper - rid.lower) > np.median(opt.upper - opt.lower)
        # pruning keeps certified neighbour values where they cannot change the cell bound
        pr = rkhs.cell_ranges(model, lo, up, rkhs_bound=2.0, noise_bound=0.02, method="optimal")
        assert np.all(pr.vertex_upper >= opt.vertex_upper - 1e-9)
        assert np.max(pr.upper - opt.upper) < 1e-3 and np.max(opt.lower - pr.lower) < 1e-3
    del rng


def test_known_affine_part_is_added_exactly():
    # g = 0 data: the range of A x + b over each cell is [A c + b - |A| r, A c + b + |A| r]; our bound
    # must contain it and exceed it only by the remainder and noise terms.
    rng = np.random.default_rng(9)
    X = rng.uniform(-1, 1, (30, 2))
    model = rkhs.KernelModel(X, np.zeros(30), 1.0)
    lo, up = grid_cells(2, -1.0, 1.0, 0.5)
    A, b = np.array([2.0, -3.0]), 0.7
    cr = rkhs.cell_ranges(model, lo, up, rkhs_bound=1e-3, noise_bound=1e-6, known_row=A, known_offset=b)
    c, r = 0.5 * (lo + up), 0.5 * (up - lo)
    exact_up = c @ A + b + r @ np.abs(A)
    exact_lo = c @ A + b - r @ np.abs(A)
    assert np.all(cr.upper >= exact_up) and np.all(cr.lower <= exact_lo)
    assert np.all(cr.upper - exact_up < 2e-3) and np.all(exact_lo - cr.lower < 2e-3)


# ----------------------------------------------------------------------------- the assumption (section 4)
def test_min_norm_certificate_is_sound_and_tight():
    rng = np.random.default_rng(10)
    for seed in range(5):
        ls = rng.uniform(0.5, 1.5)
        h = kernel_function(rng, 2, 6, ls, rng.uniform(1, 4))
        X = rng.uniform(-1, 1, (40, 2))
        y = h(X) + rng.uniform(-0.01, 0.01, 40)
        r = rkhs.min_rkhs_norm(X, y, ls, 0.01)
        mn, n_used = r["minimum"], r["n_points"]
        w, primal = rkhs_min_norm_socp(rkhs.KernelModel(X, y, ls).K, y, 0.01)
        assert mn <= primal * (1 + 1e-6)  # the certified lower bound never exceeds a feasible norm
        assert mn >= primal * (1 - 1e-3)  # and it is tight
        assert mn * (1 + 1e-2) > primal  # teeth: a 1 % over-claim would exceed a feasible norm
        assert n_used == 40


def test_min_norm_never_exceeds_the_norm_of_the_generating_function():
    rng = np.random.default_rng(11)
    for _ in range(10):
        ls = rng.uniform(0.5, 2.0)
        B = rng.uniform(0.5, 5.0)
        h = kernel_function(rng, 2, 5, ls, B)
        X = rng.uniform(-1, 1, (30, 2))
        y = h(X) + rng.choice([-0.02, 0.02], 30)
        assert rkhs.min_rkhs_norm(X, y, ls, 0.02)["minimum"] <= B  # h explains the data


def test_min_norm_single_point_and_subset():
    X = np.array([[0.0, 0.0], [1.0, 1.0], [0.5, -0.5]])
    y = np.array([0.1, 7.5, -0.2])
    r = rkhs.min_rkhs_norm(X, y, 1.0, 0.5, solver=False)
    assert r["sample"] == 1 and r["n_points"] == 1
    # |h(x)| <= ||h|| for the unit kernel: one point with |y| = 7.5 and noise 0.5 needs ||h|| >= 7
    assert r["minimum"] == pytest.approx(7.0, rel=1e-12) and r["minimum"] <= 7.0
    rng = np.random.default_rng(12)
    Xb = rng.uniform(-1, 1, (300, 2))
    yb = np.sin(3 * Xb[:, 0]) + rng.uniform(-0.01, 0.01, 300)
    full = rkhs.min_rkhs_norm(Xb, yb, 0.7, 0.01)
    sub = rkhs.min_rkhs_norm(Xb, yb, 0.7, 0.01, max_points=100)
    assert full["n_points"] == 300 and sub["n_points"] == 100
    assert sub["minimum"] <= full["minimum"] * (1 + 1e-9)  # fewer constraints, smaller minimum


def test_check_assumption_refuses_a_refuted_bound_with_a_clear_message():
    rng = np.random.default_rng(13)
    X = rng.uniform(-1, 1, (40, 2))
    Y = np.stack([np.sin(2 * X[:, 0]), 0.1 * X[:, 1]], axis=1)
    data = [(X, Y), (X, 0.5 * Y)]
    checks = rkhs.check_assumption(data, lengthscale=1.0, rkhs_bound=100.0, noise_bound=[0.01, 0.01],
                                   mode_names=["left", "right"])
    worst = max(c.minimum for c in checks)
    assert len(checks) == 4 and worst > 0.5
    with pytest.raises(AssumptionError, match=r"\[learning\]\.rkhs_bound = 0\.5.*mode 'left', component 1"):
        rkhs.check_assumption(data, lengthscale=1.0, rkhs_bound=0.5, noise_bound=[0.01, 0.01],
                              mode_names=["left", "right"])
    Yb = Y.copy()
    Yb[7, 1] = 99.0
    with pytest.raises(AssumptionError, match=r"sample 17 alone has residual 99"):
        rkhs.check_assumption([(X, Yb)], lengthscale=1.0, rkhs_bound=5.0, noise_bound=[0.01, 0.01],
                              sample_index=[np.arange(10, 50)])


def test_empty_interval_is_reported_as_refuted_data(monkeypatch):
    # A certified interval with lower > upper proves that no admissible function exists; image_ranges
    # must say so instead of passing an invalid box on (the abstraction would reject it less clearly).
    X = np.array([[0.0], [0.5]])
    Y = np.array([[0.0], [0.1]])

    class Zero:
        A = np.zeros((1, 1))
        b = np.zeros(1)

    real = rkhs.cell_ranges

    def empty(*args, **kwargs):
        cr = real(*args, **kwargs)
        return rkhs.CellRange(cr.upper + 1.0, cr.upper, cr.eps, cr.support, cr.vertex_lower, cr.vertex_upper,
                              cr.taylor)

    monkeypatch.setattr(rkhs, "cell_ranges", empty)
    with pytest.raises(AssumptionError, match="contradict the assumption.*mode 0, component 1"):
        rkhs.image_ranges([(X, Y)], [Zero()], np.array([[0.0]]), np.array([[0.25]]), lengthscale=1.0,
                          rkhs_bound=0.5, noise_bound=[0.01])


# ----------------------------------------------------------------------------- noise events
def test_noise_bound_at_confidence():
    b, fail = rkhs.noise_bound_at_confidence(TruncatedGaussianNoise(0.1, 0.2), 500, 0.01)
    assert fail == 0.0 and np.all(b == 0.2)
    b, fail = rkhs.noise_bound_at_confidence(UniformNoise([0.1, 0.3]), 500, 0.01)
    assert fail == 0.0 and b.tolist() == [0.1, 0.3]
    g = GaussianNoise([0.1, 0.2])
    b, fail = rkhs.noise_bound_at_confidence(g, 500, 0.01)
    assert fail == 0.01
    # P(|v_i| > b_i) <= delta / (m n) for each of the m n noise values (mpmath tail)
    for i, s in enumerate([0.1, 0.2]):
        tail = mp.erfc(mp.mpf(b[i]) / (mp.mpf(s) * mp.sqrt(2)))
        assert tail <= mp.mpf(0.01) / (500 * 2)
        assert tail >= mp.mpf(0.01) / (500 * 2) * (1 - mp.mpf("1e-6"))


def test_hoeffding_factor():
    s = rkhs.hoeffding_factor(1000, 0.01)
    assert 2 * mp.e ** (-mp.mpf(s) ** 2 / 2) * 1000 <= mp.mpf(0.01)
    assert 2 * mp.e ** (-mp.mpf(s * (1 - 1e-6)) ** 2 / 2) * 1000 > mp.mpf(0.01)
    with pytest.raises(InvalidInputError, match="delta"):
        rkhs.hoeffding_factor(10, 1.5)


def test_iid_intersection_is_sound_and_never_wider():
    # Independent uniform noise: with probability >= 1 - delta the iid interval holds; over 20 data
    # sets at delta = 0.01 a failure anywhere has probability <= 0.2 -- but the union bound over
    # all cells makes each data set's failure far rarer; we demand zero.
    rng = np.random.default_rng(14)
    viol = 0
    for _ in range(20):
        ls = 1.0
        h = kernel_function(rng, 1, 6, ls, 1.0)
        X = rng.uniform(-1, 1, (200, 1))
        y = h(X) + rng.uniform(-0.05, 0.05, 200)
        lo, up = grid_cells(1, -1.0, 1.0, 0.05)
        model = rkhs.KernelModel(X, y, ls)
        fac = rkhs.hoeffding_factor(lo.shape[0] * 2, 0.01)
        det = rkhs.cell_ranges(model, lo, up, rkhs_bound=1.0, noise_bound=0.05)
        both = rkhs.cell_ranges(model, lo, up, rkhs_bound=1.0, noise_bound=0.05, iid_factor=fac,
                                iid_theta=0.05 / np.sqrt(3))
        assert np.all(both.upper <= det.upper) and np.all(both.lower >= det.lower)
        P = samples_in_cells(rng, lo, up, 10)
        vals = np.stack([h(P[q]) for q in range(lo.shape[0])])
        viol += count_violations(vals, both.lower, both.upper)
    assert viol == 0


# ----------------------------------------------------------------------------- input validation
def test_bad_inputs_name_the_argument():
    X = np.zeros((3, 2))
    with pytest.raises(DimensionError, match="y must have shape"):
        rkhs.KernelModel(X, np.zeros(4), 1.0)
    with pytest.raises(InvalidInputError, match="lengthscale"):
        rkhs.KernelModel(X, np.zeros(3), -1.0)
    with pytest.raises(DimensionError, match="lengthscale"):
        rkhs.KernelModel(X, np.zeros(3), [1.0, 2.0, 3.0])
    model = rkhs.KernelModel(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), np.zeros(3), 1.0)
    lo, up = np.zeros((1, 2)), np.ones((1, 2))
    with pytest.raises(InvalidInputError, match="method"):
        rkhs.cell_ranges(model, lo, up, rkhs_bound=1.0, noise_bound=0.1, method="exact")
    with pytest.raises(InvalidInputError, match="rkhs_bound"):
        rkhs.cell_ranges(model, lo, up, rkhs_bound=0.0, noise_bound=0.1)
    with pytest.raises(InvalidInputError, match="noise_bound"):
        rkhs.cell_ranges(model, lo, up, rkhs_bound=1.0, noise_bound=-0.1)
    with pytest.raises(DimensionError, match="cells_lower"):
        rkhs.cell_ranges(model, np.zeros((1, 3)), np.ones((1, 3)), rkhs_bound=1.0, noise_bound=0.1)
    with pytest.raises(InvalidInputError, match="cells_lower"):
        rkhs.cell_ranges(model, up, lo, rkhs_bound=1.0, noise_bound=0.1)
