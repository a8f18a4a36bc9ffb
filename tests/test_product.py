"""Tests of the lazy IMDP x DFA product: hand-built 3-cell examples, first-label semantics,
lazy vs materialised product, strategy evaluation, horizons, bad input.

The DFAs are tiny stand-ins with the duck-type fields (the real ``dfa.py`` is tested elsewhere).
"""

from types import SimpleNamespace

import numpy as np
import pytest

from robust_imdp.errors import DimensionError, InvalidInputError, InvalidModelError
from robust_imdp.models.imdp import IMDP
from robust_imdp.solvers.product import evaluate_product_strategy, materialize_product, solve_product
from robust_imdp.solvers.api import solve_reachability

# F des over atoms (des,): letter 1 = des.  State 0 initial, 1 accepting.
F_DES = SimpleNamespace(atoms=("des",), n_states=2, initial=0, accepting=np.array([False, True]),
                        delta=np.array([[0, 1], [1, 1]]))
# G !obs & F des over atoms (obs, des): bit 0 = obs, bit 1 = des.  0 initial, 1 accepting, 2 sink.
G_NOT_OBS_F_DES = SimpleNamespace(atoms=("obs", "des"), n_states=3, initial=0,
                                  accepting=np.array([False, True, False]),
                                  delta=np.array([[0, 2, 1, 2], [1, 1, 1, 1], [2, 2, 2, 2]]))


def dense(n, a=1):
    return np.zeros((n, a, n)), np.zeros((n, a, n))


def three_cells_f_des():
    # cells 0, 1, 2 (= des) and the outside state 3 (avoid).
    # 0 -> 1 [0.5, 0.7], outside [0.3, 0.5];  1 -> 2 [0.6, 0.8], 0 [0.2, 0.4];  2, 3 absorbing
    lo, up = dense(4)
    lo[0, 0, 1], up[0, 0, 1], lo[0, 0, 3], up[0, 0, 3] = 0.5, 0.7, 0.3, 0.5
    lo[1, 0, 2], up[1, 0, 2], lo[1, 0, 0], up[1, 0, 0] = 0.6, 0.8, 0.2, 0.4
    for s in (2, 3):
        lo[s, 0, s] = up[s, 0, s] = 1.0
    return IMDP.from_dense(lo, up), np.array([0, 0, 1, 0])


def test_f_des_three_cells_hand_solved():
    m, letters = three_cells_f_des()
    r = solve_product(m, letters, F_DES, avoid=[3])
    # robust: the adversary sends the least mass toward des:
    #   V1 = 0.6 + 0.4 V0, V0 = 0.5 V1  =>  V1 = 0.75, V0 = 0.375
    exact = np.array([0.375, 0.75, 1.0, 0.0])
    assert r.converged
    assert np.all(r.initial_lower <= exact) and np.all(r.initial_upper >= exact)
    np.testing.assert_allclose(r.initial_lower, exact, atol=1e-8)
    # optimistic: V1 = 0.8 + 0.2 V0, V0 = 0.7 V1  =>  V1 = 0.8/0.86, V0 = 0.56/0.86
    r = solve_product(m, letters, F_DES, avoid=[3], adversary="optimistic")
    exact = np.array([0.56 / 0.86, 0.8 / 0.86, 1.0, 0.0])
    assert np.all(r.initial_lower <= exact) and np.all(r.initial_upper >= exact)
    np.testing.assert_allclose(r.initial_upper, exact, atol=1e-8)


def test_first_label_semantics():
    m, letters = three_cells_f_des()
    r = solve_product(m, letters, F_DES, avoid=[3])
    # a cell that starts inside des satisfies F des with probability 1: initial DFA state is
    # delta(s0, L(2)) = 1 (accepting), read once -- not delta(delta(s0, L(q)), L(q))
    np.testing.assert_array_equal(r.initial_state, [0, 0, 1, 0])
    assert r.initial_lower[2] == 1.0 and r.initial_upper[2] == 1.0
    # the outside state is never accepting, even in the accepting layer
    assert r.upper[1, 3] == 0.0


def test_obstacle_and_sink_hand_solved():
    # cells: 0 free, 1 obs, 2 des, 3 outside.  0 -> 1 [0.1, 0.3], 2 [0.5, 0.9], 0 [0, 0.2]
    lo, up = dense(4)
    lo[0, 0, 1], up[0, 0, 1] = 0.1, 0.3
    lo[0, 0, 2], up[0, 0, 2] = 0.5, 0.9
    up[0, 0, 0] = 0.2
    for s in (1, 2, 3):
        lo[s, 0, s] = up[s, 0, s] = 1.0
    m = IMDP.from_dense(lo, up)
    letters = np.array([0, 1, 2, 0])  # obs = bit 0, des = bit 1
    r = solve_product(m, letters, G_NOT_OBS_F_DES, avoid=[3])
    # robust: lowers (0.1 obs, 0.5 des), the remaining 0.4 to the lowest values: obs (sink, 0)
    # up to 0.3, then 0 itself 0.2:  V0 = 0.5 + 0.2 V0  =>  V0 = 0.625
    # optimistic: 0.9 to des, 0.1 (lower) to obs  =>  V0 = 0.9
    np.testing.assert_allclose(r.initial_lower[0], 0.625, atol=1e-8)
    assert r.initial_lower[0] <= 0.625 <= r.initial_upper[0]
    assert r.initial_upper[1] == 0.0  # starting on an obstacle: DFA sink
    ro = solve_product(m, letters, G_NOT_OBS_F_DES, avoid=[3], adversary="optimistic")
    assert ro.initial_lower[0] <= 0.9 <= ro.initial_upper[0] and ro.initial_upper[0] - 0.9 < 1e-8
    assert np.all(r.upper[2] == 0.0)  # the sink layer is 0 everywhere


def random_floor_imdp(rng, n, a, k, floor):
    cols, los, ups, row_ptr = [], [], [], [0]
    for _ in range(n * a):
        c = np.sort(rng.choice(n, k, replace=False))
        p = rng.dirichlet(np.ones(k)) * (1 - floor * (n - k) * 0.5)
        cols.append(c)
        los.append(np.clip(p - 0.1, 0, 1))
        ups.append(np.clip(p + 0.1, 0, 1))
        row_ptr.append(row_ptr[-1] + k)
    return IMDP.from_csr(np.arange(0, n * a + 1, a), row_ptr, np.concatenate(cols), np.concatenate(los),
                         np.concatenate(ups), floor=np.full(n * a, floor))


@pytest.mark.parametrize("floor", [0.0, 0.02])
@pytest.mark.parametrize("adversary", ["pessimistic", "optimistic"])
def test_lazy_equals_materialised(floor, adversary):
    rng = np.random.default_rng(42)
    n = 12
    m = random_floor_imdp(rng, n, 2, 4, floor)
    letters = rng.integers(0, 4, n)
    letters[-1] = 0
    lazy = solve_product(m, letters, G_NOT_OBS_F_DES, avoid=[n - 1], adversary=adversary)
    mp = materialize_product(m, letters, G_NOT_OBS_F_DES, avoid=[n - 1])
    assert mp.imdp.n_states == 3 * n and not mp.imdp.has_floor  # floor mass listed explicitly
    ref = solve_reachability(mp.imdp, mp.target, avoid=mp.avoid, adversary=adversary)
    assert lazy.converged and ref.converged
    np.testing.assert_allclose(lazy.lower.reshape(-1), ref.lower, atol=2e-8)
    np.testing.assert_allclose(lazy.upper.reshape(-1), ref.upper, atol=2e-8)
    np.testing.assert_allclose(lazy.initial_lower, ref.lower[mp.initial], atol=2e-8)
    # bounded horizon too (exact k-step values, agree to rounding)
    lk = solve_product(m, letters, G_NOT_OBS_F_DES, avoid=[n - 1], adversary=adversary, horizon=4)
    rk = solve_reachability(mp.imdp, mp.target, avoid=mp.avoid, adversary=adversary, horizon=4)
    np.testing.assert_allclose(lk.lower.reshape(-1), rk.lower, atol=1e-12)
    assert lk.strategy.shape == (4, 3, n)


def test_product_strategy_achieves_reported_value():
    rng = np.random.default_rng(3)
    n = 15
    m = random_floor_imdp(rng, n, 3, 4, 0.01)
    letters = rng.integers(0, 4, n)
    r = solve_product(m, letters, G_NOT_OBS_F_DES, avoid=[0])
    ev = evaluate_product_strategy(m, letters, G_NOT_OBS_F_DES, r.strategy, avoid=[0])
    assert np.all(ev.initial_lower >= r.initial_lower - 2e-8)
    evo = evaluate_product_strategy(m, letters, G_NOT_OBS_F_DES, r.strategy, avoid=[0], adversary="optimistic")
    assert np.all(evo.initial_upper >= ev.initial_lower)
    ro = solve_product(m, letters, G_NOT_OBS_F_DES, avoid=[0], adversary="optimistic")
    assert np.all(evo.initial_lower <= ro.initial_upper + 1e-12)  # p_up <= p_up_star
    rk = solve_product(m, letters, G_NOT_OBS_F_DES, avoid=[0], horizon=3)
    evk = evaluate_product_strategy(m, letters, G_NOT_OBS_F_DES, rk.strategy, avoid=[0], horizon=3)
    np.testing.assert_allclose(evk.initial_lower, rk.initial_lower, atol=1e-12)


@pytest.mark.parametrize("letters, dfa, exc, match", [
    (np.array([0, 0, 1]), F_DES, DimensionError, r"letters must have shape \(4,\)"),
    (np.array([0, 0, 2, 0]), F_DES, InvalidInputError, r"letters\[2\] = 2 is not a letter .* \[0, 2\)"),
    (np.array([0.0, 0, 1, 0]), F_DES, InvalidInputError, "integer bit masks"),
    (np.array([0, 0, 1, 0]), SimpleNamespace(n_states=2, initial=0, accepting=[0, 1]), InvalidModelError,
     "dfa must have attribute 'delta'"),
    (np.array([0, 0, 1, 0]), SimpleNamespace(n_states=2, initial=0, accepting=np.array([0, 1]),
                                            delta=np.array([[0, 2], [1, 1]])), InvalidModelError,
     r"dfa.delta must hold DFA states in \[0, 2\)"),
])
def test_bad_input_product(letters, dfa, exc, match):
    m, _ = three_cells_f_des()
    with pytest.raises(exc, match=match):
        solve_product(m, letters, dfa, avoid=[3])


def test_bad_product_strategy_shape():
    m, letters = three_cells_f_des()
    with pytest.raises(DimensionError, match=r"strategy must have shape \(2, 4\) or \(k, 2, 4\)"):
        evaluate_product_strategy(m, letters, F_DES, np.zeros(4, dtype=int), avoid=[3])
