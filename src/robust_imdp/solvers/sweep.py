"""Bellman sweeps over the value arrays of a layered model (:class:`Sweeper`): the Python driver of
:func:`robust_imdp.solvers.kernels.bellman_layer` (Jacobi or in place), of its threaded twin, and of the
bucketed sweep of long rows (:func:`robust_imdp.solvers.kernels.bellman_layer_bucketed`, the same bits)."""

from __future__ import annotations

import weakref

import numpy as np
import numba

from robust_imdp.solvers.kernels import (LayerValues, RowArrays, bellman_layer, bellman_layer_bucketed,
                                         bellman_layer_bucketed_parallel, bellman_layer_parallel, dd_prefix,
                                         entry_transpose, rows_sorted)

#: The fewest active states of a layer for which :class:`Sweeper` uses the threaded kernel
#: (benchmarks/parallel_sweep.py).
PAR_MIN_STATES = 16384

#: The least mean number of entries per row for which Jacobi sweeps order the rows by buckets
#: (:func:`robust_imdp.solvers.kernels.bellman_layer_bucketed`) instead of sorting each row by insertion,
#: whose O(k^2) dominates long rows (benchmarks/finite_horizon.py).  Either way the same bits.
BUCKET_MIN_ROW = 32

#: The fewest entries of a model for which the bucketed sweep runs on numba's threads.
PAR_MIN_ENTRIES = 262_144

#: Most blocks of the bucketed sweep (tasks of its threaded form); never more than the entries per state,
#: so the transpose's pointers take at most one number per entry.
BUCKET_BLOCKS = 64

# The transposes of the models swept recently, by ``id(model.col)`` (dropped with that array): a synthesis
# sweeps the same model in several solves.  Built from immutable arrays (IMDP's are read-only).
_TRANSPOSES: dict = {}


def _entry_order(m):
    """(EntryOrder, RowArrays) of IMDP ``m`` for the bucketed sweep, or None where it does not apply (short
    rows, or rows not in increasing successor order without floor rows: their ties follow storage order)."""
    nnz, R = m.col.shape[0], m.row_ptr.shape[0] - 1
    if R == 0 or nnz < BUCKET_MIN_ROW * R:
        return None
    key = id(m.col)
    hit = _TRANSPOSES.get(key)
    if hit is not None and hit[0]() is m.col and hit[1]() is m.row_ptr and hit[2]() is m.state_ptr:
        tr, ok = hit[3], hit[4]
    else:
        ok = rows_sorted(m.row_ptr, m.col)
        n_blocks = int(max(1, min(BUCKET_BLOCKS, m.n_states, nnz // (m.n_states + 1))))
        tr = entry_transpose(m.state_ptr, m.row_ptr, m.col, n_blocks)
        _TRANSPOSES[key] = (weakref.ref(m.col), weakref.ref(m.row_ptr), weakref.ref(m.state_ptr), tr, ok)
        weakref.finalize(m.col, _TRANSPOSES.pop, key, None)
    if not (ok or m.has_floor):
        return None
    return tr, RowArrays(m.state_ptr, m.row_ptr, m.col, m.lower, m.upper, m.floor)


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
        self._bucket = _entry_order(imdp)
        self._sl = None  # the bucketed sweep's entry order (nnz,), allocated on first use

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
        bucket = self._bucket is not None and not gs
        for l in self.layers:
            w = np.ascontiguousarray(self.successor_values(V, l))
            rank, sv, hi, lo = self._dummy_i, self._dummy_f, self._dummy_f, self._dummy_f
            if self.use_rank or bucket:
                # the adversary's order of the successor values (ties: state index) and each state's place
                order = np.argsort(-w if self.adv_max else w, kind="stable")
                rank = np.empty(self.n, dtype=np.int64)
                rank[order] = self._ar
            if self.use_rank:
                sv = w[order]
                hi, lo = dd_prefix(sv)
            strat = self._dummy_i if self.strategy is None else self.strategy[
                strat_layer if strat_layer is not None else 0][l]
            out_rows = rows[l * m.n_choices:(l + 1) * m.n_choices] if want_rows else rows
            if bucket:
                # long rows, Jacobi: every row ordered at once (the same bits as bellman_layer), on
                # numba's threads for large models (bit-identical for any number of threads)
                tr, arrays = self._bucket
                if self._sl is None:
                    self._sl = np.empty(m.col.shape[0], dtype=np.int32)
                args = (arrays, tr, LayerValues(w, order, rank, sv, hi, lo), self.active[l], self.adv_max,
                        self.use_rank, self.ctrl, strat, direction, newV[l], arg[l], out_rows, want_rows, inplace,
                        self._sl)
                if numba.get_num_threads() > 1 and m.col.shape[0] >= PAR_MIN_ENTRIES:
                    bellman_layer_bucketed_parallel(*args, numba.get_num_threads())
                else:
                    bellman_layer_bucketed(*args)
                continue
            # Jacobi sweeps of many states run on numba's threads (bit-identical results);
            # Gauss-Seidel ones (newV is V) stay serial: their order is part of the method
            args = (m.state_ptr, m.row_ptr, m.col, m.lower, m.upper, m.floor, w, self.active[l],
                    self.adv_max, self.use_rank, rank, sv, hi, lo, self.ctrl, strat, direction,
                    newV[l], arg[l], out_rows, want_rows, inplace)
            if not gs and numba.get_num_threads() > 1 and np.count_nonzero(self.active[l]) >= PAR_MIN_STATES:
                bellman_layer_parallel(*args, numba.get_num_threads())
            else:
                bellman_layer(*args)
        return newV, arg, rows


__all__ = ["Sweeper"]
