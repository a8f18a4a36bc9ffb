"""Bellman sweeps over the value arrays of a layered model (:class:`Sweeper`): the Python driver of
:func:`robust_imdp.solvers.kernels.bellman_layer` (Jacobi or in place) and its threaded twin."""

from __future__ import annotations

import numpy as np
import numba

from robust_imdp.solvers.kernels import bellman_layer, bellman_layer_parallel, dd_prefix

#: The fewest active states of a layer for which :class:`Sweeper` uses the threaded kernel
#: (benchmarks/parallel_sweep.py).
PAR_MIN_STATES = 16384


class Sweeper:
    """Bellman sweeps over value arrays ``V`` (L, n) of a layered model (L = 1: plain IMDP).

    Node (l, q) moves under a row of q to (nxt[l, q'], q') -- the lazy product's rule (standard
    semantics, docs/ARCHITECTURE.md "Product semantics") -- so the successor values of layer l
    are the gather ``w_l[q'] = V[nxt[l, q'], q']`` and the base rows are reused unchanged.
    ``ctrl``: a :class:`~robust_imdp.solvers.common.Control` (passed to the kernels as an int).
    """

    def __init__(self, imdp, nxt, active, ctrl, adv_max, strategy):
        self.m = imdp
        self.nxt = np.ascontiguousarray(nxt, dtype=np.int64)
        self.L, self.n = self.nxt.shape
        self.active = active
        self.ctrl = int(ctrl)
        self.adv_max = adv_max
        self.strategy = strategy
        self.use_rank = imdp.has_floor
        self.layers = [l for l in range(self.L) if active[l].any()]
        self._ar = np.arange(self.n)
        self._dummy_i = np.zeros(1, dtype=np.int64)
        self._dummy_f = np.zeros(1)

    def successor_values(self, V, l):
        if self.L == 1:
            return V[0]
        return V[self.nxt[l], self._ar]

    def sweep(self, V, direction, want_rows=False, strat_layer=None, inplace=False):
        """One sweep; ``direction`` -1/+1 keeps the better of old and new bound per node.

        ``inplace`` (unbounded iteration only, never for k-step values) keeps per node the
        better of the old and new bound, and updates ``V`` in place (Gauss-Seidel) when that
        is exact: one layer and no floor rows (the global order and prefix sums of a floor
        model are computed from the values at the start of a sweep).
        """
        m = self.m
        gs = inplace and direction != 0 and self.L == 1 and not self.use_rank
        newV = V if gs else V.copy()
        arg = np.zeros((self.L, self.n), dtype=np.int64)
        rows = np.full(self.L * m.n_choices if want_rows else 1, -np.inf)
        for l in self.layers:
            w = np.ascontiguousarray(self.successor_values(V, l))
            if self.use_rank:
                order = np.argsort(-w if self.adv_max else w, kind="stable")
                rank = np.empty(self.n, dtype=np.int64)
                rank[order] = self._ar
                sv = w[order]
                hi, lo = dd_prefix(sv)
            else:
                rank, sv, hi, lo = self._dummy_i, self._dummy_f, self._dummy_f, self._dummy_f
            strat = self._dummy_i if self.strategy is None else self.strategy[
                strat_layer if strat_layer is not None else 0][l]
            out_rows = rows[l * m.n_choices:(l + 1) * m.n_choices] if want_rows else rows
            # Jacobi sweeps of many states run on numba's threads (bit-identical results);
            # Gauss-Seidel ones (newV is V) stay serial: their order is part of the method
            kernel = bellman_layer
            if not gs and numba.get_num_threads() > 1 and np.count_nonzero(self.active[l]) >= PAR_MIN_STATES:
                kernel = bellman_layer_parallel
            kernel(m.state_ptr, m.row_ptr, m.col, m.lower, m.upper, m.floor, w, self.active[l],
                   self.adv_max, self.use_rank, rank, sv, hi, lo, self.ctrl, strat, direction,
                   newV[l], arg[l], out_rows, want_rows, inplace)
        return newV, arg, rows


__all__ = ["Sweeper"]
