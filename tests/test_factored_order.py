"""The component-ordered pass of the factored unbounded solve (solvers/factored_order.py,
solvers/factored.py ``_ordered_pass``).

Independent references, each with the tolerance it is accurate to:

* the per-row reduction (``factored_bellman(kernel="rows")``) against an exact-rational evaluation of
  the nested O-maximisation (``exact_operator`` of tests/test_factored.py): ``lower <= exact <=
  upper`` with no tolerance, and within 1e-12 of the shared sweep (rounding margins ~1e-14);
* the components against scipy's strongly connected components of the support graph built here
  from the per-axis listed ranges (a separate enumeration), and every edge going to the same or an
  earlier component;
* the ordered solve against the whole-model iteration alone (``ORDERED = False``) and against the
  joint solver on the joint expansion (every axis lists its whole support): brackets that overlap,
  and the pessimistic factored lower value never below the joint one, up to the precision asked
  (1e-10) and the joint solver's (1e-10);
* the pass alone (no whole-model sweep after it) against the converged whole-model bracket: its
  lower end never above the reference upper end and its upper end never below the reference lower end
  (up to 1e-12: both are sound bounds of one value).
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

import robust_imdp.solvers.factored as F
from robust_imdp.models.factored import AxisMarginals, FactoredIMDP
from robust_imdp.solvers.api import solve_reachability
from robust_imdp.solvers.common import Control
from robust_imdp.solvers.factored import (factored_bellman, factored_operator, solve_factored_product,
                                          solve_factored_reachability)
from robust_imdp.solvers.factored_order import ProductRows, product_sccs
from robust_imdp.solvers.product import solve_product
from robust_imdp.spec.api import to_dfa
from test_factored import exact_operator, random_model


# --------------------------------------------------------------------------- one row
@pytest.mark.parametrize("seed", range(4))
def test_row_kernel_brackets_the_exact_rational_value(seed):
    rng = np.random.default_rng(110 + seed)
    for shape in [(4,), (3, 4), (3, 2, 3), (2, 3, 2, 2)]:
        m = random_model(rng, shape, M=2, rest=True, width=0.15)
        w = rng.random(m.n_states)
        if seed % 2:
            w = np.round(w, 1)  # ties between values
        for adv in ("pessimistic", "optimistic"):
            lo = factored_bellman(m, w, adversary=adv, rounding="down", kernel="rows")
            up = factored_bellman(m, w, adversary=adv, rounding="up", kernel="rows")
            ex = exact_operator(m, w, adv == "optimistic")
            below = [(u, q) for u in range(2) for q in range(m.n_cells) if not Fraction(lo[u, q]) <= ex[u, q]]
            above = [(u, q) for u in range(2) for q in range(m.n_cells) if not Fraction(up[u, q]) >= ex[u, q]]
            assert not below and not above, (shape, adv, below[:3], above[:3])
            assert np.max(up - lo) <= 1e-12  # the rounding margins are a few 1e-14
            tree = factored_bellman(m, w, adversary=adv, rounding="nearest")
            rows = factored_bellman(m, w, adversary=adv, rounding="nearest", kernel="rows")
            np.testing.assert_allclose(rows, tree, rtol=0, atol=1e-12)  # two summation orders of one value


def test_row_kernel_refuses_an_unknown_kernel():
    m = random_model(np.random.default_rng(1), (3,), M=1)
    with pytest.raises(ValueError, match="kernel"):
        factored_bellman(m, np.zeros(m.n_states), kernel="joint")


# --------------------------------------------------------------------------- the components
def _edges(m, nxt, active, ctrl=Control.MAXIMISE, strat=None):
    """Support-graph edges of the active nodes, enumerated from the per-axis positions (the module
    docstring's graph): every listed position that is a cell, every mode (the strategy's when fixed)."""
    S, n = nxt.shape
    N = m.n_cells
    pos = [ax.positions() for ax in m.axes]  # (M, N, k) grid interval or -1
    src, dst = [], []
    for s in range(S):
        for q in range(N):
            v = s * n + q
            if not active[v]:
                continue
            modes = range(m.n_modes) if ctrl != Control.FIXED else [int(strat[v])]
            for u in modes:
                per_axis = [[int(p) for p in pos[i][u, q] if p >= 0] for i in range(m.dim)]
                for cell in np.array(np.meshgrid(*per_axis, indexing="ij")).reshape(m.dim, -1).T:
                    q2 = int(np.ravel_multi_index(tuple(cell), m.shape))
                    w = int(nxt[s, q2]) * n + q2
                    if active[w]:
                        src.append(v)
                        dst.append(w)
    return np.array(src, dtype=np.int64), np.array(dst, dtype=np.int64)


@pytest.mark.parametrize("seed", range(5))
def test_components_are_the_support_graphs_sccs_in_reverse_topological_order(seed):
    rng = np.random.default_rng(200 + seed)
    shape = [(5,), (4, 3), (3, 2, 3), (6, 5), (2, 2, 2, 3)][seed]
    m = random_model(rng, shape, M=2, rest=False, width=0.1)
    S = 1 + seed % 3
    n = m.n_states
    nxt = rng.integers(0, S, size=(S, n))
    active = rng.random(S * n) < 0.85
    active[m.n_cells::n] = False
    ctrl = Control.FIXED if seed == 4 else Control.MAXIMISE
    strat = rng.integers(0, m.n_modes, size=S * n) if ctrl == Control.FIXED else np.zeros(1, dtype=np.int64)
    op = factored_operator(m)
    pr = ProductRows(ids=op.ids, nxt=nxt.reshape(-1).astype(np.int64), n=n, ctrl=int(ctrl), strat=strat)
    comp, cyclic, rank = product_sccs(op.grid, op.marginals, pr, active)
    src, dst = _edges(m, nxt, active, ctrl, strat)
    g = sp.csr_matrix((np.ones(src.size), (src, dst)), shape=(S * n, S * n))
    _, ref = connected_components(g, directed=True, connection="strong")
    act = np.flatnonzero(active)
    assert np.all(comp[~active] == -1) and np.all(comp[act] >= 0)
    # the same partition: a bijection between the labels
    pairs = set(zip(comp[act].tolist(), ref[act].tolist()))
    assert len(pairs) == len(set(comp[act].tolist())) == len(set(ref[act].tolist()))
    # reverse topological: every edge stays in its component or goes to an earlier one
    assert np.all(comp[dst] <= comp[src])
    # cyclic = an edge inside the component
    inside = np.zeros(cyclic.size, dtype=bool)
    inside[comp[src][comp[src] == comp[dst]]] = True
    np.testing.assert_array_equal(cyclic, inside)
    # the pop order lists the components in order
    order = act[np.argsort(rank[act])]
    assert np.all(np.diff(comp[order]) >= 0)


# --------------------------------------------------------------------------- the solve
def _solve_both(monkeypatch, fn):
    monkeypatch.setattr(F, "ORDERED", True)
    a = fn()
    monkeypatch.setattr(F, "ORDERED", False)
    b = fn()
    monkeypatch.setattr(F, "ORDERED", True)
    return a, b


@pytest.mark.parametrize("seed", range(3))
def test_ordered_solve_agrees_with_the_whole_model_iteration_and_the_joint_solver(seed, monkeypatch):
    rng = np.random.default_rng(300 + seed)
    shape = [(3, 3), (2, 3, 2), (4, 3)][seed]
    m = random_model(rng, shape, M=2, width=0.15, full=True, rest=False)
    J = m.to_joint()
    n = m.n_states
    target = np.zeros(n, bool)
    target[rng.choice(m.n_cells, 2, replace=False)] = True
    avoid = np.zeros(n, bool)
    avoid[-1] = True
    for objective in ("maximize", "minimize"):
        for adversary in ("pessimistic", "optimistic"):
            kw = dict(avoid=avoid, adversary=adversary, objective=objective, precision=1e-10)
            o, w = _solve_both(monkeypatch, lambda: solve_factored_reachability(m, target, **kw))
            assert o.converged and w.converged
            # both are sound brackets of one value
            assert np.all(o.lower <= w.upper + 1e-12) and np.all(w.lower <= o.upper + 1e-12)
            j = solve_reachability(J, target, **kw)
            adv_max = (adversary == "optimistic") == (objective == "maximize")
            if adv_max:
                assert np.all(o.upper <= j.upper + 1e-9), (objective, adversary)
            else:
                assert np.all(o.lower >= j.lower - 1e-9), (objective, adversary)


def test_ordered_product_solve_matches_the_joint_product():
    rng = np.random.default_rng(41)
    m = random_model(rng, (4, 3), M=2, width=0.1, full=True, rest=False)
    J = m.to_joint()
    dfa = to_dfa("G !b & F a")
    N = m.n_cells
    letters = np.zeros(N + 1, dtype=np.int64)
    cells = rng.permutation(N)
    atoms = list(dfa.atoms)
    a_bit, b_bit = 1 << atoms.index("a"), 1 << atoms.index("b")
    letters[cells[:2]] = a_bit
    letters[cells[2:4]] = b_bit
    for adversary in ("pessimistic", "optimistic"):
        f = solve_factored_product(m, letters, dfa, avoid=[N], adversary=adversary, precision=1e-10)
        j = solve_product(J, letters, dfa, avoid=[N], adversary=adversary, precision=1e-10)
        assert f.converged
        if adversary == "pessimistic":
            assert np.all(f.lower >= j.lower - 1e-9)
        else:
            assert np.all(f.upper <= j.upper + 1e-9)


def _chain_model(L, p_fwd=0.6, p_back=0.3):
    """A 1-D chain of L cells: forward w.p. >= p_fwd, back w.p. <= p_back, the rest to the outside;
    one mode.  Cell L-1 is the target."""
    st = np.maximum(np.arange(L) - 1, 0)
    lo = np.zeros((1, L, 3))
    up = np.zeros((1, L, 3))
    for q in range(L):
        j_self = q - st[q]
        if q > 0:
            up[0, q, 0] = p_back  # back
        up[0, q, j_self] = 0.05 if q + 1 < L else 1.0  # the target's own row: anything valid
        if q + 1 < L:
            lo[0, q, j_self + 1] = p_fwd
            up[0, q, j_self + 1] = 1.0
    ax = AxisMarginals(n=L, periodic=False, start=st[None], lower=lo, upper=up, out_lower=np.zeros((1, L)),
                       out_upper=np.full((1, L), 0.1), rest_upper=np.zeros((1, L)))
    return FactoredIMDP(shape=(L,), axes=(ax,))


def test_a_long_chain_needs_few_sweeps_in_order(monkeypatch):
    # a chain of 300 cells: the whole-model iteration moves a value one cell per sweep (>= 299 sweeps for the
    # optimistic value, which sends the free mass forward), the ordered pass sweeps the chain's one cyclic
    # component back to front (Tarjan's pop order): one sweep. Measured: 1 against 299 (optimistic), 67 against
    # 197 (pessimistic: the adversary sends up to 0.3 back, a real cycle)
    m = _chain_model(300)
    for adversary, ratio in (("optimistic", 0.02), ("pessimistic", 0.5)):
        o, w = _solve_both(monkeypatch, lambda: solve_factored_reachability(m, [299], avoid=[300], precision=1e-9,
                                                                            adversary=adversary))
        assert o.converged and w.converged
        assert w.iterations >= (299 if adversary == "optimistic" else 150)
        assert o.iterations <= ratio * w.iterations, (adversary, o.iterations, w.iterations)
        assert np.all(o.lower <= w.upper + 1e-12) and np.all(w.lower <= o.upper + 1e-12)


# --------------------------------------------------------------------------- the pass alone
@pytest.mark.parametrize("seed", range(4))
def test_the_pass_alone_gives_sound_bounds_with_rest_entries(seed, monkeypatch):
    # models with an unlisted rest (its value is the layer's min / max, read once per pass): the pass's
    # ends must stay on their sides of the converged whole-model bracket
    rng = np.random.default_rng(400 + seed)
    shape = [(5, 4), (3, 3, 3), (6,), (4, 2, 3)][seed]
    m = random_model(rng, shape, M=2, rest=True, width=0.1)
    n = m.n_states
    target = np.zeros(n, bool)
    target[rng.choice(m.n_cells, 2, replace=False)] = True
    avoid = np.zeros(n, bool)
    avoid[-1] = True
    seen = {}
    orig = F._ordered_pass

    def record(lay, lo, up, active, precision, max_iterations):
        r = orig(lay, lo, up, active, precision, max_iterations)
        seen["lo"], seen["up"] = lo.copy(), up.copy()
        return r

    monkeypatch.setattr(F, "_ordered_pass", record)
    for objective in ("maximize", "minimize"):
        for adversary in ("pessimistic", "optimistic"):
            monkeypatch.setattr(F, "ORDERED", False)
            ref = solve_factored_reachability(m, target, avoid=avoid, adversary=adversary, objective=objective,
                                              precision=1e-11)
            monkeypatch.setattr(F, "ORDERED", True)
            solve_factored_reachability(m, target, avoid=avoid, adversary=adversary, objective=objective,
                                        precision=1e-11)
            lo, up = seen["lo"][0], seen["up"][0]
            assert np.all(lo <= ref.upper + 1e-12), (objective, adversary, np.max(lo - ref.upper))
            assert np.all(up >= ref.lower - 1e-12), (objective, adversary, np.max(ref.lower - up))


# --------------------------------------------------------------------------- upper guesses (Lemma OVI)
def _slow_loop(stay=0.99):
    """Cell 0 stays w.p. ``stay`` and moves to the target cell 1 otherwise (exact intervals): value 1 (the
    target is reached almost surely), approached by the lower iterates as 1 - stay^k."""
    ax = AxisMarginals(n=2, periodic=False, start=np.array([[0, 0]]),
                       lower=np.array([[[stay, 1 - stay], [0.0, 1.0]]]), upper=np.array([[[stay, 1 - stay], [0.0, 1.0]]]),
                       out_lower=np.zeros((1, 2)), out_upper=np.zeros((1, 2)), rest_upper=np.zeros((1, 2)))
    return FactoredIMDP(shape=(2,), axes=(ax,))


def test_an_upper_guess_below_the_value_is_refuted_and_undone(monkeypatch):
    # the lower end moves by 0.01 * 0.99^k per sweep: when that is below the guessing threshold it is still
    # ~25 delta below 1, so the guess lo + delta is below the value 1 and its check must fail; the upper end
    # must stay 1 (the exact value; any lower is unsound) and the lower converge to within the precision
    m = _slow_loop()
    r = solve_factored_reachability(m, [1], avoid=[2], precision=1e-9)
    assert r.converged and r.upper[0] == 1.0 and r.lower[0] >= 1.0 - 1e-9
    # the same for the pessimistic and optimistic adversaries of a product layer (the intervals are points)
    o = solve_factored_reachability(m, [1], avoid=[2], precision=1e-9, adversary="optimistic")
    assert o.upper[0] == 1.0 and o.lower[0] >= 1.0 - 1e-9


def test_an_upper_guess_above_the_value_is_accepted_on_a_contracting_loop():
    # stay w.p. [0.5, 0.6], to the target w.p. [0.2, 0.5], out w.p. [0, 0.2]: pessimistic value from
    # V = 0.6 V + 0.2 (the adversary keeps the most mass in the loop and sends 0.2 out) -> V = 0.5;
    # the bracket holds 0.5 and is within the precision
    ax = AxisMarginals(n=2, periodic=False, start=np.array([[0, 0]]),
                       lower=np.array([[[0.5, 0.2], [0.0, 1.0]]]), upper=np.array([[[0.6, 0.5], [0.0, 1.0]]]),
                       out_lower=np.zeros((1, 2)), out_upper=np.array([[0.2, 0.0]]), rest_upper=np.zeros((1, 2)))
    m = FactoredIMDP(shape=(2,), axes=(ax,))
    r = solve_factored_reachability(m, [1], avoid=[2], precision=1e-9)
    assert r.converged and r.lower[0] <= 0.5 <= r.upper[0] and r.upper[0] - r.lower[0] <= 1e-9


def test_the_pass_runs_only_where_marginals_are_not_widely_shared(monkeypatch):
    # a row-wise sweep reads unshared_work entries, a shared one work: the pass runs where the ratio is at most
    # ORDER_MAX_SHARING (the chain: every row its own marginal, ratio 1), not on a model whose cells share one
    # marginal per axis (ratio = cells)
    calls = []
    orig = F._ordered_pass
    monkeypatch.setattr(F, "_ordered_pass", lambda *a: calls.append(1) or orig(*a))
    chain = _chain_model(20)
    assert factored_operator(chain).unshared_work <= F.ORDER_MAX_SHARING * factored_operator(chain).work
    solve_factored_reachability(chain, [19], avoid=[20])
    assert calls == [1]
    shared = FactoredIMDP(shape=(4, 4), axes=tuple(
        AxisMarginals(n=4, periodic=False, start=np.zeros((1, 16), np.int64), lower=np.full((1, 16, 4), 0.2),
                      upper=np.full((1, 16, 4), 0.3), out_lower=np.zeros((1, 16)), out_upper=np.full((1, 16), 0.1),
                      rest_upper=np.zeros((1, 16)), axis=i) for i in range(2)))
    op = factored_operator(shared)
    assert op.unshared_work > F.ORDER_MAX_SHARING * op.work
    solve_factored_reachability(shared, [5], avoid=[16])
    assert calls == [1]
