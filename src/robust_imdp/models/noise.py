"""Additive process-noise models ``v`` with independent components.

Every model is per-dimension: ``v = (v_1, ..., v_d)`` with independent,
zero-mean, symmetric components. The abstraction (Thm 1 of the paper) needs

* ``P[|v_i| <= eta_i]`` as a **lower** bound (:meth:`prob_abs_le`, rounded down);
* a sub-Gaussian parameter ``theta`` for the RKHS error bound (Lemma 1,
  Chowdhury & Gopalan 2017), :meth:`sub_gaussian_parameter`:

  - ``GaussianNoise(sigma)``: ``E exp(l v) = exp(l^2 sigma^2 / 2)`` -> ``theta = sigma``.
  - ``UniformNoise(a)`` on ``[-a, a]``: ``E exp(l v) = sinh(l a)/(l a)
    = sum_k (l a)^{2k}/(2k+1)! <= sum_k (l^2 a^2/6)^k / k! = exp(l^2 a^2 / 6)``
    because ``(2k+1)! >= 6^k k!`` (true for k = 0, 1 and the ratio of consecutive
    terms ``(2k+3)(2k+2) >= 6(k+1)``) -> ``theta = a/sqrt(3)`` (smaller than the
    Hoeffding value ``a``).
  - ``TruncatedGaussianNoise(sigma, a)`` (``N(0, sigma^2)`` conditioned on
    ``|v| <= a``, the paper's case study): ``E exp(l v) = E[cosh(l v) | |v| <= a]``
    by symmetry; ``cosh(l t)`` is increasing in ``|t|`` and ``|v|`` conditioned
    on ``|v| <= a`` is stochastically smaller than ``|v|`` unconditioned, so the
    MGF is at most the Gaussian one ``exp(l^2 sigma^2/2)``; Hoeffding's lemma for
    a zero-mean variable in ``[-a, a]`` gives ``exp(l^2 a^2/2)``. Both hold, so
    ``theta = min(sigma, a)``.

Probabilities of bounded noise at ``eta >= bound`` are exactly 1 and are
returned as 1.0 (no rounding is needed); all other values go through one
rounding helper, :func:`_round_down`.

The exact per-axis transition bounds (``abstraction.marginals``, docs/abstraction.md) need more:
certified lower and upper bounds of ``P[alpha <= v_i <= beta]`` for real ``alpha <= beta``
(:meth:`NoiseModel.interval_prob_lower` / :meth:`NoiseModel.interval_prob_upper`). They use the
standard normal CDF (scipy's ``ndtr``) with an explicit error allowance measured against mpmath
(:func:`ndtr_error`), and ``robust_imdp._fp`` for every other rounding; bounded noise gives exact
0 and 1 where the interval misses or covers the support. Every model here is symmetric with a
density non-increasing in ``|t|`` (symmetric unimodal): the shape the exact bounds rely on.
"""

from __future__ import annotations

import numpy as np
from scipy import special

from robust_imdp._fp import U, down, up
from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["NoiseModel", "GaussianNoise", "TruncatedGaussianNoise", "UniformNoise"]

# Relative error allowance for erf/erfinv/division in float64 (scipy's erf is
# accurate to a few ulps; 1e-13 is ~450 ulps of margin).
_REL = 1e-13
_SQRT2 = np.sqrt(2.0)


def _round_down(p: np.ndarray) -> np.ndarray:
    """Lower bound of a computed probability: shrink by a relative margin, one ulp down.

    The clamp at 0 is safe: every probability is >= 0, so 0 is a valid lower bound.

    Why not ``robust_imdp._fp``: the helpers there move a value by an error bound derived
    operation by operation (``err``, ``gamma_n``). scipy's erf/erfinv come with no such bound,
    only "a few ulps", so the error here is a blanket relative allowance ``_REL`` (~450 ulps)
    that covers the special function, the divisions and the CDF algebra at once. It is the
    only user of that rule.
    """
    p = np.asarray(p, dtype=float)
    return np.maximum(np.nextafter(p * (1.0 - _REL), -np.inf), 0.0)


#: Absolute part of the ``ndtr`` allowance: covers results in (or rounded to) the subnormal range, where a
#: relative bound does not hold (Phi(-37) = 5.7e-300 > 2^-990 = 9.8e-299 / 10 already).
NDTR_ABS = 2.0 ** -990


def ndtr_error(t, value):
    """Allowance ``e`` with ``|ndtr(t) - Phi(t)| <= e`` for the float ``value = scipy.special.ndtr(t)``.

    ``e = (32 + 8 t^2) u value + 2^-990`` (``t^2`` capped at 1600; ``u = 2^-53``). Why this form:
    scipy evaluates ``ndtr(t) = erfc(-t/sqrt 2) / 2``; the rounding of ``t / sqrt 2`` alone moves
    ``erfc`` by a relative ``~t^2 u``. Measured against mpmath at 200 bits on 52,000 points of
    [-39, 39] (``tests/test_marginals.py::test_ndtr_allowance_against_mpmath`` repeats it on a seeded
    sample): at most 5.4 ulp on [-1, 1], 1.45 t^2 ulp on [-20, -1], 1.63 t^2 ulp on [-30, -20]; the
    allowance is 4x to 8x that. Below t = -37.5 the result is subnormal or 0: the absolute term
    ``2^-990 >= Phi(-37)`` covers it (every ``Phi(t)`` there is smaller).
    """
    t = np.asarray(t, dtype=float)
    t2 = np.minimum(np.where(np.isnan(t), 1600.0, t * t), 1600.0)
    return (32.0 + 8.0 * t2) * U * np.abs(value) + NDTR_ABS


def _std_normal_interval(ta, tb, upward: bool):
    """Certified bound of ``P[ta <= Z <= tb]``, ``Z ~ N(0, 1)``, for the exact reals ``ta``, ``tb`` (floats, +-inf ok).

    The difference is formed where it does not cancel: both ends >= 0 as ``Q(ta) - Q(tb)`` (upper
    tails ``Q(t) = ndtr(-t)``), both <= 0 as ``Phi(tb) - Phi(ta)``, else ``1 - Phi(ta) - Q(tb)`` (two
    terms <= 1/2). Error: each ``ndtr`` value within :func:`ndtr_error`, plus the float subtractions
    (``u`` per rounding, relative to the magnitudes); moved outward by ``_fp.down`` / ``_fp.up``.
    Empty intervals (``tb <= ta``) give exactly 0. The clamps to [0, 1] are safe: a probability lies there.
    """
    ta, tb = np.broadcast_arrays(np.asarray(ta, dtype=float), np.asarray(tb, dtype=float))
    right = ta >= 0
    left = ~right & (tb <= 0)
    mid = ~right & ~left
    na, nb = -ta, -tb
    A = special.ndtr(np.where(right, na, ta))  # Q(ta) where right, else Phi(ta)
    B = special.ndtr(np.where(left, tb, nb))  # Phi(tb) where left, else Q(tb)
    eA = ndtr_error(ta, A)
    eB = ndtr_error(tb, B)
    # right: A - B; left: B - A; mid: 1 - (A + B)
    s = A + B
    val = np.where(right, A - B, np.where(left, B - A, 1.0 - s))
    err = eA + eB + np.where(mid, 2.0 * U * (1.0 + s), U * (A + B))
    out = up(val, err) if upward else down(val, err)
    out = np.clip(out, 0.0, 1.0)
    return np.where(tb > ta, out, 0.0)


def _div_bound(x, s, upward: bool):
    """``x / s`` (s > 0) rounded to the safe side (one correctly rounded division, one ulp)."""
    q = x / s
    return np.where(np.isinf(q), q, up(q) if upward else down(q))


def _positive_vector(value, name: str) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.ndim != 1 or arr.size == 0:
        raise DimensionError(f"{name} must be a positive float or a 1-D array of positive floats; got shape {np.shape(value)}")
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise InvalidInputError(f"{name} must be finite and > 0 in every dimension; got {arr.tolist()}")
    arr.setflags(write=False)
    return arr


class NoiseModel:
    """Base class: independent, zero-mean, symmetric components per dimension.

    Subclasses implement ``_cdf_abs(t, i)`` (``P[|v_i| <= t]`` for ``t >= 0``, nearest
    float), ``_abs_quantile(p, i)``, ``_cdf(x, i)`` (``P[v_i <= x]``) and ``_sample``.
    """

    dim: int
    bounded: bool = False

    # -- probabilities -----------------------------------------------------------
    def _check_last_axis(self, arr: np.ndarray, name: str) -> np.ndarray:
        arr = np.asarray(arr, dtype=float)
        if arr.ndim == 0 or arr.shape[-1] != self.dim:
            raise DimensionError(f"{name} must have shape (..., {self.dim}); got {arr.shape}")
        if np.any(np.isnan(arr)):
            raise InvalidInputError(f"{name} must not contain NaN")
        return arr

    def marginal_prob_abs_le(self, eta, i: int) -> np.ndarray:
        """Lower bound of ``P[|v_i| <= eta]`` for any-shaped ``eta`` (component ``i``).

        ``eta < 0`` gives 0 (empty event).
        """
        eta = np.asarray(eta, dtype=float)
        t = np.maximum(eta, 0.0)
        p = _round_down(self._cdf_abs(t, i))
        if self.bounded:
            # exact: the whole mass of v_i lies in [-bound_i, bound_i]
            p = np.where(eta >= self.bound[i], 1.0, p)
        return np.where(eta < 0, 0.0, p)

    def prob_abs_le(self, eta) -> np.ndarray:
        """Lower bounds of ``P[|v_i| <= eta_i]``.

        Parameters
        ----------
        eta : (..., d) float array

        Returns
        -------
        (..., d) float array in [0, 1], rounded down.
        """
        eta = self._check_last_axis(eta, "eta")
        out = np.empty(eta.shape)
        for i in range(self.dim):
            out[..., i] = self.marginal_prob_abs_le(eta[..., i], i)
        return out

    def prob_interval(self, lo, hi) -> np.ndarray:
        """``P[lo_i <= v_i <= hi_i]`` per dimension (nearest float, not a bound).

        Parameters
        ----------
        lo, hi : (..., d) float arrays (``hi < lo`` gives 0)

        Returns
        -------
        (..., d) float array.
        """
        lo = self._check_last_axis(lo, "lo")
        hi = self._check_last_axis(hi, "hi")
        lo, hi = np.broadcast_arrays(lo, hi)
        out = np.empty(lo.shape)
        for i in range(self.dim):
            out[..., i] = np.maximum(self._cdf(hi[..., i], i) - self._cdf(lo[..., i], i), 0.0)
        return out

    def interval_prob_lower(self, alpha, beta, i: int) -> np.ndarray:
        """Certified lower bound of ``P[alpha <= v_i <= beta]`` for the exact reals ``alpha``, ``beta``.

        Parameters
        ----------
        alpha, beta : float arrays (broadcast), +-inf allowed; ``beta <= alpha`` gives 0
            The interval's ends as exact reals: a caller that holds only an enclosure passes the
            inner ends (``alpha`` rounded up, ``beta`` rounded down) for a lower bound.
        i : int
            The component.

        Returns
        -------
        float array in [0, 1]: exactly 0 or 1 where bounded noise's interval misses or covers the support.
        """
        return self._interval_bound(np.asarray(alpha, dtype=float), np.asarray(beta, dtype=float), int(i), False)

    def interval_prob_upper(self, alpha, beta, i: int) -> np.ndarray:
        """Certified upper bound of ``P[alpha <= v_i <= beta]`` (pass the outer ends of an enclosure)."""
        return self._interval_bound(np.asarray(alpha, dtype=float), np.asarray(beta, dtype=float), int(i), True)

    def _interval_bound(self, alpha, beta, i, upward):  # pragma: no cover - abstract
        raise NotImplementedError(f"{type(self).__name__} has no certified interval probabilities: "
                                  "the exact transition bounds need them (docs/extending.md, a new noise model)")

    def wrapped_unimodal(self, period: float, i: int) -> bool:
        """Whether the law of ``v_i`` wrapped onto a circle of ``period`` is symmetric unimodal (docs/abstraction.md).

        Gaussian: always (Jacobi's triple product writes the wrapped density as a product of positive
        factors, each non-increasing in the circular distance). Bounded noise: when ``bound <= period/2``
        (then only one copy of the density meets the circle's half-period around 0).
        """
        if self.bounded:
            return bool(self.bound[i] <= 0.5 * period)
        return isinstance(self, GaussianNoise)

    def listing_radius(self, tol: float) -> np.ndarray:
        """``(d,)`` radii ``R_i`` with ``P[|v_i| > R_i] <= tol`` (about; a listing choice, not a bound).

        Bounded noise: slightly more than the bound, so that nothing beyond it is left unlisted.
        """
        if self.bounded:
            return np.asarray(self.bound, dtype=float) * (1.0 + 1e-9)
        return self.abs_quantile(1.0 - float(tol))

    def abs_quantile(self, p) -> np.ndarray:
        """Smallest ``t_i`` with ``P[|v_i| <= t_i] = p`` per dimension (nearest float).

        Parameters
        ----------
        p : float or (...,) array in [0, 1)

        Returns
        -------
        (..., d) float array.
        """
        p = np.asarray(p, dtype=float)
        if np.any(~((p >= 0) & (p < 1))) and not self.bounded:
            raise InvalidInputError(f"p must lie in [0, 1) for unbounded noise; got {p}")
        if np.any(~((p >= 0) & (p <= 1))):
            raise InvalidInputError(f"p must lie in [0, 1]; got {p}")
        return np.stack([self._abs_quantile(p, i) for i in range(self.dim)], axis=-1)

    def default_eta(self) -> np.ndarray:
        """``(d,)``: the bound of bounded noise, else the 0.99 quantile of ``|v_i|``."""
        if self.bounded:
            return np.array(self.bound, dtype=float)
        return self.abs_quantile(0.99)

    def sample(self, k: int, rng=None) -> np.ndarray:
        """``(k, d)`` independent samples; ``rng`` is anything ``np.random.default_rng`` accepts."""
        if int(k) != k or k < 0:
            raise InvalidInputError(f"k must be a non-negative integer; got {k!r}")
        return self._sample(int(k), np.random.default_rng(rng))

    def sub_gaussian_parameter(self) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError


class GaussianNoise(NoiseModel):
    """``v_i ~ N(0, sigma_i^2)`` independent.

    Parameters
    ----------
    sigma : float or (d,) float array, > 0
    """

    def __init__(self, sigma):
        self.sigma = _positive_vector(sigma, "sigma")
        self.dim = self.sigma.size

    def _cdf_abs(self, t, i):
        return special.erf(t / (self.sigma[i] * _SQRT2))

    def _cdf(self, x, i):
        return special.ndtr(x / self.sigma[i])

    def _abs_quantile(self, p, i):
        return self.sigma[i] * _SQRT2 * special.erfinv(p)

    def _interval_bound(self, alpha, beta, i, upward):
        # P[alpha <= v <= beta] = P[alpha/s <= Z <= beta/s]: the standardised ends rounded outward
        # (upper bound) or inward (lower bound), then the standard normal interval
        s = self.sigma[i]
        return _std_normal_interval(_div_bound(alpha, s, not upward), _div_bound(beta, s, upward), upward)

    def _sample(self, k, rng):
        return rng.standard_normal((k, self.dim)) * self.sigma

    def sub_gaussian_parameter(self) -> np.ndarray:
        """``(d,)``: ``sigma`` (the Gaussian MGF is exactly ``exp(l^2 sigma^2/2)``)."""
        return np.array(self.sigma)

    def __repr__(self):
        return f"GaussianNoise(sigma={self.sigma.tolist()})"


class TruncatedGaussianNoise(NoiseModel):
    """``v_i ~ N(0, sigma_i^2)`` conditioned on ``|v_i| <= bound_i``, independent.

    Parameters
    ----------
    sigma, bound : float or (d,) float arrays, > 0 (a scalar broadcasts to the other's length)
    """

    bounded = True

    def __init__(self, sigma, bound):
        s = _positive_vector(sigma, "sigma")
        b = _positive_vector(bound, "bound")
        if s.size != b.size and 1 not in (s.size, b.size):
            raise DimensionError(f"sigma and bound must have the same length; got {s.size} and {b.size}")
        s, b = np.broadcast_arrays(s, b)
        self.sigma, self.bound = np.array(s), np.array(b)
        self.sigma.setflags(write=False)
        self.bound.setflags(write=False)
        self.dim = self.sigma.size
        self._z = special.erf(self.bound / (self.sigma * _SQRT2))  # P[|N(0,s^2)| <= a]

    def _cdf_abs(self, t, i):
        t = np.minimum(t, self.bound[i])
        return special.erf(t / (self.sigma[i] * _SQRT2)) / self._z[i]

    def _cdf(self, x, i):
        x = np.clip(x, -self.bound[i], self.bound[i])
        # P[v <= x] = (Phi(x/s) - Phi(-a/s)) / (Phi(a/s) - Phi(-a/s)) = (1 + erf-part)/2 by symmetry
        return 0.5 + 0.5 * special.erf(x / (self.sigma[i] * _SQRT2)) / self._z[i]

    def _abs_quantile(self, p, i):
        return np.minimum(self.sigma[i] * _SQRT2 * special.erfinv(p * self._z[i]), self.bound[i])

    def _interval_bound(self, alpha, beta, i, upward):
        # P[alpha <= v <= beta] = P_N[max(alpha, -c) <= N <= min(beta, c)] / P_N[|N| <= c], N ~ N(0, s^2):
        # the numerator bounded like GaussianNoise's, the normaliser Z the other way, one division
        s, c = self.sigma[i], self.bound[i]
        lo, hi = np.maximum(alpha, -c), np.minimum(beta, c)  # exact (no rounding)
        num = _std_normal_interval(_div_bound(lo, s, not upward), _div_bound(hi, s, upward), upward)
        # the normaliser the other way: an upper bound of P divides by a lower bound of Z (c/s rounded
        # down), a lower bound of P by an upper bound of Z (c/s rounded up)
        tc = _div_bound(c, s, not upward)
        z = _std_normal_interval(-tc, tc, not upward)
        val = up(num / z) if upward else down(num / z)
        val = np.clip(val, 0.0, 1.0)  # safe: a probability lies in [0, 1]
        # exact where the interval misses the support (0) or covers it (1)
        return np.where(hi <= lo, 0.0, np.where((alpha <= -c) & (beta >= c), 1.0, val))

    def _sample(self, k, rng):
        # inverse CDF of |v| with a random sign (the law is symmetric)
        u = rng.random((k, self.dim))
        sign = np.where(rng.random((k, self.dim)) < 0.5, -1.0, 1.0)
        mag = self.sigma * _SQRT2 * special.erfinv(u * self._z)
        return sign * np.minimum(mag, self.bound)

    def sub_gaussian_parameter(self) -> np.ndarray:
        """``(d,)``: ``min(sigma, bound)`` (see the module docstring for the proof)."""
        return np.minimum(self.sigma, self.bound)

    def __repr__(self):
        return f"TruncatedGaussianNoise(sigma={self.sigma.tolist()}, bound={self.bound.tolist()})"


class UniformNoise(NoiseModel):
    """``v_i ~ U[-bound_i, bound_i]`` independent.

    Parameters
    ----------
    bound : float or (d,) float array, > 0
    """

    bounded = True

    def __init__(self, bound):
        self.bound = _positive_vector(bound, "bound")
        self.dim = self.bound.size

    def _cdf_abs(self, t, i):
        return np.minimum(t / self.bound[i], 1.0)

    def _cdf(self, x, i):
        return np.clip((x + self.bound[i]) / (2 * self.bound[i]), 0.0, 1.0)

    def _abs_quantile(self, p, i):
        return p * self.bound[i]

    def _interval_bound(self, alpha, beta, i, upward):
        # P[alpha <= v <= beta] = (min(beta, c) - max(alpha, -c)) / (2c): two correctly rounded
        # operations, each moved one ulp to the safe side (2c = c + c is exact)
        c = self.bound[i]
        lo, hi = np.maximum(alpha, -c), np.minimum(beta, c)
        if upward:
            val = up(up(hi - lo) / (2.0 * c))
        else:
            val = down(down(hi - lo) / (2.0 * c))
        val = np.clip(val, 0.0, 1.0)  # safe: a probability lies in [0, 1]
        return np.where(hi <= lo, 0.0, np.where((alpha <= -c) & (beta >= c), 1.0, val))

    def _sample(self, k, rng):
        return rng.uniform(-1.0, 1.0, (k, self.dim)) * self.bound

    def sub_gaussian_parameter(self) -> np.ndarray:
        """``(d,)``: ``bound/sqrt(3)`` (``sinh(x)/x <= exp(x^2/6)``, module docstring)."""
        return self.bound / np.sqrt(3.0)

    def __repr__(self):
        return f"UniformNoise(bound={self.bound.tolist()})"
