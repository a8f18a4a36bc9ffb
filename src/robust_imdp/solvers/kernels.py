"""Numba kernels of the interval Bellman operator: one row's optimal ``p.w`` (:func:`row_value`,
:func:`row_value_cached`), sweeps over a layer (:func:`bellman_layer`, Jacobi or in place) and over
a node list (:func:`node_sweep`, Gauss-Seidel), and the per-component optimistic value iteration
of the default engine (:func:`ovi_component`, :func:`solve_components`).  Why the results are
sound: :mod:`robust_imdp.solvers.engine`.

numba caches each kernel per source file, keyed by that file alone: a kernel here calls only
kernels of this file (``solvers/graph.py`` has its own copy of :func:`_rows`) and the intrinsic
``_atomic.fetch_add``, compiled into the caller (an edit of ``_atomic.py`` needs the cache emptied, as
the Makefile does on any source change; ``robust_imdp.warmup``).  The integer constants read by the kernels
(:class:`robust_imdp.solvers.common.Control`) are frozen into the compiled code; their values
never change.

Hot loop: numba (``@njit(cache=True)``), serial; the kernels called from Python release the GIL
(``nogil=True``: another thread of the process, e.g. the side lane's dispatch, runs meanwhile).  A
numpy formulation needs a per-row sort (``np.lexsort`` over all nnz entries each iteration) and
several nnz-sized temporaries.  The
default engine's sweep (:func:`node_sweep`) keeps each row's order of successor values from the
previous sweep (1 byte per entry) and re-sorts by insertion, which costs O(k) once the order has
settled, and prefetches the successor values of the entries ``PREFETCH_DISTANCE`` ahead (the
gathers of a large model miss the caches); ``benchmarks/results/solver.md`` has the numbers.  Jacobi
sweeps of long rows (k-step values, strategy extraction, floor models) order all rows at once by buckets
(:func:`bellman_layer_bucketed`, section "sweeps of long rows"): O(nnz) per sweep instead of the
insertion sort's O(k^2) per row, the same bits; ``benchmarks/results/finite_horizon.md``.

Rounding-error bound of one row (ROW_ERR)
-----------------------------------------
The same bound rounds lower results down and upper results up.  All
quantities are in [0, 1] (probabilities, values, partial sums), so each rounded operation
errs by at most u = 2**-53 in absolute value.  Per row with k listed entries: the base sum
``sum(lower*w)`` costs 2k operations; ``rem = 1 - sum(lower)`` k; every greedy step (capacity,
min, rem update, accumulate) 4; every floor block (double-double prefix difference, product,
rem update) at most 8 plus the relative error of the double-double sums (< 4u of the block
mass, whose total is <= 1).  The greedy allocation is 1-Lipschitz (in l1) in ``rem`` and the
capacities, so perturbing them moves ``p.w`` by at most the l1 size of the perturbation.
Summing, the error is below (2k + k + 4k + 8(k+1) + 4) u <= (15k + 12) u; we use
``ROW_ERR(k) = (16 k + 64) u``, a safety margin above the derivation."""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from llvmlite import ir
import numba
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from robust_imdp._atomic import fetch_add
from robust_imdp._fp import U
from robust_imdp.solvers.common import Control

# controller codes of the kernels (plain ints: compiled as constants)
_MAX = int(Control.MAXIMISE)
_MIN = int(Control.MINIMISE)
_FIXED = int(Control.FIXED)


@njit(cache=True, inline="always")
def row_err(k):
    return (16.0 * k + 64.0) * U


@njit(cache=True)
def dd_prefix(sv):
    """Double-double prefix sums of ``sv``: ``hi[i] + lo[i] ~= sum(sv[:i])`` (TwoSum, Knuth)."""
    n = sv.shape[0]
    hi = np.empty(n + 1)
    lo = np.empty(n + 1)
    s = 0.0
    c = 0.0
    hi[0] = 0.0
    lo[0] = 0.0
    for i in range(n):
        x = sv[i]
        t = s + x
        bp = t - s
        err = (s - (t - bp)) + (x - bp)
        s = t
        c += err
        hi[i + 1] = s
        lo[i + 1] = c
    return hi, lo


@njit(cache=True, inline="always")
def _block(hi, lo, a, b):
    """sum(sv[a:b]) from the double-double prefix sums."""
    return (hi[b] - hi[a]) + (lo[b] - lo[a])


@njit(cache=True, inline="always")
def _fill_floors(val, rem, f, cnt, pos, hi, lo, sv):
    """``val`` plus the value of the mass ``rem`` (<= ``cnt f``) put on the unlisted states
    ``sv[pos:pos + cnt]`` (adversary order) at most ``f`` each: ``kf`` whole floors, then a part."""
    kf = int(rem / f)
    if kf > cnt:
        kf = cnt
    part = rem - kf * f
    if part < 0.0:
        part = 0.0
    if part > f:
        part = f
    val += f * _block(hi, lo, pos, pos + kf)
    if kf < cnt:
        val += part * sv[pos + kf]
    return val


@njit(cache=True)
def row_value(j0, j1, col, lower, upper, f, w, use_rank, rank, sv, hi, lo, adv_max, keys, idx):
    """Optimal ``p.w`` of one row for the adversary; returns (value, mass left unassigned).

    ``use_rank``: order the listed entries by ``rank`` (global adversary order), needed when
    the row has floor mass; otherwise by ``w`` directly.  ``keys``/``idx``: scratch buffers.
    """
    n = w.shape[0]
    val = 0.0
    rem = 1.0
    m = 0
    floor_row = use_rank and f > 0.0 and (j1 - j0) < n
    for j in range(j0, j1):
        q = col[j]
        val += lower[j] * w[q]
        rem -= lower[j]
        if floor_row or upper[j] > lower[j]:
            if use_rank:
                kk = float(rank[q])
            elif adv_max:
                kk = -w[q]
            else:
                kk = w[q]
            # insertion sort by key (k is ~20: cheaper than a general sort)
            i = m
            while i > 0 and keys[i - 1] > kk:
                keys[i] = keys[i - 1]
                idx[i] = idx[i - 1]
                i -= 1
            keys[i] = kk
            idx[i] = j
            m += 1
    if rem <= 0.0:
        return val, 0.0  # sum(lower) >= 1 (within the model tolerance): p = lower
    return _fill_in_order(val, rem, idx, 0, 0, m, col, lower, upper, f, w, floor_row, rank, sv, hi, lo)


@njit(cache=True, inline="always")
def _fill_in_order(val, rem, order, off, base, m, col, lower, upper, f, w, floor_row, rank, sv, hi, lo):
    """The greedy part of :func:`row_value` and :func:`row_value_sorted`: the mass ``rem`` left above the
    lower bounds given to the row's entries in adversary order (entry ``base + order[off + t]`` t-th, ``m``
    entries), with the floor mass of unlisted states between them on a floor row; returns (value, mass left)."""
    n = w.shape[0]
    pos = 0
    for t in range(m):
        j = base + order[off + t]
        if floor_row:
            p = rank[col[j]]
            cnt = p - pos
            if cnt > 0:
                mass = cnt * f
                if mass >= rem:
                    return _fill_floors(val, rem, f, cnt, pos, hi, lo, sv), 0.0
                val += f * _block(hi, lo, pos, p)
                rem -= mass
            pos = p + 1
        # entries with upper == lower (which row_value leaves out of its order) have cap 0: no-op
        cap = upper[j] - lower[j]
        if cap > 0.0:
            if cap >= rem:
                val += rem * w[col[j]]
                return val, 0.0
            val += cap * w[col[j]]
            rem -= cap
    if floor_row and pos < n:
        cnt = n - pos
        mass = cnt * f
        if mass >= rem:
            return _fill_floors(val, rem, f, cnt, pos, hi, lo, sv), 0.0
        val += f * _block(hi, lo, pos, n)
        rem -= mass
    return val, rem


@njit(cache=True, inline="always")
def _round_row(v, left, k, direction):
    """One row's value ``v`` (mass ``left`` unassigned) rounded by its error bound ``ROW_ERR(k)`` in
    ``direction`` (-1 down, +1 up, 0 plain) and clamped to [0, 1]."""
    if direction < 0:
        v = v - row_err(k)
        if v < 0.0:
            v = 0.0  # safe: every true value is >= 0
    elif direction > 0:
        # mass left unassigned (a row whose upper sum is below 1 within the model
        # tolerance) is credited with the largest possible value 1: stays an upper bound
        v = v + row_err(k) + left
        if v > 1.0:
            v = 1.0  # safe: every true value is <= 1
    return v


@njit(cache=True, inline="always")
def _store_state(q, best, barg, out_val, out_arg, direction, keep_better):
    """Write state q's best row value and its row: unbounded iteration (keep_better) keeps the better of
    the old bound (in out_val) and the new one, both sound for the same value; with out_val aliasing w
    this is a sound Gauss-Seidel sweep.  Never for k-step values (the old bound is for k-1 steps)."""
    if keep_better and direction < 0:
        if best > out_val[q]:
            out_val[q] = best
    elif keep_better and direction > 0:
        if best < out_val[q]:
            out_val[q] = best
    else:
        out_val[q] = best
    out_arg[q] = barg


@njit(cache=True, inline="always")
def _bellman_state(q, state_ptr, row_ptr, col, lower, upper, floor, w, adv_max, use_rank, rank, sv, hi, lo, ctrl,
                   strat, direction, out_val, out_arg, out_rows, want_rows, keep_better, keys, idx):
    """The update of one state q by :func:`bellman_layer` (writes only index q of the outputs and
    the entries of q's rows in ``out_rows``)."""
    r0, r1 = _rows(state_ptr, q, ctrl, strat, q)
    best = -1.0
    barg = 0
    for r in range(r0, r1):
        j0 = row_ptr[r]
        j1 = row_ptr[r + 1]
        v, left = row_value(j0, j1, col, lower, upper, floor[r], w, use_rank, rank, sv, hi, lo,
                            adv_max, keys, idx)
        v = _round_row(v, left, j1 - j0, direction)
        if want_rows:
            out_rows[r] = v
        if best < 0.0 or (ctrl == _MAX and v > best) or (ctrl == _MIN and v < best):
            best = v
            barg = r - state_ptr[q]
    _store_state(q, best, barg, out_val, out_arg, direction, keep_better)


@njit(cache=True)
def _max_row_len(row_ptr):
    maxk = 1
    for r in range(row_ptr.shape[0] - 1):
        if row_ptr[r + 1] - row_ptr[r] > maxk:
            maxk = row_ptr[r + 1] - row_ptr[r]
    return maxk


@njit(cache=True, nogil=True)
def bellman_layer(state_ptr, row_ptr, col, lower, upper, floor, w, active, adv_max, use_rank,
                  rank, sv, hi, lo, ctrl, strat, direction, out_val, out_arg, out_rows, want_rows, keep_better):
    """One Bellman update of the states with ``active[q]``.

    ctrl (:class:`~robust_imdp.solvers.common.Control`): maximise over rows, minimise, or the
    fixed row ``strat[q]``.
    direction: -1 round down (sound lower), +1 round up (sound upper), 0 plain.
    Writes ``out_val[q]`` (rounded, clamped to [0, 1]) and ``out_arg[q]`` (row index within q);
    with ``want_rows`` also every evaluated row's rounded value into ``out_rows``.
    """
    n = state_ptr.shape[0] - 1
    maxk = _max_row_len(row_ptr)
    keys = np.empty(maxk)
    idx = np.empty(maxk, dtype=np.int64)
    for q in range(n):
        if active[q]:
            _bellman_state(q, state_ptr, row_ptr, col, lower, upper, floor, w, adv_max, use_rank, rank, sv, hi, lo,
                           ctrl, strat, direction, out_val, out_arg, out_rows, want_rows, keep_better, keys, idx)


#: States per parallel task of :func:`bellman_layer_parallel` (the fewest active states of a
#: layer for which ``sweep.Sweeper`` uses it is ``sweep.PAR_MIN_STATES``). Every thread takes the next
#: block from a shared counter (``_atomic.fetch_add``) as it comes free: the active states are bunched,
#: and numba's ``prange`` splits statically on the "omp" layer (``_atomic``'s note).
PAR_BLOCK = 1024


@njit(cache=True, parallel=True, nogil=True)
def bellman_layer_parallel(state_ptr, row_ptr, col, lower, upper, floor, w, active, adv_max, use_rank,
                           rank, sv, hi, lo, ctrl, strat, direction, out_val, out_arg, out_rows, want_rows,
                           keep_better, lanes=1):
    """:func:`bellman_layer` on numba's threads (blocks of ``PAR_BLOCK`` states).  Only for Jacobi
    sweeps (``out_val`` is not ``w``): every state's update reads ``w`` and writes its own outputs,
    so the result is the serial one, bit for bit, for any number of threads. ``lanes``: the threads
    (the caller's ``numba.get_num_threads()``; read in a kernel it would keep numba from caching it)."""
    n = state_ptr.shape[0] - 1
    maxk = _max_row_len(row_ptr)
    n_blocks = (n + PAR_BLOCK - 1) // PAR_BLOCK
    lanes = max(1, min(lanes, n_blocks))
    taken = np.zeros(1, dtype=np.int64)  # blocks handed out (PAR_BLOCK's note); never read after the loop
    for t in numba.prange(lanes):
        keys = np.empty(maxk)
        idx = np.empty(maxk, dtype=np.int64)
        while True:
            b = fetch_add(taken, 0, 1)
            if b >= n_blocks:
                break
            for q in range(b * PAR_BLOCK, min(n, (b + 1) * PAR_BLOCK)):
                if active[q]:
                    _bellman_state(q, state_ptr, row_ptr, col, lower, upper, floor, w, adv_max, use_rank, rank, sv,
                                   hi, lo, ctrl, strat, direction, out_val, out_arg, out_rows, want_rows, keep_better,
                                   keys, idx)


# =========================================================================== sweeps of long rows
# A row's greedy allocation visits its entries in the adversary's order of the successor values.
# row_value sorts them by insertion: O(k^2) per row, which dominates rows of hundreds of entries
# (exact Gaussian rows: 300-400).  The bucketed sweep instead orders every row at once: the states
# are sorted once per sweep (the global order of ``Sweeper``), and walking them in that order
# through a transpose of the rows (the entries of each state, per block of rows) appends every
# entry to its row's list: O(nnz) per sweep, no comparison.  The order is the one row_value sorts
# into -- by rank (unique) with floor rows, by the value with ties in storage order otherwise,
# which is the global order's tie order (state index) when every row lists its states in
# increasing order (``Sweeper`` checks it) -- and the arithmetic is row_value's, so the values
# are the same bits.

#: The transpose of a model's rows for the bucketed sweep (:func:`entry_transpose`): states in
#: blocks ``bstate[b] .. bstate[b+1]`` (about equal numbers of entries); block b's entries with
#: successor q are ``ptr[b*(n+1) + q] .. ptr[b*(n+1) + q + 1]`` of ``row`` (their rows) and ``loc``
#: (their indices within the row), in storage order.
EntryOrder = namedtuple("EntryOrder", ["bstate", "ptr", "row", "loc"])

#: The model's rows as the bucketed sweep reads them.
RowArrays = namedtuple("RowArrays", ["state_ptr", "row_ptr", "col", "lower", "upper", "floor"])

#: The successor values of one layer and their order: ``w`` (n,), ``order`` (states in adversary
#: order), and for floor rows ``rank`` (position of every state in ``order``), ``sv = w[order]`` and
#: its double-double prefix sums ``hi``/``lo`` (:func:`dd_prefix`).
LayerValues = namedtuple("LayerValues", ["w", "order", "rank", "sv", "hi", "lo"])


@njit(cache=True, nogil=True)
def entry_transpose(state_ptr, row_ptr, col, n_blocks):
    """:class:`EntryOrder` of a model: its states cut into ``n_blocks`` blocks of about equal numbers of
    entries, and per block a counting sort of its entries by successor (stable: storage order)."""
    n = state_ptr.shape[0] - 1
    nnz = col.shape[0]
    bstate = np.empty(n_blocks + 1, dtype=np.int64)
    bstate[0] = 0
    s = 0
    for b in range(1, n_blocks):
        goal = (nnz * b) // n_blocks
        while s < n and row_ptr[state_ptr[s]] < goal:
            s += 1
        bstate[b] = s
    bstate[n_blocks] = n
    ptr = np.zeros(n_blocks * (n + 1) + 1, dtype=np.int64)
    row = np.empty(nnz, dtype=np.int32)
    loc = np.empty(nnz, dtype=np.int32)
    for b in range(n_blocks):
        base = b * (n + 1)
        e0 = row_ptr[state_ptr[bstate[b]]]
        e1 = row_ptr[state_ptr[bstate[b + 1]]]
        for j in range(e0, e1):
            ptr[base + col[j] + 1] += 1
        ptr[base] = e0
        for q in range(n):
            ptr[base + q + 1] += ptr[base + q]
        fill = ptr[base:base + n].copy()
        for r in range(state_ptr[bstate[b]], state_ptr[bstate[b + 1]]):
            for j in range(row_ptr[r], row_ptr[r + 1]):
                c = col[j]
                row[fill[c]] = r
                loc[fill[c]] = j - row_ptr[r]
                fill[c] += 1
    return EntryOrder(bstate, ptr, row, loc)


@njit(cache=True)
def rows_sorted(row_ptr, col):
    """Whether every row lists its successors in increasing order."""
    for r in range(row_ptr.shape[0] - 1):
        for j in range(row_ptr[r] + 1, row_ptr[r + 1]):
            if col[j] <= col[j - 1]:
                return False
    return True


@njit(cache=True, inline="always")
def row_value_sorted(j0, j1, sl, col, lower, upper, f, vals, use_rank, adv_max):
    """:func:`row_value` (same operations in the same order, hence the same bits and the same
    ``ROW_ERR``) of a row whose entries come in adversary order: entry ``j0 + sl[j0 + t]`` t-th."""
    w = vals.w
    n = w.shape[0]
    val = 0.0
    rem = 1.0
    floor_row = use_rank and f > 0.0 and (j1 - j0) < n
    for j in range(j0, j1):
        lj = lower[j]
        val += lj * w[col[j]]
        rem -= lj
    if rem <= 0.0:
        return val, 0.0  # sum(lower) >= 1 (within the model tolerance): p = lower
    return _fill_in_order(val, rem, sl, j0, j0, j1 - j0, col, lower, upper, f, w, floor_row, vals.rank, vals.sv,
                          vals.hi, vals.lo)


#: The bucketed sweep sorts the evaluated entries of a block by counting instead of walking the block's
#: transpose when they are fewer than this fraction of the block's entries (a fixed strategy: 1 row in a
#: state's several).
BUCKET_SPARSE = 3


@njit(cache=True, inline="always")
def _bucketed_block(b, m, tr, vals, active, adv_max, use_rank, ctrl, strat, direction, out_val, out_arg, out_rows,
                    want_rows, keep_better, sl):
    """Block b of :func:`bellman_layer_bucketed`: order the entries of its evaluated rows (into ``sl``, at
    the rows' own positions), then update its active states."""
    state_ptr, row_ptr = m.state_ptr, m.row_ptr
    s0 = tr.bstate[b]
    s1 = tr.bstate[b + 1]
    rb0 = state_ptr[s0]
    nr = state_ptr[s1] - rb0
    if nr == 0:
        return
    cursor = np.full(nr, -1, dtype=np.int64)  # -1: row not evaluated
    n_eval = 0
    for q in range(s0, s1):
        if active[q]:
            r0, r1 = _rows(state_ptr, q, ctrl, strat, q)
            for r in range(r0, r1):
                cursor[r - rb0] = 0
                n_eval += row_ptr[r + 1] - row_ptr[r]
    order = vals.order
    n = order.shape[0]
    if BUCKET_SPARSE * n_eval < row_ptr[state_ptr[s1]] - row_ptr[rb0]:
        # few rows evaluated (a fixed strategy's): a counting sort of their entries by rank, then
        # each entry appended to its row, instead of walking every entry of the block
        rank = vals.rank
        start = np.zeros(n + 1, dtype=np.int64)
        for q in range(s0, s1):
            if active[q]:
                r0, r1 = _rows(state_ptr, q, ctrl, strat, q)
                for j in range(row_ptr[r0], row_ptr[r1]):
                    start[rank[m.col[j]] + 1] += 1
        for k in range(n):
            start[k + 1] += start[k]
        by_rank = np.empty(n_eval, dtype=np.int64)  # (row - rb0) << 32 | index within the row
        for q in range(s0, s1):
            if active[q]:
                r0, r1 = _rows(state_ptr, q, ctrl, strat, q)
                for r in range(r0, r1):
                    for j in range(row_ptr[r], row_ptr[r + 1]):
                        k = rank[m.col[j]]
                        by_rank[start[k]] = ((r - rb0) << 32) | (j - row_ptr[r])
                        start[k] += 1
        for t in range(n_eval):
            i = by_rank[t] >> 32
            sl[row_ptr[rb0 + i] + cursor[i]] = by_rank[t] & 0xFFFFFFFF
            cursor[i] += 1
    else:
        base = b * (n + 1)
        for t in range(n):
            q2 = order[t]
            for e in range(tr.ptr[base + q2], tr.ptr[base + q2 + 1]):
                i = tr.row[e] - rb0
                c = cursor[i]
                if c >= 0:
                    sl[row_ptr[rb0 + i] + c] = tr.loc[e]
                    cursor[i] = c + 1
    for q in range(s0, s1):
        if not active[q]:
            continue
        r0, r1 = _rows(state_ptr, q, ctrl, strat, q)
        best = -1.0
        barg = 0
        for r in range(r0, r1):
            j0 = row_ptr[r]
            j1 = row_ptr[r + 1]
            v, left = row_value_sorted(j0, j1, sl, m.col, m.lower, m.upper, m.floor[r], vals, use_rank, adv_max)
            v = _round_row(v, left, j1 - j0, direction)
            if want_rows:
                out_rows[r] = v
            if best < 0.0 or (ctrl == _MAX and v > best) or (ctrl == _MIN and v < best):
                best = v
                barg = r - state_ptr[q]
        _store_state(q, best, barg, out_val, out_arg, direction, keep_better)


@njit(cache=True, nogil=True)
def bellman_layer_bucketed(m, tr, vals, active, adv_max, use_rank, ctrl, strat, direction, out_val, out_arg, out_rows,
                           want_rows, keep_better, sl):
    """:func:`bellman_layer` (same outputs, bit for bit) for a Jacobi sweep (``out_val`` is not ``vals.w``)
    with the entries ordered by buckets (section comment above): ``m`` :class:`RowArrays`, ``tr``
    :class:`EntryOrder`, ``vals`` :class:`LayerValues`, ``sl`` (nnz,) int32 scratch."""
    for b in range(tr.bstate.shape[0] - 1):
        _bucketed_block(b, m, tr, vals, active, adv_max, use_rank, ctrl, strat, direction, out_val, out_arg,
                        out_rows, want_rows, keep_better, sl)


@njit(cache=True, parallel=True, nogil=True)
def bellman_layer_bucketed_parallel(m, tr, vals, active, adv_max, use_rank, ctrl, strat, direction, out_val, out_arg,
                                    out_rows, want_rows, keep_better, sl, lanes=1):
    """:func:`bellman_layer_bucketed` on numba's threads, one block of states per task: a block reads
    ``vals`` and writes only its own states, rows and entries, so the result is the serial one, bit for
    bit, for any number of threads (``lanes``, as in :func:`bellman_layer_parallel`), each taking the next
    block as it comes free."""
    n_blocks = tr.bstate.shape[0] - 1
    lanes = max(1, min(lanes, n_blocks))
    taken = np.zeros(1, dtype=np.int64)  # blocks handed out as lanes come free; never read after the loop
    for t in numba.prange(lanes):
        while True:
            b = fetch_add(taken, 0, 1)
            if b >= n_blocks:
                break
            _bucketed_block(b, m, tr, vals, active, adv_max, use_rank, ctrl, strat, direction, out_val, out_arg,
                            out_rows, want_rows, keep_better, sl)


@njit(cache=True, inline="always")
def _rows(state_ptr, q, ctrl, strat, k):
    """Row range of state q: all its rows, or (ctrl FIXED) the fixed strategy's row ``strat[k]``."""
    if ctrl == _FIXED:
        r0 = state_ptr[q] + strat[k]
        return r0, r0 + 1
    return state_ptr[q], state_ptr[q + 1]



# =========================================================================== topological OVI kernels
def _prefetch_name():
    """The mangled name of LLVM's prefetch intrinsic for this llvmlite (typed or opaque pointers)."""
    return "llvm.prefetch.p0" if str(ir.IntType(8).as_pointer()) == "ptr" else "llvm.prefetch.p0i8"


@intrinsic
def prefetch(typingctx, arr, i):
    """Hint the CPU to fetch ``arr[i]`` (1-D array) into the cache; no effect on results.  The
    successor values of a large model are gathered at random: fetching those of an entry
    ``PREFETCH_DISTANCE`` entries ahead hides the memory latency (3x on 1M states)."""
    sig = types.void(arr, i)

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]], wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                            _prefetch_name())
        # read access, high temporal locality, data cache
        builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()
    return sig, codegen


#: Entries ahead whose successor value is prefetched (about three rows of 20).
PREFETCH_DISTANCE = 64

#: Sweep modes of :func:`node_sweep`: lower sweep ``V = max(V, B_down(V))``; check of an upper
#: guess ``V = B_up(V)``; upper sweep ``V = min(V, B_up(V))``; check of a lower guess ``V = B_down(V)``.
SWEEP_LOWER, SWEEP_CHECK_UPPER, SWEEP_UPPER, SWEEP_CHECK_LOWER = 0, 1, 2, 3


# The default unbounded engine (``method="vi"``, models without floor rows): strongly connected
# components in reverse topological order, Gauss-Seidel sweeps over a node list, and per
# component optimistic value iteration (guess an upper vector from the lower one and prove it
# with one Bellman sweep), falling back to interval iteration.  Soundness: the docstring of
# robust_imdp.solvers.engine, "Lemma OVI" and "Topological order".

@njit(cache=True, inline="always")
def row_value_cached(j0, j1, po, col, lower, upper, V, nxt, l, n, layered, adv_max, perm, keys, idx):
    """Optimal ``p.V`` of one row without floor mass; returns (value, mass left unassigned).

    Same operations as :func:`row_value` (so ``ROW_ERR`` bounds its rounding), but the entries are
    visited in the order of the previous sweep, ``perm[po + t]`` (local indices), and re-sorted by
    insertion: O(k) compares with predictable branches while the order of the successor values
    does not change, which is the usual case once the iteration settles.  The new order is
    written back.  ``V`` is the flat (L*n,) value vector; with ``layered`` the successor of
    entry j is node ``nxt[l * n + col[j]] * n + col[j]`` (``nxt`` flat (L*n,)).
    """
    k = j1 - j0
    nnz = col.shape[0]
    val = 0.0
    rem = 1.0
    moved = False
    for t in range(k):
        jp = j0 + t + PREFETCH_DISTANCE
        if jp < nnz:
            qp = col[jp]
            if layered:
                if jp + PREFETCH_DISTANCE < nnz:
                    prefetch(nxt, l * n + col[jp + PREFETCH_DISTANCE])
                prefetch(V, nxt[l * n + qp] * n + qp)
            else:
                prefetch(V, qp)
        li = perm[po + t]
        j = j0 + li
        q2 = col[j]
        if layered:
            x = V[nxt[l * n + q2] * n + q2]
        else:
            x = V[q2]
        lj = lower[j]
        val += lj * x
        rem -= lj
        kk = -x if adv_max else x
        i = t
        while i > 0 and keys[i - 1] > kk:
            keys[i] = keys[i - 1]
            idx[i] = idx[i - 1]
            i -= 1
        keys[i] = kk
        idx[i] = li
        if i != t:
            moved = True
    if moved:  # write the order back only when it changed (no store traffic in the steady state)
        for t in range(k):
            perm[po + t] = idx[t]
    if rem <= 0.0:
        return val, 0.0  # sum(lower) >= 1 (within the model tolerance): p = lower
    for t in range(k):
        j = j0 + idx[t]
        cap = upper[j] - lower[j]
        if cap > 0.0:
            x = -keys[t] if adv_max else keys[t]
            if cap >= rem:
                return val + rem * x, 0.0
            val += cap * x
            rem -= cap
    return val, rem


@njit(cache=True)
def fill_local_order(row_ptr, perm, L):
    """``perm[l * nnz + j] = j - row_ptr[r]`` (storage order) for every layer l and entry j of row r."""
    R = row_ptr.shape[0] - 1
    nnz = row_ptr[R]
    for l in range(L):
        for r in range(R):
            for j in range(row_ptr[r], row_ptr[r + 1]):
                perm[l * nnz + j] = j - row_ptr[r]


@njit(cache=True)
def node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, V, other, ctrl, strat, adv_max,
               mode, perm, keys, idx, incr):
    """One Gauss-Seidel sweep over ``nodes`` (in that order), updating the flat vector ``V`` in place.

    mode SWEEP_LOWER: ``V[s] = max(V[s], B_down(V)(s))``, and ``incr[t]`` = the increase of
    ``nodes[t]`` when ``incr`` is not empty; SWEEP_CHECK_UPPER: ``V[s] = B_up(V)(s)``;
    SWEEP_UPPER: ``V[s] = min(V[s], B_up(V)(s))``; SWEEP_CHECK_LOWER: ``V[s] = B_down(V)(s)``.
    ctrl (:class:`~robust_imdp.solvers.common.Control`): maximise over rows, minimise, or the
    fixed row ``strat[node]``.
    Returns (largest increase, largest decrease, crossed): ``crossed`` says that in SWEEP_CHECK_UPPER some
    ``B_up(V)(s) < other[s]`` (a proven lower bound; then V was not an upper bound, since V >= V*
    gives B(V) >= V*), or in SWEEP_CHECK_LOWER some ``B_down(V)(s) > other[s]`` (a proven upper bound).
    """
    nnz = col.shape[0]
    rec = incr.shape[0] > 0
    inc = 0.0
    dec = 0.0
    crossed = False
    for t in range(nodes.shape[0]):
        node = nodes[t]
        l = node // n
        q = node - l * n
        r0 = state_ptr[q]
        r1 = state_ptr[q + 1]
        if ctrl == _FIXED:
            r0 = r0 + strat[node]
            r1 = r0 + 1
        best = -1.0
        for r in range(r0, r1):
            j0 = row_ptr[r]
            j1 = row_ptr[r + 1]
            v, left = row_value_cached(j0, j1, l * nnz + j0, col, lower, upper, V, nxt, l, n, layered, adv_max,
                                       perm, keys, idx)
            if mode == SWEEP_LOWER or mode == SWEEP_CHECK_LOWER:
                v = v - row_err(j1 - j0)
                if v < 0.0:
                    v = 0.0  # safe: every true value is >= 0
            else:
                # mass left unassigned (upper sum below 1 within the model tolerance) is credited
                # with the largest possible value 1: stays an upper bound
                v = v + row_err(j1 - j0) + left
                if v > 1.0:
                    v = 1.0  # safe: every true value is <= 1
            if best < 0.0 or (ctrl == _MAX and v > best) or (ctrl == _MIN and v < best):
                best = v
        old = V[node]
        if mode == SWEEP_LOWER:
            d = best - old
            if d > 0.0:
                V[node] = best
                if d > inc:
                    inc = d
            else:
                d = 0.0
            if rec:
                incr[t] = d
        elif mode == SWEEP_UPPER:
            if best < old:
                V[node] = best
                if old - best > dec:
                    dec = old - best
        else:
            if best > old:
                if best - old > inc:
                    inc = best - old
            elif old - best > dec:
                dec = old - best
            V[node] = best
            if (mode == SWEEP_CHECK_UPPER and best < other[node]) or (mode == SWEEP_CHECK_LOWER and best > other[node]):
                crossed = True
    return inc, dec, crossed


@njit(cache=True)
def _max_gap(nodes, lo, up):
    g = 0.0
    for t in range(nodes.shape[0]):
        d = up[nodes[t]] - lo[nodes[t]]
        if d > g:
            g = d
    return g


@njit(cache=True)
def _exit_gap(nodes, c, comp, n, state_ptr, row_ptr, col, upper, nxt, layered, ctrl, strat, lo, up):
    """Largest bracket width ``up - lo`` of a possible successor outside component ``c``."""
    g = 0.0
    for t in range(nodes.shape[0]):
        node = nodes[t]
        l = node // n
        q = node - l * n
        r0, r1 = _rows(state_ptr, q, ctrl, strat, node)
        for j in range(row_ptr[r0], row_ptr[r1]):
            if upper[j] <= 0.0:
                continue
            q2 = col[j]
            s2 = nxt[l * n + q2] * n + q2 if layered else q2
            if comp[s2] != c:
                d = up[s2] - lo[s2]
                if d > g:
                    g = d
    return g


#: How a component was solved (``solve_components``' ``comp_status``): one node without a
#: self-loop (exact in one step); proven by guesses without / with a successful extrapolated
#: one; by interval iteration; not within ``max_iterations``; holds an end component (interval
#: iteration with deflation).
ST_EXACT, ST_PLAIN, ST_EXTRAP, ST_INTERVAL, ST_OPEN, ST_DEFLATED = 0, 1, 2, 3, 4, 5

#: Kinds of component (``solve_components``' ``kind``): one node without a self-loop; a component
#: solved by :func:`ovi_component`; one that holds an end component (left to the caller).
KIND_SINGLE, KIND_OVI, KIND_END_COMPONENT = 0, 1, 2

#: Indices of the optimistic value iteration parameters (``robust_imdp.solvers.ovi.OVI_PARAMS``):
#: sweeps per check of a plain guess; refuted plain guesses before the component falls back to
#: interval iteration; sweeps per check of an extrapolated guess; extrapolated guesses tried per
#: component; KAPPA of their offsets; lower sweeps between two extrapolated guesses; the shift of
#: every guess toward the other bound (tests only).
P_VERIFY_SWEEPS, P_MAX_FAILS, P_EXTRAP_SWEEPS, P_MAX_EXTRAP, P_KAPPA, P_EXTRAP_EVERY, P_SHIFT = range(7)


@njit(cache=True)
def _check_guess(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, V, other, ctrl, strat, adv_max,
                 mode, perm, keys, idx, n_sweeps):
    """Check sweeps of a guess in ``V`` (mode SWEEP_CHECK_UPPER or SWEEP_CHECK_LOWER); True when one of at most
    ``n_sweeps`` sweeps moved no value in the wrong direction (then V is proven), False when
    refuted (crossed the other bound) or undecided.  Returns (proven, sweeps)."""
    none = np.empty(0)
    for k in range(n_sweeps):
        inc, dec, crossed = node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, V, other, ctrl,
                                       strat, adv_max, mode, perm, keys, idx, none)
        if crossed:
            return False, k + 1
        if (mode == SWEEP_CHECK_UPPER and inc <= 0.0) or (mode == SWEEP_CHECK_LOWER and dec <= 0.0):
            return True, k + 1
    return False, n_sweeps


@njit(cache=True)
def ovi_aim(dgap, prec, kappa):
    """Targets of one optimistic value iteration whose successors outside have brackets of width
    <= ``dgap``: (target width, margin, plain-guess offset delta, error tolerance of a plain
    guess, offset unit of an extrapolated guess)."""
    if dgap < prec:
        target = prec
        margin = prec - dgap
    else:  # the successors' brackets are already wider than prec: aim a little above them
        target = dgap + 0.5 * prec
        margin = 0.5 * prec
    delta = dgap + 0.5 * margin
    tol = 0.125 * margin
    off = 0.4 * margin / (1.0 + kappa)  # extrapolated bracket: dgap + 2 off (1 + kappa) <= target
    return target, margin, delta, tol, off


@njit(cache=True, inline="always")
def _contraction(r, prev, k):
    """(lam, est): the contraction factor of the lower iterates from the last two residuals, and
    the estimated error ``r lam / (1 - lam)`` of the lower vector (inf while unknown)."""
    lam = 1.0
    est = np.inf
    if r <= 0.0:
        est = 0.0
    elif k >= 2 and r < prev:
        lam = r / prev
        est = r * lam / (1.0 - lam)
    return lam, est


@njit(cache=True)
def _plain_guess(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl, strat, adv_max, lo, up,
                 perm, keys, idx, saved, delta, shift, n_sweeps):
    """The upper guess ``min(proven, lo + delta)``, checked by at most ``n_sweeps`` sweeps; kept
    (as its minimum with the proven vector ``saved``) when proven, else ``up`` goes back to
    ``saved``.  Returns (proven, sweeps)."""
    m = nodes.shape[0]
    for t in range(m):
        g = lo[nodes[t]] + delta - shift
        up[nodes[t]] = g if g < saved[t] else saved[t]
    ok, s = _check_guess(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, up, lo, ctrl, strat,
                         adv_max, SWEEP_CHECK_UPPER, perm, keys, idx, n_sweeps)
    if ok:
        # proven: B(u) <= u on the component (the outside is final), so u >= V*; the
        # minimum with the previously proven upper vector is an upper bound as well
        for t in range(m):
            if saved[t] < up[nodes[t]]:
                up[nodes[t]] = saved[t]
        return True, s
    for t in range(m):
        up[nodes[t]] = saved[t]  # refuted or undecided: back to the proven vector
    return False, s


@njit(cache=True)
def _aitken(nodes, lo, incr, cen, lam, have_cen):
    """Aitken extrapolation ``cen = lo + incr lam / (1 - lam)`` of the lower iterates; returns
    (largest move of ``cen`` since the last one, when ``have_cen``; largest increment)."""
    cf = lam / (1.0 - lam)
    dmax = 0.0
    vmax = 0.0
    for t in range(nodes.shape[0]):
        x = lo[nodes[t]] + incr[t] * cf
        if have_cen and abs(x - cen[t]) > dmax:
            dmax = abs(x - cen[t])
        cen[t] = x
        if incr[t] > vmax:
            vmax = incr[t]
    return dmax, vmax


@njit(cache=True)
def _extrapolated_upper(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl, strat, adv_max, lo, up,
                        perm, keys, idx, saved, incr, cen, vmax, off, kappa, dgap, shift, target, n_sweeps):
    """The upper guess ``cen + dgap + off (incr / vmax + kappa)``, checked unless the proven one
    ``saved`` is already within ``target`` of the lower guess; ``saved`` takes it when proven
    and ``up`` is ``saved`` afterwards.  Returns (proven, sweeps)."""
    m = nodes.shape[0]
    need_up = False
    for t in range(m):
        if saved[t] - (cen[t] - off * (incr[t] / vmax + kappa)) > target:
            need_up = True
            break
    if not need_up:
        return False, 0
    for t in range(m):
        g = cen[t] + dgap + off * (incr[t] / vmax + kappa) - shift
        up[nodes[t]] = g if g < saved[t] else saved[t]
    ok, s = _check_guess(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, up, lo, ctrl, strat,
                         adv_max, SWEEP_CHECK_UPPER, perm, keys, idx, n_sweeps)
    for t in range(m):
        if ok and up[nodes[t]] < saved[t]:
            saved[t] = up[nodes[t]]  # proven upper vector (min with the old one: also proven)
        up[nodes[t]] = saved[t]
    return ok, s


@njit(cache=True)
def _extrapolated_lower(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl, strat, adv_max, lo, up,
                        perm, keys, idx, saved_lo, incr, cen, vmax, off, kappa, shift, n_sweeps):
    """The lower guess ``max(lo, cen - off (incr / vmax + kappa))``, checked by sweeps that must
    decrease no value (unique fixed point: no end components); kept when proven, else ``lo``
    goes back to its value before the guess.  Returns (proven, sweeps)."""
    m = nodes.shape[0]
    for t in range(m):
        saved_lo[t] = lo[nodes[t]]
        g = cen[t] - off * (incr[t] / vmax + kappa) + shift
        if g > saved_lo[t]:
            lo[nodes[t]] = g
    ok, s = _check_guess(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, lo, up, ctrl, strat,
                         adv_max, SWEEP_CHECK_LOWER, perm, keys, idx, n_sweeps)
    for t in range(m):
        if not ok or lo[nodes[t]] < saved_lo[t]:
            lo[nodes[t]] = saved_lo[t] if not ok else max(lo[nodes[t]], saved_lo[t])
    return ok, s


@njit(cache=True)
def _interval_nodes(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl, strat, adv_max, lo, up,
                    perm, keys, idx, target, sweeps, max_sweeps):
    """Interval iteration on ``nodes`` (lower and upper sweeps) from ``sweeps`` sweeps done until
    the bracket is within ``target`` (ST_INTERVAL) or ``max_sweeps`` (ST_OPEN).  Returns
    (sweeps, status)."""
    none = np.empty(0)
    while sweeps < max_sweeps:
        node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, lo, lo, ctrl, strat, adv_max,
                   SWEEP_LOWER, perm, keys, idx, none)
        node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, up, lo, ctrl, strat, adv_max,
                   SWEEP_UPPER, perm, keys, idx, none)
        sweeps += 2
        if _max_gap(nodes, lo, up) <= target:
            return sweeps, ST_INTERVAL
    return sweeps, ST_OPEN


@njit(cache=True)
def ovi_component(nodes, c, comp, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl, strat, adv_max,
                  lo, up, perm, keys, idx, prec, max_sweeps, saved, saved_lo, incr, cen, params):
    """Solve one strongly connected component without end components to a bracket <= ``prec``.

    Its successors outside have their final brackets (width <= ``dgap``).  Optimistic value
    iteration (Hartmanns & Kaminski, CAV 2020) adapted to the interval Bellman operator, with
    Gauss-Seidel lower sweeps and two kinds of guesses, each checked by sweeps of Lemma OVI (the
    docstring of :mod:`robust_imdp.solvers.engine`; a refuted or undecided guess is discarded,
    restoring the last proven vectors ``saved``/``saved_lo``):

    * *extrapolated* (once the per-node increments ``d`` of the lower sweeps decay by a stable
      factor lam, so ``V* ~ c = lo + d lam / (1 - lam)``, Aitken): upper ``c + dgap + off (v + KAPPA)``
      and lower ``c - off (v + KAPPA)`` with ``v = d / max(d)``; the lower one is proven by a sweep
      that decreases no value, which needs the unique fixed point of a component without end
      components (engine docstring);
    * *plain*: when the estimated error ``r lam / (1 - lam)`` of the lower vector (residual r) is
      below ``tol``, the upper guess ``min(proven, lo + delta)``.

    After ``params[P_MAX_FAILS]`` (``ovi.OVI_PARAMS``) refuted plain guesses: interval iteration (lower
    and upper sweeps from the last proven upper vector, initially 1).
    Returns (sweeps, status): status ``ST_PLAIN`` (proven without a successful extrapolated
    guess), ``ST_EXTRAP`` (with one), ``ST_INTERVAL`` (by interval iteration), ``ST_OPEN`` (not
    within ``max_sweeps``; the bracket is still sound).
    """
    verify_sweeps = int(params[P_VERIFY_SWEEPS])
    max_fails = int(params[P_MAX_FAILS])
    extrap_sweeps = int(params[P_EXTRAP_SWEEPS])
    max_extrap = int(params[P_MAX_EXTRAP])
    kappa = params[P_KAPPA]
    extrap_every = int(params[P_EXTRAP_EVERY])
    shift = params[P_SHIFT]
    dgap = _exit_gap(nodes, c, comp, n, state_ptr, row_ptr, col, upper, nxt, layered, ctrl, strat, lo, up)
    target, margin, delta, tol, off = ovi_aim(dgap, prec, kappa)
    for t in range(nodes.shape[0]):
        saved[t] = up[nodes[t]]
    sweeps = 0
    fails = 0
    k = 0
    prev = np.inf
    have_cen = False
    attempts = 0
    next_try = 3
    extrap_ok = False  # some extrapolated guess was proven
    while sweeps < max_sweeps and fails < max_fails:
        r = node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, lo, up, ctrl, strat, adv_max,
                       SWEEP_LOWER, perm, keys, idx, incr)[0]
        sweeps += 1
        k += 1
        if _max_gap(nodes, lo, up) <= target:
            return sweeps, ST_EXTRAP if extrap_ok else ST_PLAIN
        lam, est = _contraction(r, prev, k)
        prev = r
        if est <= tol:
            ok, s = _plain_guess(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl, strat, adv_max,
                                 lo, up, perm, keys, idx, saved, delta, shift, min(verify_sweeps, max_sweeps - sweeps))
            sweeps += s
            if ok:
                return sweeps, ST_EXTRAP if extrap_ok else ST_PLAIN
            fails += 1
            tol *= 0.0625
            if fails >= max_fails:
                break
            continue
        if attempts >= max_extrap or lam >= 1.0 or k < next_try:
            have_cen = False
            continue
        # Aitken extrapolation of the lower iterates, and whether it has settled
        dmax, vmax = _aitken(nodes, lo, incr, cen, lam, have_cen)
        settled = have_cen and dmax <= 0.1 * margin and vmax > 0.0
        have_cen = True
        if not settled:
            continue
        attempts += 1
        next_try = k + extrap_every
        have_cen = False
        ok, s = _extrapolated_upper(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl, strat,
                                    adv_max, lo, up, perm, keys, idx, saved, incr, cen, vmax, off, kappa, dgap, shift,
                                    target, min(extrap_sweeps, max_sweeps - sweeps))
        sweeps += s
        extrap_ok = extrap_ok or ok
        ok, s = _extrapolated_lower(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl, strat,
                                    adv_max, lo, up, perm, keys, idx, saved_lo, incr, cen, vmax, off, kappa, shift,
                                    min(extrap_sweeps, max_sweeps - sweeps))
        sweeps += s
        extrap_ok = extrap_ok or ok
        if _max_gap(nodes, lo, up) <= target:
            return sweeps, ST_EXTRAP if extrap_ok else ST_PLAIN
        if ok:
            prev = np.inf  # the lower vector jumped: restart the contraction estimate
            k = 0
            next_try = 3
    return _interval_nodes(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl, strat, adv_max, lo, up,
                           perm, keys, idx, target, sweeps, max_sweeps)


@njit(cache=True, nogil=True)
def component_levels(order, comp_ptr, comp, n, state_ptr, row_ptr, col, upper, nxt, layered, ctrl, strat):
    """Level of every component in the DAG of components: 0 without successor components,
    else 1 + the largest level of a successor component.  Components must come in reverse
    topological order (successor components first), as Tarjan numbers them."""
    nc = comp_ptr.shape[0] - 1
    level = np.zeros(nc, dtype=np.int64)
    for c in range(nc):
        lv = 0
        for t in range(comp_ptr[c], comp_ptr[c + 1]):
            node = order[t]
            l = node // n
            q = node - l * n
            r0, r1 = _rows(state_ptr, q, ctrl, strat, node)
            for j in range(row_ptr[r0], row_ptr[r1]):
                if upper[j] <= 0.0:
                    continue
                q2 = col[j]
                c2 = comp[nxt[l * n + q2] * n + q2 if layered else q2]
                if c2 >= 0 and c2 != c and level[c2] + 1 > lv:
                    lv = level[c2] + 1
        level[c] = lv
    return level


@njit(cache=True, nogil=True)
def solve_components(c0, order, comp_ptr, kind, comp, n, state_ptr, row_ptr, col, lower, upper, nxt, layered,
                     ctrl, strat, adv_max, lo, up, perm, prec, max_sweeps, comp_sweeps, comp_status, params):
    """Solve the components ``c0, c0+1, ...`` (reverse topological order: every successor
    component comes first) until one that contains an end component (``KIND_END_COMPONENT``, returned for
    the caller) or the last one (returns the number of components).

    KIND_SINGLE: one node without a self-loop, solved exactly by one lower and one upper step;
    KIND_OVI: :func:`ovi_component`.  The nodes of component c are ``order[comp_ptr[c]:comp_ptr[c+1]]``.
    """
    maxk = 1
    for r in range(row_ptr.shape[0] - 1):
        if row_ptr[r + 1] - row_ptr[r] > maxk:
            maxk = row_ptr[r + 1] - row_ptr[r]
    keys = np.empty(maxk)
    idx = np.empty(maxk, dtype=perm.dtype)
    biggest = 1
    for c in range(comp_ptr.shape[0] - 1):
        if comp_ptr[c + 1] - comp_ptr[c] > biggest:
            biggest = comp_ptr[c + 1] - comp_ptr[c]
    saved = np.empty(biggest)
    saved_lo = np.empty(biggest)
    incr = np.empty(biggest)
    cen = np.empty(biggest)
    none = np.empty(0)
    nc = comp_ptr.shape[0] - 1
    for c in range(c0, nc):
        if kind[c] == KIND_END_COMPONENT:
            return c
        nodes = order[comp_ptr[c]:comp_ptr[c + 1]]
        if kind[c] == KIND_SINGLE:
            node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, lo, lo, ctrl, strat, adv_max,
                       SWEEP_LOWER, perm, keys, idx, none)
            node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, up, lo, ctrl, strat, adv_max,
                       SWEEP_UPPER, perm, keys, idx, none)
            comp_sweeps[c] = 2
            comp_status[c] = ST_EXACT
        else:
            s, st = ovi_component(nodes, c, comp, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl,
                                  strat, adv_max, lo, up, perm, keys, idx, prec, max_sweeps, saved, saved_lo, incr,
                                  cen, params)
            comp_sweeps[c] = s
            comp_status[c] = st
    return nc

