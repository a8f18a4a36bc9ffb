"""The graph pre-computations (``solvers/graph.py``) on several threads, and their tests against exact arithmetic.

``positive_attractor`` and ``almost_sure`` sweep in place on ``lanes`` threads; their tests are monotone in the
growing set, so the least fixed point does not depend on the order of the sweeps: every lane count must give the
same set (and one lane the serial sweep order). ``progress_strategy`` reads only the previous round, so its
lanes share a round's nodes. References: Kleene iteration of the same tests in exact rational arithmetic
(``fractions.Fraction``): the positive attractor is liberal (a superset of the exact one), the almost-sure set
conservative (a subset of the exact one), and on random models without ties at 1 they are equal.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from robust_imdp.solvers import graph
from robust_imdp.solvers.graph import _UNIT, almost_sure, positive_attractor, progress_strategy


def _model(seed: int, n: int, L: int, k: int, floor: bool, choices: int = 2):
    """A random layered interval model: n states with ``choices`` rows of <= k listed successors each, L layers
    (``nxt`` random), some uppers exactly 0 and some lowers exactly 0; rows with a floor on unlisted states when
    ``floor``. The intervals need not hold a distribution (the graph tests only read them)."""
    rng = np.random.default_rng(seed)
    state_ptr = np.arange(0, n * choices + 1, choices, dtype=np.int64)
    R = n * choices
    sizes = rng.integers(1, k + 1, size=R)
    row_ptr = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    col = np.concatenate([np.sort(rng.choice(n, size=s, replace=False)) for s in sizes]).astype(np.int64)
    upper = rng.uniform(0.0, 1.0, size=col.size)
    upper[rng.random(col.size) < 0.15] = 0.0
    upper[rng.random(col.size) < 0.1] = 1.0
    lower = upper * rng.uniform(0.0, 1.0, size=col.size)
    lower[rng.random(col.size) < 0.6] = 0.0
    fl = np.zeros(R)
    if floor:
        fl[rng.random(R) < 0.3] = 1e-3
    nxt = rng.integers(0, L, size=(L, n)).astype(np.int64)
    return state_ptr, row_ptr, col, lower, upper, fl, nxt


def _layer_counts(mask, nxt):
    """Per layer l: how many states q' have their successor node ``(nxt[l, q'], q')`` in ``mask``."""
    L, n = nxt.shape
    return [sum(bool(mask[nxt[l, q2] * n + q2]) for q2 in range(n)) for l in range(L)]


def _exact_positive(m, init, blocked, ctrl, strat, adv_max):
    """Kleene iteration of positive_attractor's exact test (rational sums)."""
    state_ptr, row_ptr, col, lower, upper, fl, nxt = m
    L, n = nxt.shape
    W = init.copy()
    while True:
        cnt = _layer_counts(W, nxt)
        new = W.copy()
        for node in range(L * n):
            if W[node] or blocked[node]:
                continue
            l, q = divmod(node, n)
            rows = [state_ptr[q] + strat[node]] if ctrl == 2 else range(state_ptr[q], state_ptr[q + 1])
            hits = []
            for r in rows:
                js = range(row_ptr[r], row_ptr[r + 1])
                inW = [j for j in js if W[nxt[l, col[j]] * n + col[j]]]
                out = [j for j in js if not W[nxt[l, col[j]] * n + col[j]]]
                unlW = cnt[l] - len(inW)
                unlOut = (n - len(js)) - unlW
                if adv_max:
                    hit = any(upper[j] > 0 for j in inW) or (fl[r] > 0 and unlW > 0)
                else:
                    stay = sum(Fraction(upper[j]) for j in out) + Fraction(fl[r]) * unlOut
                    hit = any(lower[j] > 0 for j in inW) or stay < 1
                hits.append(hit)
            if (ctrl == 1 and all(hits)) or (ctrl != 1 and any(hits)):
                new[node] = True
        if np.array_equal(new, W):
            return W
        W = new


def _exact_sure(m, target, W0, ctrl, strat, adv_max):
    """The nested fixed point of almost_sure with exact (rational) tests and no slack."""
    state_ptr, row_ptr, col, lower, upper, fl, nxt = m
    L, n = nxt.shape
    Y = W0.copy()
    while True:
        cntY = _layer_counts(Y, nxt)
        X = target.copy()
        while True:
            cntX = _layer_counts(X, nxt)
            new = X.copy()
            for node in range(L * n):
                if X[node] or not Y[node]:
                    continue
                l, q = divmod(node, n)
                rows = [state_ptr[q] + strat[node]] if ctrl == 2 else range(state_ptr[q], state_ptr[q + 1])
                for r in rows:
                    js = list(range(row_ptr[r], row_ptr[r + 1]))
                    node2 = {j: nxt[l, col[j]] * n + col[j] for j in js}
                    f = Fraction(fl[r])
                    unlY = cntY[l] - sum(bool(Y[node2[j]]) for j in js)
                    unlX = cntX[l] - sum(bool(X[node2[j]]) for j in js)
                    unlNotY = (n - len(js)) - unlY
                    unlNotX = (n - len(js)) - unlX
                    if adv_max:
                        capY = sum(Fraction(upper[j]) for j in js if Y[node2[j]]) + f * unlY
                        good = (all(lower[j] == 0 for j in js if not Y[node2[j]]) and capY >= 1
                                and (any(upper[j] > 0 for j in js if X[node2[j]]) or (f > 0 and unlX > 0))
                                and sum(Fraction(lower[j]) for j in js if Y[node2[j]] and not X[node2[j]]) < 1)
                    else:
                        if any(upper[j] > 0 for j in js if not Y[node2[j]]) or (f > 0 and unlNotY > 0):
                            good = False
                        else:
                            rest = sum(Fraction(upper[j]) for j in js if not X[node2[j]]) + f * unlNotX
                            good = any(lower[j] > 0 for j in js if X[node2[j]]) or rest < 1
                    if good:
                        new[node] = True
                        break
            if np.array_equal(new, X):
                break
            X = new
        if np.array_equal(X, Y):
            return X
        Y = X


_CASES = [(ctrl, adv_max, floor) for ctrl in (0, 1, 2) for adv_max in (False, True) for floor in (False, True)]


@pytest.mark.parametrize("ctrl, adv_max, floor", _CASES)
def test_positive_attractor_matches_exact_arithmetic(ctrl, adv_max, floor):
    for seed in range(4):
        m = _model(100 + seed, n=25, L=2, k=4, floor=floor)
        L, n = m[-1].shape
        rng = np.random.default_rng(seed)
        init = rng.random(L * n) < 0.1
        blocked = (rng.random(L * n) < 0.1) & ~init
        strat = rng.integers(0, 2, size=L * n).astype(np.int64)
        got = positive_attractor(*m, init, blocked, ctrl, strat, adv_max, 1)
        exact = _exact_positive(m, init, blocked, ctrl, strat, adv_max)
        assert np.all(got >= exact)  # liberal: every exact member is found
        assert np.array_equal(got, exact)  # and no float slack adds a node here


@pytest.mark.parametrize("ctrl, adv_max, floor", [c for c in _CASES if c[0] != 1])
def test_almost_sure_matches_exact_arithmetic(ctrl, adv_max, floor):
    for seed in range(4):
        m = _model(200 + seed, n=25, L=2, k=4, floor=floor)
        L, n = m[-1].shape
        rng = np.random.default_rng(seed)
        target = rng.random(L * n) < 0.15
        blocked = np.zeros(L * n, dtype=bool)
        strat = rng.integers(0, 2, size=L * n).astype(np.int64)
        W = positive_attractor(*m, target, blocked, ctrl, strat, adv_max, 1)
        got = almost_sure(*m, target, W, ctrl, strat, adv_max, 1)
        exact = _exact_sure(m, target, W, ctrl, strat, adv_max)
        assert np.all(got <= exact)  # conservative: no node without value 1
        assert np.array_equal(got, exact)


def _sum_one_row(uppers, lower_in_w=0.0):
    """Node 0 the target (in W); node 1 the tested state, one row: the target with lower ``lower_in_w`` and the
    outside successors 2 .. k+1 with ``uppers`` (each of those a self-loop)."""
    k = len(uppers)
    n = k + 2  # node 0: the target; node 1: the tested state; 2..: the outside successors
    state_ptr = np.arange(n + 1, dtype=np.int64)
    cols = [[0]] + [[0] + list(range(2, 2 + k))] + [[q] for q in range(2, n)]
    row_ptr = np.concatenate([[0], np.cumsum([len(c) for c in cols])]).astype(np.int64)
    col = np.array([q for c in cols for q in c], dtype=np.int64)
    upper = np.ones(col.size)
    lower = np.zeros(col.size)
    j0 = row_ptr[1]
    upper[j0] = 1.0  # the target's entry of the tested row
    lower[j0] = lower_in_w
    upper[j0 + 1:j0 + 1 + k] = uppers
    nxt = np.zeros((1, n), dtype=np.int64)
    return state_ptr, row_ptr, col, lower, upper, np.zeros(n), nxt


@pytest.mark.parametrize("uppers, reached", [
    ([0.5, 0.5], False),  # the adversary keeps all the mass outside W: not forced onto W
    ([0.25, 0.25, 0.5], False),
    ([0.5, np.nextafter(0.5, 0.0)], True),  # the exact sum is 1 - 2^-54 < 1: some mass must reach W
    ([0.1, 0.2, 0.7], True),  # the floats' exact sum is below 1 (their rounded sum is 1.0)
    # exact sum 1 - 4.0e-17, rounded to nearest 1 + 2^-52: only the rounded-down sum sees it below 1
    ([0.4133043754940587, 0.2655130893842962, 0.06297040413600605, 0.0034007843232661413, 0.07759641502040365,
      0.17721493164196925], True),
    ([1.0], False),
    ([np.nextafter(1.0, 0.0)], True),
])
def test_positive_attractor_decides_sums_at_one_exactly(uppers, reached):
    """Teeth of the rounded-down sums: a test with slack (or ``<=``) adds the first two rows, a test rounded to
    nearest misses the fourth and the fifth (the band around 1 in which the rounded-down sum decides)."""
    m = _sum_one_row(np.array(uppers))
    rn = 0.0
    for u in uppers:
        rn += u
    assert (rn > 1.0) == (len(uppers) == 6)  # the fifth case is the one the nearest sum puts above 1
    from fractions import Fraction as F

    assert (sum(F(u) for u in uppers) < 1) == reached  # the premise, in exact arithmetic
    n = m[0].shape[0] - 1
    init = np.zeros(n, dtype=bool)
    init[0] = True
    W = positive_attractor(*m, init, np.zeros(n, dtype=bool), 0, np.zeros(n, dtype=np.int64), False, 1)
    assert bool(W[1]) == reached


def test_rounded_down_sums_bound_the_exact_sum():
    rng = np.random.default_rng(7)
    for _ in range(2000):
        a, b = rng.uniform(0, 1, size=2) * 10.0 ** rng.integers(-20, 1, size=2)
        s = graph._add_down(a, b)
        assert Fraction(s) <= Fraction(a) + Fraction(b) < Fraction(np.nextafter(s, np.inf))
        f = rng.uniform(0, 1) * 10.0 ** rng.integers(-310, 0)
        m = int(rng.integers(0, 10 ** 6))
        p = graph._mul_down(f, m)
        assert 0.0 <= p and Fraction(p) <= Fraction(f) * m


def _big(seed: int, floor: bool):
    """A model of more nodes than three units, so that several lanes share every sweep; the first row of every
    state but 0 is a step ``q -> q - 1`` (its other entries 0, no floor), so that sets grow against the forward
    sweep, over many units."""
    m = _model(seed, n=3 * _UNIT // 2 + 17, L=2, k=2, floor=floor)
    state_ptr, row_ptr, col, lower, upper, fl = m[:6]
    for q in range(1, state_ptr.shape[0] - 1):
        r = state_ptr[q]
        lower[row_ptr[r]:row_ptr[r + 1]] = 0.0
        upper[row_ptr[r]:row_ptr[r + 1]] = 0.0
        col[row_ptr[r]] = q - 1
        lower[row_ptr[r]], upper[row_ptr[r]], fl[r] = 1.0, 1.0, 0.0
    return m


@pytest.mark.parametrize("ctrl, adv_max, floor", [(0, False, False), (0, True, True), (1, False, True),
                                                  (2, True, False), (2, False, True)])
def test_lanes_give_the_serial_sets(ctrl, adv_max, floor):
    m = _big(300 + ctrl, floor)
    L, n = m[-1].shape
    rng = np.random.default_rng(ctrl)
    target = np.zeros(L * n, dtype=bool)
    target[rng.choice(L * n, size=3, replace=False)] = True
    blocked = (rng.random(L * n) < 0.02) & ~target
    strat = (rng.random(L * n) < 0.05).astype(np.int64)  # ctrl 2: mostly the step row
    assert L * n > 2 * _UNIT
    W1 = positive_attractor(*m, target, blocked, ctrl, strat, adv_max, 1)
    # a grown set (every row must hit for ctrl 1: a few nodes)
    assert W1.sum() - target.sum() > (0 if ctrl == 1 else 100)
    for lanes in (2, 3, 5):
        assert np.array_equal(positive_attractor(*m, target, blocked, ctrl, strat, adv_max, lanes), W1)
    if ctrl != 1:
        one1 = almost_sure(*m, target, W1, ctrl, strat, adv_max, 1)
        assert one1.sum() > target.sum()
        for lanes in (2, 3, 5):
            assert np.array_equal(almost_sure(*m, target, W1, ctrl, strat, adv_max, lanes), one1)


@pytest.mark.parametrize("adv_max", [False, True])
def test_progress_strategy_lanes(adv_max):
    m = _big(400, floor=False)
    state_ptr = m[0]
    L, n = m[-1].shape
    R = state_ptr[-1]
    rng = np.random.default_rng(11)
    target = rng.random(L * n) < 0.02
    optimal = rng.random(L * R) < 0.7
    fallback = rng.integers(0, 2, size=L * n).astype(np.int64)
    score = np.where(rng.random(L * R) < 0.5, -np.inf, rng.integers(0, 3, size=L * R).astype(float))
    tie = np.where(rng.random(L * n) < 0.3, rng.integers(0, 2, size=L * n), -1).astype(np.int64)
    s1 = progress_strategy(*m, target, optimal, adv_max, fallback, score, tie, 1)
    assert np.any(s1 != fallback)
    for lanes in (2, 3, 5):
        assert np.array_equal(progress_strategy(*m, target, optimal, adv_max, fallback, score, tie, lanes), s1)


def _cycle_model(uppers):
    """Node 0 the target, node 1 a sink; nodes 2 .. 2+k-1 ("the cycle") each with row A (target or sink, half each)
    and row B (the target with [0, 1], every cycle node j with [0, uppers[j]]). Row B reaches the target almost
    surely iff the adversary cannot keep all the mass on the cycle: iff sum(uppers) < 1 exactly."""
    k = len(uppers)
    n = 2 + k
    rows = [[(0, 1.0, 1.0)], [(1, 1.0, 1.0)]]
    state_ptr = [0, 1, 2]
    for _ in range(k):
        rows.append([(0, 0.5, 0.5), (1, 0.5, 0.5)])
        rows.append([(0, 0.0, 1.0)] + [(2 + j, 0.0, float(u)) for j, u in enumerate(uppers)])
        state_ptr.append(state_ptr[-1] + 2)
    row_ptr = np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int64)
    col = np.array([c for r in rows for c, _, _ in r], dtype=np.int64)
    lower = np.array([lo for r in rows for _, lo, _ in r])
    upper = np.array([up for r in rows for _, _, up in r])
    return (np.array(state_ptr, dtype=np.int64), row_ptr, col, lower, upper, np.zeros(len(rows)),
            np.zeros((1, n), dtype=np.int64))


@pytest.mark.parametrize("uppers, sure", [
    ([0.5, 0.5], False),  # the adversary keeps all the mass on the cycle
    ([1.0 - 2.0 ** -53] + [2.0 ** -55] * 4, False),  # exact sum 1, but rounded to nearest 1 - 2^-53
    ([0.5, 0.25], True),  # a quarter forced onto the target at every step
])
def test_almost_sure_refuses_cycles_the_adversary_can_keep(uppers, sure):
    """Teeth of almost_sure's conservative test: without its slack the second cycle would get the value 1 (the
    float sum of its uppers is below 1), with ``<=`` the first; the true value of a cycle node there is 1/2."""
    from fractions import Fraction as F

    assert (sum(F(u) for u in uppers) < 1) == sure  # the premise, in exact arithmetic
    m = _cycle_model(uppers)
    n = m[0].shape[0] - 1
    target = np.zeros(n, dtype=bool)
    target[0] = True
    strat = np.zeros(n, dtype=np.int64)
    W = positive_attractor(*m, target, np.zeros(n, dtype=bool), 0, strat, False, 1)
    assert W[2:].all() and not W[1]  # row A reaches the target with probability 1/2
    one = almost_sure(*m, target, W, 0, strat, False, 1)
    assert one[2:].all() if sure else not one[2:].any()
