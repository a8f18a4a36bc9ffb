"""Certificate weights of the RKHS route: optimal weights by a primal active-set method (the conic dual of the
vertex problem, section 3 of ``bounds/rkhs.py``'s docstring) and kernel-ridge weights over a grid of lambdas."""

from __future__ import annotations

import math

import numba
import numpy as np

from robust_imdp._atomic import fetch_add
from robust_imdp.bounds.rkhs_model import KernelModel, _certify, _lanes, _certify_parts, _vertex_functional, _weight_parts, vertex_problems

#: Ways to choose the certificate weights (see ``bounds/rkhs.py``'s docstring, sections 1-3).
METHODS = ("optimal", "ridge")
#: Ridge regularisers tried per vertex by ``method="ridge"`` and by the iid route.
RIDGE_LAMBDAS = tuple(float(v) for v in np.logspace(-9, 1, 31))
#: Largest support (number of data points with a non-zero weight) of one optimal certificate.
MAX_SUPPORT = 400


# ============================================================================ optimal weights
@numba.njit(cache=True)
def _chol_factor(P, n, L, jitter):  # pragma: no cover - compiled
    """Lower Cholesky factor of ``P[:n, :n] + jitter I`` into ``L``; False if not positive definite."""
    for j in range(n):
        s = P[j, j] + jitter
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            t = P[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / L[j, j]
    return True


@numba.njit(cache=True)
def _chol_solve(L, n, rhs, out):  # pragma: no cover - compiled
    for i in range(n):
        t = rhs[i]
        for k in range(i):
            t -= L[i, k] * out[k]
        out[i] = t / L[i, i]
    for i in range(n - 1, -1, -1):
        t = out[i]
        for k in range(i + 1, n):
            t -= L[k, i] * out[k]
        out[i] = t / L[i, i]


@numba.njit(cache=True)
def _chol_solve2(P, n, L, r1, r2, o1, o2):  # pragma: no cover - compiled
    """Cholesky factor of ``P[:n, :n]`` into ``L``; solve for two right-hand sides. False if not PD."""
    if not _chol_factor(P, n, L, 0.0):
        return False
    _chol_solve(L, n, r1, o1)
    _chol_solve(L, n, r2, o2)
    return True


#: ``_active_set``'s status codes (``optimal_weights``' ``status``).
AS_OPTIMAL, AS_ITER_CAP, AS_INCONSISTENT, AS_FACTOR_FAILED, AS_SUPPORT_CAP, AS_STALLED = 0, 1, 2, 3, 4, 5
#: Steps without a decrease of the objective after which the active set stops (anti-cycling).
_STALL_STEPS = 4


@numba.njit(cache=True)
def _restricted_system(K, ys, b, dbar, S, sg, nS, P, bSv, aS):  # pragma: no cover - compiled
    """``P = K_SS`` (+1e-11 on the diagonal), ``b_S`` and ``a_S = ys_S + dbar sg`` of the support S."""
    for p in range(nS):
        i = S[p]
        bSv[p] = b[i]
        aS[p] = ys[i] + dbar * sg[p]
        for q in range(nS):
            P[p, q] = K[i, S[q]]
        P[p, p] += 1e-11


@numba.njit(cache=True)
def _restricted_step(s0, G, sg, w, nS, bSv, aS, uu, vv, dw):  # pragma: no cover - compiled
    """The move from ``w`` towards the restricted optimum (``uu = P^{-1} b_S``, ``vv = P^{-1} a_S``) into ``dw``,
    or along the descent ray ``-vv`` when ``n >= G``; ``(alpha, jmin, unbounded)``: the step length, stopped
    at the first sign change (index ``jmin``, -1 if none)."""
    rho2 = s0
    n2 = 0.0
    for p in range(nS):
        rho2 -= bSv[p] * uu[p]
        n2 += aS[p] * vv[p]
    if rho2 < 1e-300:
        rho2 = 1e-300
    unbounded = n2 >= G * G * (1.0 - 1e-12)
    if not unbounded:
        t = math.sqrt(rho2) / math.sqrt(G * G - n2)
        for p in range(nS):
            dw[p] = uu[p] - t * vv[p] - w[p]
        alpha = 1.0
    else:
        for p in range(nS):
            dw[p] = -vv[p]
        alpha = np.inf
    jmin = -1
    for p in range(nS):
        if sg[p] * dw[p] < 0.0:
            a = -w[p] / dw[p]
            if a < alpha:
                alpha = a
                jmin = p
    return alpha, jmin, unbounded


@numba.njit(cache=True)
def _drop_index(S, sg, w, nS, jmin, inS):  # pragma: no cover - compiled
    """Remove index ``jmin`` and every weight of the wrong sign from the support; its new size."""
    k = 0
    for p in range(nS):
        if p == jmin or sg[p] * w[p] <= 0.0:
            inS[S[p]] = False
            continue
        S[k] = S[p]
        sg[k] = sg[p]
        w[k] = w[p]
        k += 1
    return k


@numba.njit(cache=True)
def _objective_parts(K, ys, b, s0, dbar, S, w, nS, Kw):  # pragma: no cover - compiled
    """``Kw = K w`` and ``(r2, Fv)``: ``s0 - 2 b.w + w.K w`` and ``ys.w + dbar ||w||_1`` on the support."""
    m = K.shape[0]
    for j in range(m):
        Kw[j] = 0.0
    r2 = s0
    Fv = 0.0
    for p in range(nS):
        i = S[p]
        r2 -= 2.0 * w[p] * b[i]
        Fv += w[p] * ys[i] + dbar * abs(w[p])
        wp = w[p]
        for j in range(m):  # K is symmetric: read row i (contiguous) for column i
            Kw[j] += K[i, j] * wp
    for p in range(nS):
        r2 += w[p] * Kw[S[p]]
    return r2, Fv


@numba.njit(cache=True)
def _keep_best(S, w, nS, bS_idx, bw):  # pragma: no cover - compiled
    """Copy the support and its weights into ``bS_idx[:nS], bw[:nS]``."""
    for p in range(nS):
        bS_idx[p] = S[p]
        bw[p] = w[p]


@numba.njit(cache=True)
def _most_violated(ys, b, dbar, G, Kw, r, inS, tol):  # pragma: no cover - compiled
    """The index outside S whose condition ``|f*(x_j) - ys_j| <= dbar`` (``f* = G (phi - Phi* w)/r``) is
    violated most, by more than ``tol``, and its sign: ``(jadd, sadd)``, ``jadd = -1`` if none."""
    worst = tol
    jadd = -1
    sadd = 0.0
    for j in range(Kw.shape[0]):
        if inS[j]:
            continue
        f = G * (b[j] - Kw[j]) / r
        viol = abs(f - ys[j]) - dbar
        if viol > worst:
            worst = viol
            jadd = j
            sadd = 1.0 if f > ys[j] else -1.0
    return jadd, sadd


@numba.njit(cache=True)
def _active_set(K, ys, b, s0, dbar, G, S, sg, w, nS, cap, max_iter, tol, bS_idx, bw, P, L):  # pragma: no cover
    """Approximately ``min_w ys.w + dbar ||w||_1 + G sqrt(s0 - 2 b.w + w.K w)`` (a heuristic).

    Primal active-set method on the sign-constrained orthant: on a support S with signs sg the
    smooth restricted problem has the closed form ``w = P^{-1}(b_S - t a_S)``, ``P = K_SS``,
    ``a = ys_S + dbar sg``, ``t = rho / sqrt(G^2 - n^2)`` with ``rho^2 = s0 - b_S.P^{-1} b_S`` and
    ``n^2 = a.P^{-1} a`` (minimise ``a.w + G sqrt(rho^2 + (w - P^{-1}b).P(w - P^{-1}b))``). From
    the current sign-consistent point we move towards it (or along the descent ray ``-P^{-1}a``
    when ``n >= G``) and stop at the first sign change, dropping that index; at a restricted
    optimum the most violated optimality condition outside S, ``|f*(x_j) - ys_j| <= dbar`` with
    ``f* = G (phi - Phi* w)/r``, adds an index. Stops when no condition is violated by more
    than ``tol``, when the objective stalls (anti-cycling), or after ``max_iter`` steps.

    ``S, sg, w`` hold a warm start in their first ``nS`` entries and receive the result; the
    best point met is returned in ``bS_idx[:nb], bw[:nb]``. ``P`` and ``L`` are (cap, cap)
    workspaces allocated once by the caller: allocating them per call costs a page-faulting
    mmap each time where glibc's mmap threshold is fixed (Dask workers set
    MALLOC_TRIM_THRESHOLD_, measured 1.7x slower). Returns ``(nS, nb, iters, status)``
    (status 0 optimal, 1 iteration cap, 2 data inconsistent with the norm bound, 3 factorisation
    failed, 4 support cap, 5 stalled: the ``AS_*`` constants).
    """
    m = K.shape[0]
    inS = np.zeros(m, dtype=np.bool_)
    for k in range(nS):
        inS[S[k]] = True
    bSv = np.empty(cap)
    aS = np.empty(cap)
    uu = np.empty(cap)
    vv = np.empty(cap)
    dw = np.empty(cap)
    Kw = np.empty(m)
    status = AS_ITER_CAP
    it = 0
    nb = 0
    Fbest = np.inf
    stall = 0
    restricted_ok = False
    while it < max_iter:
        it += 1
        if not restricted_ok:
            _restricted_system(K, ys, b, dbar, S, sg, nS, P, bSv, aS)
            if nS > 0:
                if not _chol_solve2(P, nS, L, bSv, aS, uu, vv):
                    status = AS_FACTOR_FAILED
                    break
            alpha, jmin, unbounded = _restricted_step(s0, G, sg, w, nS, bSv, aS, uu, vv, dw)
            if jmin < 0 and unbounded:
                status = AS_INCONSISTENT
                break
            for p in range(nS):
                w[p] += alpha * dw[p]
            if jmin >= 0:
                nS = _drop_index(S, sg, w, nS, jmin, inS)
                continue
            restricted_ok = True
        # at a restricted optimum: objective and optimality conditions outside S
        r2, Fv = _objective_parts(K, ys, b, s0, dbar, S, w, nS, Kw)
        if not r2 > 0.0:
            status = AS_OPTIMAL
            nb = nS
            _keep_best(S, w, nS, bS_idx, bw)
            break
        r = math.sqrt(r2)
        Fv += G * r
        if Fv < Fbest - 1e-13 * (1.0 + abs(Fv)):
            Fbest = Fv
            stall = 0
            nb = nS
            _keep_best(S, w, nS, bS_idx, bw)
        else:
            stall += 1
            if stall >= _STALL_STEPS:
                status = AS_STALLED
                break
        jadd, sadd = _most_violated(ys, b, dbar, G, Kw, r, inS, tol)
        if jadd < 0:
            status = AS_OPTIMAL
            break
        if nS >= cap:
            status = AS_SUPPORT_CAP
            break
        S[nS] = jadd
        sg[nS] = sadd
        w[nS] = 0.0
        inS[jadd] = True
        nS += 1
        restricted_ok = False
    return nS, nb, it, status


def optimal_weights(model: KernelModel, b, s0: float, *, noise: float, rkhs_bound: float, side: int = 1,
                    max_iter: int = 5000, tol: float = 1e-12):
    """The optimiser of :func:`cell_ranges` for one functional: weights approximately minimising
    ``side w.y + noise ||w||_1 + rkhs_bound ||phi - Phi* w||`` (``b = Phi phi``, ``s0 >= <phi, phi>``).

    Returns
    -------
    w : (m,) float array (dense)
    status : int
        0 optimal, 1 iteration cap, 2 data inconsistent with the bound, 3 factorisation failed,
        4 support cap, 5 stalled (see :func:`_active_set`).
    """
    m = model.m
    cap = int(min(m, MAX_SUPPORT))
    S = np.zeros(cap, dtype=np.int64)
    sg = np.zeros(cap)
    w = np.zeros(cap)
    bidx = np.zeros(cap, dtype=np.int64)
    bw = np.zeros(cap)
    ys = np.ascontiguousarray(float(side) * model.y)
    _, nb, _, status = _active_set(model.K, ys, np.ascontiguousarray(b, float), float(s0), float(noise),
                                   float(rkhs_bound), S, sg, w, 0, cap, int(max_iter), float(tol), bidx, bw,
                                   np.empty((cap, cap)), np.empty((cap, cap)))
    out = np.zeros(m)
    out[bidx[:nb]] = bw[:nb]
    return out, int(status)


@numba.njit(cache=True)
def _largest_group(group):  # pragma: no cover - compiled
    """Length of the longest run of equal consecutive entries of ``group`` (most sub-boxes of one cell)."""
    best = 1 if group.shape[0] > 0 else 0
    run = 1
    for q in range(1, group.shape[0]):
        run = run + 1 if group[q] == group[q - 1] else 1
        if run > best:
            best = run
    return best


def _optimal_cells(X, y, K, K_err, inv_l2, c, r, signs, dbar, G, cap, max_iter, tol, ptr, lin, prune, group):
    """:func:`_optimal_cells_coef` without the coefficients: ``val, support, status``."""
    val, sup, stat, _ = _optimal_cells_coef(X, y, K, K_err, inv_l2, c, r, signs, dbar, G, cap, max_iter, tol, ptr,
                                            lin, prune, group, _lanes())
    return val, sup, stat


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: the chunk writer runs beside it
def _optimal_cells_coef(X, y, K, K_err, inv_l2, c, r, signs, dbar, G, cap, max_iter, tol, ptr, lin,
                        prune, group, lanes):  # pragma: no cover - compiled
    """Certified bounds of ``<h, phi_v>`` (eq. W) with optimal weights, all cells, vertices, sides.

    Per cell and side, every vertex first gets the (certified) value of the neighbouring problem's
    weights; vertices are then optimised in the order of those values, and with ``prune`` a vertex
    whose certified value (plus ``lin``, the float known part) cannot exceed the best vertex found
    so far keeps it (status 6): the cell's bound is a maximum (upper side) or a minimum (lower side)
    over vertices, so optimising it would not change the cell bound, and any certified value is
    sound. Consecutive boxes with the same ``group`` (the sub-boxes of one cell, whose bound is
    the maximum over all of them) share that best value, and per side they are visited in the
    order of their neighbour-weight values (largest first): the sub-box that decides the cell's
    bound is optimised first and most of the others are pruned whole. Boxes ``ptr[j] .. ptr[j+1]-1``
    form one parallel work unit (warm starts run through it); ``lanes`` threads take the next unit as they come
    free (``_atomic.fetch_add``, ``rkhs_model._lanes``). Returns ``val (n, V, 2)`` (side 0:
    upper bound, side 1: lower bound), ``support (n, V, 2)``, ``status (n, V, 2)`` and ``coef (n, V, 2)``:
    the upper bound of ``||phi_v - Phi* w||`` each value used (its coefficient of G, for
    ``rkhs_model.rescale_vertex_values``).
    """
    n, d = c.shape
    V = signs.shape[0]
    m = X.shape[0]
    val = np.empty((n, V, 2))
    sup = np.zeros((n, V, 2), dtype=np.int64)
    stat = np.zeros((n, V, 2), dtype=np.int64)
    coef = np.empty((n, V, 2))
    n_chunks = ptr.shape[0] - 1
    gmax = _largest_group(group)
    nt = max(1, min(lanes, n_chunks))  # lanes take the next block as they come free (rkhs_model._lanes): same bits
    taken = np.zeros(1, dtype=np.int64)
    for t in numba.prange(nt):
        while True:
            ch = fetch_add(taken, 0, 1)
            if ch >= n_chunks:
                break
            S = np.zeros((2, cap), dtype=np.int64)
            sg = np.zeros((2, cap))
            w = np.zeros((2, cap))
            nS = np.zeros(2, dtype=np.int64)
            lastS = np.zeros((2, cap), dtype=np.int64)
            lastw = np.zeros((2, cap))
            lastn = np.zeros(2, dtype=np.int64)
            lastp = np.zeros((2, 4))  # _weight_parts of the last weights per side (w = 0: all zero)
            newp = np.zeros(4)
            bidx = np.zeros(cap, dtype=np.int64)
            bw = np.zeros(cap)
            Pw = np.empty((cap, cap))  # workspaces of _active_set, once per chunk
            Lw = np.empty((cap, cap))
            B = np.empty((gmax, V, m))  # vertex functionals of every box of the current group
            EB = np.empty((gmax, V, m))
            s0 = np.empty((gmax, V))
            cheap = np.empty((gmax, V))
            cheap_r = np.empty((gmax, V))  # the coefficient of G of each cheap value
            key = np.empty(gmax)
            border = np.zeros(gmax, dtype=np.int64)
            ys = np.empty(m)
            v = np.empty(d)
            q = ptr[ch]
            while q < ptr[ch + 1]:
                q1 = q + 1
                while q1 < ptr[ch + 1] and group[q1] == group[q]:
                    q1 += 1
                nbox = q1 - q
                for j in range(nbox):
                    for jv in range(V):
                        s0[j, jv] = _vertex_functional(X, inv_l2, c[q + j], r[q + j], signs[jv], v, B[j, jv], EB[j, jv])
                for side in range(2):
                    sgn = 1.0 if side == 0 else -1.0
                    for i in range(m):
                        ys[i] = sgn * y[i]
                    n_first = lastn[side]
                    if nbox > 1:
                        # sub-boxes: certified values of the previous weights everywhere, boxes in the
                        # order of their best vertex (any order is sound; this one prunes the most)
                        for j in range(nbox):
                            top = -np.inf
                            for jv in range(V):
                                cert = _certify_parts(lastS[side], lastw[side], lastn[side], y, B[j, jv], EB[j, jv],
                                                      K_err, s0[j, jv], dbar, 0.0, G, sgn, lastp[side])
                                cheap[j, jv] = cert[0]
                                cheap_r[j, jv] = cert[2]
                                if sgn * (lin[q + j, jv] + cheap[j, jv]) > top:
                                    top = sgn * (lin[q + j, jv] + cheap[j, jv])
                            key[j] = -top
                        border[:nbox] = np.argsort(key[:nbox])
                    else:
                        border[0] = 0
                    best = -np.inf
                    for jj in range(nbox):
                        j = border[jj]
                        qb = q + j
                        if nbox > 1 and prune and best > -np.inf:
                            top = -np.inf
                            for jv in range(V):
                                if sgn * (lin[qb, jv] + cheap[j, jv]) > top:
                                    top = sgn * (lin[qb, jv] + cheap[j, jv])
                            if top <= best:  # no vertex of this sub-box can raise the cell's bound
                                for jv in range(V):
                                    val[qb, jv, side] = cheap[j, jv]
                                    coef[qb, jv, side] = cheap_r[j, jv]
                                    sup[qb, jv, side] = n_first
                                    stat[qb, jv, side] = 6
                                continue
                        for jv in range(V):
                            cert = _certify_parts(lastS[side], lastw[side], lastn[side], y, B[j, jv], EB[j, jv], K_err,
                                                  s0[j, jv], dbar, 0.0, G, sgn, lastp[side])
                            if nbox == 1 or sgn * cert[0] < sgn * cheap[j, jv]:
                                cheap[j, jv] = cert[0]
                                cheap_r[j, jv] = cert[2]
                        order = np.argsort(-sgn * (lin[qb] + cheap[j]))
                        for k in range(V):
                            jv = order[k]
                            if prune and best > -np.inf and sgn * (lin[qb, jv] + cheap[j, jv]) <= best:
                                val[qb, jv, side] = cheap[j, jv]
                                coef[qb, jv, side] = cheap_r[j, jv]
                                sup[qb, jv, side] = lastn[side]
                                stat[qb, jv, side] = 6
                                continue
                            res = _active_set(K, ys, B[j, jv], s0[j, jv], dbar, G, S[side], sg[side], w[side], nS[side],
                                              cap, max_iter, tol, bidx, bw, Pw, Lw)
                            nS[side] = res[0]
                            nb = res[1]
                            stat[qb, jv, side] = res[3]
                            # the certificate: the best weights met (any weights are sound; none -> w = 0)
                            newp[0], newp[1], newp[2], newp[3] = _weight_parts(bidx, bw, nb, K)
                            cert = _certify_parts(bidx, bw, nb, y, B[j, jv], EB[j, jv], K_err, s0[j, jv], dbar, 0.0, G,
                                                  sgn, newp)
                            cv = cert[0]
                            cr = cert[2]
                            if sgn * cv > sgn * cheap[j, jv]:  # the neighbour's weights were better: keep them
                                cv = cheap[j, jv]
                                cr = cheap_r[j, jv]
                            val[qb, jv, side] = cv
                            coef[qb, jv, side] = cr
                            sup[qb, jv, side] = nb
                            if sgn * (lin[qb, jv] + cv) > best:
                                best = sgn * (lin[qb, jv] + cv)
                            lastn[side] = nb
                            for p in range(nb):
                                lastS[side, p] = bidx[p]
                                lastw[side, p] = bw[p]
                            for p in range(4):
                                lastp[side, p] = newp[p]
                            if prune:  # the weights just found certify the remaining vertices of this box too
                                for k2 in range(k + 1, V):
                                    j2 = order[k2]
                                    cert = _certify_parts(bidx, bw, nb, y, B[j, j2], EB[j, j2], K_err, s0[j, j2], dbar,
                                                          0.0, G, sgn, newp)
                                    if sgn * cert[0] < sgn * cheap[j, j2]:
                                        cheap[j, j2] = cert[0]
                                        cheap_r[j, j2] = cert[2]
                            if res[3] == 2 or res[3] == 3:
                                # inconsistent or ill-conditioned support: restart cold next time
                                nS[side] = 0
                q = q1
    return val, sup, stat, coef


# ============================================================================ ridge weights
@numba.njit(cache=True, parallel=True)
def _certify_dense(W, y, B, EB, K, K_err, s0, a1, a2, G):  # pragma: no cover - compiled
    """Certified (upper, lower, coefficient) of (eq. W) for dense weight columns ``W[:, k]``: the coefficient of
    G is the upper bound of ``||phi - Phi* w||`` both sides used (the same weights and functional)."""
    m, N = W.shape
    up = np.empty(N)
    lo = np.empty(N)
    coef = np.empty(N)
    idx = np.arange(m)
    for k in numba.prange(N):
        w = np.ascontiguousarray(W[:, k])
        up[k], _, coef[k] = _certify(idx, w, m, y, B[:, k], EB[:, k], K, K_err, s0[k], a1, a2, G, 1.0)
        lo[k] = _certify(idx, w, m, y, B[:, k], EB[:, k], K, K_err, s0[k], a1, a2, G, -1.0)[0]
    return up, lo, coef


def _ridge_weights(model: KernelModel, B, s0, a1: float, a2: float, G: float, lambdas=RIDGE_LAMBDAS):
    """Per column of ``B`` (m, N), ridge weights ``(K + lambda I)^{-1} b`` with the lambda that
    minimises the (float) radius ``a1 ||w||_1 + a2 ||w||_2 + G ||phi - Phi* w||``.

    The radius does not involve y, so the choice is a function of the inputs only (needed by
    the iid route). The eigendecomposition is a float approximation: it only proposes weights.
    """
    lam_k, Vk = np.linalg.eigh(model.K)
    lam_k = np.maximum(lam_k, 0.0)
    beta = Vk.T @ B  # (m, N)
    best = np.full(B.shape[1], np.inf)
    W = np.zeros_like(B)
    for lam in lambdas:
        om = beta / (lam_k + lam)[:, None]
        q = np.maximum(s0 - np.sum(beta * beta * (lam_k + 2 * lam)[:, None] / ((lam_k + lam)[:, None] ** 2), axis=0),
                       0.0)
        radius = G * np.sqrt(q)
        if a2:
            radius = radius + a2 * np.sqrt(np.sum(om * om, axis=0))
        w = None
        if a1:
            w = Vk @ om
            radius = radius + a1 * np.sum(np.abs(w), axis=0)
        better = radius < best
        if np.any(better):
            best = np.where(better, radius, best)
            W[:, better] = (Vk @ om[:, better]) if w is None else w[:, better]
    return W


def _ridge_vertex_bounds(model: KernelModel, c, r, signs, a1: float, a2: float, G: float, coef: bool = False):
    """Certified (upper, lower) bounds of ``<h, phi_v>`` (n, V) with the best ridge weights per vertex; with
    ``coef`` also their coefficient of G (n, V), the same for both sides."""
    vp = vertex_problems(model, c, r, signs)
    Bm = np.ascontiguousarray(vp["b"].reshape(-1, model.m).T)
    EB = np.ascontiguousarray(vp["b_err"].reshape(-1, model.m).T)
    s0 = vp["s0"].ravel()
    W = _ridge_weights(model, Bm, s0, a1, a2, G)
    up, lo, cf = _certify_dense(np.ascontiguousarray(W), model.y, Bm, EB, model.K, model.K_err, s0, a1, a2, G)
    V = signs.shape[0]
    if coef:
        return up.reshape(-1, V), lo.reshape(-1, V), cf.reshape(-1, V)
    return up.reshape(-1, V), lo.reshape(-1, V)
