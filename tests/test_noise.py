"""Tests of robust_imdp.models.noise: probabilities vs closed forms and Monte Carlo, moments, validation."""

import numpy as np
import pytest
from scipy import integrate, stats

from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.models.noise import GaussianNoise, TruncatedGaussianNoise, UniformNoise

MODELS = [
    GaussianNoise([0.1, 0.3]),
    TruncatedGaussianNoise([0.1, 0.2], [0.15, 0.1]),
    UniformNoise([0.2, 0.05]),
]
N_MC = 200_000
# binomial standard error of a frequency <= sqrt(0.25 / N_MC) = 1.1e-3; we allow 5 standard
# errors (two-sided failure probability 6e-7 per comparison)
MC_TOL = 5 * np.sqrt(0.25 / N_MC)


@pytest.mark.parametrize("noise", MODELS, ids=lambda m: type(m).__name__)
def test_prob_abs_le_matches_monte_carlo_and_is_a_lower_bound(noise):
    rng = np.random.default_rng(1)
    v = noise.sample(N_MC, rng)
    for eta in ([0.02, 0.05], [0.1, 0.2], [0.3, 0.01]):
        p = noise.prob_abs_le(eta)
        freq = (np.abs(v) <= eta).mean(axis=0)
        np.testing.assert_allclose(p, freq, atol=MC_TOL)
        assert np.all((p >= 0) & (p <= 1))


def test_prob_abs_le_closed_forms_rounded_down():
    g = GaussianNoise([0.1])
    exact = stats.norm.cdf(0.15 / 0.1) - stats.norm.cdf(-0.15 / 0.1)
    p = g.prob_abs_le([0.15])[0]
    assert p <= exact and exact - p < 1e-12  # rounded down by ~1e-13 relative
    t = TruncatedGaussianNoise([0.1], [0.2])
    # P[|v| <= 0.1 | |v| <= 0.2] = (2 Phi(1) - 1) / (2 Phi(2) - 1)
    exact_t = (2 * stats.norm.cdf(1.0) - 1) / (2 * stats.norm.cdf(2.0) - 1)
    pt = t.prob_abs_le([0.1])[0]
    assert pt <= exact_t and exact_t - pt < 1e-12
    # bounded noise: eta at or above the bound is exactly probability 1 (no rounding loss)
    assert t.prob_abs_le([0.2])[0] == 1.0 and UniformNoise([0.3]).prob_abs_le([0.5])[0] == 1.0
    assert UniformNoise([0.4]).prob_abs_le([0.1])[0] <= 0.25
    assert g.prob_abs_le([-1.0])[0] == 0.0  # empty event


@pytest.mark.parametrize("noise", MODELS, ids=lambda m: type(m).__name__)
def test_prob_interval_matches_monte_carlo(noise):
    rng = np.random.default_rng(2)
    v = noise.sample(N_MC, rng)
    lo, hi = np.array([-0.05, 0.01]), np.array([0.12, 0.04])
    freq = ((v >= lo) & (v <= hi)).mean(axis=0)
    np.testing.assert_allclose(noise.prob_interval(lo, hi), freq, atol=MC_TOL)


@pytest.mark.parametrize("noise", MODELS, ids=lambda m: type(m).__name__)
def test_sampling_moments(noise):
    v = noise.sample(N_MC, np.random.default_rng(3))
    assert v.shape == (N_MC, 2)
    var = [integrate.quad(lambda x, i=i: x**2 * _density(noise, i, x), -1, 1, points=[0])[0] for i in range(2)]
    # mean 0 within 5 standard errors sqrt(var / N); variance within 5 % (kurtosis <= 3 here)
    assert np.all(np.abs(v.mean(axis=0)) <= 5 * np.sqrt(np.array(var) / N_MC))
    np.testing.assert_allclose(v.var(axis=0), var, rtol=0.05)


def _density(noise, i, x):
    if isinstance(noise, GaussianNoise):
        return stats.norm.pdf(x, scale=noise.sigma[i])
    if isinstance(noise, TruncatedGaussianNoise):
        a, s = noise.bound[i], noise.sigma[i]
        return stats.truncnorm.pdf(x, -a / s, a / s, scale=s)
    a = noise.bound[i]
    return (abs(x) <= a) / (2 * a)


def test_abs_quantile_and_default_eta():
    g = GaussianNoise([0.1, 0.2])
    np.testing.assert_allclose(g.default_eta(), np.array([0.1, 0.2]) * stats.norm.ppf(0.995), rtol=1e-12)
    np.testing.assert_allclose(g.prob_abs_le(g.default_eta()), 0.99, rtol=1e-12)
    t = TruncatedGaussianNoise([0.01, 0.01], [0.01, 0.02])
    np.testing.assert_array_equal(t.default_eta(), [0.01, 0.02])  # bound of bounded noise
    q = t.abs_quantile(0.5)
    np.testing.assert_allclose(t.prob_abs_le(q), 0.5, rtol=1e-10)
    with pytest.raises(InvalidInputError, match="p must lie"):
        g.abs_quantile(1.0)


def test_sub_gaussian_parameters():
    np.testing.assert_array_equal(GaussianNoise([0.3]).sub_gaussian_parameter(), [0.3])
    np.testing.assert_allclose(UniformNoise([0.3]).sub_gaussian_parameter(), [0.3 / np.sqrt(3)])
    np.testing.assert_array_equal(TruncatedGaussianNoise([0.1, 0.5], [0.2, 0.2]).sub_gaussian_parameter(), [0.1, 0.2])
    # check the MGF inequality E exp(l v) <= exp(l^2 theta^2 / 2) numerically on a grid of l
    for noise in (UniformNoise([0.3]), TruncatedGaussianNoise([0.1], [0.05]), TruncatedGaussianNoise([0.1], [0.5])):
        th = noise.sub_gaussian_parameter()[0]
        for lam in (0.1, 1.0, 10.0, 50.0, 200.0):
            mgf = integrate.quad(lambda x: np.exp(lam * x) * _density(noise, 0, x), -1, 1, points=[0], limit=200)[0]
            assert mgf <= np.exp(lam**2 * th**2 / 2) * (1 + 1e-9)


def test_validation_messages():
    with pytest.raises(InvalidInputError, match="sigma must be finite and > 0"):
        GaussianNoise([0.1, 0.0])
    with pytest.raises(InvalidInputError, match="bound must be finite and > 0"):
        TruncatedGaussianNoise(0.1, -1.0)
    with pytest.raises(InvalidInputError, match="bound must be finite and > 0"):
        UniformNoise([np.inf])
    with pytest.raises(DimensionError, match="same length"):
        TruncatedGaussianNoise([0.1, 0.1], [0.1, 0.1, 0.1])
    with pytest.raises(DimensionError, match=r"eta must have shape \(\.\.\., 2\)"):
        GaussianNoise([0.1, 0.1]).prob_abs_le([0.1])
    with pytest.raises(InvalidInputError, match="k must be"):
        UniformNoise([1.0]).sample(-1)
