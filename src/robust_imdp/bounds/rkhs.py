r"""Certified bounds of an unknown function of bounded RKHS norm over whole cells, from noisy data.

This is the *learn + bound* stage of the tight route (``error_bound="optimal"`` or ``"ridge"``). It needs no Gaussian-process
posterior, no probability over the data (for bounded noise) and no branch and bound.

Setting (``docs/rkhs_bounds.md`` has the derivations in full)
    ``k`` is the squared-exponential kernel with **unit amplitude** and lengthscales ``l_a``,
    ``H`` its RKHS. The unknown component satisfies ``g = h + e`` with ``||h||_H <= B`` (the
    user's ``rkhs_bound``) and ``sup_X |e| <= tau`` (the misspecification allowance, 0 by
    default). The data are ``y_i = g(x_i) + d_i`` with ``|d_i| <= dbar`` (the noise bound); nothing
    else is assumed about ``d`` (it may be biased, dependent or adversarial), so with
    ``dbar' = dbar + tau`` we have ``|h(x_i) - y_i| <= dbar'``.

1. Any weights give a bound (Maddalena, Scharnhorst & Jones, Automatica 2021)
    For a functional ``phi`` in ``H`` and any ``w`` in R^m, by the reproducing property
    ``<h, phi> - w.y = <h, phi - sum_i w_i k_{x_i}> - w.(h(X) - y)``, hence::

        |<h, phi> - w.y| <= B ||phi - Phi* w||_H + dbar' ||w||_1                (eq. W)

    ``||phi - Phi* w||^2 = <phi, phi> - 2 w.b + w.K w`` with ``b_i = <k_{x_i}, phi>``.
    The bound holds for *every* w: the weights are only a certificate, so the optimiser that
    proposes them needs no proof, and **one certified evaluator** (:func:`_certify`) is the
    only place where soundness is decided.

2. Whole cells: Taylor expansion of the feature map
    For a cell with centre c, half-widths r, ``x = c + D``, ``t(D) = sum_a D_a^2 / l_a^2``::

        h(x) = <h, k_c + sum_a D_a dk_c/dc_a> + <h, k_x - k_c - sum_a D_a dk_c/dc_a>
             <= <h, phi_D> + B sqrt(R(t)),     R(t) = 2 (1 - e^{-t/2}) + t (1 - 2 e^{-t/2})  (eq. T)

    (closed form for the SE kernel; R is increasing, so ``t <= t_max = sum r_a^2/l_a^2`` gives
    ``R(t_max)``). ``<h, phi_D>`` is affine in D, so its maximum over the cell is attained at a
    vertex v of the box, and the known affine part ``f_u(x) = A x + b`` joins it. Hence for
    every x in the cell (``s = +1`` upper, ``s = -1`` lower)::

        s (f_u + g)(x) <= max_v  s f_u(c + v) + [ s w_v.y + dbar' ||w_v||_1 + B ||phi_v - Phi* w_v|| ]
                          + B sqrt(R(t_max)) + tau                                    (eq. C)

    with one weight vector per vertex and side, ``phi_v = k_c + sum_a v_a dk_c/dc_a``,
    ``<phi_v, phi_v> = 1 + sum_a v_a^2/l_a^2``, ``b_i = k(x_i, c) (1 + sum_a v_a (x_ia - c_a)/l_a^2)``.
    Eq. C holds on any box, so with ``split_tol`` a cell is certified on sub-boxes covering it
    (:func:`sub_boxes`) and its range is the hull of theirs: the Taylor term shrinks like ``1/s^2``
    with ``s`` pieces per axis (:func:`split_counts`).

3. Optimal weights (Scharnhorst, Maddalena, Jiang & Jones, IEEE TAC 2022)
    ``min_w s w.y + dbar' ||w||_1 + B ||phi_v - Phi* w||`` is the conic dual of
    ``max { s <h, phi_v> : ||h|| <= B, |h(x_i) - y_i| <= dbar' }``, with no duality gap when the
    data are strictly consistent with the assumption; so ``method="optimal"`` gives the
    tightest interval consistent with the assumption at every vertex. It is solved by a
    primal active-set method (:func:`_active_set`, warm-started from the neighbouring problem),
    whose optimum is checked against cvxpy/clarabel in the tests (``lp.rkhs_vertex_socp``).
    ``method="ridge"`` uses kernel-ridge weights ``(K + lambda I)^{-1} b`` with the best of
    a grid of lambda per vertex (the closed form of the notes, cheaper and looser).

4. Independent noise (optional, ``iid_noise``)
    If the noise is also independent across samples, zero-mean, theta-sub-Gaussian, and the
    inputs do not depend on it, then for weights chosen from the inputs alone,
    ``P(|w.d| > theta ||w||_2 s) <= 2 exp(-s^2/2)``. With one weight vector per (mode, output,
    cell, vertex) and a union bound over all ``N`` of them, with probability ``>= 1 - delta``
    over the data ``|w.d| <= theta ||w||_2 sqrt(2 ln(2N/delta))`` for all of them, and (eq. W)
    holds with the noise term ``tau ||w||_1 + theta ||w||_2 sqrt(2 ln(2N/delta))``. The weights
    are ridge weights whose lambda minimises ``B ||phi - Phi* w|| + c theta ||w||_2`` (a
    function of the inputs only). The final interval is the intersection with the
    deterministic one.

Floating point
    Every certified value is computed with an explicit bound of its rounding error (standard
    ``gamma_n = n u / (1 - n u)`` bounds of sums, a relative error bound of every computed
    kernel value, see :func:`_kernel_rel_err`) and moved outward by it and one ulp. The
    cancellation in ``||phi - Phi* w||^2`` is the only term where this matters; its error
    bound is added *before* the square root.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Callable

import numba
import numpy as np

from robust_imdp._fp import U as _U, down as _down, up as _up
from robust_imdp._kernels import (  # noqa: F401  (re-exported: tests and benchmarks use the old names)
    inv_l2_up as _inv_l2,
    kernel_matrix as _kernel_matrix,
    kernel_rel_err as _kernel_rel_err,
    kernel_rel_err_nb as _kernel_rel_err_nb,
    norm_inflation as _norm_inflation,
)
from robust_imdp.bounds.rkhs_check import NormCheck, check_assumption, min_rkhs_norm, refutation_reason  # noqa: F401
from robust_imdp.bounds.rkhs_local import _local_cells, _local_chunk, local_lambda, local_pools  # noqa: F401
from robust_imdp.bounds.rkhs_model import (  # noqa: F401  (re-exported)
    CELL_BLOCK,
    MAX_SUB,
    SPLIT_TOL,
    KernelModel,
    _blocks,
    _certify,
    _certify_parts,
    _check_cells,
    _combine_vertices,
    _corner_boxes,
    _known_at_vertices,
    _lanes,
    _scaled_remainder_sqrt_up,
    _weight_parts,
    _writable,
    cell_centres,
    certify_weights,
    split_counts,
    rescale_vertex_values,
    scaled_norm_bound,
    scaled_ranges,
    sub_boxes,
    t_max_up,
    taylor_remainder_sqrt_up,
    unit_kernel,
    vertex_problems,
    vertex_signs,
)
from robust_imdp.bounds.rkhs_weights import (  # noqa: F401  (re-exported)
    MAX_SUPPORT,
    METHODS,
    RIDGE_LAMBDAS,
    _active_set,
    _optimal_cells,
    _optimal_cells_coef,
    _ridge_vertex_bounds,
    _ridge_weights,
    optimal_weights,
)
from robust_imdp.errors import AssumptionError, DimensionError, InvalidInputError

__all__ = [
    "KernelModel", "NormCheck", "CellRange", "ImageRanges", "METHODS",
    "taylor_remainder_sqrt_up", "cell_centres", "vertex_signs", "unit_kernel",
    "certify_weights", "vertex_problems", "optimal_weights", "cell_ranges", "min_rkhs_norm", "check_assumption",
    "image_ranges", "bound_chunk", "check_ranges", "CELL_BLOCK", "local_pools", "local_lambda", "noise_bound_at_confidence", "hoeffding_factor",
    "SPLIT_TOL", "MAX_SUB", "split_counts", "sub_boxes",
]

log = logging.getLogger(__name__)


# ============================================================================ cell ranges
@dataclass(frozen=True, eq=False)
class CellRange:
    """Certified range of ``f_u(x) + g(x)`` (one output) over every cell.

    Attributes
    ----------
    lower, upper : (n_cells,) float arrays
        For every x in cell q: ``lower[q] <= f_u(x) + g(x) <= upper[q]`` under the assumption.
    eps : (n_cells,) float array
        Error radius: the largest half-width of a vertex interval plus the Taylor and
        misspecification terms (how far the bound is from the exact vertex values at worst);
        comparable to the cell's half-width.
    support : (n_cells,) int array
        Largest number of data points used by one certificate of the cell.
    vertex_lower, vertex_upper : (n_cells, V) float arrays
        Certified bounds of ``f_u(c+v) + <h, phi_v>`` per vertex (before the Taylor term).
    taylor : (n_cells,) float array
        ``B sqrt(R(t_max))`` rounded up (plus tau).
    n_unconverged : int
        Vertex problems whose optimiser stopped early (their bounds are sound, maybe looser).
    scaled_lower, scaled_upper : (n_scales, n_cells) float arrays or None
        With ``scales``: the range under ``||h|| <= scale * B`` for each scale, certified by the same
        weights (``rkhs_model.scaled_ranges``; docs/rkhs_bounds.md, "Assumption margins").
    """

    lower: np.ndarray
    upper: np.ndarray
    eps: np.ndarray
    support: np.ndarray
    vertex_lower: np.ndarray
    vertex_upper: np.ndarray
    taylor: np.ndarray
    n_unconverged: int = 0
    scaled_lower: np.ndarray | None = None
    scaled_upper: np.ndarray | None = None


def cell_ranges(model: KernelModel, cells_lower, cells_upper, *, rkhs_bound: float, noise_bound: float,
                misspecification: float = 0.0, known_row=None, known_offset: float = 0.0,
                method: str = "optimal", iid_factor: float | None = None, iid_theta: float = 0.0,
                chunk: int = 16, max_iter: int = 2000, tol: float = 1e-9, prune: bool = True,
                split_tol: float | None = None, scales=None) -> CellRange:
    """Certified range of ``known_row . x + known_offset + g(x)`` over every cell (eq. C).

    Parameters
    ----------
    model : KernelModel
        Inputs, residuals of this output, lengthscales of the assumption.
    cells_lower, cells_upper : (n_cells, d) float arrays
    rkhs_bound : float > 0
        B, the bound on ``||h||`` for the unit-amplitude SE kernel.
    noise_bound : float >= 0
        dbar, the bound of the data noise ``|d_i|`` (a statement about the data).
    misspecification : float >= 0
        tau: ``g`` is within tau of an ``h`` with ``||h|| <= B`` on X.
    known_row : (d,) float array, optional
        Row ``A_i`` of the known affine part (default 0); ``known_offset`` is ``b_i``.
    method : {"optimal", "ridge"}
    iid_factor : float, optional
        ``sqrt(2 ln(2N/delta))`` of the union bound of the iid route; when given, the
        deterministic interval is intersected with the iid one (noise sub-Gaussian with
        parameter ``iid_theta``, independent across samples, inputs independent of it).
    chunk, max_iter, tol
        Optimiser settings (cells per parallel chunk, active-set iterations, optimality tolerance).
    prune : bool
        Skip optimising vertices whose certified neighbour value cannot change the cell bound
        (their values stay certified; ``vertex_lower``/``vertex_upper`` are then not all optimal).
    split_tol : float or None
        Certify a cell on sub-boxes where its Taylor term exceeds this (:func:`split_counts`,
        :func:`sub_boxes`); the cell's range is the hull of its sub-boxes' ranges. None: never.
    scales : sequence of float >= 1, optional
        Also the range under ``||h|| <= scale * B`` for each scale, from the weights found for B
        (eq. W holds for any weights; ``rkhs_model.scaled_ranges``): ``scaled_lower``/``scaled_upper``.
        The sub-boxes and the weights are those of B; nothing is optimised again.

    Returns
    -------
    CellRange
        For a split cell, ``vertex_lower``/``vertex_upper`` are those of the corner sub-box at
        each vertex and ``taylor`` the largest sub-box term.
    """
    if method not in METHODS:
        raise InvalidInputError(f"method must be one of {METHODS}; got {method!r}")
    G = float(rkhs_bound)
    if not (np.isfinite(G) and G > 0):
        raise InvalidInputError(f"rkhs_bound must be a positive finite float; got {rkhs_bound!r}")
    for name, val in (("noise_bound", noise_bound), ("misspecification", misspecification)):
        if not (np.isfinite(val) and val >= 0):
            raise InvalidInputError(f"{name} must be a finite float >= 0; got {val!r}")
    d = model.d
    lower, upper = _check_cells(cells_lower, cells_upper, d)
    a_row = np.zeros(d) if known_row is None else np.asarray(known_row, float).reshape(d)
    G_eff = float(_up(G * _norm_inflation(d)))
    tau = float(misspecification)
    dbar = float(_up(float(noise_bound) + tau))  # |h(x_i) - y_i| <= dbar + tau
    c, r = cell_centres(lower, upper)
    signs = vertex_signs(d)
    n_cells = lower.shape[0]
    s_split = split_counts(t_max_up(r, model.inv_l2), G_eff, d, split_tol)
    if np.any(s_split > 1):  # certify on sub-boxes (their union covers the cell): the hull is sound
        box_lo, box_up, parent, starts = sub_boxes(lower, upper, s_split)
        c, r = cell_centres(box_lo, box_up)
    else:
        parent = np.arange(n_cells, dtype=np.int64)
        starts = parent
    lin_v, lin_err = _known_at_vertices(c, r, signs, a_row, float(known_offset))
    t_max = t_max_up(r, model.inv_l2)
    n_unconv = 0
    if method == "optimal":
        cap = int(min(model.m, MAX_SUPPORT))
        ptr = _blocks(n_cells, starts, c.shape[0], int(chunk))
        # the lanes take the units as they come free (rkhs_model._lanes): the units' costs differ (active-set
        # iterations); the units are independent (warm starts restart at each): the same bits for any lanes
        val, sup, stat, coef = _optimal_cells_coef(model.X, model.y, model.K, model.K_err, model.inv_l2, c, r,
                                                   signs, dbar, G_eff, cap, int(max_iter), float(tol), ptr,
                                                   lin_v, bool(prune), parent, _lanes())
        su, sl = val[:, :, 0], val[:, :, 1]
        cu, cl = coef[:, :, 0], coef[:, :, 1]
        optimised = (stat[:, :, 0] != 6) & (stat[:, :, 1] != 6)
        support = sup.max(axis=(1, 2))
        n_unconv = int(np.sum((stat != 0) & (stat != 5) & (stat != 6)))
    else:
        su, sl, cu = _ridge_vertex_bounds(model, c, r, signs, dbar, 0.0, G_eff, coef=True)
        cl = cu
        optimised = None
        support = np.full(c.shape[0], model.m)
    if iid_factor is not None:
        a2 = float(_up(float(iid_factor) * float(iid_theta) * (1 + 4 * _U)))
        iu, il, ic = _ridge_vertex_bounds(model, c, r, signs, tau, a2, G_eff, coef=True)
        # the certificate kept per vertex and side carries its own coefficient of G (for scales)
        cu, cl = np.where(iu < su, ic, cu), np.where(il > sl, ic, cl)
        # Intersection of two intervals that both hold (the iid one on the data event).
        su, sl = np.minimum(su, iu), np.maximum(sl, il)
    lower_c, upper_c, taylor = _combine_vertices(lin_v, lin_err, su, sl, t_max, G_eff, tau)
    scaled = (None, None)
    if scales is not None:  # the same weights at scale * B (docs/rkhs_bounds.md, "Assumption margins")
        G_s = [scaled_norm_bound(G, sc, d) for sc in scales]
        scaled = scaled_ranges(lin_v, lin_err, su, sl, cu, cl, t_max, G_eff, tau, G_s,
                               starts if c.shape[0] != n_cells else None)
    vu = _up(lin_v + su, lin_err + 2 * _U * (np.abs(lin_v) + np.abs(su)))
    vl = _down(lin_v + sl, lin_err + 2 * _U * (np.abs(lin_v) + np.abs(sl)))
    # Error radius (a diagnostic): half the vertex interval, over the vertices optimised on both
    # sides (a pruned vertex keeps a looser neighbour value that says nothing about the data).
    half = 0.5 * (su - sl)
    solved = np.ones_like(half, dtype=bool) if optimised is None else optimised
    eps = np.where(solved.any(axis=1), np.max(np.where(solved, half, -np.inf), axis=1), half.min(axis=1)) + taylor
    if c.shape[0] != n_cells:  # hull of each cell's sub-boxes (eq. C holds on every sub-box)
        lower_c = np.minimum.reduceat(lower_c, starts)
        upper_c = np.maximum.reduceat(upper_c, starts)
        eps = np.maximum.reduceat(eps, starts)
        taylor = np.maximum.reduceat(taylor, starts)
        support = np.maximum.reduceat(support, starts)
        corner = _corner_boxes(s_split, starts, signs)
        jv = np.arange(signs.shape[0])[None, :]
        vl, vu = vl[corner, jv], vu[corner, jv]
    return CellRange(lower=lower_c, upper=upper_c, eps=eps, support=support, vertex_lower=vl, vertex_upper=vu,
                     taylor=taylor, n_unconverged=n_unconv, scaled_lower=scaled[0], scaled_upper=scaled[1])


# ============================================================================ noise events
def noise_bound_at_confidence(noise, n_samples: int, delta: float):
    """Per-output bound ``dbar`` of the data noise and the probability that it fails.

    Bounded noise (``noise.bounded``): its bound, failure probability 0. Otherwise the
    ``1 - delta / (n_samples * n)`` quantile of ``|v_i|`` (rounded up), so that by a union bound
    over all ``n_samples * n`` noise values ``P(max |d| > dbar) <= delta``.

    Returns
    -------
    bound : (n,) float array
    failure : float (0 or delta)
    """
    if getattr(noise, "bounded", False):
        return np.array(noise.bound, float), 0.0
    n = int(noise.dim)
    p = 1.0 - float(delta) / (int(n_samples) * n)
    # quantiles (erfinv) are accurate to a few ulps; 1e-12 relative is ample margin.
    return _up(np.asarray(noise.abs_quantile(p), float) * (1 + 1e-12)), float(delta)


def hoeffding_factor(n_events: int, delta: float) -> float:
    """``sqrt(2 ln(2 N / delta))`` rounded up: ``P(|w.d| > theta ||w||_2 s) <= 2 e^{-s^2/2}`` for each
    of N weight vectors, union bound to ``delta``."""
    if not (int(n_events) >= 1 and 0 < float(delta) < 1):
        raise InvalidInputError(f"n_events must be >= 1 and delta in (0, 1); got {n_events!r}, {delta!r}")
    return float(_up(math.sqrt(2.0 * math.log(2.0 * int(n_events) / float(delta))) * (1 + 1e-12)))


# ============================================================================ all modes
@dataclass(frozen=True, eq=False)
class ImageRanges:
    """Certified image boxes of every mode over every cell, with diagnostics.

    Attributes
    ----------
    lower, upper : (n_modes, n_cells, n) float arrays
        ``{f_u(x) + g_u(x) : x in cell}`` lies in the box (under the assumption, and on the data
        event when ``confidence < 1``).
    eps : (n_modes, n_cells, n) float array
        Error radius per cell (:class:`CellRange`).
    support : (n_modes, n_cells, n) int array
    norm_checks : tuple of NormCheck
    confidence : float
        Probability over the data with which every box holds (1.0 for bounded noise without
        the iid intersection).
    n_unconverged : int
    seconds : float
    """

    lower: np.ndarray
    upper: np.ndarray
    eps: np.ndarray
    support: np.ndarray
    norm_checks: tuple
    confidence: float
    n_unconverged: int
    seconds: float


def bound_chunk(X, Y, A, b, cells_lower, cells_upper, *, lengthscale, rkhs_bound: float, noise_bound,
                misspecification: float = 0.0, method: str = "optimal", iid_factor: float | None = None,
                iid_theta=None, local_points: int | None = None, local_lambda: float | None = None,
                threads: int | None = None, split_tol: float | None = None, scales=None) -> dict:
    """Certified image boxes of one mode over a chunk of cells (all outputs): a pure function.

    The unit of work of the bound stage (``pipeline`` runs it on a scheduler). Its result
    depends only on its arguments; a chunk must start at a multiple of :data:`CELL_BLOCK` of the
    global cell index for the result to be independent of the chunking.

    Parameters
    ----------
    X : (m, d) float array
    Y : (m, n) float array
        Residuals ``x_next - f_u(x)`` of this mode.
    A : (n, d) float array, b : (n,) float array
        Known affine part of this mode.
    cells_lower, cells_upper : (k, d) float arrays
    lengthscale, rkhs_bound, noise_bound (n,), misspecification, method, iid_factor, iid_theta (n,)
        As in :func:`cell_ranges` (per output where an array).
    local_points : int, optional
        Let only the ``local_points`` data points nearest to each cell (:func:`local_pools`)
        carry weight: the cost per cell no longer grows with the data size and no m x m kernel
        matrix is built (for large data sets). ``local_lambda`` is the ridge regulariser of
        ``method="ridge"`` there (:func:`local_lambda`, chosen once for all chunks).
    threads : int, optional
        numba threads for this call (1 inside a scheduler's worker process).
    split_tol : float or None
        Certification sub-boxes where the Taylor term exceeds this (:func:`cell_ranges`).
    scales : sequence of float >= 1, optional
        Also the boxes under ``||h|| <= scale * B`` from the same weights (:func:`cell_ranges`).

    Returns
    -------
    dict with ``lower``, ``upper``, ``eps`` ((k, n) float arrays), ``support`` ((k, n) int array),
    ``n_unconverged`` (int) and ``seconds`` (float); with ``scales`` also ``scaled_lower`` and
    ``scaled_upper`` ((n_scales, k, n) float arrays).
    """
    t0 = time.perf_counter()
    if threads is not None:
        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    if local_points is not None:
        out = _local_chunk(X, Y, A, b, cells_lower, cells_upper, lengthscale=lengthscale, rkhs_bound=rkhs_bound,
                           noise_bound=noise_bound, misspecification=misspecification, method=method,
                           iid_factor=iid_factor, iid_theta=iid_theta, k=int(local_points), lam=local_lambda,
                           split_tol=split_tol, **({} if scales is None else {"scales": tuple(scales)}))
        out["seconds"] = time.perf_counter() - t0
        return out
    Y = np.asarray(Y, float).reshape(np.shape(X)[0], -1)
    n = Y.shape[1]
    nb = np.broadcast_to(np.asarray(noise_bound, float), (n,))
    th = None if iid_theta is None else np.broadcast_to(np.asarray(iid_theta, float), (n,))
    k = np.shape(cells_lower)[0]
    out = {key: np.empty((k, n)) for key in ("lower", "upper", "eps")}
    out["support"] = np.empty((k, n), dtype=np.int64)
    if scales is not None:
        out["scaled_lower"] = np.empty((len(scales), k, n))
        out["scaled_upper"] = np.empty((len(scales), k, n))
    unconv = 0
    A = np.asarray(A, float)
    b = np.asarray(b, float)
    for i in range(n):
        model = KernelModel(X, Y[:, i], lengthscale)
        cr = cell_ranges(model, cells_lower, cells_upper, rkhs_bound=rkhs_bound, noise_bound=float(nb[i]),
                         misspecification=misspecification, known_row=A[i], known_offset=float(b[i]), method=method,
                         iid_factor=iid_factor, iid_theta=0.0 if th is None else float(th[i]), chunk=CELL_BLOCK,
                         split_tol=split_tol, scales=scales)
        out["lower"][:, i], out["upper"][:, i], out["eps"][:, i] = cr.lower, cr.upper, cr.eps
        if scales is not None:
            out["scaled_lower"][:, :, i], out["scaled_upper"][:, :, i] = cr.scaled_lower, cr.scaled_upper
        out["support"][:, i] = cr.support
        unconv += cr.n_unconverged
    out["n_unconverged"] = unconv
    out["seconds"] = time.perf_counter() - t0
    return out


def check_ranges(lower, upper, mode: int) -> None:
    """Raise :class:`AssumptionError` where a certified range is empty (the data refute the assumption)."""
    bad = np.argwhere(lower > upper)
    if bad.size:
        q, i = (int(v) for v in bad[0])
        raise AssumptionError(
            f"the data contradict the assumption: the certified range of mode {mode}, component {i + 1} is "
            f"empty on {len(bad)} cells (e.g. cell {q}: [{lower[q, i]:.6g}, {upper[q, i]:.6g}]); "
            "no function allowed by [learning].rkhs_bound, the lengthscale and the noise bound explains them")


def image_ranges(data, known_maps, cells_lower, cells_upper, *, lengthscale, rkhs_bound: float, noise_bound,
                 misspecification: float = 0.0, method: str = "optimal", iid_theta=None, iid_delta: float = 0.0,
                 data_failure: float = 0.0, progress: Callable[[str], None] | None = None,
                 chunk_cells: int | None = None) -> ImageRanges:
    """Certified image boxes ``f_u + g_u`` of all modes and outputs over all cells (in this process).

    The pipeline runs the same :func:`bound_chunk` tasks on a scheduler; this is the serial form.

    Parameters
    ----------
    data : sequence (n_modes) of (X (m_u, d), Y (m_u, n)) pairs
        Inputs and residuals ``x_next - f_u(x)``.
    known_maps : sequence (n_modes) of objects with ``A (n, d)`` and ``b (n,)``
    cells_lower, cells_upper : (n_cells, d) float arrays
    lengthscale, rkhs_bound, misspecification
        The assumption (see the module docstring).
    noise_bound : (n,) float array
        Bound of the data noise per output (from :func:`noise_bound_at_confidence`).
    method : {"optimal", "ridge"}
    iid_theta : (n,) float array, optional
        Sub-Gaussian parameter per output: intersect with the iid bound (section 4) at failure
        probability ``iid_delta``.
    data_failure : float
        Probability that ``noise_bound`` fails (0 for bounded noise), for the stated confidence.
    progress : callable(str), optional
        Receives one line per mode with its time and error radius.
    chunk_cells : int, optional
        Cells per call of :func:`bound_chunk` (rounded up to a multiple of :data:`CELL_BLOCK`).

    Returns
    -------
    ImageRanges
    """
    t0 = time.perf_counter()
    M = len(data)
    lower, upper = _check_cells(cells_lower, cells_upper, np.shape(data[0][0])[1])
    N, d = lower.shape
    n = len(np.atleast_1d(noise_bound))
    iid_factor = None if iid_theta is None else hoeffding_factor(M * n * N * 2 ** d, iid_delta)
    step = N if chunk_cells is None else max(CELL_BLOCK, -(-int(chunk_cells) // CELL_BLOCK) * CELL_BLOCK)
    out_lo = np.empty((M, N, n))
    out_up = np.empty((M, N, n))
    eps = np.empty((M, N, n))
    sup = np.empty((M, N, n), dtype=np.int64)
    unconv = 0
    for u, (X, Y) in enumerate(data):
        t = time.perf_counter()
        for s0 in range(0, N, step):
            sl = slice(s0, min(N, s0 + step))
            r = bound_chunk(X, Y, known_maps[u].A, known_maps[u].b, lower[sl], upper[sl], lengthscale=lengthscale,
                            rkhs_bound=rkhs_bound, noise_bound=noise_bound, misspecification=misspecification,
                            method=method, iid_factor=iid_factor, iid_theta=iid_theta)
            out_lo[u, sl], out_up[u, sl], eps[u, sl], sup[u, sl] = r["lower"], r["upper"], r["eps"], r["support"]
            unconv += r["n_unconverged"]
        check_ranges(out_lo[u], out_up[u], u)
        line = (f"bound: mode {u}: {N} cells x {n} outputs in {time.perf_counter() - t:.2f} s, eps median "
                f"{np.median(eps[u]):.4g} max {np.max(eps[u]):.4g}")
        log.info(line)
        if progress is not None:
            progress(line)
    confidence = 1.0 - float(data_failure) - (float(iid_delta) if iid_factor is not None else 0.0)
    return ImageRanges(out_lo, out_up, eps, sup, (), confidence, unconv, time.perf_counter() - t0)
