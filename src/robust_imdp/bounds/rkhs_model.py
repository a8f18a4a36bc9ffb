"""The RKHS route's building blocks: cell geometry and Taylor remainders, the data's kernel model, the
vertex problems, the one certified evaluator of a weight vector (eq. W), the vertex combination (eq. C) and the
certification sub-boxes. The derivations are in ``bounds/rkhs.py``'s docstring and docs/rkhs_bounds.md."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np

from robust_imdp._fp import U as _U, down as _down, up as _up
from robust_imdp._kernels import inv_l2_up as _inv_l2, kernel_matrix as _kernel_matrix, kernel_rel_err as _kernel_rel_err
from robust_imdp._kernels import kernel_rel_err_nb as _kernel_rel_err_nb
from robust_imdp._blas import quiet_openmp_waits
from robust_imdp.errors import DimensionError, InvalidInputError

# Idle OpenMP threads (numba's "omp" layer) sleep soon between parallel regions instead of spinning while this
# thread runs the Python between kernels (robust_imdp._blas.quiet_openmp_waits: the unicycle's bound kernels on
# 2 threads spent 7.7 s of CPU for 7.2 s on one, 7.0 s without spinning; the side lane's helpers get that CPU back).
# libgomp reads it when it is loaded (the first parallel kernel); a value the user set stays. No effect on any number.
quiet_openmp_waits()


#: Cells per numba work unit: warm starts restart at every multiple of this global cell index, so
#: results do not depend on how the cells are split into tasks (task sizes are multiples of it).
CELL_BLOCK = 16


def _lanes() -> int:
    """Parallel lanes of the bound kernels (``lanes`` of ``_optimal_cells_coef`` / ``_local_cells_coef``): the numba
    threads of the caller. Every lane takes the next work unit (a block of :data:`CELL_BLOCK` cells) from a shared
    counter as it comes free (``robust_imdp._atomic.fetch_add``): the blocks' costs differ (active-set iterations)
    and numba's ``prange`` splits statically on the "omp" layer, also by ``numba.parallel_chunksize`` (round-robin):
    the cyclic split had left one of two lanes with 30 % more work on a slice of the 2-D benchmark.
    Every unit allocates its own workspaces and restarts its warm starts, so the bits do not depend on the lanes.
    (Passed in, not read in the kernel: ``numba.get_num_threads`` there would keep numba from caching it.)"""
    return int(numba.get_num_threads())


def _writable(a) -> np.ndarray:
    """A writable C-contiguous float64 array (a copy only when needed)."""
    return np.require(np.asarray(a, dtype=np.float64), requirements=["C", "W"])


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


@numba.njit(cache=True)
def _vertex_functional(X, inv_l2, c, r, sign, v, b, eb):  # pragma: no cover - compiled
    """The vertex ``v = sign * r`` of the box around ``c`` (written into ``v``): ``b``, its absolute error
    ``eb`` including the kernel's own relative error, and the returned upper bound of
    ``<phi_v, phi_v> = 1 + sum_a v_a^2 inv_l2_a`` (eq. C's data of one vertex; the compiled twin of
    :func:`vertex_problems`, shared by the optimal, local and sub-box paths)."""
    d = c.shape[0]
    for a in range(d):
        v[a] = sign[a] * r[a]
    z = _vertex_b(X, inv_l2, c, v, b, eb)
    kerr = _kernel_rel_err_nb(z, d)
    for i in range(X.shape[0]):
        eb[i] += abs(b[i]) * kerr
    t = 1.0
    for a in range(d):
        t += v[a] * v[a] * inv_l2[a]
    return t * (1.0 + (d + 8) * 2.220446049250313e-16)  # upper bound of <phi_v, phi_v>


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
def _weight_parts(idx, w, n, K):  # pragma: no cover - compiled
    """The sums of (eq. W) that do not involve the functional: ``sum |w_i|``, ``sum w_i^2``, ``w.K w``
    and ``sum |w_i| K_ij |w_j|`` (float, unrounded; :func:`_norms_from_parts` bounds their errors).

    One weight vector often certifies many functionals (the vertices of a cell, its sub-boxes): these
    O(n^2) sums are then computed once.
    """
    l1 = 0.0
    l2 = 0.0
    for p in range(n):
        wi = w[p]
        l1 += abs(wi)
        l2 += wi * wi
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
    return l1, l2, wKw, wKw_abs


@numba.njit(cache=True)
def _norms_from_parts(idx, w, n, b, eb, K_err, s0, l1, l2, wKw, wKw_abs):  # pragma: no cover - compiled
    """Upper bounds of ``||w||_1``, ``||w||_2`` and ``||phi - Phi* w||`` from :func:`_weight_parts`."""
    u = 1.1102230246251565e-16
    bw = 0.0
    bw_abs = 0.0
    bw_err = 0.0
    for p in range(n):
        i = idx[p]
        wi = w[p]
        bw += wi * b[i]
        bw_abs += abs(wi * b[i])
        bw_err += abs(wi) * eb[i]
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
def _certified_norms(idx, w, n, b, eb, K, K_err, s0):  # pragma: no cover - compiled
    """Upper bounds of ``||w||_1``, ``||w||_2`` and ``||phi - Phi* w||`` (the y-free part of eq. W).

    ``w`` is supported on ``idx[:n]``; ``b``/``eb`` are ``<k_{x_i}, phi>`` and their absolute
    errors, ``K`` the kernel matrix with relative entry error ``K_err``, ``s0`` an upper bound
    of ``<phi, phi>``.
    """
    l1, l2, wKw, wKw_abs = _weight_parts(idx, w, n, K)
    return _norms_from_parts(idx, w, n, b, eb, K_err, s0, l1, l2, wKw, wKw_abs)


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
    the exact value for these weights, the radius ``a1||w||_1 + a2||w||_2 + G r`` and ``r_up``, the
    upper bound of ``||phi - Phi* w||`` the value used: the coefficient of G, with which the same
    weights certify (eq. W) at a larger norm bound (:func:`rescale_vertex_values`).
    """
    l1_up, l2_up, r_up = _certified_norms(idx, w, n, b, eb, K, K_err, s0)
    value, radius = _certified_value(idx, w, n, y, l1_up, l2_up, r_up, a1, a2, G, side)
    return value, radius, r_up


@numba.njit(cache=True)
def _certify_parts(idx, w, n, y, b, eb, K_err, s0, a1, a2, G, side, parts):  # pragma: no cover - compiled
    """:func:`_certify` with the weights' sums ``parts = _weight_parts(idx, w, n, K)`` computed once
    (the same arithmetic, so the same bits; the same three values)."""
    l1_up, l2_up, r_up = _norms_from_parts(idx, w, n, b, eb, K_err, s0, parts[0], parts[1], parts[2], parts[3])
    value, radius = _certified_value(idx, w, n, y, l1_up, l2_up, r_up, a1, a2, G, side)
    return value, radius, r_up


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


def _check_cells(lower, upper, d: int):
    lower = np.ascontiguousarray(lower, float)
    upper = np.ascontiguousarray(upper, float)
    if lower.ndim != 2 or lower.shape[1] != d or upper.shape != lower.shape:
        raise DimensionError(f"cells_lower and cells_upper must have shape (n_cells, {d}); "
                             f"got {lower.shape} and {upper.shape}")
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))) or np.any(lower > upper):
        raise InvalidInputError("cells_lower and cells_upper must be finite with lower <= upper")
    return lower, upper


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

    Parameters
    ----------
    lin_v, lin_err, su, sl : (..., n, V) float arrays
        The known part at the vertices, its error, the vertex bounds; leading axes (e.g. the outputs of one
        chunk) are combined each on its own, element by element as one at a time (the same bits), in one call.
    t_max : (n,) float array
    G, tau : float

    Returns
    -------
    lower, upper : (..., n) float arrays
    taylor : (..., n) float array
        The remainder-plus-tau term of the scaling that gave the narrower interval.
    """
    shape = np.shape(su)[:-1]
    best_lo = np.full(shape, -np.inf)
    best_up = np.full(shape, np.inf)
    best_tay = np.full(shape, np.inf)
    best_w = np.full(shape, np.inf)
    for a in (np.ones_like(t_max), np.exp(-0.5 * t_max)):
        rho = taylor_remainder_sqrt_up(t_max) if np.all(a == 1.0) else _scaled_remainder_sqrt_up(a, t_max)
        tay = _up(_up(G * rho) + tau, 4 * _U * (G * rho + tau))
        asu = _up(a[:, None] * su, 2 * _U * np.abs(a[:, None] * su))
        asl = _down(a[:, None] * sl, 2 * _U * np.abs(a[:, None] * sl))
        vu = _up(lin_v + asu, lin_err + 2 * _U * (np.abs(lin_v) + np.abs(asu))).max(axis=-1)
        vl = _down(lin_v + asl, lin_err + 2 * _U * (np.abs(lin_v) + np.abs(asl))).min(axis=-1)
        up = _up(vu + tay, 4 * _U * (np.abs(vu) + tay))
        lo = _down(vl - tay, 4 * _U * (np.abs(vl) + tay))
        width = up - lo
        better = width < best_w
        best_tay = np.where(better, tay, best_tay)
        best_w = np.where(better, width, best_w)
        best_up = np.minimum(best_up, up)
        best_lo = np.maximum(best_lo, lo)
    return best_lo, best_up, best_tay


# ============================================================================ a larger norm bound
def scaled_norm_bound(rkhs_bound: float, scale: float, d: int) -> float:
    """The certificate's norm bound at ``scale * B``: ``up(up(scale B) * inflation)``, the main path's
    ``G_eff = up(B * inflation)`` with ``B`` replaced by an upper bound of ``scale B`` (docs/rkhs_bounds.md,
    "Assumption margins")."""
    from robust_imdp._kernels import norm_inflation

    scale = float(scale)
    if not (np.isfinite(scale) and scale >= 1.0):
        raise InvalidInputError(f"scale must be a finite float >= 1; got {scale!r}")
    return float(_up(_up(float(rkhs_bound) * scale) * norm_inflation(int(d))))


def rescale_vertex_values(su, sl, cu, cl, G: float, G_new: float):
    """Vertex bounds of (eq. C) at the norm bound ``G_new >= G``, with the weights that certified them at ``G``.

    Any weights give a bound (eq. W), so those found for ``G`` hold at ``G_new`` too:
    ``w.y + dbar' ||w||_1 + G_new ||e|| = [w.y + dbar' ||w||_1 + G ||e||] + (G_new - G) ||e||``
    with ``e = phi_v - Phi* w``. The bracket is at most the certified value ``su`` (at least ``sl`` on the
    lower side) and ``||e||`` at most ``cu`` (``cl``), the upper bound of it that ``su`` (``sl``) used
    (:func:`_certify`'s third value). Each step is rounded up: ``dG = up(G_new - G)``, ``up(dG * cu)``,
    ``up(su + .)`` (``down(sl - .)``); with ``G_new = G`` the values move by a few ulps only.

    Parameters
    ----------
    su, sl : (n, V) float arrays
        Certified upper / lower bounds of ``<h, phi_v>`` at ``G`` (before the known part and the Taylor term).
    cu, cl : (n, V) float arrays
        Their coefficients of ``G`` (upper bounds of ``||phi_v - Phi* w||`` for the weights used), >= 0.
    G, G_new : float, ``0 <= G <= G_new``

    Returns
    -------
    su_new, sl_new : (n, V) float arrays
    """
    G, G_new = float(G), float(G_new)
    if not (np.isfinite(G_new) and 0.0 <= G <= G_new):
        raise InvalidInputError(f"G_new must be finite and >= G = {G!r}; got {G_new!r}")
    cu = np.asarray(cu, float)
    cl = np.asarray(cl, float)
    if np.any(~(cu >= 0)) or np.any(~(cl >= 0)):
        raise InvalidInputError("cu and cl (upper bounds of norms) must be >= 0 and not NaN")
    dG = _up(G_new - G)  # >= the exact difference of the two floats
    add_u = _up(dG * cu)
    add_l = _up(dG * cl)
    return _up(np.asarray(su, float) + add_u), _down(np.asarray(sl, float) - add_l)


def scaled_ranges(lin_v, lin_err, su, sl, cu, cl, t_max, G: float, tau: float, G_scaled, starts=None):
    """Cell ranges of (eq. C) at every norm bound of ``G_scaled``, re-using the weights found at ``G``.

    :func:`rescale_vertex_values` moves every vertex value to ``G_s``; :func:`_combine_vertices` then adds the
    known part and the Taylor remainder ``G_s rho(t_max)`` (recomputed at ``G_s``, both feature scalings) and
    tau, as on the main path; ``starts`` (the first sub-box of every cell) takes the hull over sub-boxes.

    Parameters
    ----------
    lin_v, lin_err, su, sl, cu, cl : (..., N, V) float arrays
        The known part at the vertices and its error, the vertex bounds at ``G`` and their coefficients (leading
        axes, e.g. the outputs, each on its own as in :func:`_combine_vertices`).
    t_max : (N,) float array
    G, tau : float
    G_scaled : sequence (S) of float, each >= G
    starts : (n_cells,) int array, optional

    Returns
    -------
    lower, upper : (S, ..., n_cells) float arrays
    """
    rows_lo, rows_up = [], []
    for Gs in G_scaled:
        su_s, sl_s = rescale_vertex_values(su, sl, cu, cl, G, Gs)
        lo, up, _ = _combine_vertices(lin_v, lin_err, su_s, sl_s, t_max, float(Gs), tau)
        if starts is not None:  # the hull of each cell's sub-boxes (eq. C holds on every sub-box)
            lo = np.minimum.reduceat(lo, starts, axis=-1)
            up = np.maximum.reduceat(up, starts, axis=-1)
        rows_lo.append(lo)
        rows_up.append(up)
    n = np.shape(su)[-2] if starts is None else len(starts)
    shape = (len(rows_lo), *np.shape(su)[:-2], n)
    return (np.reshape(np.array(rows_lo, float), shape), np.reshape(np.array(rows_up, float), shape))


#: Suggested ``split_tol`` (off by default): a cell whose Taylor term ``B rho(t_max)`` exceeds it is
#: certified on ``s^d`` sub-boxes (``docs/rkhs_bounds.md``, "Sub-boxes"), ``s`` chosen so that the
#: sub-box term is at most it.


SPLIT_TOL = 1.5e-3
#: Most sub-boxes per cell (``s <= floor(MAX_SUB^(1/d))``): 6 pieces per axis in 3-D, 14 in 2-D, 3 in 4-D.
#: 216 rather than 64 (4 per axis in 3-D): the family's 3-D cells at r/l 0.25 want s = 6, and with all
#: points their slack over the optimal range is 0.0031 at s = 4, 0.0014 at s = 6 (benchmarks/results/sub_cap.md);
#: in 1-D and 2-D the rule's s stays at or below 8 on the family, so the cap does not bind there.
MAX_SUB = 216


def _blocks(n_parents: int, starts, n_boxes: int, block: int) -> np.ndarray:
    """Box index where each block of ``block`` parent cells starts, and ``n_boxes`` (a work-unit pointer)."""
    return np.ascontiguousarray(np.append(np.asarray(starts, np.int64)[0:n_parents:block], n_boxes), dtype=np.int64)


def t_max_up(r, inv_l2) -> np.ndarray:
    """``t_max = sum_a r_a^2 / l_a^2`` of every box of half-widths ``r`` (n, d) (the argument of eq. C's
    remainder), rounded up: d products and d - 1 sums of non-negative terms, covered by ``1 + (d + 4) U``."""
    r = np.asarray(r, float)
    return _up(np.sum(r * r * inv_l2, axis=1) * (1 + (r.shape[1] + 4) * _U))


def split_term(t_max, rkhs_bound: float) -> np.ndarray:
    """The Taylor term ``B rho(t_max)`` that :func:`split_counts` weighs against ``split_tol`` (a choice of
    sub-boxes, not a bound: eq. C takes its own remainder on every box)."""
    t_max = np.asarray(t_max, float)
    a = np.exp(-0.5 * t_max)
    return float(rkhs_bound) * np.minimum(taylor_remainder_sqrt_up(t_max), _scaled_remainder_sqrt_up(a, t_max))


def split_counts(t_max, rkhs_bound: float, d: int, split_tol: float | None = SPLIT_TOL) -> np.ndarray:
    """Pieces per axis ``s`` of every cell's certification sub-boxes (1: the cell itself).

    A choice only (any split is sound): the Taylor term of eq. C is about ``B rho(t)`` with
    ``rho(t) ~ t`` for small ``t``, and a sub-box of ``1/s`` the size has ``t / s^2``, so
    ``s = ceil(sqrt(B rho(t_max) / split_tol))``, capped at ``floor(MAX_SUB^(1/d))``.
    """
    t_max = np.asarray(t_max, float)
    if not split_tol:
        return np.ones(t_max.shape, dtype=np.int64)
    s = np.ceil(np.sqrt(split_term(t_max, rkhs_bound) / float(split_tol)))
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
