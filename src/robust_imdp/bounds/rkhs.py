r"""Certified bounds of an unknown function of bounded RKHS norm over whole cells, from noisy data.

This is the *learn + bound* stage of the tight route (issue 9). It needs no Gaussian-process
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

import itertools
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numba
import numpy as np

from robust_imdp.errors import AssumptionError, DimensionError, InvalidInputError

__all__ = [
    "KernelModel", "NormCheck", "CellRange", "ImageRanges", "METHODS",
    "taylor_remainder_sqrt_up", "cell_centres", "vertex_signs", "unit_kernel",
    "certify_weights", "vertex_problems", "optimal_weights", "cell_ranges", "min_rkhs_norm", "check_assumption",
    "image_ranges", "bound_chunk", "check_ranges", "CELL_BLOCK", "local_pools", "local_lambda", "noise_bound_at_confidence", "hoeffding_factor",
    "SPLIT_TOL", "MAX_SUB", "split_counts", "sub_boxes",
]

log = logging.getLogger(__name__)

_U = 2.0 ** -53  # unit round-off of float64
#: Ways to choose the certificate weights (see the module docstring, sections 1-3).
METHODS = ("optimal", "ridge")
#: Ridge regularisers tried per vertex by ``method="ridge"`` and by the iid route.
RIDGE_LAMBDAS = tuple(float(v) for v in np.logspace(-9, 1, 31))
#: Largest support (number of data points with a non-zero weight) of one optimal certificate.
MAX_SUPPORT = 400


def _gamma(n: float) -> float:
    """``gamma_n = n u / (1 - n u)``: relative error bound of a sum of ``n + 1`` float terms."""
    return n * _U / (1.0 - n * _U)


def _writable(a) -> np.ndarray:
    """A writable C-contiguous float64 array (a copy only when needed)."""
    return np.require(np.asarray(a, dtype=np.float64), requirements=["C", "W"])


def _up(x, err=0.0):
    """Upper bound of a real known to lie within ``err`` of the float ``x`` (one more ulp up)."""
    return np.nextafter(np.asarray(x, float) + err, np.inf)


def _down(x, err=0.0):
    """Lower bound of a real known to lie within ``err`` of the float ``x`` (one more ulp down)."""
    return np.nextafter(np.asarray(x, float) - err, -np.inf)


# ============================================================================ geometry
def cell_centres(lower, upper):
    """Centres ``c`` and half-widths ``r`` with ``[lower, upper] ⊆ [c - r, c + r]`` exactly.

    ``c = fl((lower + upper) / 2)`` need not be the exact midpoint, so ``r`` is the larger of
    ``upper - c`` and ``c - lower``, each rounded up.

    Parameters
    ----------
    lower, upper : (n_cells, d) float arrays

    Returns
    -------
    c, r : (n_cells, d) float arrays
    """
    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)
    c = 0.5 * lower + 0.5 * upper  # no overflow; within the box since both halves are exact
    c = np.minimum(np.maximum(c, lower), upper)
    r = np.maximum(_up(upper - c), _up(c - lower))
    return c, r


def vertex_signs(d: int) -> np.ndarray:
    """``(2^d, d)`` array of the sign patterns ``{-1, +1}^d`` (vertex ``v = signs * r``)."""
    return np.array(list(itertools.product((-1.0, 1.0), repeat=int(d))), dtype=float)


def taylor_remainder_sqrt_up(t) -> np.ndarray:
    """Upper bound of ``sqrt(R(t))``, the feature-map Taylor remainder of (eq. T).

    ``R(t) = 2(1 - e^{-t/2}) + t(1 - 2e^{-t/2})`` (``t >= 0``). Two upper bounds are combined:
    ``R(t) <= 3 t^2 / 4`` (because ``R(0) = R'(0) = 0`` and ``R'(t) <= 3t/2``: the function
    ``3t/2 - R'(t)`` vanishes at 0 and has derivative ``3/2 - e^{-t/2}(3 - t)/2 >= 0``), and the
    float evaluation ``2 E (1 + t) - t`` with ``E = -expm1(-t/2)`` plus its error bound
    (``8 u`` times the magnitude of the terms; expm1 and exp are accurate to a few ulps).

    Parameters
    ----------
    t : float or array, >= 0

    Returns
    -------
    float array
    """
    t = np.asarray(t, float)
    if np.any(~np.isfinite(t) | (t < 0)):
        raise InvalidInputError(f"t must be finite and >= 0; got {t[~np.isfinite(t) | (t < 0)].ravel()[:3]}")
    quad = _up(_up(_up(t * t) * 3.0) / 4.0)
    E = -np.expm1(-0.5 * t)
    direct = 2.0 * E * (1.0 + t) - t
    direct = _up(direct, 8 * _U * (2.0 * E * (1.0 + t) + t) + 1e-300)
    R = np.minimum(quad, np.maximum(direct, 0.0))
    return _up(np.sqrt(R))


# ============================================================================ kernel
@numba.njit(cache=True)
def _kernel_matrix(A, B, inv_l2):  # pragma: no cover - compiled
    """``exp(-z/2)``, ``z = sum_a (A_a - B_a)^2 inv_l2_a``, and the largest ``z`` met."""
    p, q, d = A.shape[0], B.shape[0], A.shape[1]
    K = np.empty((p, q))
    zmax = 0.0
    for i in range(p):
        for j in range(q):
            z = 0.0
            for a in range(d):
                diff = A[i, a] - B[j, a]
                z += diff * diff * inv_l2[a]
            if z > zmax:
                zmax = z
            K[i, j] = math.exp(-0.5 * z)
    return K, zmax


def _kernel_rel_err(zmax: float, d: int) -> float:
    """Relative error bound of every computed kernel value ``exp(-z/2)`` with ``z <= zmax``.

    ``z`` is a sum of d products of rounded differences: relative error ``<= (d + 3) u``
    (difference, square, product with ``inv_l2`` and ``d - 1`` additions), i.e. an absolute
    error ``<= (d + 3) u z / 2`` in the exponent, a relative error ``<= e^{(d+3) u z/2} - 1`` of the
    exact exponential; exp itself is accurate to 1 ulp in glibc/LLVM (we allow 2, and the
    inverse lengthscales' own rounding, 3 u relative in ``z``, is covered by using ``d + 6``).
    """
    x = (d + 6) * _U * zmax / 2.0
    return float((math.expm1(x) + 2 * _U) * (1 + 1e-6) + 4 * _U)


def _inv_l2(lengthscale, d: int, name: str = "lengthscale") -> np.ndarray:
    ls = np.asarray(lengthscale, float)
    if ls.ndim == 0:
        ls = np.full(d, float(ls))
    if ls.shape != (d,):
        raise DimensionError(f"{name} must be a float or have shape ({d},); got shape {ls.shape}")
    if not np.all(np.isfinite(ls) & (ls > 0)):
        raise InvalidInputError(f"{name} must be positive and finite; got {ls.tolist()}")
    # Rounded UP: the kernel actually evaluated has lengthscales l' <= l, and for SE kernels
    # H_l ⊆ H_l' with ||f||_l' <= prod_a (l_a/l'_a)^{1/2} ||f||_l (Steinwart & Christmann 2008,
    # Prop. 4.46), so the assumption carries over with B inflated by :func:`_norm_inflation`.
    return _up((1.0 / (ls * ls)) * (1.0 + 4 * _U))


def _norm_inflation(d: int) -> float:
    """Factor covering ``prod_a (l_a / l'_a)^{1/2}`` for the rounded-up inverse squares (<= 1 + 8u per axis)."""
    return 1.0 + (4 * d + 8) * _U


def unit_kernel(A, B, lengthscale) -> np.ndarray:
    """Unit-amplitude SE kernel matrix ``exp(-sum_a (A_a - B_a)^2 / (2 l_a^2))``.

    Parameters
    ----------
    A : (p, d) float array
    B : (q, d) float array
    lengthscale : float or (d,) float array

    Returns
    -------
    (p, q) float array
    """
    A = np.ascontiguousarray(A, float)
    B = np.ascontiguousarray(B, float)
    return _kernel_matrix(A, B, _inv_l2(lengthscale, A.shape[1]))[0]


@dataclass(frozen=True, eq=False)
class KernelModel:
    """The data of one unknown component (one mode, one output) and the kernel.

    Parameters
    ----------
    X : (m, d) float array
        Inputs.
    y : (m,) float array
        Residuals ``x_next_i - f_u(x_i)`` of this output.
    lengthscale : float or (d,) float array
        SE lengthscales of the unit-amplitude kernel of the assumption.

    Attributes
    ----------
    K : (m, m) float array
        Kernel matrix; every entry within relative ``K_err`` of the exact value.
    K_err : float
    inv_l2 : (d,) float array
    """

    X: np.ndarray
    y: np.ndarray
    lengthscale: Any
    K: np.ndarray = field(init=False, repr=False)
    K_err: float = field(init=False)
    inv_l2: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        # Writable C-contiguous copies: numba compiles (and caches) one specialisation per array
        # type, and arrays received from a Dask worker's deserialiser are read-only (a second
        # 12-s compilation in every worker otherwise).
        X = _writable(self.X)
        y = _writable(self.y)
        if X.ndim != 2 or X.shape[0] < 1:
            raise DimensionError(f"X must be a (m, d) float array with m >= 1; got shape {X.shape}")
        if y.shape != (X.shape[0],):
            raise DimensionError(f"y must have shape ({X.shape[0]},) like X's rows; got {y.shape}")
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(y))):
            raise InvalidInputError("X and y must be finite")
        inv_l2 = _inv_l2(self.lengthscale, X.shape[1])
        K, zmax = _kernel_matrix(X, X, inv_l2)
        object.__setattr__(self, "X", X)
        object.__setattr__(self, "y", y)
        object.__setattr__(self, "inv_l2", inv_l2)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "K_err", _kernel_rel_err(zmax, X.shape[1]))

    @property
    def m(self) -> int:
        return self.X.shape[0]

    @property
    def d(self) -> int:
        return self.X.shape[1]


# ============================================================================ vertex problems
@numba.njit(cache=True)
def _vertex_b(X, inv_l2, c, v, b, eb):  # pragma: no cover - compiled
    """``b_i = <k_{x_i}, phi_v> = k(x_i, c) (1 + sum_a v_a (x_ia - c_a) inv_l2_a)`` and abs. errors.

    Returns the largest exponent ``z`` met (for the kernel's relative error bound).
    """
    m, d = X.shape
    zmax = 0.0
    for i in range(m):
        z = 0.0
        br = 1.0
        mag = 1.0
        for a in range(d):
            diff = X[i, a] - c[a]
            z += diff * diff * inv_l2[a]
            t = v[a] * diff * inv_l2[a]
            br += t
            mag += abs(t)
        if z > zmax:
            zmax = z
        k = math.exp(-0.5 * z)
        b[i] = k * br
        # bracket: d + 1 terms, each of 3 roundings -> (d + 4) u * mag; product: 1 ulp
        eb[i] = k * (d + 5) * 1.1102230246251565e-16 * mag
    return zmax


def vertex_problems(model: KernelModel, c, r, signs=None):
    """The data of (eq. C) for every cell and vertex: ``b``, its error, ``<phi_v, phi_v>``.

    Parameters
    ----------
    model : KernelModel
    c, r : (n_cells, d) float arrays
        Centres and half-widths (:func:`cell_centres`).
    signs : (V, d) float array, optional
        Vertex sign patterns (default all ``2^d``).

    Returns
    -------
    dict with ``b`` (n_cells, V, m), ``b_err`` (same; absolute errors including the kernel's),
    ``s0`` (n_cells, V) upper bounds of ``<phi_v, phi_v>`` and ``v`` (n_cells, V, d).
    """
    signs = vertex_signs(model.d) if signs is None else np.asarray(signs, float)
    n, V, m = c.shape[0], signs.shape[0], model.m
    b = np.empty((n, V, m))
    eb = np.empty((n, V, m))
    v_all = signs[None, :, :] * r[:, None, :]
    for q in range(n):
        for j in range(V):
            z = _vertex_b(model.X, model.inv_l2, c[q], v_all[q, j], b[q, j], eb[q, j])
            eb[q, j] += np.abs(b[q, j]) * _kernel_rel_err(z, model.d)
    s0 = _up(1.0 + np.sum(v_all * v_all * model.inv_l2, axis=-1), (model.d + 8) * _U * 2.0)
    return {"b": b, "b_err": eb, "s0": s0, "v": v_all}


# ============================================================================ certified evaluator
@numba.njit(cache=True)
def _certified_norms(idx, w, n, b, eb, K, K_err, s0):  # pragma: no cover - compiled
    """Upper bounds of ``||w||_1``, ``||w||_2`` and ``||phi - Phi* w||`` (the y-free part of eq. W).

    ``w`` is supported on ``idx[:n]``; ``b``/``eb`` are ``<k_{x_i}, phi>`` and their absolute
    errors, ``K`` the kernel matrix with relative entry error ``K_err``, ``s0`` an upper bound
    of ``<phi, phi>``.
    """
    u = 1.1102230246251565e-16
    l1 = 0.0
    l2 = 0.0
    bw = 0.0
    bw_abs = 0.0
    bw_err = 0.0
    for p in range(n):
        i = idx[p]
        wi = w[p]
        l1 += abs(wi)
        l2 += wi * wi
        bw += wi * b[i]
        bw_abs += abs(wi * b[i])
        bw_err += abs(wi) * eb[i]
    wKw = 0.0
    wKw_abs = 0.0
    for p in range(n):
        i = idx[p]
        row = 0.0
        row_abs = 0.0
        for q in range(n):
            kij = K[i, idx[q]]
            row += kij * w[q]
            row_abs += kij * abs(w[q])
        wKw += w[p] * row
        wKw_abs += abs(w[p]) * row_abs
    q2 = s0 - 2.0 * bw + wKw
    # Error of q2 against the exact <phi,phi> - 2 w.b + w.K w (exact b, K): summation
    # (2n + 6 terms deep, gamma bound on the sum of magnitudes), entry errors of b and K, and
    # s0 is already an upper bound (so it only enters the magnitude).
    nn = 2.0 * n + 8.0
    gam = nn * u / (1.0 - nn * u)
    mag = s0 + 2.0 * bw_abs + wKw_abs
    err = gam * mag + 2.0 * bw_err + K_err * wKw_abs
    err = err * (1.0 + 4.0 * gam) + 1e-300
    q_up = q2 + err
    if q_up < 0.0:
        q_up = 0.0
    r_up = math.sqrt(q_up) * (1.0 + 2.0 * u)
    g1 = (n + 2.0) * u / (1.0 - (n + 2.0) * u)
    l1_up = l1 * (1.0 + g1) * (1.0 + 2.0 * u)
    l2_up = math.sqrt(l2 * (1.0 + g1)) * (1.0 + 2.0 * u)
    return l1_up, l2_up, r_up


@numba.njit(cache=True)
def _certified_value(idx, w, n, y, l1_up, l2_up, r_up, a1, a2, G, side):  # pragma: no cover - compiled
    """Certified ``w.y + side (a1 ||w||_1 + a2 ||w||_2 + G ||phi - Phi* w||)`` from :func:`_certified_norms`."""
    u = 1.1102230246251565e-16
    yw = 0.0
    yw_abs = 0.0
    for p in range(n):
        t = w[p] * y[idx[p]]
        yw += t
        yw_abs += abs(t)
    radius = (a1 * l1_up + a2 * l2_up + G * r_up) * (1.0 + 8.0 * u)
    total = yw + side * radius
    # yw: n-term sum; final addition: 1 ulp of |yw| + radius.
    g1 = (n + 2.0) * u / (1.0 - (n + 2.0) * u)
    terr = g1 * yw_abs + 4.0 * u * (abs(yw) + radius) + 1e-300
    if side > 0:
        return np.nextafter(total + terr, np.inf), radius
    return np.nextafter(total - terr, -np.inf), radius


@numba.njit(cache=True)
def _certify(idx, w, n, y, b, eb, K, K_err, s0, a1, a2, G, side):  # pragma: no cover - compiled
    """Certified ``w.y + side (a1 ||w||_1 + a2 ||w||_2 + G ||phi - Phi* w||)`` (eq. W).

    The one certified evaluator: an upper bound (side = +1) or a lower bound (side = -1) of
    the exact value for these weights, and the radius ``a1||w||_1 + a2||w||_2 + G r``.
    """
    l1_up, l2_up, r_up = _certified_norms(idx, w, n, b, eb, K, K_err, s0)
    return _certified_value(idx, w, n, y, l1_up, l2_up, r_up, a1, a2, G, side)


def certify_weights(model: KernelModel, b, b_err, s0, weights, *, noise_l1: float, rkhs_bound: float,
                    noise_l2: float = 0.0, side: int = 1):
    """Certified value of (eq. W) for given weights (dense vectors), vectorised over problems.

    Returns an upper bound (``side=+1``) of ``w.y + noise_l1 ||w||_1 + noise_l2 ||w||_2 +
    B ||phi - Phi* w||`` or a lower bound (``side=-1``) of ``w.y - (...)``. Which weights are
    used does not matter for soundness; this is the public face of the one evaluator that
    every method goes through (used by the tests to check it independently).

    Parameters
    ----------
    model : KernelModel
    b, b_err : (k, m) float arrays
        ``<k_{x_i}, phi>`` per problem and their absolute errors.
    s0 : (k,) float array
        Upper bounds of ``<phi, phi>``.
    weights : (k, m) float array
    noise_l1, noise_l2, rkhs_bound : float >= 0
    side : {+1, -1}

    Returns
    -------
    (k,) float array
    """
    b = np.atleast_2d(np.asarray(b, float))
    b_err = np.atleast_2d(np.asarray(b_err, float))
    w = np.atleast_2d(np.asarray(weights, float))
    s0 = np.atleast_1d(np.asarray(s0, float))
    if side not in (1, -1):
        raise InvalidInputError(f"side must be +1 or -1; got {side!r}")
    if b.shape != w.shape or b_err.shape != w.shape or b.shape[1] != model.m or s0.shape != (b.shape[0],):
        raise DimensionError(
            f"b, b_err and weights must have shape (k, {model.m}) and s0 (k,); got {b.shape}, {b_err.shape}, "
            f"{w.shape}, {s0.shape}")
    out = np.empty(b.shape[0])
    idx = np.arange(model.m, dtype=np.int64)
    for k in range(b.shape[0]):
        out[k] = _certify(idx, np.ascontiguousarray(w[k]), model.m, model.y, b[k], b_err[k], model.K,
                          model.K_err, float(s0[k]), float(noise_l1), float(noise_l2), float(rkhs_bound),
                          float(side))[0]
    return out


# ============================================================================ optimal weights
@numba.njit(cache=True)
def _chol_solve2(P, n, L, r1, r2, o1, o2):  # pragma: no cover - compiled
    """Cholesky factor of ``P[:n, :n]`` into ``L``; solve for two right-hand sides. False if not PD."""
    for j in range(n):
        s = P[j, j]
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
    for rhs in range(2):
        for i in range(n):
            t = r1[i] if rhs == 0 else r2[i]
            for k in range(i):
                t -= L[i, k] * (o1[k] if rhs == 0 else o2[k])
            if rhs == 0:
                o1[i] = t / L[i, i]
            else:
                o2[i] = t / L[i, i]
        for i in range(n - 1, -1, -1):
            t = o1[i] if rhs == 0 else o2[i]
            for k in range(i + 1, n):
                t -= L[k, i] * (o1[k] if rhs == 0 else o2[k])
            if rhs == 0:
                o1[i] = t / L[i, i]
            else:
                o2[i] = t / L[i, i]
    return True


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
    failed, 4 support cap, 5 stalled).
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
    status = 1
    it = 0
    nb = 0
    Fbest = np.inf
    stall = 0
    restricted_ok = False
    while it < max_iter:
        it += 1
        if not restricted_ok:
            for p in range(nS):
                i = S[p]
                bSv[p] = b[i]
                aS[p] = ys[i] + dbar * sg[p]
                for q in range(nS):
                    P[p, q] = K[i, S[q]]
                P[p, p] += 1e-11
            if nS > 0:
                if not _chol_solve2(P, nS, L, bSv, aS, uu, vv):
                    status = 3
                    break
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
            if jmin < 0 and unbounded:
                status = 2
                break
            for p in range(nS):
                w[p] += alpha * dw[p]
            if jmin >= 0:
                k = 0
                for p in range(nS):
                    if p == jmin or sg[p] * w[p] <= 0.0:
                        inS[S[p]] = False
                        continue
                    S[k] = S[p]
                    sg[k] = sg[p]
                    w[k] = w[p]
                    k += 1
                nS = k
                continue
            restricted_ok = True
        # at a restricted optimum: objective and optimality conditions outside S
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
        if not r2 > 0.0:
            status = 0
            nb = nS
            for p in range(nS):
                bS_idx[p] = S[p]
                bw[p] = w[p]
            break
        r = math.sqrt(r2)
        Fv += G * r
        if Fv < Fbest - 1e-13 * (1.0 + abs(Fv)):
            Fbest = Fv
            stall = 0
            nb = nS
            for p in range(nS):
                bS_idx[p] = S[p]
                bw[p] = w[p]
        else:
            stall += 1
            if stall >= 4:
                status = 5
                break
        worst = tol
        jadd = -1
        sadd = 0.0
        for j in range(m):
            if inS[j]:
                continue
            f = G * (b[j] - Kw[j]) / r
            viol = abs(f - ys[j]) - dbar
            if viol > worst:
                worst = viol
                jadd = j
                sadd = 1.0 if f > ys[j] else -1.0
        if jadd < 0:
            status = 0
            break
        if nS >= cap:
            status = 4
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


@numba.njit(cache=True, parallel=True)
def _optimal_cells(X, y, K, K_err, inv_l2, c, r, signs, dbar, G, cap, max_iter, tol, ptr, lin,
                   prune, group):  # pragma: no cover - compiled
    """Certified bounds of ``<h, phi_v>`` (eq. W) with optimal weights, all cells, vertices, sides.

    Per cell and side, every vertex first gets the (certified) value of the neighbouring problem's
    weights; vertices are then optimised in the order of those values, and with ``prune`` a vertex
    whose certified value (plus ``lin``, the float known part) cannot exceed the best vertex found
    so far keeps it (status 6): the cell's bound is a maximum (upper side) or a minimum (lower side)
    over vertices, so optimising it would not change the cell bound, and any certified value is
    sound. Consecutive boxes with the same ``group`` (the sub-boxes of one cell, whose bound is
    the maximum over all of them) share that best value. Boxes ``ptr[j] .. ptr[j+1]-1`` form one
    parallel work unit (warm starts run through it). Returns ``val (n, V, 2)`` (side 0: upper
    bound, side 1: lower bound), ``support (n, V, 2)`` and ``status (n, V, 2)``.
    """
    n, d = c.shape
    V = signs.shape[0]
    m = X.shape[0]
    val = np.empty((n, V, 2))
    sup = np.zeros((n, V, 2), dtype=np.int64)
    stat = np.zeros((n, V, 2), dtype=np.int64)
    n_chunks = ptr.shape[0] - 1
    for ch in numba.prange(n_chunks):
        S = np.zeros((2, cap), dtype=np.int64)
        sg = np.zeros((2, cap))
        w = np.zeros((2, cap))
        nS = np.zeros(2, dtype=np.int64)
        lastS = np.zeros((2, cap), dtype=np.int64)
        lastw = np.zeros((2, cap))
        lastn = np.zeros(2, dtype=np.int64)
        bidx = np.zeros(cap, dtype=np.int64)
        bw = np.zeros(cap)
        Pw = np.empty((cap, cap))  # workspaces of _active_set, once per chunk
        Lw = np.empty((cap, cap))
        B = np.empty((V, m))
        EB = np.empty((V, m))
        s0 = np.empty(V)
        cheap = np.empty(V)
        ys = np.empty(m)
        v = np.empty(d)
        best_side = np.empty(2)
        for q in range(ptr[ch], ptr[ch + 1]):
            if q == ptr[ch] or group[q] != group[q - 1]:
                best_side[0] = -np.inf
                best_side[1] = -np.inf
            for jv in range(V):
                for a in range(d):
                    v[a] = signs[jv, a] * r[q, a]
                z = _vertex_b(X, inv_l2, c[q], v, B[jv], EB[jv])
                kerr = _kernel_rel_err_nb(z, d)
                for i in range(m):
                    EB[jv, i] += abs(B[jv, i]) * kerr
                t = 1.0
                for a in range(d):
                    t += v[a] * v[a] * inv_l2[a]
                s0[jv] = t * (1.0 + (d + 8) * 2.220446049250313e-16)  # upper bound of <phi_v, phi_v>
            for side in range(2):
                sgn = 1.0 if side == 0 else -1.0
                for i in range(m):
                    ys[i] = sgn * y[i]
                for jv in range(V):
                    cheap[jv] = _certify(lastS[side], lastw[side], lastn[side], y, B[jv], EB[jv], K, K_err, s0[jv],
                                         dbar, 0.0, G, sgn)[0]
                order = np.argsort(-sgn * (lin[q] + cheap))
                best = best_side[side]
                for k in range(V):
                    jv = order[k]
                    if prune and best > -np.inf and sgn * (lin[q, jv] + cheap[jv]) <= best:
                        val[q, jv, side] = cheap[jv]
                        sup[q, jv, side] = lastn[side]
                        stat[q, jv, side] = 6
                        continue
                    res = _active_set(K, ys, B[jv], s0[jv], dbar, G, S[side], sg[side], w[side], nS[side], cap,
                                      max_iter, tol, bidx, bw, Pw, Lw)
                    nS[side] = res[0]
                    nb = res[1]
                    stat[q, jv, side] = res[3]
                    # the certificate: the best weights met (any weights are sound; none -> w = 0)
                    cv = _certify(bidx, bw, nb, y, B[jv], EB[jv], K, K_err, s0[jv], dbar, 0.0, G, sgn)[0]
                    if sgn * cv > sgn * cheap[jv]:  # the neighbour's weights were better: keep them
                        cv = cheap[jv]
                    val[q, jv, side] = cv
                    sup[q, jv, side] = nb
                    if sgn * (lin[q, jv] + cv) > best:
                        best = sgn * (lin[q, jv] + cv)
                    lastn[side] = nb
                    for p in range(nb):
                        lastS[side, p] = bidx[p]
                        lastw[side, p] = bw[p]
                    if prune:  # the weights just found certify the remaining vertices of this cell too
                        for k2 in range(k + 1, V):
                            j2 = order[k2]
                            c2 = _certify(bidx, bw, nb, y, B[j2], EB[j2], K, K_err, s0[j2], dbar, 0.0, G, sgn)[0]
                            if sgn * c2 < sgn * cheap[j2]:
                                cheap[j2] = c2
                    if res[3] == 2 or res[3] == 3:
                        # inconsistent or ill-conditioned support: restart cold next time
                        nS[side] = 0
                best_side[side] = best
    return val, sup, stat


@numba.njit(cache=True)
def _kernel_rel_err_nb(zmax, d):  # pragma: no cover - compiled
    """Numba twin of :func:`_kernel_rel_err` (same formula; tested equal)."""
    x = (d + 6) * 1.1102230246251565e-16 * zmax / 2.0
    return (math.expm1(x) + 2 * 1.1102230246251565e-16) * (1 + 1e-6) + 4 * 1.1102230246251565e-16


# ============================================================================ ridge weights
@numba.njit(cache=True, parallel=True)
def _certify_dense(W, y, B, EB, K, K_err, s0, a1, a2, G):  # pragma: no cover - compiled
    """Certified (upper, lower, radius) of (eq. W) for dense weight columns ``W[:, k]``."""
    m, N = W.shape
    up = np.empty(N)
    lo = np.empty(N)
    rad = np.empty(N)
    idx = np.arange(m)
    for k in numba.prange(N):
        w = np.ascontiguousarray(W[:, k])
        up[k], rad[k] = _certify(idx, w, m, y, B[:, k], EB[:, k], K, K_err, s0[k], a1, a2, G, 1.0)
        lo[k], _ = _certify(idx, w, m, y, B[:, k], EB[:, k], K, K_err, s0[k], a1, a2, G, -1.0)
    return up, lo, rad


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
    """

    lower: np.ndarray
    upper: np.ndarray
    eps: np.ndarray
    support: np.ndarray
    vertex_lower: np.ndarray
    vertex_upper: np.ndarray
    taylor: np.ndarray
    n_unconverged: int = 0


def _check_cells(lower, upper, d: int):
    lower = np.ascontiguousarray(lower, float)
    upper = np.ascontiguousarray(upper, float)
    if lower.ndim != 2 or lower.shape[1] != d or upper.shape != lower.shape:
        raise DimensionError(f"cells_lower and cells_upper must have shape (n_cells, {d}); "
                             f"got {lower.shape} and {upper.shape}")
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))) or np.any(lower > upper):
        raise InvalidInputError("cells_lower and cells_upper must be finite with lower <= upper")
    return lower, upper


def _ridge_vertex_bounds(model: KernelModel, c, r, signs, a1: float, a2: float, G: float):
    """Certified (upper, lower) bounds of ``<h, phi_v>`` (n, V) with the best ridge weights per vertex."""
    vp = vertex_problems(model, c, r, signs)
    Bm = np.ascontiguousarray(vp["b"].reshape(-1, model.m).T)
    EB = np.ascontiguousarray(vp["b_err"].reshape(-1, model.m).T)
    s0 = vp["s0"].ravel()
    W = _ridge_weights(model, Bm, s0, a1, a2, G)
    up, lo, _ = _certify_dense(np.ascontiguousarray(W), model.y, Bm, EB, model.K, model.K_err, s0, a1, a2, G)
    V = signs.shape[0]
    return up.reshape(-1, V), lo.reshape(-1, V)


def _scaled_remainder_sqrt_up(a, t) -> np.ndarray:
    """Upper bound of ``max_{0 <= s <= t} ||k_x - a phi_D||`` (``t(D) = s``) for a scale ``a`` in (0, 1].

    ``||k_x - a (k_c + D.dk_c)||^2 = f(s) = 1 + a^2 + a^2 s - 2 a (1 + s) e^{-s/2}`` (the same inner
    products as (eq. T)); ``f''(s) = a e^{-s/2} (3 - s)/2 > 0`` for ``s < 3``, so on ``[0, t]`` with
    ``t <= 3`` the maximum is at an end: ``max((1 - a)^2, f(t))``. (``a = 1`` gives ``R``.) The float
    evaluation of ``f(t)`` is moved up by 16 u times the magnitude of its terms; ``1 - a`` is exact
    (Sterbenz, ``a >= 1/2``). Where ``t > 3`` the result is inf (use ``a = 1`` there).
    """
    a = np.asarray(a, float)
    t = np.asarray(t, float)
    # With alpha = a - 1 (exact, Sterbenz) and E = expm1(-t/2) the expression rearranges to
    # f(t) = alpha^2 (1 + t) - t - 2 (1 + alpha)(1 + t) E, whose terms are O(t), not O(1).
    alpha = a - 1.0
    E = np.expm1(-0.5 * t)
    p1 = alpha * alpha * (1.0 + t)
    p3 = 2.0 * (1.0 + alpha) * (1.0 + t) * E
    f_t = _up(p1 - t - p3, 16 * _U * (p1 + t + np.abs(p3)) + 1e-300)
    one_minus = 1.0 - a
    f_0 = _up(one_minus * one_minus)
    out = _up(np.sqrt(np.maximum(np.maximum(f_t, f_0), 0.0)))
    return np.where((t <= 3.0) & (a >= 0.5) & (a <= 1.0), out, np.inf)


def _known_at_vertices(c, r, signs, a_row, offset: float):
    """The known affine part at every vertex, ``f(c + v) = a.c + b + a.v`` (n, V), and its rounding error."""
    v_all = signs[None, :, :] * r[:, None, :]
    lin_v = (c @ a_row + offset)[:, None] + v_all @ a_row
    d = c.shape[1]
    lin_err = (2 * d + 4) * _U * 1.01 * ((np.abs(c) @ np.abs(a_row) + abs(offset))[:, None]
                                          + np.abs(v_all) @ np.abs(a_row)) + 1e-300
    return lin_v, lin_err


def _combine_vertices(lin_v, lin_err, su, sl, t_max, G: float, tau: float):
    """Cell bounds from the vertex bounds of ``<h, phi_v>`` (eq. C), best of two feature scalings.

    For any fixed ``a >= 0``: ``h(x) = a <h, phi_D> + <h, k_x - a phi_D>``, so
    ``h(x) <= max_v a su_v + B rho(a)`` and ``h(x) >= min_v a sl_v - B rho(a)`` with ``rho(a)`` of
    :func:`_scaled_remainder_sqrt_up` (``a sup <h, phi_v> = sup <h, a phi_v>`` for ``a >= 0``).
    ``a = 1`` is the plain Taylor bound (eq. T); ``a = e^{-t_max/2}`` shrinks the remainder by
    about ``sqrt(2/3)``. Both intervals hold, so their intersection does. Then add tau.

    Returns
    -------
    lower, upper : (n,) float arrays
    taylor : (n,) float array
        The remainder-plus-tau term of the scaling that gave the narrower interval.
    """
    best_lo = np.full(su.shape[0], -np.inf)
    best_up = np.full(su.shape[0], np.inf)
    best_tay = np.full(su.shape[0], np.inf)
    best_w = np.full(su.shape[0], np.inf)
    for a in (np.ones_like(t_max), np.exp(-0.5 * t_max)):
        rho = taylor_remainder_sqrt_up(t_max) if np.all(a == 1.0) else _scaled_remainder_sqrt_up(a, t_max)
        tay = _up(_up(G * rho) + tau, 4 * _U * (G * rho + tau))
        asu = _up(a[:, None] * su, 2 * _U * np.abs(a[:, None] * su))
        asl = _down(a[:, None] * sl, 2 * _U * np.abs(a[:, None] * sl))
        vu = _up(lin_v + asu, lin_err + 2 * _U * (np.abs(lin_v) + np.abs(asu))).max(axis=1)
        vl = _down(lin_v + asl, lin_err + 2 * _U * (np.abs(lin_v) + np.abs(asl))).min(axis=1)
        up = _up(vu + tay, 4 * _U * (np.abs(vu) + tay))
        lo = _down(vl - tay, 4 * _U * (np.abs(vl) + tay))
        width = up - lo
        better = width < best_w
        best_tay = np.where(better, tay, best_tay)
        best_w = np.where(better, width, best_w)
        best_up = np.minimum(best_up, up)
        best_lo = np.maximum(best_lo, lo)
    return best_lo, best_up, best_tay


#: Suggested ``split_tol`` (off by default): a cell whose Taylor term ``B rho(t_max)`` exceeds it is
#: certified on ``s^d`` sub-boxes (``docs/rkhs_bounds.md``, "Sub-boxes"), ``s`` chosen so that the
#: sub-box term is at most it.
SPLIT_TOL = 1.5e-3
#: Most sub-boxes per cell (``s <= floor(MAX_SUB^(1/d))``).
MAX_SUB = 64


def _blocks(n_parents: int, starts, n_boxes: int, block: int) -> np.ndarray:
    """Box index where each block of ``block`` parent cells starts, and ``n_boxes`` (a work-unit pointer)."""
    return np.ascontiguousarray(np.append(np.asarray(starts, np.int64)[0:n_parents:block], n_boxes), dtype=np.int64)


def split_counts(t_max, rkhs_bound: float, d: int, split_tol: float | None = SPLIT_TOL) -> np.ndarray:
    """Pieces per axis ``s`` of every cell's certification sub-boxes (1: the cell itself).

    A choice only (any split is sound): the Taylor term of eq. C is about ``B rho(t)`` with
    ``rho(t) ~ t`` for small ``t``, and a sub-box of ``1/s`` the size has ``t / s^2``, so
    ``s = ceil(sqrt(B rho(t_max) / split_tol))``, capped at ``floor(MAX_SUB^(1/d))``.
    """
    t_max = np.asarray(t_max, float)
    if not split_tol:
        return np.ones(t_max.shape, dtype=np.int64)
    a = np.exp(-0.5 * t_max)
    rho = np.minimum(taylor_remainder_sqrt_up(t_max), _scaled_remainder_sqrt_up(a, t_max))
    s = np.ceil(np.sqrt(float(rkhs_bound) * rho / float(split_tol)))
    s_max = max(1, int(math.floor(MAX_SUB ** (1.0 / d) + 1e-9)))
    return np.clip(np.nan_to_num(s, nan=1.0, posinf=s_max), 1, s_max).astype(np.int64)


def sub_boxes(lower, upper, s):
    """The ``s[q]^d`` sub-boxes of every cell whose union covers the cell exactly.

    Per axis the edges are ``e_0 = lower``, ``e_k = min(fl(lower + fl(w k / s)), upper)``,
    ``e_s = upper`` (non-decreasing in k), and sub-box ``(k_1, .., k_d)`` is
    ``prod_a [e_{k_a}, e_{k_a + 1}]``: neighbours share their float edges, so every point of the
    cell lies in some sub-box (no gap from rounding). Sub-boxes of a cell are consecutive, in
    ``itertools.product(range(s), repeat=d)`` order.

    Parameters
    ----------
    lower, upper : (n, d) float arrays
    s : (n,) int array >= 1

    Returns
    -------
    box_lower, box_upper : (N, d) float arrays
    parent : (N,) int array
        The cell of each sub-box (non-decreasing).
    starts : (n,) int array
        Index of each cell's first sub-box.
    """
    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)
    s = np.asarray(s, np.int64)
    n, d = lower.shape
    counts = s ** d
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    N = int(counts.sum())
    blo = np.empty((N, d))
    bup = np.empty((N, d))
    parent = np.repeat(np.arange(n, dtype=np.int64), counts)
    for sv in np.unique(s):
        cells = np.flatnonzero(s == sv)
        k = np.arange(int(sv) + 1, dtype=float)
        w = upper[cells] - lower[cells]
        e = np.minimum(lower[cells, :, None] + w[:, :, None] * (k / float(sv)), upper[cells, :, None])
        e[:, :, 0] = lower[cells]
        e[:, :, -1] = upper[cells]  # (nc, d, s + 1)
        idx = np.array(list(itertools.product(range(int(sv)), repeat=d)), dtype=np.int64)  # (s^d, d)
        rows = starts[cells][:, None] + np.arange(idx.shape[0])[None, :]  # (nc, s^d)
        blo[rows] = np.stack([e[:, a, idx[:, a]] for a in range(d)], axis=-1)
        bup[rows] = np.stack([e[:, a, idx[:, a] + 1] for a in range(d)], axis=-1)
    return blo, bup, parent, starts


def _corner_boxes(s, starts, signs) -> np.ndarray:
    """(n, V) index of the sub-box holding each cell vertex (the corner sub-box on that side)."""
    d = signs.shape[1]
    s = np.asarray(s, np.int64)
    k = (signs[None, :, :] > 0) * (s[:, None, None] - 1)  # (n, V, d): sub-box index per axis
    place = s[:, None, None] ** np.arange(d - 1, -1, -1)[None, None, :]
    return starts[:, None] + np.sum(k * place, axis=-1)


def cell_ranges(model: KernelModel, cells_lower, cells_upper, *, rkhs_bound: float, noise_bound: float,
                misspecification: float = 0.0, known_row=None, known_offset: float = 0.0,
                method: str = "optimal", iid_factor: float | None = None, iid_theta: float = 0.0,
                chunk: int = 16, max_iter: int = 2000, tol: float = 1e-9, prune: bool = True,
                split_tol: float | None = None) -> CellRange:
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
    t_cell = _up(np.sum(r * r * model.inv_l2, axis=1) * (1 + (d + 4) * _U))
    s_split = split_counts(t_cell, G_eff, d, split_tol)
    if np.any(s_split > 1):  # certify on sub-boxes (their union covers the cell): the hull is sound
        box_lo, box_up, parent, starts = sub_boxes(lower, upper, s_split)
        c, r = cell_centres(box_lo, box_up)
    else:
        parent = np.arange(n_cells, dtype=np.int64)
        starts = parent
    lin_v, lin_err = _known_at_vertices(c, r, signs, a_row, float(known_offset))
    t_max = _up(np.sum(r * r * model.inv_l2, axis=1) * (1 + (d + 4) * _U))
    n_unconv = 0
    if method == "optimal":
        cap = int(min(model.m, MAX_SUPPORT))
        ptr = _blocks(n_cells, starts, c.shape[0], int(chunk))
        val, sup, stat = _optimal_cells(model.X, model.y, model.K, model.K_err, model.inv_l2, c, r, signs, dbar,
                                        G_eff, cap, int(max_iter), float(tol), ptr, lin_v, bool(prune), parent)
        su, sl = val[:, :, 0], val[:, :, 1]
        optimised = (stat[:, :, 0] != 6) & (stat[:, :, 1] != 6)
        support = sup.max(axis=(1, 2))
        n_unconv = int(np.sum((stat != 0) & (stat != 5) & (stat != 6)))
    else:
        su, sl = _ridge_vertex_bounds(model, c, r, signs, dbar, 0.0, G_eff)
        optimised = None
        support = np.full(c.shape[0], model.m)
    if iid_factor is not None:
        a2 = float(_up(float(iid_factor) * float(iid_theta) * (1 + 4 * _U)))
        iu, il = _ridge_vertex_bounds(model, c, r, signs, tau, a2, G_eff)
        # Intersection of two intervals that both hold (the iid one on the data event).
        su, sl = np.minimum(su, iu), np.maximum(sl, il)
    lower_c, upper_c, taylor = _combine_vertices(lin_v, lin_err, su, sl, t_max, G_eff, tau)
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
                     taylor=taylor, n_unconverged=n_unconv)


# ============================================================================ the assumption
@dataclass(frozen=True)
class NormCheck:
    """Data-implied minimum RKHS norm of one unknown component (a certified lower bound).

    Attributes
    ----------
    mode, output : int
    minimum : float
        Every function ``h`` with ``|h(x_i) - y_i| <= noise_bound + tau`` for the points used has
        ``||h|| >= minimum`` (for the assumption's lengthscale); rounded down.
    n_points : int
        Number of data points used (a subset of a large data set still gives a valid bound).
    sample : int
        Row (in the user's data) of the point with the largest single-point bound.
    single_minimum : float
        That point's own bound ``|y_i| - noise_bound - tau`` (``|h(x)| <= ||h||`` for the
        unit-amplitude kernel, so one point alone can refute B).
    residual : float
        That point's residual.
    """

    mode: int
    output: int
    minimum: float
    n_points: int
    sample: int = -1
    single_minimum: float = 0.0
    residual: float = 0.0


def min_rkhs_norm(X, y, lengthscale, noise_bound: float, misspecification: float = 0.0, *,
                  max_points: int | None = 300, rng: Any = 0, solver: bool = True) -> dict:
    """Certified lower bound of ``min { ||h|| : |h(x_i) - y_i| <= noise_bound + tau }`` (section 4).

    Two certificates, the larger is the minimum: single points (``||h|| >= |h(x_i)| >=
    |y_i| - dbar'``) and the dual weights of the SOCP of :func:`robust_imdp.solvers.lp.rkhs_min_norm_socp`
    (``||h|| >= (w.y - dbar' ||w||_1) / sqrt(w.K w)`` for every such h). Both are evaluated with
    outward rounding, and divided by the lengthscale-rounding factor of :func:`_inv_l2`.

    Parameters
    ----------
    X : (m, d) float array
    y : (m,) float array
    lengthscale : float or (d,) float array
    noise_bound, misspecification : float >= 0
    max_points : int or None
        Largest number of points given to the SOCP (a seeded random subset; dropping points
        only lowers the minimum, so the bound stays valid).
    rng : seed
    solver : bool
        False: single points only (no cvxpy).

    Returns
    -------
    dict with ``minimum`` (float), ``n_points`` (points behind it), ``sample`` (index of the
    point with the largest single-point bound) and ``single_minimum`` (that bound).
    """
    X = np.ascontiguousarray(X, float)
    y = np.ascontiguousarray(y, float)
    dbar = float(_up(float(noise_bound) + float(misspecification)))
    infl = _norm_inflation(X.shape[1])
    single = _down(np.abs(y) - dbar)
    i_best = int(np.argmax(single))
    single_min = max(float(_down(max(float(single[i_best]), 0.0) / infl)), 0.0)
    best, n_used = single_min, 1
    if solver and X.shape[0] >= 2:
        idx = np.arange(X.shape[0])
        if max_points is not None and X.shape[0] > int(max_points):
            idx = np.sort(np.random.default_rng(rng).choice(X.shape[0], int(max_points), replace=False))
        model = KernelModel(X[idx], y[idx], lengthscale)
        from robust_imdp.solvers.lp import rkhs_min_norm_socp

        w, _ = rkhs_min_norm_socp(model.K, model.y, dbar)
        m = idx.size
        g = _gamma(2 * m + 4)
        num = float(w @ model.y - dbar * np.sum(np.abs(w)))
        num_lo = float(_down(num, g * float(np.abs(w) @ np.abs(model.y) + dbar * np.sum(np.abs(w)))))
        aw = np.abs(w)
        wKw_abs = float(aw @ model.K @ aw)
        den_up = float(_up(float(w @ model.K @ w), (g + model.K_err) * wKw_abs * (1 + 4 * g)))
        if num_lo > 0 and den_up > 0:
            joint = float(_down(num_lo / float(_up(math.sqrt(den_up))), 2 * _U * num_lo))
            joint = float(_down(joint / infl))
            if joint > best:
                best, n_used = joint, m
    return {"minimum": best, "n_points": n_used, "sample": i_best, "single_minimum": single_min}


def check_assumption(data, *, lengthscale, rkhs_bound: float, noise_bound, misspecification: float = 0.0,
                     mode_names: Sequence[str] | None = None, sample_index=None, max_points: int | None = 300,
                     solver: bool = True, refuse: bool = True) -> tuple:
    """Compute the data-implied minimum norm of every component; refuse a refuted ``rkhs_bound``.

    Parameters
    ----------
    data : sequence (n_modes) of (X (m_u, d), Y (m_u, n)) pairs
        Inputs and residuals ``x_next - f_u(x)`` per mode.
    lengthscale, rkhs_bound, misspecification
        The assumption.
    noise_bound : (n,) float array
        Noise bound per output.
    mode_names : sequence of str, optional
        For messages.
    sample_index : sequence (n_modes) of (m_u,) int arrays, optional
        Row of each sample in the user's data (for messages).
    refuse : bool
        Raise :class:`AssumptionError` when the data refute the assumption.

    Returns
    -------
    tuple of NormCheck
    """
    n = len(np.atleast_1d(noise_bound))
    nb = np.broadcast_to(np.asarray(noise_bound, float), (n,))
    names = mode_names or [str(u) for u in range(len(data))]
    checks = []
    for u, (X, Y) in enumerate(data):
        Y = np.asarray(Y, float).reshape(np.shape(X)[0], -1)
        for i in range(Y.shape[1]):
            r = min_rkhs_norm(X, Y[:, i], lengthscale, float(nb[i]), misspecification,
                              max_points=max_points, solver=solver)
            s = r["sample"]
            row = int(sample_index[u][s]) if sample_index is not None else int(s)
            checks.append(NormCheck(u, i, r["minimum"], r["n_points"], row, r["single_minimum"], float(Y[s, i])))
            log.info("assumption check: mode %s output %d: data need ||g|| >= %.4g (B = %.4g, %d points)",
                     names[u], i, r["minimum"], rkhs_bound, r["n_points"])
    if refuse:
        bad = [c for c in checks if c.minimum > float(rkhs_bound)]
        if bad:
            c = max(bad, key=lambda c: c.minimum)
            why = refutation_reason(c, float(rkhs_bound), float(nb[c.output]), float(misspecification))
            raise AssumptionError(
                f"[gp].rkhs_bound = {float(rkhs_bound):g} is refuted by the data: mode {names[c.mode]!r}, component "
                f"{c.output + 1} needs an RKHS norm of at least {c.minimum:.4g} (lengthscale "
                f"{np.asarray(lengthscale).tolist()}); {why}. Choose rkhs_bound >= {c.minimum:.4g} (with a margin), "
                "a different lengthscale, a misspecification allowance, or check the data"
                + (f" ({len(bad)} of {len(checks)} components are refuted)" if len(bad) > 1 else ""))
    return tuple(checks)


def refutation_reason(c, rkhs_bound: float, noise_bound: float, tau: float) -> str:
    """Why the check ``c`` refutes ``rkhs_bound``: one sample beyond ``B + noise bound + tau``, or no
    function of norm <= B fitting the samples (the refusal messages of every assumption check)."""
    if c.single_minimum > rkhs_bound:
        return (f"sample {c.sample} alone has residual {c.residual:.6g} in component {c.output + 1}, but "
                f"|g| <= B + noise bound + misspecification = {rkhs_bound + noise_bound + tau:.6g} everywhere")
    return (f"no function of RKHS norm <= {rkhs_bound:g} fits its {c.n_points} samples within "
            f"the noise bound {noise_bound:g}" + (f" + misspecification {tau:g}" if tau else ""))


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


# ============================================================================ local weights
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


@numba.njit(cache=True, parallel=True)
def _local_cells(X, Y, inv_l2, c, r, signs, pools, lam, a1, a2, G, optimal, max_iter, tol, ptr, group):  # pragma: no cover
    """Certified bounds of ``<h, phi_v>`` (eq. W) with weights on each cell's pool of data points.

    ``pools[q]`` are the data points allowed to carry weight for cell q (any weights are sound;
    the pool only bounds the cost). Ridge weights ``(K_PP + lam I)^{-1} b`` (one factorisation
    per cell, the same weights for every output: the radius does not involve y), or with
    ``optimal`` the active-set weights per output and side (warm-started across the cell's
    vertices). Consecutive boxes of the same ``group`` (the sub-boxes of one cell) share its pool:
    one kernel matrix and factorisation, and the warm starts run on through them. Boxes
    ``ptr[j] .. ptr[j+1]-1`` form one parallel work unit. Returns ``val (n, V, n_out, 2)``
    (side 0 upper, 1 lower) and the support sizes.
    """
    n, d = c.shape
    V = signs.shape[0]
    k = pools.shape[1]
    n_out = Y.shape[1]
    val = np.empty((n, V, n_out, 2))
    sup = np.zeros((n, V, n_out, 2), dtype=np.int64)
    n_chunks = ptr.shape[0] - 1
    for ch in numba.prange(n_chunks):
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
        for q in range(ptr[ch], ptr[ch + 1]):
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
            for jv in range(V):
                for a in range(d):
                    v[a] = signs[jv, a] * r[q, a]
                z = _vertex_b(Xp, inv_l2, c[q], v, b, eb)
                kerr = _kernel_rel_err_nb(z, d)
                for i in range(k):
                    eb[i] += abs(b[i]) * kerr
                s0 = 1.0
                for a in range(d):
                    s0 += v[a] * v[a] * inv_l2[a]
                s0 = s0 * (1.0 + (d + 8) * 2.220446049250313e-16)
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
                            val[q, jv, o, sd] = _certify(bidx, bw, nb, ys, b, eb, Kp, K_err, s0, a1[o], 0.0, G, sgn)[0]
                            sup[q, jv, o, sd] = nb
    return val, sup


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
    from scipy.spatial import cKDTree

    X = np.asarray(X, float)
    scale = np.sqrt(_inv_l2(lengthscale, X.shape[1]))
    k = int(min(max(int(k), 1), X.shape[0]))
    c = 0.5 * (np.asarray(cells_lower, float) + np.asarray(cells_upper, float))
    _, idx = cKDTree(X * scale).query(c * scale, k=k)
    return np.ascontiguousarray(np.asarray(idx, dtype=np.int64).reshape(c.shape[0], k))


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
                              float(rkhs_bound), False, 0, 0.0, _blocks(c.shape[0], one, c.shape[0], CELL_BLOCK), one)
        radius = float(np.median(val[:, :, 0, 0]))  # y = 0: the certified value is the radius
        if radius < best:
            best, best_lam = radius, lam
    return best_lam


#: Cells per numba work unit: warm starts restart at every multiple of this global cell index, so
#: results do not depend on how the cells are split into tasks (task sizes are multiples of it).
CELL_BLOCK = 16


def bound_chunk(X, Y, A, b, cells_lower, cells_upper, *, lengthscale, rkhs_bound: float, noise_bound,
                misspecification: float = 0.0, method: str = "optimal", iid_factor: float | None = None,
                iid_theta=None, local_points: int | None = None, local_lambda: float | None = None,
                threads: int | None = None, split_tol: float | None = None) -> dict:
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

    Returns
    -------
    dict with ``lower``, ``upper``, ``eps`` ((k, n) float arrays), ``support`` ((k, n) int array),
    ``n_unconverged`` (int) and ``seconds`` (float).
    """
    t0 = time.perf_counter()
    if threads is not None:
        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    if local_points is not None:
        out = _local_chunk(X, Y, A, b, cells_lower, cells_upper, lengthscale=lengthscale, rkhs_bound=rkhs_bound,
                           noise_bound=noise_bound, misspecification=misspecification, method=method,
                           iid_factor=iid_factor, iid_theta=iid_theta, k=int(local_points), lam=local_lambda,
                           split_tol=split_tol)
        out["seconds"] = time.perf_counter() - t0
        return out
    Y = np.asarray(Y, float).reshape(np.shape(X)[0], -1)
    n = Y.shape[1]
    nb = np.broadcast_to(np.asarray(noise_bound, float), (n,))
    th = None if iid_theta is None else np.broadcast_to(np.asarray(iid_theta, float), (n,))
    k = np.shape(cells_lower)[0]
    out = {key: np.empty((k, n)) for key in ("lower", "upper", "eps")}
    out["support"] = np.empty((k, n), dtype=np.int64)
    unconv = 0
    A = np.asarray(A, float)
    b = np.asarray(b, float)
    for i in range(n):
        model = KernelModel(X, Y[:, i], lengthscale)
        cr = cell_ranges(model, cells_lower, cells_upper, rkhs_bound=rkhs_bound, noise_bound=float(nb[i]),
                         misspecification=misspecification, known_row=A[i], known_offset=float(b[i]), method=method,
                         iid_factor=iid_factor, iid_theta=0.0 if th is None else float(th[i]), chunk=CELL_BLOCK,
                         split_tol=split_tol)
        out["lower"][:, i], out["upper"][:, i], out["eps"][:, i] = cr.lower, cr.upper, cr.eps
        out["support"][:, i] = cr.support
        unconv += cr.n_unconverged
    out["n_unconverged"] = unconv
    out["seconds"] = time.perf_counter() - t0
    return out


def _local_chunk(X, Y, A, b, cells_lower, cells_upper, *, lengthscale, rkhs_bound, noise_bound, misspecification,
                 method, iid_factor, iid_theta, k, lam, split_tol=None):
    """:func:`bound_chunk` with local weights (see its ``local_points``)."""
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
    s_split = split_counts(_up(np.sum(r * r * inv_l2, axis=1) * (1 + (d + 4) * _U)), G_eff, d, split_tol)
    if np.any(s_split > 1):  # certify on sub-boxes (their union covers the cell), each with its cell's pool
        box_lo, box_up, parent, starts = sub_boxes(lower, upper, s_split)
        c, r = cell_centres(box_lo, box_up)
        pools = np.ascontiguousarray(pools[parent])
    else:
        parent = np.arange(n_cells, dtype=np.int64)
        starts = parent
    ptr = _blocks(n_cells, starts, c.shape[0], CELL_BLOCK)
    val, sup = _local_cells(X, Y, inv_l2, c, r, signs, pools, float(lam or 0.0), np.ascontiguousarray(dbar),
                            np.zeros(n), G_eff, method == "optimal", 2000, 1e-9, ptr, parent)
    if iid_factor is not None:
        th = np.broadcast_to(np.asarray(iid_theta, float), (n,))
        a2 = _up(float(iid_factor) * th * (1 + 4 * _U))
        lam2 = local_lambda(X, lower, upper, lengthscale=lengthscale, rkhs_bound=rkhs_bound, noise_l1=tau,
                            noise_l2=float(a2.max()), k=k)
        iv, _ = _local_cells(X, Y, inv_l2, c, r, signs, pools, lam2, np.full(n, tau), np.ascontiguousarray(a2),
                             G_eff, False, 0, 0.0, ptr, parent)
        val[..., 0] = np.minimum(val[..., 0], iv[..., 0])  # both intervals hold: intersect
        val[..., 1] = np.maximum(val[..., 1], iv[..., 1])
    t_max = _up(np.sum(r * r * inv_l2, axis=1) * (1 + (d + 4) * _U))
    A = np.asarray(A, float)
    b = np.asarray(b, float)
    out = {key: np.empty((n_cells, n)) for key in ("lower", "upper", "eps")}
    for i in range(n):
        lin_v, lin_err = _known_at_vertices(c, r, signs, A[i], float(b[i]))
        su, sl = val[:, :, i, 0], val[:, :, i, 1]
        lo_i, up_i, taylor = _combine_vertices(lin_v, lin_err, su, sl, t_max, G_eff, tau)
        eps_i = np.max(0.5 * (su - sl), axis=1) + taylor
        # hull of each cell's sub-boxes (eq. C holds on every sub-box; reduceat is the identity unsplit)
        out["lower"][:, i] = np.minimum.reduceat(lo_i, starts)
        out["upper"][:, i] = np.maximum.reduceat(up_i, starts)
        out["eps"][:, i] = np.maximum.reduceat(eps_i, starts)
    out["support"] = np.maximum.reduceat(sup.max(axis=(1, 3)), starts, axis=0)
    out["n_unconverged"] = 0
    return out


def check_ranges(lower, upper, mode: int) -> None:
    """Raise :class:`AssumptionError` where a certified range is empty (the data refute the assumption)."""
    bad = np.argwhere(lower > upper)
    if bad.size:
        q, i = (int(v) for v in bad[0])
        raise AssumptionError(
            f"the data contradict the assumption: the certified range of mode {mode}, component {i + 1} is "
            f"empty on {len(bad)} cells (e.g. cell {q}: [{lower[q, i]:.6g}, {upper[q, i]:.6g}]); "
            "no function allowed by [gp].rkhs_bound, the lengthscale and the noise bound explains them")


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
