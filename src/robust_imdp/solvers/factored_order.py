"""Component order for the factored unbounded solve: the strongly connected components of the lazy
product's support graph in reverse topological order, each iterated in place (Gauss-Seidel) before
the next, with one factored row at a time (:func:`ordered_pass`).  The driver and the soundness
argument of the iteration: :mod:`robust_imdp.solvers.factored` and docs/factored.md.

Why an order
------------
The whole-model sweeps of :func:`robust_imdp.solvers.factored_kernels.factored_rows` move a value
one step along a path per sweep: a transient chain of length L needs L sweeps.  Taken in reverse
topological order of the components, every successor outside the component being solved already
holds its final bracket, so a component without cycles needs one update and a cyclic one is iterated
on its own nodes only (the joint engine's order, :mod:`robust_imdp.solvers.ovi`).

The graph (over-approximated)
-----------------------------
Node ``s * n + q`` of the product (DFA state s, base state q) has the successors ``(nxt[s, q'], q')``
for every cell q' of the box ``prod_i [start_i, start_i + k_i)`` (periodic axes wrap; non-periodic
positions past the grid are not cells) of every row the controller may take (every mode; the
strategy's under a fixed strategy).  Every cell the row can reach with positive probability lies in
it, except the outside state and the unlisted rest: the outside state is never iterated (absorbing,
fixed), and rows with an unlisted rest (``rest_upper > 0``) read the global minimum (maximum) of the
layer's values, which the order ignores.  The order is a heuristic for speed only: every update is
``l <- max(l, B_down(l))`` / ``u <- min(u, B_up(u))`` on the current vectors, sound in any order and
on any subset of nodes (module :mod:`robust_imdp.solvers.factored`, "Soundness of the iteration"),
and the whole-model iteration that follows the pass decides convergence as before.

One row (:func:`_row_value`)
----------------------------
The nested O-maximisation of one (cell, mode) on a local buffer over the row's box: the successor
values gathered in C order, then the last axis reduced first.  Each reduction performs the
operations of :func:`robust_imdp.solvers.factored_kernels._omax_gather` in the same order (listed
entries while they are cells, the outside entry, the rest entry, the greedy fill, ``_finish``), so
the same ``LEVEL_ERR`` bounds its rounding and the levels compose as there (monotone O-maximisation).

Stale rest values.  ``w_rest`` (the least value of a layer's successor vector for a minimising
adversary, the largest for a maximising one) is taken once per pass from the vectors before it.
Lower iterates only rise and upper ones only fall, so a lower pass reads a minimum that is at most
(a maximum at most) the current one and an upper pass one at least the current one: the O-maximisation
is monotone in ``w_rest``, so each update stays below ``B(l)`` (above ``B(u)``).
"""

from __future__ import annotations

from collections import namedtuple

import numba
import numpy as np
from numba import njit

from robust_imdp.solvers.factored_kernels import _finish, _insert

#: The fewest nodes of a cyclic component whose two ends are swept side by side on numba's threads.
PAR_MIN_NODES = 256

#: Refuted upper guesses (Lemma OVI) per component before its sweeps go on without guessing.
OVI_MAX_FAILS = 4

#: Controller codes of the kernels (the values of :class:`robust_imdp.solvers.common.Control`).
_MAX, _MIN, _FIXED = 0, 1, 2

#: The rows of a product: per (mode, cell, axis) marginal id ``ids`` (M, N, d) int32 into the
#: operator's ``Marginals``; successor layers ``nxt`` (S * n,) flat (node ``s * n + q'`` -> the
#: layer of its successor ``q'``); ``n`` states per layer (cells, then outside); controller ``ctrl``
#: with its stationary ``strat`` (S * n,) under a fixed strategy (else length 1).
ProductRows = namedtuple("ProductRows", ["ids", "nxt", "n", "ctrl", "strat"])


@njit(cache=True)
def _box(grid, mg, ids, u, q, st, ke):
    """First position ``st`` (d,) and cell count ``ke`` (d,) per axis of the row (u, q) (non-periodic
    axes: the listed positions that are cells); returns the box's cell count."""
    d = grid.shape.shape[0]
    tot = 1
    for i in range(d):
        mm = ids[u, q, i]
        s0 = mg.start[mm]
        k = mg.k[mm]
        if not grid.periodic[i] and s0 + k > grid.shape[i]:
            k = grid.shape[i] - s0
            if k < 0:
                k = 0
        st[i] = s0
        ke[i] = k
        tot *= k
    return tot


@njit(cache=True)
def _cell(grid, st, ke, t):
    """The cell of C-order index t of the box (``st``, ``ke``); periodic positions wrap."""
    d = grid.shape.shape[0]
    q = 0
    r = t
    for i in range(d - 1, -1, -1):
        p = st[i] + r % ke[i]
        r //= ke[i]
        if p >= grid.shape[i]:
            p -= grid.shape[i]
        q += p * grid.strides[i]
    return q


@njit(cache=True, inline="always")
def _omax_local(buf, off, kk, mg, mm, w_out, w_rest, adv_max, direction, keys, caps):
    """One O-maximisation of marginal ``mm`` over ``buf[off:off + kk]`` (the listed entries that are
    cells, in order): :func:`robust_imdp.solvers.factored_kernels._omax_gather`'s operations in its
    order (same ``LEVEL_ERR``)."""
    k = mg.k[mm]
    e0 = mg.ptr[mm]
    val = 0.0
    m = 0
    for j in range(kk):
        x = buf[off + j]
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


@njit(cache=True)
def _row_value(grid, mg, pr, V, s, u, q, w_out, w_rest, adv_max, direction, buf, keys, caps, st, ke, offs, idx):
    """The factored value of row (cell q, mode u) in layer s against the flat values ``V`` (S * n,):
    successor q' reads ``V[nxt[s * n + q'] * n + q']``; outward rounded by ``direction``.  ``buf`` (>= box
    volume), ``keys``/``caps`` (k + 2), ``st``/``ke``/``idx`` (d,) and ``offs`` (d, kmax): scratch."""
    d = grid.shape.shape[0]
    n = pr.n
    tot = _box(grid, mg, pr.ids, u, q, st, ke)
    base = s * n
    if tot > 0:
        # gather in C order over the box: an odometer over axes 0 .. d-2 (offsets of the wrapped positions in
        # ``offs``), a run along the last axis
        for i in range(d):
            for j in range(ke[i]):
                p = st[i] + j
                if p >= grid.shape[i]:
                    p -= grid.shape[i]
                offs[i, j] = p * grid.strides[i]
            idx[i] = 0
        kl = ke[d - 1]
        for o in range(tot // kl):
            qb = 0
            for i in range(d - 1):
                qb += offs[i, idx[i]]
            for j in range(kl):
                q2 = qb + offs[d - 1, j]
                buf[o * kl + j] = V[pr.nxt[base + q2] * n + q2]
            i = d - 2
            while i >= 0:
                idx[i] += 1
                if idx[i] < ke[i]:
                    break
                idx[i] = 0
                i -= 1
    # reduce the last axis first: after axis a the buffer holds prod(ke[:a]) values in C order
    outer = tot
    for a in range(d - 1, -1, -1):
        kk = ke[a]
        if kk > 0:
            outer = outer // kk
        else:
            outer = 1
            for i in range(a):
                outer *= ke[i]
        mm = pr.ids[u, q, a]
        for o in range(outer):
            # in place: block o is read (positions o kk .. o kk + kk - 1 >= o) before buf[o] is written
            buf[o] = _omax_local(buf, o * kk, kk, mg, mm, w_out, w_rest, adv_max, direction, keys, caps)
    return buf[0]


@njit(cache=True)
def _node_value(grid, mg, pr, V, node, w_out, w_rest, adv_max, direction, buf, keys, caps, st, ke, offs, idx):
    """The controller's value of node ``s * n + q`` (a cell): max / min over the modes, or the
    strategy's mode."""
    n = pr.n
    s = node // n
    q = node - s * n
    M = pr.ids.shape[0]
    if pr.ctrl == _FIXED:
        return _row_value(grid, mg, pr, V, s, pr.strat[node], q, w_out, w_rest, adv_max, direction, buf, keys, caps,
                          st, ke, offs, idx)
    best = -1.0 if pr.ctrl == _MAX else 2.0
    for u in range(M):
        v = _row_value(grid, mg, pr, V, s, u, q, w_out, w_rest, adv_max, direction, buf, keys, caps, st, ke, offs,
                       idx)
        if (pr.ctrl == _MAX and v > best) or (pr.ctrl == _MIN and v < best):
            best = v
    return best


@njit(cache=True)
def product_sccs(grid, mg, pr, active):
    """Strongly connected components of the active nodes' support graph (module docstring, "The
    graph"), by Tarjan's algorithm with an explicit stack.

    Parameters
    ----------
    grid, mg : the operator's ``Grid`` and ``Marginals``
    pr : ProductRows
    active : (S * n,) bool
        The nodes to order (others are fixed and not followed).

    Returns
    -------
    comp : (S * n,) int64
        Component of every active node (-1 elsewhere), numbered in reverse topological order
        (every successor of a node lies in its component or in one with a smaller number).
    cyclic : (n_components,) bool
        The component has an edge inside it (more than one node, or a self-loop).
    rank : (S * n,) int64
        Order in which the nodes left Tarjan's stack (-1 for inactive nodes): within a component, a
        node found later on a search path (nearer its end) comes first, so a sweep in this order
        carries values back along the search's paths.
    """
    n_nodes = active.shape[0]
    n = pr.n
    N = n - 1
    d = grid.shape.shape[0]
    M = pr.ids.shape[0]
    index = np.full(n_nodes, -1, dtype=np.int64)
    low = np.zeros(n_nodes, dtype=np.int64)
    onstack = np.zeros(n_nodes, dtype=np.bool_)
    comp = np.full(n_nodes, -1, dtype=np.int64)
    selfloop = np.zeros(n_nodes, dtype=np.bool_)
    stack = np.empty(n_nodes, dtype=np.int64)
    cs_node = np.empty(n_nodes, dtype=np.int64)
    cs_u = np.empty(n_nodes, dtype=np.int64)
    cs_t = np.empty(n_nodes, dtype=np.int64)
    cyc = np.zeros(n_nodes, dtype=np.bool_)
    rank = np.full(n_nodes, -1, dtype=np.int64)
    popped = 0
    st = np.empty(d, dtype=np.int64)
    ke = np.empty(d, dtype=np.int64)
    counter = 0
    sp = 0
    nc = 0
    for root in range(n_nodes):
        if not active[root] or index[root] >= 0 or root % n == N:
            continue
        top = 0
        cs_node[0] = root
        cs_u[0] = 0 if pr.ctrl != _FIXED else pr.strat[root]
        cs_t[0] = 0
        index[root] = counter
        low[root] = counter
        counter += 1
        stack[sp] = root
        sp += 1
        onstack[root] = True
        while top >= 0:
            v = cs_node[top]
            s = v // n
            q = v - s * n
            u_end = M if pr.ctrl != _FIXED else pr.strat[v] + 1
            pushed = False
            while cs_u[top] < u_end:
                u = cs_u[top]
                tot = _box(grid, mg, pr.ids, u, q, st, ke)
                while cs_t[top] < tot:
                    t = cs_t[top]
                    cs_t[top] = t + 1
                    q2 = _cell(grid, st, ke, t)
                    w = pr.nxt[s * n + q2] * n + q2
                    if not active[w]:
                        continue
                    if w == v:
                        selfloop[v] = True
                    if index[w] < 0:
                        index[w] = counter
                        low[w] = counter
                        counter += 1
                        stack[sp] = w
                        sp += 1
                        onstack[w] = True
                        top += 1
                        cs_node[top] = w
                        cs_u[top] = 0 if pr.ctrl != _FIXED else pr.strat[w]
                        cs_t[top] = 0
                        pushed = True
                        break
                    elif onstack[w] and index[w] < low[v]:
                        low[v] = index[w]
                if pushed:
                    break
                cs_u[top] = u + 1
                cs_t[top] = 0
            if pushed:
                continue
            # v is finished
            if low[v] == index[v]:
                size = 0
                while True:
                    sp -= 1
                    x = stack[sp]
                    onstack[x] = False
                    comp[x] = nc
                    rank[x] = popped
                    popped += 1
                    size += 1
                    if x == v:
                        break
                cyc[nc] = size > 1 or selfloop[v]
                nc += 1
            top -= 1
            if top >= 0:
                p = cs_node[top]
                if low[v] < low[p]:
                    low[p] = low[v]
    return comp, cyc[:nc].copy(), rank


@njit(cache=True)
def _scratch(grid, mg):
    """Scratch arrays of :func:`_row_value`: (buf, keys, caps, st, ke, offs, idx)."""
    d = grid.shape.shape[0]
    kmax = 1
    for m in range(mg.k.shape[0]):
        if mg.k[m] > kmax:
            kmax = mg.k[m]
    vol = 1
    for i in range(d):
        vol *= kmax
    return (np.empty(vol), np.empty(kmax + 2), np.empty(kmax + 2), np.empty(d, dtype=np.int64),
            np.empty(d, dtype=np.int64), np.empty((d, kmax), dtype=np.int64), np.empty(d, dtype=np.int64))


@njit(cache=True)
def _sweep_end(grid, mg, pr, V, nodes, c0, c1, wr, adv_max, direction, backward=False):
    """One in-place sweep of one end over ``nodes[c0:c1]`` (``backward``: last node first): ``V <- max(V,
    B_down(V))`` (direction -1) or ``V <- min(V, B_up(V))`` (+1).  Returns the largest change.  A cyclic
    component's sweeps alternate direction (values flow both ways in a cycle; the vehicle 4-D at 12^4: 35 -> 29
    sweeps over the four solves of a synthesis, 16^4: 95 -> 95)."""
    buf, keys, caps, st, ke, offs, idx = _scratch(grid, mg)
    n = pr.n
    change = 0.0
    for ii in range(c0, c1):
        i = c0 + c1 - 1 - ii if backward else ii
        node = nodes[i]
        s = node // n
        wo = V[pr.nxt[s * n + n - 1] * n + n - 1]
        v = _node_value(grid, mg, pr, V, node, wo, wr[s], adv_max, direction, buf, keys, caps, st, ke, offs, idx)
        if direction < 0:
            if v > V[node]:
                if v - V[node] > change:
                    change = v - V[node]
                V[node] = v
        elif v < V[node]:
            if V[node] - v > change:
                change = V[node] - v
            V[node] = v
    return change


@njit(cache=True)
def _verify_up(grid, mg, pr, up, nodes, c0, c1, wr, adv_max):
    """Lemma OVI's check of an upper guess on ``nodes[c0:c1]`` (module docstring of
    :mod:`robust_imdp.solvers.engine`): the in-place sweep ``u(s) <- B_up(u)(s)``; True when no value
    increased (then the vector is a proven upper bound), False at the first increase (the caller restores
    the last proven vector)."""
    buf, keys, caps, st, ke, offs, idx = _scratch(grid, mg)
    n = pr.n
    for i in range(c0, c1):
        node = nodes[i]
        s = node // n
        wo = up[pr.nxt[s * n + n - 1] * n + n - 1]
        v = _node_value(grid, mg, pr, up, node, wo, wr[s], adv_max, 1, buf, keys, caps, st, ke, offs, idx)
        if v > up[node]:
            return False
        up[node] = v
    return True



@njit(cache=True)
def _gap(lo, up, nodes, c0, c1):  # pragma: no cover - compiled
    """The widest bracket ``up - lo`` over the component's nodes ``nodes[c0:c1]``."""
    gap = 0.0
    for i in range(c0, c1):
        g = up[nodes[i]] - lo[nodes[i]]
        if g > gap:
            gap = g
    return gap

@njit(cache=True, parallel=True)
def factored_components(grid, mg, pr, lo, up, nodes, comp_ptr, cyclic, wr_lo, wr_up, adv_max, precision, stall,
                     max_sweeps, sweeps):
    """Every component in order (``nodes[comp_ptr[c]:comp_ptr[c + 1]]``, reverse topological): one
    update of an acyclic one, in-place sweeps of a cyclic one until its bracket is within
    ``precision``, both ends stop moving by more than ``stall`` per sweep, or ``max_sweeps``.
    The two ends of a sweep are independent iterations: they run side by side on numba's threads.
    Once the lower end moves by at most ``precision / 8`` per sweep, the upper end is guessed at ``min(up,
    lo + precision / 2)`` and checked by one sweep (:func:`_verify_up`, Lemma OVI of
    :mod:`robust_imdp.solvers.engine`, sound here because every successor outside the component is final
    and the guess only lowers values, so the pass's stale rest value stays on the safe side); a refuted guess
    is undone and the next waits for a lower end 4 x more settled, at most ``OVI_MAX_FAILS`` times.  A
    check counts as a sweep.
    ``lo``/``up`` (S * n,) are updated in place; ``sweeps[c]`` receives each component's count.
    Returns the number of components that stopped at ``max_sweeps`` with a gap above ``precision``."""
    capped = 0
    nc = comp_ptr.shape[0] - 1
    change = np.zeros(2)
    saved = np.empty(1)
    for c in range(nc):
        c0 = comp_ptr[c]
        c1 = comp_ptr[c + 1]
        if not cyclic[c]:
            _sweep_end(grid, mg, pr, lo, nodes, c0, c1, wr_lo, adv_max, -1)
            _sweep_end(grid, mg, pr, up, nodes, c0, c1, wr_up, adv_max, 1)
            sweeps[c] = 1
            continue
        k = 0
        do_lo = True
        do_up = True
        fails = 0
        delta = 0.5 * precision
        aim = 0.25 * delta
        if saved.shape[0] < c1 - c0:
            saved = np.empty(c1 - c0)
        while k < max_sweeps:
            k += 1
            change[0] = 0.0
            change[1] = 0.0
            if c1 - c0 < PAR_MIN_NODES:  # a small component: one thread (a parallel launch waits for both)
                if do_lo:
                    change[0] = _sweep_end(grid, mg, pr, lo, nodes, c0, c1, wr_lo, adv_max, -1, k % 2 == 0)
                if do_up:
                    change[1] = _sweep_end(grid, mg, pr, up, nodes, c0, c1, wr_up, adv_max, 1, k % 2 == 0)
            else:
                for e in numba.prange(2):
                    if e == 0 and do_lo:
                        change[0] = _sweep_end(grid, mg, pr, lo, nodes, c0, c1, wr_lo, adv_max, -1, k % 2 == 0)
                    elif e == 1 and do_up:
                        change[1] = _sweep_end(grid, mg, pr, up, nodes, c0, c1, wr_up, adv_max, 1, k % 2 == 0)
            if _gap(lo, up, nodes, c0, c1) <= precision:
                break
            if fails < OVI_MAX_FAILS and (change[0] <= aim or not do_lo):
                # the lower end has (nearly) settled: guess the upper end at lower + delta and check it
                # (Lemma OVI: every node's outside successors already hold their final, proven brackets)
                k += 1
                for i in range(c0, c1):
                    node = nodes[i]
                    saved[i - c0] = up[node]
                    g = lo[node] + delta
                    if g < up[node]:
                        up[node] = g
                if _verify_up(grid, mg, pr, up, nodes, c0, c1, wr_up, adv_max):
                    if _gap(lo, up, nodes, c0, c1) <= precision:
                        break
                else:
                    for i in range(c0, c1):
                        up[nodes[i]] = saved[i - c0]  # refuted: back to the last proven vector
                    fails += 1
                    aim *= 0.25
            # an end that stopped moving is not swept again in this pass (sound: no update is needed)
            if do_lo and change[0] <= stall:
                do_lo = False
            if do_up and change[1] <= stall:
                do_up = False
            if not (do_lo or do_up):
                break
        if k >= max_sweeps and (do_lo or do_up):
            capped += 1
        sweeps[c] = k
    return capped


@njit(cache=True)
def row_values(grid, mg, pr, V, w_rest, adv_max, direction, out):
    """Every row of layer 0 one at a time (:func:`_row_value`): ``out[u, q]`` for the cells q and modes u,
    against the flat values ``V`` (S * n,) with the rest valued ``w_rest``.  The independent check of the
    per-row reduction against :func:`robust_imdp.solvers.factored_kernels.factored_rows` and exact
    arithmetic (tests)."""
    buf, keys, caps, st, ke, offs, idx = _scratch(grid, mg)
    n = pr.n
    w_out = V[pr.nxt[n - 1] * n + n - 1]
    for u in range(out.shape[0]):
        for q in range(out.shape[1]):
            out[u, q] = _row_value(grid, mg, pr, V, 0, u, q, w_out, w_rest, adv_max, direction, buf, keys, caps, st,
                                   ke, offs, idx)


__all__ = ["ProductRows", "product_sccs", "row_values", "factored_components"]
