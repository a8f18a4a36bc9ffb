"""The incremental assumption check of the sampling loop (robust_imdp.improve.IncrementalCheck) and its witnesses
(robust_imdp.bounds.rkhs_check: Witness, fit_witness, witness_residuals, witness_norm_upper).

Oracles: the full check (pipeline.bound_stage._check_assumption) on the same data, round by round (the same
decision, the same refusal message, the same NormCheck where the component took the full check); mpmath at
60 digits for the certified norm and residuals of a witness; witnesses built by hand whose residual at a new
point sits just inside or just outside the check's allowance dbar' = up(noise bound + tau).
"""

import mpmath
import numpy as np
import pytest

from robust_imdp import Problem, TruncatedGaussianNoise
from robust_imdp.bounds.rkhs_check import (Witness, data_allowance, fit_witness, witness_fits, witness_norm_upper,
                                           witness_residuals)
from robust_imdp.errors import AssumptionError
from robust_imdp.improve import IncrementalCheck
from robust_imdp.pipeline.bound_stage import _check_assumption, _residual_data
from robust_imdp.pipeline.runtime import _Log

LOG = _Log(False)
SHIFT = np.array([[0.3, 0.0], [0.0, 0.3]])


def _problem(x, u, xn, B, tau=0.001, A=np.eye(2), shift=SHIFT):
    return Problem.from_arrays(
        x, u, xn, lower=[0, 0], upper=[3, 3], cell_size=0.5, regions={"goal": ([2, 2], [3, 3])}, formula="F goal",
        threshold=0.9, modes={"a": (A, shift[0]), "b": (A, shift[1])},
        noise=TruncatedGaussianNoise([0.005, 0.005], [0.01, 0.01]), rkhs_bound=B, lengthscale=1.0,
        misspecification=tau)


def _samples(rng, k, amp):
    x = rng.uniform(0, 3, (k, 2))
    u = rng.integers(0, 2, k)
    xn = x + SHIFT[u] + amp * np.sin(x[:, ::-1]) + rng.uniform(-0.01, 0.01, (k, 2))
    return x, u, xn


def _outcome(fn):
    try:
        return fn(), None
    except AssumptionError as exc:
        return None, str(exc)


@pytest.mark.parametrize("socp", [True, False])
@pytest.mark.parametrize("B", [0.058, 0.062, 0.07, 0.2])
def test_incremental_decision_equals_the_full_check_on_seeded_random_rounds(B, socp):
    # 10 samples, then 8 rounds of 6; from round 5 on the new samples come from a larger drift (amplitude 0.08
    # instead of 0.05), which no function of norm <= 0.2 fits together with the earlier ones
    rng = np.random.default_rng(1)
    x, u, xn = _samples(rng, 10, 0.05)
    chk = IncrementalCheck(socp_witness=socp)
    p = _problem(x, u, xn, B)
    chk.seed(p, _residual_data(p), checks=_check_assumption(p, _residual_data(p), LOG, None)[0])
    hows, decisions = set(), []
    for rnd in range(8):
        a, b, c = _samples(rng, 6, 0.05 if rnd < 5 else 0.08)
        x, u, xn = np.vstack([x, a]), np.concatenate([u, b]), np.vstack([xn, c])
        p = _problem(x, u, xn, B)
        res = _residual_data(p)
        full, full_msg = _outcome(lambda: _check_assumption(p, res, LOG, None))
        inc, inc_msg = _outcome(lambda: chk(p, res, LOG))
        assert inc_msg == full_msg  # both pass (None) or both refuse with the same message
        decisions.append(full_msg is None)
        if full_msg is not None:
            break
        checks, nb, report = inc
        np.testing.assert_array_equal(nb, full[1])
        for c_inc, c_full, row in zip(checks, full[0], report):
            hows.add(row["how"])
            if row["how"] == "full check":  # the component's own job of the full check: the same numbers
                assert c_inc == c_full
            else:  # a witness: its norm bounds the minimum norm from above, the full check's from below
                assert c_full.minimum <= row["witness_norm_upper"] <= B
                # the kept lower bound: the last full check's (more data only raise the minimum) or single points
                assert 0.0 <= c_inc.minimum <= row["witness_norm_upper"]
    assert decisions[-1] is False and any(decisions)  # refused by a round's new samples, after passing rounds
    if B >= 0.07 or socp:
        assert {"witness kept", "witness refitted"} <= hows  # the witness path is taken (not only the SOCP)
    if B <= 0.062 and not socp:  # no ridge fit has norm <= B: the components' own full checks
        assert "full check" in hows


def test_refusal_by_new_points_is_the_full_check_s_message():
    # B = 0.058: rounds 0 and 1 pass (the SOCP's certified minimum <= B), round 2's samples refute B jointly
    rng = np.random.default_rng(1)
    x, u, xn = _samples(rng, 10, 0.05)
    chk = IncrementalCheck()
    for rnd in range(3):
        a, b, c = _samples(rng, 6, 0.05)
        x, u, xn = np.vstack([x, a]), np.concatenate([u, b]), np.vstack([xn, c])
        p = _problem(x, u, xn, 0.058)
        res = _residual_data(p)
        if rnd < 2:
            chk(p, res, LOG)
            continue
        with pytest.raises(AssumptionError) as full:
            _check_assumption(p, res, LOG, None)
        with pytest.raises(AssumptionError) as inc:
            chk(p, res, LOG)
        assert str(inc.value) == str(full.value) and "no function of RKHS norm <= 0.058" in str(inc.value)
        return
    raise AssertionError("round 2 should have refuted B")  # pragma: no cover


# ------------------------------------------------------------------------- the witness's tolerance
def _one_point_problem(y_points, B, tau):
    """Points all at (1, 1): mode 'a' with residuals ``y_points`` in component 1, mode 'b' one sample of residual 0
    (f = 0, so the residual is x_next itself, and the allowance the noise bound 0.01 + tau plus the residuals'
    rounding bound, the same for these residuals)."""
    k = len(y_points)
    x = np.ones((k + 1, 2))
    xn = np.column_stack([np.r_[y_points, 0.0], np.zeros(k + 1)])
    return _problem(x, np.r_[np.zeros(k, int), 1], xn, B, tau=tau, A=np.zeros((2, 2)), shift=np.zeros((2, 2)))


def _kept_witness(tau, B=1.0):
    """A round with one sample of residual 0.5: the check's witness h = alpha k(x0, .) (kernel ridge)."""
    chk = IncrementalCheck()
    p = _one_point_problem([0.5], B, tau)
    chk(p, _residual_data(p), LOG)
    w = chk.state[(0, 0)].witness
    assert w is not None and w.alpha.size == 1
    return chk, w


def test_a_new_point_inside_the_allowance_by_a_hair_keeps_the_witness():
    # tau = 0.002: dbar' = up(0.01 + 0.002). The new point's residual under h is 0.9995 dbar' > 0.01 + 0.999 * tau:
    # a check that shrank the allowance by 0.1 % (or dropped tau) would refit instead of keeping h.
    tau = 0.002
    chk, w = _kept_witness(tau)
    dbar = data_allowance(0.01, tau)
    h = float(w.alpha[0])  # h(x0) = alpha k(x0, x0) = alpha (exact: k = 1)
    y_new = h + 0.9995 * dbar
    assert 0.999 * dbar < float(witness_residuals(w, np.ones((1, 2)), [y_new])[0]) <= dbar
    p = _one_point_problem([0.5, y_new], 1.0, tau)
    checks, _, report = chk(p, _residual_data(p), LOG)
    assert report[0]["how"] == "witness kept" and report[0]["witness_norm_upper"] == w.norm_upper


def test_a_new_point_outside_the_allowance_by_a_hair_is_refused_like_the_full_check():
    # The new point's residual under h is dbar' (1 + 1e-4); with B = ||h|| no other function of norm <= B fits
    # both points (h(x0) would have to be >= y_new - dbar' > ||h||), and the single point refutes B. A check
    # that allowed 0.1 % more than dbar' would keep h and pass.
    tau = 0.002
    dbar = data_allowance(0.01, tau)
    chk, w = _kept_witness(tau)
    B = w.norm_upper
    chk, w = _kept_witness(tau, B)  # the same witness under B = its norm bound (the ridge path is the same)
    assert w.norm_upper <= B
    y_new = float(w.alpha[0]) + dbar * (1 + 1e-4)
    assert dbar < float(witness_residuals(w, np.ones((1, 2)), [y_new])[0]) < 1.001 * dbar
    p = _one_point_problem([0.5, y_new], B, tau)
    with pytest.raises(AssumptionError) as full:
        _check_assumption(p, _residual_data(p), LOG, None)
    with pytest.raises(AssumptionError) as inc:
        chk(p, _residual_data(p), LOG)
    assert str(inc.value) == str(full.value) and "alone has residual" in str(inc.value)


# ------------------------------------------------------------------------- certified witness numbers
def _exact_kernel(a, b, ls):
    return mpmath.exp(-sum((mpmath.mpf(float(p)) - mpmath.mpf(float(q))) ** 2 / (2 * mpmath.mpf(float(l)) ** 2)
                           for p, q, l in zip(a, b, ls)))


def test_witness_norm_and_residuals_bound_the_exact_values_tightly():
    mpmath.mp.dps = 60
    rng = np.random.default_rng(5)
    ls = np.array([0.7, 1.3])
    for _ in range(20):
        C = rng.uniform(-2, 2, (6, 2))
        alpha = rng.normal(0, 1, 6) * 10.0 ** rng.uniform(-3, 1)
        X = rng.uniform(-2, 2, (5, 2))
        y = rng.normal(0, 1, 5)
        w = Witness(C, alpha, ls, witness_norm_upper(C, alpha, ls))
        sq = sum(mpmath.mpf(float(alpha[i])) * mpmath.mpf(float(alpha[j])) * _exact_kernel(C[i], C[j], ls)
                 for i in range(6) for j in range(6))
        exact = mpmath.sqrt(sq)
        assert w.norm_upper >= exact and w.norm_upper <= exact * (1 + 1e-12)  # sound, and tight to 1e-12
        r = witness_residuals(w, X, y)
        for k in range(5):
            h = sum(mpmath.mpf(float(alpha[j])) * _exact_kernel(X[k], C[j], ls) for j in range(6))
            e = abs(h - mpmath.mpf(float(y[k])))
            spread = sum(abs(float(alpha[j])) * _exact_kernel(X[k], C[j], ls) for j in range(6))
            # sound, and within 1e-13 of the sum's scale (~500 u: the error allowance is a few ulps of it)
            assert r[k] >= e and r[k] <= e + 1e-13 * (1 + spread)


def test_fit_witness_fits_every_point_and_returns_none_when_b_is_too_small():
    rng = np.random.default_rng(2)
    X = rng.uniform(-2, 2, (80, 2))
    y = 0.4 * X[:, 0] + 0.1 * X[:, 1] + rng.uniform(-0.01, 0.01, 80)
    w = fit_witness(X, y, 2.0, 0.01, 0.001, 6.0)
    assert w is not None and w.norm_upper <= 6.0 and witness_fits(w, X, y, 0.01, 0.001)
    assert w.norm_upper == witness_norm_upper(w.centres, w.alpha, 2.0)
    assert fit_witness(X, y, 2.0, 0.01, 0.001, 0.1) is None  # |y| up to ~1: no norm-0.1 function fits
    # known component (B = 0): h = 0 is the witness exactly when every |y_i| <= dbar'
    assert fit_witness(X, np.full(80, 0.011), 2.0, 0.01, 0.001, 0.0).norm_upper == 0.0
    assert fit_witness(X, np.full(80, 0.0111), 2.0, 0.01, 0.001, 0.0) is None


def test_witness_norm_bound_holds_under_cancellation():
    # alpha = (a, -a) at centres 1e-3 apart: ||h||^2 = 2 a^2 (1 - k) is ~1e-6 of A = |alpha|^T K |alpha|, so
    # the computed alpha^T K alpha is off by up to ~u A, far beyond one ulp of the result: eq. N's error term
    # (gamma_{2c+2} + r) A is what keeps the bound above the exact norm
    mpmath.mp.dps = 60
    rng = np.random.default_rng(11)
    ls = np.array([1.0, 1.0])
    for _ in range(40):
        c0 = rng.uniform(-1, 1, 2)
        C = np.array([c0, c0 + rng.uniform(-1e-3, 1e-3, 2)])
        a = 10.0 ** rng.uniform(0, 4)
        alpha = np.array([a, -a * (1 + rng.uniform(-1e-9, 1e-9))])
        up = witness_norm_upper(C, alpha, ls)
        sq = sum(mpmath.mpf(float(alpha[i])) * mpmath.mpf(float(alpha[j])) * _exact_kernel(C[i], C[j], ls)
                 for i in range(2) for j in range(2))
        A = sum(abs(float(alpha[i] * alpha[j])) * _exact_kernel(C[i], C[j], ls) for i in range(2) for j in range(2))
        assert up >= mpmath.sqrt(sq) and up ** 2 - sq <= 1e-13 * A  # sound; slack ~ the error term only


def test_fit_witness_accepts_a_ridge_fit_only_within_the_allowance():
    # One point, y = 11 * 1.0005 dbar': the ridge fit with lambda = 0.1 is alpha = y / 1.1, residual
    # y * 0.1 / 1.1 = 1.0005 dbar' (just outside: must be rejected); lambda = 0.01 fits (residual 0.109 dbar')
    dbar = data_allowance(0.01, 0.002)
    X, y = np.zeros((1, 2)), np.array([11 * 1.0005 * dbar])
    w = fit_witness(X, y, 1.0, 0.01, 0.002, 10.0, socp=False)
    assert w is not None and witness_fits(w, X, y, 0.01, 0.002)
    assert float(w.alpha[0]) == pytest.approx(y[0] / 1.01, rel=1e-12)  # the lambda = 0.01 fit, not 0.1
