"""Confidence mode of the abstraction: the GP error folded into the image boxes at one data
confidence level (``confidence_cell_bounds``), the sound reading of Thm 1 for a fixed system.

Independent check: an affine system with a *fixed* worst-case error ``g - mu = +-eps`` (the
largest error the confidence event allows) and Gaussian noise, where T(q'|x) has a closed form
(products of normal-cdf differences). Every interval of the abstraction must contain it.
"""

import numpy as np
import pytest
from scipy.stats import norm

from robust_imdp.abstraction.rows import CellBounds, abstract, confidence_cell_bounds
from robust_imdp.errors import InvalidInputError
from robust_imdp.models.geometry import Box, Partition
from robust_imdp.models.noise import GaussianNoise

A = np.array([[0.3, 0.05], [-0.05, 0.3]])
B = np.array([0.05, -0.02])


class LinearEpsModel:
    """eps_for_prob(p, s) = c(p) * s with c increasing in p (a stand-in for beta(1 - p))."""

    def eps_for_prob(self, p, std_upper):
        return (1.0 + 10.0 * np.asarray(p)) * np.asarray(std_upper)

    def prob_within(self, eps, std_upper):  # not used by the confidence mode
        raise AssertionError("confidence mode must not use per-entry probabilities")


def _setup():
    part = Partition(Box([-1.0, -1.0], [1.0, 1.0]), 0.25)
    c = 0.5 * (part.cells_lower + part.cells_upper)
    h = 0.5 * (part.cells_upper - part.cells_lower)
    cc, rr = c @ A.T + B, h @ np.abs(A).T  # exact image box of the affine mean
    lo, hi = (cc - rr - 1e-12)[None], (cc + rr + 1e-12)[None]
    s = np.random.default_rng(3).uniform(0.0005, 0.003, (1, part.n_cells, 2))
    return part, CellBounds(lo, hi, s), s


def test_confidence_bounds_expand_by_eps_and_drop_std():
    part, cb, s = _setup()
    out = confidence_cell_bounds(cb, [[LinearEpsModel()] * 2], confidence=0.9)
    # delta per GP = 0.1 / 2, p = 0.95 -> eps = 10.5 * s (up to rounding, outward)
    eps = 10.5 * s
    assert out.std_upper is None
    assert np.all(out.image_lower <= cb.image_lower - eps + 1e-12)
    assert np.all(out.image_upper >= cb.image_upper + eps - 1e-12)
    assert np.all(out.image_lower <= cb.image_lower - eps * (1 - 1e-6))


def test_confidence_mode_contains_fixed_worst_case_error():
    """With g - mu fixed at +-eps (the edge of the confidence event) every listed interval, the
    floor and the outside entry contain the exact T(q'|x) at corners and centre of every cell.
    Tolerance 1e-10: the closed form is evaluated in float64 (error ~1e-15)."""
    sigma = np.array([0.01, 0.02])
    part, cb, s = _setup()
    model = LinearEpsModel()
    conf = 0.9
    cbe = confidence_cell_bounds(cb, [[model] * 2], confidence=conf)
    ab = abstract(part, cbe, GaussianNoise(sigma))
    lo, up = ab.imdp.to_dense()
    N = part.n_cells
    eps = model.eps_for_prob(1 - (1 - conf) / 2, s[0])  # (N, 2)
    signs = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=float)
    worst = np.inf
    informative = 0
    for q in range(N):
        pts = np.array([part.cells_lower[q], part.cells_upper[q],
                        [part.cells_lower[q][0], part.cells_upper[q][1]],
                        [part.cells_upper[q][0], part.cells_lower[q][1]],
                        0.5 * (part.cells_lower[q] + part.cells_upper[q])])
        for sg in signs:
            mean = pts @ A.T + B + sg * eps[q]
            per = []
            for j in range(2):
                bp = part.breakpoints[j]
                z_hi = (bp[None, 1:] - mean[:, j, None]) / sigma[j]
                z_lo = (bp[None, :-1] - mean[:, j, None]) / sigma[j]
                per.append(norm.cdf(z_hi) - norm.cdf(z_lo))
            T = np.einsum("ka,kb->kab", per[0], per[1]).reshape(len(pts), -1)
            T = np.column_stack([T, 1.0 - T.sum(axis=1)])  # outside X
            L, U = lo[q], up[q]
            worst = min(worst, np.min(T - L), np.min(U - T))
        informative += int(np.sum(lo[q] > 0.5))
    assert worst >= -1e-10, worst
    assert informative > 5  # not vacuous: some transitions are certified with probability > 0.5


def test_confidence_mode_bad_input():
    part, cb, _ = _setup()
    with pytest.raises(InvalidInputError, match="confidence"):
        confidence_cell_bounds(cb, [[LinearEpsModel()] * 2], confidence=1.0)
    with pytest.raises(InvalidInputError, match="std_upper"):
        confidence_cell_bounds(CellBounds(cb.image_lower, cb.image_upper, None), [[LinearEpsModel()] * 2])
