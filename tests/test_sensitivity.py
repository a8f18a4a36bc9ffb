"""Tests of the tests (issue 14): every soundness check must fail on a slightly unsound bound.

Pattern: build a problem on which the bound is *tight*, run the check of
``tests/soundness_checks.py`` on the real bound (0 violations) and on the same bound shrunk by
0.1 % -- a lower bound times 1 + 1e-3, an upper bound times 1 - 1e-3, a box bound moved inward
by 1e-3 of its width -- (> 0 violations). A shrunk bound that the check cannot see would mean
the check is blind at that resolution. The Monte-Carlo checks of synthesis and controller have
their own sensitivity tests in ``test_tight_monte_carlo.py`` (1 % errors, statistical), the
abstraction's floor in ``test_abstraction.py`` and the outward rounding in ``test_rounding.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import special

from robust_imdp.abstraction.rows import CellBounds, abstract
from robust_imdp.bounds.gp_cells import bound_image, bound_posterior
from robust_imdp.spec.dfa import ltlf_to_dfa
from robust_imdp.models.geometry import Box, Partition, Region
from robust_imdp.models.imdp import IMDP
from robust_imdp.models.noise import GaussianNoise
from robust_imdp.solvers.api import evaluate_strategy, solve_reachability
from robust_imdp.synthesis.core import synthesize

from soundness_checks import (
    KINDS, check_bracket, check_intervals, check_posterior_bounds, check_synthesis, dense_rows, drop_upper,
    gauss_interval, interval_kinds, raise_lower, shrink_kind,
)
from test_bounds import random_boxes, random_gp
from test_synthesis import _inner, bruteforce_evaluate, bruteforce_solve, random_imdp


# ============================================================================ GP box bounds
@pytest.mark.parametrize("d", [1, 2, 3])
def test_posterior_bound_check_sees_a_shrink(d):
    """bounds.py mean/std bounds at tol 1e-7 against samples + corners + L-BFGS-B polish.

    Real bounds: 0 violations. Mean bounds moved inward by 1e-3 of the box's mean range
    (>= 1e-5 here, 100x the certified gap) and the std bound times 1 - 1e-3: every one of the
    3 x 6 bounds is flagged (the polished estimates are within ~1e-10 of the true extrema).
    """
    gp, rng = random_gp(d, 3)
    lo, hi = random_boxes(rng, 6, d)
    pb = bound_posterior(gp, lo, hi, tol=1e-7, max_boxes=20_000)
    assert not pb.budget_exhausted.any()
    w = pb.mean_upper - pb.mean_lower
    assert np.all(w > 1e-2)  # the inward shift 1e-3 w is far above the 1e-7 gap
    real = check_posterior_bounds(pb.mean_lower, pb.mean_upper, pb.std_upper, gp, lo, hi,
                                  np.random.default_rng(0), n=2000)
    shrunk = check_posterior_bounds(pb.mean_lower + 1e-3 * w, pb.mean_upper - 1e-3 * w, drop_upper(pb.std_upper),
                                    gp, lo, hi, np.random.default_rng(0), n=2000)
    assert real == 0
    assert shrunk == 3 * lo.shape[0]


def test_image_bound_check_sees_a_shrink():
    """bound_image (affine part + mean, bounded jointly) with the same check and shrink."""
    gp, rng = random_gp(2, 5)
    A, b = np.array([[0.7, -1.2]]), np.array([0.3])
    lo, hi = random_boxes(rng, 4, 2)
    ib = bound_image([gp], A, b, lo, hi, tol=1e-7, max_boxes=20_000)

    class Image:  # the image x -> A x + b + mu(x) with the posterior's std, for the check
        signal_variance_, alpha_, X_train_ = gp.signal_variance_, gp.alpha_, gp.X_train_

        @staticmethod
        def predict(Z, return_std=False):
            mu, sd = gp.predict(Z, return_std=True)
            img = Z @ A[0] + b[0] + mu
            return (img, sd) if return_std else img

    w = ib.upper[:, 0] - ib.lower[:, 0]
    real = check_posterior_bounds(ib.lower[:, 0], ib.upper[:, 0], ib.std_upper[:, 0], Image, lo, hi,
                                  np.random.default_rng(1), n=2000)
    shrunk = check_posterior_bounds(ib.lower[:, 0] + 1e-3 * w, ib.upper[:, 0] - 1e-3 * w,
                                    drop_upper(ib.std_upper[:, 0]), Image, lo, hi, np.random.default_rng(1), n=2000)
    assert real == 0 and shrunk == 3 * lo.shape[0]


# ============================================================================ abstraction intervals
def setpoint_abstraction(sigma, setpoints):
    """1-D "setpoint" system x' = c_u + v (v ~ N(0, sigma^2)) on X = [-1, 1].

    Every cell's image under mode u is the single point c_u (an exact image box), so the exact
    transition probabilities are the same for every x of a cell and Thm 1 is tight where the
    event is symmetric about c_u. Cells: width 0.5 plus a narrow cell [0.6, 0.7].
    Returns the abstraction and T (n_modes, n_cells, n_cells + 1), exact to ~1e-16.
    """
    part = Partition(Box([-1.0], [1.0]), 0.5, [Region("n", (Box([0.6], [0.7]),))])
    c = np.asarray(setpoints, dtype=float)
    M, N = c.size, part.n_cells
    img = c[:, None, None] * np.ones((M, N, 1))
    ab = abstract(part, CellBounds(img, img), GaussianNoise([sigma]))
    bp = part.breakpoints[0]
    T = gauss_interval((bp[None, :-1] - c[:, None]) / sigma, (bp[None, 1:] - c[:, None]) / sigma)
    out = special.ndtr((-1.0 - c) / sigma) + special.ndtr((c - 1.0) / sigma)
    T = np.concatenate([T, out[:, None]], axis=1)
    return ab, np.broadcast_to(T[:, None, :], (M, N, N + 1))


# Which entries are tight (exact values from setpoint_abstraction):
#   sigma 0.07, c = 0.25 (centre of [0, 0.5], margin 3.57 sigma): listed upper 1 vs truth 0.99964
#   sigma 0.07, c = 0.65 (centre of [0.6, 0.7]): listed lower P[|v| <= 0.05] = 0.52495 = truth
#   sigma 0.4,  c = 0 (centre of X): outside upper P[|v| > 1] = 0.012419 = truth
#   sigma 0.4,  c = 2.5 (outside, gap 1.5): outside lower P[|v| <= 1.5] = 0.99982 vs truth 0.99991
#   (the complement of an outside-lower bound is two tails against the truth's one, so it is
#   tight only near 1, where x (1 + 1e-3) passes the truth)
SETPOINT_PROBLEMS = [(0.07, [0.25, 0.65]), (0.4, [0.0, 2.5])]
TOL_T = 1e-13  # T is a difference of ndtr values (error ~1e-16); the bounds carry ~1e-13 rounding


@pytest.mark.parametrize("kind", [k for k in KINDS if k != "floor"])
def test_interval_check_sees_a_shrink_of_every_kind(kind):
    """Per kind, summed over the two setpoint problems: 0 violations (all kinds, the floor
    included), and > 0 once that kind is shrunk by 0.1 %. The floor needs its own problem (the
    unlisted cells must start right where Im + e_f ends): test_abstraction.py,
    test_floor_is_tight_for_the_unlisted_cells, with the same check functions."""
    real, shrunk = 0, 0
    for sigma, setpoints in SETPOINT_PROBLEMS:
        ab, T = setpoint_abstraction(sigma, setpoints)
        low, up = dense_rows(ab)
        kinds = interval_kinds(ab)
        real += sum(check_intervals(low, up, T, T, kinds, TOL_T).values())
        low, up = shrink_kind(low, up, kinds, kind)
        shrunk += check_intervals(low, up, T, T, kinds, TOL_T)[kind]
    assert real == 0
    assert shrunk > 0


# ============================================================================ value iteration
def reference_values(m, target, avoid, adv_max, ctrl_max=True, strategy=None, horizon=None):
    """Dense value iteration from below with the ordering inner problem (test_synthesis._inner).

    Unbounded: iterate until no value moves by 1e-15 (the models below converge geometrically,
    so the distance to the least fixed point is < 1e-12); k-step: exactly k steps.
    """
    lo, up = m.to_dense()
    V = target.astype(float)
    it = 0
    while True:
        rows = np.array([_inner(V, lo[r], up[r], adv_max) for r in range(m.n_choices)])
        new = V.copy()
        for s in range(m.n_states):
            if target[s] or avoid[s]:
                continue
            vals = rows[m.state_ptr[s]:m.state_ptr[s + 1]]
            if strategy is not None:
                new[s] = vals[strategy[s]]
            else:
                new[s] = vals.max() if ctrl_max else vals.min()
        it += 1
        done = it == horizon if horizon is not None else np.max(np.abs(new - V)) < 1e-15
        V = new
        if done or it > 50_000:
            assert it <= 50_000
            return V


def leaky_model(seed, n=7, a=2):
    """Random intervals around random distributions, every row leaking >= 0.05 to the avoid state
    (so value iteration contracts); state n-2 is the target, n-1 the avoid state."""
    rng = np.random.default_rng(seed)
    lo, up = np.zeros((n, a, n)), np.zeros((n, a, n))
    for s in range(n - 2):
        for u in range(a):
            succ = rng.choice(n - 1, size=3, replace=False)
            p = 0.9 * rng.dirichlet(np.ones(3))
            w = rng.uniform(0.0, 0.1, 3)
            lo[s, u, succ] = np.clip(p - w, 0.0, 1.0)
            up[s, u, succ] = np.clip(p + w, 0.0, 1.0)
            lo[s, u, n - 1], up[s, u, n - 1] = 0.05, 0.15
    for s in (n - 2, n - 1):
        lo[s, :, s] = up[s, :, s] = 1.0
    target, avoid = np.zeros(n, bool), np.zeros(n, bool)
    target[n - 2], avoid[n - 1] = True, True
    return IMDP.from_dense(lo, up), target, avoid


TOL_V = 1e-9  # reference within 1e-12 of the least fixed point; solver brackets at precision 1e-10


@pytest.mark.parametrize("horizon", [None, 4])
@pytest.mark.parametrize("adversary", ["pessimistic", "optimistic"])
@pytest.mark.parametrize("objective", ["maximize", "minimize"])
def test_value_bracket_check_sees_a_shrink(adversary, objective, horizon):
    """solve_reachability's [lower, upper] contains the reference; lower x (1 + 1e-3) or
    upper x (1 - 1e-3) does not (values between 0.05 and 0.9 here: shifts >= 5e-5 >> 1e-9)."""
    real = low_bad = up_bad = 0
    for seed in range(2):
        m, target, avoid = leaky_model(seed)
        r = solve_reachability(m, target, avoid=avoid, adversary=adversary, objective=objective, horizon=horizon,
                               precision=1e-10)
        adv_max = (adversary == "optimistic") == (objective == "maximize")
        ref = reference_values(m, target, avoid, adv_max, objective == "maximize", horizon=horizon)
        assert np.sum((ref > 0.05) & ~target) >= 2  # informative values
        real += check_bracket(r.lower, r.upper, ref, TOL_V)
        low_bad += check_bracket(raise_lower(r.lower), r.upper, ref, TOL_V)
        up_bad += check_bracket(r.lower, drop_upper(r.upper), ref, TOL_V)
    assert real == 0
    assert low_bad > 0 and up_bad > 0


@pytest.mark.parametrize("horizon", [None, 4])
@pytest.mark.parametrize("adversary", ["pessimistic", "optimistic"])
def test_evaluate_strategy_check_sees_a_shrink(adversary, horizon):
    """evaluate_strategy of a fixed random strategy: same check, same shrink."""
    real = low_bad = up_bad = 0
    for seed in range(2):
        m, target, avoid = leaky_model(seed)
        strat = np.random.default_rng(100 + seed).integers(0, 2, m.n_states)
        r = evaluate_strategy(m, target, strat, avoid=avoid, adversary=adversary, horizon=horizon, precision=1e-10)
        ref = reference_values(m, target, avoid, adversary == "optimistic", strategy=strat, horizon=horizon)
        real += check_bracket(r.lower, r.upper, ref, TOL_V)
        low_bad += check_bracket(raise_lower(r.lower), r.upper, ref, TOL_V)
        up_bad += check_bracket(r.lower, drop_upper(r.upper), ref, TOL_V)
    assert real == 0
    assert low_bad > 0 and up_bad > 0


# ============================================================================ synthesis
@pytest.mark.parametrize("horizon", [None, 3])
def test_synthesis_check_sees_a_shrink(horizon):
    """p_low <= min_adv P(pi), p_up >= max_adv P(pi), p_up_star >= max_pi max_adv P against the
    brute-force product oracle of test_synthesis (tolerance 1e-6: the oracle's own VI slack);
    each bound shrunk by 0.1 % is flagged."""
    dfa = ltlf_to_dfa("G !o & F d1 & F d2")
    atoms = ("o", "d1", "d2")
    totals = {"p_low": [0, 0], "p_up": [0, 0], "p_up_star": [0, 0]}
    for seed in range(3):
        rng = np.random.default_rng(seed)
        n_cells = 6
        imdp = random_imdp(rng, n_cells + 1, 2, width=0.1)
        labels = rng.choice([0, 2, 4, 6], size=n_cells)
        res = synthesize(imdp, labels, atoms, dfa, threshold=0.5, horizon=horizon, outside_state=n_cells)
        letters = np.append(res.labels, 0)
        pi = res.strategy.T if horizon is None else np.transpose(res.strategy, (0, 2, 1))
        pi = np.concatenate([pi, np.zeros(pi.shape[:-1] + (1,), dtype=np.int64)], axis=-1)
        kw = dict(avoid=[n_cells], horizon=horizon)
        v_pess = bruteforce_evaluate(imdp, letters, dfa, pi, adversary="pessimistic", **kw).initial_lower[:n_cells]
        v_opt = bruteforce_evaluate(imdp, letters, dfa, pi, adversary="optimistic", **kw).initial_lower[:n_cells]
        v_star = bruteforce_solve(imdp, letters, dfa, adversary="optimistic", **kw).initial_lower[:n_cells]
        real = check_synthesis(res.p_low, res.p_up, res.p_up_star, v_pess, v_opt, v_star, 1e-6)
        bad = check_synthesis(raise_lower(res.p_low), drop_upper(res.p_up), drop_upper(res.p_up_star),
                              v_pess, v_opt, v_star, 1e-6)
        for k in totals:
            totals[k][0] += real[k]
            totals[k][1] += bad[k]
    assert all(t[0] == 0 for t in totals.values()), totals
    assert all(t[1] > 0 for t in totals.values()), totals
