"""The assumption certificate of the case studies: the shipped (lengthscale, B, tau) is honest.

Why the shipped assumption (lengthscale, rkhs_bound B, misspecification tau) is honest for the
TRUE unknown parts: for every mode u and output i we exhibit an h = sum_j alpha_j k(., z_j) and
certify, in floating point with outward rounding, ||h||_H <= norm_upper and
sup_X |g_u^(i) - h| <= sup_error_upper. Then g_u^(i) is within tau of a function of norm <= B
whenever sup_error_upper <= tau and norm_upper <= B. The certificate (certify_expansion) does
not depend on how alpha was found; the fit (_min_norm_fit) only proposes it.

Used by the tests and the README (never by the library itself).
"""

from __future__ import annotations

import numpy as np

from robust_imdp._fp import U, gamma, up_rounded
from robust_imdp._kernels import se_kernel_with_error as _se_kernel  # the SE kernel and its error bound
from robust_imdp.casestudies.systems import _TERM_KINDS, get_case_study
from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["rkhs_norm_upper", "certify_expansion", "assumption_certificate"]

_SQRT3_UP = float(np.nextafter(np.sqrt(3.0), np.inf))  # >= sqrt(3): sqrt is correctly rounded
#: Eigenvalues of the centres' kernel matrix below this fraction of the largest are dropped by
#: the fit (a proposal only; the certificate uses the resulting alpha as it is).
_FIT_EIG_REL_TOL = 1e-9
_CHUNK = 4096  # check-grid points per kernel block (memory: _CHUNK x n_centres floats)


def _check_lengthscale(lengthscale, d: int) -> np.ndarray:
    ls = np.asarray(lengthscale, dtype=float)
    if ls.ndim == 0:
        ls = np.full(d, float(ls))
    if ls.shape != (d,):
        raise DimensionError(f"lengthscale must be a float or have shape ({d},); got shape {ls.shape}")
    if not np.all(np.isfinite(ls) & (ls > 0)):
        raise InvalidInputError(f"lengthscale must be positive and finite; got {ls.tolist()}")
    return ls


def rkhs_norm_upper(centres, alpha, lengthscale) -> float:
    """Certified upper bound of ``||sum_j alpha_j k(., z_j)||_H`` (unit-amplitude SE kernel).

    ``||h||^2 = alpha^T K alpha`` (reproducing property). In floats, with ``K'`` the computed
    matrix (``|K' - K| <= rel K`` entrywise, :func:`_se_kernel`) and ``N' = fl(alpha . fl(K' alpha))``::

        |N' - alpha^T K' alpha| <= gamma_{2n} |alpha|^T K' |alpha|      (n-term dot products, twice)
        |alpha^T K' alpha - alpha^T K alpha| <= rel |alpha|^T K |alpha| <= rel / (1 - rel) |alpha|^T K' |alpha|

    and ``|alpha|^T K' |alpha| <= W' / (1 - gamma_{2n})`` for its float value ``W'`` (all terms
    >= 0). So ``||h||^2 <= max(N', 0) + (gamma_{2n} + rel / (1 - rel)) W' / (1 - gamma_{2n})``;
    the error is added BEFORE the square root (where cancellation in ``N'`` hurts), the sum is
    rounded up (:func:`_up_rounded`) and ``sqrt`` (correctly rounded) moved one ulp up.

    Parameters
    ----------
    centres : (n, d) float array
    alpha : (n,) float array
    lengthscale : float or (d,) float array

    Returns
    -------
    float
    """
    Z = np.ascontiguousarray(centres, dtype=float)
    alpha = np.ascontiguousarray(alpha, dtype=float)
    if Z.ndim != 2 or Z.shape[0] < 1:
        raise DimensionError(f"centres must have shape (n, d) with n >= 1; got {Z.shape}")
    if alpha.shape != (Z.shape[0],):
        raise DimensionError(f"alpha must have shape ({Z.shape[0]},) like centres' rows; got {alpha.shape}")
    if not (np.all(np.isfinite(Z)) and np.all(np.isfinite(alpha))):
        raise InvalidInputError("centres and alpha must be finite")
    K, rel = _se_kernel(Z, Z, _check_lengthscale(lengthscale, Z.shape[1]))
    n = Z.shape[0]
    N = float(alpha @ (K @ alpha))
    a = np.abs(alpha)
    W = float(a @ (K @ a))
    g = gamma(2 * n + 2)  # 2n + 2 >= the 2n roundings of the nested dot products
    # (g + rel/(1-rel)) W / (1-g): a handful of roundings of non-negative values -> _up_rounded
    err = up_rounded((g + rel / (1.0 - rel)) * W / (1.0 - g), 6)
    N_up = up_rounded(max(N, 0.0) + float(err), 1)  # ||h||^2 <= max(N', 0) + err (one addition)
    return float(np.nextafter(np.sqrt(N_up), np.inf))  # sqrt correctly rounded: one ulp up suffices


def _terms_values(terms, P: np.ndarray):
    """Values of ``sum_t term_t`` (a ``g_terms`` entry) at the points ``P`` (k, d), with error bounds.

    Per term: ``c`` (const) is exact; ``fl(c x_j)`` has one rounding; ``fl(c fl(sin x_j))``:
    libm/numpy sin and cos are within 4 ulp <= 8u (absolute, values in [-1, 1]), times ``|c|``,
    plus the product's rounding. The recursive sum of T terms adds ``gamma_T sum |t|``. So
    ``err <= (u + gamma_T) S + 8u (1 + u) C`` with S the sum of |term values| and C of the trig
    ``|c|``; we return ``2 ((gamma_{T+1}) S + 9u C)``, rounded up (a factor 2 of slack).
    """
    val = np.zeros(P.shape[0])
    S = np.zeros(P.shape[0])
    C = 0.0
    for kind, j, c in terms:
        c = float(c)
        if kind == "const":
            t = np.full(P.shape[0], c)
        elif kind == "lin":
            t = c * P[:, j]
        elif kind in ("sin", "cos"):
            t = c * (np.sin(P[:, j]) if kind == "sin" else np.cos(P[:, j]))
            C += abs(c)
        else:
            raise InvalidInputError(f"terms must have kinds in {_TERM_KINDS}; got {kind!r}")
        val = val + t
        S = S + np.abs(t)
    err = up_rounded(2.0 * (gamma(len(terms) + 1) * S + 9.0 * U * C), 4 + len(terms))
    return val, err


def _terms_second_derivative_bounds(terms, d: int) -> np.ndarray:
    """Upper bounds ``G_a >= sup |d^2 g / dx_a^2|`` of a ``g_terms`` entry, (d,) array.

    const and lin terms have no second derivative; ``(c sin x_j)'' = -c sin x_j`` and
    ``(c cos x_j)'' = -c cos x_j`` are bounded by ``|c|`` and only along axis j. Rounded up.
    """
    G = np.zeros(d)
    for kind, j, c in terms:
        if kind in ("sin", "cos"):
            G[j] += abs(float(c))
    return up_rounded(G, len(terms))


def _axis_grid(lo: float, hi: float, spacing: float, name: str):
    """Points ``lo = p_0 < ... < p_n = hi`` (floats, endpoints exact) with gaps ``<= spacing``.

    Returns the points and an upper bound of their largest gap (float differences rounded up).
    """
    if not (np.isfinite(spacing) and spacing > 0):
        raise InvalidInputError(f"{name} must be positive and finite; got {spacing!r}")
    n = max(1, int(np.ceil((hi - lo) / spacing)))
    pts = lo + (hi - lo) * (np.arange(n + 1) / n)
    pts[0], pts[-1] = lo, hi  # the grid covers [lo, hi] exactly
    gaps = np.diff(pts)
    if not np.all(gaps > 0):
        raise InvalidInputError(f"{name} = {spacing!r} is too fine for the box [{lo!r}, {hi!r}] in float64")
    # |fl(p - q) - (p - q)| <= u |p - q|: one rounding per gap, so round the largest up
    return pts, float(up_rounded(gaps.max(), 1))


def _tensor_points(axes) -> np.ndarray:
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))


def certify_expansion(terms, centres, alpha, lengthscale, lower, upper, *, check_spacing=1.0 / 64.0) -> dict:
    """Certified ``||h||_H`` and ``sup_X |g - h|`` for ``h = sum_j alpha_j k(., z_j)`` and ``g = sum terms``.

    ``k`` is the unit-amplitude SE kernel with ``lengthscale``; ``g`` is a ``g_terms`` entry
    (a sum of ``const``, ``c x_j``, ``c sin x_j``, ``c cos x_j`` terms, see :class:`TrueSystem`);
    ``X = [lower, upper]``.

    Method (every step rounded outward; ``e = g - h``)
        1. ``||h|| <= norm_upper`` by :func:`rkhs_norm_upper`.
        2. ``e`` at the points of a tensor grid covering X exactly (endpoints included, gaps
           ``<= s_a`` per axis), each with a bound of its float error: ``g`` by
           :func:`_terms_values`; ``h`` as ``fl(K' alpha)`` with
           ``|fl(K' alpha) - K alpha| <= (rel / (1 - rel) + gamma_n) S / (1 - gamma_n)``, ``S =
           fl(K' |alpha|)`` (kernel error ``rel`` of :func:`_se_kernel`, n-term dot product);
           the subtraction adds ``u |e'|``. Hence ``|e(p)| <= E_grid`` at every grid point.
        3. Between grid points, on each grid cell (a box with widths ``h_a <= s_a``), with ``I e``
           the multilinear interpolant of ``e`` at the cell's ``2^d`` vertices::

               |e(x)| <= |I e(x)| + |e(x) - I e(x)| <= max_vertices |e| + sum_a (s_a^2 / 8) sup |d^2 e / dx_a^2|.

           ``|I e(x)| <= max_vertices |e|`` since ``I e(x)`` is a convex combination of the vertex
           values. The remainder: with ``L_a`` linear interpolation along axis a (other
           coordinates fixed), ``I = L_1 ... L_d`` and, telescoping,
           ``e - I e = sum_a L_1 ... L_{a-1} (e - L_a e)``; every ``L_b`` is a convex combination of
           point values, so ``||L_b f||_inf <= ||f||_inf`` on the cell, and the 1-D bound
           ``|f(t) - L f(t)| = |f''(xi)| (t - t_0)(t_1 - t) / 2 <= h^2 / 8 sup |f''|`` (Atkinson, An
           Introduction to Numerical Analysis, 2nd ed., Thm 3.2 with n = 1) gives the sum of 1-D
           bounds. ``|d^2 e/dx_a^2| <= |d^2 g/dx_a^2| + |d^2 h/dx_a^2|``; the first is bounded by
           :func:`_terms_second_derivative_bounds`; for the second the derivative reproducing
           property (Zhou, J. Comput. Appl. Math. 2008, Thm 1; Steinwart & Christmann 2008,
           Cor. 4.36) gives ``d^2_a h(x) = <h, d^2_a k(x, .)>``, so
           ``|d^2_a h(x)| <= ||h|| ||d^2_a k(x, .)||_H = ||h|| sqrt(3) / l_a^2``: ``||d^2_a k(x, .)||^2 =
           d^2_{x_a} d^2_{x'_a} k(x, x')|_{x = x'} = phi''''(0)`` for ``phi(r) = e^{-r^2/(2 l_a^2)} =
           1 - r^2/(2 l_a^2) + r^4/(8 l_a^4) - ...`` (the other factors of the product kernel are 1
           at ``x = x'``), i.e. ``4! / (8 l_a^4) = 3 / l_a^4``.

        So ``sup_X |g - h| <= E_grid + sum_a (s_a^2 / 8)(G_a + norm_upper sqrt(3) / l_a^2) = sup_error_upper``.

    Parameters
    ----------
    terms : tuple of (kind, coordinate, coefficient)
        The function g (one entry of ``TrueSystem.g_terms``).
    centres : (n, d) float array
    alpha : (n,) float array
    lengthscale : float or (d,) float array
    lower, upper : (d,) float arrays
        The box X.
    check_spacing : float or (d,) float array
        Largest gap of the check grid per axis (smaller: tighter and slower).

    Returns
    -------
    dict with ``norm_upper``, ``sup_error_upper``, ``grid_max_error`` (``E_grid``, including the
    evaluation errors), ``eval_error`` (largest evaluation-error bound on the grid),
    ``interp_remainder``, ``check_spacing`` ((d,) upper bounds of the grid gaps), ``n_check``.
    """
    return _certify_batch([terms], centres, np.asarray(alpha, dtype=float)[None, :], lengthscale, lower, upper,
                          check_spacing)[0]


def _certify_batch(terms_list, centres, alphas, lengthscale, lower, upper, check_spacing) -> list:
    """:func:`certify_expansion` of several ``(terms, alpha)`` pairs on the same centres and grid.

    ``alphas`` (m, n); the kernel blocks of the check grid are computed once for all m.
    Returns a list of m dicts (see :func:`certify_expansion`).
    """
    Z = np.ascontiguousarray(centres, dtype=float)
    if Z.ndim != 2 or Z.shape[0] < 1:
        raise DimensionError(f"centres must have shape (n, d) with n >= 1; got {Z.shape}")
    n, d = Z.shape
    alphas = np.asarray(alphas, dtype=float)
    if alphas.ndim != 2 or alphas.shape[1] != n or alphas.shape[0] != len(terms_list):
        raise DimensionError(f"alpha must have shape ({n},) like centres' rows; got {alphas.shape[1:]}")
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    if lower.shape != (d,) or upper.shape != (d,):
        raise DimensionError(f"lower and upper must have shape ({d},) like centres' columns; got {lower.shape}, "
                             f"{upper.shape}")
    if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)) and np.all(lower < upper)):
        raise InvalidInputError(f"lower must be < upper and both finite; got {lower.tolist()}, {upper.tolist()}")
    ls = _check_lengthscale(lengthscale, d)
    spacing = np.broadcast_to(np.asarray(check_spacing, dtype=float), (d,))
    norms = [rkhs_norm_upper(Z, alpha, ls) for alpha in alphas]  # also validates each alpha

    axes, gaps = [], np.empty(d)
    for a in range(d):
        pts, gaps[a] = _axis_grid(float(lower[a]), float(upper[a]), float(spacing[a]), "check_spacing")
        axes.append(pts)
    P = _tensor_points(axes)
    m = alphas.shape[0]
    gam = gamma(n + 1)  # n-term dot products (one spare rounding)
    grid_max = np.zeros(m)
    eval_max = np.zeros(m)
    abs_alphas = np.abs(alphas)
    for start in range(0, P.shape[0], _CHUNK):
        Pc = P[start:start + _CHUNK]
        K, rel = _se_kernel(Pc, Z, ls)
        H = K @ alphas.T  # (chunk, m): h'(p) = fl(K' alpha)
        S = K @ abs_alphas.T  # fl(K' |alpha|)
        err_H = up_rounded((rel / (1.0 - rel) + gam) * S / (1.0 - gam), 6)
        for k, terms in enumerate(terms_list):
            g, err_g = _terms_values(terms, Pc)
            e = np.abs(g - H[:, k])
            err = up_rounded(err_g + err_H[:, k] + U * e * (1.0 + 2 * U), 4)
            bound = up_rounded(e + err, 1)  # |e(p)| <= |e'| + err (one addition)
            grid_max[k] = max(grid_max[k], float(bound.max()))
            eval_max[k] = max(eval_max[k], float(err.max()))

    out = []
    for k, terms in enumerate(terms_list):
        # sup |d^2 e / dx_a^2| <= G_a + norm_upper sqrt(3) / l_a^2 (certify_expansion, step 3)
        M = _terms_second_derivative_bounds(terms, d) + norms[k] * _SQRT3_UP / (ls * ls)
        remainder = float(up_rounded(np.sum(gaps * gaps / 8.0 * M), 8 + 2 * d))
        sup_error = float(up_rounded(grid_max[k] + remainder, 1))
        out.append({"norm_upper": norms[k], "sup_error_upper": sup_error, "grid_max_error": float(grid_max[k]),
                    "eval_error": float(eval_max[k]), "interp_remainder": remainder, "check_spacing": gaps.copy(),
                    "n_check": P.shape[0]})
    return out


def _fit_basis(K_fz: np.ndarray, K_zz: np.ndarray):
    """``T = V_r diag(lambda_r)^{-1/2}`` (eigenvalues of ``K_zz`` above ``_FIT_EIG_REL_TOL`` x max) and ``K_fz T``."""
    lam, V = np.linalg.eigh((K_zz + K_zz.T) / 2.0)
    keep = lam > _FIT_EIG_REL_TOL * lam.max()
    T = V[:, keep] / np.sqrt(lam[keep])
    return T, K_fz @ T


def _min_norm_fit(T: np.ndarray, A: np.ndarray, y: np.ndarray, tol: float, what: str) -> np.ndarray:
    """Weights ``alpha`` of a small-norm kernel expansion within ``tol`` of ``y`` at the fit points.

    Program (a second-order cone program, solved by cvxpy + Clarabel)::

        minimise over beta in R^r   ||beta||_2
        subject to                  -tol <= K_fz T beta - y <= tol,      alpha = T beta

    (``A = K_fz T``) with ``T = V_r diag(lambda_r)^{-1/2}`` from the eigenvalues of ``K_zz`` above
    ``_FIT_EIG_REL_TOL`` times the largest (:func:`_fit_basis`), so that ``alpha^T K_zz alpha = ||beta||^2``: the
    smallest RKHS norm among expansions on these centres (restricted to the well-conditioned
    eigen-directions) that fit the data points within ``tol``. Its optimum need not bound
    anything: ``alpha`` is only a proposal, and :func:`certify_expansion` certifies norm and
    sup error of whatever comes back (an inaccurate solve costs tightness, never soundness).

    Test-support exception to the house rule "cvxpy only in robust_imdp.solvers.lp": this program is
    used only to certify the case studies' assumption (tests, README), so it lives next to
    them; cvxpy is imported lazily, and the library never calls it.
    """
    import cvxpy as cp

    from robust_imdp.errors import ConvergenceError

    beta = cp.Variable(T.shape[1])
    prob = cp.Problem(cp.Minimize(cp.norm(beta)), [A @ beta - y <= tol, y - A @ beta <= tol])
    try:
        prob.solve(solver=cp.CLARABEL)
    except cp.error.SolverError as exc:
        raise ConvergenceError(f"CLARABEL failed on the fit SOCP of {what}: {exc}") from None
    if prob.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or beta.value is None:
        raise ConvergenceError(
            f"CLARABEL did not solve the fit SOCP of {what} (tolerance {tol:g}): status {prob.status!r}; "
            "try a larger tau, more centres or a larger centre_margin")
    return T @ np.asarray(beta.value, dtype=float)


def assumption_certificate(name: str, lengthscale=2.0, tau: float = 0.002, *, fit_spacing: float = 0.2,
                           check_spacing: float = 1.0 / 64.0, centre_spacing: float = 0.5,
                           centre_margin: float = 1.0, fit_fraction: float = 0.8) -> list:
    """Certify that every true unknown component of case study ``name`` is within ``tau`` of an RKHS function.

    For every mode u and output i, ``g = g_u^(i)`` (``TrueSystem.g_terms``, i.e. ``x_next - f_u(x)``
    without noise) is fitted by ``h = sum_j alpha_j k(., z_j)`` (unit-amplitude SE kernel with
    ``lengthscale``, centres ``z_j`` on a tensor grid over X widened by ``centre_margin``, gaps
    ``<= centre_spacing``) by :func:`_min_norm_fit` with tolerance ``fit_fraction * tau`` on a fit
    grid of gaps ``<= fit_spacing``; then :func:`certify_expansion` certifies
    ``||h||_H <= norm_upper`` and ``sup_X |g - h| <= sup_error_upper`` rigorously (outward
    rounding, interpolation remainder between the check-grid points of gaps ``<= check_spacing``).
    If ``sup_error_upper <= tau``, then ``g`` satisfies the assumption "within tau (sup norm on X)
    of a function of RKHS norm <= B" for every ``B >= norm_upper``. Components with the same
    terms are fitted once.

    Parameters
    ----------
    name : str
        A case study in ``CASE_STUDIES``.
    lengthscale : float or (d,) float array
    tau : float > 0
        The misspecification allowance to certify.
    fit_spacing, check_spacing, centre_spacing : float > 0
    centre_margin : float >= 0
    fit_fraction : float in (0, 1]
        The fit's tolerance as a fraction of ``tau`` (room for the error between fit points and
        the interpolation remainder of the certificate).

    Returns
    -------
    list of dict, one per (mode, output) in mode order
        ``mode`` (name), ``output`` (0-based), ``terms``, ``lengthscale``, ``tau``, ``tau_fit``,
        ``norm_upper``, ``sup_error_upper``, ``certified`` (``sup_error_upper <= tau``),
        ``grid_max_error``, ``eval_error``, ``interp_remainder``, ``check_spacing``, ``n_check``,
        ``n_centres``, ``centres`` (n, d), ``alpha`` (n,).

    Raises
    ------
    InvalidInputError
        Unknown case study or a parameter out of range (the message names it).
    ConvergenceError
        The fit SOCP failed (no certificate can be given with these settings).
    """
    case = get_case_study(name)
    system = case.system
    lower = np.asarray(case.lower, dtype=float)
    upper = np.asarray(case.upper, dtype=float)
    d = lower.size
    ls = _check_lengthscale(lengthscale, d)
    tau = float(tau)
    if not (np.isfinite(tau) and tau > 0):
        raise InvalidInputError(f"tau must be positive and finite; got {tau!r}")
    if not (0 < float(fit_fraction) <= 1):
        raise InvalidInputError(f"fit_fraction must be in (0, 1]; got {fit_fraction!r}")
    if not (np.isfinite(centre_margin) and centre_margin >= 0):
        raise InvalidInputError(f"centre_margin must be finite and >= 0; got {centre_margin!r}")
    if system.g_terms is None:
        raise InvalidInputError(f"case study {name!r} has no g_terms (the separable form of g); cannot certify")
    centre_axes = [_axis_grid(float(lower[a] - centre_margin), float(upper[a] + centre_margin),
                              float(centre_spacing), "centre_spacing")[0] for a in range(d)]
    Z = _tensor_points(centre_axes)
    fit_axes = [_axis_grid(float(lower[a]), float(upper[a]), float(fit_spacing), "fit_spacing")[0]
                for a in range(d)]
    Pf = _tensor_points(fit_axes)
    K_zz = _se_kernel(Z, Z, ls)[0]
    K_fz = _se_kernel(Pf, Z, ls)[0]
    tau_fit = fit_fraction * tau
    T, A = _fit_basis(K_fz, K_zz)
    keys = list(dict.fromkeys(tuple(terms) for row in system.g_terms for terms in row))  # distinct, in order
    alphas = np.stack([_min_norm_fit(T, A, _terms_values(key, Pf)[0], tau_fit, f"terms {key}") for key in keys])
    certs = dict(zip(keys, zip(alphas, _certify_batch(keys, Z, alphas, ls, lower, upper, check_spacing))))
    out = []
    for u, mode in enumerate(system.mode_names):
        for i, terms in enumerate(system.g_terms[u]):
            alpha, cert = certs[tuple(terms)]
            out.append({"mode": mode, "output": i, "terms": tuple(terms), "lengthscale": ls, "tau": tau,
                        "tau_fit": tau_fit, **cert, "certified": cert["sup_error_upper"] <= tau,
                        "n_centres": Z.shape[0], "centres": Z, "alpha": alpha})
    return out
