"""The data-implied minimum RKHS norm and the assumption check (does any function of norm <= B fit the data?)."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from robust_imdp._fp import U as _U, down as _down, gamma as _gamma, up as _up
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
