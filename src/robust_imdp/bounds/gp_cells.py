"""Certified bounds of a GP posterior mean and standard deviation over many boxes.

For an SE-kernel GP ``k(a, b) = sf2 * exp(-z/2)``, ``z = sum_j ((a_j - b_j)/l_j)^2``, the
posterior mean is the kernel sum ``mu(x) = sum_i alpha_i k(x, x_i)`` and the variance is
``sigma^2(x) = sf2 - k_x^T (K + lambda' I)^{-1} k_x`` (``lambda' = noise + jitter``, the
matrix whose Cholesky factor is ``gp.L_``).  This module returns, for every box, a
*guaranteed* lower/upper bound of ``mu`` (optionally plus an affine term, the image of a mode
``f_u(x) + mu(x)``) and a guaranteed upper bound of ``sigma``, together with *achieved* values
(the objective at a point of the box), so that ``bound - achieved`` is a certified gap.

Guaranteed side (Blaas et al., AISTATS 2020; Cardelli et al., 2019)
    On a box every ``z_i(x)`` ranges in a closed-form interval ``[z_L, z_U]``.  ``e(z) =
    exp(-z/2)`` is convex: it lies above its tangent at any ``z_0`` and below its chord on
    ``[z_L, z_U]``.  Replacing each term ``w_i e(z_i)`` by the tangent (``w_i > 0``) or the chord
    (``w_i < 0``) gives an under-estimator that is affine in the ``z_i``, i.e. a *separable
    quadratic* in ``x``, minimised in closed form per coordinate.  The affine part
    ``a . x + c`` is added to that separable quadratic (exact per coordinate), so the image is
    bounded jointly, not as a sum of two separate bounds.
    The variance uses the tangent of the convex quadratic form ``q(k) = k^T M k``,
    ``M = (K + lambda' I)^{-1}``: for any vector ``b``, ``q(k) >= 2 b^T k - b^T M^{-1} b``
    (minimise the right-hand side minus ``q`` over ``k``), tight at ``k = M^{-1} b``.  With
    ``b = M k(c)`` for the leaf centre ``c`` this gives ``sigma^2(x) <= sf2 + b^T (K + lambda'
    I) b - sum_i 2 b_i k(x, x_i)``, a kernel sum bounded like the mean.  Only ``M^{-1} = K +
    lambda' I`` enters the inequality, so an inexact ``b`` costs tightness, never soundness.
    Both relaxations run inside a best-first branch-and-bound that returns the minimum over
    *all* leaves (open or pruned), so the result is sound even when the budget runs out.

    Limitation: ``b = M k(c)`` grows like ``1/lambda'``, so with a tiny regulariser the
    variance relaxation is loose (more leaves); with ``lambda = 1 + 2/m`` (the error lemma's
    regulariser) it is tight.

Achieved side
    The objective at the relaxation's minimiser and at the centre of every leaf, and, on
    request (``local_solver='casadi'``), for problems still open after a few iterations, a
    casadi (IPOPT) local optimisation from the best point so far.  These values prune leaves
    and close the gap from the other side.  Measured: casadi does not pay here (the leaf
    minimisers of the relaxation converge to the optimum as the leaves shrink), so it is off
    by default.

Floating point
    Every relaxation value is lowered by ``2 (m + 4 d + 64) eps * mag`` where ``mag`` bounds the
    sum of the absolute values of every term that enters it (the standard bound on the error
    of a sum of ``m`` terms, ``|err| <= (m - 1) u sum|t_i|``, ``u = eps/2``, plus a few ulps per
    term for exp, products and the expanded quadratic), then moved one more ulp outward with
    ``np.nextafter`` through ``robust_imdp._fp``'s ``down`` / ``up``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numba
import numpy as np
from scipy.linalg import cho_solve, solve_triangular

from robust_imdp._fp import down as _round_down  # x - abs_err, one more ulp down
from robust_imdp._fp import up as _round_up  # x + abs_err, one more ulp up
from robust_imdp.errors import DimensionError, InvalidInputError

_EPS = np.finfo(float).eps
_U = 0.5 * _EPS  # unit round-off

# --------------------------------------------------------------------------- results


@dataclass(frozen=True)
class PosteriorBounds:
    """Certified bounds of one GP's posterior over ``k`` boxes.

    Attributes
    ----------
    mean_lower, mean_upper : (k,) float arrays
        Guaranteed ``min`` / ``max`` of the posterior mean over each box (rounded outward).
    std_upper : (k,) float array
        Guaranteed ``max`` of the posterior standard deviation over each box.
    mean_min_achieved, mean_max_achieved, std_max_achieved : (k,) float arrays
        Values of the mean / std at points of the box (so ``mean_lower <= mean_min_achieved``).
    mean_lower_gap, mean_upper_gap, std_upper_gap : (k,) float arrays
        Certified gaps ``|achieved - bound|``: the true extremum lies within the gap of both.
    n_leaves : int
        Number of branch-and-bound boxes whose relaxation was evaluated (all problems).
    n_iterations : int
        Branch-and-bound iterations (batched over all boxes).
    budget_exhausted : (k,) bool array
        ``True`` where one of the three problems stopped at ``max_boxes`` before reaching
        ``tol``; the bounds there are still sound, only looser.
    """

    mean_lower: np.ndarray
    mean_upper: np.ndarray
    std_upper: np.ndarray
    mean_min_achieved: np.ndarray
    mean_max_achieved: np.ndarray
    std_max_achieved: np.ndarray
    mean_lower_gap: np.ndarray
    mean_upper_gap: np.ndarray
    std_upper_gap: np.ndarray
    n_leaves: int
    n_iterations: int
    budget_exhausted: np.ndarray


@dataclass(frozen=True)
class ImageBounds:
    """Certified bounds of the image ``A x + b + mu(x)`` of ``k`` boxes, per output.

    Attributes
    ----------
    lower, upper : (k, n) float arrays
        Guaranteed ``min`` / ``max`` over each box of output ``i``: ``A[i] . x + b[i] +
        mu_i(x)`` (affine term bounded jointly with the mean).
    std_upper : (k, n) float array
        Guaranteed ``max`` of ``sigma_i`` over each box.
    lower_gap, upper_gap, std_upper_gap : (k, n) float arrays
        Certified gaps (achieved value vs bound).
    n_leaves, n_iterations : int
        Totals over all outputs.
    budget_exhausted : (k, n) bool array
        Where a problem stopped at ``max_boxes`` (bounds sound but looser than ``tol``).
    """

    lower: np.ndarray
    upper: np.ndarray
    std_upper: np.ndarray
    lower_gap: np.ndarray
    upper_gap: np.ndarray
    std_upper_gap: np.ndarray
    n_leaves: int
    n_iterations: int
    budget_exhausted: np.ndarray


# --------------------------------------------------------------------------- rounding
def _pad(m: int, d: int, mag: np.ndarray) -> np.ndarray:
    """Stated bound on the float error of a relaxation value of ``m`` terms in ``d`` dims.

    ``2 (m + 4 d + 64) eps mag``: summing ``m`` terms costs at most ``(m - 1) u sum|t|``
    (``u = eps / 2``, any summation order), each term carries at most ~20 roundings (exp is
    correctly rounded to < 1 ulp in glibc; products, the expanded quadratic per coordinate),
    and the closed-form coordinate minimum ~10 more; the factor 4 on top is slack.
    """
    return 2.0 * (m + 4 * d + 64) * _EPS * mag


# --------------------------------------------------------------------------- relaxation


@numba.njit(cache=True)
def _relax_sums(X, inv_l2, W, lo, hi):  # pragma: no cover - compiled
    """Per leaf, the sums of the tangent/chord relaxation terms (hot loop, O(N m d)).

    For term i with weight w = W[n, i] (row 0 if W has one row), ``e(z_i) = exp(-z_i/2)`` is
    replaced by ``p + q z_i``: the tangent at ``z_c`` (leaf centre) when ``w > 0`` (a lower
    bound of the convex e), the chord on ``[z_L, z_U]`` when ``w < 0`` (an upper bound of e on
    that interval).  Guard ``z_L == z_U``: the constant ``e(z_L)`` (the max of the decreasing e
    on the interval, slope 0).  Returns, per leaf, ``sum w p``, ``sum w q``, ``sum w q x_ij``,
    ``sum w q x_ij^2`` (per j) and the magnitudes used by :func:`_pad`.
    """
    N, d = lo.shape
    m = X.shape[0]
    shared = W.shape[0] == 1
    cst = np.zeros(N)
    Ah = np.zeros(N)
    WX = np.zeros((N, d))
    WX2 = np.zeros((N, d))
    mag = np.zeros(N)
    aW = np.zeros(N)
    aWX = np.zeros((N, d))
    aWX2 = np.zeros((N, d))
    for n in range(N):
        r = 0 if shared else n
        for i in range(m):
            w = W[r, i]
            if w == 0.0:
                continue
            if w > 0.0:
                zc = 0.0
                for j in range(d):
                    t = 0.5 * (lo[n, j] + hi[n, j]) - X[i, j]
                    zc += t * t * inv_l2[j]
                e0 = np.exp(-0.5 * zc)
                p = e0 * (1.0 + 0.5 * zc)  # tangent: e(z) >= e0 (1 + zc/2) - (e0/2) z
                q = -0.5 * e0
            else:
                zL = 0.0
                zU = 0.0
                for j in range(d):
                    a = lo[n, j] - X[i, j]
                    b = X[i, j] - hi[n, j]
                    g = max(a, b, 0.0)  # distance of x_ij to [lo_j, hi_j]
                    f = max(abs(a), abs(b))  # distance to the farthest face
                    zL += g * g * inv_l2[j]
                    zU += f * f * inv_l2[j]
                eL = np.exp(-0.5 * zL)
                if zU - zL > 1e-9 * (1.0 + zU):
                    q = (np.exp(-0.5 * zU) - eL) / (zU - zL)  # chord slope
                else:
                    q = 0.0  # z_L == z_U guard: e <= e(z_L)
                p = eL - q * zL
            wq = w * q
            cst[n] += w * p
            Ah[n] += wq
            awq = abs(wq)
            aW[n] += awq
            mag[n] += abs(w) * (1.0 + abs(p))
            for j in range(d):
                x = X[i, j]
                WX[n, j] += wq * x
                WX2[n, j] += wq * x * x
                aWX[n, j] += awq * abs(x)
                aWX2[n, j] += awq * x * x
    return cst, Ah, WX, WX2, mag, aW, aWX, aWX2


@numba.njit(cache=True)
def _kvec(x, X, inv_l2, sf2):  # pragma: no cover - compiled
    """(N, m) SE kernel matrix ``sf2 exp(-z/2)`` (achieved values and tangent points only)."""
    N, d = x.shape
    m = X.shape[0]
    out = np.empty((N, m))
    for n in range(N):
        for i in range(m):
            z = 0.0
            for j in range(d):
                t = x[n, j] - X[i, j]
                z += t * t * inv_l2[j]
            out[n, i] = sf2 * np.exp(-0.5 * z)
    return out


def _kernel_sum_lower(X, ls, W, lo, hi, lin, const):
    """Lower bound of ``F(x) = sum_i W_i exp(-z_i(x)/2) + lin . x + const`` over boxes.

    Tangent/chord relaxation of ``e(z) = exp(-z/2)`` per term (module docstring), minimised in
    closed form per coordinate.

    Parameters
    ----------
    X : (m, d) float array
        Training inputs.
    ls : (d,) float array
        Lengthscales.
    W : (N, m) or (1, m) float array
        Weights of the kernel terms (``sf2`` included).
    lo, hi : (N, d) float arrays
        Boxes.
    lin : (N, d) float array
        Linear part of the affine term.
    const : (N,) float array
        Constant part.

    Returns
    -------
    lb : (N,) float array
        Sound lower bound of ``min_box F`` (padded and rounded down).
    xstar : (N, d) float array
        Minimiser of the relaxation (a point of the box, good candidate for ``F``).
    """
    m, d = X.shape
    inv_l2 = 1.0 / ls**2
    lo = np.ascontiguousarray(lo)
    hi = np.ascontiguousarray(hi)
    cst, Ah, WX, WX2, mag, aW, aWX, aWX2 = _relax_sums(
        X, inv_l2, np.ascontiguousarray(W), lo, hi
    )
    c = 0.5 * (lo + hi)
    h = 0.5 * (hi - lo)
    # relaxation = cst + const + lin.x + sum_i Wq_i z_i(x); expanded per coordinate in
    # y = x - c in [-h, h]: sum_i Wq_i (y_j - d_ij)^2 / l_j^2 with d_ij = x_ij - c_j
    A = Ah[:, None] * inv_l2[None, :]
    S = (WX - c * Ah[:, None]) * inv_l2
    C = (WX2 - 2.0 * c * WX + c * c * Ah[:, None]) * inv_l2
    B = lin - 2.0 * S  # q_j(y) = A y^2 + B y + C
    qlo = A * h * h - B * h + C
    qhi = A * h * h + B * h + C
    end_min = np.minimum(qlo, qhi)
    y_end = np.where(qlo <= qhi, -h, h)
    Apos = A > 0
    Asafe = np.where(Apos, A, 1.0)
    v = -B / (2.0 * Asafe)
    # vertex inside (with slack): the unconstrained minimum C - B^2/(4A) is <= the box minimum,
    # so a wrong "inside" decision near the boundary only loosens the bound, never breaks it.
    inside = Apos & (np.abs(v) <= h * (1.0 + 1e-9) + 1e-300)
    val = np.where(inside, C - B * B / (4.0 * Asafe), end_min)
    ystar = np.where(inside, np.clip(v, -h, h), y_end)
    lb = cst + const + (lin * c).sum(axis=1) + val.sum(axis=1)
    # magnitude of everything summed (see _pad): |W|(1 + |p|) + |Wq| Zabs,
    # Zabs_i = sum_j (H_j + |x_ij|)^2 / l_j^2 >= every expanded z-term, H_j = max(|lo_j|, |hi_j|)
    H = np.maximum(np.abs(lo), np.abs(hi))
    zab = (H * H * aW[:, None] + 2.0 * H * aWX + aWX2) * inv_l2
    mag = mag + zab.sum(axis=1) + (np.abs(lin) * H).sum(axis=1) + np.abs(const)
    # c + y can leave [lo, hi] by an ulp: clip (xstar is only a candidate point)
    return _round_down(lb, _pad(m, d, mag)), np.clip(c + ystar, lo, hi)


# --------------------------------------------------------------------------- GP adapter


class _GPTerms:
    """Arrays of a fitted GP needed by the bounds (read once, validated)."""

    def __init__(self, gp, name: str = "gp"):
        attrs = ("X_train_", "alpha_", "L_", "lengthscale_", "signal_variance_",
                 "noise_variance_", "jitter_")
        for attr in attrs:
            if not hasattr(gp, attr):
                raise InvalidInputError(
                    f"{name} must be a fitted GaussianProcess with attribute {attr!r}; "
                    f"got {type(gp).__name__} without it (call fit first)"
                )
        self.X = np.ascontiguousarray(np.asarray(gp.X_train_, float))
        if self.X.ndim != 2:
            raise DimensionError(f"{name}.X_train_ must have shape (m, d); got {self.X.shape}")
        m, d = self.X.shape
        self.m, self.d = m, d
        self.alpha = np.asarray(gp.alpha_, float).reshape(m)
        self.L = np.asarray(gp.L_, float)
        self.ls = np.broadcast_to(np.asarray(gp.lengthscale_, float), (d,)).copy()
        self.sf2 = float(gp.signal_variance_)
        # lambda' = noise + jitter: the matrix whose Cholesky factor is L_ (the variance bound is
        # for sigma^2 with exactly this regulariser; a smaller one would bound a smaller function)
        lam = float(gp.noise_variance_) + float(gp.jitter_)
        self.lam = lam
        if not (np.all(self.ls > 0) and self.sf2 > 0 and lam >= 0):
            raise InvalidInputError(
                f"{name} hyperparameters must be positive; got lengthscale {self.ls}, "
                f"signal_variance {self.sf2}, noise+jitter {lam}"
            )
        finite = all(np.all(np.isfinite(a)) for a in (self.X, self.alpha, self.L))
        if self.L.shape != (m, m) or not finite:
            raise InvalidInputError(
                f"{name}.L_ must be a finite (m, m) = ({m}, {m}) Cholesky factor and X_train_, "
                f"alpha_ finite; got L_ of shape {self.L.shape}"
            )
        # diag(L L^T) must be sf2 + lambda' (K_ii = sf2): catches an L_ of another regulariser
        diag = (self.L * self.L).sum(axis=1)
        if not np.allclose(diag, self.sf2 + lam, rtol=1e-8, atol=0.0):
            raise InvalidInputError(
                f"{name}.L_ must be the Cholesky factor of K + (noise_variance_ + jitter_) I with "
                f"diagonal {self.sf2 + lam}; got diagonal in [{diag.min()}, {diag.max()}]"
            )
        self._M = None
        self._Klam = None
        y = getattr(gp, "y_train_", None)
        self.y = None if y is None else np.asarray(y, float).reshape(-1)
        if self.y is not None and (self.y.shape != (m,) or not np.all(np.isfinite(self.y))):
            raise InvalidInputError(f"{name}.y_train_ must be {m} finite values; got shape {self.y.shape}")

    @property
    def alpha_err(self) -> float:
        """Bound of ``|k_x^T (alpha - alpha_)|`` over all x, alpha = (K + lambda' I)^{-1} y exact.

        The error lemma is about the exact posterior mean; ``alpha_`` is a floating-point solve.
        With the computed residual r~ = y - (K + lambda' I) alpha_ and its rounding error
        (componentwise <= (m + 2) u (|y| + (K + lambda' I)|alpha_|), Higham 2002, eq. 3.4-3.5,
        plus ~20 u relative error of each recomputed kernel entry: we use (m + 32) u),
        ||alpha - alpha_||_2 <= ||r||_2 / lambda_min(K + lambda' I) <= ||r||_2 / lambda'
        (K is PSD), and ||k_x||_2 <= sqrt(m) sf2. Returns 0 for a GP without ``y_train_``
        (then ``alpha_`` itself defines the mean being bounded) and inf for lambda' = 0.
        """
        if self.y is None:
            return 0.0
        if self.lam <= 0.0:
            return np.inf
        Kl = self.Klam
        r = self.y - Kl @ self.alpha
        slack = (self.m + 32) * _U * (np.abs(self.y) + Kl @ np.abs(self.alpha))
        r_norm = np.linalg.norm(np.abs(r) + slack) * (1.0 + 4.0 * self.m * _U)
        return float(_round_up(np.sqrt(self.m) * self.sf2 * r_norm / self.lam * (1.0 + 4.0 * _U)))

    def kvec(self, x):
        """(N, m) kernel vectors k(x, X)."""
        return _kvec(np.ascontiguousarray(x, dtype=float), self.X, 1.0 / self.ls**2, self.sf2)

    def mean(self, x):
        return self.kvec(x) @ self.alpha

    def var(self, x):
        v = solve_triangular(self.L, self.kvec(x).T, lower=True)
        return self.sf2 - (v * v).sum(axis=0)

    @property
    def M(self):
        """(K + lambda' I)^{-1} from the Cholesky factor (only used to pick the tangent b)."""
        if self._M is None:
            self._M = cho_solve((self.L, True), np.eye(self.m))
        return self._M

    @property
    def Klam(self):
        """K + lambda' I recomputed from the data (enters the variance bound)."""
        if self._Klam is None:
            self._Klam = self.kvec(self.X) + self.lam * np.eye(self.m)
        return self._Klam

    @property
    def Klam_rowsum(self):
        """Max row sum of K + lambda' I (>= its largest eigenvalue; all entries >= 0)."""
        return float(self.Klam.sum(axis=1).max())


# --------------------------------------------------------------------------- branch and bound


@dataclass
class _BnBResult:
    lb: np.ndarray  # (P,) sound lower bound of the objective
    best: np.ndarray  # (P,) achieved objective value
    best_x: np.ndarray  # (P, d)
    exhausted: np.ndarray  # (P,) bool
    n_leaves: int
    n_iterations: int


def _chunked(fn, n, m, *arrays):
    """Apply ``fn`` to row chunks so that (chunk, m) temporaries stay ~8 MB."""
    step = max(1, int(1_000_000 // max(m, 1)))
    if n <= step:
        return fn(*arrays)
    outs = [fn(*(a[s : s + step] for a in arrays)) for s in range(0, n, step)]
    return tuple(np.concatenate(o) for o in zip(*outs))


def _branch_and_bound(
    lo,
    hi,
    relax: Callable,
    value: Callable,
    tol_of: Callable,
    max_boxes: int,
    ls,
    refine: Callable | None = None,
    refine_after: int = 3,
    per_iter: int = 4,
):
    """Best-first branch-and-bound minimising P objectives, each over its own box.

    ``relax(lo, hi, pid) -> (lb, x)`` gives a sound lower bound over each leaf and a candidate
    point, ``value(x, pid)`` the objective at points, ``tol_of(best)`` the per-problem gap
    target.  Every iteration splits, for every open problem, its ``per_iter`` leaves with the
    smallest bounds (best-first, batched over problems) along the longest side scaled by the
    lengthscale.  Leaves with ``lb >= best - tol`` are pruned, but their bounds are kept: the
    result is the minimum over *all* leaves, so it is sound whenever the budget runs out.
    """
    P, d = lo.shape
    pid = np.arange(P)
    lb, xs = relax(lo, hi, pid)
    centre = 0.5 * (lo + hi)
    fx = value(xs, pid)
    fc = value(centre, pid)
    best = np.minimum(fx, fc)
    best_x = np.where((fx <= fc)[:, None], xs, centre)
    L_lo, L_hi, L_lb, L_pid = lo.copy(), hi.copy(), lb, pid
    pruned_min = np.full(P, np.inf)
    n_eval = np.ones(P, dtype=np.int64)
    exhausted = np.zeros(P, bool)
    n_leaves, it = P, 0
    refined = False
    while True:
        tol = tol_of(best)
        prune = L_lb >= best[L_pid] - tol[L_pid]
        if prune.any():
            np.minimum.at(pruned_min, L_pid[prune], L_lb[prune])
            keep = ~prune
            L_lo, L_hi, L_lb, L_pid = L_lo[keep], L_hi[keep], L_lb[keep], L_pid[keep]
        exhausted |= n_eval >= max_boxes
        active = ~exhausted[L_pid]
        if not active.any():
            break
        if refine is not None and it == refine_after and not refined:
            refined = True
            open_p = np.unique(L_pid[active])
            fr, xr = refine(best_x[open_p], lo[open_p], hi[open_p], open_p)
            better = fr < best[open_p]
            best[open_p[better]] = fr[better]
            best_x[open_p[better]] = xr[better]
            continue  # re-prune with the improved achieved values
        it += 1
        # best-first selection: per problem, the per_iter leaves of smallest bound
        idx = np.flatnonzero(active)
        order = idx[np.lexsort((L_lb[idx], L_pid[idx]))]
        sp = L_pid[order]
        first = np.r_[True, sp[1:] != sp[:-1]]
        start = np.maximum.accumulate(np.where(first, np.arange(sp.size), 0))
        sel = order[(np.arange(sp.size) - start) < per_iter]
        s_lo, s_hi, s_lb, s_pid = L_lo[sel], L_hi[sel], L_lb[sel], L_pid[sel]
        rest = np.ones(L_lb.size, bool)
        rest[sel] = False
        # split along the longest side in lengthscale units
        k = np.argmax((s_hi - s_lo) / ls, axis=1)
        r = np.arange(sel.size)
        mid = 0.5 * (s_lo[r, k] + s_hi[r, k])
        a_hi = s_hi.copy()
        a_hi[r, k] = mid
        b_lo = s_lo.copy()
        b_lo[r, k] = mid
        c_lo = np.concatenate([s_lo, b_lo])
        c_hi = np.concatenate([a_hi, s_hi])
        c_pid = np.concatenate([s_pid, s_pid])
        c_lb, c_x = relax(c_lo, c_hi, c_pid)
        # a child is inside its parent, so the parent's bound holds for it too
        c_lb = np.maximum(c_lb, np.concatenate([s_lb, s_lb]))
        fx = value(c_x, c_pid)
        np.minimum.at(best, c_pid, fx)
        hit = fx <= best[c_pid]
        best_x[c_pid[hit]] = c_x[hit]
        np.add.at(n_eval, c_pid, 1)
        n_leaves += c_pid.size
        L_lo = np.concatenate([L_lo[rest], c_lo])
        L_hi = np.concatenate([L_hi[rest], c_hi])
        L_lb = np.concatenate([L_lb[rest], c_lb])
        L_pid = np.concatenate([L_pid[rest], c_pid])
    final = pruned_min.copy()
    np.minimum.at(final, L_pid, L_lb)
    open_left = np.zeros(P, bool)
    open_left[L_pid] = True
    return _BnBResult(final, best, best_x, exhausted & open_left, n_leaves, it)


# --------------------------------------------------------------------------- casadi (local optima)


def _casadi_refiner(gpt: _GPTerms, kind: str, sign, lin, value: Callable):
    """Batched IPOPT local optimisation of a mean (``kind='mean'``) or ``-variance`` objective.

    Returns ``refine(x0, lo, hi, pid) -> (f, x)``; ``f`` is re-evaluated by ``value`` (numpy),
    so achieved values never depend on casadi's arithmetic, and ``x`` is clipped into the box.
    One NLP per GP and kind is built once and mapped over the open problems (``Function.map``).
    """
    import casadi as ca  # the only casadi import of the library

    d, m = gpt.d, gpt.m
    x = ca.MX.sym("x", d)
    p = ca.MX.sym("p", d + 1)  # (sign, linear term) of the mean objective
    diff = (ca.repmat(x.T, m, 1) - ca.DM(gpt.X)) / ca.repmat(ca.DM(gpt.ls).T, m, 1)
    kx = gpt.sf2 * ca.exp(-0.5 * ca.sum2(diff * diff))
    if kind == "mean":
        f = p[0] * ca.dot(ca.DM(gpt.alpha), kx) + ca.dot(p[1:], x)
    else:  # -sigma^2 = k^T M k - sf2
        f = ca.dot(kx, ca.mtimes(ca.DM(gpt.M), kx)) - gpt.sf2
    opts = {
        "ipopt.print_level": 0,
        "ipopt.sb": "yes",
        "print_time": 0,
        "ipopt.max_iter": 30,
        "ipopt.tol": 1e-10,
        "error_on_fail": False,
    }
    solver = ca.nlpsol("local", "ipopt", {"x": x, "p": p, "f": f}, opts)

    def refine(x0, lo, hi, pids):
        n = x0.shape[0]
        if kind == "mean":
            par = np.column_stack([sign[pids], lin[pids]])
        else:
            par = np.zeros((n, d + 1))
        sol = solver.map(n, "serial")(x0=x0.T, p=par.T, lbx=lo.T, ubx=hi.T)
        xr = np.clip(np.asarray(sol["x"]).reshape(d, n).T, lo, hi)
        return value(xr, pids), xr

    return refine


# --------------------------------------------------------------------------- public API


def _check_boxes(lower, upper, d: int):
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    for nm, a in (("lower", lower), ("upper", upper)):
        if a.ndim != 2 or a.shape[1] != d:
            raise DimensionError(f"{nm} must have shape (k, {d}) (one box per row); got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InvalidInputError(f"{nm} must contain only finite values; got NaN or inf")
    if lower.shape != upper.shape:
        raise DimensionError(
            f"upper must have the same shape as lower {lower.shape}; got {upper.shape}"
        )
    bad = np.flatnonzero((lower > upper).any(axis=1))
    if bad.size:
        i = bad[0]
        raise InvalidInputError(
            f"boxes must have lower <= upper; box {i} has lower {lower[i]} > upper {upper[i]}"
        )
    return lower, upper


def _check_options(tol, max_boxes, per_iter):
    if int(per_iter) != per_iter or per_iter < 1:
        raise InvalidInputError(f"per_iter must be a positive integer; got {per_iter!r}")
    if not (np.isfinite(tol) and tol > 0):
        raise InvalidInputError(f"tol must be a positive finite float; got {tol!r}")
    if int(max_boxes) != max_boxes or max_boxes < 1:
        raise InvalidInputError(f"max_boxes must be a positive integer; got {max_boxes!r}")


def _bound_one(gpt: _GPTerms, lower, upper, lin, const, tol, max_boxes, local_solver, per_iter):
    """Mean min/max of ``lin . x + const + mu`` and variance max for one GP over k boxes."""
    k, d = lower.shape
    # ---- mean: problems 0..k-1 minimise +F, k..2k-1 minimise -F
    sign = np.r_[np.ones(k), -np.ones(k)]
    w0 = gpt.sf2 * gpt.alpha
    lin2 = np.concatenate([lin, -lin])
    const2 = np.concatenate([const, -const])

    def relax_mean(lo, hi, pid):
        def f(lo, hi, pid):
            return _kernel_sum_lower(
                gpt.X, gpt.ls, sign[pid, None] * w0[None, :], lo, hi, lin2[pid], const2[pid]
            )

        return _chunked(f, lo.shape[0], gpt.m, lo, hi, pid)

    def value_mean(x, pid):
        return sign[pid] * gpt.mean(x) + (lin2[pid] * x).sum(axis=1) + const2[pid]

    refine = None
    if local_solver == "casadi":
        refine = _casadi_refiner(gpt, "mean", sign, lin2, value_mean)
    lo2, hi2 = np.concatenate([lower, lower]), np.concatenate([upper, upper])
    rm = _branch_and_bound(
        lo2, hi2, relax_mean, value_mean, lambda b: np.full(b.shape, tol), max_boxes, gpt.ls,
        refine=refine, per_iter=per_iter,
    )

    # ---- variance: minimise -sigma^2
    def relax_var(lo, hi, pid):
        def f(lo, hi):
            c = 0.5 * (lo + hi)
            bvec = gpt.kvec(c) @ gpt.M  # tangent point; any b is sound (module docstring)
            bK = bvec @ gpt.Klam
            cq = (bK * bvec).sum(axis=1)  # b^T (K + lambda' I) b
            # |b|^T (K + lambda' I) |b| <= rho |b|^2, rho = max row sum (entries >= 0)
            cmag = gpt.Klam_rowsum * (bvec * bvec).sum(axis=1)
            cq_up = _round_up(cq, _pad(gpt.m, d, cmag))
            lbS, xs = _kernel_sum_lower(
                gpt.X, gpt.ls, 2.0 * gpt.sf2 * bvec, lo, hi, np.zeros_like(lo), np.zeros(len(lo))
            )
            # sigma^2 <= sf2 + b^T(K+lambda'I)b - min S; objective -sigma^2 >= lbS - sf2 - cq_up
            t = lbS - gpt.sf2 - cq_up
            err = _pad(2, d, np.abs(lbS) + gpt.sf2 + np.abs(cq_up))
            return _round_down(t, err), xs

        return _chunked(f, lo.shape[0], gpt.m, lo, hi)

    def value_var(x, pid):
        return -gpt.var(x)

    def tol_var(best):
        # std gap <= tol if var gap <= max(2 tol sqrt(v), tol^2):
        # sqrt(v + g) - sqrt(v) <= min(g / (2 sqrt v), sqrt g)
        v = np.maximum(-best, 0.0)
        return np.maximum(2.0 * tol * np.sqrt(v), tol * tol)

    refine_v = None
    if local_solver == "casadi":
        refine_v = _casadi_refiner(gpt, "var", None, None, value_var)
    rv = _branch_and_bound(
        lower, upper, relax_var, value_var, tol_var, max_boxes, gpt.ls,
        refine=refine_v, per_iter=per_iter,
    )
    # lb of -F rounded down => -lb is rounded up; both widened by the bound of the floating-point
    # error of alpha_ so that they hold for the exact posterior mean of the error lemma.
    a_err = gpt.alpha_err
    mean_lower = _round_down(rm.lb[:k], a_err) if a_err > 0 else rm.lb[:k]
    mean_upper = _round_up(-rm.lb[k:], a_err) if a_err > 0 else -rm.lb[k:]
    var_up = -rv.lb
    # sigma^2 >= 0 exactly (Schur complement of a PSD matrix), so clipping the upper bound at 0
    # keeps it above the true value; sqrt then rounded up one ulp.
    std_upper = _round_up(np.sqrt(np.maximum(var_up, 0.0)))
    std_ach = np.sqrt(np.maximum(-rv.best, 0.0))
    return dict(
        mean_lower=mean_lower,
        mean_upper=mean_upper,
        std_upper=std_upper,
        mean_min_achieved=rm.best[:k],
        mean_max_achieved=-rm.best[k:],
        std_max_achieved=std_ach,
        mean_lower_gap=rm.best[:k] - mean_lower,
        mean_upper_gap=mean_upper + rm.best[k:],
        std_upper_gap=std_upper - std_ach,
        n_leaves=rm.n_leaves + rv.n_leaves,
        n_iterations=rm.n_iterations + rv.n_iterations,
        budget_exhausted=rm.exhausted[:k] | rm.exhausted[k:] | rv.exhausted,
        exhausted_parts=(rm.exhausted[:k], rm.exhausted[k:], rv.exhausted),
    )


def _check_local_solver(local_solver):
    if local_solver not in (None, "casadi"):
        raise InvalidInputError(f"local_solver must be 'casadi' or None; got {local_solver!r}")


def bound_posterior(
    gp,
    lower,
    upper,
    *,
    tol: float = 1e-3,
    max_boxes: int = 2000,
    local_solver: str | None = None,
    per_iter: int = 4,
) -> PosteriorBounds:
    """Certified bounds of a GP's posterior mean and std over many boxes.

    Parameters
    ----------
    gp : fitted GaussianProcess
        Needs ``X_train_ (m, d)``, ``alpha_ (m,)``, ``L_ (m, m)`` (lower Cholesky factor of
        ``K + (noise + jitter) I``), ``lengthscale_``, ``signal_variance_``, ``noise_variance_``,
        ``jitter_``.  The bounds are for ``mu(x) = k_x^T alpha_`` and ``sigma^2(x) = sf2 -
        k_x^T (K + (noise + jitter) I)^{-1} k_x`` in exact arithmetic.
    lower, upper : (k, d) float arrays
        Boxes, one per row.
    tol : float
        Target certified gap (in the units of the mean and of the std).
    max_boxes : int
        Branch-and-bound budget per problem (box and bound); when reached the bound is the
        minimum over all leaves (sound) and ``budget_exhausted`` is set.
    local_solver : {None, 'casadi'}
        ``'casadi'``: IPOPT local optimisation (batched with ``Function.map``) of the problems
        still open after 3 iterations.  Off by default: measured not to pay
        (``benchmarks/results/bounds.md``: the relaxation minimisers of the leaves are already
        near-optimal achieved values; casadi saved < 0.01 % of the leaves at 30x the time).
    per_iter : int
        Leaves split per open problem and iteration (best first).

    Returns
    -------
    PosteriorBounds
    """
    gpt = _GPTerms(gp)
    lower, upper = _check_boxes(lower, upper, gpt.d)
    _check_options(tol, max_boxes, per_iter)
    _check_local_solver(local_solver)
    k = lower.shape[0]
    r = _bound_one(
        gpt, lower, upper, np.zeros((k, gpt.d)), np.zeros(k), tol, max_boxes, local_solver,
        per_iter,
    )
    r.pop("exhausted_parts")
    return PosteriorBounds(**r)


def bound_image(
    gps: Sequence,
    A,
    b,
    lower,
    upper,
    *,
    tol: float = 1e-3,
    max_boxes: int = 2000,
    local_solver: str | None = None,
    per_iter: int = 4,
) -> ImageBounds:
    """Certified bounds of the image ``f_u(x) + mu(x)`` of boxes, per output dimension.

    Output ``i`` is ``A[i] . x + b[i] + mu_i(x)``; the affine term is added to the separable
    relaxation of ``mu_i`` (exact per coordinate), so it is bounded jointly with the mean.

    Parameters
    ----------
    gps : sequence of n fitted GaussianProcess
        One GP per output dimension (all with inputs of dimension d).
    A : (n, d) float array
    b : (n,) float array
    lower, upper : (k, d) float arrays
    tol, max_boxes, local_solver, per_iter
        As in :func:`bound_posterior`.

    Returns
    -------
    ImageBounds
    """
    gps = list(gps)
    if len(gps) == 0:
        raise InvalidInputError("gps must be a non-empty sequence of fitted GPs; got none")
    terms = [_GPTerms(g, f"gps[{i}]") for i, g in enumerate(gps)]
    n, d = len(terms), terms[0].d
    for i, t in enumerate(terms):
        if t.d != d:
            raise DimensionError(f"gps[{i}] must have input dimension {d} like gps[0]; got {t.d}")
    A = np.asarray(A, float)
    b = np.asarray(b, float)
    if A.shape != (n, d):
        raise DimensionError(f"A must have shape (n, d) = ({n}, {d}); got {A.shape}")
    if b.shape != (n,):
        raise DimensionError(f"b must have shape (n,) = ({n},); got {b.shape}")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        raise InvalidInputError("A and b must contain only finite values; got NaN or inf")
    lower, upper = _check_boxes(lower, upper, d)
    _check_options(tol, max_boxes, per_iter)
    _check_local_solver(local_solver)
    k = lower.shape[0]
    cols = []
    for i, t in enumerate(terms):  # loop over outputs only; everything inside is batched
        cols.append(
            _bound_one(
                t, lower, upper, np.broadcast_to(A[i], (k, d)).copy(), np.full(k, b[i]), tol,
                max_boxes, local_solver, per_iter,
            )
        )

    def stack(key):
        return np.column_stack([c[key] for c in cols])

    return ImageBounds(
        lower=stack("mean_lower"),
        upper=stack("mean_upper"),
        std_upper=stack("std_upper"),
        lower_gap=stack("mean_lower_gap"),
        upper_gap=stack("mean_upper_gap"),
        std_upper_gap=stack("std_upper_gap"),
        n_leaves=int(sum(c["n_leaves"] for c in cols)),
        n_iterations=int(sum(c["n_iterations"] for c in cols)),
        budget_exhausted=stack("budget_exhausted"),
    )


__all__ = ["PosteriorBounds", "ImageBounds", "bound_posterior", "bound_image"]
