"""Value iteration with sound lower and upper bounds (issue 2, items 3-4; issue 11).

Contract
--------
``solve_reachability(imdp, target, *, avoid, adversary, objective, horizon, precision)`` and
``evaluate_strategy(imdp, target, strategy, ...)`` return a frozen :class:`ReachabilityResult`
whose ``lower``/``upper`` bracket the true value of every state.

Soundness (why every printed bound is on the safe side)
-------------------------------------------------------
Let B be the Bellman operator of the (controller, adversary) pair: targets fixed to 1, avoid
states to 0, ``B(x)(s) = opt_a adv_{p in P(s,a)} p.x``.  B is monotone and the reachability
value V* is its *least* fixed point (for every combination max/min x max/min).

* **Lower**: ``l_0`` = indicator of the target <= V*; ``l_{k+1} = max(l_k, B_down(l_k))`` where
  ``B_down`` is B evaluated in floating point minus a proven bound of its rounding error
  (``ROW_ERR``, derivation below).  By monotonicity ``B_down(l) <= B(l) <= B(V*) = V*``.
  Unbounded iteration without floors updates in place (Gauss-Seidel): every partially
  updated vector is still a vector of lower bounds, so the same argument applies per node.
  (Upper bounds likewise with ``min``; k-step values use plain Jacobi sweeps.)
* **Graph pre-computation** (exact, integer/boolean): (a) the nodes with V* = 0 (no admissible
  way to put positive probability on the target; liberal in borderline cases, so it never
  zeroes a positive value) and (a') for a maximising controller or a fixed strategy the nodes
  with V* = 1 (almost-sure reachability, nested fixed point; conservative, so it never claims
  1 wrongly).  Both are fixed like avoid states / targets.
* **Upper**: (b) ``u_0 = 1`` elsewhere and ``u_{k+1} = min(u_k, B_up(u_k))``, sound since
  ``u >= V*`` implies ``B_up(u) >= B(u) >= B(V*) = V*``.  End components make (b) stall at a
  larger fixed point, so (d) the first iterations and every 4th one also apply
* **Lemma D (deflation)**.  Let C be any set of non-target nodes and u >= V*.  Call a row
  (s, a), s in C, *stay-able* if some admissible p has support inside C.  Define the row bound
  ``b(s, a)``: for a minimising adversary, -inf if the row is stay-able and ``B_a(u)(s)``
  otherwise; for a maximising adversary, -inf if no admissible p leaves C, otherwise (an
  upper bound of) the conditional exit average ``sup {p_out.u / p(out) : p(out) > 0}``.
  Let ``b(s)`` combine the rows as the controller does (max, min, or its fixed row) and
  ``e = max_{s in C} b(s)``.  Then ``V* <= max(e, 0)`` on C.
  *Proof.*  Put ``V' = min(V*, max(e, 0))`` on C and ``V' = V*`` elsewhere, so V' <= V* and
  ``B(V') <= B(V*) = V*``.  For s in C and a row a: a stay-able row under a minimising
  adversary gives ``B_a(V')(s) <= p_C.V' <= max_C V' <= max(e,0)``; a non-stay-able one
  ``<= B_a(V*)(s) <= B_a(u)(s) <= e``; under a maximising adversary every p gives
  ``p.V' <= p(C) max(e,0) + p_out.u <= p(C) max(e,0) + p(out) b(s,a) <= max(e,0)``.  Hence
  ``B(V') <= V'``, V' is a pre-fixed point, and by Knaster-Tarski V* = lfp <= V'.  QED.
  The lemma holds for *any* C; we apply it to the maximal end components of the stay-able
  rows (Haddad & Monmege 2014; Baier et al. CAV 2017; the game version is Kelmendi et al.
  CAV 2018), which is what makes the upper iterates converge in the usual cases.  When they
  do not within ``max_iterations``, the result says ``converged=False`` and a
  ``ConvergenceWarning`` is issued; the bracket is still sound.
* **Fixing the pre-computed nodes keeps the least fixed point.**  Let B' be B with the nodes of
  (a)/(a') fixed to 0/1.  V* is a fixed point of B'; for w = lfp(B') <= V*, B(w) = B'(w) = w on
  the other nodes, ``B(w) <= B(V*) = 0 = w`` on the value-0 nodes and ``B(w) <= 1 = w`` on the
  value-1 nodes, so w is a pre-fixed point of B and w >= V*: lfp(B') = V*.  Below, B means B'.
* **Lemma OVI (optimistic value iteration, Hartmanns & Kaminski CAV 2020).**  Any u with
  ``B(u) <= u`` satisfies ``u >= V*`` (Knaster-Tarski: the least fixed point is the least
  pre-fixed point).  We check it with ``B_up >= B``, so rounding can only make the check fail.
  The check is a Gauss-Seidel sweep ``u(s) <- B_up(u)(s)`` over the nodes in order; if no value
  increased, the final u_f is proven: with u^(s) the vector when s was processed, u_f <= u^(s)
  (values only decreased), hence ``B(u_f)(s) <= B(u^(s))(s) <= B_up(u^(s))(s) = u_f(s)``.
  Guesses: ``u = min(proven upper, lower + delta)`` once the lower iteration's estimated error
  is below delta, or the Aitken extrapolation of the lower iterates plus a margin (see
  :func:`ovi_component`); a refuted or undecided guess is discarded (the last proven vector is
  restored), so only proven vectors are ever reported.
* **OVI with end components** (Jacobi checks, :func:`_ovi_jacobi`).  Rounding makes ``B_up(u) <=
  u`` fail where a row can stay in a cycle of equal values, so a node s of an end component C
  may pass instead by ``cap_C <= u(s)``, with ``cap_C = max(0, e_C)`` Lemma D's bound computed
  from u (row values ``B_up(u)``, exit ratios of u).  If every node passes one way, u >= V*.
  *Proof.*  Let P be the nodes passing by the cap, ``w = cap_C`` on P (of C) and ``w = u``
  elsewhere, ``V' = min(V*, w) <= u``.  On C, ``V' <= cap_C`` everywhere: on P by definition,
  elsewhere in C because such a node failed the cap (``u < cap_C``).  At s in P every row gives
  at most cap_C: a stay-able row (minimising adversary) ``p.V' <= max_C V'``, a non-stay-able
  one ``B_a(V')(s) <= B_a(u)(s) <= e_C``, a maximising adversary ``p.V' <= p(C) cap_C + p_out.u
  <= cap_C``; elsewhere ``B(V')(s) <= B(u)(s) <= u(s) = w(s)``.  With ``B(V') <= B(V*) = V*``,
  V' is a pre-fixed point, so V* <= V' <= u.  QED.
* **Lower guesses** need a unique fixed point.  In a component C without end component (no set
  D in C where every node has a row with an admissible p supported in D; found liberally, see
  :func:`_end_components`) the restricted operator has one: for fixed points x, y let
  M = max(x - y) > 0 be attained on D; at s in D take x's row a and y's adversary choice p_y of
  that row (or symmetrically, depending on who maximises); then
  ``M = x(s) - y(s) <= p_y.(x - y) <= M`` forces p_y into D (the outside is common, difference
  0 < M), so D would be an end component.  Hence ``x <= B(x)`` implies x <= gfp = lfp = V*
  (Knaster-Tarski), checked by a Gauss-Seidel sweep ``x(s) <- B_down(x)(s)`` that decreased no
  value (the mirror image of the upper argument).
* **Topological order.**  Components C of the graph of possible successors are solved in
  reverse topological order; when C is solved, every successor outside C has its final
  bracket l <= V* <= u.  Lower sweeps on C read l outside: still below V* by monotonicity.
  For the upper end let ``B_C(x) = B(x on C, u outside)`` and ``B*_C(x) = B(x on C, V* outside)
  <= B_C(x)``.  V*_C is the least fixed point of B*_C (if y = lfp(B*_C) <= V*_C, the vector
  (y on C, V* outside) is a pre-fixed point of B, hence >= V*).  So ``B_C(u_C) <= u_C`` gives
  ``u_C >= lfp(B_C) >= lfp(B*_C) = V*_C``, and interval iteration on C (and Lemma D, which
  holds for any set C) is sound from a proven start as before.  Components without an end
  component have a unique fixed point (every strategy and adversary leave them), which is
  what makes the guesses succeed; components with one use the checks with Lemma D's caps
  above, falling back to interval iteration with Lemma D.

Strategy extraction: rows within ``_TIE_TOL`` of the best (w.r.t. the final lower values) are
optimal; among them a backward attractor picks rows that make progress toward the target, so a
maximising strategy is never trapped in an end component by a tie.  Ties are broken
lexicographically when the optimistic (max, max) solve is given (``tie_break``): among the
optimal rows through which a node joins the attractor, the one with the largest optimistic row
value ``max_p p.U`` (U the proven upper bound of the max-max value, the p_up_star vector of
synthesis) wins; a node the attractor never reaches -- its lower value is 0 for every row, e.g.
the nodes the graph pre-computation proved 0 -- takes the optimistic solve's own
(progress-making) row.  Choosing there by ``max_p p.U`` alone would not do: a row that stays in
a set of equal U values (a self-loop) ties with the best row, and the strategy could circle
forever.  Changing the rows of nodes whose value under the strategy is 0 cannot lower the
value of any other node: with ``y_k = B_pi^k(0)`` and ``x_k = B_pi'^k(0)``, pi' = pi off those
nodes Z, induction gives ``x_k >= y_k`` (``y_k = 0`` on Z, B monotone elsewhere), and the least
fixed points are the limits.  The strategy's bounds are always re-evaluated by the caller
(:func:`robust_imdp.synthesis.core.synthesize` checks they keep the optimal lower value).

Hot loop: numba (``@njit(cache=True)``), serial.  A numpy formulation needs a per-row sort
(``np.lexsort`` over all nnz entries each iteration) and several nnz-sized temporaries.  The
default engine's sweep (:func:`node_sweep`) keeps each row's order of successor values from the
previous sweep (1 byte per entry) and re-sorts by insertion, which costs O(k) once the order has
settled, and prefetches the successor values of the entries ``PREFETCH_DISTANCE`` ahead (the
gathers of a large model miss the caches); ``benchmarks/results/solver.md`` has the numbers.

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

import warnings
from dataclasses import dataclass
from enum import Enum

import numpy as np
from llvmlite import ir
import numba
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from robust_imdp.errors import ConvergenceWarning, DimensionError, InvalidInputError
from robust_imdp.models.imdp import IMDP

# =========================================================================== numba kernels
U = 2.0 ** -53  # unit roundoff of float64


@njit(cache=True, inline="always")
def row_err(k):
    return (16.0 * k + 64.0) * U


@njit(cache=True, inline="always")
def _sum_slack(n_terms, with_product):
    """Bound of the rounding error of a float sum of ``n_terms`` values in [0, 1] (total <= 2),
    plus one product and addition when ``with_product``: exact (0) for a single term."""
    ops = n_terms - 1 if n_terms > 1 else 0
    if with_product:
        ops += 2
    return ops * 4.0 * U


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
    pos = 0
    for t in range(m):
        j = idx[t]
        if floor_row:
            p = rank[col[j]]
            cnt = p - pos
            if cnt > 0:
                mass = cnt * f
                if mass >= rem:
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
                    return val, 0.0
                val += f * _block(hi, lo, pos, p)
                rem -= mass
            pos = p + 1
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
            return val, 0.0
        val += f * _block(hi, lo, pos, n)
        rem -= mass
    return val, rem


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
        if direction < 0:
            v = v - row_err(j1 - j0)
            if v < 0.0:
                v = 0.0  # safe: every true value is >= 0
        elif direction > 0:
            # mass left unassigned (a row whose upper sum is below 1 within the model
            # tolerance) is credited with the largest possible value 1: stays an upper bound
            v = v + row_err(j1 - j0) + left
            if v > 1.0:
                v = 1.0  # safe: every true value is <= 1
        if want_rows:
            out_rows[r] = v
        if best < 0.0 or (ctrl == 0 and v > best) or (ctrl == 1 and v < best):
            best = v
            barg = r - state_ptr[q]
    # unbounded iteration (keep_better): keep the better of the old bound (in out_val) and
    # the new one, both sound for the same value; with out_val aliasing w this is a sound
    # Gauss-Seidel sweep.  Never for k-step values (the old bound is for k-1 steps).
    if keep_better and direction < 0:
        if best > out_val[q]:
            out_val[q] = best
    elif keep_better and direction > 0:
        if best < out_val[q]:
            out_val[q] = best
    else:
        out_val[q] = best
    out_arg[q] = barg


@njit(cache=True)
def _max_row_len(row_ptr):
    maxk = 1
    for r in range(row_ptr.shape[0] - 1):
        if row_ptr[r + 1] - row_ptr[r] > maxk:
            maxk = row_ptr[r + 1] - row_ptr[r]
    return maxk


@njit(cache=True)
def bellman_layer(state_ptr, row_ptr, col, lower, upper, floor, w, active, adv_max, use_rank,
                  rank, sv, hi, lo, ctrl, strat, direction, out_val, out_arg, out_rows, want_rows, keep_better):
    """One Bellman update of the states with ``active[q]``.

    ctrl: 0 = controller maximises over rows, 1 = minimises, 2 = fixed row ``strat[q]``.
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


#: States per parallel task of :func:`bellman_layer_parallel`, and the fewest active states of a
#: layer for which :class:`_Sweeper` uses it (benchmarks/parallel_sweep.py).
PAR_BLOCK = 1024
PAR_MIN_STATES = 16384


@njit(cache=True, parallel=True)
def bellman_layer_parallel(state_ptr, row_ptr, col, lower, upper, floor, w, active, adv_max, use_rank,
                           rank, sv, hi, lo, ctrl, strat, direction, out_val, out_arg, out_rows, want_rows,
                           keep_better):
    """:func:`bellman_layer` on numba's threads (blocks of ``PAR_BLOCK`` states).  Only for Jacobi
    sweeps (``out_val`` is not ``w``): every state's update reads ``w`` and writes its own outputs,
    so the result is the serial one, bit for bit, for any number of threads."""
    n = state_ptr.shape[0] - 1
    maxk = _max_row_len(row_ptr)
    n_blocks = (n + PAR_BLOCK - 1) // PAR_BLOCK
    for b in numba.prange(n_blocks):
        keys = np.empty(maxk)
        idx = np.empty(maxk, dtype=np.int64)
        for q in range(b * PAR_BLOCK, min(n, (b + 1) * PAR_BLOCK)):
            if active[q]:
                _bellman_state(q, state_ptr, row_ptr, col, lower, upper, floor, w, adv_max, use_rank, rank, sv, hi,
                               lo, ctrl, strat, direction, out_val, out_arg, out_rows, want_rows, keep_better, keys,
                               idx)


@njit(cache=True, inline="always")
def _rows(state_ptr, q, ctrl, strat, k):
    """Row range of state q: all its rows, or (ctrl 2) the fixed strategy's row ``strat[k]``."""
    if ctrl == 2:
        r0 = state_ptr[q] + strat[k]
        return r0, r0 + 1
    return state_ptr[q], state_ptr[q + 1]


@njit(cache=True)
def positive_attractor(state_ptr, row_ptr, col, lower, upper, floor, nxt, init, blocked,
                       ctrl, strat, adv_max):
    """States (layer, q) from which the target is reached with positive probability.

    Layered graph: node ``l*n + q``; listed successor ``q'`` of a row of ``q`` in layer ``l`` is
    node ``(nxt[l, q'], q')``; a floor row also reaches every unlisted ``q'`` with capacity floor.
    ``init`` (L*n,) bool: the target nodes; ``blocked``: nodes fixed to 0 (never added).
    A row "hits" the set W if every admissible distribution puts positive mass on W
    (minimising adversary, ``adv_max`` False) or some does (maximising adversary).
    ctrl 0: some row of the state hits; 1: every row hits; 2: the row ``strat`` hits.
    Liberal in borderline float cases (a node wrongly added only loosens upper bounds; a node
    wrongly left out would fix a positive value to 0, so the tests err toward adding).
    Returns the (L*n,) bool mask W (includes ``init``).
    """
    L = nxt.shape[0]
    n = state_ptr.shape[0] - 1
    W = init.copy()
    changed = True
    # per layer: number of q' whose successor node (nxt[l, q'], q') is in W
    cntW = np.zeros(L, dtype=np.int64)
    while changed:
        changed = False
        for l in range(L):
            c = 0
            for q2 in range(n):
                if W[nxt[l, q2] * n + q2]:
                    c += 1
            cntW[l] = c
        newW = W.copy()
        for l in range(L):
            for q in range(n):
                node = l * n + q
                if W[node] or blocked[node]:
                    continue
                r0, r1 = _rows(state_ptr, q, ctrl, strat, l * n + q)
                any_hit = False
                all_hit = True
                for r in range(r0, r1):
                    lowW = 0.0
                    upOut = 0.0
                    upW = 0.0
                    listedW = 0
                    nOut = 0
                    for j in range(row_ptr[r], row_ptr[r + 1]):
                        q2 = col[j]
                        if W[nxt[l, q2] * n + q2]:
                            lowW += lower[j]
                            upW += upper[j]
                            listedW += 1
                        elif upper[j] > 0.0:
                            upOut += upper[j]
                            nOut += 1
                    unlW = cntW[l] - listedW
                    unlOut = (n - (row_ptr[r + 1] - row_ptr[r])) - unlW
                    f = floor[r]
                    if adv_max:
                        hit = upW > 0.0 or (f > 0.0 and unlW > 0)
                    else:
                        # forced positive mass on W: lower mass on W, or the mass that can stay
                        # outside W is below 1.  Liberal: the float sum of nOut terms may be
                        # below the exact one by (nOut + 2) u, so compare with that slack.
                        slack = (nOut + 2.0) * 2.0 * U if nOut > 1 or (f > 0.0 and unlOut > 0) else 0.0
                        hit = lowW > 0.0 or (upOut + f * unlOut) < 1.0 + slack
                    if hit:
                        any_hit = True
                    else:
                        all_hit = False
                if (ctrl == 1 and all_hit) or (ctrl != 1 and any_hit):
                    newW[node] = True
                    changed = True
        W = newW
    return W


@njit(cache=True)
def almost_sure(state_ptr, row_ptr, col, lower, upper, floor, nxt, target, W, ctrl, strat, adv_max):
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
    """
    L = nxt.shape[0]
    n = state_ptr.shape[0] - 1
    Y = W.copy()
    cntX = np.zeros(L, dtype=np.int64)
    cntY = np.zeros(L, dtype=np.int64)
    while True:
        for l in range(L):
            c = 0
            for q2 in range(n):
                if Y[nxt[l, q2] * n + q2]:
                    c += 1
            cntY[l] = c
        X = target.copy()
        changed = True
        while changed:
            changed = False
            for l in range(L):
                c = 0
                for q2 in range(n):
                    if X[nxt[l, q2] * n + q2]:
                        c += 1
                cntX[l] = c
            newX = X.copy()
            for l in range(L):
                for q in range(n):
                    node = l * n + q
                    if X[node] or not Y[node]:
                        continue
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
                            newX[node] = True
                            changed = True
                            break
            X = newX
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


@njit(cache=True)
def progress_strategy(state_ptr, row_ptr, col, lower, upper, floor, nxt, target, optimal, adv_max,
                      fallback, score, tie_strat):
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
    """
    L = nxt.shape[0]
    n = state_ptr.shape[0] - 1
    R = row_ptr.shape[0] - 1
    W = target.copy()
    strat = fallback.copy()
    cntW = np.zeros(L, dtype=np.int64)
    changed = True
    while changed:
        changed = False
        for l in range(L):
            c = 0
            for q2 in range(n):
                if W[nxt[l, q2] * n + q2]:
                    c += 1
            cntW[l] = c
        newW = W.copy()
        for l in range(L):
            for q in range(n):
                node = l * n + q
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
                        changed = True
        W = newW
    for l in range(L):
        for q in range(n):
            node = l * n + q
            if W[node]:
                continue
            t = tie_strat[node]
            if t >= 0 and optimal[l * R + state_ptr[q] + t]:
                strat[node] = t
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
            agg = -np.inf if ctrl != 1 else np.inf
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
                if ctrl == 1:
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


# The default unbounded engine (``method="vi"``, models without floor rows): strongly connected
# components in reverse topological order, Gauss-Seidel sweeps over a node list, and per
# component optimistic value iteration (guess an upper vector from the lower one and prove it
# with one Bellman sweep), falling back to interval iteration.  Soundness: module docstring,
# "Optimistic value iteration" and "Topological order".

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

    mode 0 (lower): ``V[s] = max(V[s], B_down(V)(s))``, and ``incr[t]`` = the increase of
    ``nodes[t]`` when ``incr`` is not empty; 1 (upper guess check): ``V[s] = B_up(V)(s)``;
    2 (upper): ``V[s] = min(V[s], B_up(V)(s))``; 3 (lower guess check): ``V[s] = B_down(V)(s)``.
    ctrl: 0 = controller maximises over rows, 1 = minimises, 2 = fixed row ``strat[node]``.
    Returns (largest increase, largest decrease, crossed): ``crossed`` says that in mode 1 some
    ``B_up(V)(s) < other[s]`` (a proven lower bound; then V was not an upper bound, since V >= V*
    gives B(V) >= V*), or in mode 3 some ``B_down(V)(s) > other[s]`` (a proven upper bound).
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
        if ctrl == 2:
            r0 = r0 + strat[node]
            r1 = r0 + 1
        best = -1.0
        for r in range(r0, r1):
            j0 = row_ptr[r]
            j1 = row_ptr[r + 1]
            v, left = row_value_cached(j0, j1, l * nnz + j0, col, lower, upper, V, nxt, l, n, layered, adv_max,
                                       perm, keys, idx)
            if mode == 0 or mode == 3:
                v = v - row_err(j1 - j0)
                if v < 0.0:
                    v = 0.0  # safe: every true value is >= 0
            else:
                # mass left unassigned (upper sum below 1 within the model tolerance) is credited
                # with the largest possible value 1: stays an upper bound
                v = v + row_err(j1 - j0) + left
                if v > 1.0:
                    v = 1.0  # safe: every true value is <= 1
            if best < 0.0 or (ctrl == 0 and v > best) or (ctrl == 1 and v < best):
                best = v
        old = V[node]
        if mode == 0:
            d = best - old
            if d > 0.0:
                V[node] = best
                if d > inc:
                    inc = d
            else:
                d = 0.0
            if rec:
                incr[t] = d
        elif mode == 2:
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
            if (mode == 1 and best < other[node]) or (mode == 3 and best > other[node]):
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

#: Optimistic value iteration parameters (passed to the kernels at every solve):
#: [0] sweeps per check of a plain guess; [1] refuted plain guesses before the component falls
#: back to interval iteration (each asks the lower iteration for a 16x smaller estimated
#: error); [2] sweeps per check of an extrapolated guess; [3] extrapolated guesses tried per
#: component (0: none); [4] KAPPA of their offsets ``off (v + KAPPA)``; [5] lower sweeps
#: between two extrapolated guesses; [6] a shift of every guess toward the other bound (0; the
#: tests set it > 0 to feed the checks wrong guesses, which must be refuted).
OVI_PARAMS = np.array([12.0, 4.0, 2.0, 12.0, 0.25, 4.0, 0.0])


@njit(cache=True)
def _check_guess(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, V, other, ctrl, strat, adv_max,
                 mode, perm, keys, idx, n_sweeps):
    """Check sweeps of a guess in ``V`` (mode 1: upper, 3: lower); True when one of at most
    ``n_sweeps`` sweeps moved no value in the wrong direction (then V is proven), False when
    refuted (crossed the other bound) or undecided.  Returns (proven, sweeps)."""
    none = np.empty(0)
    for k in range(n_sweeps):
        inc, dec, crossed = node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, V, other, ctrl,
                                       strat, adv_max, mode, perm, keys, idx, none)
        if crossed:
            return False, k + 1
        if (mode == 1 and inc <= 0.0) or (mode == 3 and dec <= 0.0):
            return True, k + 1
    return False, n_sweeps


@njit(cache=True)
def ovi_component(nodes, c, comp, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl, strat, adv_max,
                  lo, up, perm, keys, idx, prec, max_sweeps, saved, saved_lo, incr, cen, params):
    """Solve one strongly connected component without end components to a bracket <= ``prec``.

    Its successors outside have their final brackets (width <= ``dgap``).  Optimistic value
    iteration (Hartmanns & Kaminski, CAV 2020) adapted to the interval Bellman operator, with
    Gauss-Seidel lower sweeps and two kinds of guesses, each checked by sweeps of the module
    docstring's Lemma OVI (a refuted or undecided guess is discarded, restoring the last proven
    vectors ``saved``/``saved_lo``):

    * *extrapolated* (once the per-node increments ``d`` of the lower sweeps decay by a stable
      factor lam, so ``V* ~ c = lo + d lam / (1 - lam)``, Aitken): upper ``c + dgap + off (v + KAPPA)``
      and lower ``c - off (v + KAPPA)`` with ``v = d / max(d)``; the lower one is proven by a sweep
      that decreases no value, which needs the unique fixed point of a component without end
      components (module docstring);
    * *plain*: when the estimated error ``r lam / (1 - lam)`` of the lower vector (residual r) is
      below ``tol``, the upper guess ``min(proven, lo + delta)``.

    After ``params[1]`` (``OVI_PARAMS``) refuted plain guesses: interval iteration (lower and mode-2 upper
    sweeps from the last proven upper vector, initially 1).
    Returns (sweeps, status): status ``ST_PLAIN`` (proven without a successful extrapolated
    guess), ``ST_EXTRAP`` (with one), ``ST_INTERVAL`` (by interval iteration), ``ST_OPEN`` (not
    within ``max_sweeps``; the bracket is still sound).
    """
    m = nodes.shape[0]
    none = np.empty(0)
    verify_sweeps = int(params[0])
    max_fails = int(params[1])
    extrap_sweeps = int(params[2])
    max_extrap = int(params[3])
    kappa = params[4]
    extrap_every = int(params[5])
    shift = params[6]
    dgap = _exit_gap(nodes, c, comp, n, state_ptr, row_ptr, col, upper, nxt, layered, ctrl, strat, lo, up)
    if dgap < prec:
        target = prec
        margin = prec - dgap
    else:  # the successors' brackets are already wider than prec: aim a little above them
        target = dgap + 0.5 * prec
        margin = 0.5 * prec
    delta = dgap + 0.5 * margin
    tol = 0.125 * margin
    off = 0.4 * margin / (1.0 + kappa)  # extrapolated bracket: dgap + 2 off (1 + kappa) <= target
    for t in range(m):
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
                       0, perm, keys, idx, incr)[0]
        sweeps += 1
        k += 1
        if _max_gap(nodes, lo, up) <= target:
            return sweeps, ST_EXTRAP if extrap_ok else ST_PLAIN
        lam = 1.0
        est = np.inf
        if r <= 0.0:
            est = 0.0
        elif k >= 2 and r < prev:
            lam = r / prev
            est = r * lam / (1.0 - lam)
        prev = r
        if est <= tol:
            # plain guess
            for t in range(m):
                g = lo[nodes[t]] + delta - shift
                up[nodes[t]] = g if g < saved[t] else saved[t]
            ok, s = _check_guess(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, up, lo, ctrl, strat,
                                 adv_max, 1, perm, keys, idx, min(verify_sweeps, max_sweeps - sweeps))
            sweeps += s
            if ok:
                # proven: B(u) <= u on the component (the outside is final), so u >= V*; the
                # minimum with the previously proven upper vector is an upper bound as well
                for t in range(m):
                    if saved[t] < up[nodes[t]]:
                        up[nodes[t]] = saved[t]
                return sweeps, ST_EXTRAP if extrap_ok else ST_PLAIN
            for t in range(m):
                up[nodes[t]] = saved[t]  # refuted or undecided: back to the proven vector
            fails += 1
            tol *= 0.0625
            if fails >= max_fails:
                break
            continue
        if attempts >= max_extrap or lam >= 1.0 or k < next_try:
            have_cen = False
            continue
        # Aitken extrapolation of the lower iterates, and whether it has settled
        cf = lam / (1.0 - lam)
        dmax = 0.0
        vmax = 0.0
        for t in range(m):
            x = lo[nodes[t]] + incr[t] * cf
            if have_cen and abs(x - cen[t]) > dmax:
                dmax = abs(x - cen[t])
            cen[t] = x
            if incr[t] > vmax:
                vmax = incr[t]
        settled = have_cen and dmax <= 0.1 * margin and vmax > 0.0
        have_cen = True
        if not settled:
            continue
        attempts += 1
        next_try = k + extrap_every
        have_cen = False
        # the upper guess is checked unless the proven one is already close enough
        need_up = False
        for t in range(m):
            if saved[t] - (cen[t] - off * (incr[t] / vmax + kappa)) > target:
                need_up = True
                break
        if need_up:
            for t in range(m):
                g = cen[t] + dgap + off * (incr[t] / vmax + kappa) - shift
                up[nodes[t]] = g if g < saved[t] else saved[t]
            ok, s = _check_guess(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, up, lo, ctrl, strat,
                                 adv_max, 1, perm, keys, idx, min(extrap_sweeps, max_sweeps - sweeps))
            sweeps += s
            extrap_ok = extrap_ok or ok
            for t in range(m):
                if ok and up[nodes[t]] < saved[t]:
                    saved[t] = up[nodes[t]]  # proven upper vector (min with the old one: also proven)
                up[nodes[t]] = saved[t]
        for t in range(m):
            saved_lo[t] = lo[nodes[t]]
            g = cen[t] - off * (incr[t] / vmax + kappa) + shift
            if g > saved_lo[t]:
                lo[nodes[t]] = g
        ok, s = _check_guess(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, lo, up, ctrl, strat,
                             adv_max, 3, perm, keys, idx, min(extrap_sweeps, max_sweeps - sweeps))
        sweeps += s
        extrap_ok = extrap_ok or ok
        for t in range(m):
            if not ok or lo[nodes[t]] < saved_lo[t]:
                lo[nodes[t]] = saved_lo[t] if not ok else max(lo[nodes[t]], saved_lo[t])
        if _max_gap(nodes, lo, up) <= target:
            return sweeps, ST_EXTRAP if extrap_ok else ST_PLAIN
        if ok:
            prev = np.inf  # the lower vector jumped: restart the contraction estimate
            k = 0
            next_try = 3
    while sweeps < max_sweeps:
        node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, lo, lo, ctrl, strat, adv_max, 0,
                   perm, keys, idx, none)
        node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, up, lo, ctrl, strat, adv_max, 2,
                   perm, keys, idx, none)
        sweeps += 2
        if _max_gap(nodes, lo, up) <= target:
            return sweeps, ST_INTERVAL
    return sweeps, ST_OPEN


@njit(cache=True)
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


@njit(cache=True)
def solve_components(c0, order, comp_ptr, kind, comp, n, state_ptr, row_ptr, col, lower, upper, nxt, layered,
                     ctrl, strat, adv_max, lo, up, perm, prec, max_sweeps, comp_sweeps, comp_status, params):
    """Solve the components ``c0, c0+1, ...`` (reverse topological order: every successor
    component comes first) until one that contains an end component (``kind`` 2, returned for
    the caller) or the last one (returns the number of components).

    kind 0: one node without a self-loop, solved exactly by one lower and one upper step;
    kind 1: :func:`ovi_component`.  The nodes of component c are ``order[comp_ptr[c]:comp_ptr[c+1]]``.
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
        if kind[c] == 2:
            return c
        nodes = order[comp_ptr[c]:comp_ptr[c + 1]]
        if kind[c] == 0:
            node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, lo, lo, ctrl, strat, adv_max,
                       0, perm, keys, idx, none)
            node_sweep(nodes, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, up, lo, ctrl, strat, adv_max,
                       2, perm, keys, idx, none)
            comp_sweeps[c] = 2
            comp_status[c] = ST_EXACT
        else:
            s, st = ovi_component(nodes, c, comp, n, state_ptr, row_ptr, col, lower, upper, nxt, layered, ctrl,
                                  strat, adv_max, lo, up, perm, keys, idx, prec, max_sweeps, saved, saved_lo, incr,
                                  cen, params)
            comp_sweeps[c] = s
            comp_status[c] = st
    return nc


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


# =========================================================================== public API
class Adversary(str, Enum):
    """How the probabilities inside the intervals are resolved.

    PESSIMISTIC works against the objective (the robust value), OPTIMISTIC with it.
    """

    PESSIMISTIC = "pessimistic"
    OPTIMISTIC = "optimistic"


class Objective(str, Enum):
    """Whether the controller maximises or minimises the reachability probability."""

    MAXIMIZE = "maximize"
    MINIMIZE = "minimize"


def _enum(cls, value, name):
    try:
        return cls(value.value if isinstance(value, Enum) else value)
    except ValueError:
        allowed = ", ".join(repr(m.value) for m in cls)
        raise InvalidInputError(f"{name} must be one of {allowed}; got {value!r}") from None


@dataclass(frozen=True)
class ReachabilityResult:
    """Sound bracket of a reachability value.

    Attributes
    ----------
    lower, upper : (n,) float arrays
        ``lower <= true value <= upper`` for every state (rounded outward).
    strategy : (n,) int array, or (k, n) with a horizon
        Choice index within each state (``strategy[t]`` is used at time t for k-step).
    iterations : int
        Unbounded, default method: the largest number of Bellman sweeps (lower, upper and guess
        checks) spent on one strongly connected component; ``method="interval"``: lower/upper
        sweep pairs.  k-step: k.
    precision : float
        Achieved ``max(upper - lower)``.
    converged : bool
        ``precision <= requested precision``.
    """

    lower: np.ndarray
    upper: np.ndarray
    strategy: np.ndarray
    iterations: int
    precision: float
    converged: bool


def adversary_maximises(adversary, objective) -> bool:
    """True when the adversary picks the distribution maximising the reachability value."""
    a = _enum(Adversary, adversary, "adversary")
    o = _enum(Objective, objective, "objective")
    return (a is Adversary.OPTIMISTIC) == (o is Objective.MAXIMIZE)


def _as_mask(x, n, name, allow_none=False):
    if x is None:
        if allow_none:
            return np.zeros(n, dtype=bool)
        raise InvalidInputError(f"{name} must be a boolean mask of length {n} or an index array; got None")
    a = np.asarray(x)
    if a.dtype == bool:
        if a.shape != (n,):
            raise DimensionError(f"{name} as a boolean mask must have shape ({n},); got {a.shape}")
        return a.copy()
    if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
        raise InvalidInputError(f"{name} must be a boolean mask of length {n} or a 1-D integer index array; "
                                f"got dtype {a.dtype}, shape {a.shape}")
    a = a.astype(np.int64)  # an empty list arrives as float
    bad = a[(a < 0) | (a >= n)]
    if bad.size:
        raise InvalidInputError(f"{name} holds index {int(bad[0])} outside [0, {n})")
    m = np.zeros(n, dtype=bool)
    m[a] = True
    return m


def check_strategy(imdp: IMDP, strategy, name="strategy") -> np.ndarray:
    """Validate a stationary ``(n,)`` or time-varying ``(k, n)`` strategy of choice indices."""
    s = np.asarray(strategy)
    n = imdp.n_states
    if s.ndim not in (1, 2) or s.shape[-1] != n:
        raise DimensionError(f"{name} must have shape ({n},) or (k, {n}); got {s.shape}")
    if s.size and not np.issubdtype(s.dtype, np.integer):
        raise InvalidInputError(f"{name} must hold integer choice indices; got dtype {s.dtype}")
    s = s.astype(np.int64)
    nch = np.diff(imdp.state_ptr)
    bad = np.argwhere((s < 0) | (s >= nch))
    if bad.size:
        idx = tuple(int(i) for i in bad[0])
        q = idx[-1]
        raise InvalidInputError(f"{name}{list(idx)} = {int(s[idx])} is not a choice of state {q} "
                                f"(it has {int(nch[q])} choices)")
    return s


def solve_reachability(imdp: IMDP, target, *, avoid=None, adversary="pessimistic", objective="maximize",
                       horizon=None, precision=1e-8, max_iterations=100_000, method="vi", tie_break=None):
    """Sound bounds of the optimal probability to reach ``target`` while avoiding ``avoid``.

    Parameters
    ----------
    imdp : IMDP
    target, avoid : (n,) bool mask or 1-D int index array
        Target states count as reached (value 1); avoid states are absorbing failures (0).
    adversary : {"pessimistic", "optimistic"} or Adversary
    objective : {"maximize", "minimize"} or Objective
    horizon : int or None
        ``k`` gives k-step bounded reachability; None unbounded.
    precision : float
        Stop when ``max(upper - lower) <= precision`` (unbounded only).
    method : {"vi", "interval", "lp"}
        "vi" (default): strongly connected components in reverse topological order, each solved by
        optimistic value iteration with Gauss-Seidel sweeps and a proven upper vector (falls back to
        interval iteration; models with floor rows use "interval").  "interval": interval
        iteration (a lower and an upper sequence) on the whole model.  Both return proven
        brackets.  "lp" dispatches to :func:`robust_imdp.solvers.lp.solve_reachability_lp` (small models).
    tie_break : ReachabilityResult, optional
        ``objective="maximize"`` only, not with "lp": the ``adversary="optimistic"`` solve of the
        same problem.  Rows tied in the lower value are then chosen by their optimistic value
        (lexicographic choice, see "Strategy extraction" above); without it ties go to the
        first choice.

    Returns
    -------
    ReachabilityResult
        ``lower``/``upper`` (n,) sound bracket, ``strategy`` (n,) or (k, n).

    Warns
    -----
    ConvergenceWarning
        When ``max_iterations`` is hit; the returned bracket is still sound.
    """
    if method == "lp":
        if tie_break is not None:
            raise InvalidInputError("tie_break is not available with method='lp'; use 'vi' or 'interval'")
        from robust_imdp.solvers import lp  # lazy: cvxpy is imported only there (lp is below api)

        r = lp.solve_reachability_lp(imdp, target, avoid=avoid, adversary=adversary, objective=objective)
        return ReachabilityResult(r.lower, r.upper, r.strategy, r.iterations, r.precision, r.converged)
    _check_method(method)
    adv_max = adversary_maximises(adversary, objective)
    ctrl = 0 if _enum(Objective, objective, "objective") is Objective.MAXIMIZE else 1
    t, z = _target_avoid(imdp, target, avoid)
    nxt = np.zeros((1, imdp.n_states), dtype=np.int64)
    res = solve_layered(imdp, nxt, t[None, :], z[None, :], ctrl=ctrl, adv_max=adv_max, horizon=horizon,
                        precision=precision, max_iterations=max_iterations, method=method, tie_break=tie_break)
    return _single_layer(res)


def evaluate_strategy(imdp: IMDP, target, strategy, *, avoid=None, adversary="pessimistic", horizon=None,
                      precision=1e-8, max_iterations=100_000, method="vi"):
    """Sound bounds of the reachability probability of a fixed strategy (an interval Markov chain).

    ``adversary="pessimistic"`` minimises the probability (the strategy's guaranteed value),
    ``"optimistic"`` maximises it.  ``strategy`` is (n,) or (k, n) (time-varying, with a horizon
    of k steps).  ``method`` as in :func:`solve_reachability` ("vi" or "interval").  Returns a
    :class:`ReachabilityResult` whose ``strategy`` is the input.
    """
    _check_method(method)
    s = check_strategy(imdp, strategy)
    adv_max = _enum(Adversary, adversary, "adversary") is Adversary.OPTIMISTIC
    if s.ndim == 2 and (horizon is None or s.shape[0] != int(horizon)):
        raise DimensionError(f"a time-varying strategy of shape {s.shape} needs horizon={s.shape[0]}; got {horizon}")
    t, z = _target_avoid(imdp, target, avoid)
    nxt = np.zeros((1, imdp.n_states), dtype=np.int64)
    strat = s[:, None, :] if s.ndim == 2 else s[None, None, :]
    res = solve_layered(imdp, nxt, t[None, :], z[None, :], ctrl=2, adv_max=adv_max, horizon=horizon,
                        precision=precision, max_iterations=max_iterations, strategy=strat, method=method)
    return _single_layer(res)


def _check_method(method):
    if method not in ("vi", "interval"):
        raise InvalidInputError(f"method must be 'vi', 'interval' or 'lp'; got {method!r}")


def _target_avoid(imdp, target, avoid):
    n = imdp.n_states
    t = _as_mask(target, n, "target")
    z = _as_mask(avoid, n, "avoid", allow_none=True)
    if not t.any():
        raise InvalidInputError("target must contain at least one state; got an empty target")
    both = np.flatnonzero(t & z)
    if both.size:
        raise InvalidInputError(f"target and avoid must be disjoint; state {int(both[0])} is in both")
    return t, z


def _single_layer(res: ReachabilityResult) -> ReachabilityResult:
    strat = res.strategy[:, 0, :] if res.strategy.ndim == 3 else res.strategy[0]
    return ReachabilityResult(lower=res.lower[0], upper=res.upper[0], strategy=strat,
                              iterations=res.iterations, precision=res.precision, converged=res.converged)


# =========================================================================== layered engine
class _Sweeper:
    """Bellman sweeps over value arrays ``V`` (L, n) of a layered model (L = 1: plain IMDP).

    Node (l, q) moves under a row of q to (nxt[l, q'], q') -- the lazy product's rule
    (issue 3, standard semantics) -- so the successor values of layer l are the gather
    ``w_l[q'] = V[nxt[l, q'], q']`` and the base rows are reused unchanged.
    """

    def __init__(self, imdp, nxt, active, ctrl, adv_max, strategy):
        self.m = imdp
        self.nxt = np.ascontiguousarray(nxt, dtype=np.int64)
        self.L, self.n = self.nxt.shape
        self.active = active
        self.ctrl = ctrl
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


def solve_layered(imdp, nxt, target, zero, *, ctrl, adv_max, horizon=None, precision=1e-8,
                  max_iterations=100_000, strategy=None, method="vi", tie_break=None) -> ReachabilityResult:
    """Engine shared by :func:`solve_reachability`, :func:`evaluate_strategy` and the lazy product.

    Parameters
    ----------
    nxt : (L, n) int
        Layer of the successor q' when moving from layer l (``delta(s, L(q'))`` for the product).
    target, zero : (L, n) bool
        Nodes with value fixed to 1 / to 0 (``zero`` wins over ``target``).
    ctrl : 0 maximise, 1 minimise, 2 fixed ``strategy`` ((1 or k, L, n) choice indices).
    adv_max : bool
        The adversary maximises the value (else minimises).
    tie_break : result of the optimistic solve, optional
        Only for ``ctrl=0``: an object with ``upper`` (L, n) and ``strategy`` (L, n), the
        (max, max) solve of the same model (``ctrl=0, adv_max=True``).  Rows tied in the lower
        value are then chosen by their optimistic value (see "Strategy extraction" in the module
        docstring).  k-step: only its presence matters; the optimistic values of every step are
        recomputed alongside the lower ones (one more sweep per step).

    Returns a ReachabilityResult with (L, n) arrays and a (L, n) or (k, L, n) strategy.
    """
    if horizon is not None:
        horizon = int(horizon)
        if horizon < 0:
            raise InvalidInputError(f"horizon must be a non-negative integer or None; got {horizon}")
    if not (np.isfinite(precision) and precision > 0):
        raise InvalidInputError(f"precision must be a positive number; got {precision!r}")
    L, n = nxt.shape
    target = target & ~zero
    active = ~(target | zero)
    V0 = target.astype(np.float64)
    if strategy is not None:
        strategy = np.ascontiguousarray(strategy, dtype=np.int64)
    if tie_break is not None:
        tie_break = _check_tie_break(tie_break, imdp, L, n, ctrl, horizon)
    sw = _Sweeper(imdp, nxt, active, ctrl, adv_max, strategy)
    if horizon is not None:
        return _bounded(sw, V0, horizon, ctrl, strategy, tie_break)
    return _unbounded(sw, imdp, nxt, target, zero, active, ctrl, adv_max, strategy, precision, max_iterations,
                      method, tie_break)


def _check_tie_break(tie_break, imdp, L, n, ctrl, horizon):
    """``(upper (L, n) float, strategy (L, n) int)`` of an optimistic result, checked; k-step: ``()``."""
    if ctrl != 0:
        raise InvalidInputError(f"tie_break applies to a maximising controller only (ctrl=0); got ctrl={ctrl}")
    if not (hasattr(tie_break, "upper") and hasattr(tie_break, "strategy")):
        raise InvalidInputError("tie_break must be the result of the optimistic solve of the same model (with "
                                f"'upper' and 'strategy'); got {type(tie_break).__name__}")
    if horizon is not None:
        return ()
    up = np.asarray(tie_break.upper, dtype=np.float64)
    st = np.asarray(tie_break.strategy)
    if L == 1 and up.shape == (n,):  # a single-layer ReachabilityResult
        up = up[None, :]
    if up.shape != (L, n) or st.shape not in ((L, n), (n,) if L == 1 else (L, n)):
        raise DimensionError(f"tie_break must come from a solve of the same model: upper ({L}, {n}) and an "
                             f"({L}, {n}) stationary strategy; got upper {np.shape(tie_break.upper)}, "
                             f"strategy {st.shape}")
    return np.ascontiguousarray(up), np.ascontiguousarray(st.reshape(L, n), dtype=np.int64)


def _optimistic_rows(imdp, nxt, mask, U):
    """Per row (index ``l*R + r``) its value under the maximising adversary against ``U`` (L, n),
    rounded up; -inf for the rows of nodes outside ``mask``.  Only used to order tied rows."""
    sw = _Sweeper(imdp, nxt, mask, 0, True, None)
    _, _, rows = sw.sweep(U, +1, want_rows=True)
    return rows


def _lex_choice(rows_lo, rows_up, state_ptr, arg):
    """Per node, among the rows within ``_TIE_TOL`` of its best lower row value ``rows_lo``
    (L, R), the first one with the largest ``rows_up``; ``arg`` where no row was evaluated."""
    L = rows_lo.shape[0]
    nch = np.diff(state_ptr)
    has = nch > 0
    starts = state_ptr[:-1][has]
    out = arg.copy()
    lo = np.where(np.isfinite(rows_lo), rows_lo, -1.0)
    best_lo = np.maximum.reduceat(lo, starts, axis=1)
    optimal = (lo >= np.repeat(best_lo, nch[has], axis=1) - _TIE_TOL) & np.isfinite(rows_lo)
    sc = np.where(optimal, rows_up, -np.inf)
    best = np.maximum.reduceat(sc, starts, axis=1)
    is_best = optimal & (sc >= np.repeat(best, nch[has], axis=1))
    pos = np.where(is_best, np.arange(rows_lo.shape[1])[None, :], rows_lo.shape[1])
    first = np.minimum.reduceat(pos, starts, axis=1)  # (L, number of states with rows)
    ok = np.isfinite(best)
    q_idx = np.flatnonzero(has)
    for l in range(L):
        sel = ok[l]
        out[l, q_idx[sel]] = first[l, sel] - starts[sel]
    return out


def _bounded(sw, V0, k, ctrl, strategy, tie_break=None):
    """k-step values by k exact Bellman steps, rounded down (lower) and up (upper).

    With ``tie_break`` the optimistic (max, max) k-step values ``U_t`` are iterated alongside and
    the decision with t steps to go is, among the rows within ``_TIE_TOL`` of the best lower row
    value, the one of largest optimistic value ``B_row(U_{t-1})`` (no cycles to fear: the
    strategy is time-varying and every chosen row is optimal for the lower recursion).
    """
    lo = V0.copy()
    up = V0.copy()
    opt = V0.copy()
    opt_sw = None if tie_break is None else _Sweeper(sw.m, sw.nxt, sw.active, 0, True, None)
    R = sw.m.n_choices
    strat = np.zeros((k,) + V0.shape, dtype=np.int64)
    for t in range(1, k + 1):
        # with t steps to go the decision is the one taken at time k - t
        sl = None if strategy is None else (k - t if strategy.shape[0] == k else 0)
        lo_rows = opt_sw is not None
        new_lo, arg, rows_lo = sw.sweep(lo, -1, strat_layer=sl, want_rows=lo_rows)
        up, _, _ = sw.sweep(up, +1, strat_layer=sl)
        if opt_sw is not None:
            opt, _, rows_up = opt_sw.sweep(opt, +1, want_rows=True)
            arg = _lex_choice(rows_lo.reshape(-1, R), rows_up.reshape(-1, R), sw.m.state_ptr, arg)
        lo = new_lo
        strat[k - t] = arg
    if ctrl == 2:
        strat = np.broadcast_to(strategy, strat.shape).copy() if strategy.shape[0] == k else np.repeat(strategy, k, 0)
    prec = float(np.max(up - lo)) if up.size else 0.0
    return ReachabilityResult(lower=lo, upper=up, strategy=strat, iterations=k, precision=prec, converged=True)


def _unbounded(sw, imdp, nxt, target, zero, active, ctrl, adv_max, strategy, precision, max_iterations, method,
               tie_break=None):
    L, n = nxt.shape
    flat_strat = strategy[0].reshape(-1) if strategy is not None else np.zeros(1, dtype=np.int64)
    # (a) graph pre-computation: nodes that reach the target with positive probability
    W = positive_attractor(imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper, imdp.floor,
                           nxt, target.reshape(-1), zero.reshape(-1), ctrl, flat_strat, adv_max)
    one = np.zeros(L * n, dtype=bool)
    if ctrl != 1:
        # value exactly 1 (almost-sure reachability); not computed for a minimising controller
        one = almost_sure(imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper, imdp.floor, nxt,
                          target.reshape(-1), W, ctrl, flat_strat, adv_max)
    W = W.reshape(L, n)
    one = one.reshape(L, n) & ~target
    zero_all = zero | (active & ~W)  # value exactly 0: the target cannot be reached
    fixed1 = target | one  # value exactly 1: fixed like targets (lower = upper = 1 is sound)
    active2 = active & W & ~one
    sw.active = active2
    sw.layers = [l for l in range(L) if active2[l].any()]
    lo = fixed1.astype(np.float64)
    up = np.where(zero_all, 0.0, 1.0)
    topo = method == "vi" and not imdp.has_floor
    comp, ncomp, comp_cnt, sccs = _end_components(imdp, nxt, active2, ctrl, flat_strat, want_sccs=topo)
    if topo:
        # components in reverse topological order, optimistic value iteration in each
        it = _topological(imdp, nxt, lo, up, active2, ctrl, adv_max, flat_strat, precision, max_iterations, sccs,
                          (comp, ncomp, comp_cnt))
        gap = float(np.max(up - lo)) if up.size else 0.0
    elif method == "vi":
        # floor rows: optimistic value iteration with Jacobi sweeps on the whole model
        lo, up, it = _ovi_jacobi(sw, imdp, nxt, lo, up, active2, ctrl, adv_max, flat_strat, precision,
                                 max_iterations, (comp, ncomp, comp_cnt))
        gap = float(np.max(up - lo)) if up.size else 0.0
    else:
        # interval iteration on the whole model (floor rows: their global order needs Jacobi sweeps)
        it = 0
        gap = float(np.max(up - lo)) if up.size else 0.0
        members = np.flatnonzero(active2.reshape(-1)) if ncomp else None
        while gap > precision and it < max_iterations:
            it += 1
            lo, up, _ = _interval_step(sw, imdp, nxt, lo, up, it, (comp, ncomp, comp_cnt), members, adv_max, ctrl,
                                       flat_strat)
            gap = float(np.max(up - lo))
    converged = gap <= precision
    if not converged:
        warnings.warn(f"value iteration stopped after {it} iterations with max(upper - lower) = {gap:.3g} > "
                      f"precision {precision:g}; the returned bounds are sound but loose", ConvergenceWarning,
                      stacklevel=3)
    # strategy: optimal rows w.r.t. the final lower values (value-1 nodes included), ties
    # broken toward progress to the *original* target
    sw.active = active2 | one
    sw.layers = [l for l in range(L) if sw.active[l].any()]
    _, arg, rows = sw.sweep(lo, -1, want_rows=(ctrl == 0))
    if ctrl == 0:
        R = imdp.n_choices
        rv = rows.reshape(L, R)
        # best-row value of each node (computed with the same rounding) and a tie tolerance
        rowbest = np.maximum.reduceat(np.where(np.isfinite(rv), rv, -1.0), imdp.state_ptr[:-1], axis=1)
        optimal = rv >= np.repeat(rowbest, np.diff(imdp.state_ptr), axis=1) - _TIE_TOL
        # nodes the graph pre-computation proved 0 (not swept above): every row is optimal
        proven0 = active & ~sw.active
        optimal |= np.repeat(proven0, np.diff(imdp.state_ptr), axis=1)
        if tie_break is None:
            score = np.full(L * R, -np.inf)
            tie_strat = np.full(L * n, -1, dtype=np.int64)
        else:
            score = _optimistic_rows(imdp, nxt, active, tie_break[0])
            tie_strat = tie_break[1].reshape(-1)
        strat = progress_strategy(imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper, imdp.floor,
                                  nxt, target.reshape(-1), optimal.reshape(-1), adv_max, arg.reshape(-1),
                                  score, tie_strat)
        strat = strat.reshape(L, n)
    elif ctrl == 2:
        strat = strategy[0].copy()
    else:
        strat = arg
    return ReachabilityResult(lower=lo, upper=up, strategy=strat, iterations=it, precision=gap, converged=converged)


#: Rows whose (rounded) value is within this of the best row count as optimal (tied) for strategy
#: extraction.  Far below any precision a user asks for (>= 1e-10 in practice, 1e-8 by default),
#: so a tied row loses nothing the reported bracket could show; far above the rounding error of
#: one row (``ROW_ERR`` ~ 1e-14 for rows of a few dozen entries), so rows of equal value that
#: were rounded differently still tie.  Exact ties (the rows of a node whose lower value is 0)
#: need no tolerance at all.
_TIE_TOL = 1e-12


def _end_components(imdp, nxt, active, ctrl, flat_strat, want_sccs=False):
    """Components for the deflation step (Lemma D in the module docstring).

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
    if ctrl == 2:
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


def _deflation_caps(imdp, nxt, up, rows, comp, ncomp, comp_cnt, adv_max, ctrl, flat_strat):
    """Lemma D's cap ``max(0, e_C)`` of every node in a component C (+inf elsewhere), from the
    vector ``up`` and its upper row values ``rows`` (``_Sweeper.sweep(up, +1, want_rows=True)``)."""
    L, n = nxt.shape
    uf = up.reshape(-1)
    best_out = np.zeros(L)
    best_out_comp = np.full(L, -2, dtype=np.int64)
    second_out = np.zeros(L)
    if adv_max and imdp.has_floor:
        for l in range(L):
            w = up[nxt[l], np.arange(n)]
            cs = comp.reshape(L, n)[nxt[l], np.arange(n)]
            i = int(np.argmax(w))
            best_out[l] = w[i]
            best_out_comp[l] = cs[i] if cs[i] >= 0 else -2
            other = w[cs != cs[i]] if cs[i] >= 0 else w
            second_out[l] = other.max() if other.size else 0.0
    bound = np.full(L * n, -np.inf)
    stay_exit_bounds(imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper, imdp.floor, nxt, comp,
                     comp_cnt, rows, uf, best_out, best_out_comp, second_out, adv_max, ctrl, flat_strat, bound)
    e = np.full(ncomp, -np.inf)
    inc = comp >= 0
    np.maximum.at(e, comp[inc], bound[inc])
    cap = np.full(L * n, np.inf)
    cap[inc] = np.maximum(e, 0.0)[comp[inc]]  # Lemma D with e = -inf: every row stays, the value is 0
    return cap


def _deflate(imdp, nxt, up, rows, comp, ncomp, comp_cnt, adv_max, ctrl, flat_strat):
    """Lemma D: in each component C, ``V* <= max(0, e_C)``; apply ``up <- min(up, max(0, e_C))``."""
    uf = up.reshape(-1)
    np.minimum(uf, _deflation_caps(imdp, nxt, up, rows, comp, ncomp, comp_cnt, adv_max, ctrl, flat_strat), out=uf)


def _ovi_jacobi(sw, imdp, nxt, lo, up, active, ctrl, adv_max, flat_strat, precision, max_iterations, mec,
                dgap=0.0):
    """Optimistic value iteration with Jacobi sweeps on the ``active`` nodes: models with floor
    rows (whose global order forbids Gauss-Seidel and whose floors connect everything: one
    component), and components holding end components (``dgap``: the largest bracket width of
    a successor outside, as in :func:`ovi_component`).

    The guesses of :func:`ovi_component` (plain and extrapolated), with Jacobi checks: an upper
    guess u is proven when at every node ``B_up(u) <= u`` or, for a node of an end component C,
    Lemma D's cap of C computed from u is <= u there (module docstring, "OVI with end
    components"); a lower guess x (only without end components: unique fixed point) when
    ``B_down(x) >= x``.  Falls back to interval iteration with deflation.  Returns
    (lo, up, sweeps).
    """
    comp, ncomp, comp_cnt = mec
    p = np.asarray(OVI_PARAMS, dtype=np.float64)
    verify, max_fails, extrap_sweeps, max_extrap, kappa, every, shift = (
        int(p[0]), int(p[1]), int(p[2]), int(p[3]), float(p[4]), int(p[5]), float(p[6]))
    act = active
    inmec = act & (comp.reshape(act.shape) >= 0)
    unique = ncomp == 0
    if dgap < precision:
        target, margin = precision, precision - dgap
    else:  # the successors' brackets are already wider than precision: aim a little above them
        target, margin = dgap + 0.5 * precision, 0.5 * precision
    delta, tol, off = dgap + 0.5 * margin, 0.125 * margin, 0.4 * margin / (1.0 + kappa)
    sweeps = 0

    idx = np.flatnonzero(act.reshape(-1))  # per-sweep work stays O(component), not O(model)

    def gap():
        return float(np.max(up.reshape(-1)[idx] - lo.reshape(-1)[idx])) if idx.size else 0.0

    def check_upper(u):
        """(proven, B_up(u)) for the guess u; counts its sweep."""
        new, _, rows = sw.sweep(u, +1, want_rows=ncomp > 0)
        bad = act & (new > u)
        if ncomp and np.any(bad & inmec):
            cap = _deflation_caps(imdp, nxt, u, rows, comp, ncomp, comp_cnt, adv_max, ctrl, flat_strat).reshape(u.shape)
            bad &= ~(inmec & (cap <= u))
        return not bad.any(), new

    def try_upper(g):
        nonlocal up, sweeps
        u = np.where(act, np.minimum(up, g), up)
        for _ in range(verify):
            ok, new = check_upper(u)
            sweeps += 1
            if ok:
                up = np.minimum(u, new)  # u >= V* proven, so B_up(u) >= V* as well
                return True
            if np.any(new[act] < lo[act]):
                return False  # B_up(u) < lo <= V*: u was not an upper bound
            u = np.where(act, new, up)
        return False

    def try_lower(g):
        nonlocal lo, sweeps
        x = np.where(act, np.maximum(lo, g), lo)
        for _ in range(extrap_sweeps):
            new = sw.sweep(x, -1)[0]
            sweeps += 1
            if np.all(new[act] >= x[act]):
                lo = np.maximum(x, new)  # x <= V* proven (unique fixed point), so B_down(x) <= V* too
                return True
            if np.any(new[act] > up[act]):
                return False
            x = np.where(act, new, lo)
        return False

    fails = attempts = k = 0
    prev = np.inf
    next_try = 3
    cen = None
    while sweeps < max_iterations and fails < max_fails and gap() > target:
        old = lo.reshape(-1)[idx]  # a copy (the sweep may update lo in place: Gauss-Seidel)
        lo = sw.sweep(lo, -1, inplace=True)[0]
        sweeps += 1
        k += 1
        dm = lo.reshape(-1)[idx] - old  # >= 0: lower sweeps keep max(old, new)
        r = float(dm.max()) if dm.size else 0.0
        if gap() <= target:
            break
        lam, est = 1.0, np.inf
        if r <= 0.0:
            est = 0.0
        elif k >= 2 and r < prev:
            lam = r / prev
            est = r * lam / (1.0 - lam)
        prev = r
        if est <= tol:
            if try_upper(lo + delta - shift) and gap() <= target:
                break
            fails += 1
            tol *= 0.0625
            continue
        if attempts >= max_extrap or lam >= 1.0 or k < next_try:
            cen = None
            continue
        d = np.zeros_like(lo)
        d.reshape(-1)[idx] = dm
        c = lo + d * (lam / (1.0 - lam))
        settled = cen is not None and float(np.max(np.abs(np.where(act, c - cen, 0.0)))) <= 0.1 * margin and r > 0
        cen = c
        if not settled:
            continue
        attempts += 1
        next_try = k + every
        cen = None
        v = d / r + kappa
        if np.max(np.where(act, up - (c - off * v), 0.0)) > target:
            try_upper(c + dgap + off * v - shift)
        if unique and try_lower(c - off * v + shift):
            prev, k, next_try = np.inf, 0, 3  # the lower vector jumped: restart the estimate
    # interval iteration with deflation (also the fallback); every RESPONSE_EVERY-th iteration
    # Lemma D is applied to the end components of the adversary's response to lo as well
    # (:func:`response_end_components`), and the loop stops early when a whole period changed
    # no value (a fixed point of the iteration: more sweeps cannot help)
    it = 0
    last = None
    while gap() > target and sweeps < max_iterations:
        it += 1
        lo, up, responded = _interval_step(sw, imdp, nxt, lo, up, it, mec, idx, adv_max, ctrl, flat_strat)
        if responded:
            now = (lo.reshape(-1)[idx], up.reshape(-1)[idx])  # copies
            if last is not None and np.array_equal(now[0], last[0]) and np.array_equal(now[1], last[1]):
                break  # nothing changed in a whole period
            last = now
        sweeps += 2
    return lo, up, sweeps


#: Period (in interval-iteration steps) of the deflation with the response end components.
RESPONSE_EVERY = 8


def _interval_step(sw, imdp, nxt, lo, up, it, mec, members, adv_max, ctrl, flat_strat):
    """Step ``it`` (from 1) of interval iteration with deflation: a lower and an upper sweep
    (each keeps the better of old and new bound), then Lemma D on the end components ``mec``
    at the first 3 and every 4th step, and on the response end components of ``members``
    against ``lo`` every RESPONSE_EVERY-th step (deflation is an optional tightening, sound
    whenever applied).  Returns (lo, up, whether the response family was applied)."""
    comp, ncomp, comp_cnt = mec
    lo = sw.sweep(lo, -1, inplace=True)[0]
    deflate = ncomp > 0 and (it <= 3 or it % 4 == 0)
    respond = ncomp > 0 and it % RESPONSE_EVERY == 0
    up, _, rows = sw.sweep(up, +1, want_rows=deflate or respond, inplace=True)
    if deflate:
        _deflate(imdp, nxt, up, rows, comp, ncomp, comp_cnt, adv_max, ctrl, flat_strat)
    if respond:
        rcomp, rn, rcnt = _response_family(imdp, nxt, lo, members, adv_max, ctrl, flat_strat)
        if rn:
            _deflate(imdp, nxt, up, rows, rcomp, rn, rcnt, adv_max, ctrl, flat_strat)
    return lo, up, respond


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


def _topological(imdp, nxt, lo, up, active, ctrl, adv_max, flat_strat, precision, max_iterations, sccs, mec):
    """Unbounded values by components in reverse topological order (models without floor rows).

    ``sccs`` = (label (L*n,) of the strongly connected components of the active nodes, in
    reverse topological order, -1 for inactive nodes; self-loop flags); ``mec`` = the
    end-component labels of :func:`_end_components`.  ``lo``/``up`` (L, n) are updated in place.
    Returns the largest number of sweeps spent on one component.
    """
    L, n = nxt.shape
    act = active.reshape(-1)
    nodes = np.flatnonzero(act)
    if nodes.size == 0:
        return 0
    lab, has_self = sccs
    mcomp, nmec, mcnt = mec
    # components in label order (Tarjan numbers them sinks first), nodes in index order inside
    order = nodes[np.argsort(lab[nodes], kind="stable")]
    ls = lab[order]
    first = np.flatnonzero(np.r_[True, ls[1:] != ls[:-1]])
    comp_ptr = np.r_[first, order.size].astype(np.int64)
    nc = first.size
    comp = np.full(L * n, -1, dtype=np.int64)
    comp[order] = np.repeat(np.arange(nc), np.diff(comp_ptr))
    size = np.diff(comp_ptr)
    kind = np.where((size == 1) & ~has_self[order[first]], 0, 1).astype(np.int64)
    if nmec:
        in_mec = np.zeros(nc, dtype=bool)
        in_mec[comp[mcomp >= 0]] = True
        kind[in_mec] = 2
    strat = flat_strat if ctrl == 2 else np.zeros(1, dtype=np.int64)
    nx = np.ascontiguousarray(nxt, dtype=np.int64).reshape(-1)  # flat: node (l, q') -> layer of its successor
    level = np.zeros(nc, dtype=np.int64)
    if nmec:
        # components of one level do not depend on each other: order them by level (still
        # reverse topological), end-component ones last in their level, so that those of a level
        # are solved together by one (Python-level) call
        level = component_levels(order, comp_ptr, comp, n, imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.upper, nx,
                                 L > 1, ctrl, strat)
        new = np.lexsort((np.arange(nc), kind == 2, level))
        sizes = size[new]
        new_ptr = np.r_[0, np.cumsum(sizes)].astype(np.int64)
        order = order[np.repeat(comp_ptr[new] - new_ptr[:-1], sizes) + np.arange(order.size)]
        comp_ptr = new_ptr
        kind, level = kind[new], level[new]
        comp[order] = np.repeat(np.arange(nc), sizes)
    maxk = int(np.max(np.diff(imdp.row_ptr))) if imdp.n_choices else 1
    perm = np.empty(L * imdp.nnz, dtype=np.uint8 if maxk <= 256 else (np.uint16 if maxk <= 65536 else np.int32))
    fill_local_order(imdp.row_ptr, perm, L)
    lof, upf = lo.reshape(-1), up.reshape(-1)
    comp_sweeps = np.zeros(nc, dtype=np.int64)
    comp_status = np.zeros(nc, dtype=np.int64)
    args = (imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.lower, imdp.upper, nx, L > 1, ctrl, strat, adv_max)
    c = 0
    while c < nc:
        c = solve_components(c, order, comp_ptr, kind, comp, n, *args, lof, upf, perm, precision, max_iterations,
                             comp_sweeps, comp_status, np.asarray(OVI_PARAMS, dtype=np.float64))
        if c < nc:
            # the components holding end components of this level, together (their successors
            # outside are final: lower levels come first)
            c2 = c + 1
            while c2 < nc and kind[c2] == 2 and level[c2] == level[c]:
                c2 += 1
            members = order[comp_ptr[c]:comp_ptr[c2]]
            comp_sweeps[c:c2] = _deflated_component(imdp, nxt, lo, up, members, mcomp, mcnt, ctrl, adv_max,
                                                    flat_strat, precision, max_iterations)
            comp_status[c:c2] = ST_DEFLATED
            c = c2
    return int(comp_sweeps.max())


def _deflated_component(imdp, nxt, lo, up, members, mcomp, mcnt, ctrl, adv_max, flat_strat, precision,
                        max_iterations):
    """One component that holds end components (its successors outside have their final
    brackets): :func:`_ovi_jacobi` restricted to it, with upper guesses checked by Lemma D's caps
    and interval iteration with deflation as the fallback.  ``lo``/``up`` (L, n) are updated in
    place.  Returns the number of sweeps."""
    L, n = nxt.shape
    mask = np.zeros(L * n, dtype=bool)
    mask[members] = True
    strategy = None if ctrl != 2 else flat_strat.reshape(1, L, n)
    sw = _Sweeper(imdp, nxt, mask.reshape(L, n), ctrl, adv_max, strategy)
    # only this component's end components are used (rows elsewhere are not evaluated)
    comp = np.where(mask, mcomp, -1)
    ids = np.unique(comp[comp >= 0])
    remap = np.full(int(mcomp.max()) + 1, -1, dtype=np.int64)
    remap[ids] = np.arange(ids.size)
    comp = np.where(comp >= 0, remap[np.maximum(comp, 0)], -1)
    cnt = np.ascontiguousarray(mcnt[:, ids])
    # the largest bracket width of a possible successor outside the component
    nx = np.ascontiguousarray(nxt, dtype=np.int64).reshape(-1)
    cid = np.where(mask, 0, -1).astype(np.int64)
    strat = flat_strat if ctrl == 2 else np.zeros(1, dtype=np.int64)
    dgap = _exit_gap(members, 0, cid, n, imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.upper, nx, L > 1, ctrl, strat,
                     lo.reshape(-1), up.reshape(-1))
    new_lo, new_up, sweeps = _ovi_jacobi(sw, imdp, nxt, lo, up, mask.reshape(L, n), ctrl, adv_max, flat_strat,
                                         precision, max_iterations, (comp, ids.size, cnt), dgap=dgap)
    lo[...] = new_lo
    up[...] = new_up
    return sweeps


__all__ = ["Adversary", "Objective", "ReachabilityResult", "solve_reachability", "evaluate_strategy",
           "adversary_maximises", "check_strategy", "solve_layered"]
