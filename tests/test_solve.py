"""Tests of the interval value iteration: hand-solved models, LP/brute-force references,
soundness properties, end-component traps, floors, horizons and bad input."""

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from robust_imdp.errors import ConvergenceWarning, DimensionError, InvalidInputError
from robust_imdp.models.imdp import IMDP
from robust_imdp.solvers.api import (Adversary, Objective, _Sweeper, evaluate_strategy, solve_reachability)

from soundness_checks import check_bracket

ATOL = 1e-7  # results are requested at precision 1e-8; references (LP, closed forms) agree to ~1e-10


def dense(n, a):
    return np.zeros((n, a, n)), np.zeros((n, a, n))


def absorbing(lo, up, states):
    for s in states:
        lo[s, :, s] = up[s, :, s] = 1.0


def trap_model():
    # state 0: choice 0 = self loop (end component), choice 1 = 0.5 to T(1), 0.5 to Z(2)
    lo, up = dense(3, 2)
    lo[0, 0, 0] = up[0, 0, 0] = 1.0
    lo[0, 1, 1] = up[0, 1, 1] = 0.5
    lo[0, 1, 2] = up[0, 1, 2] = 0.5
    absorbing(lo, up, [1, 2])
    return IMDP.from_dense(lo, up)


# ----------------------------------------------------------------------------- hand-solved
def test_one_step_interval_hand_solved():
    # state 0 -> T [0.2, 0.6], Z [0.4, 0.8]: robust value 0.2 (least mass to T), optimistic 0.6
    lo, up = dense(3, 1)
    lo[0, 0, 1], up[0, 0, 1] = 0.2, 0.6
    lo[0, 0, 2], up[0, 0, 2] = 0.4, 0.8
    absorbing(lo, up, [1, 2])
    m = IMDP.from_dense(lo, up)
    for adv, v in (("pessimistic", 0.2), ("optimistic", 0.6)):
        r = solve_reachability(m, [1], avoid=[2], adversary=adv)
        assert r.converged and r.lower[0] <= v <= r.upper[0]
        np.testing.assert_allclose([r.lower[0], r.upper[0]], v, atol=1e-12)


def test_two_state_cycle_hand_solved():
    # 0 -> 1 [0.5,0.7], Z [0.3,0.5];  1 -> T [0.6,0.8], 0 [0.2,0.4]
    # robust: V1 = 0.6 + 0.4 V0, V0 = 0.5 V1  =>  V1 = 0.75, V0 = 0.375
    # optimistic: V1 = 0.8 + 0.2 V0, V0 = 0.7 V1  =>  V1 = 0.8 / 0.86, V0 = 0.56 / 0.86
    lo, up = dense(4, 1)
    lo[0, 0, 1], up[0, 0, 1] = 0.5, 0.7
    lo[0, 0, 3], up[0, 0, 3] = 0.3, 0.5
    lo[1, 0, 2], up[1, 0, 2] = 0.6, 0.8
    lo[1, 0, 0], up[1, 0, 0] = 0.2, 0.4
    absorbing(lo, up, [2, 3])
    m = IMDP.from_dense(lo, up)
    r = solve_reachability(m, [2], avoid=[3])
    np.testing.assert_allclose(r.lower[:2], [0.375, 0.75], atol=ATOL)
    assert np.all(r.lower[:2] <= [0.375, 0.75]) and np.all(r.upper[:2] >= [0.375, 0.75])
    r = solve_reachability(m, [2], avoid=[3], adversary=Adversary.OPTIMISTIC)
    exact = np.array([0.56, 0.8]) / 0.86
    assert np.all(r.lower[:2] <= exact) and np.all(r.upper[:2] >= exact)
    np.testing.assert_allclose(r.upper[:2], exact, atol=ATOL)


def test_floor_row_hand_solved():
    # 4 states, target {1, 3}, avoid {2}; row of 0 lists only 1 with [0.1, 0.3]; floor 0.3 gives
    # the unlisted 0, 2, 3 each [0, 0.3].
    # optimistic: 0.3 to 1, 0.3 to 3, then 0.3 to 0 (value V0), 0.1 to 2: V0 = 0.6 + 0.3 V0 = 6/7
    # robust: lower 0.1 to 1, then 0.3 to 2 (value 0), 0.3 to 0, 0.3 to a target: V0 = 0.4 + 0.3 V0 = 4/7
    m = IMDP.from_csr([0, 1, 2, 3, 4], [0, 1, 2, 3, 4], [1, 1, 2, 3], [0.1, 1, 1, 1], [0.3, 1, 1, 1],
                      floor=[0.3, 0, 0, 0])
    r = solve_reachability(m, [1, 3], avoid=[2], adversary="optimistic")
    assert r.lower[0] <= 6 / 7 <= r.upper[0] and r.precision <= 1e-8
    r = solve_reachability(m, [1, 3], avoid=[2], adversary="pessimistic")
    assert r.lower[0] <= 4 / 7 <= r.upper[0] and r.precision <= 1e-8


def test_minimize_objective_hand_solved():
    # state 0: choice 0 -> T w.p. [0.3, 0.5] else Z; choice 1 -> T [0.6, 0.9] else Z
    # minimising controller, adversary against it (maximising): min(0.5, 0.9) = 0.5
    lo, up = dense(3, 2)
    lo[0, 0, 1], up[0, 0, 1], lo[0, 0, 2], up[0, 0, 2] = 0.3, 0.5, 0.5, 0.7
    lo[0, 1, 1], up[0, 1, 1], lo[0, 1, 2], up[0, 1, 2] = 0.6, 0.9, 0.1, 0.4
    absorbing(lo, up, [1, 2])
    m = IMDP.from_dense(lo, up)
    r = solve_reachability(m, [1], avoid=[2], objective=Objective.MINIMIZE, adversary="pessimistic")
    np.testing.assert_allclose(r.lower[0], 0.5, atol=1e-12)
    assert r.strategy[0] == 0
    r = solve_reachability(m, [1], avoid=[2], objective="minimize", adversary="optimistic")
    np.testing.assert_allclose(r.upper[0], 0.3, atol=1e-12)  # both minimise: min(0.3, 0.6)


# ----------------------------------------------------------------------------- end components
@pytest.mark.parametrize("adversary", ["pessimistic", "optimistic"])
def test_end_component_trap_upper_converges_and_strategy_exits(adversary):
    m = trap_model()
    r = solve_reachability(m, [1], avoid=[2], adversary=adversary)
    # the self loop has the same value as the exit at the fixed point; the value is 0.5
    assert r.converged and r.lower[0] <= 0.5 <= r.upper[0] and r.upper[0] - r.lower[0] <= 1e-8
    assert r.strategy[0] == 1  # tie broken toward progress, not the self loop
    ev = evaluate_strategy(m, [1], r.strategy, avoid=[2], adversary="pessimistic")
    assert ev.upper[0] >= r.lower[0] - 1e-12 and ev.lower[0] >= r.lower[0] - 1e-8


def test_larger_end_component_with_interval_exit():
    # states 0 <-> 1 can cycle forever (choice 0 of each); choice 1 of state 1 exits to T with
    # [0.4, 0.6] and to Z otherwise; from 0 the exit is reached through 1.  Robust value 0.4.
    lo, up = dense(4, 2)
    lo[0, :, 1] = up[0, :, 1] = 1.0
    lo[1, 0, 0] = up[1, 0, 0] = 1.0
    lo[1, 1, 2], up[1, 1, 2], lo[1, 1, 3], up[1, 1, 3] = 0.4, 0.6, 0.4, 0.6
    absorbing(lo, up, [2, 3])
    m = IMDP.from_dense(lo, up)
    r = solve_reachability(m, [2], avoid=[3])
    assert r.converged
    np.testing.assert_allclose(r.lower[:2], 0.4, atol=1e-8)
    assert np.all(r.upper[:2] >= 0.4)
    assert r.strategy[1] == 1
    ev = evaluate_strategy(m, [2], r.strategy, avoid=[3])
    np.testing.assert_allclose(ev.lower[:2], 0.4, atol=1e-8)


def test_adversary_can_trap_gives_zero():
    # state 0: self [0, 1], T [0, 1]: the robust adversary stays forever (value 0), the
    # optimistic one goes to T (value 1)
    lo, up = dense(2, 1)
    up[0, 0, 0] = up[0, 0, 1] = 1.0
    absorbing(lo, up, [1])
    m = IMDP.from_dense(lo, up)
    r = solve_reachability(m, [1])
    assert r.lower[0] == 0.0 and r.upper[0] == 0.0
    r = solve_reachability(m, [1], adversary="optimistic")
    assert r.converged and r.lower[0] >= 1 - 1e-8 and r.upper[0] == 1.0


# ----------------------------------------------------------------------------- references
def random_dense(rng, n, a, k, zero_lower=0.5):
    lo, up = dense(n, a)
    for s in range(n):
        for u in range(a):
            succ = rng.choice(n, size=k, replace=False)
            p = rng.dirichlet(np.ones(k))
            w = rng.uniform(0, 0.3, k)
            lo[s, u, succ] = np.clip(p - w, 0, 1) * (rng.uniform(size=k) > zero_lower)
            up[s, u, succ] = np.clip(p + w, 0, 1)
    return lo, up


def lp_inner(lo, up, v, maximize):
    # tight HiGHS tolerances: the default 1e-7 feasibility tolerance moves fixed points by ~1e-7
    res = linprog(-v if maximize else v, A_eq=np.ones((1, v.size)), b_eq=[1], bounds=list(zip(lo, up)),
                  method="highs", options=dict(primal_feasibility_tolerance=1e-10, dual_feasibility_tolerance=1e-10))
    assert res.status == 0
    return float(res.x @ v)


def reference_values(lo, up, target, avoid, adv_max, ctrl_max, iters=400):
    """Plain value iteration from below with LP inner problems (converges to the lfp)."""
    n, a, _ = lo.shape
    V = target.astype(float)
    for _ in range(iters):
        Vn = V.copy()
        for s in np.flatnonzero(~(target | avoid)):
            vals = [lp_inner(lo[s, u], up[s, u], V, adv_max) for u in range(a)]
            Vn[s] = max(vals) if ctrl_max else min(vals)
        if np.max(np.abs(Vn - V)) < 1e-14:
            return Vn
        V = Vn
    raise AssertionError("reference value iteration did not converge; pick another seed")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 4, 7])  # seeds whose reference converges in < 400 sweeps
def test_random_models_bracket_lp_value_iteration(seed):
    rng = np.random.default_rng(seed)
    lo, up = random_dense(rng, 6, 2, 3)
    m = IMDP.from_dense(lo, up)
    target = np.zeros(6, bool)
    target[0] = True
    avoid = np.zeros(6, bool)
    avoid[1] = True
    results = {}
    for adv in ("pessimistic", "optimistic"):
        for obj in ("maximize", "minimize"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                r = solve_reachability(m, target, avoid=avoid, adversary=adv, objective=obj, max_iterations=20_000)
            adv_max = (adv == "optimistic") == (obj == "maximize")
            ref = reference_values(lo, up, target, avoid, adv_max, obj == "maximize")
            # the reference stopped at a 1e-14 step; its distance to the lfp is far below 1e-9
            # (sensitivity of this check: tests/test_sensitivity.py, test_value_bracket_check_sees_a_shrink)
            assert check_bracket(r.lower, r.upper, ref, 1e-9) == 0, (adv, obj)
            assert np.all((0 <= r.lower) & (r.lower <= r.upper) & (r.upper <= 1))
            results[adv, obj] = r
    for obj in ("maximize", "minimize"):
        # the adversary against the objective gives the smaller value when maximising, the larger
        # when minimising: the brackets overlap in that order
        small, large = ("pessimistic", "optimistic") if obj == "maximize" else ("optimistic", "pessimistic")
        assert np.all(results[small, obj].lower <= results[large, obj].upper), obj
    assert np.all(results["pessimistic", "maximize"].lower <= results["optimistic", "maximize"].lower + 1e-8)
    assert np.all(results["optimistic", "minimize"].lower <= results["pessimistic", "minimize"].upper + 1e-8)


def inner_value(lo_row, up_row, floor, listed, w, adv_max):
    """The solver's ordering value of a single row (state 0 of a helper model) for values w."""
    n = w.size
    cols = np.flatnonzero(listed)
    m = IMDP.from_csr(np.arange(n + 1), np.r_[0, np.cumsum([cols.size] + [1] * (n - 1))],
                      np.r_[cols, np.arange(1, n)], np.r_[lo_row[cols], np.ones(n - 1)],
                      np.r_[up_row[cols], np.ones(n - 1)], floor=np.r_[floor, np.zeros(n - 1)])
    active = np.zeros((1, n), bool)
    active[0, 0] = True
    sw = _Sweeper(m, np.zeros((1, n), np.int64), active, 0, adv_max, None)
    V, _, _ = sw.sweep(w[None, :], 0)
    return V[0, 0]


@settings(deadline=None, max_examples=40)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 9), use_floor=st.booleans(), adv_max=st.booleans())
def test_ordering_solution_is_lp_optimal(seed, n, use_floor, adv_max):
    # random feasible row: intervals around a distribution p; a floor covers the unlisted states
    rng = np.random.default_rng(seed)
    p = rng.dirichlet(np.ones(n))
    listed = rng.uniform(size=n) < 0.6
    listed[0] |= not listed.any()
    lo_row = np.where(listed, np.clip(p - rng.uniform(0, 0.2, n), 0, 1), 0.0)
    up_row = np.where(listed, np.clip(p + rng.uniform(0, 0.2, n), 0, 1), 0.0)
    floor = 0.0
    if use_floor or not np.all(listed):
        floor = min(1.0, float(np.max(np.where(listed, 0, p))) + rng.uniform(0, 0.2))
    dense_up = np.where(listed, up_row, floor)
    w = rng.uniform(size=n)
    w[rng.uniform(size=n) < 0.3] = rng.uniform()  # ties
    got = inner_value(lo_row, up_row, floor, listed, w, adv_max)
    ref = lp_inner(lo_row, dense_up, w, adv_max)  # LP on the densified twin of the row
    assert abs(got - ref) <= 1e-12  # both exact up to a few rounding errors of sums of <= 9 terms


def test_floor_model_equals_densified_twin():
    rng = np.random.default_rng(7)
    n, a, k = 30, 2, 4
    state_ptr = np.arange(0, n * a + 1, a)
    cols, los, ups, floors, row_ptr = [], [], [], [], [0]
    for r in range(n * a):
        c = np.sort(rng.choice(n, k, replace=False))
        p = rng.dirichlet(np.ones(k)) * 0.9
        cols.append(c)
        los.append(np.clip(p - 0.05, 0, 1))
        ups.append(np.clip(p + 0.05, 0, 1))
        floors.append(0.02)  # 0.02 * 26 unlisted >= the missing mass
        row_ptr.append(row_ptr[-1] + k)
    m = IMDP.from_csr(state_ptr, row_ptr, np.concatenate(cols), np.concatenate(los), np.concatenate(ups),
                      floor=floors)
    lo2, up2 = m.to_dense()
    twin = IMDP.from_dense(lo2.reshape(n, a, n), up2.reshape(n, a, n))
    assert not twin.has_floor
    for adv in ("pessimistic", "optimistic"):
        r1 = solve_reachability(m, [0, 1], avoid=[2], adversary=adv)
        r2 = solve_reachability(twin, [0, 1], avoid=[2], adversary=adv)
        assert r1.converged and r2.converged
        np.testing.assert_allclose(r1.lower, r2.lower, atol=2e-8)
        np.testing.assert_allclose(r1.upper, r2.upper, atol=2e-8)
        rb1 = solve_reachability(m, [0, 1], avoid=[2], adversary=adv, horizon=5)
        rb2 = solve_reachability(twin, [0, 1], avoid=[2], adversary=adv, horizon=5)
        np.testing.assert_allclose(rb1.lower, rb2.lower, atol=1e-12)


# ----------------------------------------------------------------------------- properties
def test_strategy_achieves_reported_lower_value_on_random_models():
    for seed in range(4):
        rng = np.random.default_rng(100 + seed)
        lo, up = random_dense(rng, 12, 3, 4)
        m = IMDP.from_dense(lo, up)
        r = solve_reachability(m, [0], avoid=[1])
        ev = evaluate_strategy(m, [0], r.strategy, avoid=[1])
        assert ev.converged
        # the strategy's guaranteed value reaches the optimum up to the two precisions
        assert np.all(ev.upper >= r.lower - 1e-12)
        assert np.all(ev.lower >= r.lower - 2e-8)


def test_bounded_values_grow_with_horizon_toward_unbounded():
    rng = np.random.default_rng(11)
    lo, up = random_dense(rng, 10, 2, 4, zero_lower=0.0)
    m = IMDP.from_dense(lo, up)
    r = solve_reachability(m, [0], avoid=[1])
    prev = np.zeros(10)
    for k in (1, 2, 4, 8, 16, 64, 256):
        b = solve_reachability(m, [0], avoid=[1], horizon=k)
        assert b.converged and b.strategy.shape == (k, 10)
        assert np.all(b.lower >= prev - 1e-15)  # k-step value is monotone in k
        assert np.all(b.lower <= r.upper + 1e-15)  # and below the unbounded value
        prev = b.lower
    np.testing.assert_allclose(prev, r.lower, atol=1e-6)


def test_bounded_hand_solved_and_time_varying_strategy():
    # chain 0 -> 1 -> T with prob 1 (choice 0), or 0 -> T w.p. 0.5 / Z 0.5 (choice 1).
    # horizon 1: from 0 only choice 1 reaches T (0.5); horizon 2: choice 0 gives 1.
    lo, up = dense(4, 2)
    lo[0, 0, 1] = up[0, 0, 1] = 1.0
    lo[0, 1, 2] = up[0, 1, 2] = lo[0, 1, 3] = up[0, 1, 3] = 0.5
    lo[1, :, 2] = up[1, :, 2] = 1.0
    absorbing(lo, up, [2, 3])
    m = IMDP.from_dense(lo, up)
    b1 = solve_reachability(m, [2], avoid=[3], horizon=1)
    # exact 0.5, bracketed by the rounding bound (16 k + 64) u ~ 1e-14
    assert b1.lower[0] <= 0.5 <= b1.upper[0] and b1.upper[0] - b1.lower[0] < 1e-13
    assert b1.strategy[0, 0] == 1
    b2 = solve_reachability(m, [2], avoid=[3], horizon=2)
    assert b2.lower[0] >= 1 - 1e-13 and b2.strategy[0, 0] == 0 and b2.strategy[1, 0] == 1
    ev = evaluate_strategy(m, [2], b2.strategy, avoid=[3], horizon=2)
    assert ev.lower[0] >= 1 - 1e-13
    with pytest.raises(DimensionError, match="needs horizon=2"):
        evaluate_strategy(m, [2], b2.strategy, avoid=[3])


def test_not_converged_warns_and_stays_sound():
    rng = np.random.default_rng(5)
    lo, up = random_dense(rng, 8, 2, 3)
    m = IMDP.from_dense(lo, up)
    full = solve_reachability(m, [0], avoid=[1])
    with pytest.warns(ConvergenceWarning, match="sound but loose"):
        r = solve_reachability(m, [0], avoid=[1], max_iterations=2)
    assert not r.converged and r.iterations == 2
    assert np.all(r.lower <= full.upper) and np.all(r.upper >= full.lower)


# ----------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("kw, exc, match", [
    (dict(target=[]), InvalidInputError, "target must contain at least one state"),
    (dict(target=[0], avoid=[0]), InvalidInputError, "disjoint; state 0"),
    (dict(target=[5]), InvalidInputError, r"target holds index 5 outside \[0, 3\)"),
    (dict(target=np.array([True, False])), DimensionError, r"target as a boolean mask must have shape \(3,\)"),
    (dict(target=[1], adversary="robust"), InvalidInputError, "adversary must be one of 'pessimistic', 'optimistic'; got 'robust'"),
    (dict(target=[1], objective="max"), InvalidInputError, "objective must be one of"),
    (dict(target=[1], horizon=-1), InvalidInputError, "horizon must be a non-negative"),
    (dict(target=[1], precision=0.0), InvalidInputError, "precision must be a positive"),
    (dict(target=[1], method="simplex"), InvalidInputError, "method must be 'vi', 'interval' or 'lp'; got 'simplex'"),
])
def test_bad_input_solve(kw, exc, match):
    with pytest.raises(exc, match=match):
        solve_reachability(trap_model(), **kw)


@pytest.mark.parametrize("strategy, exc, match", [
    ([0, 0], DimensionError, r"strategy must have shape \(3,\) or \(k, 3\); got \(2,\)"),
    ([2, 0, 0], InvalidInputError, r"strategy\[0\] = 2 is not a choice of state 0 \(it has 2 choices\)"),
    ([0.0, 0, 0], InvalidInputError, "integer choice indices"),
])
def test_bad_strategy(strategy, exc, match):
    with pytest.raises(exc, match=match):
        evaluate_strategy(trap_model(), [1], np.asarray(strategy))


def test_almost_sure_states_get_exactly_one_without_iterating():
    # state 0: self [0, 0.9], T [0.1, 1]: every admissible p sends >= 0.1 to T and nothing
    # leaves {0, T}, so T is reached almost surely (value 1) against every adversary.
    # state 2: self [0, 0.9], T [0.1, 0.5], Z [0, 0.5]: the robust value is < 1:
    # V2 = 0.1 + 0.4 V2 ... the adversary puts 0.5 on Z, 0.4 on self, 0.1 on T -> V2 = 0.1 / 0.6
    lo, up = dense(4, 1)
    up[0, 0, 0], lo[0, 0, 1], up[0, 0, 1] = 0.9, 0.1, 1.0
    up[2, 0, 2], lo[2, 0, 1], up[2, 0, 1], up[2, 0, 3] = 0.9, 0.1, 0.5, 0.5
    absorbing(lo, up, [1, 3])
    m = IMDP.from_dense(lo, up)
    r = solve_reachability(m, [1], avoid=[3])
    assert r.lower[0] == 1.0 and r.upper[0] == 1.0
    assert r.lower[2] <= 0.1 / 0.6 <= r.upper[2] and r.precision <= 1e-8
    ev = evaluate_strategy(m, [1], r.strategy, avoid=[3])
    assert ev.lower[0] == 1.0


def test_strong_components_match_scipy():
    # independent check of the numba Tarjan used for end components
    import scipy.sparse as sp
    from scipy.sparse import csgraph

    from robust_imdp.solvers.api import strong_components

    rng = np.random.default_rng(0)
    for _ in range(30):
        N = int(rng.integers(1, 40))
        E = int(rng.integers(0, 3 * N))
        g = sp.csr_matrix((np.ones(E), (rng.integers(0, N, E), rng.integers(0, N, E))), shape=(N, N))
        nc, lab = csgraph.connected_components(g, directed=True, connection="strong")
        lab2, nc2 = strong_components(g.indptr.astype(np.int64), g.indices.astype(np.int32))
        assert nc2 == nc and len(set(zip(lab.tolist(), lab2.tolist()))) == nc  # same partition


def test_parallel_jacobi_sweeps_give_the_serial_results_bit_for_bit(monkeypatch):
    """Jacobi sweeps of large layers run on numba's threads (``bellman_layer_parallel``): with the
    threshold lowered so that every layer of these small models qualifies, a bounded solve, an
    interval-iteration solve, a floor model and a product with a DFA give exactly the serial
    bounds and strategies, and the parallel kernel was really used."""
    import numba

    from robust_imdp.solvers import sweep as S
    from robust_imdp.solvers.kernels import PAR_BLOCK
    from robust_imdp.spec.dfa import ltlf_to_dfa
    from robust_imdp.solvers.product import solve_product

    rng = np.random.default_rng(5)
    n, A, k = 2600, 2, 5  # more than two of the kernel's blocks of PAR_BLOCK = 1024 states
    assert n > 2 * PAR_BLOCK
    col = np.sort(rng.choice(n, size=(n * A, k)), axis=1)
    col = np.where(np.diff(col, axis=1, prepend=-1) == 0, -1, col)  # duplicates dropped below
    p = rng.dirichlet(np.ones(k), size=n * A)
    keep = col >= 0
    row_ptr = np.r_[0, np.cumsum(keep.sum(1))]
    pk = np.where(keep, p, 0.0)
    pk /= pk.sum(1, keepdims=True)
    low, upp = 0.7 * pk[keep], np.minimum(1.0, 1.3 * pk[keep])
    m = IMDP.from_csr(np.arange(0, n * A + 1, A), row_ptr, col[keep], low, upp)
    fl = IMDP.from_csr(m.state_ptr, m.row_ptr, m.col, m.lower, m.upper, floor=np.full(m.n_choices, 2e-4))
    letters = rng.integers(0, 4, size=n)
    dfa = ltlf_to_dfa("G !b & F a")
    calls = []
    parallel = S.bellman_layer_parallel
    monkeypatch.setattr(S, "bellman_layer_parallel", lambda *a: calls.append(1) or parallel(*a))

    def runs():
        t, z = np.arange(100), np.arange(100, 200)
        return [solve_reachability(m, t, avoid=z, horizon=15),
                solve_reachability(m, t, avoid=z, method="interval", adversary="optimistic"),
                solve_reachability(fl, t, avoid=z),
                solve_product(m, letters, dfa, adversary="pessimistic")]

    previous = numba.get_num_threads()
    numba.set_num_threads(min(2, numba.config.NUMBA_NUM_THREADS))
    try:
        monkeypatch.setattr(S, "PAR_MIN_STATES", 10 ** 9)
        serial = runs()
        assert not calls
        monkeypatch.setattr(S, "PAR_MIN_STATES", 1)
        par = runs()
    finally:
        numba.set_num_threads(previous)
    if numba.config.NUMBA_NUM_THREADS > 1:
        assert calls  # the parallel kernel did the sweeps
    assert all(0 < np.mean(r.lower) < 1 for r in serial[:3])  # informative values, not all 0 or 1
    for a, b in zip(serial, par):
        for name in ("lower", "upper", "strategy"):
            assert np.array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name))), name
