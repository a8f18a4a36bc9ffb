"""Graph pre-computations of the layered models (exact, integer/boolean or liberal in float
borderline cases): the nodes with value 0 (:func:`positive_attractor`) and 1 (:func:`almost_sure`),
strongly connected components (:func:`strong_components`), stay-able rows and the end components
used by the deflation (:func:`_end_components`, :func:`response_end_components`), Lemma D's exit
bounds (:func:`stay_exit_bounds`) and the progress-making strategy (:func:`progress_strategy`).
Why they are sound: :mod:`robust_imdp.solvers.engine`.

Kernels here call only kernels of this file and the intrinsic ``_atomic.fetch_add`` (numba caches per
file; see :mod:`robust_imdp.solvers.kernels`).

In place: :func:`positive_attractor` and the inner fixed point of
:func:`almost_sure` add nodes to their set during a sweep (Gauss-Seidel, sweeps alternating
forwards and backwards) instead of Kleene's ``W_{k+1} = F(W_k)``: a path of m steps against the
sweep order no longer needs m sweeps. The per-layer counts ``cnt`` of unlisted members are taken
at the start of a sweep, so within it they can only be too small, which makes no test pass that
would fail with the true counts (fewer unlisted members: less unlisted mass on the set). The loop
stops after a sweep that added nothing, with exact counts: the set is a fixed point of the test.

* :func:`almost_sure` (conservative: a node wrongly added would get the value 1): every node added
  passes the float test, hence the exact one, at a subset of the exact least fixed point, so it is
  in it (the exact test is monotone: more members never make a row fail).
* :func:`positive_attractor` (liberal: a node wrongly left out would get the value 0): the result
  is a fixed point of the float test, which passes wherever the exact one does, so it contains the
  exact least fixed point.

Both float tests are monotone too (more members never make a row fail: :func:`positive_attractor` compares
a rounded-down sum with 1, :func:`almost_sure`'s slack shrinks as its set grows), so their least fixed point
is unique: the in-place sweeps, on one thread or shared by several, give Kleene's set bit for bit
(tests/test_graph_lanes.py).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit

from robust_imdp._atomic import fetch_add
from robust_imdp._fp import U
from robust_imdp.solvers.common import Control

# controller codes of the kernels (plain ints: compiled as constants)
_MIN = int(Control.MINIMISE)
_FIXED = int(Control.FIXED)


@njit(cache=True, inline="always")
def _sum_slack(n_terms, with_product):
    """Bound of the rounding error of a float sum of ``n_terms`` values in [0, 1] (total <= 2),
    plus one product and addition when ``with_product``: exact (0) for a single term."""
    ops = n_terms - 1 if n_terms > 1 else 0
    if with_product:
        ops += 2
    return ops * 4.0 * U


@njit(cache=True, inline="always")
def _rows(state_ptr, q, ctrl, strat, k):
    """Row range of state q: all its rows, or (ctrl FIXED) the fixed strategy's row ``strat[k]``
    (a copy of ``kernels._rows``: numba caches per file)."""
    if ctrl == _FIXED:
        r0 = state_ptr[q] + strat[k]
        return r0, r0 + 1
    return state_ptr[q], state_ptr[q + 1]



#: Nodes per work unit of the parallel sweeps (:func:`positive_attractor`, :func:`almost_sure`,
#: :func:`progress_strategy`): every lane takes the next unit in sweep order from a shared counter
#: (``_atomic.fetch_add``) until none is left. The undecided nodes are bunched in some layers and
#: regions, so units differ in cost by orders of magnitude: a static split (numba's ``prange`` on
#: the "omp" layer, also the interleaved ``t, t + nt, ...`` these sweeps had) left one lane idle for
#: a third of a sweep (unicycle 64^3, 559 sweeps of ``almost_sure``: 1 lane 3.8 s, 2 static lanes
#: 3.2 s, 2 dynamic lanes 2.1 s). One lane visits every node in the sweep order of the serial
#: algorithm.
_UNIT = 2048


def graph_lanes() -> int:
    """Lanes of the graph kernels: the caller's numba threads (passed in, not read in a kernel: reading
    ``numba.get_num_threads`` there would keep numba from caching it)."""
    return int(numba.get_num_threads())


@njit(cache=True, inline="always")
def _add_down(a, b):
    """The largest float <= the exact ``a + b`` (TwoSum's error term says on which side the rounded
    sum lies); finite non-negative operands."""
    s = a + b
    bb = s - a
    e = (a - (s - bb)) + (b - bb)
    if e < 0.0:
        s = np.nextafter(s, -np.inf)
    return s


@njit(cache=True, inline="always")
def _mul_down(f, m):
    """A float <= the exact ``f * m`` (f >= 0, m a non-negative integer count), non-decreasing in both:
    the rounded product shrunk by 4 units of roundoff and the smallest subnormal (which covers the
    rounding of a subnormal product), clipped at 0."""
    p = (f * m) * (1.0 - 4.0 * U) - 5e-324
    return p if p > 0.0 else 0.0


@njit(cache=True, inline="always")
def _successor_counts(mask, nxt, n, out):
    """``out[l]`` = the number of states q' whose successor node ``(nxt[l, q'], q')`` from layer l
    is in ``mask`` (L*n,)."""
    for l in range(nxt.shape[0]):
        c = 0
        for q2 in range(n):
            if mask[nxt[l, q2] * n + q2]:
                c += 1
        out[l] = c


@njit(cache=True, inline="always")
def _positive_node(node, l, q, n, state_ptr, row_ptr, col, lower, upper, floor, nxt, W, cntW, ctrl, strat, adv_max):
    """:func:`positive_attractor`'s test of ``node`` = ``l * n + q`` (not in W, not blocked) against the set ``W``."""
    r0, r1 = _rows(state_ptr, q, ctrl, strat, node)
    any_hit = False
    all_hit = True
    for r in range(r0, r1):
        listedW = 0
        f = floor[r]
        if adv_max:
            upW = 0.0
            for j in range(row_ptr[r], row_ptr[r + 1]):
                q2 = col[j]
                if W[nxt[l, q2] * n + q2]:
                    upW += upper[j]
                    listedW += 1
            hit = upW > 0.0 or (f > 0.0 and cntW[l] - listedW > 0)
        else:
            # forced positive mass on W: lower mass on W (a float sum of non-negative terms is positive iff one
            # is), or a lower bound of the mass that can stay outside W below 1 (liberal)
            lowW = 0.0
            upOut = 0.0
            nOut = 0
            for j in range(row_ptr[r], row_ptr[r + 1]):
                q2 = col[j]
                if W[nxt[l, q2] * n + q2]:
                    lowW += lower[j]
                    listedW += 1
                elif upper[j] > 0.0:
                    upOut += upper[j]
                    nOut += 1
            unlOut = (n - (row_ptr[r + 1] - row_ptr[r])) - (cntW[l] - listedW)
            withf = f > 0.0 and unlOut > 0
            if lowW > 0.0:
                hit = True
            else:
                stay = upOut + f * unlOut if withf else upOut
                # the rounded-to-nearest sum is within (nOut + 2) units of roundoff of the exact one (relative): far
                # from 1 it decides like the rounded-down sum below, near 1 that sum decides
                band = (nOut + 4.0) * 8.0 * U * (1.0 + stay)
                if stay < 1.0 - band:
                    hit = True
                elif stay > 1.0 + band:
                    hit = False
                else:
                    down = 0.0
                    for j in range(row_ptr[r], row_ptr[r + 1]):
                        q2 = col[j]
                        if not W[nxt[l, q2] * n + q2] and upper[j] > 0.0:
                            down = _add_down(down, upper[j])
                    if withf:
                        down = _add_down(down, _mul_down(f, unlOut))
                    hit = down < 1.0
        if hit:
            any_hit = True
        else:
            all_hit = False
    return (ctrl == _MIN and all_hit) or (ctrl != _MIN and any_hit)


@njit(cache=True)
def _positive_sweep(state_ptr, row_ptr, col, lower, upper, floor, nxt, W, blocked, cntW, ctrl, strat, adv_max, back):
    """One in-place sweep of :func:`positive_attractor` in node order (``back``: reversed); True if it added."""
    n = state_ptr.shape[0] - 1
    L = nxt.shape[0]
    changed = False
    for li in range(L):
        l = L - 1 - li if back else li
        for qi in range(n):
            q = n - 1 - qi if back else qi
            node = l * n + q
            if W[node] or blocked[node]:
                continue
            if _positive_node(node, l, q, n, state_ptr, row_ptr, col, lower, upper, floor, nxt, W, cntW, ctrl, strat,
                              adv_max):
                W[node] = True
                changed = True
    return changed


@njit(cache=True, parallel=True)
def _positive_sweep_lanes(state_ptr, row_ptr, col, lower, upper, floor, nxt, W, blocked, cntW, ctrl, strat, adv_max,
                          back, nt):
    """:func:`_positive_sweep` on ``nt`` threads, each taking the next unit of nodes as it comes free, in place."""
    n = state_ptr.shape[0] - 1
    N = W.shape[0]
    nu = (N + _UNIT - 1) // _UNIT
    flags = np.zeros(nt, dtype=np.bool_)
    taken = np.zeros(1, dtype=np.int64)  # units handed out (_UNIT's note); never read after the loop
    for t in numba.prange(nt):
        while True:
            u = fetch_add(taken, 0, 1)
            if u >= nu:
                break
            for idx in range(u * _UNIT, min(N, (u + 1) * _UNIT)):
                node = N - 1 - idx if back else idx
                if W[node] or blocked[node]:
                    continue
                l = node // n
                if _positive_node(node, l, node - l * n, n, state_ptr, row_ptr, col, lower, upper, floor, nxt, W, cntW,
                                  ctrl, strat, adv_max):
                    W[node] = True
                    flags[t] = True
    return flags.any()


@njit(cache=True)
def positive_attractor(state_ptr, row_ptr, col, lower, upper, floor, nxt, init, blocked,
                       ctrl, strat, adv_max, lanes=1):
    """States (layer, q) from which the target is reached with positive probability.

    Layered graph: node ``l*n + q``; listed successor ``q'`` of a row of ``q`` in layer ``l`` is
    node ``(nxt[l, q'], q')``; a floor row also reaches every unlisted ``q'`` with capacity floor.
    ``init`` (L*n,) bool: the target nodes; ``blocked``: nodes fixed to 0 (never added).
    A row "hits" the set W if every admissible distribution puts positive mass on W
    (minimising adversary, ``adv_max`` False) or some does (maximising adversary).
    ctrl 0: some row of the state hits; 1: every row hits; 2: the row ``strat`` hits.
    Liberal (a node wrongly added only loosens upper bounds; a node wrongly left out would fix a
    positive value to 0, so the tests err toward adding): the minimising adversary's test compares
    a lower bound of the mass that can stay outside W (sums rounded down, :func:`_add_down`) with 1.
    The test is monotone in W (rounded-down sums of fewer non-negative terms are not larger), so the
    least fixed point is unique and the sweeps' order does not change it: ``lanes`` threads sweep
    units of nodes in place, each taking the next as it comes free (the module's "In place" note),
    and give the same set.
    Returns the (L*n,) bool mask W (includes ``init``).
    """
    L = nxt.shape[0]
    n = state_ptr.shape[0] - 1
    nt = max(1, min(lanes, (L * n + _UNIT - 1) // _UNIT))
    W = init.copy()
    # per layer: number of q' whose successor node (nxt[l, q'], q') is in W
    cntW = np.zeros(L, dtype=np.int64)
    changed = True
    sweep = 0
    while changed:
        _successor_counts(W, nxt, n, cntW)
        # in place, every other sweep backwards (the module's "In place" note)
        back = sweep % 2 == 1
        sweep += 1
        if nt == 1:
            changed = _positive_sweep(state_ptr, row_ptr, col, lower, upper, floor, nxt, W, blocked, cntW, ctrl,
                                      strat, adv_max, back)
        else:
            changed = _positive_sweep_lanes(state_ptr, row_ptr, col, lower, upper, floor, nxt, W, blocked, cntW,
                                            ctrl, strat, adv_max, back, nt)
    return W


@njit(cache=True, inline="always")
def _sure_node(node, l, q, n, state_ptr, row_ptr, col, lower, upper, floor, nxt, X, Y, cntX, cntY, ctrl, strat,
               adv_max):
    """:func:`almost_sure`'s test of ``node`` = ``l * n + q`` (in Y, not in X): some (ctrl 0) / the fixed row is
    good."""
    r0, r1 = _rows(state_ptr, q, ctrl, strat, node)
    for r in range(r0, r1):
        k = row_ptr[r + 1] - row_ptr[r]
        f = floor[r]
        outY = False
        lowOutY = 0.0
        capY = 0.0
        nY = 0
        lowX = 0.0
        capX = 0.0
        lowYnX = 0.0
        upNotX = 0.0
        nNotX = 0
        listedX = 0
        listedY = 0
        for j in range(row_ptr[r], row_ptr[r + 1]):
            q2 = col[j]
            node2 = nxt[l, q2] * n + q2
            inY = Y[node2]
            inX = X[node2]
            if inY:
                listedY += 1
                capY += upper[j]
                nY += 1
            else:
                lowOutY += lower[j]
                if upper[j] > 0.0:
                    outY = True
            if inX:
                listedX += 1
                lowX += lower[j]
                capX += upper[j]
            else:
                if upper[j] > 0.0:
                    upNotX += upper[j]
                    nNotX += 1
                if inY:
                    lowYnX += lower[j]
        unlY = cntY[l] - listedY
        unlX = cntX[l] - listedX
        unlNotY = (n - k) - unlY
        unlNotX = (n - k) - unlX
        fl = f > 0.0
        if adv_max:
            capYt = capY + (f * unlY if fl else 0.0)
            good = (lowOutY == 0.0
                    and capYt - _sum_slack(nY, fl and unlY > 0) >= 1.0
                    and (capX > 0.0 or (fl and unlX > 0))
                    and lowYnX + _sum_slack(k, False) < 1.0)
        else:
            if outY or (fl and unlNotY > 0):
                good = False
            else:
                rest = upNotX + (f * unlNotX if fl else 0.0)
                good = lowX > 0.0 or rest + _sum_slack(nNotX, fl and unlNotX > 0) < 1.0
        if good:
            return True
    return False


@njit(cache=True)
def _sure_sweep(state_ptr, row_ptr, col, lower, upper, floor, nxt, X, Y, cntX, cntY, ctrl, strat, adv_max, back):
    """One in-place sweep of :func:`almost_sure`'s inner fixed point; True if it added."""
    n = state_ptr.shape[0] - 1
    L = nxt.shape[0]
    changed = False
    for li in range(L):
        l = L - 1 - li if back else li
        for qi in range(n):
            q = n - 1 - qi if back else qi
            node = l * n + q
            if X[node] or not Y[node]:
                continue
            if _sure_node(node, l, q, n, state_ptr, row_ptr, col, lower, upper, floor, nxt, X, Y, cntX, cntY, ctrl,
                          strat, adv_max):
                X[node] = True
                changed = True
    return changed


@njit(cache=True, parallel=True)
def _sure_sweep_lanes(state_ptr, row_ptr, col, lower, upper, floor, nxt, X, Y, cntX, cntY, ctrl, strat, adv_max,
                      back, nt):
    """:func:`_sure_sweep` on ``nt`` threads, each taking the next unit of nodes as it comes free, in place."""
    n = state_ptr.shape[0] - 1
    N = X.shape[0]
    nu = (N + _UNIT - 1) // _UNIT
    flags = np.zeros(nt, dtype=np.bool_)
    taken = np.zeros(1, dtype=np.int64)  # units handed out (_UNIT's note); never read after the loop
    for t in numba.prange(nt):
        while True:
            u = fetch_add(taken, 0, 1)
            if u >= nu:
                break
            for idx in range(u * _UNIT, min(N, (u + 1) * _UNIT)):
                node = N - 1 - idx if back else idx
                if X[node] or not Y[node]:
                    continue
                l = node // n
                if _sure_node(node, l, node - l * n, n, state_ptr, row_ptr, col, lower, upper, floor, nxt, X, Y, cntX,
                              cntY, ctrl, strat, adv_max):
                    X[node] = True
                    flags[t] = True
    return flags.any()


@njit(cache=True)
def almost_sure(state_ptr, row_ptr, col, lower, upper, floor, nxt, target, W, ctrl, strat, adv_max, lanes=1):
    """Nodes from which the controller reaches the target with probability 1 (ctrl 0 or 2).

    Nested fixed point (almost-sure reachability of turn-based stochastic games):
    ``Y = nu Y. mu X. target  U  {node in Y : some row (ctrl 0) / the fixed row (ctrl 2) is
    good}``; a row is good when, for a minimising adversary, every admissible p keeps its
    support inside Y (every possible successor is in Y) and puts positive mass on X; for a
    maximising adversary, some admissible p has support inside Y and positive mass on X.
    Playing good rows, every step reaches X with probability >= delta > 0 (compactness of the
    interval polytopes) without leaving Y, hence the target almost surely.  All tests are
    *conservative* (a node wrongly added would be given the value 1): sums are compared with
    a margin covering their rounding.  Starts from ``W`` (the positive-probability nodes).
    For a fixed Y every test is monotone in X (more members: more mass on X, less outside it, fewer
    terms and less slack), so the inner least fixed point is unique and the order of the in-place
    sweeps does not change it: ``lanes`` threads sweep units of nodes taken as they come free (as in
    :func:`positive_attractor`) and give the same nodes.
    """
    L = nxt.shape[0]
    n = state_ptr.shape[0] - 1
    nt = max(1, min(lanes, (L * n + _UNIT - 1) // _UNIT))
    Y = W.copy()
    cntX = np.zeros(L, dtype=np.int64)
    cntY = np.zeros(L, dtype=np.int64)
    while True:
        _successor_counts(Y, nxt, n, cntY)
        X = target.copy()
        changed = True
        sweep = 0
        while changed:
            _successor_counts(X, nxt, n, cntX)
            back = sweep % 2 == 1  # in place, alternating directions (the module's "In place" note)
            sweep += 1
            if nt == 1:
                changed = _sure_sweep(state_ptr, row_ptr, col, lower, upper, floor, nxt, X, Y, cntX, cntY, ctrl,
                                      strat, adv_max, back)
            else:
                changed = _sure_sweep_lanes(state_ptr, row_ptr, col, lower, upper, floor, nxt, X, Y, cntX, cntY, ctrl,
                                            strat, adv_max, back, nt)
        same = True
        for i in range(Y.shape[0]):
            if Y[i] != X[i]:
                same = False
                break
        if same:
            return X
        Y = X


@njit(cache=True)
def edge_csr(state_ptr, row_ptr, col, upper, nxt, rowmask, act):
    """CSR (indptr int64 (N+1,), indices int32) of the listed positive-upper entries of the rows
    in ``rowmask`` between active nodes of the layered graph (node ``l*n + q``)."""
    L = nxt.shape[0]
    n = state_ptr.shape[0] - 1
    R = row_ptr.shape[0] - 1
    N = L * n
    indptr = np.zeros(N + 1, dtype=np.int64)
    for l in range(L):
        for q in range(n):
            node = l * n + q
            if not act[node]:
                continue
            c = 0
            for r in range(state_ptr[q], state_ptr[q + 1]):
                if not rowmask[l * R + r]:
                    continue
                for j in range(row_ptr[r], row_ptr[r + 1]):
                    if upper[j] > 0.0 and act[nxt[l, col[j]] * n + col[j]]:
                        c += 1
            indptr[node + 1] = c
    for i in range(N):
        indptr[i + 1] += indptr[i]
    indices = np.empty(indptr[N], dtype=np.int32)
    for l in range(L):
        for q in range(n):
            node = l * n + q
            if not act[node]:
                continue
            pos = indptr[node]
            for r in range(state_ptr[q], state_ptr[q + 1]):
                if not rowmask[l * R + r]:
                    continue
                for j in range(row_ptr[r], row_ptr[r + 1]):
                    d = nxt[l, col[j]] * n + col[j]
                    if upper[j] > 0.0 and act[d]:
                        indices[pos] = d
                        pos += 1
    return indptr, indices


@njit(cache=True)
def strong_components(indptr, indices):
    """Strongly connected components (iterative Tarjan); returns (label (N,), count)."""
    N = indptr.shape[0] - 1
    index = np.full(N, -1, dtype=np.int64)
    low = np.zeros(N, dtype=np.int64)
    onstack = np.zeros(N, dtype=np.bool_)
    stack = np.empty(N, dtype=np.int64)
    cs_node = np.empty(N, dtype=np.int64)
    cs_edge = np.empty(N, dtype=np.int64)
    comp = np.full(N, -1, dtype=np.int64)
    sp = 0
    nc = 0
    idx = 0
    for s in range(N):
        if index[s] != -1:
            continue
        cs_node[0] = s
        cs_edge[0] = indptr[s]
        csp = 1
        index[s] = idx
        low[s] = idx
        idx += 1
        stack[sp] = s
        sp += 1
        onstack[s] = True
        while csp > 0:
            v = cs_node[csp - 1]
            e = cs_edge[csp - 1]
            if e < indptr[v + 1]:
                cs_edge[csp - 1] = e + 1
                w = indices[e]
                if index[w] == -1:
                    index[w] = idx
                    low[w] = idx
                    idx += 1
                    stack[sp] = w
                    sp += 1
                    onstack[w] = True
                    cs_node[csp] = w
                    cs_edge[csp] = indptr[w]
                    csp += 1
                elif onstack[w] and index[w] < low[v]:
                    low[v] = index[w]
            else:
                csp -= 1
                if csp > 0:
                    u = cs_node[csp - 1]
                    if low[v] < low[u]:
                        low[u] = low[v]
                if low[v] == index[v]:
                    while True:
                        sp -= 1
                        w = stack[sp]
                        onstack[w] = False
                        comp[w] = nc
                        if w == v:
                            break
                    nc += 1
    return comp, nc


@njit(cache=True, parallel=True)
def progress_strategy(state_ptr, row_ptr, col, lower, upper, floor, nxt, target, optimal, adv_max,
                      fallback, score, tie_strat, lanes=1):
    """Among optimal rows pick, per node, one that makes progress toward the target.

    ``optimal`` (R*L,) bool: row r in layer l is optimal (index ``l*R + r``).  Backward
    attractor over optimal rows (Haddad & Monmege 2014 / Baier et al. 2017 strategy
    extraction): a node joins at round i+1 through an optimal row that puts positive mass on
    the nodes of rounds <= i for every (minimising adversary) / some (maximising) admissible
    distribution; the row is remembered.  Here the tests are strict (no slack): a wrongly
    chosen row would break the strategy.

    Lexicographic ties: among the rows through which a node joins in the same round, the one
    with the largest ``score`` (R*L,) is remembered (the first on equal scores).  A node the
    attractor never reaches (its lower value is 0, or within the tie tolerance of 0) keeps the
    choice ``tie_strat[node]`` if that row is optimal (``tie_strat`` (L*n,) holds -1 where there
    is none), else its optimal row of largest finite score, else ``fallback``.  With all scores
    -inf and ``tie_strat`` all -1 this is the first hitting row / ``fallback``.
    A round reads only the previous rounds' nodes, so ``lanes`` threads share its nodes (units taken
    as they come free, as in :func:`positive_attractor`) with the same result.
    """
    L = nxt.shape[0]
    n = state_ptr.shape[0] - 1
    R = row_ptr.shape[0] - 1
    W = target.copy()
    strat = fallback.copy()
    cntW = np.zeros(L, dtype=np.int64)
    N = L * n
    nu = (N + _UNIT - 1) // _UNIT
    nt = max(1, min(lanes, nu))
    flags = np.zeros(nt, dtype=np.bool_)
    changed = True
    while changed:
        _successor_counts(W, nxt, n, cntW)
        newW = W.copy()
        flags[:] = False
        taken = np.zeros(1, dtype=np.int64)  # units handed out (_UNIT's note); never read after the loop
        for t in numba.prange(nt):
            while True:
                u = fetch_add(taken, 0, 1)
                if u >= nu:
                    break
                for node in range(u * _UNIT, min(N, (u + 1) * _UNIT)):
                    l = node // n
                    q = node - l * n
                    if W[node]:
                        continue
                    best = -np.inf
                    for r in range(state_ptr[q], state_ptr[q + 1]):
                        if not optimal[l * R + r]:
                            continue
                        lowW = 0.0
                        upW = 0.0
                        upOut = 0.0
                        listedW = 0
                        for j in range(row_ptr[r], row_ptr[r + 1]):
                            q2 = col[j]
                            if W[nxt[l, q2] * n + q2]:
                                lowW += lower[j]
                                upW += upper[j]
                                listedW += 1
                            else:
                                upOut += upper[j]
                        unlW = cntW[l] - listedW
                        unlOut = (n - (row_ptr[r + 1] - row_ptr[r])) - unlW
                        f = floor[r]
                        if adv_max:
                            hit = upW > 0.0 or (f > 0.0 and unlW > 0)
                        else:
                            hit = lowW > 0.0 or (upOut + f * unlOut) * (1.0 + 1e-12) < 1.0
                        if hit and (not newW[node] or score[l * R + r] > best):
                            newW[node] = True
                            strat[node] = r - state_ptr[q]
                            best = score[l * R + r]
                            flags[t] = True
        changed = False
        for tt in range(nt):
            if flags[tt]:
                changed = True
        W = newW
    for l in range(L):
        for q in range(n):
            node = l * n + q
            if W[node]:
                continue
            ts = tie_strat[node]
            if ts >= 0 and optimal[l * R + state_ptr[q] + ts]:
                strat[node] = ts
                continue
            best = -np.inf
            for r in range(state_ptr[q], state_ptr[q + 1]):
                if optimal[l * R + r] and score[l * R + r] > best:
                    best = score[l * R + r]
                    strat[node] = r - state_ptr[q]
    return strat


@njit(cache=True)
def _exit_ratio(j0, j1, col, lower, upper, nxt, comp, c, l, n, u, f, unlIn, unlOut, bo, caps, vals):
    """Upper bound of ``sup {p_out.u / p(out) : p admissible, p(out) > 0}`` for one row.

    The exit mass m ranges over [m_min, m_max] with m_min = max(L_out, 1 - H_in); for a fixed m
    the best numerator is the ordering solution on the outside entries, and the ratio grows
    while the next entry's value exceeds it (a linear-fractional programme is optimal at a
    vertex).  With m_min = 0 the supremum is the largest value reachable outside.  Unlisted
    outside successors (floor mass) are one pseudo-entry of capacity f*unlOut valued ``bo``
    (an upper bound of their values), which can only increase the ratio.  Rounding: numerator
    and denominator are widened by a bound of their errors and the result is capped by the
    largest outside value (a ratio is an average).
    """
    m = 0
    lowIn = 0.0
    capIn = 0.0
    lowOut = 0.0
    num = 0.0
    vmax = -np.inf
    for j in range(j0, j1):
        q2 = col[j]
        node2 = nxt[l, q2] * n + q2
        if comp[node2] == c:
            lowIn += lower[j]
            capIn += upper[j]
            continue
        if upper[j] <= 0.0:
            continue
        v = u[node2]
        lowOut += lower[j]
        num += lower[j] * v
        if v > vmax:
            vmax = v
        cap = upper[j] - lower[j]
        i = m
        while i > 0 and vals[i - 1] < v:
            vals[i] = vals[i - 1]
            caps[i] = caps[i - 1]
            i -= 1
        vals[i] = v
        caps[i] = cap
        m += 1
    if f > 0.0 and unlOut > 0 and bo > -np.inf:
        capIn += f * unlIn
        if bo > vmax:
            vmax = bo
        i = m
        while i > 0 and vals[i - 1] < bo:
            vals[i] = vals[i - 1]
            caps[i] = caps[i - 1]
            i -= 1
        vals[i] = bo
        caps[i] = f * unlOut
        m += 1
    if m == 0:
        return -np.inf
    m_min = lowOut
    if 1.0 - capIn > m_min:
        m_min = 1.0 - capIn
    if m_min <= 0.0:
        return vmax  # leak an arbitrarily small mass to the best outside successor
    # fill the extra m_min - lowOut greedily, then keep adding while it raises the ratio
    need = m_min - lowOut
    mass = lowOut
    t = 0
    while t < m and need > 0.0:
        take = caps[t] if caps[t] < need else need
        num += take * vals[t]
        mass += take
        need -= take
        caps[t] -= take
        if caps[t] <= 0.0:
            t += 1
    max_mass = 1.0 - lowIn
    while t < m and mass < max_mass and vals[t] * mass > num:
        take = caps[t] if caps[t] < max_mass - mass else max_mass - mass
        num += take * vals[t]
        mass += take
        t += 1
    err = (8.0 * (j1 - j0) + 32.0) * U
    if mass - err <= 0.0:
        return vmax
    ratio = (num + err) / (mass - err)
    return ratio if ratio < vmax else vmax


@njit(cache=True)
def stay_exit_bounds(state_ptr, row_ptr, col, lower, upper, floor, nxt, comp, comp_cnt,
                     row_vals, u, best_out, best_out_comp, second_out, adv_max, ctrl, strat, out_state):
    """Per node (l, q) in a component, the deflation bound of its rows (see solve.py, Lemma D).

    comp (L*n,) int: component of each node (-1: none); comp_cnt (L, C): per layer l and
    component c, the number of q' with comp[nxt[l,q'], q'] == c.
    Minimising adversary: a row that can stay inside its component (some admissible p has
    support inside) is bounded by -inf (it cannot beat the others); otherwise by its upper
    Bellman value ``row_vals[l*R + r]``.  Maximising adversary: a row that cannot leave gives
    -inf; otherwise the largest ``u`` of a possible successor outside the component (for
    floor mass: the largest ``u`` outside the component, ``best_out``).
    The controller combines rows by max (ctrl 0), min (1) or its fixed row (2).
    """
    L = nxt.shape[0]
    n = state_ptr.shape[0] - 1
    R = row_ptr.shape[0] - 1
    maxk = 1
    for r in range(R):
        if row_ptr[r + 1] - row_ptr[r] > maxk:
            maxk = row_ptr[r + 1] - row_ptr[r]
    keys = np.empty(maxk + 1)
    vals = np.empty(maxk + 1)
    for l in range(L):
        for q in range(n):
            node = l * n + q
            c = comp[node]
            if c < 0:
                continue
            r0, r1 = _rows(state_ptr, q, ctrl, strat, node)
            agg = -np.inf if ctrl != _MIN else np.inf
            for r in range(r0, r1):
                lowOut = 0.0
                upIn = 0.0
                listedIn = 0
                bestListedOut = -np.inf
                anyOut = False
                for j in range(row_ptr[r], row_ptr[r + 1]):
                    q2 = col[j]
                    if comp[nxt[l, q2] * n + q2] == c:
                        upIn += upper[j]
                        listedIn += 1
                    else:
                        lowOut += lower[j]
                        if upper[j] > 0.0:
                            anyOut = True
                            v2 = u[nxt[l, q2] * n + q2]
                            if v2 > bestListedOut:
                                bestListedOut = v2
                f = floor[r]
                k = row_ptr[r + 1] - row_ptr[r]
                unlIn = comp_cnt[l, c] - listedIn
                unlOut = (n - k) - unlIn
                if adv_max:
                    b = -np.inf
                    if anyOut or (f > 0.0 and unlOut > 0):
                        bo = -np.inf
                        if f > 0.0 and unlOut > 0:
                            bo = best_out[l] if best_out_comp[l] != c else second_out[l]
                        b = _exit_ratio(row_ptr[r], row_ptr[r + 1], col, lower, upper, nxt, comp, c, l, n, u,
                                        f, unlIn, unlOut, bo, keys, vals)
                else:
                    # stay-able: no lower mass outside and enough capacity inside (conservative:
                    # declared stay-able only with a relative margin covering the rounding)
                    cap = upIn + f * unlIn
                    stay = lowOut == 0.0 and cap - _sum_slack(listedIn, f > 0.0 and unlIn > 0) >= 1.0
                    b = -np.inf if stay else row_vals[l * R + r]
                if ctrl == _MIN:
                    if b < agg:
                        agg = b
                else:
                    if b > agg:
                        agg = b
            out_state[node] = agg


@njit(cache=True)
def stayable_rows(state_ptr, row_ptr, col, lower, upper, floor, nxt, comp, comp_cnt, rowmask, liberal):
    """(L*R,) bool: row r in layer l (in ``rowmask``) has an admissible distribution supported
    inside the component of its node.  ``liberal``: also when it may have one within the
    rounding of the capacity sum (then a row that can stay is never missed, so a component found
    free of end components is free of them: the unique-fixed-point argument of the lower OVI
    guesses); otherwise conservative (only when it surely has one)."""
    L = nxt.shape[0]
    n = state_ptr.shape[0] - 1
    R = row_ptr.shape[0] - 1
    out = np.zeros(L * R, dtype=np.bool_)
    for l in range(L):
        for q in range(n):
            c = comp[l * n + q]
            if c < 0:
                continue
            for r in range(state_ptr[q], state_ptr[q + 1]):
                if not rowmask[l * R + r]:
                    continue
                lowOut = 0.0
                upIn = 0.0
                listedIn = 0
                for j in range(row_ptr[r], row_ptr[r + 1]):
                    q2 = col[j]
                    if comp[nxt[l, q2] * n + q2] == c:
                        upIn += upper[j]
                        listedIn += 1
                    else:
                        lowOut += lower[j]
                unlIn = comp_cnt[l, c] - listedIn
                cap = upIn + floor[r] * unlIn
                slack = _sum_slack(listedIn, floor[r] > 0.0 and unlIn > 0)
                # lowOut == 0 is exact: a float sum of non-negative numbers is 0 iff all are 0
                out[l * R + r] = lowOut == 0.0 and (cap + slack >= 1.0 if liberal else cap - slack >= 1.0)
    return out


@njit(cache=True)
def response_end_components(members, state_ptr, row_ptr, col, lower, upper, nxt, lo, adv_max, ctrl, strat):
    """End components of the adversary's *response* to the lower vector ``lo``: the family of
    sets that :func:`_deflate` needs when the maximal end components are too coarse (Kelmendi
    et al. CAV 2018 restrict the minimiser to its optimal actions for the same reason).

    Each row (s, a) of a node in ``members`` is replaced by the support of the adversary's
    ordering solution against ``lo`` (lowest ``lo`` first for a minimising adversary, highest
    first for a maximising one; floor mass ignored); a row whose support leaves ``members`` is
    dropped.  The maximal end components of that graph (SCCs, drop rows whose support leaves
    their SCC, repeat) are returned as (comp (L*n,) int, -1 outside, count).

    Example: a node whose row 1 can stay on itself (upper 1 on the self-loop) while row 2 exits
    to a value 0.025 lies in a maximal end component with a neighbour that exits at 0.039; that
    component's Lemma D cap is 0.039 and the upper iterates stall there, while the singleton
    found here has the cap 0.025.  Lemma D holds for *any* set, so the family only decides how
    fast the upper bounds converge, never whether they are sound.
    """
    L = nxt.shape[0]
    n = state_ptr.shape[0] - 1
    m = members.shape[0]
    pos = np.full(L * n, -1, dtype=np.int64)
    for t in range(m):
        pos[members[t]] = t
    # rows of the members and their response supports (local indices)
    n_rows = 0
    n_ent = 0
    for t in range(m):
        r0, r1 = _rows(state_ptr, members[t] % n, ctrl, strat, members[t])
        n_rows += r1 - r0
        n_ent += row_ptr[r1] - row_ptr[r0]
    row_node = np.empty(n_rows, dtype=np.int64)
    sup_ptr = np.zeros(n_rows + 1, dtype=np.int64)
    sup = np.empty(n_ent, dtype=np.int64)
    alive = np.zeros(n_rows, dtype=np.bool_)
    rr = 0
    ne = 0
    for t in range(m):
        node = members[t]
        l = node // n
        q = node - l * n
        r0, r1 = _rows(state_ptr, q, ctrl, strat, node)
        for r in range(r0, r1):
            j0 = row_ptr[r]
            k = row_ptr[r + 1] - j0
            vals = np.empty(k)
            rem = 1.0
            for i in range(k):
                d = nxt[l, col[j0 + i]] * n + col[j0 + i]
                vals[i] = -lo[d] if adv_max else lo[d]
                rem -= lower[j0 + i]
            order = np.argsort(vals, kind="mergesort")
            inside = True
            start = ne
            for i in order:
                j = j0 + i
                take = upper[j] - lower[j]
                if rem <= 0.0 or take <= 0.0:
                    take = 0.0
                elif take > rem:
                    take = rem
                rem -= take
                if lower[j] > 0.0 or take > 0.0:
                    d = nxt[l, col[j]] * n + col[j]
                    if pos[d] < 0:
                        inside = False
                    else:
                        sup[ne] = pos[d]
                        ne += 1
            if not inside:
                ne = start
            row_node[rr] = t
            alive[rr] = inside and ne > start
            sup_ptr[rr + 1] = ne
            rr += 1
    # maximal end components of the response graph
    lab = np.full(m, -1, dtype=np.int64)
    nc = 0
    while True:
        indptr = np.zeros(m + 1, dtype=np.int64)
        for r in range(n_rows):
            if alive[r]:
                indptr[row_node[r] + 1] += sup_ptr[r + 1] - sup_ptr[r]
        for t in range(m):
            indptr[t + 1] += indptr[t]
        indices = np.empty(indptr[m], dtype=np.int64)
        fill = indptr[:m].copy()
        for r in range(n_rows):
            if alive[r]:
                t = row_node[r]
                for e in range(sup_ptr[r], sup_ptr[r + 1]):
                    indices[fill[t]] = sup[e]
                    fill[t] += 1
        lab, nc = strong_components(indptr, indices)
        changed = False
        for r in range(n_rows):
            if alive[r]:
                c = lab[row_node[r]]
                for e in range(sup_ptr[r], sup_ptr[r + 1]):
                    if lab[sup[e]] != c:
                        alive[r] = False
                        changed = True
                        break
        if not changed:
            break
    has_row = np.zeros(nc, dtype=np.bool_)
    for r in range(n_rows):
        if alive[r]:
            has_row[lab[row_node[r]]] = True
    newid = np.full(nc, -1, dtype=np.int64)
    cnt = 0
    for c in range(nc):
        if has_row[c]:
            newid[c] = cnt
            cnt += 1
    comp = np.full(L * n, -1, dtype=np.int64)
    for t in range(m):
        comp[members[t]] = newid[lab[t]]
    return comp, cnt



@njit(cache=True)
def self_loops(indptr, indices):
    """(N,) bool: node v has an edge to itself."""
    N = indptr.shape[0] - 1
    out = np.zeros(N, dtype=np.bool_)
    for v in range(N):
        for e in range(indptr[v], indptr[v + 1]):
            if indices[e] == v:
                out[v] = True
                break
    return out


def _end_components(imdp, nxt, active, ctrl, flat_strat, want_sccs=False):
    """Components for the deflation step (Lemma D in the docstring of :mod:`robust_imdp.solvers.engine`).

    Any set works for soundness; tight sets make the iteration converge.  We use the
    maximal end components of the graph of *stay-able* rows (rows with an admissible
    distribution supported inside the component), found by the usual refinement: SCCs of the
    listed positive-upper edges, drop rows that cannot stay, repeat.  Stay-ability is tested
    liberally and the refinement stops after 8 rounds at the latest, so every end component lies
    inside a returned component (invariant of the refinement: an end component is strongly
    connected through its own rows, which stay inside it); nodes outside them are in no end
    component.  Returns (comp (L*n,) int with -1 for none, number of components, comp_cnt
    (L, C), sccs): with ``want_sccs``, ``sccs`` = (labels of the strongly connected components of
    all active nodes, in reverse topological order (Tarjan), -1 elsewhere; self-loop flags).
    """
    L, n = nxt.shape
    N = L * n
    act = active.reshape(-1)
    sccs = None
    if not act.any():
        return np.full(N, -1), 0, np.zeros((L, 0), dtype=np.int64), sccs
    R = imdp.n_choices
    rowmask = np.ones(L * R, dtype=bool)
    if ctrl == _FIXED:
        rowmask[:] = False
        rsel = (imdp.state_ptr[:-1][None, :] + flat_strat.reshape(L, n)) + (np.arange(L) * R)[:, None]
        rowmask[rsel.reshape(-1)] = True
    comp = np.full(N, -1, dtype=np.int64)
    ncomp = 0
    for _ in range(8):
        indptr, indices = edge_csr(imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.upper, nxt, rowmask, act)
        lab, nc = strong_components(indptr, indices)
        if want_sccs and sccs is None:  # first round: the components of the whole graph
            sccs = (np.where(act, lab, -1), self_loops(indptr, indices))
        del indptr, indices
        lab = np.where(act, lab, -1)
        cnt = np.zeros((L, nc), dtype=np.int64)
        for l in range(L):
            lab_succ = lab.reshape(L, n)[nxt[l], np.arange(n)]
            ok = lab_succ >= 0
            cnt[l] = np.bincount(lab_succ[ok], minlength=nc)
        # liberal: every end component survives the refinement (Lemma D holds for any set C)
        stay = stayable_rows(imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper, imdp.floor, nxt,
                             lab, cnt, rowmask, True)
        newmask = rowmask & stay
        same = np.array_equal(lab, comp)
        comp = lab
        ncomp = nc
        if np.array_equal(newmask, rowmask) and same:
            break
        rowmask = newmask
    # keep only components with at least one stay-able row (others need no deflation)
    has_stay = np.zeros(ncomp + 1, dtype=bool)
    node_of_row = (np.arange(L)[:, None] * n + imdp.row_state[None, :]).reshape(-1)
    c_of_row = comp[node_of_row]
    has_stay[c_of_row[rowmask & (c_of_row >= 0)]] = True
    keep = has_stay[:ncomp]
    newid = np.cumsum(keep) - 1
    comp = np.where((comp >= 0) & keep[np.maximum(comp, 0)], newid[np.maximum(comp, 0)], -1)
    cnt = cnt[:, keep] if ncomp else cnt
    return comp, int(keep.sum()), np.ascontiguousarray(cnt), sccs


def _response_family(imdp, nxt, lo, members, adv_max, ctrl, flat_strat):
    """(comp, count, comp_cnt) of :func:`response_end_components` against ``lo``, in the form
    :func:`_deflate` takes (comp_cnt as in :func:`_end_components`)."""
    L, n = nxt.shape
    nx = np.ascontiguousarray(nxt, dtype=np.int64)
    comp, nc = response_end_components(members, imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper,
                                       nx, lo.reshape(-1), adv_max, ctrl, flat_strat)
    cnt = np.zeros((L, nc), dtype=np.int64)
    if nc:
        for l in range(L):
            lab_succ = comp.reshape(L, n)[nx[l], np.arange(n)]
            ok = lab_succ >= 0
            cnt[l] = np.bincount(lab_succ[ok], minlength=nc)
    return comp, nc, cnt
