"""The data-implied minimum RKHS norm and the assumption check (does any function of norm <= B fit the data?);
witnesses (a function of certified norm <= B fitting the data) that let a growing data set skip the check."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from robust_imdp._fp import U as _U, down as _down, gamma as _gamma, up as _up, up_rounded as _up_rounded
from robust_imdp._kernels import norm_inflation as _norm_inflation
from robust_imdp.bounds.rkhs_model import KernelModel
from robust_imdp.errors import AssumptionError

log = logging.getLogger("robust_imdp.bounds.rkhs")


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


def data_allowance(noise_bound: float, misspecification: float = 0.0) -> float:
    """``dbar' >= noise_bound + tau``, rounded up: the tolerance ``|h(x_i) - y_i| <= dbar'`` of every
    assumption check (:func:`min_rkhs_norm`) and of the witnesses that stand in for it (:func:`witness_fits`)."""
    return float(_up(float(noise_bound) + float(misspecification)))


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
    dbar = data_allowance(noise_bound, misspecification)
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


def norm_task(X, y, lengthscale, noise_bound: float, misspecification: float, max_points, solver: bool, *,
              threads: int = 1) -> dict:
    """One component's :func:`min_rkhs_norm`, as a scheduler task (``pipeline.parallel``: ``threads`` is
    not used, the SOCP runs on one core)."""
    return min_rkhs_norm(X, y, lengthscale, noise_bound, misspecification, max_points=max_points, solver=solver)


def serial_norms(jobs: Sequence[tuple]) -> list:
    """The :func:`norm_task` of every job (its positional arguments), in this process, in order."""
    return [norm_task(*a) for a in jobs]


def check_assumption(data, *, lengthscale, rkhs_bound: float, noise_bound, misspecification: float = 0.0,
                     mode_names: Sequence[str] | None = None, sample_index=None, max_points: int | None = 300,
                     solver: bool = True, refuse: bool = True, norms=None) -> tuple:
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
    norms : callable, optional
        ``norms(jobs) -> results``: the :func:`norm_task` of every job (a tuple of its positional
        arguments), in the jobs' order; default :func:`serial_norms` (the pipeline passes one that runs
        them on its scheduler: the same computations, so the same bits).

    Returns
    -------
    tuple of NormCheck
    """
    n = len(np.atleast_1d(noise_bound))
    nb = np.broadcast_to(np.asarray(noise_bound, float), (n,))
    names = mode_names or [str(u) for u in range(len(data))]
    jobs, where = [], []
    for u, (X, Y) in enumerate(data):
        Y = np.asarray(Y, float).reshape(np.shape(X)[0], -1)
        for i in range(Y.shape[1]):
            jobs.append((X, Y[:, i], lengthscale, float(nb[i]), misspecification, max_points, solver))
            where.append((u, i, Y))
    checks = []
    for (u, i, Y), r in zip(where, (norms or serial_norms)(jobs)):
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
                f"[learning].rkhs_bound = {float(rkhs_bound):g} is refuted by the data: mode {names[c.mode]!r}, component "
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


# ============================================================================ witnesses (the incremental check)
#: Most centres of a witness: beyond it an evenly spaced subset of the points (its fit is still checked at
#: every point, so any subset gives a valid witness).
WITNESS_CENTRES = 400
#: Ridge parameters tried for a witness (:func:`fit_witness`), largest (smoothest function) first.
WITNESS_RIDGES = tuple(10.0 ** -k for k in range(1, 10))
#: The SOCP witness fits within this fraction of the allowance (a margin far above the solver's accuracy).
WITNESS_SOCP_SHRINK = 0.99


@dataclass(frozen=True, eq=False)
class Witness:
    """A function ``h = sum_j alpha_j k(c_j, .)`` of the assumption's SE kernel, with a certified norm bound.

    If ``|h(x_i) - y_i| <= dbar'`` at every data point (:func:`witness_fits`, with the check's allowance
    :func:`data_allowance`) and ``norm_upper <= B``, the data are consistent with ``||g|| <= B``: the
    assumption check's certified minimum (:func:`min_rkhs_norm`, on any subset of these points) is a lower
    bound of ``||f||`` for *every* f that fits within ``dbar'``, so of ``||h|| <= norm_upper <= B``, and the
    check cannot refuse B. ``norm_upper`` is an *upper* bound of the data-implied minimum norm.

    Attributes
    ----------
    centres : (c, d) float array
    alpha : (c,) float array
    lengthscale : (d,) float array
        The assumption's lengthscales (the exact kernel ``exp(-sum_a (x_a - x'_a)^2 / (2 l_a^2))``).
    norm_upper : float
        Upper bound of ``||h||`` in that kernel's RKHS (eq. N of :func:`_norm_upper`), rounded up.
    """

    centres: np.ndarray
    alpha: np.ndarray
    lengthscale: np.ndarray
    norm_upper: float


def _norm_upper(K, rel: float, alpha) -> float:
    """Eq. N: ``||h||`` for ``h = sum_j alpha_j k(c_j, .)`` from the computed Gram matrix ``K`` of the centres
    (``|K - K_exact| <= rel K_exact`` entrywise, :func:`robust_imdp._kernels.se_kernel_with_error`), rounded up.

    ``||h||^2 = alpha^T K_exact alpha``. With ``r = rel / (1 - rel)``, ``|K - K_exact| <= r K`` (K >= 0), so
    ``|alpha^T (K - K_exact) alpha| <= r A`` with ``A = |alpha|^T K |alpha|``; the two inner products of the
    computed ``q = alpha . (K alpha)`` are off by at most ``(2 gamma_c + gamma_c^2) A <= gamma_{2c+2} A``
    (Higham, ASNA, eq. 3.5). Hence ``||h||^2 <= q + (gamma_{2c+2} + r) A``, A rounded up.
    """
    c = alpha.size
    if c == 0:
        return 0.0
    r = float(_up_rounded(rel / (1.0 - rel), 3))
    aa = np.abs(alpha)
    A = float(_up_rounded(aa @ (K @ aa), 2 * c))  # non-negative terms: 2c roundings in sequence at most
    q = float(alpha @ (K @ alpha))
    sq = float(_up(q, float(_up_rounded((_gamma(2 * c + 2) + r) * A, 2))))
    return float(_up(math.sqrt(max(sq, 0.0))))  # sqrt is correctly rounded: one ulp up bounds it


def _residual_upper(Kx, rel: float, alpha, y) -> np.ndarray:
    """Eq. R: upper bounds of ``|h(x_i) - y_i|`` from the computed kernel values ``Kx`` (p, c) between the
    points and the centres (``|Kx - Kx_exact| <= rel Kx_exact``).

    ``h(x_i) = (Kx_exact alpha)_i``; the computed ``v = Kx alpha`` is within ``(gamma_c + r) (Kx |alpha|)_i``
    of it (the inner product's rounding, ASNA eq. 3.5, and the kernel values' error, ``r = rel / (1 - rel)``),
    and ``fl(v_i - y_i)`` is within one rounding of ``v_i - y_i``.
    """
    y = np.asarray(y, float)
    if alpha.size == 0:
        return np.abs(y)  # h = 0: |y_i| is exact
    c = alpha.size
    r = float(_up_rounded(rel / (1.0 - rel), 3))
    spread = _up_rounded(Kx @ np.abs(alpha), c)
    err = _up_rounded((_gamma(c) + r) * spread, 2)
    return _up(_up_rounded(np.abs(Kx @ alpha - y), 1), err)


def witness_norm_upper(centres, alpha, lengthscale) -> float:
    """Certified upper bound of the RKHS norm of ``sum_j alpha_j k(c_j, .)`` (eq. N)."""
    from robust_imdp._kernels import check_lengthscale, se_kernel_with_error

    centres = np.ascontiguousarray(centres, float)
    alpha = np.ascontiguousarray(alpha, float)
    if alpha.size == 0:
        return 0.0
    K, rel = se_kernel_with_error(centres, centres, check_lengthscale(lengthscale, centres.shape[1]))
    return _norm_upper(K, rel, alpha)


def witness_residuals(witness: Witness, X, y) -> np.ndarray:
    """(m,) certified upper bounds of ``|h(x_i) - y_i|`` of the witness at the points ``X`` (eq. R).

    Raises ``InvalidInputError`` (from ``se_kernel_with_error``) for points more than ~37 lengthscales
    from a centre."""
    from robust_imdp._kernels import se_kernel_with_error

    X = np.ascontiguousarray(X, float).reshape(-1, witness.lengthscale.size)
    if witness.alpha.size == 0 or X.shape[0] == 0:
        return np.abs(np.asarray(y, float))
    Kx, rel = se_kernel_with_error(X, witness.centres, witness.lengthscale)
    return _residual_upper(Kx, rel, witness.alpha, y)


def witness_fits(witness: Witness, X, y, noise_bound: float, misspecification: float = 0.0) -> bool:
    """True when the witness fits every ``(X_i, y_i)`` within the check's allowance ``dbar' >= noise_bound +
    tau`` (:func:`data_allowance`: the same float as :func:`min_rkhs_norm`'s)."""
    dbar = data_allowance(noise_bound, misspecification)
    return bool(np.all(witness_residuals(witness, X, y) <= dbar))


def fit_witness(X, y, lengthscale, noise_bound: float, misspecification: float, rkhs_bound: float, *,
                socp: bool = True):
    """A :class:`Witness` with ``norm_upper <= rkhs_bound`` fitting every point within the allowance, or None.

    Kernel-ridge fits ``alpha = (K + lambda I)^{-1} y`` (centres: the points, or an evenly spaced subset of
    :data:`WITNESS_CENTRES` of them with the normal equations ``(K_cx K_xc + lambda K_cc) alpha = K_cx y``),
    for the ridge parameters of :data:`WITNESS_RIDGES`, largest first; the first whose certified norm
    (eq. N) and residuals at *every* point (eq. R) pass is returned. If none does (a ridge fit needs a
    larger norm than the minimum to meet every constraint) and ``socp`` (at most :data:`WITNESS_CENTRES`
    points), the minimum-norm function within ``WITNESS_SOCP_SHRINK dbar'`` (one SOCP). The fits are
    heuristics; only the certified checks decide. None also for points too far apart for the certified
    kernel (the caller then runs the full check).
    """
    from robust_imdp._kernels import check_lengthscale, se_kernel_with_error
    from robust_imdp.errors import InvalidInputError

    X = np.ascontiguousarray(X, float)
    y = np.ascontiguousarray(y, float)
    ls = check_lengthscale(lengthscale, X.shape[1])
    dbar = data_allowance(noise_bound, misspecification)
    m = X.shape[0]
    if m == 0 or float(rkhs_bound) <= 0.0 or np.all(np.abs(y) <= dbar):  # h = 0 fits: norm 0
        zero = Witness(np.zeros((0, X.shape[1])), np.zeros(0), ls, 0.0)
        return zero if np.all(np.abs(y) <= dbar) else None
    pick = np.arange(m) if m <= WITNESS_CENTRES else np.unique(np.linspace(0, m - 1, WITNESS_CENTRES).round().astype(int))
    C = X[pick]
    try:
        Kx, rel_x = se_kernel_with_error(X, C, ls)
        Kc, rel_c = (Kx, rel_x) if pick.size == m else se_kernel_with_error(C, C, ls)
    except InvalidInputError:
        return None
    c = pick.size
    for lam in WITNESS_RIDGES:
        try:
            if c == m:
                alpha = np.linalg.solve(Kc + lam * np.eye(c), y)
            else:
                alpha = np.linalg.solve(Kx.T @ Kx + lam * Kc + 1e-12 * np.eye(c), Kx.T @ y)
        except np.linalg.LinAlgError:
            continue
        if not np.all(np.isfinite(alpha)):
            continue
        norm = _norm_upper(Kc, rel_c, alpha)
        if norm <= float(rkhs_bound) and np.all(_residual_upper(Kx, rel_x, alpha, y) <= dbar):
            return Witness(np.ascontiguousarray(C), alpha, ls, norm)
    if socp and c == m and m >= 2:
        # The minimum-norm function within WITNESS_SOCP_SHRINK dbar' (solvers.lp.rkhs_min_norm_socp): by the
        # SOCP's stationarity, beta = ||beta|| M^T w, so h = sum_i alpha_i k(x_i, .) with alpha = value * w
        # (w: its dual weights). It meets its constraints only to the solver's accuracy, hence the margin;
        # eqs. N and R decide, as for the ridge fits.
        from robust_imdp.solvers.lp import rkhs_min_norm_socp

        w, value = rkhs_min_norm_socp(Kc, y, WITNESS_SOCP_SHRINK * dbar)
        alpha = float(value) * np.asarray(w, float)
        if np.isfinite(value) and np.all(np.isfinite(alpha)):
            norm = _norm_upper(Kc, rel_c, alpha)
            if norm <= float(rkhs_bound) and np.all(_residual_upper(Kx, rel_x, alpha, y) <= dbar):
                return Witness(np.ascontiguousarray(C), alpha, ls, norm)
    return None
