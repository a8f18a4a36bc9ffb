"""Gaussian-process regression with a squared-exponential kernel: the model of the GP route.

:class:`GaussianProcess` is a scikit-learn-like estimator (``__init__`` stores, ``fit(X, y)``
returns ``self``, learned attributes end in ``_``); its posterior is the paper's eqs.
(post-mean), (post-kernel) with regulariser ``lambda`` on K's diagonal. Hyperparameters can
come from maximum marginal likelihood (``_fit_hyperparameters``). The public names are
re-exported by ``bounds.gp``; the error bound is ``bounds.gp_error``.

Attribute contract after ``GaussianProcess.fit`` (``bounds.gp_cells`` relies on it):
``X_train_ (m, d)``, ``y_train_ (m,)``, ``lengthscale_ (d,)``, ``signal_variance_``,
``noise_variance_`` (lambda, without jitter), ``jitter_``, ``L_ (m, m)`` lower Cholesky
factor of ``K + (lambda + jitter) I``, ``alpha_ (m,)`` = ``(K + (lambda + jitter) I)^{-1} y``.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Sequence

import numpy as np
import scipy.linalg
import scipy.optimize

from robust_imdp._kernels import se_kernel  # the one SE kernel (bit for bit the GP route's own)
from robust_imdp.errors import ConvergenceError, DimensionError, InvalidInputError

# The GP route logs under one name, ``robust_imdp.bounds.gp`` (the public module).
log = logging.getLogger("robust_imdp.bounds.gp")

#: Factorisations of ``K + (lambda + jitter) I`` tried, the jitter growing tenfold each time.
_JITTER_TRIES = 12
#: The negative log likelihood reported where the kernel matrix is not positive definite.
_FAILED_NLL = 1e25

#: The string accepted as ``noise_variance`` to request the regulariser of Chowdhury &
#: Gopalan (2017, Thm 2): ``lambda = 1 + eta`` with ``eta = 2 / m`` (m = number of samples).
CHOWDHURY = "chowdhury"


def chowdhury_regulariser(n_samples: int) -> float:
    """The regulariser ``lambda = 1 + 2/m`` that C&G (2017, Thm 2) prescribes for ``m`` samples.

    Parameters
    ----------
    n_samples : int
        Number of training points ``m >= 1``.

    Returns
    -------
    float
        ``1 + 2/m`` (computed the same way everywhere, so equality checks are exact).
    """
    m = int(n_samples)
    if m < 1:
        raise InvalidInputError(f"n_samples must be a positive integer; got {n_samples!r}")
    return 1.0 + 2.0 / m


def _positive_float(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a positive finite float; got {value!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise InvalidInputError(f"{name} must be a positive finite float; got {value!r}")
    return v


def _as_matrix(name: str, X: Any, d: int | None = None) -> np.ndarray:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2:
        raise DimensionError(f"{name} must be a 2-D (n_points, n_dims) array; got shape {X.shape}")
    if d is not None and X.shape[1] != d:
        raise DimensionError(f"{name} must have shape (k, {d}) like the training inputs; got {X.shape}")
    if not np.all(np.isfinite(X)):
        bad = np.argwhere(~np.isfinite(X))[0]
        raise InvalidInputError(f"{name} must be finite; got {X[tuple(bad)]} at index {tuple(bad)}")
    return X


# --------------------------------------------------------------------------- GP
class GaussianProcess:
    """GP regression with a squared-exponential kernel (isotropic or per-dimension).

    Parameters
    ----------
    lengthscale : float or (d,) float array, default 1.0
        Kernel lengthscale(s) ``l_j > 0``; a scalar is broadcast to every input dimension.
        With ``optimize=True`` this is the first starting point.
    signal_variance : float, default 1.0
        ``sf2 = k(x, x) > 0``.
    noise_variance : float or ``"chowdhury"``
        The regulariser ``lambda > 0`` on K's diagonal. ``"chowdhury"`` means
        ``lambda = 1 + 2/m`` (Chowdhury & Gopalan 2017, Thm 2), the only value
        :meth:`RKHSErrorBound.from_gp` accepts.
    optimize : bool, default False
        Fit lengthscales and signal variance by maximum marginal likelihood (scipy
        L-BFGS-B over log-parameters, analytic gradient, ``n_restarts`` seeded starts).
        With a numeric ``noise_variance`` that value stays fixed. With ``"chowdhury"``
        the likelihood uses its own free noise variance ``s2`` (reported as
        ``likelihood_noise_variance_``); the posterior is then computed with
        ``lambda = 1 + 2/m`` and ``sf2 = sf2_ml * lambda / s2`` -- the same ratio
        ``lambda / sf2`` as the likelihood fit, hence exactly the same posterior mean,
        while satisfying the lemma's regulariser. (Caveat: hyperparameters chosen from the
        same data are outside C&G's theorem, which assumes a fixed kernel; see
        :class:`RKHSErrorBound`.)
    n_restarts : int, default 5
        Number of starts of the likelihood optimisation (the first is the given values).
    max_fit_points : int or None, default 400
        The likelihood is maximised on a seeded random subset of at most this many points
        (its cost is O(m^3) per evaluation); the posterior always uses all the data.
    rng : seed or Generator, optional
        Randomness of the restart points and of the subset.

    Attributes
    ----------
    X_train_ : (m, d) float64 array
    y_train_ : (m,) float64 array
    lengthscale_ : (d,) float64 array
    signal_variance_ : float
    noise_variance_ : float
        lambda actually used by the posterior (excluding jitter).
    jitter_ : float
        Extra diagonal added only if the Cholesky factorisation failed (0 normally).
    L_ : (m, m) float64 array
        Lower Cholesky factor of ``K + (lambda + jitter) I``.
    alpha_ : (m,) float64 array
        ``(K + (lambda + jitter) I)^{-1} y``.
    likelihood_noise_variance_ : float
        Noise variance of the likelihood fit (equals ``noise_variance_`` unless the
        ``"chowdhury"`` + ``optimize`` route above was taken).
    log_marginal_likelihood_ : float
        Log marginal likelihood of the hyperparameters at the likelihood fit.
    """

    def __init__(
        self,
        lengthscale: float | Sequence[float] = 1.0,
        signal_variance: float = 1.0,
        noise_variance: float | str = CHOWDHURY,
        *,
        optimize: bool = False,
        n_restarts: int = 5,
        max_fit_points: int | None = 400,
        rng: Any = None,
    ) -> None:
        self.lengthscale = lengthscale
        self.signal_variance = signal_variance
        self.noise_variance = noise_variance
        self.optimize = optimize
        self.n_restarts = n_restarts
        self.max_fit_points = max_fit_points
        self.rng = rng

    # ------------------------------------------------------------------ public API
    def kernel(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """Kernel matrix ``k(A_i, B_j)`` with the fitted hyperparameters.

        Parameters
        ----------
        A : (p, d) float array
        B : (q, d) float array

        Returns
        -------
        (p, q) float array
        """
        self._check_fitted()
        d = self.lengthscale_.shape[0]
        return se_kernel(_as_matrix("A", A, d), _as_matrix("B", B, d), self.lengthscale_, self.signal_variance_)

    def fit(self, X: Any, y: Any) -> "GaussianProcess":
        """Fit the GP to training data.

        Parameters
        ----------
        X : (m, d) float array
        y : (m,) float array

        Returns
        -------
        self
        """
        X = _as_matrix("X", X)
        m, d = X.shape
        if m < 1:
            raise DimensionError(f"X must have at least one row; got shape {X.shape}")
        y = np.asarray(y, dtype=np.float64)
        if y.shape != (m,):
            raise DimensionError(f"y must have shape ({m},) like X's rows; got {y.shape}")
        if not np.all(np.isfinite(y)):
            i = int(np.argmax(~np.isfinite(y)))
            raise InvalidInputError(f"y must be finite; got {y[i]} at index {i}")
        ls = np.asarray(self.lengthscale, dtype=np.float64)
        if ls.ndim == 0:
            ls = np.full(d, float(ls))
        if ls.shape != (d,):
            raise DimensionError(f"lengthscale must be a scalar or have shape ({d},); got {ls.shape}")
        if not np.all(np.isfinite(ls) & (ls > 0)):
            raise InvalidInputError(f"lengthscale must be positive and finite; got {ls}")
        sf2 = _positive_float("signal_variance", self.signal_variance)
        chowdhury = isinstance(self.noise_variance, str)
        if chowdhury:
            if self.noise_variance != CHOWDHURY:
                raise InvalidInputError(
                    f"noise_variance must be a positive float or {CHOWDHURY!r}; got {self.noise_variance!r}"
                )
            lam = chowdhury_regulariser(m)
        else:
            lam = _positive_float("noise_variance", self.noise_variance)
        n_restarts = int(self.n_restarts)
        if n_restarts < 1:
            raise InvalidInputError(f"n_restarts must be >= 1; got {self.n_restarts!r}")

        self.X_train_ = X
        self.y_train_ = y
        s2 = lam
        if self.optimize:
            gen = np.random.default_rng(self.rng)
            sub = np.arange(m)
            if self.max_fit_points is not None:
                k = int(self.max_fit_points)
                if k < 1:
                    raise InvalidInputError(f"max_fit_points must be a positive integer or None; got {k!r}")
                if m > k:
                    sub = np.sort(gen.choice(m, size=k, replace=False))
            ls, sf2, s2, lml = _fit_hyperparameters(X[sub], y[sub], ls, sf2, s2, fit_noise=chowdhury,
                                                     n_restarts=n_restarts, rng=gen)
            if chowdhury:
                # Same ratio lambda/sf2 as the likelihood fit => identical posterior mean
                # (the mean depends on (sf2, lambda) only through their ratio).
                sf2 = sf2 * lam / s2
            self.log_marginal_likelihood_ = lml
        self.lengthscale_ = ls
        self.signal_variance_ = float(sf2)
        self.noise_variance_ = float(lam)
        self.likelihood_noise_variance_ = float(s2)
        K = se_kernel(X, X, ls, self.signal_variance_)
        self.L_, self.jitter_ = _stable_cholesky(K, self.noise_variance_)
        self.alpha_ = scipy.linalg.cho_solve((self.L_, True), y, check_finite=False)
        if not self.optimize:
            self.log_marginal_likelihood_ = float(
                -0.5 * y @ self.alpha_ - np.sum(np.log(np.diag(self.L_))) - 0.5 * m * math.log(2 * math.pi)
            )
        return self

    def predict(self, X: Any, return_std: bool = False):
        """Posterior mean (and std) at test points (eqs. (post-mean), (post-kernel)).

        The std is a floating-point estimate, not a certified bound (``bounds.py``
        certifies it over boxes).

        Parameters
        ----------
        X : (k, d) float array
        return_std : bool

        Returns
        -------
        mean : (k,) float array
        std : (k,) float array, only if ``return_std``
        """
        self._check_fitted()
        X = _as_matrix("X", X, self.X_train_.shape[1])
        Ks = se_kernel(X, self.X_train_, self.lengthscale_, self.signal_variance_)
        mean = Ks @ self.alpha_
        if not return_std:
            return mean
        V = scipy.linalg.solve_triangular(self.L_, Ks.T, lower=True, check_finite=False)
        var = self.signal_variance_ - np.einsum("ij,ij->j", V, V)
        # Negative variances only come from cancellation (the exact value is >= 0).
        return mean, np.sqrt(np.maximum(var, 0.0))

    def information_gain(self) -> float:
        """``1/2 ln det(I + K / lambda')`` from the Cholesky factor, ``lambda' = lambda + jitter``.

        ``ln det(K + lambda' I) = 2 sum_i ln L_ii`` so the gain is
        ``sum_i ln L_ii - (m/2) ln lambda'``. This is the float value; the guaranteed
        path (:meth:`RKHSErrorBound.from_gp`) rounds it up.

        Returns
        -------
        float
        """
        self._check_fitted()
        m = self.L_.shape[0]
        lam = self.noise_variance_ + self.jitter_
        return float(np.sum(np.log(np.diag(self.L_))) - 0.5 * m * math.log(lam))

    def rkhs_norm_of_mean(self) -> float:
        """RKHS norm of the posterior mean w.r.t. this GP's kernel: ``sqrt(alpha^T K alpha)``.

        A diagnostic only: the true function's norm is unknown and can be larger.

        Returns
        -------
        float
        """
        self._check_fitted()
        K = se_kernel(self.X_train_, self.X_train_, self.lengthscale_, self.signal_variance_)
        return float(math.sqrt(max(float(self.alpha_ @ K @ self.alpha_), 0.0)))

    def _check_fitted(self) -> None:
        if not hasattr(self, "alpha_"):
            raise InvalidInputError("GaussianProcess is not fitted; call fit(X, y) first")

    def __repr__(self) -> str:
        if hasattr(self, "alpha_"):
            return (f"GaussianProcess(m={self.X_train_.shape[0]}, lengthscale_={self.lengthscale_}, "
                    f"signal_variance_={self.signal_variance_:.4g}, noise_variance_={self.noise_variance_:.6g}, "
                    f"jitter_={self.jitter_:.2g})")
        return (f"GaussianProcess(lengthscale={self.lengthscale!r}, signal_variance={self.signal_variance!r}, "
                f"noise_variance={self.noise_variance!r}, optimize={self.optimize!r})")


def _stable_cholesky(K: np.ndarray, lam: float) -> tuple[np.ndarray, float]:
    """Lower Cholesky factor of ``K + (lam + jitter) I`` with the smallest jitter that works.

    Returns ``(L, jitter)``; jitter is 0 unless the factorisation of ``K + lam I`` failed.
    """
    m = K.shape[0]
    scale = float(np.mean(np.diag(K))) + lam
    jitter = 0.0
    for _ in range(_JITTER_TRIES):
        A = K.copy()
        A[np.diag_indices(m)] += lam + jitter
        try:
            return scipy.linalg.cholesky(A, lower=True, check_finite=False), jitter
        except np.linalg.LinAlgError:
            jitter = scale * 1e-12 if jitter == 0.0 else jitter * 10.0
    raise ConvergenceError(
        f"Cholesky factorisation of K + (lambda + jitter) I failed up to jitter {jitter:.3g} "
        f"(lambda={lam:.3g}, m={m}); the kernel matrix is numerically indefinite"
    )


# --------------------------------------------------------------------------- likelihood
def _nll_and_grad(theta: np.ndarray, X: np.ndarray, y: np.ndarray, fixed_noise: float | None,
                  sq_dims: np.ndarray) -> tuple[float, np.ndarray]:
    """Negative log marginal likelihood and its gradient in log-parameters.

    ``theta = [ln l_1..ln l_d, ln sf2, (ln s2)]``; ``sq_dims[j]`` = squared differences in dim j.
    NLL = 1/2 y^T a + sum ln L_ii + m/2 ln 2 pi  (Rasmussen & Williams, Alg. 2.1);
    dNLL/dtheta_j = -1/2 tr((a a^T - A^{-1}) dA/dtheta_j)  (R&W eq. 5.9).
    """
    m, d = X.shape
    ls = np.exp(theta[:d])
    sf2 = math.exp(theta[d])
    s2 = fixed_noise if fixed_noise is not None else math.exp(theta[d + 1])
    scaled = sq_dims / (ls * ls)[:, None, None]  # (d, m, m): ((x_i - x_j)/l)^2 per dim
    Kf = sf2 * np.exp(-0.5 * scaled.sum(axis=0))
    A = Kf.copy()
    A[np.diag_indices(m)] += s2
    try:
        L = scipy.linalg.cholesky(A, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        return _FAILED_NLL, np.zeros_like(theta)
    a = scipy.linalg.cho_solve((L, True), y, check_finite=False)
    nll = 0.5 * y @ a + np.sum(np.log(np.diag(L))) + 0.5 * m * math.log(2 * math.pi)
    # A^{-1} from the Cholesky factor (LAPACK potri fills the lower triangle only).
    Ainv, info = scipy.linalg.lapack.dpotri(L, lower=1)
    if info != 0:  # pragma: no cover - L is a valid factor here
        return _FAILED_NLL, np.zeros_like(theta)
    Ainv = np.tril(Ainv) + np.tril(Ainv, -1).T
    W = np.outer(a, a) - Ainv
    grad = np.empty_like(theta)
    WK = W * Kf
    # dK/d ln l_j = K * ((x_i - x_j)/l_j)^2 ; dK/d ln sf2 = K ; dK/d ln s2 = s2 I
    grad[:d] = -0.5 * np.einsum("ij,kij->k", WK, scaled)
    grad[d] = -0.5 * WK.sum()
    if fixed_noise is None:
        grad[d + 1] = -0.5 * s2 * np.trace(W)
    return float(nll), grad


def _fit_hyperparameters(X, y, ls0, sf20, s20, *, fit_noise: bool, n_restarts: int, rng):
    """Maximum marginal likelihood by L-BFGS-B over log-parameters, several seeded starts."""
    m, d = X.shape
    gen = np.random.default_rng(rng)
    sq_dims = np.stack([(X[:, j, None] - X[None, :, j]) ** 2 for j in range(d)])
    span = np.maximum(np.ptp(X, axis=0), 1e-3)
    yvar = max(float(np.var(y)), 1e-12)
    # Bounds on log-parameters keep the optimiser in a numerically sane region.
    bounds = [(math.log(1e-3 * s), math.log(1e2 * s)) for s in span]
    bounds.append((math.log(1e-6 * yvar), math.log(1e6 * yvar + 1e-6)))
    if fit_noise:
        bounds.append((math.log(1e-8 * yvar + 1e-300), math.log(1e2 * yvar + 1e-6)))
    lo = np.array([b[0] for b in bounds])
    hi = np.array([b[1] for b in bounds])
    first = list(np.log(ls0)) + [math.log(sf20)] + ([math.log(min(s20, yvar))] if fit_noise else [])
    starts = [np.clip(np.array(first), lo, hi)]
    for _ in range(n_restarts - 1):
        starts.append(gen.uniform(lo, hi))
    fixed = None if fit_noise else s20
    best = None
    for t0 in starts:
        res = scipy.optimize.minimize(_nll_and_grad, t0, args=(X, y, fixed, sq_dims), jac=True,
                                      method="L-BFGS-B", bounds=bounds)
        if best is None or res.fun < best.fun:
            best = res
    theta = best.x
    ls = np.exp(theta[:d])
    sf2 = math.exp(theta[d])
    s2 = math.exp(theta[d + 1]) if fit_noise else s20
    log.info("GP hyperparameters: lengthscale=%s sf2=%.4g noise=%.4g (-NLL=%.4g)", ls, sf2, s2, -best.fun)
    return ls, sf2, s2, float(-best.fun)
