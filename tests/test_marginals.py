"""Tests of the exact transition bounds: abstraction.marginals (per axis), abstraction.exact_rows (joint),
the noise models' certified interval probabilities, and ``transitions="exact"`` in abstract().

Independent references used here (none of them uses the unimodality the code relies on):
* mpmath at 80-200 bits for the noise CDFs (Gaussian, truncated Gaussian, uniform), wrapped copies
  summed far beyond the noise's reach on periodic axes;
* dense sampling of the image interval (81 points, then 81 more between the best one's neighbours,
  both ends included) for the min and max over y;
* per-point products of exact per-axis probabilities for joint transitions, and seeded Monte Carlo
  of the next state with Wilson intervals (z = 5).
Tolerances: containment is strict against the references (the references are exact to far below
the bounds' own rounding allowances); "tight" means within 5e-4 relative of the dense optimum (the
refined grid's sampling error is below 1e-5 relative here): a 0.1 % shrink of a bound breaks one or
the other.
"""

import mpmath
import numpy as np
import pytest
from scipy import special

from robust_imdp._fp import U, down, up
from robust_imdp.abstraction.exact_rows import exact_rows
from robust_imdp.abstraction.marginals import (
    axis_data, axis_marginals, axis_runs, interval_bounds, outside_bounds,
)
from robust_imdp.abstraction.rows import Abstraction, CellBounds, abstract, abstract_rows, assemble_abstraction
from robust_imdp.errors import InvalidInputError
from robust_imdp.models.factored import FactoredIMDP
from robust_imdp.models.geometry import Box, BoxPartition, Partition, Region
from robust_imdp.models.noise import GaussianNoise, TruncatedGaussianNoise, UniformNoise, ndtr_error

from soundness_checks import wilson

mpmath.mp.prec = 120
TWO_PI = 2 * np.pi


# --------------------------------------------------------------------------- references
def cdf_mp(noise, i, x):
    """P[v_i <= x] in mpmath."""
    x = mpmath.mpf(x) if not isinstance(x, mpmath.mpf) else x
    if isinstance(noise, GaussianNoise):
        return mpmath.ncdf(x / mpmath.mpf(noise.sigma[i]))
    c = mpmath.mpf(noise.bound[i])
    x = min(max(x, -c), c)
    if isinstance(noise, UniformNoise):
        return (x + c) / (2 * c)
    s = mpmath.mpf(noise.sigma[i])
    return (mpmath.ncdf(x / s) - mpmath.ncdf(-c / s)) / (mpmath.ncdf(c / s) - mpmath.ncdf(-c / s))


def reach(noise, i):
    # Gaussian: the copies beyond 20 sigma hold < 1e-88 together, far below every bound's rounding slack
    return 20.0 * noise.sigma[i] if isinstance(noise, GaussianNoise) else float(noise.bound[i])


def g_mp(noise, i, y, l, h, circle=None):
    """P[y + v_i in [l, h]] (summed over the translates by whole periods on a circle), mpmath."""
    y, l, h = mpmath.mpf(float(y)), mpmath.mpf(float(l)), mpmath.mpf(float(h))
    if circle is None:
        return cdf_mp(noise, i, h - y) - cdf_mp(noise, i, l - y)
    T = mpmath.mpf(circle[1]) - mpmath.mpf(circle[0])
    r = reach(noise, i)
    k0 = int(np.floor(float((y - h - r) / T))) - 1
    k1 = int(np.ceil(float((y - l + r) / T))) + 1
    return mpmath.fsum(cdf_mp(noise, i, h + k * T - y) - cdf_mp(noise, i, l + k * T - y) for k in range(k0, k1 + 1))


def out_mp(noise, i, y, L, H):
    y = mpmath.mpf(float(y))
    return cdf_mp(noise, i, mpmath.mpf(L) - y) + (1 - cdf_mp(noise, i, mpmath.mpf(H) - y))


def dense_extrema(f, a, b, n=81):
    """(min, max) of f over [a, b] by dense sampling (ends included), refined around the best samples."""
    if b <= a:
        v = f(a)
        return v, v
    ys = np.linspace(a, b, n)
    vals = [f(y) for y in ys]
    out = []
    for pick in (min, max):
        best = vals.index(pick(vals))
        lo, hi = ys[max(best - 1, 0)], ys[min(best + 1, n - 1)]
        out.append(pick(vals + [f(y) for y in np.linspace(lo, hi, n)]))
    return out[0], out[1]


NOISES = {
    "gauss": GaussianNoise([0.7]),
    "gauss-wide": GaussianNoise([3.0]),
    "truncated": TruncatedGaussianNoise([0.5], [0.8]),
    "uniform": UniformNoise([0.3]),
}


def _random_cases(rng, k, circle):
    cases = []
    for t in range(k):
        a = rng.uniform(-3, 8)
        width = [0.0, rng.uniform(0, 0.7), rng.uniform(0, 8)][t % 3]
        l = rng.uniform(0, 6)
        h = l + rng.uniform(0.01, 1.5 if circle is None else 3.0)
        cases.append((a, a + width, l, h))
    return cases


# --------------------------------------------------------------------------- the noise side
def test_ndtr_allowance_against_mpmath():
    rng = np.random.default_rng(0)
    t = np.concatenate([rng.uniform(-39, 39, 500), rng.uniform(-1, 1, 200), rng.uniform(-37.5, -30, 100)])
    v = special.ndtr(t)
    err = ndtr_error(t, v)
    mpmath.mp.prec = 200
    exact = [mpmath.ncdf(mpmath.mpf(float(x))) for x in t]
    mpmath.mp.prec = 120
    miss = [abs(mpmath.mpf(float(vi)) - e) for vi, e in zip(v, exact)]
    # the allowance covers the measured error with room (4x to 8x in the docstring's measurement)
    assert all(m <= e / 2 for m, e in zip(miss, err))


def _std_interval_by_doc(ta, tb, upward):
    """The documented rule of noise._std_normal_interval, written again (the test of its allowance)."""
    right, left = ta >= 0, (ta < 0) & (tb <= 0)
    A = special.ndtr(np.where(right, -ta, ta))
    B = special.ndtr(np.where(left, tb, -tb))
    tA, tB = np.minimum(ta * ta, 1600.0), np.minimum(tb * tb, 1600.0)
    eA = (32.0 + 8.0 * tA) * U * A + 2.0 ** -990
    eB = (32.0 + 8.0 * tB) * U * B + 2.0 ** -990
    s = A + B
    val = np.where(right, A - B, np.where(left, B - A, 1.0 - s))
    err = eA + eB + np.where(~right & ~left, 2.0 * U * (1.0 + s), U * s)
    out = np.clip(up(val, err) if upward else down(val, err), 0.0, 1.0)
    return np.where(tb > ta, out, 0.0)


def test_gaussian_interval_probabilities_apply_the_documented_allowance_exactly():
    # a shrink of the allowance (ndtr's error, the subtraction's) changes these bits
    rng = np.random.default_rng(1)
    a = np.sort(rng.uniform(-12, 12, (400, 2)), axis=1)
    g = GaussianNoise([1.0])
    np.testing.assert_array_equal(g.interval_prob_lower(a[:, 0], a[:, 1], 0), _std_interval_by_doc(
        up(a[:, 0]), down(a[:, 1]), False))
    np.testing.assert_array_equal(g.interval_prob_upper(a[:, 0], a[:, 1], 0), _std_interval_by_doc(
        down(a[:, 0]), up(a[:, 1]), True))


@pytest.mark.parametrize("name", sorted(NOISES))
def test_interval_probabilities_enclose_mpmath_and_are_tight(name):
    noise = NOISES[name]
    rng = np.random.default_rng(2)
    sc = float(noise.sigma[0]) if name.startswith("gauss") else float(noise.bound[0])
    al = rng.uniform(-6, 6, 150) * sc
    be = al + rng.uniform(0, 4, 150) * sc
    al[:10], be[10:20] = -np.inf, np.inf
    lo, hi = noise.interval_prob_lower(al, be, 0), noise.interval_prob_upper(al, be, 0)
    for x, y, l_, h_ in zip(al, be, lo, hi):
        ex = cdf_mp(noise, 0, mpmath.mpf(y) if np.isfinite(y) else mpmath.inf) - \
            cdf_mp(noise, 0, mpmath.mpf(x) if np.isfinite(x) else -mpmath.inf)
        assert l_ <= ex <= h_, (x, y, l_, float(ex), h_)
        assert h_ - l_ <= 1e-12 * float(ex) + 1e-15  # tight: a 0.1 % shrink leaves the enclosure
    # bounded noise: exact 0 outside the support and 1 over it (no rounding there)
    if noise.bounded:
        c = float(noise.bound[0])
        assert noise.interval_prob_upper(c, c + 1, 0) == 0.0 and noise.interval_prob_lower(-c, c, 0) == 1.0


# --------------------------------------------------------------------------- per-axis bounds
CIRCLES = {"line": None, "two-pi": (0.0, TWO_PI), "odd": (-1.0, 1.5)}


@pytest.mark.parametrize("circle_name", sorted(CIRCLES))
@pytest.mark.parametrize("name", sorted(NOISES))
def test_axis_bounds_enclose_the_dense_optimum_over_the_image(name, circle_name):
    noise, circle = NOISES[name], CIRCLES[circle_name]
    if circle_name == "odd" and name == "gauss-wide":
        pytest.skip("covered by two-pi (many copies); keeps the test short")
    rng = np.random.default_rng(3)
    unimodal = circle is None or noise.wrapped_unimodal(circle[1] - circle[0], 0)
    for a, b, l, h in _random_cases(rng, 4 if name == "gauss-wide" and circle else 6, circle):
        if circle is not None:
            h = min(h, l + (circle[1] - circle[0]))
        lo, hi = interval_bounds(noise, 0, a, b, l, h, circle)
        mn, mx = dense_extrema(lambda y: g_mp(noise, 0, y, l, h, circle), a, b)
        assert lo <= mn and mx <= hi, (a, b, l, h, float(lo), float(mn), float(mx), float(hi))
        if unimodal:  # the exact extremum: within the sampling error of the reference
            assert float(mn) - lo <= 5e-4 * float(mn) + 1e-14 and hi - float(mx) <= 5e-4 * float(mx) + 1e-14


def test_wrapped_uniform_wider_than_half_the_period_uses_the_sound_per_copy_bound():
    noise = UniformNoise([4.0])  # on a circle of 2 pi the wrapped law is not unimodal
    assert not noise.wrapped_unimodal(TWO_PI, 0)
    rng = np.random.default_rng(4)
    for a, b, l, h in _random_cases(rng, 9, (0.0, TWO_PI)):
        lo, hi = interval_bounds(noise, 0, a, b, l, h, (0.0, TWO_PI))
        mn, mx = dense_extrema(lambda y: g_mp(noise, 0, y, l, h, (0.0, TWO_PI)), a, b)
        assert lo <= mn and mx <= hi


def test_circle_sum_truncation_is_sound_with_few_copies(monkeypatch):
    # with one copy each side of the nearest, the copies beyond carry real mass: the tail bound must cover it
    import robust_imdp.abstraction.marginals as mg

    monkeypatch.setattr(mg, "MAX_COPIES", 1)
    noise = GaussianNoise([4.0])
    for a, b, l, h in [(0.3, 0.3, 1.0, 2.0), (2.0, 2.5, 0.0, 0.5), (5.0, 5.0, 3.0, 6.0)]:
        lo, hi = interval_bounds(noise, 0, a, b, l, h, (0.0, TWO_PI))
        mn, mx = dense_extrema(lambda y: g_mp(noise, 0, y, l, h, (0.0, TWO_PI)), a, b, n=21)
        assert lo <= mn and mx <= hi
        assert float(mn) - lo > 1e-3  # the dropped copies' mass is real: the lower bound is visibly below


@pytest.mark.parametrize("name", sorted(NOISES))
def test_outside_bounds_enclose_the_dense_optimum(name):
    noise = NOISES[name]
    rng = np.random.default_rng(5)
    L, H = -1.0, 2.0
    for t in range(9):
        a = rng.uniform(-4, 4)
        b = a + [0.0, 0.3, 5.0][t % 3]
        lo, hi = outside_bounds(noise, 0, a, b, L, H)
        mn, mx = dense_extrema(lambda y: out_mp(noise, 0, y, L, H), a, b)
        assert lo <= mn and mx <= hi
        assert float(mn) - lo <= 5e-4 * float(mn) + 1e-14 and hi - float(mx) <= 5e-4 * float(mx) + 1e-14


# --------------------------------------------------------------------------- the factored arrays of a grid
def _grid(periodic=False):
    # X = [0, 6] x [-2, 2], cells 0.5; a region refines axis 0 at 1.3 and axis 1 at 0.7 (non-uniform grid)
    regions = [Region("r", [Box([1.3, -2.0], [3.0, 0.7])])]
    return Partition(Box([0.0, -2.0], [6.0, 2.0]), 0.5, regions, periodic=(False, True) if periodic else None)


def _boxes(part, rng, M=2):
    """Image boxes: shifted cells, some beyond X's faces (and across a periodic seam), some points."""
    N = part.n_cells
    shift = rng.uniform(-1.5, 1.5, (M, N, 2))
    width = rng.uniform(0, 1.0, (M, N, 2)) * (rng.random((M, N, 1)) < 0.8)
    lo = part.cells_lower[None] + shift
    return lo, lo + width


@pytest.mark.parametrize("periodic", [False, True], ids=["plain", "periodic"])
def test_axis_marginals_enclose_listed_outside_and_unlisted_mass(periodic):
    part = _grid(periodic)
    rng = np.random.default_rng(6)
    lo, hi = _boxes(part, rng)
    noise = GaussianNoise([0.3, 0.2])
    axes = axis_marginals(part, lo, hi, noise)
    FactoredIMDP(shape=part.shape, axes=axes)  # the factored model accepts them (its checks pass)
    for j, ax in enumerate(axes):
        bp = part.breakpoints[j]
        circle = (float(part.space.lower[j]), float(part.space.upper[j])) if periodic and j == 1 else None
        pos = ax.positions()
        for u, q in [(0, 0), (1, 5), (0, part.n_cells - 1), (1, 40), (0, 77)]:
            a, b = lo[u, q, j], hi[u, q, j]
            listed = set(int(p) for p in pos[u, q] if p >= 0)
            unl = [z for z in range(ax.n) if z not in listed]

            def rest(y):
                return mpmath.fsum(g_mp(noise, j, y, bp[z], bp[z + 1], circle) for z in unl)

            mn, mx = dense_extrema(rest, a, b, n=41) if unl else (0, 0)
            assert mx <= ax.rest_upper[u, q]
            if mx > 1e-300:  # tight: the unlisted pieces' maxima are at the same end here
                assert ax.rest_upper[u, q] <= float(mx) * (1 + 5e-4)
            for t in range(ax.k)[:3]:
                z = int(pos[u, q, t])
                mn, mx = dense_extrema(lambda y: g_mp(noise, j, y, bp[z], bp[z + 1], circle), a, b, n=41)
                assert ax.lower[u, q, t] <= mn and mx <= ax.upper[u, q, t]
            if circle is None:
                mn, mx = dense_extrema(lambda y: out_mp(noise, j, y, bp[0], bp[-1]), a, b, n=41)
                assert ax.out_lower[u, q] <= mn and mx <= ax.out_upper[u, q]
            else:
                assert ax.out_upper[u, q] == 0.0


def test_bounded_noise_lists_its_whole_support_and_leaves_nothing_unlisted():
    part = _grid()
    lo, hi = _boxes(part, np.random.default_rng(7))
    axes = axis_marginals(part, lo, hi, UniformNoise([0.4, 0.3]))
    for ax in axes:
        assert np.all(ax.rest_upper == 0.0)  # exact: no mass of bounded noise beyond its support


# --------------------------------------------------------------------------- the joint rows
def _true_row(part, noise, y, periodic=None):
    """Exact transition probabilities (n_cells + 1,) from the point y: products of per-axis masses (mpmath)."""
    lo, hi = part.cells_lower, part.cells_upper
    p = np.ones(part.n_cells)
    p_in = 1.0
    for j in range(part.dim):
        L, H = float(part.space.lower[j]), float(part.space.upper[j])
        circle = (L, H) if periodic is not None and periodic[j] else None
        p = p * np.array([float(g_mp(noise, j, y[j], a, b, circle)) for a, b in zip(lo[:, j], hi[:, j])])
        if circle is None:
            p_in *= 1.0 - float(out_mp(noise, j, y[j], L, H))
    return np.append(p, 1.0 - p_in)


def _dense_rows(ab):
    lo, up_ = ab.imdp.to_dense()
    M, N = ab.n_modes, ab.partition.n_cells
    return lo[: N * M].reshape(N, M, N + 1), up_[: N * M].reshape(N, M, N + 1)


def _small_grid(periodic=None):
    return Partition(Box([0.0, 0.0], [3.0, 2.0]), [0.5, 0.5], [Region("g", [Box([1.2, 0.0], [3.0, 1.0])])],
                     periodic=periodic)


@pytest.mark.parametrize("kind", ["grid", "grid-periodic", "boxes", "boxes-periodic", "union"])
def test_joint_rows_enclose_exact_transition_probabilities(kind):
    periodic = (True, False) if "periodic" in kind else None
    part = _small_grid(periodic)
    if kind.startswith("boxes"):
        part = BoxPartition(part).split([0, 5, 9], axes=None).split([1], axes=[1])
    rng = np.random.default_rng(8)
    N = part.n_cells
    # x' = A x + c + v with a known affine map: image box from the cell's corners (A diagonal)
    A = np.array([0.8, 1.1])
    c = np.array([0.4, -0.2])
    lo = (part.cells_lower * A + c)[None]
    hi = (part.cells_upper * A + c)[None]
    noise = GaussianNoise([0.35, 0.25])
    combine = "union" if kind == "union" else "product"
    ab = abstract(part, CellBounds(lo, hi), noise, transitions="exact", combine=combine)
    assert ab.transitions == "exact"
    L, Hh = _dense_rows(ab)
    for q in rng.choice(N, 6, replace=False):
        for x in rng.uniform(part.cells_lower[q], part.cells_upper[q], (3, 2)):
            t = _true_row(part, noise, x * A + c, periodic)
            assert np.all(L[q, 0] <= t + 1e-15) and np.all(t <= Hh[q, 0] + 1e-15), q


def test_joint_rows_are_tight_at_the_per_axis_extremes_and_the_floor_is_its_formula():
    part = Partition(Box([0.0, 0.0], [6.0, 4.0]), 0.5)  # larger than the listing radius: some cells unlisted
    noise = GaussianNoise([0.35, 0.25])
    lo = np.array([[[1.1, 0.6]]]) * np.ones((1, part.n_cells, 2))
    hi = lo + np.array([0.3, 0.2])
    ab = abstract(part, CellBounds(lo, hi), noise, transitions="exact", floor_tol=1e-12)
    L, Hh = _dense_rows(ab)
    row = ab.imdp.row_ptr[0], ab.imdp.row_ptr[1]
    a, b = lo[0, 0], hi[0, 0]
    bp = part.breakpoints
    # every listed cell: the bounds are the products of the per-axis optima (dense search per axis)
    for col in ab.imdp.col[row[0]:row[1]][:-1][:12]:
        i0, i1 = np.unravel_index(col, part.shape)
        e0 = dense_extrema(lambda y: g_mp(noise, 0, y, bp[0][i0], bp[0][i0 + 1]), a[0], b[0])
        e1 = dense_extrema(lambda y: g_mp(noise, 1, y, bp[1][i1], bp[1][i1 + 1]), a[1], b[1])
        lo_t, hi_t = float(e0[0] * e1[0]), float(e0[1] * e1[1])
        assert L[0, 0, col] <= lo_t and hi_t <= Hh[0, 0, col]
        assert lo_t - L[0, 0, col] <= 5e-4 * lo_t + 1e-14 and Hh[0, 0, col] - hi_t <= 5e-4 * hi_t + 1e-14
    # outside: 1 - prod(1 - out_j) at the per-axis extremes
    o = [dense_extrema(lambda y, j=j: out_mp(noise, j, y, part.space.lower[j], part.space.upper[j]), a[j], b[j])
         for j in range(2)]
    out_lo = float(1 - (1 - o[0][0]) * (1 - o[1][0]))
    out_hi = float(1 - (1 - o[0][1]) * (1 - o[1][1]))
    N = part.n_cells
    assert L[0, 0, N] <= out_lo and out_hi <= Hh[0, 0, N]
    assert out_lo - L[0, 0, N] <= 5e-4 * out_lo and Hh[0, 0, N] - out_hi <= 5e-4 * out_hi
    # the floor: max_i rest_i prod_{j != i} m_j of the row's own runs (exact_rows' docstring)
    R = noise.listing_radius(1e-9)
    per = []
    for j in range(2):
        first, count = axis_runs(part, j, down(a[j] - R[j]), up(b[j] + R[j]))
        per.append(axis_data(part, j, np.array(a[j]), np.array(b[j]), noise, first, count, int(count)))
    m = [max(p[1].max(), p[4]) for p in per]
    want = max(per[0][4] * m[1], per[1][4] * m[0], 1e-12 / 20)  # floor_tol / 20: the floor's least value
    assert want > 1e-12 / 20 and abs(ab.imdp.floor[0] - want) <= 1e-12 * want
    # every unlisted cell's true mass is at most the floor
    listed = set(ab.imdp.col[row[0]:row[1]].tolist())
    for y in [a, b, (a + b) / 2]:
        t = _true_row(part, noise, y)
        assert all(t[z] <= ab.imdp.floor[0] for z in range(N) if z not in listed)


def test_joint_monte_carlo_frequencies_lie_in_the_bounds():
    part = _small_grid()
    A, c = np.array([0.8, 1.1]), np.array([0.4, -0.2])
    noise = TruncatedGaussianNoise([0.3, 0.2], [0.5, 0.4])
    ab = abstract(part, CellBounds((part.cells_lower * A + c)[None], (part.cells_upper * A + c)[None]), noise,
                  transitions="exact")
    L, Hh = _dense_rows(ab)
    rng = np.random.default_rng(9)
    n = 40_000
    for q in (0, 7, 13, 22):
        x = rng.uniform(part.cells_lower[q], part.cells_upper[q], (n, 2))
        nxt = x * A + c + noise.sample(n, rng)
        inside = part.contains(nxt)
        cell = np.full(n, part.n_cells)
        cell[inside] = part.locate(nxt[inside])
        hits = np.bincount(cell, minlength=part.n_cells + 1)
        w_lo, w_hi = wilson(hits, n, 5.0)
        assert np.all(w_hi >= L[q, 0]) and np.all(w_lo <= Hh[q, 0])


def test_gp_route_mixes_the_error_probability_like_thm1():
    class Model:  # P[sup |g - mu| <= eps] >= 1 - exp(-eps / s) (any law with that tail)
        def prob_within(self, eps, s):
            return np.clip(np.nextafter(1.0 - np.exp(-np.asarray(eps) / s), 0), 0, 1)

        def eps_for_prob(self, p, s):
            return -np.asarray(s) * np.log1p(-np.asarray(p)) * (1 + 1e-12)

    part = _small_grid()
    A, c = np.array([0.8, 1.1]), np.array([0.4, -0.2])
    lo, hi = (part.cells_lower * A + c)[None], (part.cells_upper * A + c)[None]
    std = np.full(lo.shape, 0.01)
    noise = GaussianNoise([0.35, 0.25])
    models = [[Model(), Model()]]
    ab = abstract(part, CellBounds(lo, hi, std), noise, models, transitions="exact")
    plain = abstract(part, CellBounds(lo, hi), noise, transitions="exact")
    L, Hh = _dense_rows(ab)
    L0, H0 = _dense_rows(plain)
    # a deterministic g inside every level's eps box (eps(0.9) = 0.023): every candidate's event holds
    rng = np.random.default_rng(10)
    for q in (3, 11, 20):
        x = rng.uniform(part.cells_lower[q], part.cells_upper[q], 2)
        t = _true_row(part, noise, x * A + c + 0.02)
        assert np.all(L[q, 0] <= t + 1e-15) and np.all(t <= Hh[q, 0] + 1e-15)
    # the mixture is never tighter than the bounds without a learned error (where those list the entry: an
    # entry below the floor is not listed there, its lower bound at most the floor)
    assert np.all(L <= L0 + plain.imdp.floor[0]) and np.all(Hh >= H0 - 1e-15)
    assert np.max(L0 - L) > 0.0


def test_rows_do_not_depend_on_the_chunks_and_survive_save_load(tmp_path):
    part = _grid(periodic=True)
    lo, hi = _boxes(part, np.random.default_rng(11))
    noise = GaussianNoise([0.3, 0.2])
    whole = abstract(part, CellBounds(lo, hi), noise, transitions="exact")
    cuts = [0, 17, 60, part.n_cells]
    chunks = [abstract_rows(part, CellBounds(lo[:, a:b], hi[:, a:b]), noise, transitions="exact")
              for a, b in zip(cuts[:-1], cuts[1:])]
    joined = assemble_abstraction(part, chunks)
    for name in ("row_ptr", "col", "lower", "upper", "floor"):
        np.testing.assert_array_equal(getattr(whole.imdp, name), getattr(joined.imdp, name))
    whole.save(tmp_path / "a.npz")
    back = Abstraction.load(tmp_path / "a.npz")
    assert back.transitions == "exact"
    np.testing.assert_array_equal(back.imdp.upper, whole.imdp.upper)


def test_exact_entries_are_never_looser_than_thm1():
    part = _grid()
    lo, hi = _boxes(part, np.random.default_rng(12))
    for noise in (GaussianNoise([0.3, 0.2]), UniformNoise([0.4, 0.3])):
        cb = CellBounds(lo, hi)
        ex, th = abstract(part, cb, noise, transitions="exact"), abstract(part, cb, noise)
        Le, He = _dense_rows(ex)
        Lt, Ht = _dense_rows(th)
        assert np.all(Le >= Lt) and np.all(He <= Ht)  # floors expanded: every entry of every row
        assert np.sum(Le > Lt) > 0


def test_transitions_is_checked():
    part = _small_grid()
    lo = part.cells_lower[None]
    with pytest.raises(InvalidInputError, match="transitions"):
        abstract(part, CellBounds(lo, lo), GaussianNoise([0.1, 0.1]), transitions="joint")
    with pytest.raises(InvalidInputError, match="floor_level"):
        exact_rows(part, CellBounds(lo, lo), GaussianNoise([0.1, 0.1]), floor_level=1.0)


# --------------------------------------------------------------------------- the pipeline option
def test_problem_files_and_the_pipeline_take_transitions(tmp_path):
    from problem_texts import write_one_d

    from robust_imdp.errors import ProblemFileError
    from robust_imdp.io.problem_file import load_problem
    from robust_imdp.pipeline.cache import abstraction_key
    from robust_imdp.pipeline.problem import DEFAULT_TRANSITIONS, TRANSITIONS
    from robust_imdp.abstraction.rows import TRANSITIONS as ROWS_TRANSITIONS
    from robust_imdp.pipeline.run import synthesize_from_data

    assert sorted(TRANSITIONS) == sorted(ROWS_TRANSITIONS)  # one list of values, kept in two layers
    path = write_one_d(tmp_path)
    default = load_problem(path)
    assert default.transitions == DEFAULT_TRANSITIONS == "exact"
    path.write_text(path.read_text() + '[abstraction]\ntransitions = "thm1"\n')
    base = load_problem(path)
    ex = base.replace(transitions="exact")
    assert base.transitions == "thm1" and base.abstraction.transitions == "thm1"
    assert abstraction_key(ex) != abstraction_key(base)  # a cached Thm 1 abstraction is never reused
    assert abstraction_key(ex) == abstraction_key(default)
    res = synthesize_from_data(ex, progress=False, advice=False)
    ref = synthesize_from_data(base, progress=False, advice=False)
    assert res.abstraction.transitions == "exact" and res.parameters["transitions"] == "exact"
    # never looser entry by entry (docs/abstraction.md), so the robust lower bounds cannot fall
    assert np.all(np.asarray(res.synthesis.p_low) >= np.asarray(ref.synthesis.p_low) - 1e-12)
    path.write_text(path.read_text().replace('"thm1"', '"joint"'))
    with pytest.raises(ProblemFileError, match=r"\[abstraction\]\.transitions"):
        load_problem(path)
    with pytest.raises(InvalidInputError, match="transitions"):
        base.replace(transitions="joint")


def test_unlisted_cells_stay_below_the_floor_at_their_worst_image_point():
    # every cell a row does not list must have its largest probability over the image box (the product of the
    # per-axis maxima) at most the floor; the floor is set just below a listed entry's upper bound (floor_tol
    # = 20 x upper / 1.5, least floor = floor_tol / 20), so an entry between the floor and twice it exists
    part = Partition(Box([0.0, 0.0], [6.0, 4.0]), 0.5)
    noise = GaussianNoise([0.35, 0.25])
    lo = np.array([[[2.1, 1.6]]]) * np.ones((1, part.n_cells, 2))
    hi = lo + np.array([0.3, 0.2])
    first = abstract(part, CellBounds(lo, hi), noise, transitions="exact")
    r0, r1 = first.imdp.row_ptr[0], first.imdp.row_ptr[1] - 1  # without the outside entry
    ups = first.imdp.upper[r0:r1]
    pick = ups[(ups > 1e-5) & (ups < 1e-3)][0]
    ab = abstract(part, CellBounds(lo, hi), noise, transitions="exact", floor_tol=20 * pick / 1.5)
    r0, r1 = ab.imdp.row_ptr[0], ab.imdp.row_ptr[1]
    floor = ab.imdp.floor[0]
    assert floor < pick < 2 * floor and pick in ab.imdp.upper[r0:r1]  # listed, and within twice the floor
    listed = set(ab.imdp.col[r0:r1].tolist())
    bp = part.breakpoints
    per_axis = [{i: dense_extrema(lambda y: g_mp(noise, j, y, bp[j][i], bp[j][i + 1]), lo[0, 0, j], hi[0, 0, j],
                                  n=21)[1] for i in range(part.shape[j])} for j in range(2)]
    worst = [float(per_axis[0][i0] * per_axis[1][i1]) for i0 in range(part.shape[0]) for i1 in range(part.shape[1])
             if np.ravel_multi_index((i0, i1), part.shape) not in listed]
    assert worst and max(worst) <= floor
