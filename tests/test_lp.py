"""Tests of the LP cross-checks (lp.py) and, through them, of the ordering solver (solve.py).

Tolerances: Clarabel runs with gap/feasibility tolerances LP_TOL = 1e-10; on rows of <= 12
entries and models of <= 8 states its values agree with the ordering solutions to ~1e-9,
so comparisons use 1e-7 (the brief's cross-check tolerance).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robust_imdp.solvers import api as solve
from robust_imdp.errors import ConvergenceError, DimensionError, InvalidInputError
from robust_imdp.models.imdp import IMDP
from robust_imdp.solvers.lp import (
    evaluate_strategy_lp,
    inner_lp,
    nature_maximises,
    ordering_inner_dense,
    solve_reachability_lp,
)

TOL = 1e-7


# ----------------------------------------------------------------------------- builders
def random_row(rng, k, m, with_floor):
    """A feasible row: k listed entries around a Dirichlet point, m unlisted with a floor."""
    p = rng.dirichlet(np.ones(k + m))
    w = rng.uniform(0.0, 0.3, size=k)
    lo = np.clip(p[:k] - w, 0.0, 1.0)
    up = np.clip(p[:k] + w, 0.0, 1.0)
    floor = min(1.0, float(p[k:].max() * rng.uniform(1.0, 2.0))) if (with_floor and m) else 0.0
    if not (with_floor and m):  # no floor: the listed entries must carry all the mass
        lo = np.clip(p[:k] / p[:k].sum() - w, 0.0, 1.0)
        up = np.clip(p[:k] / p[:k].sum() + w, 0.0, 1.0)
    return lo, up, floor


def random_imdp(rng, n, a, k, *, floor=False, positive_lower=False):
    """Random dense-ish IMDP with n states, a actions, k successors per row (optionally floors)."""
    lo = np.zeros((n, a, n))
    up = np.zeros((n, a, n))
    for s in range(n):
        for u in range(a):
            succ = rng.choice(n, size=k, replace=False)
            p = rng.dirichlet(np.ones(k))
            w = rng.uniform(0.0, 0.2, size=k)
            lo[s, u, succ] = np.clip(p - w, 0.01 if positive_lower else 0.0, 1.0)
            up[s, u, succ] = np.clip(p + w, 0.0, 1.0)
            lo[s, u, succ] = np.minimum(lo[s, u, succ], p)  # keep p inside the intervals
    m = IMDP.from_dense(lo, up)
    if not floor:
        return m
    # add a floor of 0.02 on every row: still feasible, and the unlisted states matter
    return IMDP.from_csr(m.state_ptr, m.row_ptr, m.col, m.lower, m.upper, floor=np.full(m.n_choices, 0.02))


def reference_vi(imdp, target, nature_max, ctrl_max, strategy=None, avoid=None):
    """Plain value iteration from below with the dense ordering operator (converges for these models)."""
    lo, up = imdp.to_dense()
    n = imdp.n_states
    avoid = np.zeros(n, bool) if avoid is None else avoid
    x = target.astype(float)
    for _ in range(100_000):
        q = ordering_inner_dense(lo, up, x, nature_max)
        if strategy is not None:
            v = q[imdp.state_ptr[:-1] + strategy]
        else:
            v = np.full(n, -np.inf if ctrl_max else np.inf)
            (np.maximum if ctrl_max else np.minimum).at(v, imdp.row_state, q)
        v = np.where(target, 1.0, np.where(avoid, 0.0, v))
        if np.max(np.abs(v - x)) < 1e-15:
            break
        x = v
    return x


def mid(res):
    return 0.5 * (res.lower + res.upper)


def tiny_example():
    """3 states: 0 -> {0, 1 (target), 2 (sink)} or 0 -> 2; 1 and 2 absorbing."""
    lo = np.zeros((3, 2, 3))
    up = np.zeros((3, 2, 3))
    lo[0, 0] = [0.05, 0.2, 0.05]
    up[0, 0] = [0.5, 0.9, 0.8]
    lo[0, 1, 2] = up[0, 1, 2] = 1.0
    lo[1, :, 1] = up[1, :, 1] = 1.0
    lo[2, :, 2] = up[2, :, 2] = 1.0
    return IMDP.from_dense(lo, up)


# ----------------------------------------------------------------------------- inner problem
@settings(deadline=None, max_examples=25)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 6), m=st.integers(0, 6),
       with_floor=st.booleans(), maximize=st.booleans())
def test_ordering_matches_inner_lp(seed, k, m, with_floor, maximize):
    rng = np.random.default_rng(seed)
    lo, up, floor = random_row(rng, k, m, with_floor)
    if not with_floor or m == 0:
        m = 0
    v = rng.uniform(0, 1, size=k)
    w = rng.uniform(0, 1, size=m)
    val, p = inner_lp(lo, up, v, floor=floor, n_unlisted=m, unlisted_values=w if m else None, maximize=maximize)
    # the LP solution is feasible (to the solver tolerance)
    full_lo = np.concatenate([lo, np.zeros(m)])
    full_up = np.concatenate([up, np.full(m, floor)])
    assert np.all(p >= full_lo - 1e-8) and np.all(p <= full_up + 1e-8)
    assert abs(p.sum() - 1.0) <= 1e-8
    # ... and the ordering solution (densified) has the same optimal value
    ref = ordering_inner_dense(full_lo[None], full_up[None], np.concatenate([v, w]), maximize)[0]
    assert abs(val - ref) <= TOL


def test_inner_lp_floor_by_hand():
    # listed [0.1,0.5] (v=1) and [0.2,0.6] (v=0); 3 unlisted with floor 0.1 and v=(0.5,0.2,0.9):
    # max: lower bounds 0.3, remaining 0.7: v=1 gets +0.4 -> 0.5, v=.9,.5,.2 get 0.1 each -> done.
    # value = 0.5*1 + 0.1*(0.9+0.5+0.2) = 0.66
    val, p = inner_lp([0.1, 0.2], [0.5, 0.6], [1.0, 0.0], floor=0.1, n_unlisted=3, unlisted_values=[0.5, 0.2, 0.9])
    assert val == pytest.approx(0.66, abs=1e-8)
    np.testing.assert_allclose(p, [0.5, 0.2, 0.1, 0.1, 0.1], atol=1e-7)


def test_inner_lp_bad_input():
    with pytest.raises(DimensionError, match="lower, upper and values"):
        inner_lp([0.1], [0.5, 0.6], [1.0, 0.0])
    with pytest.raises(InvalidInputError, match="unlisted_values"):
        inner_lp([0.5], [1.0], [1.0], floor=0.1, n_unlisted=2)
    with pytest.raises(ConvergenceError, match="CLARABEL.*inner"):
        inner_lp([0.1, 0.1], [0.2, 0.2], [1.0, 0.0])  # sum of upper bounds 0.4 < 1: empty polytope


def test_ordering_matches_solver_inner_problem():
    """The solver's ordering Bellman step (one iteration from the target indicator) against the LP."""
    rng = np.random.default_rng(3)
    m = random_imdp(rng, 6, 2, 3, floor=True)
    target = np.zeros(6, bool)
    target[0] = True
    for adversary in ("pessimistic", "optimistic"):
        res = solve.solve_reachability(m, target, adversary=adversary, horizon=1)
        lo, up = m.to_dense()
        nat = nature_maximises(adversary, "maximize")
        q = np.array([inner_lp(lo[r], up[r], target.astype(float), maximize=nat)[0] for r in range(m.n_choices)])
        best = np.full(6, -np.inf)
        np.maximum.at(best, m.row_state, q)
        best[target] = 1.0
        assert np.all(res.lower <= best + TOL) and np.all(res.upper >= best - TOL)
        np.testing.assert_allclose(mid(res), best, atol=TOL)


# ----------------------------------------------------------------------------- whole problems vs reference
def test_hand_solved_example():
    m = tiny_example()
    tgt = np.array([False, True, False])
    # pessimistic: nature puts 0.05 on the self-loop, 0.2 on the target, 0.75 on the sink:
    # x0 = 0.2 / (1 - 0.05) = 4/19.  Optimistic: 0.05 self, 0.9 target: x0 = 0.9 / 0.95 = 18/19.
    pes = solve_reachability_lp(m, tgt, adversary="pessimistic")
    opt = solve_reachability_lp(m, tgt, adversary="optimistic")
    np.testing.assert_allclose(mid(pes), [4 / 19, 1, 0], atol=TOL)
    np.testing.assert_allclose(mid(opt), [18 / 19, 1, 0], atol=TOL)
    assert pes.strategy[0] == 0 and opt.strategy[0] == 0  # action 1 goes to the sink
    # minimising: the controller takes action 1 (straight to the sink): value 0 either way
    np.testing.assert_allclose(mid(solve_reachability_lp(m, tgt, objective="minimize", adversary="optimistic")), [0, 1, 0], atol=TOL)


@pytest.mark.parametrize("adversary,objective", [("optimistic", "maximize"), ("pessimistic", "maximize"),
                                                 ("optimistic", "minimize"), ("pessimistic", "minimize")])
def test_random_models_against_value_iteration(adversary, objective):
    rng = np.random.default_rng(11)
    for _ in range(3):
        m = random_imdp(rng, 5, 2, 3, floor=bool(rng.integers(2)))
        tgt = np.zeros(5, bool)
        tgt[0] = True
        res = solve_reachability_lp(m, tgt, adversary=adversary, objective=objective)
        ref = reference_vi(m, tgt, nature_maximises(adversary, objective), objective == "maximize")
        np.testing.assert_allclose(mid(res), ref, atol=TOL)
        assert np.all((res.lower >= 0) & (res.upper <= 1) & (res.lower <= res.upper))
        # the returned strategy attains the value (no end-component trap)
        ev = evaluate_strategy_lp(m, tgt, res.strategy, adversary=adversary, objective=objective)
        np.testing.assert_allclose(mid(ev), ref, atol=TOL)


def test_pessimistic_below_optimistic_and_avoid():
    rng = np.random.default_rng(5)
    m = random_imdp(rng, 6, 2, 3)
    tgt = np.zeros(6, bool)
    tgt[0] = True
    avoid = np.zeros(6, bool)
    avoid[1] = True
    pes = mid(solve_reachability_lp(m, tgt, avoid=avoid, adversary="pessimistic"))
    opt = mid(solve_reachability_lp(m, tgt, avoid=avoid, adversary="optimistic"))
    assert np.all(pes <= opt + TOL)
    assert pes[1] == pytest.approx(0, abs=TOL) and opt[1] == pytest.approx(0, abs=TOL)
    np.testing.assert_allclose(opt, reference_vi(m, tgt, True, True, avoid=avoid), atol=TOL)


def test_end_component_trap_strategy():
    # state 0: action 0 is a self-loop (value equal to the best), action 1 reaches the target
    # with probability 1; a maximising strategy must not pick the self-loop.
    lo = np.zeros((2, 2, 2))
    lo[0, 0, 0] = 1.0
    lo[0, 1, 1] = 1.0
    lo[1, :, 1] = 1.0
    m = IMDP.from_dense(lo, lo.copy())
    tgt = np.array([False, True])
    for adversary in ("pessimistic", "optimistic"):
        res = solve_reachability_lp(m, tgt, adversary=adversary)
        np.testing.assert_allclose(mid(res), [1, 1], atol=TOL)
        assert res.strategy[0] == 1


# ----------------------------------------------------------------------------- against the solver (solve.py)
@pytest.mark.slow
def test_solver_against_lp_random_models():
    rng = np.random.default_rng(2024)
    for trial in range(4):
        m = random_imdp(rng, 6, 2, 3, floor=trial % 2 == 1)
        tgt = np.zeros(6, bool)
        tgt[[0, 5]] = True
        for adversary in ("pessimistic", "optimistic"):
            ours = solve.solve_reachability(m, tgt, adversary=adversary, precision=1e-10)
            lp = solve_reachability_lp(m, tgt, adversary=adversary)
            assert np.all(ours.lower <= mid(lp) + TOL) and np.all(ours.upper >= mid(lp) - TOL)
            np.testing.assert_allclose(ours.lower, mid(lp), atol=TOL)
            # fixed-strategy evaluation of the solver's strategy, both adversaries
            for adv2 in ("pessimistic", "optimistic"):
                ev = solve.evaluate_strategy(m, tgt, ours.strategy, adversary=adv2, precision=1e-10)
                ev_lp = evaluate_strategy_lp(m, tgt, ours.strategy, adversary=adv2)
                np.testing.assert_allclose(ev.lower, mid(ev_lp), atol=TOL)


# ----------------------------------------------------------------------------- bad input
def test_bad_input_messages():
    m = tiny_example()
    tgt = np.array([False, True, False])
    with pytest.raises(InvalidInputError, match="horizon"):
        solve_reachability_lp(m, tgt, horizon=3)
    with pytest.raises(InvalidInputError, match="adversary"):
        solve_reachability_lp(m, tgt, adversary="robust")
    with pytest.raises(DimensionError, match="target"):
        solve_reachability_lp(m, np.array([True, False]))
    with pytest.raises(InvalidInputError, match="target holds state 7"):
        solve_reachability_lp(m, [7])
    with pytest.raises(DimensionError, match="strategy"):
        evaluate_strategy_lp(m, tgt, [0, 0])
    with pytest.raises(InvalidInputError, match=r"strategy\[0\] = 2 is not a choice of state 0"):
        evaluate_strategy_lp(m, tgt, [2, 0, 0])
    with pytest.raises(InvalidInputError, match="max_strategies"):
        solve_reachability_lp(m, tgt, adversary="pessimistic", max_strategies=4)


def test_target_avoid_checks():
    m = tiny_example()
    with pytest.raises(InvalidInputError, match="empty target"):
        solve_reachability_lp(m, np.zeros(3, bool))
    with pytest.raises(InvalidInputError, match="state 1 is in both"):
        solve_reachability_lp(m, [1], avoid=[1, 2])


def _probe_model(lo, up, floor, v):
    """A model whose 2-step value at state 0 is the inner problem of one row against values v.

    State 0 carries the row under test: listed successors 1..k with [lo, up], floor on every
    other state (successors k+1..N, the target T = N+1, the sink N+2 and state 0 itself).
    State j in 1..N moves to T with probability exactly v[j-1] and to the sink otherwise,
    so its 1-step value is v[j-1]; T and the sink are absorbing.
    """
    N = v.size
    k = lo.size
    T, sink = N + 1, N + 2
    cols = [list(range(1, k + 1))] + [[T, sink] for _ in range(N)] + [[T], [sink]]
    lows = [list(lo)] + [[x, 1.0 - x] for x in v] + [[1.0], [1.0]]
    ups = [list(up)] + [[x, 1.0 - x] for x in v] + [[1.0], [1.0]]
    row_ptr = np.concatenate([[0], np.cumsum([len(c) for c in cols])])
    floors = np.zeros(N + 3)
    floors[0] = floor
    m = IMDP.from_csr(np.arange(N + 4), row_ptr, np.concatenate(cols), np.concatenate(lows), np.concatenate(ups), floor=floors)
    return m, T


@settings(deadline=None, max_examples=15)
@given(seed=st.integers(0, 2**32 - 1), k=st.integers(1, 5), extra=st.integers(0, 4),
       with_floor=st.booleans(), adversary=st.sampled_from(["pessimistic", "optimistic"]))
def test_solver_inner_problem_matches_lp_with_floors(seed, k, extra, with_floor, adversary):
    """The solver's ordering inner problem (through a 2-step query on a probe model) against the LP."""
    rng = np.random.default_rng(seed)
    N = k + extra
    m_unlisted = N - k + 3  # successors k+1..N, T, sink, state 0
    lo, up, floor = random_row(rng, k, m_unlisted, with_floor)
    v = rng.uniform(0, 1, size=N)
    m, T = _probe_model(lo, up, floor, v)
    nat = nature_maximises(adversary, "maximize")
    dlo, dup = m.to_dense()
    # 1-step values: state 0 from its row against the target indicator, j -> v_j, T -> 1, sink -> 0
    v1 = np.concatenate([[0.0], v, [1.0, 0.0]])
    v1[0] = inner_lp(dlo[0], dup[0], (np.arange(N + 3) == T).astype(float), maximize=nat)[0]
    expected = inner_lp(dlo[0], dup[0], v1, maximize=nat)[0]
    res = solve.solve_reachability(m, [T], adversary=adversary, horizon=2)
    assert res.lower[0] <= expected + TOL and res.upper[0] >= expected - TOL  # the bracket holds the LP value
    assert res.upper[0] - res.lower[0] <= TOL


def test_heavy_backends_are_imported_lazily():
    import subprocess
    import sys

    code = ("import sys, robust_imdp.solvers.lp, robust_imdp.io.formats; "
            "print(sorted(m for m in ('cvxpy', 'clarabel', 'stormpy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_solver_dispatches_method_lp():
    m = tiny_example()
    res = solve.solve_reachability(m, [1], adversary="optimistic", method="lp")
    assert isinstance(res, solve.ReachabilityResult)
    np.testing.assert_allclose(mid(res), [18 / 19, 1, 0], atol=TOL)  # hand-solved above
