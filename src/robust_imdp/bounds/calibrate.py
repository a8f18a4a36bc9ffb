r"""Choosing the assumption from the data: lengthscale, RKHS bound B and the misspecification advice.

Every guarantee of the RKHS route is conditional on ``[learning].rkhs_bound`` (B), ``lengthscale`` and
``misspecification`` (tau). This module measures, per mode and component, what the data say about them
and suggests values. **What it returns is evidence, not proof**: no finite data set can show that an
unknown function's RKHS norm is at most B (docs/calibration.md says what each number does and does not
prove).

Per component (:func:`calibrate_component`; residuals ``y_i = x_next_i - f_u(x_i)`` of one mode and
output):

1. **Lengthscale** (:func:`lengthscale_curves`). On a log grid of isotropic lengthscales
   (:func:`lengthscale_grid`), two curves: the GP log marginal likelihood of the SE kernel with the noise
   model's variance (:func:`noise_variance`) as the noise variance and the signal variance profiled out
   (Rasmussen & Williams 2006, eq. 2.30, on the eigenbasis of K), and the K-fold cross-validation error of
   the kernel-ridge fit (the ridge parameter chosen per lengthscale from :data:`RIDGES`). Each curve's best
   grid point is refined by a bounded scalar optimiser (scipy's Brent) between its neighbours.
   The suggestion (:func:`choose_lengthscale`) is :data:`LENGTHSCALE_SHRINK` times the smaller of the two
   optima, and at most the data's extent: both optima overestimate the lengthscale of the benchmark
   family's functions (medians 1.4x and 1.3x), and a lengthscale above ``sqrt(2)`` times the true one leaves a sum of
   SE bumps *outside* the RKHS (infinite norm: no B is sound), while below the true one the norm grows
   only mildly (``H_l`` is contained in ``H_l'`` for ``l' <= l``, Steinwart & Christmann 2008,
   Prop. 4.46). The measurements behind the constants are in benchmarks/results/calibration.md.
2. **Lower bound on B**: the certified data-implied minimum norm (:func:`rkhs_check.min_rkhs_norm`, the
   assumption check's own computation) at every grid lengthscale and at the suggested one. A B below it
   is refuted by the data; above it nothing is proved.
3. **Held-out evidence on B** (:func:`held_out_evidence`). K-fold: the optimal pointwise bound of the RKHS
   route (``rkhs.cell_ranges`` on the degenerate cell ``[x, x]``: eq. C without a Taylor term) fitted on the
   other folds is evaluated at every held-out input, for B on a geometric grid; a held-out residual outside
   the bound widened by the noise bound is a violation. Reported: the violations per B, the smallest B with
   none, and for it the one-sided Clopper-Pearson upper confidence bound (:func:`clopper_pearson_upper`) on
   the probability that a new sample from the same distribution would fall outside. By construction no
   B at or above the minimum norm of *all* the data can have a violation (the minimum-norm function fits
   every fold), so this evidence never exceeds the minimum norm; it is a check of the lengthscale and the
   noise bound as much as of B.
4. **B** = :data:`B_MARGIN` times the larger of the minimum norm and the held-out smallest B, rounded up
   to two significant digits: a margin measured on the benchmark family, not derived.
5. **Trend** (:func:`trend_check`): an affine part ``a.x + c`` of the residuals is not in the SE kernel's
   RKHS (no non-zero constant is; Steinwart, Hush & Scovel 2006) and can only be approximated at a large
   norm. Where removing the least-squares affine fit lowers the minimum norm to at most
   :data:`TREND_FACTOR` of its value, the component is flagged with two alternatives: move ``a.x + c`` into
   the known part, or keep it and set ``misspecification`` to its largest magnitude over X.

:func:`calibrate_data` runs the components (on any scheduler with ``run(fn, args)``, e.g.
``pipeline.parallel``'s) and returns a :class:`Calibration`, whose :attr:`Calibration.suggested` holds
``rkhs_bound``, ``lengthscale`` and ``misspecification`` in the shapes a problem file's ``[learning]``
table accepts (``bounds.assumptions``), and :meth:`Calibration.learning_table` the table to paste.
:func:`calibrate_problem` is the same for a ``Problem`` (``Problem.calibrate``, ``robust-imdp calibrate``).
"""

from __future__ import annotations

import math
import re
import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.jsonable import jsonable

__all__ = [
    "Calibration", "ComponentCalibration", "LengthscaleCurves", "HeldOutEvidence", "TrendCheck",
    "calibrate_problem", "calibrate_data", "calibrate_component", "lengthscale_grid", "lengthscale_curves",
    "choose_lengthscale", "held_out_evidence", "trend_check", "clopper_pearson_upper", "noise_variance",
    "kfold", "log_marginal_likelihood", "ridge_cv_error", "EVIDENCE", "FOLDS", "B_MARGIN",
    "LENGTHSCALE_SHRINK", "CONFIDENCE",
]

#: What every output says about the suggested values.
EVIDENCE = ("evidence, not proof: no finite data set shows that the unknown part's RKHS norm is at most B; the "
            "minimum norm is a certified lower bound, the held-out counts and the margin are measured, not proved "
            "(docs/calibration.md)")
#: Folds of the cross-validation and of the held-out evidence.
FOLDS = 5
#: Points per component used for the lengthscale curves and the held-out evidence (a seeded random subset
#: beyond it; the minimum norm uses the assumption check's own subset of :data:`MIN_NORM_POINTS`).
MAX_POINTS = 400
#: Points of the certified minimum norm at the suggested lengthscale (the assumption check's default).
MIN_NORM_POINTS = 300
#: Points of the minimum norm at every grid lengthscale (the curve; a smaller subset, the SOCP is O(m^3)).
CURVE_POINTS = 100
#: Candidate lengthscales: a log grid from EXTENT_RANGE[0] to EXTENT_RANGE[1] times the data's extent.
GRID_POINTS = 13
EXTENT_RANGE = (1.0 / 50.0, 5.0)
#: Ridge parameters tried per lengthscale by the cross-validation (unit-amplitude kernel).
RIDGES = tuple(float(v) for v in np.logspace(-8, 2, 21))
#: The suggested lengthscale is this times the smaller of the likelihood and cross-validation optima: on the
#: benchmark family the likelihood optimum was 1.1-2x the generating lengthscale on 94 % of the components
#: (median 1.39; cross-validation 1.26), and 0.75 kept the suggestion below sqrt(2) x it (where the true norm
#: is finite) on 108 of 109 components and within a factor 2 of it on 90 % (benchmarks/results/calibration.md).
LENGTHSCALE_SHRINK = 0.75
#: The suggested B is this times the larger of the minimum norm and the held-out smallest B. On the benchmark
#: family (benchmarks/results/calibration.md) 2 covered the true norm on 94 % of the components and, with one B
#: per problem (the largest), on 18 of the 19 configurations, never above 3 x the true norm; 2.5 covered 97 % of
#: the components but went above 3 x the true norm on 3 of the 19 configurations, and no margin up to 3 covers
#: every component of 90 % of the configurations (the rule table there).
B_MARGIN = 2.0
#: The held-out B grid: B_GRID_ABOVE x the minimum norm x 2^(k/4), k = B_GRID_STEPS[0] .. B_GRID_STEPS[1].
B_GRID_STEPS = (-4, 12)
B_GRID_ABOVE = 1.01
#: Confidence of the Clopper-Pearson bound.
CONFIDENCE = 0.95
#: A trend is flagged where removing the affine fit leaves at most this fraction of the minimum norm.
TREND_FACTOR = 0.5


# ============================================================================ small statistics
def clopper_pearson_upper(violations: int, n: int, confidence: float = CONFIDENCE) -> float:
    """One-sided Clopper-Pearson upper confidence bound of a binomial probability.

    The largest ``p`` with ``P[Bin(n, p) <= violations] >= 1 - confidence``: with probability at least
    ``confidence`` over the sample, the true probability is at most the returned value. It equals the
    ``confidence`` quantile of ``Beta(violations + 1, n - violations)`` (1 when ``violations = n``);
    computed here by bisection on the binomial CDF (``scipy.special.bdtr``), the closed form
    ``1 - (1 - confidence)^(1/n)`` when ``violations = 0``.

    Parameters
    ----------
    violations : int, 0 <= violations <= n
    n : int >= 1
    confidence : float in (0, 1)

    Returns
    -------
    float in (0, 1]
    """
    from scipy import special

    k, n = _count(violations, "violations"), _count(n, "n")
    if n < 1 or not 0 <= k <= n:
        raise InvalidInputError(f"need 0 <= violations <= n and n >= 1; got violations={violations!r}, n={n!r}")
    c = float(confidence)
    if not 0.0 < c < 1.0:
        raise InvalidInputError(f"confidence must lie in (0, 1); got {confidence!r}")
    if k == n:
        return 1.0
    alpha = 1.0 - c
    if k == 0:  # P[Bin(n, p) = 0] = (1 - p)^n = alpha
        return float(-math.expm1(math.log(alpha) / n))
    lo, hi = 0.0, 1.0  # bdtr(k, n, p) = P[Bin(n, p) <= k] decreases in p from 1 to 0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if special.bdtr(k, n, mid) > alpha:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-15 * hi:
            break
    return float(hi)


def _count(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InvalidInputError(f"{name} must be an integer; got {value!r}")
    return int(value)


def noise_variance(noise) -> np.ndarray:
    """Variance of every component of a noise model: ``E[v_i^2] = int_0^1 Q_i(p)^2 dp`` (n,).

    ``Q_i`` is the quantile function of ``|v_i|`` (``noise.abs_quantile``), so this holds for every model
    of ``models.noise`` (and any object with ``abs_quantile`` and ``dim``); the integral is the midpoint
    rule on 20,000 points (relative error below 1e-3 for the Gaussian's unbounded tail, far less for
    bounded noise). The GP likelihood's noise variance (:func:`lengthscale_curves`).
    """
    if not hasattr(noise, "abs_quantile"):
        raise InvalidInputError(f"noise must be a noise model with abs_quantile (models.noise); got {noise!r}")
    k = 20000
    p = (np.arange(k) + 0.5) / k
    q = np.asarray(noise.abs_quantile(p), float).reshape(k, -1)
    return np.mean(q * q, axis=0)


def kfold(m: int, folds: int, rng: Any = 0) -> list:
    """``folds`` disjoint index arrays covering ``range(m)`` (a seeded permutation dealt round-robin)."""
    m, folds = _count(m, "m"), _count(folds, "folds")
    if folds < 2:
        raise InvalidInputError(f"folds must be an integer >= 2; got {folds}")
    if m < 2 * folds:
        raise InvalidInputError(f"{folds}-fold cross-validation needs at least {2 * folds} samples; got {m}")
    perm = np.random.default_rng(rng).permutation(m)
    return [np.sort(perm[i::folds]) for i in range(folds)]


# ============================================================================ lengthscale
def _sq_dist(A, B) -> np.ndarray:
    return np.sum((A[:, None, :] - B[None, :, :]) ** 2, axis=-1)


def _extent(X) -> float:
    """The data's extent: the geometric mean of the per-axis ranges (axes of zero range left out)."""
    span = np.ptp(np.asarray(X, float), axis=0)
    span = span[span > 0]
    return float(np.exp(np.mean(np.log(span)))) if span.size else 1.0


def lengthscale_grid(X, n: int = GRID_POINTS) -> np.ndarray:
    """``n`` isotropic lengthscales, log-spaced from ``EXTENT_RANGE[0]`` to ``EXTENT_RANGE[1]`` times the extent."""
    e = _extent(X)
    return e * np.geomspace(EXTENT_RANGE[0], EXTENT_RANGE[1], int(n))


def log_marginal_likelihood(D2, y, lengthscale: float, noise_var: float) -> tuple:
    """GP log marginal likelihood per point of ``y ~ N(0, sf2 K + noise_var I)``, ``sf2`` maximised.

    ``K`` is the unit SE kernel at ``lengthscale`` (``D2``: squared distances). With ``K = Q diag(w) Q^T``
    and ``z = Q^T y``: ``log p = -1/2 sum z_i^2 / (sf2 w_i + s2) - 1/2 sum log(sf2 w_i + s2) - m/2 log 2 pi``
    (R&W eq. 2.30), maximised over ``log sf2`` by a bounded scalar search.

    Returns
    -------
    (log likelihood / m, sf2)
    """
    import scipy.optimize

    m = y.size
    w, Q = np.linalg.eigh(np.exp(-0.5 * D2 / (lengthscale * lengthscale)))
    w = np.maximum(w, 0.0)
    z2 = (Q.T @ y) ** 2
    vy = float(np.mean(y * y)) + noise_var

    def nll(t):
        v = math.exp(t) * w + noise_var
        return 0.5 * float(np.sum(z2 / v)) + 0.5 * float(np.sum(np.log(v)))

    r = scipy.optimize.minimize_scalar(nll, bounds=(math.log(1e-8 * vy), math.log(1e6 * vy)), method="bounded")
    return -(float(r.fun) + 0.5 * m * math.log(2 * math.pi)) / m, float(math.exp(r.x))


def ridge_cv_error(D2, y, lengthscale: float, folds) -> tuple:
    """K-fold cross-validation RMSE of the kernel-ridge fit at ``lengthscale``, the best of :data:`RIDGES`.

    ``alpha = (K_tr + lambda I)^{-1} y_tr`` on the other folds (one eigendecomposition per fold serves every
    lambda), squared errors on the held-out fold, pooled over the folds.

    Returns
    -------
    (rmse, lambda)
    """
    K = np.exp(-0.5 * D2 / (lengthscale * lengthscale))
    lam = np.asarray(RIDGES)
    sse = np.zeros(lam.size)
    everything = np.arange(y.size)
    for te in folds:
        tr = np.setdiff1d(everything, te)
        w, Q = np.linalg.eigh(K[np.ix_(tr, tr)])
        w = np.maximum(w, 0.0)
        z = Q.T @ y[tr]
        P = K[np.ix_(te, tr)] @ Q  # (k_te, m_tr)
        pred = P @ (z[:, None] / (w[:, None] + lam[None, :]))  # (k_te, n_lambda)
        sse += np.sum((pred - y[te, None]) ** 2, axis=0)
    j = int(np.argmin(sse))
    return float(math.sqrt(sse[j] / y.size)), float(lam[j])


@dataclass(frozen=True, eq=False)
class LengthscaleCurves:
    """The two lengthscale curves of one component and their optima (isotropic lengthscales).

    Attributes
    ----------
    grid : (k,) float array
        The candidate lengthscales (:func:`lengthscale_grid`).
    log_likelihood : (k,) float array
        GP log marginal likelihood per point, signal variance maximised (:func:`log_marginal_likelihood`).
    signal_variance : (k,) float array
    cv_rmse : (k,) float array
        K-fold cross-validation RMSE of the kernel-ridge fit, best ridge parameter (:func:`ridge_cv_error`).
    ridge : (k,) float array
        That ridge parameter.
    min_norm : (k,) float array
        Certified minimum norm at each grid lengthscale (on :data:`CURVE_POINTS` points).
    ml, cv : float
        The likelihood maximiser and the cross-validation minimiser (grid, then a bounded scalar search).
    """

    grid: np.ndarray
    log_likelihood: np.ndarray
    signal_variance: np.ndarray
    cv_rmse: np.ndarray
    ridge: np.ndarray
    min_norm: np.ndarray
    ml: float
    cv: float

    def to_dict(self) -> dict:
        return jsonable({"grid": self.grid, "log_likelihood_per_point": self.log_likelihood,
                         "signal_variance": self.signal_variance, "cv_rmse": self.cv_rmse, "cv_ridge": self.ridge,
                         "min_norm": self.min_norm, "likelihood_optimum": self.ml, "cv_optimum": self.cv})


def _refine(fun, grid, j: int) -> float:
    """Minimise ``fun(lengthscale)`` over ``[grid[j-1], grid[j+1]]`` in log scale (bounded Brent)."""
    import scipy.optimize

    lo, hi = math.log(grid[max(j - 1, 0)]), math.log(grid[min(j + 1, grid.size - 1)])
    best = (fun(float(grid[j])), float(grid[j]))
    r = scipy.optimize.minimize_scalar(lambda t: fun(math.exp(t)), bounds=(lo, hi), method="bounded",
                                       options={"xatol": 1e-3})
    return float(math.exp(r.x)) if float(r.fun) <= best[0] else best[1]


def lengthscale_curves(X, y, *, noise_var: float, folds, noise_bound: float, misspecification: float = 0.0,
                       grid=None, curve_points: int = CURVE_POINTS, rng: Any = 0) -> LengthscaleCurves:
    """Likelihood and cross-validation curves over the grid, their optima, and the minimum-norm curve.

    Parameters
    ----------
    X : (m, d) float array, y : (m,) float array
        One component's inputs and residuals (the calibration subset).
    noise_var : float > 0
        The GP likelihood's noise variance (:func:`noise_variance`).
    folds : list of index arrays (:func:`kfold`)
    noise_bound, misspecification : float
        The allowance of the minimum norm (``rkhs_check.min_rkhs_norm``).
    grid : (k,) float array, optional
        Default :func:`lengthscale_grid`.
    """
    from robust_imdp.bounds.rkhs_check import min_rkhs_norm

    grid = lengthscale_grid(X) if grid is None else np.asarray(grid, float)
    D2 = _sq_dist(X, X)
    s2 = max(float(noise_var), 1e-12 * (float(np.mean(y * y)) + 1e-300))
    lml = np.empty(grid.size)
    sf2 = np.empty(grid.size)
    rmse = np.empty(grid.size)
    ridge = np.empty(grid.size)
    for j, ell in enumerate(grid):
        lml[j], sf2[j] = log_marginal_likelihood(D2, y, float(ell), s2)
        rmse[j], ridge[j] = ridge_cv_error(D2, y, float(ell), folds)
    ml = _refine(lambda ell: -log_marginal_likelihood(D2, y, ell, s2)[0], grid, int(np.argmax(lml)))
    cv = _refine(lambda ell: ridge_cv_error(D2, y, ell, folds)[0], grid, int(np.argmin(rmse)))
    with warnings.catch_warnings():
        # far from the data's lengthscale the SOCP is badly conditioned and cvxpy says its solution "may be
        # inaccurate"; the minimum is certified from whatever dual weights it returns (rkhs_check), so the curve
        # only gets looser there, never wrong
        warnings.filterwarnings("ignore", message="Solution may be inaccurate")
        norms = np.array([min_rkhs_norm(X, y, float(ell), noise_bound, misspecification, max_points=curve_points,
                                        rng=rng)["minimum"] for ell in grid])
    return LengthscaleCurves(grid, lml, sf2, rmse, ridge, norms, ml, cv)


def _round_sig(value: float, digits: int, up: bool) -> float:
    """``value > 0`` rounded up or down to ``digits`` significant digits, as the float of its decimal text."""
    e = math.floor(math.log10(value)) - (digits - 1)
    m = value / 10.0 ** e
    m = math.ceil(m - 1e-9) if up else math.floor(m + 1e-9)
    out = float(f"{int(m)}e{e}")
    if up and out < value:  # the decimal text's float may sit one ulp below
        out = float(f"{int(m) + 1}e{e}")
    return out


def choose_lengthscale(curves: LengthscaleCurves, extent: float) -> tuple:
    """The suggested lengthscale and why: ``LENGTHSCALE_SHRINK * min(ml, cv)``, at most ``extent``, rounded
    down to two significant digits.

    Returns
    -------
    (lengthscale, explanation)
    """
    base = min(curves.ml, curves.cv)
    which = "likelihood" if curves.ml <= curves.cv else "cross-validation"
    value = LENGTHSCALE_SHRINK * base
    why = (f"{LENGTHSCALE_SHRINK:g} x the smaller optimum ({which}: {base:.3g}; likelihood {curves.ml:.3g}, "
           f"cross-validation {curves.cv:.3g})")
    if value > extent:
        value = extent
        why += f", capped at the data's extent {extent:.3g} (larger lengthscales are not identified by the data)"
    return _round_sig(value, 2, up=False), why


# ============================================================================ B
@dataclass(frozen=True, eq=False)
class HeldOutEvidence:
    """K-fold held-out violations of the certified pointwise bound, per B (:func:`held_out_evidence`).

    Attributes
    ----------
    rkhs_bounds : (k,) float array
        The B grid.
    violations : (k,) int array
        Held-out residuals outside ``[lower - dbar, upper + dbar]`` (the bound fitted on the other folds,
        widened by the noise bound), summed over the folds.
    evaluated : int
        Grid values evaluated (from the smallest; the counts beyond are 0, :func:`held_out_evidence`).
    n_held_out : int
        Samples held out (each once).
    smallest : float or None
        Smallest B of the grid with no violation (None: every B has some).
    cp_upper : float or None
        For it, the Clopper-Pearson upper bound (at ``confidence``) on the probability that a new sample
        from the same distribution falls outside the bound (evidence about new data, not about B).
    confidence : float
    """

    rkhs_bounds: np.ndarray
    violations: np.ndarray
    evaluated: int
    n_held_out: int
    smallest: float | None
    cp_upper: float | None
    confidence: float

    def to_dict(self) -> dict:
        return jsonable({"rkhs_bounds": self.rkhs_bounds, "violations": self.violations,
                         "evaluated": self.evaluated, "n_held_out": self.n_held_out, "smallest_without_violation": self.smallest,
                         "clopper_pearson_upper": self.cp_upper, "confidence": self.confidence})


def held_out_evidence(X, y, lengthscale, *, noise_bound: float, rkhs_bounds, folds,
                      misspecification: float = 0.0, confidence: float = CONFIDENCE,
                      stop: bool = True) -> HeldOutEvidence:
    """Count the held-out residuals outside the certified pointwise bound fitted on the other folds.

    For each fold and each B: ``rkhs.cell_ranges`` on the training folds (optimal weights) at the degenerate
    cells ``[x_j, x_j]`` of the held-out inputs gives ``lower_j <= g(x_j) <= upper_j`` under the assumption
    (eq. C with ``t_max = 0``: no Taylor term; tau included); ``y_j = g(x_j) + d_j`` with ``|d_j| <= dbar``,
    so a residual outside ``[lower_j - dbar, upper_j + dbar]`` contradicts B (or the lengthscale, the noise
    bound, tau). An empty range (``lower > upper``: the training folds alone refute B) counts every point.

    The exact optimal bound widens with B (its feasible set grows), so with ``stop`` the grid is walked
    upwards and left at the first B without a violation (``evaluated`` says how far it got; the counts beyond
    are 0). Per held-out point the smallest B without violation is the minimum norm of its training folds
    plus that point, so the smallest B of the grid never exceeds the grid point above the minimum norm of
    all the points.
    """
    from robust_imdp.bounds.rkhs import KernelModel, cell_ranges

    X = np.ascontiguousarray(X, float)
    y = np.ascontiguousarray(y, float)
    grid = np.asarray(rkhs_bounds, float)
    if grid.ndim != 1 or grid.size == 0 or np.any(~(grid > 0)) or np.any(np.diff(grid) <= 0):
        raise InvalidInputError(f"rkhs_bounds must be an increasing 1-D array of positive floats; got {grid!r}")
    viol = np.zeros(grid.size, dtype=np.int64)
    everything = np.arange(y.size)
    dbar = float(noise_bound)
    models = [(te, KernelModel(X[np.setdiff1d(everything, te)], y[np.setdiff1d(everything, te)], lengthscale))
              for te in folds]
    evaluated = 0
    for j, B in enumerate(grid):
        for te, model in models:
            P = X[te]
            cr = cell_ranges(model, P, P, rkhs_bound=float(B), noise_bound=dbar, misspecification=misspecification)
            outside = (cr.lower > cr.upper) | (y[te] > cr.upper + dbar) | (y[te] < cr.lower - dbar)
            viol[j] += int(np.sum(outside))
        evaluated = j + 1
        if viol[j] == 0 and stop:  # the exact bound widens with B: no larger B can have a violation
            break
    n = int(sum(len(te) for te in folds))
    ok = np.flatnonzero(viol[:evaluated] == 0)
    smallest = float(grid[ok[0]]) if ok.size else None
    cp = clopper_pearson_upper(0, n, confidence) if ok.size else None
    return HeldOutEvidence(grid, viol, evaluated, n, smallest, cp, float(confidence))


def _b_grid(base: float) -> np.ndarray:
    return base * 2.0 ** (np.arange(B_GRID_STEPS[0], B_GRID_STEPS[1] + 1) / 4.0)


# ============================================================================ trend
@dataclass(frozen=True, eq=False)
class TrendCheck:
    """An affine part of the residuals that the SE kernel cannot represent (:func:`trend_check`).

    Attributes
    ----------
    detected : bool
        Removing ``slope.x + offset`` leaves at most :data:`TREND_FACTOR` of the minimum norm.
    slope : (d,) float array, offset : float
        The least-squares affine fit of the residuals.
    min_norm : float
        Certified minimum norm of the residuals (as in the calibration).
    min_norm_detrended : float
        The same for the residuals less the affine fit.
    tau : float
        ``max over X of |slope.x + offset|``: the misspecification that keeps the trend out of B.
    rkhs_bound_detrended : float
        ``B_MARGIN`` times the detrended minimum norm (rounded up): the B of either alternative.
    """

    detected: bool
    slope: np.ndarray
    offset: float
    min_norm: float
    min_norm_detrended: float
    tau: float
    rkhs_bound_detrended: float

    def to_dict(self) -> dict:
        return jsonable({"detected": self.detected, "slope": self.slope, "offset": self.offset,
                         "min_norm": self.min_norm, "min_norm_detrended": self.min_norm_detrended,
                         "misspecification_alternative": self.tau,
                         "rkhs_bound_detrended": self.rkhs_bound_detrended})


def trend_check(X, y, lengthscale, *, noise_bound: float, lower, upper, min_norm: float,
                misspecification: float = 0.0, max_points: int = MIN_NORM_POINTS) -> TrendCheck:
    """Does an affine part carry most of the minimum norm? (the module docstring, item 5)

    Parameters
    ----------
    X : (m, d), y : (m,)
        All the component's samples.
    lower, upper : (d,) float arrays
        The box X (where ``tau`` must hold).
    min_norm : float
        The residuals' own minimum norm at ``lengthscale`` (computed by the caller).
    """
    from robust_imdp.bounds.rkhs_check import min_rkhs_norm

    X = np.asarray(X, float)
    A = np.hstack([X, np.ones((X.shape[0], 1))])
    coef = np.linalg.lstsq(A, y, rcond=None)[0]
    slope, offset = coef[:-1], float(coef[-1])
    detr = min_rkhs_norm(X, y - A @ coef, lengthscale, noise_bound, misspecification,
                         max_points=max_points)["minimum"]
    lo, up = np.asarray(lower, float), np.asarray(upper, float)
    # slope.x + offset is affine: its largest and smallest values over the box are at vertices, each axis at
    # the end that makes its term largest (smallest)
    top = float(np.sum(np.maximum(slope * lo, slope * up))) + offset
    bottom = float(np.sum(np.minimum(slope * lo, slope * up))) + offset
    tau = max(abs(top), abs(bottom))
    detected = bool(min_norm > 0 and detr <= TREND_FACTOR * min_norm)
    b_detr = _round_sig(B_MARGIN * detr, 2, up=True) if detr > 0 else 0.0
    return TrendCheck(detected, slope, offset, float(min_norm), float(detr), float(tau), b_detr)


# ============================================================================ one component
@dataclass(frozen=True, eq=False)
class ComponentCalibration:
    """The calibration of one mode and component (:func:`calibrate_component`).

    Attributes
    ----------
    mode : int, component : int
        Indices (the component from 0).
    n_points, n_used : int
        Samples of the component, and those in the calibration subset (:data:`MAX_POINTS`).
    noise_bound, noise_variance, misspecification : float
        The data-noise allowance of the certificate, the likelihood's noise variance, tau.
    curves : LengthscaleCurves
    lengthscale : float
        The suggested lengthscale (isotropic); ``lengthscale_rule`` says how it was chosen.
    min_norm : float
        Certified minimum norm at the suggested lengthscale (``min_norm_points`` points).
    held_out : HeldOutEvidence
    trend : TrendCheck
    rkhs_bound : float
        The suggested B.
    rkhs_bound_rule : str
    seconds : float
    """

    mode: int
    component: int
    n_points: int
    n_used: int
    noise_bound: float
    noise_variance: float
    misspecification: float
    curves: LengthscaleCurves
    lengthscale: float
    lengthscale_rule: str
    min_norm: float
    min_norm_points: int
    held_out: HeldOutEvidence
    trend: TrendCheck
    rkhs_bound: float
    rkhs_bound_rule: str
    seconds: float

    def to_dict(self, mode_names=None) -> dict:
        return jsonable({
            "mode": mode_names[self.mode] if mode_names is not None else self.mode,
            "component": self.component + 1, "n_points": self.n_points, "n_used": self.n_used,
            "noise_bound": self.noise_bound, "noise_variance": self.noise_variance,
            "misspecification": self.misspecification,
            "suggested": {"rkhs_bound": self.rkhs_bound, "lengthscale": self.lengthscale},
            "lengthscale_rule": self.lengthscale_rule, "rkhs_bound_rule": self.rkhs_bound_rule,
            "min_norm": {"value": self.min_norm, "n_points": self.min_norm_points,
                         "meaning": "certified: every function fitting the data within the noise bound has at "
                                    "least this RKHS norm at the suggested lengthscale; a smaller B is refuted"},
            "lengthscale_curves": self.curves.to_dict(), "held_out": self.held_out.to_dict(),
            "trend": self.trend.to_dict(), "seconds": self.seconds})


def _check_component(X, y, noise_bound, noise_var, misspecification, lower, upper):
    X = np.asarray(X, float)
    y = np.asarray(y, float)
    if X.ndim != 2 or X.shape[0] < 1:
        raise DimensionError(f"X must be a (m, d) float array; got shape {X.shape}")
    if y.shape != (X.shape[0],):
        raise DimensionError(f"y must have shape ({X.shape[0]},) like X's rows; got {y.shape}")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(y))):
        raise InvalidInputError("X and y must be finite")
    for name, v, strict in (("noise_bound", noise_bound, False), ("noise_variance", noise_var, True),
                            ("misspecification", misspecification, False)):
        if not (np.isfinite(v) and (v > 0 if strict else v >= 0)):
            raise InvalidInputError(f"{name} must be a finite float {'>' if strict else '>='} 0; got {v!r}")
    lo, up = np.asarray(lower, float).reshape(-1), np.asarray(upper, float).reshape(-1)
    if lo.shape != (X.shape[1],) or up.shape != lo.shape or np.any(~(lo < up)):
        raise DimensionError(f"lower and upper must be ({X.shape[1]},) arrays with lower < upper (the box X); "
                             f"got {lo.tolist()} and {up.tolist()}")
    return X, y, lo, up


def calibrate_component(X, y, *, noise_bound: float, noise_variance: float, lower, upper,
                        misspecification: float = 0.0, lengthscale=None, folds: int = FOLDS, rng: Any = 0,
                        mode: int = 0, component: int = 0, threads: int | None = None) -> ComponentCalibration:
    """Calibrate one mode and component (the module docstring, items 1-5): a pure function, a scheduler task.

    Parameters
    ----------
    X : (m, d) float array, y : (m,) float array
        Inputs and residuals ``x_next - f_u(x)`` of this output.
    noise_bound : float >= 0
        The data-noise allowance of the certificate (the noise bound plus the residuals' rounding).
    noise_variance : float > 0
        The GP likelihood's noise variance (:func:`noise_variance` of the noise model).
    lower, upper : (d,) float arrays
        The box X.
    misspecification : float >= 0
        tau of the problem (kept; it widens the allowance of every minimum norm and bound).
    lengthscale : float, (d,) float array or None
        Keep this lengthscale (the curves are still computed); None: choose one (:func:`choose_lengthscale`).
    folds : int >= 2
    rng : seed of the calibration subset and the folds
    mode, component : int
        Where the result belongs (copied into it).
    threads : int, optional
        numba threads of the certified bounds (a scheduler passes 1 per worker).

    Returns
    -------
    ComponentCalibration
    """
    from robust_imdp.bounds.rkhs_check import min_rkhs_norm

    t0 = time.perf_counter()
    if threads is not None:
        import numba

        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    X, y, lo, up = _check_component(X, y, float(noise_bound), float(noise_variance), float(misspecification),
                                     lower, upper)
    m = X.shape[0]
    gen = np.random.default_rng(rng)
    idx = np.arange(m) if m <= MAX_POINTS else np.sort(gen.choice(m, MAX_POINTS, replace=False))
    Xs, ys = X[idx], y[idx]
    fo = kfold(idx.size, folds, gen)
    nb, tau = float(noise_bound), float(misspecification)
    curves = lengthscale_curves(Xs, ys, noise_var=float(noise_variance), folds=fo, noise_bound=nb,
                                misspecification=tau)
    if lengthscale is None:
        ell, rule = choose_lengthscale(curves, _extent(X))
    else:
        ell = np.asarray(lengthscale, float)
        ell = float(ell) if ell.ndim == 0 else ell
        rule = "kept from the problem"
    check = min_rkhs_norm(X, y, ell, nb, tau, max_points=MIN_NORM_POINTS)
    gamma = float(check["minimum"])
    # the grid's k = 0 value just above the minimum norm: the certified minimum is a lower bound within about
    # 0.1 % of the true one (docs/rkhs_bounds.md, section 3), where no held-out point can be violated
    base = B_GRID_ABOVE * gamma if gamma > 0 else max(nb, 1e-12)
    held = held_out_evidence(Xs, ys, ell, noise_bound=nb, rkhs_bounds=_b_grid(base), folds=fo,
                             misspecification=tau)
    ref = max(gamma, held.smallest) if held.smallest is not None else float(held.rkhs_bounds[-1])
    B = _round_sig(B_MARGIN * ref, 2, up=True) if ref > 0 else 0.0
    source = ("the minimum norm" if held.smallest is None or gamma >= held.smallest
              else "the held-out smallest B")
    if held.smallest is None:
        source = f"the largest B tried ({ref:.3g}); every B of the held-out grid has violations"
    rule_b = f"{B_MARGIN:g} x {source} ({ref:.4g}), rounded up to 2 significant digits"
    if gamma == 0:
        rule_b += "; the zero function fits every sample within the noise bound (the grid starts at the noise bound)"
    trend = trend_check(X, y, ell, noise_bound=nb, lower=lo, upper=up, min_norm=gamma, misspecification=tau)
    return ComponentCalibration(int(mode), int(component), m, int(idx.size), nb, float(noise_variance), tau, curves,
                                ell, rule, gamma, int(check["n_points"]), held, trend, B, rule_b,
                                time.perf_counter() - t0)


# ============================================================================ all components
def _is_plain(name: str) -> bool:
    return re.fullmatch(r"[A-Za-z0-9_-]+", name) is not None


def _toml_key(name: str) -> str:
    return name if _is_plain(name) else '"' + name.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _collapse(per_mode: list, mode_names) -> Any:
    """Per-mode values (each already in a per-mode form) as one value if all modes agree, else a table."""
    first = per_mode[0]
    if all(v == first for v in per_mode):
        return first
    return {str(name): v for name, v in zip(mode_names, per_mode)}


def _per_component(values: list) -> Any:
    """One mode's per-component numbers: one number if they agree, else a list."""
    return values[0] if all(v == values[0] for v in values) else list(values)


def _lengthscale_form(rows: list, d: int) -> Any:
    """One mode's per-component lengthscales (each a float or a (d,) list) in a form ``assumptions`` reads:
    one number, one list of d numbers (every component), or a list per component whose entries are lists."""
    if all(r == rows[0] for r in rows):
        return rows[0]
    return [r if isinstance(r, list) else [r] * d for r in rows]


@dataclass(frozen=True, eq=False)
class Calibration:
    """Calibration of every mode and component (:func:`calibrate_data`).

    Attributes
    ----------
    components : tuple of ComponentCalibration
        The learned components, mode by mode.
    mode_names : tuple of str
    dim : int
    rkhs_bound, misspecification : (n_modes, n) float arrays
        The suggestion per mode and component (known components keep B = 0; tau is the problem's).
    lengthscale : (n_modes, n, d) float array
        The suggested lengthscales (known or kept components keep the problem's).
    statement : str
        :data:`EVIDENCE`.
    settings : dict
        The constants and options used.
    seconds : float
    """

    components: tuple
    mode_names: tuple
    dim: int
    rkhs_bound: np.ndarray
    lengthscale: np.ndarray
    misspecification: np.ndarray
    statement: str
    settings: dict
    seconds: float

    @property
    def suggested(self) -> dict:
        """``rkhs_bound``, ``lengthscale`` and ``misspecification`` in the shapes of a problem file's
        ``[learning]`` table (``bounds.assumptions``): one value when all modes and components agree."""
        d = self.dim
        B, tau = [], []
        L = []
        for u in range(len(self.mode_names)):
            B.append(_per_component([float(v) for v in self.rkhs_bound[u]]))
            tau.append(_per_component([float(v) for v in self.misspecification[u]]))
            rows = []
            for i in range(self.rkhs_bound.shape[1]):
                ls = [float(v) for v in self.lengthscale[u, i]]
                rows.append(ls[0] if all(v == ls[0] for v in ls) else ls)
            L.append(_lengthscale_form(rows, d))
        return {"rkhs_bound": _collapse(B, self.mode_names), "lengthscale": _collapse(L, self.mode_names),
                "misspecification": _collapse(tau, self.mode_names)}

    def learning_table(self) -> str:
        """The suggested ``[learning]`` entries as TOML text to paste into a problem file."""
        s = self.suggested
        lines = ["[learning]", f"# suggested by robust-imdp calibrate: {self.statement}"]
        for key in ("rkhs_bound", "lengthscale", "misspecification"):
            lines.append(f"{key} = {_toml(s[key])}")
        for c in self.components:
            t = c.trend
            if t.detected:
                name = self.mode_names[c.mode]
                affine = " + ".join(f"{a:.4g} x{j + 1}" for j, a in enumerate(t.slope)) + f" + {t.offset:.4g}"
                lines.append(f"# mode {name!r}, component {c.component + 1}: the affine trend {affine} carries most "
                             f"of the minimum norm ({t.min_norm:.3g} -> {t.min_norm_detrended:.3g} without it): move "
                             f"it into the known part of mode {name!r} and use rkhs_bound {t.rkhs_bound_detrended:g} "
                             f"there, or keep it with misspecification {_round_sig(t.tau, 2, up=True) if t.tau > 0 else 0:g} "
                             f"and rkhs_bound {t.rkhs_bound_detrended:g}")
        return "\n".join(lines) + "\n"

    def table(self) -> str:
        """One line per learned component: the curves' optima, the suggestion and its evidence."""
        head = (f"{'mode':>10} {'comp':>4} {'l (ML)':>8} {'l (CV)':>8} {'l sugg':>8} {'min norm':>9} "
                f"{'held-out B':>10} {'CP up':>7} {'B sugg':>8} {'trend':>5}")
        lines = [head]
        for c in self.components:
            h = c.held_out
            lines.append(
                f"{self.mode_names[c.mode]:>10} {c.component + 1:>4} {c.curves.ml:>8.3g} {c.curves.cv:>8.3g} "
                f"{_ls_text(c.lengthscale):>8} {c.min_norm:>9.3g} "
                f"{('-' if h.smallest is None else f'{h.smallest:.3g}'):>10} "
                f"{('-' if h.cp_upper is None else f'{h.cp_upper:.3g}'):>7} {c.rkhs_bound:>8.3g} "
                f"{('yes' if c.trend.detected else 'no'):>5}")
        return "\n".join(lines)

    def summary(self) -> str:
        """The table, the statement and the ``[learning]`` table."""
        n_trend = sum(c.trend.detected for c in self.components)
        return "\n".join([
            f"calibration of {len(self.components)} learned components in {self.seconds:.1f} s "
            f"({self.settings['folds']}-fold; Clopper-Pearson at {self.settings['confidence']:g})",
            self.table(),
            f"note: {self.statement}",
            *([f"note: {n_trend} component(s) carry an affine trend (see the comments below)"] if n_trend else []),
            "", self.learning_table().rstrip("\n")])

    def to_dict(self) -> dict:
        """The ``calibration.json`` document."""
        return jsonable({
            "format": "robust_imdp.calibration/1", "statement": self.statement,
            "suggested": self.suggested, "learning_table": self.learning_table(),
            "modes": list(self.mode_names), "dim": self.dim, "settings": self.settings, "seconds": self.seconds,
            "components": [c.to_dict(self.mode_names) for c in self.components]})


def _ls_text(v) -> str:
    a = np.atleast_1d(np.asarray(v, float))
    return f"{a[0]:.3g}" if np.all(a == a[0]) else "[" + ",".join(f"{x:.2g}" for x in a) + "]"


def _toml(value) -> str:
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(float(value))


def _serial(fn, args):
    for i, a in enumerate(args):
        yield i, fn(*a)


def calibrate_data(data, *, noise_bound, noise_variance, lower, upper, mode_names: Sequence[str] | None = None,
                   rkhs_bound=None, lengthscale=None, misspecification=None, keep_lengthscale: bool = False,
                   folds: int = FOLDS, rng: Any = 0, scheduler=None,
                   progress: Callable[[str], None] | None = None) -> Calibration:
    """Calibrate every learned mode and component (:func:`calibrate_component` as one task each).

    Parameters
    ----------
    data : sequence (n_modes) of (X (m_u, d), Y (m_u, n)) pairs
        Inputs and residuals per mode.
    noise_bound : (n_modes, n) or (n,) float array
        The data-noise allowance per mode and component.
    noise_variance : (n,) float array
        The noise model's variance per component (:func:`noise_variance`).
    lower, upper : (d,) float arrays
        The box X.
    mode_names : sequence of str, optional
    rkhs_bound, lengthscale, misspecification : (n_modes, n), (n_modes, n, d), (n_modes, n) arrays, optional
        The problem's current settings (``assumptions.Settings``): components with B = 0 are known and
        skipped; tau is kept; the lengthscale is kept for known components (and for all with
        ``keep_lengthscale``). Default: every component learned, tau 0.
    folds : int >= 2
    rng : seed (each component gets its own stream, drawn in a fixed order: any scheduler, same result)
    scheduler : object with ``run(fn, args)`` yielding ``(index, result)`` (``pipeline.parallel``), optional
        Default: this process, one task after the other.
    progress : callable(str), optional
        One line per finished component.

    Returns
    -------
    Calibration
    """
    t0 = time.perf_counter()
    if not isinstance(data, (list, tuple)) or not data:
        raise InvalidInputError(f"data must be a non-empty sequence of (X, Y) pairs, one per mode; got {type(data).__name__}")
    M = len(data)
    names = tuple(str(v) for v in (mode_names if mode_names is not None else range(M)))
    if len(names) != M:
        raise DimensionError(f"mode_names must have one name per mode ({M}); got {len(names)}")
    X0 = np.asarray(data[0][0], float)
    if X0.ndim != 2:
        raise DimensionError(f"data[0]'s X must be a (m, d) array; got shape {X0.shape}")
    d = X0.shape[1]
    Ys = []
    for u, (X, Y) in enumerate(data):
        X = np.asarray(X, float)
        Y = np.asarray(Y, float)
        Y = Y[:, None] if Y.ndim == 1 else Y
        if X.ndim != 2 or X.shape[1] != d or Y.ndim != 2 or Y.shape[0] != X.shape[0]:
            raise DimensionError(f"mode {names[u]!r}: X must be (m, {d}) and Y (m, n) with the same rows; got "
                                 f"{X.shape} and {np.shape(data[u][1])}")
        Ys.append(Y)
    n = Ys[0].shape[1]
    nb = np.broadcast_to(np.asarray(noise_bound, float), (M, n))
    nv = np.broadcast_to(np.asarray(noise_variance, float), (n,))
    Bp = np.ones((M, n)) if rkhs_bound is None else np.broadcast_to(np.asarray(rkhs_bound, float), (M, n))
    Lp = np.ones((M, n, d)) if lengthscale is None else np.broadcast_to(np.asarray(lengthscale, float), (M, n, d))
    Tp = np.zeros((M, n)) if misspecification is None else np.broadcast_to(np.asarray(misspecification, float), (M, n))
    folds = _count(folds, "folds")
    if folds < 2:
        raise InvalidInputError(f"folds must be an integer >= 2; got {folds}")
    jobs, where = [], []
    gen = np.random.default_rng(rng)
    for u, (X, _) in enumerate(data):
        X = np.asarray(X, float)
        learned = [i for i in range(n) if Bp[u, i] > 0]
        if learned and X.shape[0] < 2 * folds:
            raise InvalidInputError(f"mode {names[u]!r} has {X.shape[0]} samples; {folds}-fold calibration needs at "
                                    f"least {2 * folds} per mode")
        for i in learned:
            keep = Lp[u, i] if keep_lengthscale else None
            jobs.append((X, Ys[u][:, i], float(nb[u, i]), float(nv[i]), lower, upper, float(Tp[u, i]), keep, folds,
                         int(gen.integers(2 ** 63)), u, i))
            where.append((u, i))
    run = scheduler.run if scheduler is not None else _serial
    results = [None] * len(jobs)
    for done, (k, r) in enumerate(run(_component_task, jobs), start=1):
        results[k] = r
        if progress is not None:
            u, i = where[k]
            progress(f"calibrate: mode {names[u]}, component {i + 1} ({done} of {len(jobs)}, {r.seconds:.1f} s): "
                     f"lengthscale {_ls_text(r.lengthscale)}, minimum norm {r.min_norm:.3g}, suggested B "
                     f"{r.rkhs_bound:.3g}" + (", affine trend" if r.trend.detected else ""))
    B = np.array(Bp, float)
    L = np.array(Lp, float)
    for r in results:
        B[r.mode, r.component] = r.rkhs_bound
        L[r.mode, r.component] = np.broadcast_to(np.asarray(r.lengthscale, float), (d,))
    settings = {"folds": folds, "confidence": CONFIDENCE, "max_points": MAX_POINTS,
                "min_norm_points": MIN_NORM_POINTS, "curve_points": CURVE_POINTS,
                "lengthscale_shrink": LENGTHSCALE_SHRINK, "b_margin": B_MARGIN, "trend_factor": TREND_FACTOR,
                "keep_lengthscale": bool(keep_lengthscale)}
    return Calibration(tuple(results), names, d, B, L, np.array(Tp, float), EVIDENCE, settings,
                       time.perf_counter() - t0)


def _component_task(X, y, noise_bound, noise_var, lower, upper, tau, keep, folds, seed, u, i, *, threads=None):
    """:func:`calibrate_component` with positional arguments (a scheduler task)."""
    return calibrate_component(X, y, noise_bound=noise_bound, noise_variance=noise_var, lower=lower, upper=upper,
                               misspecification=tau, lengthscale=keep, folds=folds, rng=seed, mode=u, component=i,
                               threads=threads)


def calibrate_problem(problem, *, keep_lengthscale: bool = False, folds: int = FOLDS, rng: Any = 0, scheduler=None,
                      progress: Callable[[str], None] | None = None) -> Calibration:
    """:func:`calibrate_data` on a ``Problem``'s data (``Problem.calibrate``, ``robust-imdp calibrate``).

    The residuals and the noise allowance are those of the bound stage: ``y = x_next - f_u(x)`` from each
    mode's known part (its ``residuals``, whose rounding bound joins the noise bound; periodic dimensions
    wrapped, docs/periodic.md), and the noise bound of the problem's noise model at the bound stage's data
    failure probability (bounded noise: its bound; else ``1 - confidence``, half of it with ``iid_noise``;
    ``rkhs.noise_bound_at_confidence`` over all samples). The problem's tau is kept, its known components
    (B = 0) are skipped, and its B and lengthscale are only starting points (kept with ``keep_lengthscale``).
    """
    from robust_imdp.bounds.assumptions import resolve
    from robust_imdp.bounds.rkhs import noise_bound_at_confidence
    from robust_imdp.models.geometry import wrap_residuals

    lo = np.asarray(problem.space_lower, float)
    up = np.asarray(problem.space_upper, float)
    names = tuple(problem.mode_names)
    n = lo.size
    if getattr(problem, "data", None) is None:
        raise InvalidInputError("the problem has no data (every component is known): there is nothing to calibrate")
    periodic = getattr(problem, "periodic", None)
    data, rounding = [], np.zeros((len(names), n))
    for u, m in enumerate(problem.maps):
        x, xn = problem.data.by_mode(u)
        r = m.residuals(x, xn)
        y, bound = wrap_residuals(r.y, r.bound, lo, up, periodic)
        data.append((np.asarray(x, float), y))
        if x.shape[0]:
            rounding[u] = bound.max(axis=0)
    fail = 1.0 - float(problem.confidence)
    delta = fail / 2 if getattr(problem, "iid_noise", False) else fail  # the bound stage's data failure budget
    nb, _ = noise_bound_at_confidence(problem.noise, max(sum(x.shape[0] for x, _ in data), 1), delta)
    allowance = np.nextafter(np.broadcast_to(np.asarray(nb, float), (len(names), n)) + rounding, np.inf)
    st = resolve(problem.rkhs_bound, problem.gp_options.get("lengthscale"), problem.misspecification, names, n)
    return calibrate_data(data, noise_bound=allowance, noise_variance=noise_variance(problem.noise), lower=lo,
                          upper=up, mode_names=names, rkhs_bound=st.rkhs_bound, lengthscale=st.lengthscale,
                          misspecification=st.misspecification, keep_lengthscale=keep_lengthscale, folds=folds,
                          rng=rng, scheduler=scheduler, progress=progress)
