"""Optimistic value iteration (Python level): components in reverse topological order
(:func:`_topological`, the per-component kernels of :mod:`robust_imdp.solvers.kernels`), Jacobi
optimistic value iteration for floor models and components holding end components
(:func:`_ovi_jacobi`), interval iteration with deflation (:func:`_interval_step`, Lemma D).
Why each step is sound: :mod:`robust_imdp.solvers.engine`.
"""

from __future__ import annotations

import numpy as np

from robust_imdp.solvers.graph import _response_family, stay_exit_bounds
from robust_imdp.solvers.common import Control
from robust_imdp.solvers.kernels import (KIND_END_COMPONENT, KIND_OVI, KIND_SINGLE, P_EXTRAP_EVERY, P_EXTRAP_SWEEPS,
                                         P_KAPPA, P_MAX_EXTRAP, P_MAX_FAILS, P_SHIFT, P_VERIFY_SWEEPS, ST_DEFLATED,
                                         _exit_gap, component_levels, fill_local_order, ovi_aim, solve_components)
from robust_imdp.solvers.sweep import Sweeper

#: Optimistic value iteration parameters (passed to the kernels at every solve), indexed by the
#: ``P_*`` constants of :mod:`robust_imdp.solvers.kernels`:
#: [P_VERIFY_SWEEPS] sweeps per check of a plain guess; [P_MAX_FAILS] refuted plain guesses
#: before the component falls back to interval iteration (each asks the lower iteration for a
#: 16x smaller estimated error); [P_EXTRAP_SWEEPS] sweeps per check of an extrapolated guess;
#: [P_MAX_EXTRAP] extrapolated guesses tried per component (0: none); [P_KAPPA] KAPPA of their
#: offsets ``off (v + KAPPA)``; [P_EXTRAP_EVERY] lower sweeps between two extrapolated guesses;
#: [P_SHIFT] a shift of every guess toward the other bound (0; the tests set it > 0 to feed the
#: checks wrong guesses, which must be refuted).
OVI_PARAMS = np.array([12.0, 4.0, 2.0, 12.0, 0.25, 4.0, 0.0])
assert [P_VERIFY_SWEEPS, P_MAX_FAILS, P_EXTRAP_SWEEPS, P_MAX_EXTRAP, P_KAPPA, P_EXTRAP_EVERY, P_SHIFT] == list(range(7))


def _deflation_caps(imdp, nxt, up, rows, comp, ncomp, comp_cnt, adv_max, ctrl, flat_strat):
    """Lemma D's cap ``max(0, e_C)`` of every node in a component C (+inf elsewhere), from the
    vector ``up`` and its upper row values ``rows`` (``Sweeper.sweep(up, +1, want_rows=True)``)."""
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


class _JacobiOVI:
    """One run of :func:`_ovi_jacobi`: the vectors ``lo``/``up`` (replaced, never updated in
    place, except by the in-place lower sweeps), the sweeps spent, and the checks of guesses."""

    def __init__(self, sw, imdp, nxt, lo, up, active, ctrl, adv_max, flat_strat, mec, max_iterations):
        self.sw, self.imdp, self.nxt = sw, imdp, nxt
        self.lo, self.up = lo, up
        self.act = active
        self.ctrl, self.adv_max, self.flat_strat = ctrl, adv_max, flat_strat
        self.mec = mec
        comp = mec[0]
        self.inmec = active & (comp.reshape(active.shape) >= 0)
        self.max_iterations = max_iterations
        self.sweeps = 0
        self.idx = np.flatnonzero(active.reshape(-1))  # per-sweep work stays O(component), not O(model)

    def gap(self):
        idx = self.idx
        return float(np.max(self.up.reshape(-1)[idx] - self.lo.reshape(-1)[idx])) if idx.size else 0.0

    def check_upper(self, u):
        """(proven, B_up(u)) for the guess u."""
        comp, ncomp, comp_cnt = self.mec
        act, inmec = self.act, self.inmec
        new, _, rows = self.sw.sweep(u, +1, want_rows=ncomp > 0)
        bad = act & (new > u)
        if ncomp and np.any(bad & inmec):
            cap = _deflation_caps(self.imdp, self.nxt, u, rows, comp, ncomp, comp_cnt, self.adv_max, self.ctrl,
                                  self.flat_strat).reshape(u.shape)
            bad &= ~(inmec & (cap <= u))
        return not bad.any(), new

    def try_upper(self, g, n_sweeps):
        """The upper guess ``min(up, g)``, checked by at most ``n_sweeps`` sweeps; True when proven."""
        act, lo = self.act, self.lo
        u = np.where(act, np.minimum(self.up, g), self.up)
        for _ in range(n_sweeps):
            ok, new = self.check_upper(u)
            self.sweeps += 1
            if ok:
                self.up = np.minimum(u, new)  # u >= V* proven, so B_up(u) >= V* as well
                return True
            if np.any(new[act] < lo[act]):
                return False  # B_up(u) < lo <= V*: u was not an upper bound
            u = np.where(act, new, self.up)
        return False

    def try_lower(self, g, n_sweeps):
        """The lower guess ``max(lo, g)`` (unique fixed point only), checked by at most
        ``n_sweeps`` sweeps; True when proven."""
        act, up = self.act, self.up
        x = np.where(act, np.maximum(self.lo, g), self.lo)
        for _ in range(n_sweeps):
            new = self.sw.sweep(x, -1)[0]
            self.sweeps += 1
            if np.all(new[act] >= x[act]):
                self.lo = np.maximum(x, new)  # x <= V* proven (unique fixed point), so B_down(x) <= V* too
                return True
            if np.any(new[act] > up[act]):
                return False
            x = np.where(act, new, self.lo)
        return False

    def lower_sweep(self):
        """One in-place lower sweep; returns the increments of the active nodes (>= 0)."""
        idx = self.idx
        old = self.lo.reshape(-1)[idx]  # a copy (the sweep may update lo in place: Gauss-Seidel)
        self.lo = self.sw.sweep(self.lo, -1, inplace=True)[0]
        self.sweeps += 1
        return self.lo.reshape(-1)[idx] - old  # >= 0: lower sweeps keep max(old, new)

    def guesses(self, aims, dgap, p):
        """The loop of plain and extrapolated guesses (as in :func:`ovi_component`), until the
        bracket is within the target, ``max_iterations`` sweeps or ``p[P_MAX_FAILS]`` refuted plain
        guesses."""
        target, margin, delta, tol, off = aims
        verify, max_fails, extrap_sweeps = int(p[P_VERIFY_SWEEPS]), int(p[P_MAX_FAILS]), int(p[P_EXTRAP_SWEEPS])
        max_extrap, kappa, every, shift = (int(p[P_MAX_EXTRAP]), float(p[P_KAPPA]), int(p[P_EXTRAP_EVERY]),
                                           float(p[P_SHIFT]))
        act, idx = self.act, self.idx
        unique = self.mec[1] == 0
        fails = attempts = k = 0
        prev = np.inf
        next_try = 3
        cen = None
        while self.sweeps < self.max_iterations and fails < max_fails and self.gap() > target:
            dm = self.lower_sweep()
            k += 1
            r = float(dm.max()) if dm.size else 0.0
            if self.gap() <= target:
                break
            lam, est = 1.0, np.inf
            if r <= 0.0:
                est = 0.0
            elif k >= 2 and r < prev:
                lam = r / prev
                est = r * lam / (1.0 - lam)
            prev = r
            if est <= tol:
                if self.try_upper(self.lo + delta - shift, verify) and self.gap() <= target:
                    break
                fails += 1
                tol *= 0.0625
                continue
            if attempts >= max_extrap or lam >= 1.0 or k < next_try:
                cen = None
                continue
            lo = self.lo
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
            if np.max(np.where(act, self.up - (c - off * v), 0.0)) > target:
                self.try_upper(c + dgap + off * v - shift, verify)
            if unique and self.try_lower(c - off * v + shift, extrap_sweeps):
                prev, k, next_try = np.inf, 0, 3  # the lower vector jumped: restart the estimate

    def interval(self, target):
        """Interval iteration with deflation (also the fallback); every RESPONSE_EVERY-th iteration
        Lemma D is applied to the end components of the adversary's response to lo as well
        (:func:`response_end_components`), and the loop stops early when a whole period changed
        no value (a fixed point of the iteration: more sweeps cannot help)."""
        idx = self.idx
        it = 0
        last = None
        while self.gap() > target and self.sweeps < self.max_iterations:
            it += 1
            self.lo, self.up, responded = _interval_step(self.sw, self.imdp, self.nxt, self.lo, self.up, it, self.mec,
                                                         idx, self.adv_max, self.ctrl, self.flat_strat)
            if responded:
                now = (self.lo.reshape(-1)[idx], self.up.reshape(-1)[idx])  # copies
                if last is not None and np.array_equal(now[0], last[0]) and np.array_equal(now[1], last[1]):
                    break  # nothing changed in a whole period
                last = now
            self.sweeps += 2


def _ovi_jacobi(sw, imdp, nxt, lo, up, active, ctrl, adv_max, flat_strat, precision, max_iterations, mec,
                dgap=0.0):
    """Optimistic value iteration with Jacobi sweeps on the ``active`` nodes: models with floor
    rows (whose global order forbids Gauss-Seidel and whose floors connect everything: one
    component), and components holding end components (``dgap``: the largest bracket width of
    a successor outside, as in :func:`ovi_component`).

    The guesses of :func:`ovi_component` (plain and extrapolated), with Jacobi checks: an upper
    guess u is proven when at every node ``B_up(u) <= u`` or, for a node of an end component C,
    Lemma D's cap of C computed from u is <= u there (engine docstring, "OVI with end
    components"); a lower guess x (only without end components: unique fixed point) when
    ``B_down(x) >= x``.  Falls back to interval iteration with deflation.  Returns
    (lo, up, sweeps).
    """
    p = np.asarray(OVI_PARAMS, dtype=np.float64)
    aims = ovi_aim(float(dgap), float(precision), float(p[P_KAPPA]))
    run = _JacobiOVI(sw, imdp, nxt, lo, up, active, ctrl, adv_max, flat_strat, mec, max_iterations)
    run.guesses(aims, dgap, p)
    run.interval(aims[0])
    return run.lo, run.up, run.sweeps


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
    kind = np.where((size == 1) & ~has_self[order[first]], KIND_SINGLE, KIND_OVI).astype(np.int64)
    if nmec:
        in_mec = np.zeros(nc, dtype=bool)
        in_mec[comp[mcomp >= 0]] = True
        kind[in_mec] = KIND_END_COMPONENT
    strat = flat_strat if ctrl == Control.FIXED else np.zeros(1, dtype=np.int64)
    nx = np.ascontiguousarray(nxt, dtype=np.int64).reshape(-1)  # flat: node (l, q') -> layer of its successor
    level = np.zeros(nc, dtype=np.int64)
    if nmec:
        # components of one level do not depend on each other: order them by level (still
        # reverse topological), end-component ones last in their level, so that those of a level
        # are solved together by one (Python-level) call
        level = component_levels(order, comp_ptr, comp, n, imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.upper, nx,
                                 L > 1, ctrl, strat)
        new = np.lexsort((np.arange(nc), kind == KIND_END_COMPONENT, level))
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
            while c2 < nc and kind[c2] == KIND_END_COMPONENT and level[c2] == level[c]:
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
    strategy = None if ctrl != Control.FIXED else flat_strat.reshape(1, L, n)
    sw = Sweeper(imdp, nxt, mask.reshape(L, n), ctrl, adv_max, strategy)
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
    strat = flat_strat if ctrl == Control.FIXED else np.zeros(1, dtype=np.int64)
    dgap = _exit_gap(members, 0, cid, n, imdp.state_ptr, imdp.row_ptr, imdp.col, imdp.upper, nx, L > 1, ctrl, strat,
                     lo.reshape(-1), up.reshape(-1))
    new_lo, new_up, sweeps = _ovi_jacobi(sw, imdp, nxt, lo, up, mask.reshape(L, n), ctrl, adv_max, flat_strat,
                                         precision, max_iterations, (comp, ids.size, cnt), dgap=dgap)
    lo[...] = new_lo
    up[...] = new_up
    return sweeps
