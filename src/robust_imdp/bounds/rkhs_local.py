"""Local weights: only the ``k`` data points nearest to each cell carry certificate weight (``local_points``),
so a cell's cost no longer grows with the data and no m x m kernel matrix is built."""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numba
import numpy as np

from robust_imdp._fp import U as _U, up as _up
from robust_imdp._kernels import inv_l2_up as _inv_l2, kernel_matrix as _kernel_matrix, kernel_rel_err_nb as _kernel_rel_err_nb, norm_inflation as _norm_inflation
from robust_imdp._atomic import fetch_add
from robust_imdp.bounds.rkhs_model import (CELL_BLOCK, _blocks, _lanes, _certified_norms, _certified_value, _certify, _certify_parts,
                                           _check_cells, _weight_parts,
                                           _combine_vertices, _known_at_vertices, _vertex_functional, _writable, cell_centres,
                                           scaled_norm_bound, scaled_ranges, split_counts, sub_boxes, t_max_up,
                                           vertex_signs)
from robust_imdp.bounds.rkhs_weights import METHODS, _active_set, _chol_factor, _chol_solve
from robust_imdp.errors import InvalidInputError



@numba.njit(cache=True)
def _local_group_optimal(Xp, Yp, inv_l2, c, r, signs, q0, q1, lin, Kp, K_err, a1, G, max_iter, tol, S, sg, ws, nS,
                         bidx, bw, Pw, Lw, val, sup, coef):  # pragma: no cover - compiled
    """Optimal local weights for the sub-boxes ``q0 .. q1-1`` of one cell (one pool), into ``val``/``sup``
    (and ``coef``: each value's coefficient of G, the upper bound of ``||phi_v - Phi* w||`` it used).

    Per output and side: every vertex of every sub-box first gets the certified value of the last
    weights found (none at first: ``w = 0``); sub-boxes are visited in the order of their best vertex
    ``side (lin + value)``, and a sub-box or vertex whose value cannot exceed the best optimised vertex
    so far keeps it (the cell's bound is the maximum over its sub-boxes and their vertices, eq. C on
    each sub-box; any certified value is sound). The others get active-set weights (warm-started)
    through the one certified evaluator, never worse than their previous value.
    """
    nbox = q1 - q0
    V, d = signs.shape
    k = Xp.shape[0]
    n_out = Yp.shape[1]
    Bg = np.empty((nbox, V, k))
    EBg = np.empty((nbox, V, k))
    s0g = np.empty((nbox, V))
    v = np.empty(d)
    for j in range(nbox):
        for jv in range(V):
            s0g[j, jv] = _vertex_functional(Xp, inv_l2, c[q0 + j], r[q0 + j], signs[jv], v, Bg[j, jv], EBg[j, jv])
    ys = np.empty(k)
    yo = np.empty(k)
    lastS = np.zeros(k, dtype=np.int64)
    lastw = np.zeros(k)
    lastp = np.zeros(4)  # _weight_parts of the last weights
    zero = np.zeros(4)
    cheap = np.empty((nbox, V))
    cheap_r = np.empty((nbox, V))
    key = np.empty(nbox)
    for o in range(n_out):
        for i in range(k):
            yo[i] = Yp[i, o]
        for sd in range(2):
            sgn = 1.0 if sd == 0 else -1.0
            for i in range(k):
                ys[i] = sgn * yo[i]
            lastn = 0
            lastp[:] = 0.0  # the parts of w = 0 (they must always be those of lastS, lastw, lastn)
            for j in range(nbox):
                top = -np.inf
                for jv in range(V):
                    cert = _certify_parts(lastS, lastw, 0, yo, Bg[j, jv], EBg[j, jv], K_err, s0g[j, jv], a1[o], 0.0,
                                          G, sgn, zero)
                    cheap[j, jv] = cert[0]
                    cheap_r[j, jv] = cert[2]
                    if sgn * (lin[q0 + j, jv, o] + cheap[j, jv]) > top:
                        top = sgn * (lin[q0 + j, jv, o] + cheap[j, jv])
                key[j] = -top
            border = np.argsort(key)
            best = -np.inf
            for jj in range(nbox):
                j = border[jj]
                qb = q0 + j
                if best > -np.inf:
                    top = -np.inf
                    for jv in range(V):
                        if sgn * (lin[qb, jv, o] + cheap[j, jv]) > top:
                            top = sgn * (lin[qb, jv, o] + cheap[j, jv])
                    if top <= best:  # no vertex of this sub-box can move the cell's bound
                        for jv in range(V):
                            val[qb, jv, o, sd] = cheap[j, jv]
                            coef[qb, jv, o, sd] = cheap_r[j, jv]
                            sup[qb, jv, o, sd] = 0
                        continue
                for jv in range(V):
                    cert = _certify_parts(lastS, lastw, lastn, yo, Bg[j, jv], EBg[j, jv], K_err, s0g[j, jv], a1[o],
                                          0.0, G, sgn, lastp)
                    if sgn * cert[0] < sgn * cheap[j, jv]:
                        cheap[j, jv] = cert[0]
                        cheap_r[j, jv] = cert[2]
                order = np.argsort(-sgn * (lin[qb, :, o] + cheap[j]))
                for kk in range(V):
                    jv = order[kk]
                    if best > -np.inf and sgn * (lin[qb, jv, o] + cheap[j, jv]) <= best:
                        val[qb, jv, o, sd] = cheap[j, jv]
                        coef[qb, jv, o, sd] = cheap_r[j, jv]
                        sup[qb, jv, o, sd] = lastn
                        continue
                    res = _active_set(Kp, ys, Bg[j, jv], s0g[j, jv], a1[o], G, S[o, sd], sg[o, sd], ws[o, sd],
                                      nS[o, sd], k, max_iter, tol, bidx, bw, Pw, Lw)
                    nS[o, sd] = res[0] if (res[3] != 2 and res[3] != 3) else 0
                    nb = res[1]
                    # eq. W for the active-set weights (the one certified evaluator), or the previous value
                    lastp[0], lastp[1], lastp[2], lastp[3] = _weight_parts(bidx, bw, nb, Kp)
                    cert = _certify_parts(bidx, bw, nb, yo, Bg[j, jv], EBg[j, jv], K_err, s0g[j, jv], a1[o], 0.0, G,
                                          sgn, lastp)
                    cv = cert[0]
                    cr = cert[2]
                    if sgn * cv > sgn * cheap[j, jv]:
                        cv = cheap[j, jv]
                        cr = cheap_r[j, jv]
                    val[qb, jv, o, sd] = cv
                    coef[qb, jv, o, sd] = cr
                    sup[qb, jv, o, sd] = nb
                    if sgn * (lin[qb, jv, o] + cv) > best:
                        best = sgn * (lin[qb, jv, o] + cv)
                    lastn = nb
                    for p in range(nb):
                        lastS[p] = bidx[p]
                        lastw[p] = bw[p]
                    for k2 in range(kk + 1, V):  # the new weights certify the box's other vertices too
                        j2 = order[k2]
                        cert = _certify_parts(lastS, lastw, lastn, yo, Bg[j, j2], EBg[j, j2], K_err, s0g[j, j2], a1[o],
                                              0.0, G, sgn, lastp)
                        if sgn * cert[0] < sgn * cheap[j, j2]:
                            cheap[j, j2] = cert[0]
                            cheap_r[j, j2] = cert[2]


# ============================================================================ local weights
def _local_cells(X, Y, inv_l2, c, r, signs, pools, lam, a1, a2, G, optimal, max_iter, tol, ptr, group, lin):
    """:func:`_local_cells_coef` without the coefficients: ``val, support``."""
    val, sup, _ = _local_cells_coef(X, Y, inv_l2, c, r, signs, pools, lam, a1, a2, G, optimal, max_iter, tol, ptr,
                                    group, lin, _lanes())
    return val, sup


def _local_cells_coef(X, Y, inv_l2, c, r, signs, pools, lam, a1, a2, G, optimal, max_iter, tol, ptr, group, lin,
                      lanes):
    """:func:`_local_cells_into` on new arrays, every block in one piece: ``val, sup, coef``."""
    n, V, n_out = c.shape[0], signs.shape[0], Y.shape[1]
    val = np.empty((n, V, n_out, 2))
    sup = np.zeros((n, V, n_out, 2), dtype=np.int64)
    coef = np.empty((n, V, n_out, 2))
    _local_cells_into(X, Y, inv_l2, c, r, signs, pools, lam, a1, a2, G, optimal, max_iter, tol, ptr, group, lin, lanes,
                      val, sup, coef, np.zeros(1, dtype=np.int64), max(1, ptr.shape[0] - 1))
    return val, sup, coef


@numba.njit(cache=True)
def _blocks_done(done, piece):  # pragma: no cover - compiled
    """How many blocks of ``piece`` :func:`_local_cells_into` has finished: an atomic read (``fetch_add`` of 0,
    sequentially consistent), so the values of those blocks, written before the count, are seen after it."""
    return fetch_add(done, piece, 0)


@numba.njit(cache=True, parallel=True, nogil=True)  # nogil: the chunk writer and eq. C of the pieces run beside it
def _local_cells_into(X, Y, inv_l2, c, r, signs, pools, lam, a1, a2, G, optimal, max_iter, tol, ptr, group,
                      lin, lanes, val, sup, coef, done, piece_blocks):  # pragma: no cover
    """Certified bounds of ``<h, phi_v>`` (eq. W) with weights on each cell's pool of data points.

    ``pools[q]`` are the data points allowed to carry weight for cell q (any weights are sound;
    the pool only bounds the cost). Ridge weights ``(K_PP + lam I)^{-1} b`` (one factorisation
    per cell, the same weights for every output: the radius does not involve y), or with
    ``optimal`` the active-set weights per output and side (warm-started across the cell's
    vertices). Consecutive boxes of the same ``group`` (the sub-boxes of one cell) share its pool:
    one kernel matrix and factorisation, and the warm starts run on through them; with ``optimal``
    they are pruned as in ``rkhs_weights._optimal_cells`` (:func:`_local_group_optimal`, using
    ``lin (n, V, n_out)``, the float known part at the vertices). Boxes ``ptr[j] .. ptr[j+1]-1``
    form one parallel work unit (block ``j``); ``lanes`` threads take the next unit as they come free
    (``_atomic.fetch_add``, ``rkhs_model._lanes``). Writes ``val (n, V, n_out, 2)`` (side 0 upper, 1 lower) of the
    boxes of every block, their support sizes ``sup`` and ``coef`` (like ``val``): the upper bound of
    ``||phi_v - Phi* w||`` each value used (its coefficient of G, for ``rkhs_model.rescale_vertex_values``).
    When block ``j`` is written, ``done[j // piece_blocks]`` goes up by one (atomically, after its values): a
    thread beside the kernel may use a piece's values once its count is full (:func:`_blocks_done`).
    """
    n, d = c.shape
    V = signs.shape[0]
    k = pools.shape[1]
    n_out = Y.shape[1]
    n_chunks = ptr.shape[0] - 1
    nt = max(1, min(lanes, n_chunks))  # lanes take the next block as they come free (rkhs_model._lanes): same bits
    taken = np.zeros(1, dtype=np.int64)
    for t in numba.prange(nt):
        while True:
            ch = fetch_add(taken, 0, 1)
            if ch >= n_chunks:
                break
            Xp = np.empty((k, d))
            Yp = np.empty((k, n_out))
            L = np.empty((k, k))
            b = np.empty(k)
            eb = np.empty(k)
            w = np.empty(k)
            idx = np.arange(k)
            v = np.empty(d)
            ys = np.empty(k)
            S = np.zeros((n_out, 2, k), dtype=np.int64)
            sg = np.zeros((n_out, 2, k))
            ws = np.zeros((n_out, 2, k))
            nS = np.zeros((n_out, 2), dtype=np.int64)
            bidx = np.zeros(k, dtype=np.int64)
            bw = np.zeros(k)
            Pw = np.empty((k, k))  # workspaces of _active_set, once per chunk
            Lw = np.empty((k, k))
            Kp = np.empty((k, k))
            K_err = 0.0
            ok = True
            done_to = -1
            for q in range(ptr[ch], ptr[ch + 1]):
                if q < done_to:  # a sub-box already bounded with its group
                    continue
                if not (q == ptr[ch] or group[q] != group[q - 1]):
                    pass  # the same pool as the previous box: keep its kernel matrix, factor and warm starts
                else:
                    for p in range(k):
                        for a in range(d):
                            Xp[p, a] = X[pools[q, p], a]
                        for o in range(n_out):
                            Yp[p, o] = Y[pools[q, p], o]
                    Kp, zmax = _kernel_matrix(Xp, Xp, inv_l2)
                    K_err = _kernel_rel_err_nb(zmax, d)
                    ok = True
                    if not optimal:
                        ok = _chol_factor(Kp, k, L, lam)
                    for o in range(n_out):
                        for sd in range(2):
                            nS[o, sd] = 0  # a new pool: restart the warm starts
                    if optimal:
                        q1 = q + 1
                        while q1 < ptr[ch + 1] and group[q1] == group[q]:
                            q1 += 1
                        if q1 - q > 1:  # the sub-boxes of one cell: bounded together, pruned
                            _local_group_optimal(Xp, Yp, inv_l2, c, r, signs, q, q1, lin, Kp, K_err, a1, G, max_iter, tol,
                                                 S, sg, ws, nS, bidx, bw, Pw, Lw, val, sup, coef)
                            done_to = q1
                            continue
                for jv in range(V):
                    s0 = _vertex_functional(Xp, inv_l2, c[q], r[q], signs[jv], v, b, eb)
                    if not optimal:
                        if ok:
                            _chol_solve(L, k, b, w)
                        else:
                            for i in range(k):
                                w[i] = 0.0
                        l1, l2, rr = _certified_norms(idx, w, k, b, eb, Kp, K_err, s0)
                        for o in range(n_out):
                            for i in range(k):
                                ys[i] = Yp[i, o]
                            val[q, jv, o, 0] = _certified_value(idx, w, k, ys, l1, l2, rr, a1[o], a2[o], G, 1.0)[0]
                            val[q, jv, o, 1] = _certified_value(idx, w, k, ys, l1, l2, rr, a1[o], a2[o], G, -1.0)[0]
                            sup[q, jv, o, 0] = k
                            sup[q, jv, o, 1] = k
                            coef[q, jv, o, 0] = rr  # both sides: the same weights and functional
                            coef[q, jv, o, 1] = rr
                    else:
                        for o in range(n_out):
                            for sd in range(2):
                                sgn = 1.0 if sd == 0 else -1.0
                                for i in range(k):
                                    ys[i] = sgn * Yp[i, o]
                                res = _active_set(Kp, ys, b, s0, a1[o], G, S[o, sd], sg[o, sd], ws[o, sd], nS[o, sd], k,
                                                  max_iter, tol, bidx, bw, Pw, Lw)
                                nS[o, sd] = res[0] if (res[3] != 2 and res[3] != 3) else 0
                                nb = res[1]
                                for i in range(k):
                                    ys[i] = Yp[i, o]
                                cert = _certify(bidx, bw, nb, ys, b, eb, Kp, K_err, s0, a1[o], 0.0, G, sgn)
                                val[q, jv, o, sd] = cert[0]
                                coef[q, jv, o, sd] = cert[2]
                                sup[q, jv, o, sd] = nb
            fetch_add(done, ch // piece_blocks, 1)  # block ch written (its values before the count: seq_cst)


def local_pools(X, cells_lower, cells_upper, lengthscale, k: int) -> np.ndarray:
    """The ``k`` data points nearest to every cell centre in the kernel's metric (``x / l``).

    Parameters
    ----------
    X : (m, d) float array
    cells_lower, cells_upper : (n_cells, d) float arrays
    lengthscale : float or (d,) float array
    k : int >= 1 (capped at m)

    Returns
    -------
    (n_cells, min(k, m)) int array, sorted by distance
    """
    X = np.asarray(X, float)
    scale = np.sqrt(_inv_l2(lengthscale, X.shape[1]))
    k = int(min(max(int(k), 1), X.shape[0]))
    c = 0.5 * (np.asarray(cells_lower, float) + np.asarray(cells_upper, float))
    # the query points are independent: split over the caller's numba threads, the same indices on any count
    _, idx = _tree(X * scale).query(c * scale, k=k, workers=_lanes())
    return np.ascontiguousarray(np.asarray(idx, dtype=np.int64).reshape(c.shape[0], k))


#: k-d trees of the scaled data kept per process (every chunk of a mode queries the same points).
_TREE_CACHE = 4
_TREES: OrderedDict = OrderedDict()
_TREES_LOCK = threading.Lock()


def _tree(points: np.ndarray):
    """The ``cKDTree`` of ``points`` (n, d), built once per process for the same bytes (a small LRU keyed by
    a digest of the array): the bound stage's chunks of one mode query the same scaled data, and a tree
    built from equal bytes is the same tree, so the pools are the same as with a fresh one."""
    from scipy.spatial import cKDTree

    points = np.ascontiguousarray(points, float)
    key = (points.shape, hashlib.blake2b(points.tobytes(), digest_size=20).digest())
    with _TREES_LOCK:
        tree = _TREES.get(key)
        if tree is not None:
            _TREES.move_to_end(key)
            return tree
    tree = cKDTree(points)
    with _TREES_LOCK:
        _TREES[key] = tree
        while len(_TREES) > _TREE_CACHE:
            _TREES.popitem(last=False)
    return tree


#: Ridge regularisers tried by :func:`local_lambda`.
LOCAL_LAMBDAS = tuple(float(v) for v in np.logspace(-8, 0, 9))


def local_lambda(X, cells_lower, cells_upper, *, lengthscale, rkhs_bound: float, noise_l1: float, k: int,
                 noise_l2: float = 0.0, n_sample: int = 64) -> float:
    """The ridge regulariser of the local weights: the one of :data:`LOCAL_LAMBDAS` with the
    smallest median certified radius on up to ``n_sample`` evenly spaced cells.

    A function of the inputs and the cells only (not of y), so it can be fixed before the data's
    outputs are used (the iid route needs that) and is the same for every chunk of cells.
    """
    X = np.ascontiguousarray(X, float)
    lo, up = _check_cells(cells_lower, cells_upper, X.shape[1])
    sel = np.unique(np.linspace(0, lo.shape[0] - 1, min(int(n_sample), lo.shape[0])).astype(np.int64))
    c, r = cell_centres(lo[sel], up[sel])
    pools = local_pools(X, lo[sel], up[sel], lengthscale, k)
    signs = vertex_signs(X.shape[1])
    inv_l2 = _inv_l2(lengthscale, X.shape[1])
    zeros = np.zeros((X.shape[0], 1))
    best, best_lam = np.inf, LOCAL_LAMBDAS[0]
    for lam in LOCAL_LAMBDAS:
        one = np.arange(c.shape[0], dtype=np.int64)
        val, _ = _local_cells(X, zeros, inv_l2, c, r, signs, pools, lam, np.array([noise_l1]), np.array([noise_l2]),
                              float(rkhs_bound), False, 0, 0.0, _blocks(c.shape[0], one, c.shape[0], CELL_BLOCK), one,
                              np.zeros((c.shape[0], signs.shape[0], 1)))
        radius = float(np.median(val[:, :, 0, 0]))  # y = 0: the certified value is the radius
        if radius < best:
            best, best_lam = radius, lam
    return best_lam


def _local_chunk(X, Y, A, b, cells_lower, cells_upper, *, lengthscale, rkhs_bound, noise_bound, misspecification,
                 method, iid_factor, iid_theta, k, lam, split_tol=None, scales=None):
    """:func:`bound_chunk` with local weights (see its ``local_points``; ``scales``: its ranges at ``scale * B``)."""
    if method not in METHODS:
        raise InvalidInputError(f"method must be one of {METHODS}; got {method!r}")
    X = _writable(X)
    Y = _writable(np.asarray(Y, float).reshape(X.shape[0], -1))
    m, d = X.shape
    n = Y.shape[1]
    lower, upper = _check_cells(cells_lower, cells_upper, d)
    inv_l2 = _inv_l2(lengthscale, d)
    G_eff = float(_up(float(rkhs_bound) * _norm_inflation(d)))
    tau = float(misspecification)
    dbar = _up(np.broadcast_to(np.asarray(noise_bound, float), (n,)) + tau)
    c, r = cell_centres(lower, upper)
    signs = vertex_signs(d)
    pools = local_pools(X, lower, upper, lengthscale, k)
    if lam is None and method == "ridge":
        lam = local_lambda(X, lower, upper, lengthscale=lengthscale, rkhs_bound=rkhs_bound, noise_l1=float(dbar.max()),
                           k=k)
    n_cells = lower.shape[0]
    s_split = split_counts(t_max_up(r, inv_l2), G_eff, d, split_tol)
    if np.any(s_split > 1):  # certify on sub-boxes (their union covers the cell), each with its cell's pool
        box_lo, box_up, parent, starts = sub_boxes(lower, upper, s_split)
        c, r = cell_centres(box_lo, box_up)
        pools = np.ascontiguousarray(pools[parent])
    else:
        parent = np.arange(n_cells, dtype=np.int64)
        starts = parent
    ptr = _blocks(n_cells, starts, c.shape[0], CELL_BLOCK)
    A = np.asarray(A, float)
    b = np.asarray(b, float)
    known = [_known_at_vertices(c, r, signs, A[i], float(b[i])) for i in range(n)]  # (lin_v, lin_err) per output
    lin = np.ascontiguousarray(np.stack([kv[0] for kv in known], axis=-1))  # (N, V, n): orders and prunes only
    lin_v, lin_err = np.stack([kv[0] for kv in known]), np.stack([kv[1] for kv in known])  # (n, N, V)
    t_max = t_max_up(r, inv_l2)
    iid = None
    if iid_factor is not None:  # the iid event's weights (ridge, one lambda for the chunk)
        th = np.broadcast_to(np.asarray(iid_theta, float), (n,))
        a2 = _up(float(iid_factor) * th * (1 + 4 * _U))
        lam2 = local_lambda(X, lower, upper, lengthscale=lengthscale, rkhs_bound=rkhs_bound, noise_l1=tau,
                            noise_l2=float(a2.max()), k=k)
        iid = (lam2, a2)
    G_s = None if scales is None else [scaled_norm_bound(rkhs_bound, sc, d) for sc in scales]
    lanes = _lanes()

    n_blocks = ptr.shape[0] - 1
    one_piece = lanes == 1 or n_blocks <= PIECE_BLOCKS
    firsts = [0] if one_piece else list(range(0, n_blocks, PIECE_BLOCKS))
    N, V = c.shape[0], signs.shape[0]

    def arrays():  # values, supports, coefficients, blocks written per piece
        return (np.empty((N, V, n, 2)), np.zeros((N, V, n, 2), dtype=np.int64), np.empty((N, V, n, 2)),
                np.zeros(len(firsts), dtype=np.int64))

    val, sup, coef, done = arrays()
    iv, isup, icoef, idone = arrays() if iid is not None else (None, None, None, None)

    def vertex_values(piece_blocks):  # eq. W at every vertex: the kernel(s) write the arrays above
        _local_cells_into(X, Y, inv_l2, c, r, signs, pools, float(lam or 0.0), np.ascontiguousarray(dbar), np.zeros(n),
                          G_eff, method == "optimal", 2000, 1e-9, ptr, parent, lin, lanes, val, sup, coef, done,
                          piece_blocks)
        if iid is not None:
            _local_cells_into(X, Y, inv_l2, c, r, signs, pools, iid[0], np.full(n, tau), np.ascontiguousarray(iid[1]),
                              G_eff, False, 0, 0.0, ptr, parent, lin, lanes, iv, isup, icoef, idone, piece_blocks)

    if one_piece:  # the kernel, then eq. C
        vertex_values(max(1, n_blocks))
        return _cells_piece(val, sup, coef, iv, icoef, lin_v, lin_err, t_max, starts, G_eff, tau, G_s)
    # One kernel call over the chunk: its lanes take the blocks as they come free, so a lane waits for the last block
    # once per chunk, not once per piece (the unicycle at 32^3 had 2.8 s of idle core in its 392 piece calls). Eq. C
    # of each piece of PIECE_BLOCKS blocks (numpy, one thread) runs in a thread beside the kernel as soon as the
    # kernel has written the piece's blocks (``done``, read atomically by ``_blocks_done``), so no core waits for it
    # either. Each piece's numbers are its own, so the concatenated arrays are those of one piece (the same bits).
    stop, written = threading.Event(), threading.Event()  # the kernel stopped early; every block written

    def pieces():  # eq. C of the pieces in order, each once the kernel(s) wrote its blocks
        out = []
        for p, j0 in enumerate(firsts):
            j1 = min(j0 + PIECE_BLOCKS, n_blocks)

            def full():
                return _blocks_done(done, p) >= j1 - j0 and (idone is None or _blocks_done(idone, p) >= j1 - j0)

            while not full():
                if stop.is_set():  # the kernel stopped (an interrupt): nothing more will come
                    return out
                if written.is_set() and not full():  # every kernel returned: its counts are final
                    raise RuntimeError(f"the bound kernel returned without writing every block of piece {p}")
                written.wait(_PIECE_POLL_S)
            qa, qb = int(ptr[j0]), int(ptr[j1])  # its boxes
            ca, cb = j0 * CELL_BLOCK, min(j1 * CELL_BLOCK, n_cells)  # its cells
            out.append(_cells_piece(val[qa:qb], sup[qa:qb], coef[qa:qb], None if iv is None else iv[qa:qb],
                                    None if icoef is None else icoef[qa:qb], lin_v[:, qa:qb], lin_err[:, qa:qb],
                                    t_max[qa:qb], starts[ca:cb] - qa, G_eff, tau, G_s))
        return out

    beside = _piece_thread().submit(pieces)
    try:
        vertex_values(PIECE_BLOCKS)
        written.set()  # the last piece's eq. C starts now, not at the next look
    except BaseException:  # an interrupted chunk: the thread beside it stops at its next look
        stop.set()
        raise
    parts = beside.result()
    out = {key: np.concatenate([q[key] for q in parts], axis=0) for key in ("lower", "upper", "eps", "support")}
    out["n_unconverged"] = 0
    if G_s is not None:
        for key in ("scaled_lower", "scaled_upper"):
            out[key] = np.concatenate([q[key] for q in parts], axis=1)
    return out


#: Blocks of :data:`CELL_BLOCK` cells per piece of a chunk on several threads (:func:`_local_chunk`): eq. C of a piece
#: runs beside the kernel once the piece is written.
PIECE_BLOCKS = 16
#: Seconds between two looks of the thread beside the kernel at the pieces' counts (each look costs some 30 us of
#: a core: 1 ms cost more CPU than the lanes' idle time it saved on the unicycle; the last piece starts at once).
_PIECE_POLL_S = 0.005
_PIECE_POOL = None
_PIECE_LOCK = threading.Lock()


def _piece_thread():
    """The process's threads for eq. C of the pieces (started on first use, kept: no thread start per chunk)."""
    global _PIECE_POOL
    with _PIECE_LOCK:
        if _PIECE_POOL is None:
            from concurrent.futures import ThreadPoolExecutor

            # one per chunk in flight (pipeline.parallel.InProcess.run_overlapping runs two at a time)
            _PIECE_POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="robust-imdp eq. C")
        return _PIECE_POOL


def _cells_piece(val, sup, coef, iv, icoef, lin_v, lin_err, t_max, starts, G_eff: float, tau: float, G_s) -> dict:
    """The cell ranges of (eq. C) from the vertex values of a piece of a chunk: :func:`bound_chunk`'s dict.

    ``val``, ``sup``, ``coef`` (N, V, n, 2): the kernel's values, supports and coefficients of G; ``iv``, ``icoef``:
    those of the iid event's weights or None; ``lin_v``, ``lin_err`` (n, N, V); ``t_max`` (N,); ``starts`` the first
    box of every cell; ``G_s``: the norm bounds of the margins' scales or None.
    """
    if iv is not None:
        # the certificate kept per vertex and side carries its own coefficient of G (for scales)
        coef[..., 0] = np.where(iv[..., 0] < val[..., 0], icoef[..., 0], coef[..., 0])
        coef[..., 1] = np.where(iv[..., 1] > val[..., 1], icoef[..., 1], coef[..., 1])
        val[..., 0] = np.minimum(val[..., 0], iv[..., 0])  # both intervals hold: intersect
        val[..., 1] = np.maximum(val[..., 1], iv[..., 1])
    # every output in one call (n, N, V): element by element the same operations as one output at a time
    su, sl = np.moveaxis(val[..., 0], 2, 0), np.moveaxis(val[..., 1], 2, 0)
    lo_all, up_all, taylor = _combine_vertices(lin_v, lin_err, su, sl, t_max, G_eff, tau)
    eps_all = np.max(0.5 * (su - sl), axis=-1) + taylor
    # hull of each cell's sub-boxes (eq. C holds on every sub-box; reduceat is the identity unsplit)
    out = {"lower": np.ascontiguousarray(np.minimum.reduceat(lo_all, starts, axis=1).T),
           "upper": np.ascontiguousarray(np.maximum.reduceat(up_all, starts, axis=1).T),
           "eps": np.ascontiguousarray(np.maximum.reduceat(eps_all, starts, axis=1).T)}
    out["support"] = np.maximum.reduceat(sup.max(axis=(1, 3)), starts, axis=0)
    out["n_unconverged"] = 0
    if G_s is not None:  # the same weights at scale * B (docs/rkhs_bounds.md, "Assumption margins")
        s_lo, s_up = scaled_ranges(lin_v, lin_err, su, sl, np.moveaxis(coef[..., 0], 2, 0),
                                   np.moveaxis(coef[..., 1], 2, 0), t_max, G_eff, tau, G_s, starts)  # (S, n, cells)
        out["scaled_lower"] = np.ascontiguousarray(np.swapaxes(s_lo, 1, 2))
        out["scaled_upper"] = np.ascontiguousarray(np.swapaxes(s_up, 1, 2))
    return out
