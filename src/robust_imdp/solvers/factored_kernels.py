"""Numba kernels of the factored Bellman operator: nested O-maximisation, one axis at a time, over a
prefix tree of shared per-axis marginals (:func:`factored_rows`).  The driver, the value
iteration and the soundness argument: :mod:`robust_imdp.solvers.factored` and docs/factored.md.

The computation (docs/factored.md, "The operator")
--------------------------------------------------
For a (cell, mode) with per-axis interval vectors ``P_0 .. P_{d-1}`` and a value vector ``w`` over
the cells (a tensor of the grid's shape) and the outside state (``w_out``), the value is

    W_0 = w,   W_l(j_0 .. j_{d-1-l}) = O_{P_{d-l}}( W_{l-1}(j_0 .. j_{d-1-l}, .) , w_out, w_rest ),

``l = 1 .. d``: the last axis (contiguous in C order) is reduced first, axis 0 last; ``O_P`` is
one O-maximisation (the adversary's optimal ``p.x`` over the interval vector: the listed
entries, the outside entry valued ``w_out`` and the rest entry ``[0, rest_upper]`` valued
``w_rest``, the global min (or max) of ``w``).

Sharing.  ``W_l`` of a (cell, mode) depends only on the marginals of its last l axes.  Cells are
sorted by their marginal ids ``(m_{d-1}, m_{d-2}, ..., m_0)``; the groups of equal prefixes form
a tree whose level-l nodes each compute ``W_l`` once, over the bounding box of the listed ranges
of their cells on the remaining axes, from their parent's buffer.  A depth-first traversal keeps
one buffer per level; the roots (level 1) run in parallel on numba's threads.

Rounding (``LEVEL_ERR``).  Every level's result is moved outward by a bound of its rounding error
and clamped to [0, 1] (safe: every exact value is a probability).  All quantities lie in [0, 1]
(values, probabilities, partial sums), so each rounded operation errs by at most u = 2**-53.
With m = k + 2 entries: the base sum ``sum lower * x`` over the listed entries and the outside
costs 2(k + 1) operations; the precomputed ``rem0 = 1 - sum(lower) - out_lower`` k + 2; the
precomputed capacities ``upper - lower`` one each (m); each greedy step at most 4 (compare,
product, sum, ``rem`` update).  The greedy allocation is 1-Lipschitz (in l1) in ``rem`` and the
capacities, so their errors move the value by at most their sum.  Total <= (2m + m + m + 4m) u
= 8 m u; we use ``LEVEL_ERR(k) = (16 m + 64) u``, the solver's ``ROW_ERR`` with m entries.  A
level's inputs are the previous level's outward-rounded results: the exact O-maximisation is
monotone in its inputs, so the rounding of the levels composes (induction over levels).
"""

from __future__ import annotations

from collections import namedtuple

import numba
import numpy as np
from numba import njit

from robust_imdp._fp import U

#: The grid: ``shape`` (d,), C-order ``strides`` (d,), ``periodic`` (d,) bool.
Grid = namedtuple("Grid", ["shape", "strides", "periodic"])

#: The deduplicated per-axis marginals (ids global over the axes): first listed interval
#: ``start`` (T,), listed count ``k`` (T,), entries ``ptr[m] .. ptr[m] + k[m]`` of ``lower`` and
#: ``cap = upper - lower`` (E,), outside ``ol``, ``ocap = out_upper - out_lower``, rest
#: capacity ``rcap = rest_upper`` and ``rem0 = 1 - sum(lower) - out_lower`` (T,).
Marginals = namedtuple("Marginals", ["start", "k", "ptr", "lower", "cap", "ol", "ocap", "rcap", "rem0"])

#: The traversal tree (groups level-major, the modes' groups in mode order within a level):
#: ``level_start`` (d + 2,) first group of level l (levels 1 .. d; index 0 unused), marginal id
#: ``mid`` (G,) of the group's level, children ``child0 .. child1`` (G,) (global group ids of the
#: next level), cells ``cell0 .. cell1`` (G,) (positions in the mode's row of ``cells``),
#: ``mode`` (G,), boxes ``box`` (flat int64): level l's group g holds, at ``box_start[l] +
#: 2 (d - l) (g - level_start[l])``, ``lo, hi`` of each remaining axis 0 .. d-l-1 (unwrapped
#: positions), ``cells`` (M, N) the cells of each mode in tree order, ``maxvol`` (d + 1,) the
#: largest box volume of each level.
Tree = namedtuple("Tree", ["level_start", "mid", "child0", "child1", "cell0", "cell1", "mode", "box_start", "box",
                           "cells", "maxvol"])


@njit(cache=True, inline="always")
def level_err(k):
    """``LEVEL_ERR`` of an O-maximisation over k listed entries plus outside and rest (module docstring)."""
    return (16.0 * (k + 2) + 64.0) * U


@njit(cache=True, inline="always")
def _insert(keys, caps, m, key, c):
    i = m
    while i > 0 and keys[i - 1] > key:
        keys[i] = keys[i - 1]
        caps[i] = caps[i - 1]
        i -= 1
    keys[i] = key
    caps[i] = c
    return m + 1


@njit(cache=True, inline="always")
def _finish(val, rem, k, direction):
    """Outward rounding of one O-maximisation (module docstring, ``LEVEL_ERR``)."""
    if direction < 0:
        val -= level_err(k)
        if val < 0.0:
            val = 0.0  # safe: every exact value is >= 0
    elif direction > 0:
        # mass left unassigned (upper sums below 1 within the model tolerance) is credited with
        # the largest possible value 1: stays an upper bound
        val += level_err(k) + rem
        if val > 1.0:
            val = 1.0  # safe: every exact value is <= 1
    return val


@njit(cache=True, inline="always")
def _support(src, poff, base, lev1, n_a, per_a, mg, mm, w_out, w_rest):
    """The graph version of :func:`_omax_gather`: the largest value among the entries with a positive
    upper bound (can the row reach a positive value?), without rounding."""
    st = mg.start[mm]
    k = mg.k[mm]
    e0 = mg.ptr[mm]
    best = 0.0
    for j in range(k):
        s = st + j
        if s >= n_a:
            if not per_a:
                break
            if lev1:
                s -= n_a
        idx = s if lev1 else s - base
        if mg.lower[e0 + j] > 0.0 or mg.cap[e0 + j] > 0.0:
            x = src[poff + idx]
            if x > best:
                best = x
    if (mg.ol[mm] > 0.0 or mg.ocap[mm] > 0.0) and w_out > best:
        best = w_out
    if mg.rcap[mm] > 0.0 and w_rest > best:
        best = w_rest
    return best


@njit(cache=True, inline="always")
def _omax_gather(src, poff, base, lev1, n_a, per_a, mg, mm, w_out, w_rest, adv_max, direction, keys, caps):
    """One O-maximisation along the fibre ``src[poff + (s - base)]`` (level 1: ``s mod n_a``) for the
    listed positions ``s = start + j`` of marginal ``mm``: gather, insertion sort, greedy."""
    st = mg.start[mm]
    k = mg.k[mm]
    e0 = mg.ptr[mm]
    val = 0.0
    m = 0
    for j in range(k):
        s = st + j
        if s >= n_a:
            if not per_a:
                break  # non-periodic: positions past the last interval have lower = upper = 0
            if lev1:
                s -= n_a
        idx = s if lev1 else s - base
        x = src[poff + idx]
        val += mg.lower[e0 + j] * x
        c = mg.cap[e0 + j]
        if c > 0.0:
            m = _insert(keys, caps, m, -x if adv_max else x, c)
    val += mg.ol[mm] * w_out
    if mg.ocap[mm] > 0.0:
        m = _insert(keys, caps, m, -w_out if adv_max else w_out, mg.ocap[mm])
    if mg.rcap[mm] > 0.0:
        m = _insert(keys, caps, m, -w_rest if adv_max else w_rest, mg.rcap[mm])
    rem = mg.rem0[mm]
    if rem > 0.0:
        for t in range(m):
            x = -keys[t] if adv_max else keys[t]
            c = caps[t]
            if c >= rem:
                val += rem * x
                rem = 0.0
                break
            val += c * x
            rem -= c
    else:
        rem = 0.0  # sum(lower) >= 1 (within the model tolerance): p = lower
    return _finish(val, rem, k, direction)


@njit(cache=True, inline="always")
def _omax_sorted(src, perm, poff, h, base, lev1, n_a, per_a, mg, mm, w_out, w_rest, adv_max, direction):
    """The same O-maximisation in one pass over the fibre's precomputed order ``perm[poff:poff + h]``
    (fibre-local indices by increasing value; shared by every marginal that reads the fibre),
    skipping the positions the marginal does not list; the outside and rest entries are merged in
    at their places.  Same operations per entry as :func:`_omax_gather` (same ``LEVEL_ERR``)."""
    st = mg.start[mm]
    k = mg.k[mm]
    e0 = mg.ptr[mm]
    ol = mg.ol[mm]
    ocap = mg.ocap[mm]
    rcap = mg.rcap[mm]
    rem = mg.rem0[mm]
    if rem < 0.0:
        rem = 0.0  # sum(lower) >= 1 (within the model tolerance): p = lower
    val = ol * w_out
    # the outside and rest entries, in the adversary's order: (x1, c1) first, then (x2, c2)
    first_out = (w_out >= w_rest) if adv_max else (w_out <= w_rest)
    x1, c1, x2, c2 = (w_out, ocap, w_rest, rcap) if first_out else (w_rest, rcap, w_out, ocap)
    left1 = c1 > 0.0
    left2 = c2 > 0.0
    for t in range(h):
        tt = h - 1 - t if adv_max else t
        li = perm[poff + tt]
        x = src[poff + li]
        p = base + li
        j = p - st
        if lev1 and per_a and j < 0:
            j += n_a
        if j < 0 or j >= k:
            continue
        # the extra entries that come before x in the adversary's order
        if left1 and ((x1 >= x) if adv_max else (x1 <= x)):
            left1 = False
            c = c1 if c1 < rem else rem
            val += c * x1
            rem -= c
        if left2 and not left1 and ((x2 >= x) if adv_max else (x2 <= x)):
            left2 = False
            c = c2 if c2 < rem else rem
            val += c * x2
            rem -= c
        val += mg.lower[e0 + j] * x
        c = mg.cap[e0 + j]
        if c > rem:
            c = rem
        val += c * x
        rem -= c
    if left1:
        c = c1 if c1 < rem else rem
        val += c * x1
        rem -= c
    if left2:
        c = c2 if c2 < rem else rem
        val += c * x2
        rem -= c
    return _finish(val, rem, k, direction)


@njit(cache=True, inline="always")
def _sort_fibres(src, perm, n_fib, h, keys):
    """``perm[f h:(f + 1) h]`` = the order of ``src[f h:(f + 1) h]`` by increasing value (insertion
    sort on a local copy of the values: fibres are short), for every fibre f; ``keys``: scratch of
    length >= h."""
    for f in range(n_fib):
        o = f * h
        for i in range(h):
            x = src[o + i]
            t = i
            while t > 0 and keys[t - 1] > x:
                keys[t] = keys[t - 1]
                perm[o + t] = perm[o + t - 1]
                t -= 1
            keys[t] = x
            perm[o + t] = i


@njit(cache=True, parallel=True)
def fibre_order(w, n_last, out):
    """``out`` (N,) int32: per fibre of the grid's last axis (length ``n_last``), the order of ``w``."""
    n_fib = w.shape[0] // n_last
    for b in numba.prange((n_fib + 255) // 256):
        f0 = b * 256
        f1 = min(n_fib, f0 + 256)
        keys = np.empty(n_last)
        _sort_fibres(w[f0 * n_last:f1 * n_last], out[f0 * n_last:f1 * n_last], f1 - f0, n_last, keys)


@njit(cache=True, inline="always")
def _value(src, perm, poff, h, base, lev1, n_a, per_a, mg, mm, w_out, w_rest, adv_max, direction, support, keys,
           caps):
    if support:
        return _support(src, poff, base, lev1, n_a, per_a, mg, mm, w_out, w_rest)
    if h <= 2 * mg.k[mm]:
        return _omax_sorted(src, perm, poff, h, base, lev1, n_a, per_a, mg, mm, w_out, w_rest, adv_max,
                            direction)
    return _omax_gather(src, poff, base, lev1, n_a, per_a, mg, mm, w_out, w_rest, adv_max, direction, keys, caps)


@njit(cache=True)
def _reduce(level, g, pg, grid, mg, tr, w, w_perm, buf, pbuf, boff, w_out, w_rest, adv_max, direction, support,
            keys, caps, pstride, plo, skeys):
    """Compute group g's ``W_level`` (into ``buf[boff[level]:]``, with the order of its fibres along
    its last axis in ``pbuf``; or return it at the leaves) from its parent pg's buffer (level 1:
    from ``w``)."""
    d = grid.shape.shape[0]
    a = d - level  # the axis reduced here; the box spans axes 0 .. a-1
    lev1 = level == 1
    # the parent's box over axes 0 .. a and its C-order strides
    if lev1:
        for i in range(a + 1):
            plo[i] = 0
            pstride[i] = grid.strides[i]
        h = grid.shape[a]
        src = w
        sperm = w_perm
    else:
        pb = tr.box_start[level - 1] + 2 * (d - level + 1) * (pg - tr.level_start[level - 1])
        pstride[a] = 1
        for i in range(a - 1, -1, -1):
            pstride[i] = pstride[i + 1] * (tr.box[pb + 2 * (i + 1) + 1] - tr.box[pb + 2 * (i + 1)])
        for i in range(a + 1):
            plo[i] = tr.box[pb + 2 * i]
        h = tr.box[pb + 2 * a + 1] - plo[a]
        src = buf[boff[level - 1]:boff[level]]
        sperm = pbuf[boff[level - 1]:boff[level]]
    mm = tr.mid[g]
    n_a = grid.shape[a]
    per_a = grid.periodic[a]
    base = plo[a]
    if a == 0:
        return _value(src, sperm, 0, h, base, lev1, n_a, per_a, mg, mm, w_out, w_rest, adv_max, direction, support,
                      keys, caps)
    gb = tr.box_start[level] + 2 * a * (g - tr.level_start[level])
    # iterate the child box: outer points over axes 0 .. a-2, an inner run along axis a-1
    lo_in = tr.box[gb + 2 * (a - 1)]
    h_in = tr.box[gb + 2 * (a - 1) + 1] - lo_in
    n_outer = 1
    for i in range(a - 1):
        n_outer *= tr.box[gb + 2 * i + 1] - tr.box[gb + 2 * i]
    dst = buf[boff[level]:boff[level + 1]]
    n_in = grid.shape[a - 1]
    for o in range(n_outer):
        r = o
        poff0 = 0
        for i in range(a - 2, -1, -1):
            lo_i = tr.box[gb + 2 * i]
            hh = tr.box[gb + 2 * i + 1] - lo_i
            p = lo_i + r % hh
            r //= hh
            if lev1:
                if p >= grid.shape[i]:
                    p -= grid.shape[i]  # unwrapped position on a periodic axis
                poff0 += p * pstride[i]
            else:
                poff0 += (p - plo[i]) * pstride[i]
        for c in range(h_in):
            p = lo_in + c
            if lev1:
                if p >= n_in:
                    p -= n_in
                poff = poff0 + p * pstride[a - 1]
            else:
                poff = poff0 + (p - plo[a - 1]) * pstride[a - 1]
            dst[o * h_in + c] = _value(src, sperm, poff, h, base, lev1, n_a, per_a, mg, mm, w_out, w_rest, adv_max,
                                       direction, support, keys, caps)
    if not support:
        _sort_fibres(dst, pbuf[boff[level]:boff[level + 1]], n_outer, h_in, skeys)
    return 0.0


@njit(cache=True)
def _needed(tr, need_pc, g):
    u = tr.mode[g]
    return need_pc[u, tr.cell1[g]] > need_pc[u, tr.cell0[g]]


@njit(cache=True)
def _root(g, grid, mg, tr, w, w_perm, w_out, w_rest, need_pc, adv_max, direction, support, out_rows, boff, kmax):
    """The depth-first traversal of the subtree of root g (level 1)."""
    d = grid.shape.shape[0]
    buf = np.empty(max(boff[d], 1))
    pbuf = np.empty(max(boff[d], 1), dtype=np.int32)
    keys = np.empty(kmax + 2)
    caps = np.empty(kmax + 2)
    pstride = np.empty(d, dtype=np.int64)
    plo = np.empty(d, dtype=np.int64)
    skeys = np.empty(2 * grid.shape.max() + 1)  # a box's width is below 2 n (unwrapped positions)
    stack = np.empty(d + 1, dtype=np.int64)
    cur = np.empty(d + 1, dtype=np.int64)
    u = tr.mode[g]
    v = _reduce(1, g, -1, grid, mg, tr, w, w_perm, buf, pbuf, boff, w_out, w_rest, adv_max, direction, support,
                keys, caps, pstride, plo, skeys)
    if d == 1:
        for t in range(tr.cell0[g], tr.cell1[g]):
            out_rows[u, tr.cells[u, t]] = v
        return
    stack[1] = g
    cur[1] = tr.child0[g]
    lev = 1
    while lev >= 1:
        pg = stack[lev]
        if cur[lev] < tr.child1[pg]:
            c = cur[lev]
            cur[lev] += 1
            if not _needed(tr, need_pc, c):
                continue
            v = _reduce(lev + 1, c, pg, grid, mg, tr, w, w_perm, buf, pbuf, boff, w_out, w_rest, adv_max, direction,
                        support, keys, caps, pstride, plo, skeys)
            if lev + 1 == d:
                for t in range(tr.cell0[c], tr.cell1[c]):
                    out_rows[u, tr.cells[u, t]] = v
            else:
                stack[lev + 1] = c
                cur[lev + 1] = tr.child0[c]
                lev += 1
        else:
            lev -= 1


@njit(cache=True, parallel=True)
def factored_rows(grid, mg, tr, w, w_perm, w_out, w_rest, need_pc, adv_max, direction, support, out_rows):
    """The factored Bellman value of every needed (mode, cell) row, written into ``out_rows`` (M, N).

    Parameters
    ----------
    grid : Grid
    mg : Marginals
    tr : Tree
    w : (N,) float
        Successor values of the cells (C order).
    w_perm : (N,) int32
        :func:`fibre_order` of ``w`` (unused with ``support``).
    w_out, w_rest : float
        Value of the outside state; value credited to unlisted intervals (the min of ``w`` and
        ``w_out`` for a minimising adversary, the max for a maximising one).
    need_pc : (M, N + 1) int
        Prefix counts of the needed rows in each mode's tree order; other rows are left as they are.
    adv_max : bool
    direction : int
        -1 round down, +1 round up, 0 plain (module docstring).
    support : bool
        The graph version (largest value among entries with positive upper bound; no rounding).
    out_rows : (M, N) float
    """
    d = grid.shape.shape[0]
    boff = np.zeros(d + 1, dtype=np.int64)
    for lev in range(1, d):
        boff[lev + 1] = boff[lev] + tr.maxvol[lev]
    kmax = 1
    for m in range(mg.k.shape[0]):
        if mg.k[m] > kmax:
            kmax = mg.k[m]
    r0 = tr.level_start[1]
    n_roots = tr.level_start[2] - r0
    for r in numba.prange(n_roots):
        g = r0 + r
        if _needed(tr, need_pc, g):
            _root(g, grid, mg, tr, w, w_perm, w_out, w_rest, need_pc, adv_max, direction, support, out_rows, boff,
                  kmax)


__all__ = ["Grid", "Marginals", "Tree", "factored_rows", "fibre_order", "level_err"]
