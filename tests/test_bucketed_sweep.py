"""The bucketed sweep of long rows (solvers.kernels.bellman_layer_bucketed) gives the bits of the
insertion-sorted one (bellman_layer) for every controller, adversary, direction, layer and thread count.

Why bit-for-bit and not a tolerance: the two orders of a row's entries must be the same order (by rank
with floor rows, by value with ties in storage order otherwise) and the arithmetic the same, so any
difference in the order of a greedy allocation shows up as different bits or different values; results
are compared with ``np.array_equal`` on the float arrays.
"""
from __future__ import annotations

import numba
import numpy as np
import pytest

from robust_imdp.models.imdp import IMDP
from robust_imdp.solvers import sweep as sweep_mod
from robust_imdp.solvers.common import Control
from robust_imdp.solvers.engine import solve_layered
from robust_imdp.solvers.kernels import (LayerValues, bellman_layer_bucketed, bellman_layer_bucketed_parallel,
                                         dd_prefix)
from robust_imdp.solvers.sweep import Sweeper


def _model(rng, n=120, actions=3, k=(40, 90), floor=True, shuffle=False):
    """A random IMDP whose rows list k successors each (sorted unless ``shuffle``), lower bounds summing
    to at most 0.9 and upper bounds to at least 1 (with ``floor``: a tiny floor on the unlisted states and
    upper sums possibly below 1, so the floor mass matters)."""
    R = n * actions
    lens = rng.integers(k[0], k[1] + 1, R)
    cols, lows, ups = [], [], []
    for ln in lens:
        c = np.sort(rng.choice(n, ln, replace=False))
        if shuffle:
            rng.shuffle(c)
        p = rng.dirichlet(np.ones(ln))
        lo = p * rng.uniform(0.3, 0.9)
        up = np.minimum(1.0, p * rng.uniform(1.0, 3.0, ln) + (0.0 if floor else 0.02))
        # some entries exact (upper == lower): left out of row_value's order, a no-op in the bucketed one
        exact = rng.random(ln) < 0.1
        up[exact] = lo[exact]
        if not floor and up.sum() < 1.0:
            up = up / up.sum() * 1.0001
            up = np.minimum(up, 1.0)
        cols.append(c), lows.append(lo), ups.append(up)
    row_ptr = np.concatenate([[0], np.cumsum(lens)])
    fl = None
    if floor:
        # enough floor mass for every row: sum(upper) + floor * unlisted >= 1
        deficit = np.array([max(0.0, 1.0 - u.sum()) for u in ups])
        fl = np.minimum(1.0, deficit / np.maximum(n - lens, 1) * 1.5 + 1e-6)
    return IMDP.from_csr(np.arange(0, R + 1, actions), row_ptr, np.concatenate(cols), np.concatenate(lows),
                         np.concatenate(ups), floor=fl)


def _values(rng, L, n):
    """Values in [0, 1] with many ties (0, 1 and a few repeated levels) and distinct ones."""
    v = rng.uniform(0, 1, (L, n))
    tie = rng.random((L, n))
    v[tie < 0.3] = 0.0
    v[(tie >= 0.3) & (tie < 0.4)] = 1.0
    v[(tie >= 0.4) & (tie < 0.55)] = 0.25
    return v


def _both(m, nxt, active, ctrl, adv_max, strategy, V, direction, want_rows, strat_layer=None, inplace=False):
    sw = Sweeper(m, nxt, active, ctrl, adv_max, strategy)
    assert sw._bucket is not None
    new = sw.sweep(V.copy(), direction, want_rows=want_rows, strat_layer=strat_layer, inplace=inplace)
    sw._bucket = None  # the insertion-sorted kernel
    old = sw.sweep(V.copy(), direction, want_rows=want_rows, strat_layer=strat_layer, inplace=inplace)
    return new, old


@pytest.mark.parametrize("floor", [True, False])
@pytest.mark.parametrize("ctrl", [Control.MAXIMISE, Control.MINIMISE, Control.FIXED])
@pytest.mark.parametrize("adv_max", [False, True])
def test_bucketed_sweep_same_bits(floor, ctrl, adv_max):
    rng = np.random.default_rng([int(floor), int(ctrl), int(adv_max)])
    m = _model(rng, floor=floor)
    assert m.has_floor == floor
    n, L = m.n_states, 2
    nxt = rng.integers(0, L, (L, n))
    active = rng.random((L, n)) < 0.8
    strategy = rng.integers(0, 3, (2, L, n)) if ctrl == Control.FIXED else None
    V = _values(rng, L, n)
    for direction in (-1, 1, 0):
        for want_rows in (False, True):
            (v1, a1, r1), (v0, a0, r0) = _both(m, nxt, active, ctrl, adv_max, strategy, V, direction, want_rows,
                                               strat_layer=1 if strategy is not None else None)
            assert np.array_equal(v1, v0) and np.array_equal(a1, a0) and np.array_equal(r1, r0)
    # unbounded Jacobi form (keep the better bound), one layer
    (v1, a1, _), (v0, a0, _) = _both(m, np.zeros((1, n), dtype=np.int64), active[:1], ctrl, adv_max,
                                     None if strategy is None else strategy[:, :1], V[:1], -1, False, inplace=True)
    assert np.array_equal(v1, v0) and np.array_equal(a1, a0)


def test_unsorted_rows_fall_back_without_floor():
    """Rows listing their successors out of order: without floor rows the insertion sort breaks value ties by
    storage order, which the global order does not follow, so the bucketed sweep is not used; with floor rows
    the order is by (unique) rank and it is."""
    rng = np.random.default_rng(5)
    m = _model(rng, floor=False, shuffle=True)
    assert Sweeper(m, np.zeros((1, m.n_states), dtype=np.int64), np.ones((1, m.n_states), bool), 0, False,
                   None)._bucket is None
    m = _model(rng, floor=True, shuffle=True)
    n = m.n_states
    (v1, a1, r1), (v0, a0, r0) = _both(m, np.zeros((1, n), dtype=np.int64), np.ones((1, n), bool),
                                       Control.MAXIMISE, False, None, _values(rng, 1, n), -1, True)
    assert np.array_equal(v1, v0) and np.array_equal(a1, a0) and np.array_equal(r1, r0)


@pytest.mark.parametrize("ctrl", [Control.MAXIMISE, Control.FIXED])
def test_bucketed_threads_same_bits(ctrl):
    """The threaded kernel (blocks of states as tasks) equals the serial one for 1 and for all threads."""
    rng = np.random.default_rng(11 + int(ctrl))
    m = _model(rng, n=150)
    sw = Sweeper(m, np.zeros((1, m.n_states), dtype=np.int64), np.ones((1, m.n_states), bool), ctrl, True, None)
    tr, arrays = sw._bucket
    assert tr.bstate.shape[0] - 1 > 1  # several blocks, so several tasks
    w = _values(rng, 1, m.n_states)[0]
    order = np.argsort(-w, kind="stable")
    rank = np.empty(m.n_states, dtype=np.int64)
    rank[order] = np.arange(m.n_states)
    sv = w[order]
    hi, lo = dd_prefix(sv)
    vals = LayerValues(w, order, rank, sv, hi, lo)
    strat = rng.integers(0, 3, m.n_states)
    active = rng.random(m.n_states) < 0.9
    outs = []
    threads = numba.get_num_threads()
    for kernel, t in ((bellman_layer_bucketed, 1), (bellman_layer_bucketed_parallel, 1),
                      (bellman_layer_bucketed_parallel, threads)):
        numba.set_num_threads(t)
        try:
            val, arg, rows = np.zeros(m.n_states), np.zeros(m.n_states, dtype=np.int64), np.full(m.n_choices, -np.inf)
            args = (arrays, tr, vals, active, True, True, int(ctrl), strat, 1, val, arg, rows, True, False,
                    np.empty(m.nnz, dtype=np.int32))
            kernel(*args) if kernel is bellman_layer_bucketed else kernel(*args, t)
        finally:
            numba.set_num_threads(threads)
        outs.append((val, arg, rows))
    for val, arg, rows in outs[1:]:
        assert np.array_equal(val, outs[0][0]) and np.array_equal(arg, outs[0][1]) and np.array_equal(rows, outs[0][2])


@pytest.mark.parametrize("adv_max", [False, True])
def test_k_step_solve_same_bits(monkeypatch, adv_max):
    """solve_layered with a horizon (lower, upper, time-varying strategy) through either kernel."""
    rng = np.random.default_rng(21 + int(adv_max))
    m = _model(rng, n=100)
    n, L = m.n_states, 2
    nxt = rng.integers(0, L, (L, n))
    target = np.zeros((L, n), bool)
    target[1, :10] = True
    zero = np.zeros((L, n), bool)
    zero[:, 90:] = True
    kw = dict(ctrl=Control.MAXIMISE, adv_max=adv_max, horizon=7)
    new = solve_layered(m, nxt, target, zero, **kw)
    monkeypatch.setattr(sweep_mod, "BUCKET_MIN_ROW", 10 ** 9)
    old = solve_layered(m, nxt, target, zero, **kw)
    assert np.array_equal(new.lower, old.lower) and np.array_equal(new.upper, old.upper)
    assert np.array_equal(new.strategy, old.strategy)
    assert np.any(new.lower > 0) and np.any(new.lower < new.upper)  # not a trivial case
