"""Exact image boxes of the case studies' true dynamics (``TrueSystem.image_bounds``).

These boxes feed the known-dynamics reference (``benchmarks/reference.py``), the yardstick of
our learned bounds, so they must be sound (never inward) and tight (no slack beyond float
error). Each check below has a sensitivity test showing that a box shrunk by 1e-3 of its width
is caught.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from robust_imdp.abstraction.rows import CellBounds
from robust_imdp.casestudies.systems import (CASE_STUDIES, TrueSystem, get_case_study,
                                     known_dynamics_cell_bounds, true_system)
from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.models.geometry import Box, Partition, Region

NAMES = sorted(CASE_STUDIES)
N_CELLS = 48  # sampled cells per case study
N_RANDOM = 10_000  # uniform points per cell


def _n_grid(n: int) -> int:
    """Odd grid points per axis, about 10^4 grid points per cell: 101 (2-D), 21 (3-D)."""
    return 2 * int(round(10 ** (4 / n) / 2)) + 1


def _partition(name):
    c = get_case_study(name)
    regions = [Region(k, [Box(lo, up) for lo, up in v]) for k, v in c.regions.items()]
    return Partition(Box(c.lower, c.upper), c.cell_size, regions)


def _images(system, x, u):
    """Noise-free successor f_u(x) + g_u(x) as TrueSystem.step computes it, (k, n)."""
    modes = np.full(x.shape[0], u)
    return np.einsum("ij,kj->ki", system.known_A[u], x) + system.known_b[u] + system.g(x, modes)


def _sampled_ranges(system, lower, upper, rng):
    """Per mode and cell, the min / max of the images of N_RANDOM uniform points and a regular
    grid (``_n_grid`` points per axis, corners and centre included): two (n_modes, n_cells, n)
    arrays."""
    rng = np.random.default_rng(rng)
    M, (k, n) = len(system.mode_names), lower.shape
    smin, smax = np.empty((M, k, n)), np.empty((M, k, n))
    t = np.linspace(0.0, 1.0, _n_grid(n))
    grid = np.stack(np.meshgrid(*[t] * n, indexing="ij"), axis=-1).reshape(-1, n)
    for q in range(k):
        w = upper[q] - lower[q]
        x = np.concatenate([lower[q] + rng.random((N_RANDOM, n)) * w, lower[q] + grid * w])
        x = np.minimum(x, upper[q])  # lower + 1.0 * w may round above upper
        for u in range(M):
            y = _images(system, x, u)
            smin[u, q], smax[u, q] = y.min(axis=0), y.max(axis=0)
    return smin, smax


def _violations(img_lo, img_hi, smin, smax):
    """Number of (mode, cell, output, side) where a sample lies outside the box."""
    return int(np.sum(smin < img_lo) + np.sum(smax > img_hi))


def _shrink(img_lo, img_hi, frac=1e-3):
    w = img_hi - img_lo
    return img_lo + frac * w, img_hi - frac * w


@pytest.fixture(scope="module", params=NAMES)
def sampled(request):
    """(name, system, cell lower, cell upper, box lower, box upper, sample min, sample max)."""
    name = request.param
    part = _partition(name)
    rng = np.random.default_rng(12345)
    cells = rng.choice(part.n_cells, size=N_CELLS, replace=False)
    lo, up = part.cells_lower[cells], part.cells_upper[cells]
    system = true_system(name)
    img_lo, img_hi = system.image_bounds(lo, up)
    smin, smax = _sampled_ranges(system, lo, up, rng)
    return name, system, lo, up, img_lo, img_hi, smin, smax


# --------------------------------------------------------------------------- consistency
@pytest.mark.parametrize("name", NAMES)
def test_g_terms_are_the_unknown_part(name):
    """The separable form g_terms sums to g at random points (so the boxes bound the real g)."""
    system = true_system(name)
    if system.g_terms is None:  # vehicle_4d: own exact boxes (tests/test_vehicle.py), no separable form
        pytest.skip(f"{name} has no separable form g_terms")
    n = len(system.sigma)
    rng = np.random.default_rng(0)
    x = rng.uniform(-5.0, 5.0, (1000, n))
    funcs = {"lin": lambda v: v, "sin": np.sin, "cos": np.cos}
    for u in range(len(system.mode_names)):
        g = system.g(x, np.full(1000, u))
        for i in range(n):
            s = np.zeros(1000)
            for kind, j, c in system.g_terms[u][i]:
                s += c if kind == "const" else c * funcs[kind](x[:, j])
            np.testing.assert_allclose(s, g[:, i], rtol=0, atol=1e-14)


@pytest.mark.parametrize("name", NAMES)
def test_point_boxes_contain_the_point(name):
    """Degenerate cells [x, x]: the box contains f(x) + g(x) and is at most ~1e-10 wide."""
    case = get_case_study(name)
    system = case.system
    x = np.random.default_rng(1).uniform(case.lower, case.upper, (500, len(case.lower)))
    lo, hi = system.image_bounds(x, x)
    for u in range(len(system.mode_names)):
        y = _images(system, x, u)
        assert np.all(lo[u] <= y) and np.all(y <= hi[u])
    assert np.max(hi - lo) < 1e-10  # margin 1e-12 (1 + magnitudes) per side, magnitudes < 10 here


# --------------------------------------------------------------------------- soundness
def test_dense_samples_never_leave_the_box(sampled):
    """10^4 uniform points + ~10^4 grid points per cell, 48 seeded cells, every mode: 0 outside."""
    _, _, _, _, img_lo, img_hi, smin, smax = sampled
    assert img_lo.shape == smin.shape
    assert _violations(img_lo, img_hi, smin, smax) == 0


def test_box_is_tight(sampled):
    """The sampled range reaches the box: the grid includes the corners (the extremes of the
    linear terms) and lies within h/(2 (G - 1)) of any interior critical line (G grid points per
    axis), so a trig term c sin misses its extreme by at most |c| (h/(2 (G - 1)))^2 / 2: 2-D,
    0.4 (0.125/200)^2/2 < 1e-7; 3-D (G = 21, h <= pi/32), 0.15 (0.1/40)^2/2 < 5e-7. The rest is
    the 1e-12 margin."""
    _, _, _, _, img_lo, img_hi, smin, smax = sampled
    slack = np.concatenate([(smin - img_lo).ravel(), (img_hi - smax).ravel()])
    assert np.all(slack >= 0)
    assert np.max(slack) < 1e-3
    assert np.mean(slack < 1e-6) > 0.99


def test_shrunk_box_is_caught(sampled):
    """Sensitivity: the same check flags a box shrunk by 1e-3 of its width on each side, in
    almost every sampled cell (it would be a miss if a box were slightly inward)."""
    _, system, _, _, img_lo, img_hi, smin, smax = sampled
    s_lo, s_hi = _shrink(img_lo, img_hi)
    assert _violations(s_lo, s_hi, smin, smax) > 0
    caught = np.any((smin < s_lo) | (smax > s_hi), axis=2)  # (mode, cell)
    assert np.mean(caught) > 0.95


def test_linear_boxes_contain_the_exact_rational_range():
    """Three-mode linear: the exact range of A x over [l, u] is A c -+ |A| h; computed with
    Fractions (no rounding), it lies inside the float box, and the box is wider by < 1e-11."""
    part = _partition("three_mode_linear")
    system = true_system("three_mode_linear")
    cells = np.random.default_rng(2).choice(part.n_cells, size=40, replace=False)
    lo, up = part.cells_lower[cells], part.cells_upper[cells]
    img_lo, img_hi = system.image_bounds(lo, up)
    for u in range(3):
        A = _matrix_from_terms(system, u)
        for r, q in enumerate(cells):
            for i in range(2):
                ex_lo = sum(min(A[i][j] * Fraction(float(lo[r, j])), A[i][j] * Fraction(float(up[r, j])))
                            for j in range(2))
                ex_hi = sum(max(A[i][j] * Fraction(float(lo[r, j])), A[i][j] * Fraction(float(up[r, j])))
                            for j in range(2))
                assert Fraction(float(img_lo[u, r, i])) <= ex_lo <= Fraction(float(img_lo[u, r, i])) + Fraction(1, 10**11)
                assert Fraction(float(img_hi[u, r, i])) - Fraction(1, 10**11) <= ex_hi <= Fraction(float(img_hi[u, r, i]))


def _matrix_from_terms(system, u):
    A = [[Fraction(0)] * 2 for _ in range(2)]
    for i in range(2):
        for kind, j, c in system.g_terms[u][i]:
            assert kind == "lin"
            A[i][j] += Fraction(float(c))
    return A


def test_trig_terms_on_wide_boxes():
    """Boxes of width up to 8 around centres in [-10, 10] (several critical points k pi/2
    inside): dense grids stay inside and reach the box; hand cases have the textbook ranges."""
    sysm = TrueSystem(("a",), np.zeros((1, 2, 2)), np.zeros((1, 2)), lambda x, m: np.column_stack(
        [0.7 * np.sin(x[:, 0]) - 1.3 * np.cos(x[:, 1]), -0.5 * np.cos(x[:, 0]) + 2.0 * np.sin(x[:, 1])]),
        np.array([0.01, 0.01]), np.array([0.01, 0.01]),
        (((("sin", 0, 0.7), ("cos", 1, -1.3)), (("cos", 0, -0.5), ("sin", 1, 2.0))),))
    rng = np.random.default_rng(3)
    c = rng.uniform(-10, 10, (40, 2))
    w = rng.uniform(0.0, 8.0, (40, 2))
    lo, up = c - w / 2, c + w / 2
    img_lo, img_hi = sysm.image_bounds(lo, up)
    # spacing <= 0.02: each term misses its extreme by <= |c| 0.01^2 / 2; the sum by <= 1.7e-4
    t = np.linspace(0.0, 1.0, 401)
    for q in range(40):
        xs = lo[q] + t[:, None] * (up[q] - lo[q])
        X = np.stack(np.meshgrid(xs[:, 0], xs[:, 1], indexing="ij"), -1).reshape(-1, 2)
        y = sysm.g(X, np.zeros(len(X), int))
        assert np.all(y.min(0) >= img_lo[0, q]) and np.all(y.max(0) <= img_hi[0, q])
        assert np.all(y.min(0) - img_lo[0, q] < 3e-4) and np.all(img_hi[0, q] - y.max(0) < 3e-4)
    # hand cases: sin on [0, pi] = [0, 1] (0 up to float error of sin(pi)); cos on [-1, 1] = [cos 1, 1];
    # sin on [pi/2 + 0.1, 3] is decreasing: [sin 3, sin(pi/2 + 0.1)]
    one = TrueSystem(("a",), np.zeros((1, 1, 1)), np.zeros((1, 1)), None, np.ones(1), np.ones(1),
                     (((("sin", 0, 1.0),),),))
    cos1 = TrueSystem(("a",), np.zeros((1, 1, 1)), np.zeros((1, 1)), None, np.ones(1), np.ones(1),
                      (((("cos", 0, 1.0),),),))
    lo, hi = one.image_bounds([[0.0], [np.pi / 2 + 0.1]], [[np.pi], [3.0]])
    np.testing.assert_allclose([lo[0, 0, 0], hi[0, 0, 0]], [0.0, 1.0], atol=1e-11)
    np.testing.assert_allclose([lo[0, 1, 0], hi[0, 1, 0]], [np.sin(3.0), np.cos(0.1)], atol=1e-11)
    assert hi[0, 0, 0] >= 1.0 and lo[0, 1, 0] <= np.sin(3.0) and hi[0, 1, 0] >= np.cos(0.1)
    lo, hi = cos1.image_bounds([[-1.0]], [[1.0]])
    np.testing.assert_allclose([lo[0, 0, 0], hi[0, 0, 0]], [np.cos(1.0), 1.0], atol=1e-11)
    assert lo[0, 0, 0] <= np.cos(1.0) and hi[0, 0, 0] >= 1.0


# --------------------------------------------------------------------------- helper and errors
@pytest.mark.parametrize("name", NAMES)
def test_known_dynamics_cell_bounds(name):
    part = _partition(name)
    cb = known_dynamics_cell_bounds(name, part)
    assert isinstance(cb, CellBounds) and cb.std_upper is None
    assert cb.image_lower.shape == (len(true_system(name).mode_names), part.n_cells, part.dim)
    lo, hi = true_system(name).image_bounds(part.cells_lower, part.cells_upper)
    np.testing.assert_array_equal(cb.image_lower, lo)
    np.testing.assert_array_equal(cb.image_upper, hi)


def test_image_bounds_errors():
    system = true_system("three_mode_linear")
    with pytest.raises(DimensionError, match="lower"):
        system.image_bounds(np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(DimensionError, match="upper"):
        system.image_bounds(np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(InvalidInputError, match="lower must be <= upper"):
        system.image_bounds(np.ones((1, 2)), np.zeros((1, 2)))
    bare = TrueSystem(("a",), np.zeros((1, 2, 2)), np.zeros((1, 2)), None, np.ones(2), np.ones(2))
    with pytest.raises(InvalidInputError, match="g_terms"):
        bare.image_bounds(np.zeros((1, 2)), np.ones((1, 2)))
    with pytest.raises(InvalidInputError, match="g_terms"):
        TrueSystem(("a",), np.zeros((1, 2, 2)), np.zeros((1, 2)), None, np.ones(2), np.ones(2),
                   (((("tan", 0, 1.0),), ()),))
    with pytest.raises(DimensionError, match="g_terms"):
        TrueSystem(("a",), np.zeros((1, 2, 2)), np.zeros((1, 2)), None, np.ones(2), np.ones(2), ((),))
    with pytest.raises(InvalidInputError, match="partition"):
        known_dynamics_cell_bounds("three_mode_linear", object())
