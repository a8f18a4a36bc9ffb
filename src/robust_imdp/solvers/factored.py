"""Solving a factored interval MDP (:class:`~robust_imdp.models.factored.FactoredIMDP`): reachability
and the lazy product with a DFA, by value iteration with the factored Bellman operator.

The operator (docs/factored.md, "The operator")
-----------------------------------------------
For a row (cell q, mode u) with per-axis interval vectors ``P_0 .. P_{d-1}`` and successor values
``w`` (cells, outside), the row value is the nested O-maximisation

    B_{q,u}(w) = O_{P_0}( O_{P_1}( ... O_{P_{d-1}}(w) ... ) ),

the last axis reduced first; each ``O_P`` is the adversary's optimal ``p.x`` over one axis's
interval vector, whose entries are the listed intervals (value: the inner result there), the
outside (value ``w_out``) and the unlisted rest ``[0, rest_upper]`` (value ``w_rest`` = the
least value of ``w`` for a minimising adversary, the largest for a maximising one).  The
adversary chooses each axis's law after seeing the outer axes' outcomes, which is more than the
product set allows: for a minimising adversary ``B <= min over the product set`` (sound), for a
maximising one ``B >= max over the product set``; where every axis lists its whole support
(``rest_upper = 0``) the chosen law lies in the joint polytope of
:meth:`~robust_imdp.models.factored.FactoredIMDP.to_joint`, so the factored value is also
``>=`` (minimising) / ``<=`` (maximising) the joint IMDP's.  Proofs: docs/factored.md.

Soundness of the iteration
--------------------------
``B`` is monotone (the O-maximisation is, and so are the min/max of ``w``), with controller max,
min or a fixed mode per node.  The value ``V`` reported is its least fixed point (unbounded) or
its k-fold application to the target indicator (k steps).  k steps: one round-to-nearest sweep
per step and a global rounding budget (:func:`_bounded`).  Unbounded lower bounds: ``l_0`` = target
indicator, ``l <- max(l, B_down(l))`` with ``B_down <= B`` (outward rounding per level,
:mod:`robust_imdp.solvers.factored_kernels`), so ``l <= V`` by induction.  Upper bounds:
``u_0`` = 1 except on the nodes that provably cannot reach the target (support graph of the
operator, value 0) and ``u <- min(u, B_up(u))``: ``u >= V`` implies ``B_up(u) >= B(u) >= B(V) =
V``.  Both are sound for any number of iterations; without end-component deflation the upper
iterates may stop at a larger fixed point, and then ``converged`` is False with the achieved
gap (a ``ConvergenceWarning`` is issued).  Across DFA layers the update is in place
(Gauss-Seidel), which keeps every partial vector a vector of bounds.

Order (``ORDERED``, where the marginals are not widely shared: ``ORDER_MAX_SHARING``).  Before the
whole-model sweeps, :func:`_ordered_pass` goes through the strongly
connected components of the product's support graph in reverse topological order
(:mod:`robust_imdp.solvers.factored_order`), applying the same directed updates to one node at a time
(in place: still bounds) until each component's bracket is within the precision; in a cyclic
component an upper guess ``min(u, l + precision / 2)`` is kept only when one in-place sweep
``u(s) <- B_up(u)(s)`` raises no value (Lemma OVI of :mod:`robust_imdp.solvers.engine`: then ``B(u) <=
u`` on the component with proven upper bounds outside it, so ``u >= V`` by Knaster-Tarski).  The
whole-model iteration then runs from the improved bracket with its own stopping rule, so convergence
and ``converged`` are decided as without the pass; ``iterations`` adds the largest sweep count of one
component.

The result types are those of the joint solvers (:class:`~robust_imdp.solvers.product.ProductResult`,
:class:`~robust_imdp.solvers.common.ReachabilityResult`), so :mod:`robust_imdp.synthesis.core` can
use :func:`solve_factored_product` in place of ``solve_product`` / ``evaluate_product_strategy``.
"""

from __future__ import annotations

import warnings
import weakref
from dataclasses import dataclass

import numba
import numpy as np

from robust_imdp._fp import U, up_rounded
from robust_imdp.errors import ConvergenceWarning, DimensionError, InvalidInputError
from robust_imdp.models.factored import FactoredIMDP
from robust_imdp.models.imdp import ROW_SUM_TOL
from robust_imdp.solvers.common import (Adversary, Control, Objective, ReachabilityResult, adversary_maximises,
                                        enum_value, target_avoid)
from robust_imdp.solvers.engine import _TIE_TOL
from robust_imdp.solvers.factored_kernels import Grid, Marginals, Tree, factored_rows, fibre_order
from robust_imdp.solvers.product import ProductResult, _dfa_arrays, _result

__all__ = ["FactoredOperator", "factored_operator", "factored_bellman", "solve_factored_reachability",
           "solve_factored_product"]


# --------------------------------------------------------------------------- the prepared operator
@dataclass(frozen=True, eq=False)
class FactoredOperator:
    """The factored Bellman operator of one model, prepared once (deduplicated marginals and the
    traversal tree of :mod:`robust_imdp.solvers.factored_kernels`); get it with
    :func:`factored_operator`.

    Attributes
    ----------
    model : FactoredIMDP
    grid, marginals, tree : namedtuples of arrays (the kernel's inputs)
    n_marginals : tuple of int
        Distinct interval vectors per axis.
    groups : tuple of int
        Tree nodes per level 1 .. d (level l: distinct tuples of the last l axes' marginals).
    ids : (n_modes, n_cells, d) int32 array
        Marginal id (into ``marginals``) of every (mode, cell, axis): the rows one at a time
        (:mod:`robust_imdp.solvers.factored_order`).
    work : int
        Listed entries read by one full sweep of one layer (``sum`` over tree nodes of box
        volume x k): the sweep's cost, against ``n_modes * n_cells * prod(k)`` without sharing.
    nbytes : int
        Bytes of the prepared arrays.
    """

    model: FactoredIMDP
    grid: Grid
    marginals: Marginals
    tree: Tree
    ids: np.ndarray
    n_marginals: tuple
    groups: tuple
    work: int
    nbytes: int

    @property
    def unshared_work(self) -> int:
        """Listed entries a per-row nested reduction would read: ``sum over rows of prod_i k_i``
        (plus the intermediate levels)."""
        k = np.array(self.model.k, dtype=float)
        per_row = sum(np.prod(k[i:]) for i in range(len(k)))
        return int(self.model.n_modes * self.model.n_cells * per_row)


_CACHE: "weakref.WeakKeyDictionary[FactoredIMDP, FactoredOperator]" = weakref.WeakKeyDictionary()


def factored_operator(model: FactoredIMDP) -> FactoredOperator:
    """The prepared operator of ``model`` (built on first use, then cached while the model lives)."""
    if not isinstance(model, FactoredIMDP):
        raise InvalidInputError(f"model must be a FactoredIMDP; got {type(model).__name__}")
    op = _CACHE.get(model)
    if op is None:
        op = _prepare(model)
        _CACHE[model] = op
    return op


def _dedup(ax):
    """(ids (M*N,) into the axis's distinct marginals, index of one row per id)."""
    M, N, k = ax.lower.shape
    R = M * N
    key = np.concatenate([ax.start.reshape(R, 1).astype(np.float64), ax.lower.reshape(R, k), ax.upper.reshape(R, k),
                          ax.out_lower.reshape(R, 1), ax.out_upper.reshape(R, 1), ax.rest_upper.reshape(R, 1)],
                         axis=1)
    key = np.ascontiguousarray(key)
    # -0.0 and 0.0 are the same bound: normalise before comparing bytes
    key[key == 0.0] = 0.0
    void = key.view(np.dtype((np.void, key.dtype.itemsize * key.shape[1]))).reshape(R)
    _, first, ids = np.unique(void, return_index=True, return_inverse=True)
    return ids.reshape(R).astype(np.int64), first


def _prepare(model: FactoredIMDP) -> FactoredOperator:
    d, M, N = model.dim, model.n_modes, model.n_cells
    shape = np.array(model.shape, dtype=np.int64)
    strides = np.ones(d, dtype=np.int64)
    for i in range(d - 2, -1, -1):
        strides[i] = strides[i + 1] * shape[i + 1]
    grid = Grid(shape=shape, strides=strides, periodic=np.array(model.periodic, dtype=np.bool_))
    # ---- deduplicated marginals, ids global over the axes
    ids = np.empty((M, N, d), dtype=np.int64)
    parts = {k: [] for k in Marginals._fields}
    offset = 0
    n_marg = []
    for i, ax in enumerate(model.axes):
        idx, first = _dedup(ax)
        ids[:, :, i] = (idx + offset).reshape(M, N)
        T, k = first.size, ax.k
        lo = ax.lower.reshape(M * N, k)[first]
        up = ax.upper.reshape(M * N, k)[first]
        ol = ax.out_lower.reshape(-1)[first]
        parts["start"].append(ax.start.reshape(-1)[first])
        parts["k"].append(np.full(T, k, dtype=np.int64))
        parts["lower"].append(lo.reshape(-1))
        parts["cap"].append((up - lo).reshape(-1))  # rounded: its error is part of LEVEL_ERR
        parts["ol"].append(ol)
        parts["ocap"].append(ax.out_upper.reshape(-1)[first] - ol)
        parts["rcap"].append(ax.rest_upper.reshape(-1)[first])
        parts["rem0"].append(1.0 - lo.sum(axis=1) - ol)  # rounded: part of LEVEL_ERR
        offset += T
        n_marg.append(T)
    ks = np.concatenate(parts["k"])
    ptr = np.zeros(ks.size, dtype=np.int64)
    np.cumsum(ks[:-1], out=ptr[1:])
    mg = Marginals(start=np.concatenate(parts["start"]).astype(np.int64), k=ks, ptr=ptr,
                   lower=np.concatenate(parts["lower"]), cap=np.concatenate(parts["cap"]),
                   ol=np.concatenate(parts["ol"]), ocap=np.concatenate(parts["ocap"]),
                   rcap=np.concatenate(parts["rcap"]), rem0=np.concatenate(parts["rem0"]))
    # ---- listed ranges per (mode, cell, axis) in unwrapped positions: [start, end)
    st = np.stack([ax.start for ax in model.axes], axis=-1)  # (M, N, d)
    kk = np.array(model.k, dtype=np.int64)
    en = st + kk
    en = np.where(grid.periodic, en, np.minimum(en, shape))
    tree, work = _build_tree(ids, st, en, kk, d, M, N)
    ids32 = np.ascontiguousarray(ids, dtype=np.int32)
    nbytes = sum(a.nbytes for a in mg) + sum(a.nbytes for a in tree) + sum(a.nbytes for a in grid) + ids32.nbytes
    groups = tuple(int(tree.level_start[l + 1] - tree.level_start[l]) for l in range(1, d + 1))
    return FactoredOperator(model=model, grid=grid, marginals=mg, tree=tree, ids=ids32, n_marginals=tuple(n_marg),
                            groups=groups, work=int(work), nbytes=int(nbytes))


def _build_tree(ids, st, en, kk, d, M, N):
    """The traversal tree of :mod:`robust_imdp.solvers.factored_kernels` (its ``Tree`` docstring)."""
    per_level = [dict(mid=[], c0=[], c1=[], mode=[], box=[], child_local=[]) for _ in range(d + 1)]
    cells = np.empty((M, N), dtype=np.int64)
    counts = np.zeros(d + 1, dtype=np.int64)  # groups per level so far (all modes)
    maxvol = np.ones(d + 1, dtype=np.int64)
    work = 0
    for u in range(M):
        order = np.lexsort(tuple(ids[u, :, i] for i in range(d)))  # primary key: axis d-1
        cells[u] = order
        sm = ids[u, order]
        new = np.zeros(N, dtype=bool)
        new[0] = True
        starts = []
        for lev in range(1, d + 1):
            a = d - lev
            new = new | np.r_[True, sm[1:, a] != sm[:-1, a]]
            s = np.flatnonzero(new)
            starts.append(s)
        for lev in range(1, d + 1):
            a = d - lev
            s = starts[lev - 1]
            e = np.r_[s[1:], N]
            P = per_level[lev]
            P["mid"].append(sm[s, a])
            P["c0"].append(s)
            P["c1"].append(e)
            P["mode"].append(np.full(s.size, u, dtype=np.int64))
            # box over the remaining axes 0 .. a-1: union of the cells' listed ranges
            if a:
                lo = np.minimum.reduceat(st[u, order, :a], s, axis=0)
                hi = np.maximum.reduceat(en[u, order, :a], s, axis=0)
                box = np.stack([lo, hi], axis=-1).reshape(s.size, 2 * a)
                vol = np.prod(hi - lo, axis=1)
                maxvol[lev] = max(maxvol[lev], int(vol.max()))
            else:
                box = np.zeros((s.size, 0), dtype=np.int64)
                vol = np.ones(s.size, dtype=np.int64)
            work += int((vol * kk[a]).sum())
            P["box"].append(box)
            if lev < d:
                cs = starts[lev]
                P["child_local"].append((np.searchsorted(cs, s) + counts[lev + 1],
                                         np.searchsorted(cs, e) + counts[lev + 1]))
            counts[lev] += s.size
    level_start = np.zeros(d + 2, dtype=np.int64)
    for lev in range(1, d + 1):
        level_start[lev + 1] = level_start[lev] + counts[lev]
    G = int(level_start[d + 1])
    mid = np.empty(G, dtype=np.int64)
    c0 = np.empty(G, dtype=np.int64)
    c1 = np.empty(G, dtype=np.int64)
    mode = np.empty(G, dtype=np.int64)
    ch0 = np.zeros(G, dtype=np.int64)
    ch1 = np.zeros(G, dtype=np.int64)
    box_start = np.zeros(d + 2, dtype=np.int64)
    boxes = []
    for lev in range(1, d + 1):
        P = per_level[lev]
        sl = slice(level_start[lev], level_start[lev + 1])
        mid[sl] = np.concatenate(P["mid"])
        c0[sl] = np.concatenate(P["c0"])
        c1[sl] = np.concatenate(P["c1"])
        mode[sl] = np.concatenate(P["mode"])
        if lev < d:
            # children ids are local to the next level: make them global
            ch0[sl] = np.concatenate([c[0] for c in P["child_local"]]) + level_start[lev + 1]
            ch1[sl] = np.concatenate([c[1] for c in P["child_local"]]) + level_start[lev + 1]
        b = np.concatenate(P["box"]).reshape(-1)
        boxes.append(b)
        box_start[lev + 1] = box_start[lev] + b.size
    box = np.concatenate(boxes).astype(np.int64) if boxes else np.zeros(0, dtype=np.int64)
    tree = Tree(level_start=level_start, mid=mid, child0=ch0, child1=ch1, cell0=c0, cell1=c1, mode=mode,
                box_start=box_start, box=box, cells=cells, maxvol=maxvol)
    return tree, work


# --------------------------------------------------------------------------- one sweep
#: The fewest listed entries per sweep (``FactoredOperator.work``) for which the kernels run on numba's threads:
#: below it a sweep runs on one (each root's result is its own, so the bits are the same). Measured on the
#: 1,024-cell, 4-mode case study at load ~12 on 2 cores: 55k entries, 30 ms on one thread against 130-350 ms on two.
PAR_MIN_WORK = 2_000_000


def _need_pc(tree, need):
    """(M, N + 1) prefix counts of ``need`` (M, N) in each mode's tree order."""
    M, N = need.shape
    pc = np.zeros((M, N + 1), dtype=np.int64)
    np.cumsum(np.take_along_axis(need, tree.cells, axis=1), axis=1, out=pc[:, 1:])
    return pc


def _rows(op, w, need, adv_max, direction, support=False):
    """Row values (M, N) of the successor values ``w`` (n_cells + 1,) for the ``need``ed rows
    (-inf elsewhere).  ``support``: the graph version (the largest value of an entry with positive
    upper bound; the rest entry counts ``max(w)``)."""
    N = op.model.n_cells
    w = np.ascontiguousarray(w, dtype=np.float64)
    w_rest = float(w.max() if (adv_max or support) else w.min())
    out = np.full(need.shape, -np.inf)
    perm = np.zeros(N if not support else 1, dtype=np.int32)
    threads = numba.get_num_threads()
    serial = threads > 1 and op.work < PAR_MIN_WORK
    if serial:  # a small sweep: one thread (a parallel launch waits for every thread; same bits either way)
        numba.set_num_threads(1)
    try:
        if not support:
            fibre_order(w[:N], int(op.model.shape[-1]), perm)
        factored_rows(op.grid, op.marginals, op.tree, w[:N], perm, float(w[N]), w_rest, _need_pc(op.tree, need),
                      bool(adv_max), int(direction), bool(support), out)
    finally:
        if serial:
            numba.set_num_threads(threads)
    return out


def factored_bellman(model: FactoredIMDP, values, *, adversary="pessimistic", rounding="down",
                     kernel="tree") -> np.ndarray:
    """One application of the factored Bellman operator to every row: the value of each (mode, cell).

    Parameters
    ----------
    model : FactoredIMDP
    values : (n_cells + 1,) float array in [0, 1]
        Successor values of the cells and (last) the outside state.
    adversary : {"pessimistic", "optimistic"}
        Minimising or maximising adversary.
    rounding : {"down", "up", "nearest"}
        "down": a lower bound of the exact operator, "up": an upper bound (outward rounding per
        level, :mod:`robust_imdp.solvers.factored_kernels`), "nearest": plain floating point.
    kernel : {"tree", "rows"}
        "tree": the shared sweep of :func:`~robust_imdp.solvers.factored_kernels.factored_rows` (the
        whole-model iteration's); "rows": one row at a time, as the component-ordered pass evaluates them
        (:mod:`robust_imdp.solvers.factored_order`).  Both are outward rounded; they may differ in the last
        bits.

    Returns
    -------
    (n_modes, n_cells) float array
    """
    op = factored_operator(model)
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (model.n_states,):
        raise DimensionError(f"values must have shape ({model.n_states},) (cells, then the outside state); "
                             f"got {v.shape}")
    if not np.all((v >= 0) & (v <= 1)):
        raise InvalidInputError("values must lie in [0, 1] (probabilities)")
    direction = {"down": -1, "up": 1, "nearest": 0}.get(rounding)
    if direction is None:
        raise InvalidInputError(f"rounding must be one of 'down', 'up', 'nearest'; got {rounding!r}")
    adv_max = enum_value(Adversary, adversary, "adversary") is Adversary.OPTIMISTIC
    if kernel == "rows":
        from robust_imdp.solvers.factored_order import ProductRows, row_values

        n = model.n_states
        pr = ProductRows(ids=op.ids, nxt=np.zeros(n, dtype=np.int64), n=n, ctrl=0, strat=np.zeros(1, dtype=np.int64))
        out = np.empty((model.n_modes, model.n_cells))
        row_values(op.grid, op.marginals, pr, np.ascontiguousarray(v), float(v.max() if adv_max else v.min()),
                   adv_max, direction, out)
        return out
    if kernel != "tree":
        raise InvalidInputError(f"kernel must be 'tree' or 'rows'; got {kernel!r}")
    return _rows(op, v, np.ones((model.n_modes, model.n_cells), dtype=bool), adv_max, direction)


class _Layers:
    """Sweeps over the value arrays (S, n) of the lazy product (S = 1: plain reachability)."""

    def __init__(self, op, nxt, ctrl, adv_max, strategy):
        self.op = op
        self.nxt = nxt
        self.S, self.n = nxt.shape
        self.N = op.model.n_cells
        self.M = op.model.n_modes
        self.ctrl = ctrl
        self.adv_max = adv_max
        self.strategy = strategy  # (k or 1, S, n) or None
        self._ar = np.arange(self.n)

    def w(self, V, s):
        return V[self.nxt[s], self._ar]

    def layer(self, V, s, active_s, direction, strat_s=None, adv_max=None, ctrl=None):
        """(new values (n,), arg (n,), rows (M, N)) of layer s; inactive nodes keep ``V[s]``."""
        adv_max = self.adv_max if adv_max is None else adv_max
        ctrl = self.ctrl if ctrl is None else ctrl
        w = self.w(V, s)
        if ctrl == Control.FIXED:
            need = (strat_s[None, :self.N] == np.arange(self.M)[:, None]) & active_s[None, :self.N]
        else:
            need = np.broadcast_to(active_s[:self.N], (self.M, self.N)).copy()
        rows = _rows(self.op, w, need, adv_max, direction)
        new = V[s].copy()
        arg = np.zeros(self.n, dtype=np.int64)
        if ctrl == Control.MAXIMISE:
            arg[:self.N] = np.argmax(rows, axis=0)
        elif ctrl == Control.MINIMISE:
            arg[:self.N] = np.argmin(np.where(need, rows, np.inf), axis=0)
        else:
            arg[:self.N] = strat_s[:self.N]
        best = rows[arg[:self.N], np.arange(self.N)]
        cells = active_s[:self.N]
        new[:self.N] = np.where(cells, best, new[:self.N])
        if active_s[self.N]:
            new[self.N] = w[self.N]  # the outside state's self-loop (exact)
        return new, arg, rows

    def support_layer(self, ind, s, active_s, strat_s=None):
        """Nodes of layer s (n,) bool that can put positive mass on ``ind`` (liberal): through some
        mode (maximising controller), every mode (minimising) or the strategy's mode; under some
        admissible law of the support graph."""
        w = self.w(ind, s)
        if self.ctrl == Control.FIXED:
            need = (strat_s[None, :self.N] == np.arange(self.M)[:, None]) & active_s[None, :self.N]
        else:
            need = np.broadcast_to(active_s[:self.N], (self.M, self.N)).copy()
        out = np.zeros(self.n, dtype=bool)
        if need.any():
            N = self.N
            pos = _rows(self.op, w, need, False, 0, support=True) > 0
            if self.ctrl == Control.MINIMISE:
                # the controller cannot avoid the set only if every mode can reach it
                out[:N] = active_s[:N] & np.all(pos, axis=0)
            else:
                out[:N] = np.any(need & pos, axis=0)
        if active_s[self.N]:
            out[self.N] = w[self.N] > 0
        return out


# --------------------------------------------------------------------------- value iteration
def _step_error(op):
    """``(delta, lip)``: one plain (round-to-nearest) application of the operator to any ``x`` in [0, 1]
    is within ``delta`` of the exact one (sup norm), and the exact operator is ``lip``-Lipschitz.

    Per level, the float O-maximisation is within ``LEVEL_ERR(k)`` of the exact one with the same
    inputs (:mod:`robust_imdp.solvers.factored_kernels`), plus the mass the greedy leaves unassigned
    where a row's upper sums fall short of 1 (at most ``ROW_SUM_TOL``, the model's validation); the
    later levels carry an error through a sum with weights of total at most ``1 + ROW_SUM_TOL``
    (``p = lower`` where the lower sums exceed 1 within the tolerance), and so does every level for
    a difference of inputs: ``lip = (1 + ROW_SUM_TOL)^d``.  Both are rounded up."""
    d = op.model.dim
    lip = 1.0
    delta = 0.0
    for k in op.model.k:
        err = (16.0 * (k + 2) + 64.0) * U + ROW_SUM_TOL
        delta = delta * (1.0 + ROW_SUM_TOL) + err  # the later levels carry it with weight <= 1 + tol
        lip *= 1.0 + ROW_SUM_TOL
    # d + 2 roundings of non-negative terms: one relative gamma covers them, one ulp more
    return float(up_rounded(delta, 3 * d + 2)), float(up_rounded(lip, 2 * d + 2))


def _bounded(lay, V0, active, k, tie):
    """k-step values and strategy (k, S, n): one plain Jacobi sweep per step and a global error budget.

    With ``v_t`` the floating-point iterate and ``V_t`` the exact one, ``|v_t - V_t| <= E_t`` on every
    node, ``E_t = lip E_{t-1} + delta`` (:func:`_step_error`): ``|B~(v) - B(V)| <= |B~(v) - B(v)| +
    |B(v) - B(V)| <= delta + lip |v - V|``; targets and value-0 nodes are exact.  The bracket is
    ``[v_k - E_k, v_k + E_k]`` rounded outward and clamped to [0, 1] (safe: ``V_k`` is a probability);
    ``E_10`` is about 1e-10 on a 6-D model.  Half the sweeps of two directed iterations."""
    S, n = V0.shape
    v, opt = V0.copy(), V0.copy()
    strat = np.zeros((k, S, n), dtype=np.int64)
    delta, lip = _step_error(lay.op)
    E = 0.0
    for t in range(1, k + 1):
        sl = None if lay.strategy is None else lay.strategy[k - t if lay.strategy.shape[0] == k else 0]
        new_v, new_opt = v.copy(), opt.copy()
        for s in range(S):
            if not active[s].any():
                continue
            ss = None if sl is None else sl[s]
            new_v[s], arg, rows = lay.layer(v, s, active[s], 0, ss)
            if tie:
                new_opt[s], _, rows_up = lay.layer(opt, s, active[s], 0, None, adv_max=True, ctrl=Control.MAXIMISE)
                arg[:lay.N] = _lex(rows, rows_up)
            strat[k - t, s] = arg
        v, opt = new_v, new_opt
        E = float(up_rounded(E * lip + delta, 3))
    if lay.ctrl == Control.FIXED:
        strat = np.broadcast_to(lay.strategy, strat.shape).copy() if lay.strategy.shape[0] == k else \
            np.repeat(lay.strategy, k, 0)
    lo = np.where(active, np.clip(np.nextafter(v - E, -np.inf), 0.0, 1.0), v)
    up = np.where(active, np.clip(np.nextafter(v + E, np.inf), 0.0, 1.0), v)
    prec = float(np.max(up - lo)) if up.size else 0.0
    return ReachabilityResult(lower=lo, upper=up, strategy=strat, iterations=k, precision=prec, converged=True)


def _lex(rows_lo, rows_up):
    """Per cell, among the modes within ``_TIE_TOL`` of the best lower row value, the first with
    the largest optimistic row value (the lexicographic choice of :mod:`robust_imdp.solvers.engine`)."""
    best = rows_lo.max(axis=0)
    optimal = rows_lo >= best[None, :] - _TIE_TOL
    return np.argmax(np.where(optimal, rows_up, -np.inf), axis=0)


def _reach_set(lay, target, active):
    """Nodes that can reach ``target`` with positive probability in the operator's support graph
    (liberal: a superset of those with a positive value).  One support sweep per round."""
    R = target.copy()
    strat = None if lay.strategy is None else lay.strategy[0]
    while True:
        ind = R.astype(np.float64)
        new = R.copy()
        for s in range(lay.S):
            todo = active[s] & ~R[s]
            if todo.any():
                new[s] |= lay.support_layer(ind, s, todo, None if strat is None else strat[s]) & todo
        if np.array_equal(new, R):
            return R
        R = new


#: Run the component-ordered pass (:func:`_ordered_pass`) before the whole-model sweeps of an unbounded solve.
ORDERED = True

#: The pass evaluates one row at a time, without the prefix tree's sharing of marginals: it runs only where a
#: per-row sweep reads at most this many times the entries of a shared sweep (``FactoredOperator.unshared_work /
#: work``). Measured (benchmarks/results/factored_solver.md): the 4-D vehicle 1.7-2.6 (the pass wins: fewer
#: sweeps, each no dearer), car parking 14 (a shared sweep 13 ms against 120-220 ms per row-wise sweep: the
#: whole-model sweeps win although they need more of them).
ORDER_MAX_SHARING = 4.0

#: An end of a cyclic component that moves by at most ``ORDER_STALL * precision`` in one sweep of the ordered
#: pass is not swept again in that pass (the whole-model sweeps after it decide convergence).
ORDER_STALL = 1e-3


def _ordered_pass(lay, lo, up, active, precision, max_iterations):
    """The product's components in reverse topological order, each swept in place until its bracket is
    within ``precision`` (:mod:`robust_imdp.solvers.factored_order`); ``lo``/``up`` (S, n) are improved in
    place (every update is a directed Bellman update of the current vectors: sound in any order).
    Returns (largest number of sweeps of one component, number of components, number of cyclic ones)."""
    from robust_imdp.solvers.factored_order import ProductRows, factored_components, product_sccs

    op = lay.op
    S, n = lo.shape
    N = lay.N
    strat = np.zeros(1, dtype=np.int64) if lay.ctrl != Control.FIXED else \
        np.ascontiguousarray(lay.strategy[0], dtype=np.int64).reshape(-1)
    nxt = np.ascontiguousarray(lay.nxt, dtype=np.int64).reshape(-1)
    pr = ProductRows(ids=op.ids, nxt=nxt, n=n, ctrl=int(lay.ctrl), strat=strat)
    act = np.ascontiguousarray(active, dtype=np.bool_).reshape(-1).copy()
    act[N::n] = False  # the outside state is left to the whole-model sweeps (its own self-loop update)
    if not act.any():
        return 0, 0, 0
    comp, cyclic, rank = product_sccs(op.grid, op.marginals, pr, act)
    nodes = np.flatnonzero(act)
    nodes = nodes[np.argsort(rank[nodes], kind="stable")]  # components in order, Tarjan's pop order inside
    counts = np.bincount(comp[nodes], minlength=cyclic.size)
    comp_ptr = np.zeros(cyclic.size + 1, dtype=np.int64)
    np.cumsum(counts, out=comp_ptr[1:])
    # the rest entry's value per layer, from the vectors before the pass (module docstring of factored_order:
    # lower iterates only rise, upper ones only fall, so these stay on the safe side during the pass)
    ar = np.arange(n)
    pick = np.max if lay.adv_max else np.min
    wr_lo = np.array([pick(lo[lay.nxt[s], ar]) for s in range(S)], dtype=np.float64)
    wr_up = np.array([pick(up[lay.nxt[s], ar]) for s in range(S)], dtype=np.float64)
    sweeps = np.zeros(cyclic.size, dtype=np.int64)
    lof, upf = lo.reshape(-1), up.reshape(-1)
    factored_components(op.grid, op.marginals, pr, lof, upf, nodes, comp_ptr, cyclic, wr_lo, wr_up, bool(lay.adv_max),
                     float(precision), float(ORDER_STALL * precision), int(max_iterations), sweeps)
    return int(sweeps.max()) if sweeps.size else 0, int(cyclic.size), int(cyclic.sum())


def _unbounded(lay, target, zero, active, precision, max_iterations, tie_break):
    S, n = target.shape
    strat0 = None if lay.strategy is None else lay.strategy[0]
    reach = _reach_set(lay, target, active)
    zero_all = zero | (active & ~reach)
    active2 = active & reach
    lo = target.astype(np.float64)
    up = np.where(zero_all, 0.0, 1.0)
    layers = [s for s in range(S) if active2[s].any()]
    it = 0
    pre = 0  # sweeps of the ordered pass (the largest count of one component)
    if ORDERED and lay.op.unshared_work <= ORDER_MAX_SHARING * lay.op.work:
        pre, _, _ = _ordered_pass(lay, lo, up, active2, precision, max_iterations)
    gap = float(np.max(up - lo)) if up.size else 0.0
    while gap > precision and it < max_iterations:
        it += 1
        before_lo, before_up = lo.copy(), up.copy()
        for s in layers:  # in place across layers (Gauss-Seidel): every partial vector stays a bound
            ss = None if strat0 is None else strat0[s]
            new_lo, _, _ = lay.layer(lo, s, active2[s], -1, ss)
            lo[s] = np.maximum(lo[s], new_lo)
            new_up, _, _ = lay.layer(up, s, active2[s], +1, ss)
            up[s] = np.minimum(up[s], new_up)
        gap = float(np.max(up - lo))
        if np.array_equal(lo, before_lo) and np.array_equal(up, before_up):
            break  # a fixed point of both directed iterations: further sweeps change nothing (an end component
            # keeps the upper side above the lower one: no deflation, docs/factored.md)
    it += pre
    converged = gap <= precision
    if not converged:
        warnings.warn(f"factored value iteration stopped after {it} iterations with max(upper - lower) = {gap:.3g} > "
                      f"precision {precision:g}; the returned bounds are sound but loose", ConvergenceWarning,
                      stacklevel=3)
    if lay.ctrl == Control.MINIMISE:
        strat = _minimising_strategy(lay, up, active)
    else:
        strat = _strategy(lay, lo, target, active, active2, tie_break)
    return ReachabilityResult(lower=lo, upper=up, strategy=strat, iterations=it, precision=gap, converged=converged)


def _minimising_strategy(lay, up, active):
    """A minimising controller's stationary strategy: per node a mode of least (rounded-up) value
    against the upper vector ``up``.  The exact iterates keep ``B(u) <= u`` (``u_0 = 1``;
    ``u' = min(u, B(u)) >= B(u) >= B(u')``), and a strategy pi of least rows has ``B_pi(u) = B(u) <=
    u``, so its value (the least fixed point of ``B_pi``) is at most u (Knaster-Tarski): it achieves
    the reported upper bound up to the rounding of the row values (as in
    :mod:`robust_imdp.solvers.engine`; on the nodes proven 0 every successor of a least row has value
    0, so it keeps away from the target for ever).  Callers re-evaluate the strategy."""
    S, n = up.shape
    strat = np.zeros((S, n), dtype=np.int64)
    for s in range(S):
        if active[s].any():
            _, strat[s], _ = lay.layer(up, s, active[s], +1)
    return strat


def _strategy(lay, lo, target, active, swept, tie_break):
    """Stationary strategy (S, n): the fixed one, the minimising rows, or (maximising) optimal rows
    that make progress toward the target (the backward attractor of
    :func:`robust_imdp.solvers.graph.progress_strategy`, with the factored operator deciding
    whether a row puts positive mass on the attractor: for every admissible law (minimising
    adversary: its rounded-down value on the indicator is > 0) or for some (maximising: the
    support graph)); lexicographic ties with ``tie_break`` (module :mod:`robust_imdp.solvers.engine`)."""
    S, n = lo.shape
    N, M = lay.N, lay.M
    if lay.ctrl == Control.FIXED:
        return lay.strategy[0].copy()
    strat = np.zeros((S, n), dtype=np.int64)
    rows_lo = np.full((S, M, N), -np.inf)
    for s in range(S):
        if swept[s].any():
            _, strat[s], rows_lo[s] = lay.layer(lo, s, swept[s], -1)
    best = rows_lo.max(axis=1)  # (S, N)
    optimal = (rows_lo >= best[:, None, :] - _TIE_TOL) & np.isfinite(rows_lo)
    proven0 = (active & ~swept)[:, :N]
    optimal |= proven0[:, None, :]
    if tie_break is None:
        score = np.full((S, M, N), -np.inf)
        tie_strat = np.full((S, n), -1, dtype=np.int64)
    else:
        U, tie_strat = tie_break
        score = np.full((S, M, N), -np.inf)
        for s in range(S):
            if active[s].any():
                _, _, score[s] = lay.layer(U, s, active[s], +1, None, adv_max=True, ctrl=Control.MAXIMISE)
    W = target.copy()
    while True:
        ind = W.astype(np.float64)
        newW = W.copy()
        for s in range(S):
            todo = active[s] & ~W[s]
            if not todo[:N].any():
                continue
            if lay.adv_max:
                rows = _rows(lay.op, lay.w(ind, s), np.broadcast_to(todo[:N], (M, N)).copy(), True, 0, support=True)
            else:
                _, _, rows = lay.layer(ind, s, todo, -1)
            hit = optimal[s] & (rows > 0.0) & todo[None, :N]
            join = hit.any(axis=0)
            if join.any():
                sc = np.where(hit, score[s], -np.inf)
                choice = np.where(np.isfinite(sc.max(axis=0)), np.argmax(sc, axis=0), np.argmax(hit, axis=0))
                q = np.flatnonzero(join)
                strat[s, q] = choice[q]
                newW[s, q] = True
        if np.array_equal(newW, W):
            break
        W = newW
    # nodes the attractor never reached: the optimistic solve's row if optimal, else the optimal
    # row of largest score, else the first-choice row
    for s in range(S):
        rest = np.flatnonzero(active[s, :N] & ~W[s, :N])
        if not rest.size:
            continue
        t = tie_strat[s, rest]
        ok = (t >= 0) & optimal[s, np.clip(t, 0, M - 1), rest]
        sc = np.where(optimal[s][:, rest], score[s][:, rest], -np.inf)
        by_score = np.argmax(sc, axis=0)
        has = np.isfinite(sc.max(axis=0))
        strat[s, rest] = np.where(ok, t, np.where(has, by_score, strat[s, rest]))
    return strat


# --------------------------------------------------------------------------- public solvers
def _objective(control) -> Control:
    """MAXIMISE or MINIMISE from a Control, an Objective or their strings."""
    if isinstance(control, Control) and control is not Control.FIXED:
        return control
    if isinstance(control, Objective):
        control = control.value
    names = {"maximize": Control.MAXIMISE, "maximise": Control.MAXIMISE, "minimize": Control.MINIMISE,
             "minimise": Control.MINIMISE}
    if control not in names:
        raise InvalidInputError(f"control must be 'maximize' or 'minimize' (or Control.MAXIMISE / MINIMISE); "
                                f"got {control!r}")
    return names[control]


def _check_strategy(model, strategy, S, n, horizon):
    st = np.asarray(strategy)
    if st.ndim not in (2, 3) or st.shape[-2:] != (S, n):
        raise DimensionError(f"strategy must have shape ({S}, {n}) or (k, {S}, {n}); got {st.shape}")
    if st.size and not np.issubdtype(st.dtype, np.integer):
        raise InvalidInputError(f"strategy must hold integer mode indices; got dtype {st.dtype}")
    if st.ndim == 3 and (horizon is None or st.shape[0] != int(horizon)):
        raise DimensionError(f"a time-varying strategy of shape {st.shape} needs horizon={st.shape[0]}; got {horizon}")
    st = (st if st.ndim == 3 else st[None]).astype(np.int64)
    N = model.n_cells
    bad = np.argwhere((st[..., :N] < 0) | (st[..., :N] >= model.n_modes))
    if bad.size:
        idx = tuple(int(i) for i in bad[0])
        raise InvalidInputError(f"strategy{list(idx)} = {int(st[idx])} is not a mode in [0, {model.n_modes})")
    bad = np.flatnonzero(st[..., N].reshape(-1) != 0)
    if bad.size:
        raise InvalidInputError(f"the outside state {N} has one choice (0); the strategy gives it "
                                f"{int(st[..., N].reshape(-1)[bad[0]])}")
    return np.ascontiguousarray(st)


def _check_tie_break(tie_break, ctrl, S, n, horizon):
    if tie_break is None:
        return None
    if ctrl != Control.MAXIMISE:
        raise InvalidInputError("tie_break applies to a maximising controller of the reach reading only; got "
                                f"control {Control(ctrl).name}")
    if not (hasattr(tie_break, "upper") and hasattr(tie_break, "strategy")):
        raise InvalidInputError("tie_break must be the result of the optimistic solve of the same model (with "
                                f"'upper' and 'strategy'); got {type(tie_break).__name__}")
    if horizon is not None:
        return True
    up = np.asarray(tie_break.upper, dtype=np.float64)
    if S == 1 and up.shape == (n,):
        up = up[None]
    st = np.asarray(tie_break.strategy)
    if up.shape != (S, n) or st.reshape(-1).shape[0] != S * n:
        raise DimensionError(f"tie_break must come from a solve of the same model: upper ({S}, {n}) and an "
                             f"({S}, {n}) stationary strategy; got upper {np.shape(tie_break.upper)}, strategy {st.shape}")
    return np.ascontiguousarray(up, dtype=np.float64), np.ascontiguousarray(st.reshape(S, n), dtype=np.int64)


def _solve(model, nxt, target, zero, *, objective, adv_max, horizon, precision, max_iterations, strategy, tie_break):
    """Value iteration on the layers ``nxt`` (S, n) with ``target`` / ``zero`` (S, n): the reach value,
    controller ``objective`` (MAXIMISE / MINIMISE; FIXED with ``strategy``), adversary maximising
    iff ``adv_max``.  Returns a ReachabilityResult of (S, n) arrays."""
    op = factored_operator(model)
    S, n = nxt.shape
    if horizon is not None:
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 0:
            raise InvalidInputError(f"horizon must be a non-negative int or None; got {horizon!r}")
        horizon = int(horizon)
    if not (np.isfinite(precision) and precision > 0):
        raise InvalidInputError(f"precision must be a positive number; got {precision!r}")
    ctrl = Control.FIXED if strategy is not None else objective
    st = None if strategy is None else _check_strategy(model, strategy, S, n, horizon)
    tie = _check_tie_break(tie_break, ctrl, S, n, horizon)
    target = target & ~zero
    active = ~(target | zero)
    lay = _Layers(op, nxt, ctrl, adv_max, st)
    if horizon is not None:
        return _bounded(lay, target.astype(np.float64), active, horizon, tie is not None)
    return _unbounded(lay, target, zero, active, float(precision), int(max_iterations), tie)


def solve_factored_reachability(model: FactoredIMDP, target, *, avoid=None, adversary="pessimistic",
                                objective="maximize", horizon=None, precision=1e-8, max_iterations=100_000,
                                strategy=None) -> ReachabilityResult:
    """Bounds of the probability of reaching ``target`` on a factored IMDP (states: cells, then outside).

    The arguments mean what they mean for :func:`robust_imdp.solvers.api.solve_reachability`.

    Parameters
    ----------
    model : FactoredIMDP
    target : (n_cells + 1,) bool mask or index array
        Absorbing target states (value 1); may include the outside state ``n_cells``.
    avoid : (n_cells + 1,) bool mask or index array, optional
        Absorbing states of value 0.
    adversary : {"pessimistic", "optimistic"}
        Pessimistic works against the objective (minimises the probability when the objective is
        "maximize", maximises it when "minimize"), optimistic with it.
    objective : {"maximize", "minimize"}
        What the controller does with the modes (with ``strategy``: which side "pessimistic" is).
    horizon : int, optional
        k-step reachability (strategy (k, n)); unbounded when None.
    precision, max_iterations
        Unbounded: stop when ``max(upper - lower) <= precision`` (else ``converged=False``).
    strategy : (n_cells + 1,) or (k, n_cells + 1) int array, optional
        A fixed mode per state (0 for the outside state) to evaluate.

    Returns
    -------
    ReachabilityResult
        ``lower``/``upper`` (n_cells + 1,) bracket the value of the factored operator (module
        docstring): below the product set's value for an adversary that minimises, above it for
        one that maximises.
    """
    if not isinstance(model, FactoredIMDP):
        raise InvalidInputError(f"model must be a FactoredIMDP; got {type(model).__name__}")
    n = model.n_states
    t, z = target_avoid(n, target, avoid, item="state")
    obj = _objective(objective)
    adv_max = adversary_maximises(adversary, "maximize" if obj == Control.MAXIMISE else "minimize")
    st = None if strategy is None else np.asarray(strategy)
    if st is not None and st.ndim in (1, 2):
        st = st[..., None, :]  # one layer
    res = _solve(model, np.zeros((1, n), dtype=np.int64), t[None], z[None], objective=obj, adv_max=adv_max,
                 horizon=horizon, precision=precision, max_iterations=max_iterations, strategy=st, tie_break=None)
    strat = res.strategy[:, 0] if horizon is not None else res.strategy[0]
    return ReachabilityResult(lower=res.lower[0], upper=res.upper[0], strategy=strat, iterations=res.iterations,
                              precision=res.precision, converged=res.converged)


class _N:
    """The base model's state count, for :func:`robust_imdp.solvers.product._dfa_arrays`."""

    def __init__(self, n):
        self.n_states = n


def solve_factored_product(model: FactoredIMDP, letters, dfa, *, avoid=None, adversary="pessimistic", horizon=None,
                           precision=1e-8, max_iterations=100_000, control="maximize", strategy=None,
                           tie_break=None, semantics="reach") -> ProductResult:
    """The lazy product of a factored IMDP with a DFA, solved by factored value iteration.

    Same semantics and result as :func:`robust_imdp.solvers.product.solve_product` (a maximising
    controller) and :func:`~robust_imdp.solvers.product.evaluate_product_strategy` (``strategy``):
    values (S, n) with ``n = n_cells + 1``, layer s reading the successor values
    ``V[delta(s, L(q')), q']``; under the reach reading accepting DFA states are targets and
    ``avoid`` states and DFA sinks are 0.

    Parameters
    ----------
    model : FactoredIMDP
    letters : (n_cells + 1,) int array
        Letter of every base state (cells, then the outside state) w.r.t. ``dfa.atoms``.
    dfa : DFA duck type (``n_states``, ``initial``, ``accepting``, ``delta``)
    avoid : (n_cells + 1,) bool mask or index array, optional
        Absorbing never-accepting base states (usually the outside state ``n_cells``).
    adversary : {"pessimistic", "optimistic"}
        Pessimistic works against the controller's objective on the reported value (minimises it
        for ``control="maximize"``, maximises it for "minimize"), optimistic with it.
    horizon : int, optional
        k steps (strategy (k, S, n)); unbounded when None.
    precision, max_iterations
        Unbounded: stop when ``max(upper - lower) <= precision`` (else ``converged=False`` and a
        ``ConvergenceWarning``; the bracket is sound either way).
    control : {"maximize", "minimize"} or Control
        The controller maximises (synthesis) or minimises the reported value over the modes; with
        ``strategy`` it only says which side "pessimistic" is.
    strategy : (S, n) or (k, S, n) int array, optional
        A fixed strategy (mode per DFA state and base state; 0 for the outside state) to evaluate.
    tie_break : ProductResult, optional
        The ``adversary="optimistic"`` solve of the same product (maximising controller, reach
        reading): modes tied in the lower value are chosen by their optimistic value
        (lexicographic choice, :mod:`robust_imdp.solvers.engine`).
    semantics : {"reach", "safety"}
        The reported value: the probability of reaching an accepting DFA state ("reach"), or of
        never reaching a bad node -- an ``avoid`` state or a DFA state from which acceptance is
        impossible -- ("safety", solved as one minus the probability of reaching a bad node with the
        roles of controller and adversary swapped, the bracket complemented and rounded outward),
        as :func:`robust_imdp.solvers.product.solve_product` reads them.

    Returns
    -------
    ProductResult
        ``lower``/``upper`` bracket the factored value, which is below the product set's value where
        the adversary minimises the reported value and above it where it maximises it
        (docs/factored.md).
    """
    if not isinstance(model, FactoredIMDP):
        raise InvalidInputError(f"model must be a FactoredIMDP; got {type(model).__name__}")
    if semantics not in ("reach", "safety"):
        raise InvalidInputError(f"semantics must be 'reach' or 'safety'; got {semantics!r}")
    safety = semantics == "safety"
    nxt, target, zero, init = _dfa_arrays(_N(model.n_states), letters, dfa, avoid)
    obj = _objective(control)
    adv_max = adversary_maximises(adversary, "maximize" if obj == Control.MAXIMISE else "minimize")
    if safety:
        if tie_break is not None:
            raise InvalidInputError("tie_break applies to the reach reading only (semantics='reach')")
        # the bad nodes become the target of the reach value 1 - satisfaction: the controller's
        # objective and the adversary's direction flip with it
        target, zero = zero.copy(), np.zeros_like(zero)
        obj = Control.MINIMISE if obj == Control.MAXIMISE else Control.MAXIMISE
        adv_max = not adv_max
    res = _solve(model, nxt, target, zero, objective=obj, adv_max=adv_max, horizon=horizon, precision=precision,
                 max_iterations=max_iterations, strategy=strategy, tie_break=tie_break)
    if safety:
        # [lower, upper] of P(reach bad) -> [1 - upper, 1 - lower], one ulp outward (a subtraction
        # from 1 rounds once); the clamps are safe: probabilities lie in [0, 1]
        lo = np.clip(np.nextafter(1.0 - res.upper, -np.inf), 0.0, 1.0)
        up = np.clip(np.nextafter(1.0 - res.lower, np.inf), 0.0, 1.0)
        res = ReachabilityResult(lower=lo, upper=up, strategy=res.strategy, iterations=res.iterations,
                                 precision=res.precision, converged=res.converged)
    return _result(res, init)
