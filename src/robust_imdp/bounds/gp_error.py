"""The RKHS error bound of the GP route: Chowdhury & Gopalan (2017, Thm 2) for a fitted GP.

:class:`RKHSErrorBound` gives ``beta(delta)``, its inverse ``delta(eps, std_upper)`` and
``prob_within(eps, std_upper)``, which is what the abstraction needs per (mode, cell, output
dimension); the information gain ``gamma`` comes from the GP's Cholesky factor with a rigorous
floating-point margin (``_info_gain_upper``) or from Hadamard's inequality
(:func:`trivial_info_gain`). Every bound is rounded outward with ``robust_imdp._fp``; the
public names are re-exported by ``bounds.gp``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from robust_imdp import _fp
from robust_imdp.bounds.gp_model import GaussianProcess, _positive_float, chowdhury_regulariser
from robust_imdp.errors import AssumptionWarning, InvalidInputError

_EPS = np.finfo(float).eps

# --------------------------------------------------------------------------- error bound
def _info_gain_upper(gp: GaussianProcess) -> float:
    """Rigorous upper bound of the data's ``1/2 ln det(I + K / lambda)`` from ``gp.L_``.

    Floating-point Cholesky gives ``L L^T = A + E`` with ``|E| <= g_{m+1} |L| |L^T|``
    (Higham, *Accuracy and Stability*, Thm 10.3, ``g_k = k u / (1 - k u)``), hence
    ``||E||_2 <= ||E||_F <= g_{m+1} tr(L L^T) = g_{m+1} tr(A + E)`` and
    ``|ln det(A + E) - ln det A| <= m ||E||_2 / (lambda_min(A) - ||E||_2)`` with
    ``lambda_min(A) >= lambda``. Add that, plus the rounding of the sum of ``m`` logs.
    """
    m = gp.L_.shape[0]
    lam = gp.noise_variance_ + gp.jitter_
    logs = np.log(np.diag(gp.L_))
    value = float(np.sum(logs)) - 0.5 * m * math.log(lam)
    u = _EPS / 2
    g = (m + 1) * u / (1 - (m + 1) * u)
    trace = float(np.sum(gp.L_ * gp.L_))  # ||L||_F^2 = tr(L L^T)
    e_norm = g * trace * (1 + (m * m + 4) * _EPS)  # (+ rounding of the sum of m^2 squares)
    if e_norm >= 0.5 * lam:  # pragma: no cover - only for absurdly ill-scaled kernels
        return math.inf
    margin = 0.5 * m * e_norm / (lam - e_norm)
    margin += 4 * (m + 2) * _EPS * (float(np.sum(np.abs(logs))) + 0.5 * m * abs(math.log(lam)) + 1.0)
    return float(_fp.up(value + margin))


def trivial_info_gain(n_samples: int, signal_variance: float, regulariser: float) -> float:
    """``1/2 m ln(1 + sf2 / lambda)``, an upper bound of ``1/2 ln det(I + K / lambda)`` for ANY m points.

    Hadamard's inequality for the positive-definite ``I + K / lambda``:
    ``det(I + K/lambda) <= prod_i (1 + K_ii / lambda) = (1 + sf2/lambda)^m`` since
    ``K_ii = k(x_i, x_i) = sf2``. Rounded up.
    """
    m = int(n_samples)
    sf2 = _positive_float("signal_variance", signal_variance)
    lam = _positive_float("regulariser", regulariser)
    # log1p is accurate to a few ulps; (1 + 8 eps) covers it and the two products.
    return float(_fp.up(0.5 * m * math.log1p(sf2 / lam) * (1 + 8 * _EPS)))


@dataclass(frozen=True)
class RKHSErrorBound:
    r"""Uniform error bound ``|g(x) - mu(x)| <= beta(delta) sigma(x)`` for all x, w.p. >= 1 - delta.

    Chowdhury & Gopalan (2017), "On kernelized multi-armed bandits", ICML, Thm 2, in
    the form derived below (which is what this class implements).

    Parameters
    ----------
    rkhs_bound : float
        ``B >= ||g||_k`` w.r.t. the kernel ``k = sf2 * k0`` **the GP uses** (an assumption
        of the user, never estimated). A bound ``B0`` on ``||g||_{k0}`` for the
        unit-amplitude kernel ``k0`` (``k0(x, x) = 1``, same lengthscales) gives
        ``B = B0 / sqrt(sf2)``: the RKHS of ``sf2 k0`` has the same functions and norm
        ``||h||_{sf2 k0} = ||h||_{k0} / sqrt(sf2)`` (:meth:`from_gp` does this).
    sub_gaussian : float
        ``theta``: the noise is conditionally theta-sub-Gaussian,
        ``E[exp(s v_i) | past] <= exp(s^2 theta^2 / 2)`` for all real s.
    regulariser : float
        ``lambda`` on the diagonal of K in the posterior; the "+1" form below needs
        ``1 < lambda`` and ``(m/2) ln lambda <= 1``, e.g. C&G's ``lambda = 1 + 2/m``.
    info_gain : float
        ``gamma >= 1/2 ln det(I + K / lambda)`` for the training inputs of the GP.
    n_samples : int
        ``m``, the number of training points.

    Notes
    -----
    **Derivation.** Let ``H`` be the RKHS of ``k``, ``Phi: H -> R^m``, ``Phi h = (h(x_i))_i``,
    ``V = Phi* Phi + lambda I``. The posterior mean is the kernel-ridge solution
    ``mu = V^{-1} Phi* y`` and, by Woodbury, ``<k_x, V^{-1} k_x> = sigma^2(x) / lambda``
    (``sigma^2`` = eq. (post-kernel) with regulariser lambda). With ``y = Phi g + v``::

        g - mu = lambda V^{-1} g - V^{-1} Phi* v
        |<k_x, lambda V^{-1} g>| <= lambda ||V^{-1/2} k_x|| ||V^{-1/2} g||
                                 <= lambda (sigma/sqrt(lambda)) (B/sqrt(lambda)) = B sigma(x)
        |<k_x, V^{-1} Phi* v>|   <= (sigma(x)/sqrt(lambda)) sqrt(v^T K (K + lambda I)^{-1} v)

    C&G Thm 1 (self-normalised bound, method of mixtures; needs only predictable inputs
    and conditionally theta-sub-Gaussian noise, no kernel normalisation) gives for
    ``eta > 0``, w.p. >= 1 - delta,
    ``v^T (K + eta I)(K + (1+eta) I)^{-1} v <= 2 theta^2 ln(sqrt(det((1+eta) I + K)) / delta)``.
    With ``lambda = 1 + eta`` the left side dominates ``v^T K (K + lambda I)^{-1} v``
    (eigenwise ``k/(k+lambda) <= (k+eta)/(k+lambda)``) and
    ``ln det(lambda I + K) = 2 * 1/2 ln det(I + K/lambda) + m ln lambda <= 2 gamma + 2`` when
    ``(m/2) ln lambda <= 1`` (true for ``lambda = 1 + 2/m``). Hence, for all x at once::

        beta(delta) = B + (theta / sqrt(lambda)) * sqrt(2 (gamma + 1 + ln(1/delta)))

    This is C&G's printed constant ``B + theta sqrt(2(gamma + 1 + ln 1/delta))`` with the
    noise term tightened by ``1/sqrt(lambda) < 1``.

    **The paper's form is not used.** Jackson et al. (2021, Lemma 1) print
    ``beta = (theta/sqrt(lambda)) (B + theta sqrt(2(gamma + 1 + ln 1/delta)))``. It is
    dimensionally inconsistent (``theta * B`` has the units of ``g`` squared) and unsound
    (Monte Carlo in ``tests/test_gp.py``: it fails on 82/200 data sets at delta = 0.1 for
    theta = 0.3, on 200/200 for theta = 0.01). With one training point far away, ``mu ~ 0`` and
    ``sigma ~ sqrt(k(x0, x0))`` near ``x0``, and ``g = B k(., x0) / sqrt(k(x0, x0))`` (norm B)
    has ``|g(x0) - mu(x0)| ~ B sigma(x0)``, while the paper's beta gives about
    ``(theta/sqrt(lambda)) (B + theta sqrt(...)) sigma`` -- violated with probability 1
    whenever that factor is below ``B``, e.g. for theta = 0.01
    (``tests/test_gp.py`` checks this counterexample). The ``B`` term cannot carry any
    factor below 1: without data the bound must reduce to ``|g(x)| <= B sqrt(k(x, x))``.

    **gamma.** C&G's ``gamma_T`` is the maximum information gain over all T-point sets;
    they use it only to replace the data-dependent ``ln det((1+eta) I + K_t)`` of Thm 1
    by a deterministic constant. Thm 1 itself holds with the *realised* inputs, so two
    valid choices are offered: ``"data"`` -- the data's own ``1/2 ln det(I + K/lambda)``
    (from the Cholesky factor, rounded up with a rigorous floating-point margin; no
    extra assumption), and ``"trivial"`` -- ``1/2 m ln(1 + sf2/lambda)``, an upper bound of
    the gain of ANY m-point set by Hadamard's inequality (hence also of C&G's
    ``gamma_m``). ``"data"`` is never larger than ``"trivial"`` (we take the minimum).

    **Several GPs.** Each bound is for one (mode, output dimension). The event is uniform
    in x, so one event serves every cell of that GP. For several output dimensions (or
    modes) at once, combine by the union bound ``1 - sum_i delta_i``; a product of the
    probabilities needs independence of the events (true for inputs sampled independently
    of the noise with independent noise components, false for trajectory data).

    **Assumptions that remain the user's.** ``||g||_k <= B`` (not checkable from data;
    :func:`rkhs_norm_of_mean` is only a diagnostic, and ``sup|g| / sqrt(min k)`` is NOT a
    bound of the RKHS norm); the noise is conditionally theta-sub-Gaussian and the
    inputs do not depend on future noise; the kernel (lengthscale, sf2) is fixed
    independently of the noise in the data -- hyperparameters fitted by marginal
    likelihood on the same data are outside the theorem (common practice; for a strict
    guarantee fit them on separate data or fix them beforehand).
    """

    rkhs_bound: float
    sub_gaussian: float
    regulariser: float
    info_gain: float
    n_samples: int

    def __post_init__(self) -> None:
        B = _positive_float("rkhs_bound", self.rkhs_bound)
        theta = _positive_float("sub_gaussian", self.sub_gaussian)
        lam = _positive_float("regulariser", self.regulariser)
        m = self.n_samples
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 1:
            raise InvalidInputError(f"n_samples must be a positive integer; got {m!r}")
        g = float(self.info_gain)
        if not (np.isfinite(g) and g >= 0):
            raise InvalidInputError(f"info_gain must be a finite float >= 0; got {self.info_gain!r}")
        # The "+1" term of beta needs ln det(lambda I + K) <= 2 gamma + 2, i.e. (m/2) ln lambda <= 1.
        if not (lam > 1.0 and 0.5 * int(m) * math.log(lam) <= 1.0):
            raise InvalidInputError(
                f"regulariser must satisfy 1 < lambda and (m/2) ln lambda <= 1 (e.g. lambda = 1 + 2/m "
                f"= {chowdhury_regulariser(m)!r} for m = {m}); got lambda = {self.regulariser!r}"
            )
        for name, v in (("rkhs_bound", B), ("sub_gaussian", theta), ("regulariser", lam), ("info_gain", g)):
            object.__setattr__(self, name, v)
        object.__setattr__(self, "n_samples", int(m))

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_gp(cls, gp: GaussianProcess, rkhs_bound: float, sub_gaussian: float, *,
                info_gain: str = "data") -> "RKHSErrorBound":
        """Error bound for a fitted GP, refusing GPs the lemma does not cover.

        Parameters
        ----------
        gp : GaussianProcess
            Fitted with ``noise_variance="chowdhury"`` (``noise_variance_ == 1 + 2/m``) and
            no jitter; otherwise :class:`~robust_imdp.errors.InvalidInputError`.
        rkhs_bound : float
            ``B0 >= ||g||_{k0}`` for the UNIT-amplitude SE kernel with ``gp.lengthscale_``;
            the bound stores ``B = B0 / sqrt(sf2)`` (rounded up), the norm w.r.t. ``gp``'s kernel.
        sub_gaussian : float
            theta of the noise in this output dimension.
        info_gain : {"data", "trivial"}
            Which gamma to use (see the class notes).

        Returns
        -------
        RKHSErrorBound
        """
        if not isinstance(gp, GaussianProcess) or not hasattr(gp, "alpha_"):
            raise InvalidInputError(f"gp must be a fitted GaussianProcess; got {gp!r}")
        m = gp.X_train_.shape[0]
        required = chowdhury_regulariser(m)
        if gp.noise_variance_ != required:
            raise InvalidInputError(
                f"gp.noise_variance_ must be lambda = 1 + 2/m = {required!r} (m = {m}) for the RKHS error "
                f"bound (Chowdhury & Gopalan 2017, Thm 2); got {gp.noise_variance_!r}. Refit with "
                f"noise_variance='chowdhury'"
            )
        if gp.jitter_ != 0.0:
            raise InvalidInputError(
                f"gp.jitter_ must be 0 for the RKHS error bound (the posterior must use exactly lambda); "
                f"got {gp.jitter_!r}"
            )
        B0 = _positive_float("rkhs_bound", rkhs_bound)
        sf2 = gp.signal_variance_
        B = float(_fp.up(B0 / math.sqrt(sf2) * (1 + 4 * _EPS)))
        trivial = trivial_info_gain(m, sf2, required)
        if info_gain == "data":
            gamma = min(_info_gain_upper(gp), trivial)
        elif info_gain == "trivial":
            gamma = trivial
        else:
            raise InvalidInputError(f"info_gain must be 'data' or 'trivial'; got {info_gain!r}")
        norm_mean = rkhs_norm_of_mean(gp)
        if B < norm_mean:
            warnings.warn(
                f"rkhs_bound B0 = {B0:.4g} (B = {B:.4g} w.r.t. the GP's kernel) is below the RKHS norm "
                f"{norm_mean:.4g} of the posterior mean (= {norm_mean * math.sqrt(sf2):.4g} in B0 units); "
                f"the assumption ||g|| <= B looks doubtful",
                AssumptionWarning,
                stacklevel=2,
            )
        bound = cls(B, float(sub_gaussian), required, gamma, m)
        bound.check_gp(gp)
        return bound

    def check_gp(self, gp: GaussianProcess) -> None:
        """Raise unless ``gp``'s posterior is the one this bound is about (same lambda, m, no jitter).

        Consumers that take a GP and a bound separately call this before pairing them.
        """
        if not hasattr(gp, "alpha_"):
            raise InvalidInputError(f"gp must be a fitted GaussianProcess; got {gp!r}")
        m = gp.X_train_.shape[0]
        if m != self.n_samples or gp.noise_variance_ != self.regulariser or gp.jitter_ != 0.0:
            raise InvalidInputError(
                f"gp must have m = {self.n_samples} samples, noise_variance_ = {self.regulariser!r} and no jitter "
                f"to use this error bound; got m = {m}, noise_variance_ = {gp.noise_variance_!r}, "
                f"jitter_ = {gp.jitter_!r}"
            )

    # ------------------------------------------------------------------ the bound
    @property
    def _noise_factor_up(self) -> float:
        """Upper bound of ``theta / sqrt(lambda)`` (sqrt, division correctly rounded: +2 ulp)."""
        return float(_fp.up(_fp.up(self.sub_gaussian / math.sqrt(self.regulariser)) * (1 + 2 * _EPS)))

    def beta(self, delta: Any) -> np.ndarray:
        """``beta(delta) = B + (theta/sqrt(lambda)) sqrt(2 (gamma + 1 + ln 1/delta))``, rounded up.

        Parameters
        ----------
        delta : float or array, each in (0, 1]

        Returns
        -------
        float array of delta's shape
        """
        d = np.asarray(delta, dtype=np.float64)
        if not np.all((d > 0) & (d <= 1)):
            raise InvalidInputError(f"delta must lie in (0, 1]; got {d[~((d > 0) & (d <= 1))].ravel()[:3]}")
        # log is accurate to a few ulps; the relative margin 16 eps on the sum of positive
        # terms covers it, the additions, the products and the sqrt.
        inner = 2.0 * (self.info_gain + 1.0 - np.log(d))
        beta = self.rkhs_bound + self._noise_factor_up * np.sqrt(inner)
        return _fp.up(beta * (1 + 16 * _EPS))

    def delta(self, eps: Any, std_upper: Any) -> np.ndarray:
        """Smallest delta with ``beta(delta) * std_upper <= eps``, rounded up (log space).

        ``beta(delta) s <= eps  <=>  ln(1/delta) <= q - gamma - 1`` with
        ``q = ((eps/s - B) / (theta/sqrt(lambda)))^2 / 2`` (when ``eps/s > B``), so
        ``delta = exp(-(q - gamma - 1))``; q is computed rounded down step by step, so the
        exponent is a lower bound and delta an upper bound of the exact value.

        Parameters
        ----------
        eps : float or array, >= 0
        std_upper : float or array, >= 0 (an upper bound of sigma over the cell)

        Returns
        -------
        float array (broadcast shape), in [0, 1]
        """
        e = np.asarray(eps, dtype=np.float64)
        s = np.asarray(std_upper, dtype=np.float64)
        if not np.all(np.isfinite(e) & (e >= 0)):
            raise InvalidInputError(f"eps must be finite and >= 0; got {e[~(np.isfinite(e) & (e >= 0))].ravel()[:3]}")
        if not np.all(np.isfinite(s) & (s >= 0)):
            raise InvalidInputError(
                f"std_upper must be finite and >= 0; got {s[~(np.isfinite(s) & (s >= 0))].ravel()[:3]}")
        e, s = np.broadcast_arrays(e, s)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ratio = _fp.down(e / s)  # inf where s == 0 < e
            t = _fp.down(ratio - self.rkhs_bound)
            t = _fp.down(t / self._noise_factor_up)
            q = _fp.down(_fp.down(t * t) * 0.5)
            expo = _fp.down(_fp.down(q - self.info_gain) - 1.0)
            # exp has a few ulps of error: (1 + 8 eps) and one more ulp make it an upper bound.
            dl = _fp.up(np.exp(-expo) * (1 + 8 * _EPS))
        # Clamp to [0, 1]: delta >= 1 (no delta in (0,1) works, incl. eps/s <= B) means the
        # vacuous statement P >= 0, which is always true -- safe. s == 0: beta*0 <= eps for
        # every delta > 0, so P[...] >= 1 - delta for all delta, i.e. delta = 0 -- exact.
        dl = np.where(t > 0, np.minimum(dl, 1.0), 1.0)
        dl = np.where(s == 0, 0.0, dl)
        return dl

    def prob_within(self, eps: Any, std_upper: Any) -> np.ndarray:
        """Lower bound of ``P[sup_cell |g - mu| <= eps]``: ``1 - delta(eps, std_upper)``, rounded down.

        Parameters
        ----------
        eps : float or array, >= 0
        std_upper : float or array, >= 0 (upper bound of the posterior std over the cell)

        Returns
        -------
        float array (broadcast shape), in [0, 1]
        """
        dl = self.delta(eps, std_upper)
        # 1 - dl is rounded to nearest; stepping down makes it a lower bound. Clamp at 0 is
        # safe: a probability is never negative (and 1 - dl >= 0 already since dl <= 1).
        return np.maximum(np.where(dl == 0.0, 1.0, _fp.down(1.0 - dl)), 0.0)

    def eps_for_prob(self, p: Any, std_upper: Any) -> np.ndarray:
        """Paper's rule: ``eps = beta(1 - p) * std_upper`` (e.g. p = 0.99), rounded up.

        Parameters
        ----------
        p : float or array in [0, 1)
        std_upper : float or array, >= 0

        Returns
        -------
        float array (broadcast shape)
        """
        p = np.asarray(p, dtype=np.float64)
        if not np.all((p >= 0) & (p < 1)):
            raise InvalidInputError(f"p must lie in [0, 1); got {p[~((p >= 0) & (p < 1))].ravel()[:3]}")
        s = np.asarray(std_upper, dtype=np.float64)
        if not np.all(np.isfinite(s) & (s >= 0)):
            raise InvalidInputError(
                f"std_upper must be finite and >= 0; got {s[~(np.isfinite(s) & (s >= 0))].ravel()[:3]}")
        # 1 - p rounded down makes delta smaller, beta larger: the safe side.
        return _fp.up(self.beta(np.maximum(_fp.down(1.0 - p), np.finfo(float).tiny)) * s)


def rkhs_norm_of_mean(gp: GaussianProcess) -> float:
    """``sqrt(alpha^T K alpha)``: RKHS norm of the posterior mean w.r.t. ``gp``'s kernel (diagnostic).

    Not a bound of ``||g||``: the mean can be rougher or smoother than g.
    """
    return gp.rkhs_norm_of_mean()
