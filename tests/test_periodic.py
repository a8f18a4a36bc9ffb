"""Periodic dimensions ([space].periodic, docs/periodic.md): hand-computed rows of images straddling the
seam, the gap and margin on the circle against exact values (a 0.1 % inward shrink fails), a Monte-Carlo
containment check of systems whose trajectories cross the seam (1-D and 2-D, grid and BoxPartition),
wrapping in locate / controller / result file / simulate, residuals modulo the period, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from robust_imdp.abstraction.cell_bounds import CellBounds
from robust_imdp.abstraction.periodic import circle_gap, circle_margin, intervals_on_circle
from robust_imdp.abstraction.rows import abstract
from robust_imdp.errors import DimensionError, InvalidInputError, ProblemFileError
from robust_imdp.models.geometry import Box, BoxPartition, Partition, Region, wrap_points, wrap_residuals
from robust_imdp.models.noise import GaussianNoise, UniformNoise

SHRINK = 1.0 - 1e-3  # the inward shrink every sound bound must not survive


def _circle(h=0.25, kind="grid"):
    p = Partition(Box([0.0], [1.0]), h, periodic=[True])
    return p if kind == "grid" else BoxPartition(p)


def _rows(part, lo, hi, noise):
    n = part.n_cells
    ab = abstract(part, CellBounds(np.full((1, n, 1), lo), np.full((1, n, 1), hi)), noise)
    L, U = ab.imdp.to_dense()
    return L[0], U[0], ab


@pytest.mark.parametrize("kind", ["grid", "boxes"])
def test_straddling_image_by_hand(kind):
    """Circle [0, 1), cells of 0.25, image [0.9, 1.1], v ~ U[-0.05, 0.05]: successors in [0.85, 1) ∪ [0, 0.15].

    By hand: cells [0.75, 1] and [0, 0.25] are met (gap -0.1 to the copy [1, 1.25]) and contain no
    expanded image: [0, 1]; cells [0.25, 0.5] and [0.5, 0.75] are 0.15 away on the circle (> the noise
    bound): upper 0; the outside state is unreachable: [0, 0]. Without the wrap, cell 0 would get
    upper 0 and the outside state mass."""
    L, U, _ = _rows(_circle(kind=kind), 0.9, 1.1, UniformNoise(0.05))
    assert L.tolist() == [0.0, 0.0, 0.0, 0.0, 0.0]
    assert U.tolist() == [1.0, 0.0, 0.0, 1.0, 0.0]


@pytest.mark.parametrize("kind", ["grid", "boxes"])
def test_image_past_the_seam_is_contained(kind):
    """Image [1.1, 1.2] (not wrapped), U[-0.05, 0.05]: successors in [0.05, 0.25] ⊂ cell [0, 0.25] + 1.

    Margin on the circle min(1.1 - 1, 1.25 - 1.2) = 0.05 = the noise bound: eta = 0.05 (1 - 2^-40),
    P[|v| <= eta] = 1 - 2^-40 (by hand); the gap to [0.25, 0.5] + 1 is 0.05 too: upper 2^-40 + rounding."""
    L, U, _ = _rows(_circle(kind=kind), 1.1, 1.2, UniformNoise(0.05))
    p = 1.0 - 2.0 ** -40
    assert L[0] <= p and L[0] > p * (1 - 1e-12) and L[0] > p * SHRINK  # by hand, rounded down only
    assert L[1:].tolist() == [0.0] * 4
    assert U[0] == 1.0 and U[2:].tolist() == [0.0, 0.0, 0.0]
    assert 2.0 ** -40 <= U[1] < 2e-12  # plus the noise probability's relative rounding margin
    _, U2, _ = _rows(_circle(kind=kind), -0.2, -0.1, UniformNoise(0.05))  # the same from below the seam
    assert U2[3] == 1.0 and U2[4] == 0.0


def test_gaussian_gap_on_the_circle_by_hand():
    """Image [0.95, 1.0], v ~ N(0, 0.05^2): the gaps on the circle to [0.25, 0.5] and [0.5, 0.75] are 0.25
    (copy [1.25, 1.5]) and 0.2 (the cell itself): upper = P[|v| >= gap] = erfc(gap / (0.05 sqrt 2))."""
    from math import erfc, sqrt

    L, U, _ = _rows(_circle(), 0.95, 1.0, GaussianNoise(0.05))
    for cell, gap in ((1, 0.25), (2, 0.2)):
        exact = erfc(gap / (0.05 * sqrt(2.0)))
        assert U[cell] >= exact and U[cell] <= exact * 1.001 + 1e-9  # tight: a 0.1 % shrink is below exact
        assert U[cell] * SHRINK < exact or U[cell] - exact < 1e-12
    assert U[0] == 1.0 and U[3] == 1.0 and U[4] == 0.0 and L.sum() == 0.0


@pytest.mark.parametrize("lo_t,hi_t,a,b,gap,margin", [
    (0.0, 0.25, 0.9, 1.1, -0.1, -0.1),       # straddles the seam: copy k = 1
    (0.25, 0.5, 0.9, 1.1, 0.15, -0.35),
    (0.5, 0.75, 0.9, 1.1, 0.15, -0.35),
    (0.0, 0.25, 1.1, 1.2, -0.15, 0.05),      # inside the copy [1, 1.25]
    (0.75, 1.0, -0.2, -0.1, -0.15, 0.05),    # inside the copy [-0.25, 0]
    (0.0, 0.25, 7.1, 7.2, -0.15, 0.05),      # seven periods away
    (0.0, 0.25, 0.2, 1.3, -0.3, -0.8),       # an image wider than the period meets everything
])
def test_circle_gap_and_margin_exact(lo_t, hi_t, a, b, gap, margin):
    """Against the exact min/max over all copies k (hand values); computed bounds are lower bounds, tight
    to 1e-12, so a bound moved 0.1 % inward (larger) exceeds the exact value."""
    g = float(circle_gap(np.array([lo_t]), np.array([hi_t]), np.array([a]), np.array([b]), 0.0, 1.0)[0])
    m = float(circle_margin(np.array([lo_t]), np.array([hi_t]), np.array([a]), np.array([b]), 0.0, 1.0)[0])
    for got, exact in ((g, gap), (m, margin)):
        assert got <= exact + 1e-15 * max(1, abs(a)) and got >= exact - 1e-12
        assert got + 1e-3 * abs(exact) > exact - 1e-12
    # brute force over copies
    ks = np.arange(-20, 21)
    assert g <= np.min(np.maximum(lo_t + ks - b, a - hi_t - ks)) + 1e-15 * max(1, abs(a))
    assert m <= np.max(np.minimum(a - lo_t - ks, hi_t + ks - b)) + 1e-15 * max(1, abs(a))


def test_cyclic_listing():
    bp = np.linspace(0.0, 1.0, 5)
    first, count = intervals_on_circle(bp, np.array([0.85, 0.3, -0.1, 0.1]), np.array([1.15, 0.4, 2.0, 0.1]), 0.0, 1.0)
    listed = [sorted(((first[i] + np.arange(count[i])) % 4).tolist()) for i in range(4)]
    assert listed[0] == [0, 3] and listed[1] == [1] and listed[2] == [0, 1, 2, 3] and listed[3] == [0]


def _containment(part, f_shift, noise, n_samples=4000, seed=1, tol=0.03):
    """Sampled next states' empirical cell frequencies inside [lower - tol, upper + tol] of every row.

    The system: x' = x + f_shift + v on the partition (affine known part, so the image of a cell is the
    cell shifted); tol covers the Monte-Carlo error (4000 samples: 4.5 sigma of a frequency is < 0.035,
    and the Thm 1 bounds are not tight, so a real violation shows as a larger excess)."""
    rng = np.random.default_rng(seed)
    lo = part.cells_lower + f_shift
    hi = part.cells_upper + f_shift
    ab = abstract(part, CellBounds(lo[None], hi[None]), noise)
    L, U = ab.imdp.to_dense()
    worst = 0.0
    for q in range(part.n_cells):
        x = part.cells_lower[q] + rng.random((n_samples, part.dim)) * (part.cells_upper[q] - part.cells_lower[q])
        xn = x + f_shift + noise.sample(n_samples, rng)
        cells = part.locate(xn)
        freq = np.bincount(np.where(cells < 0, part.n_cells, cells), minlength=part.n_cells + 1) / n_samples
        worst = max(worst, float(np.max(freq - U[q])), float(np.max(L[q] - freq)))
    assert worst <= tol, worst
    return L, U


@pytest.mark.parametrize("kind", ["grid", "boxes"])
def test_monte_carlo_containment_1d_across_the_seam(kind):
    part = _circle(0.1, kind)
    L, U = _containment(part, np.array([0.33]), UniformNoise(0.04))
    assert np.all(U[:-1, -1] == 0.0)  # never leaves X on a circle (the last row: the outside state's)
    # cell [0.9, 1] + 0.33 ± 0.04 = [1.19, 1.37]: wrapped onto cells 1, 2, 3 only
    assert np.all(U[9, 1:4] > 0) and U[9, 0] == 0 and np.all(U[9, 4:10] == 0)


def test_monte_carlo_containment_2d_periodic_second_axis():
    part = Partition(Box([0.0, -np.pi], [1.0, np.pi]), [0.25, np.pi / 4], periodic=[False, True])
    L, U = _containment(part, np.array([0.05, 1.0]), GaussianNoise([0.03, 0.1]), n_samples=3000)
    mid = np.flatnonzero(part.cells_lower[:, 0] == 0.25)  # x1 in [0.3, 0.55] after the step: far from x1's faces
    assert np.any(U[:-1, -1] > 0) and np.all(U[mid, -1] < 1e-6)  # X is left only through x1
    bp = BoxPartition(part).split([0, 5, 17], axes=[1, 1, 0])
    _containment(bp, np.array([0.05, 1.0]), GaussianNoise([0.03, 0.1]), n_samples=2000)


def test_wrap_and_locate():
    part = Partition(Box([0.0, 0.0], [1.0, 2.0]), 0.5, periodic=[False, True])
    x = np.array([[0.2, 2.3], [0.2, -0.1], [0.2, 2.0], [1.2, 0.3]])
    w = part.wrap(x)
    assert np.allclose(w[:, 1], [0.3, 1.9, 0.0, 0.3]) and np.array_equal(w[:, 0], x[:, 0])
    assert part.locate(x).tolist() == [0, 3, 0, -1]
    assert part.contains(x).tolist() == [True, True, True, False]
    assert BoxPartition(part).locate(x).tolist() == [0, 3, 0, -1]
    assert Partition.from_dict(part.to_dict()).periodic == (False, True)
    assert "periodic" not in Partition(Box([0.0], [1.0]), 0.5).to_dict()  # unchanged descriptions
    assert np.array_equal(wrap_points(x, [0, 0], [1, 2], None), x)


def test_region_across_the_seam_is_cut():
    space = Box([0.0, 0.0], [1.0, 1.0])
    part = Partition(space, 0.25, {"goal": Region("goal", (Box([0.0, 0.75], [0.5, 1.25]),))}, periodic=[False, True])
    boxes = part.regions[0].boxes
    assert [(b.lower.tolist(), b.upper.tolist()) for b in boxes] == [([0.0, 0.75], [0.5, 1.0]), ([0.0, 0.0], [0.5, 0.25])]
    inside = part.label_sets()
    assert sum("goal" in s for s in inside) == 4
    with pytest.raises(InvalidInputError, match="at most one period wide"):
        Partition(space, 0.25, {"g": Region("g", (Box([0.0, -0.5], [0.5, 0.75]),))}, periodic=[False, True])
    with pytest.raises(DimensionError, match="periodic must be a list of 2 booleans"):
        Partition(space, 0.25, periodic=[True])


def test_residuals_modulo_the_period():
    y = np.array([[6.2, 0.1], [-6.1, 0.0], [0.05, 9.0]])
    yw, bw = wrap_residuals(y, 1e-15, [0.0, 0.0], [2 * np.pi, 1.0], (True, False))
    assert np.allclose(yw[:, 0], [6.2 - 2 * np.pi, -6.1 + 2 * np.pi, 0.05]) and np.array_equal(yw[:, 1], y[:, 1])
    assert bw[2, 0] == 1e-15 and np.all(bw[:2, 0] > 1e-15)  # the wrap's float error joins the bound
    assert np.all(np.abs(yw[:2, 0] - (y[:2, 0] - np.round(y[:2, 0] / (2 * np.pi)) * 2 * np.pi)) <= bw[:2, 0])


TOML = """
[space]
lower = [0.0, 0.0]
upper = [1.0, 6.283185307179586]
cell_size = [0.5, 1.5707963267948966]
{periodic}

[[regions.goal]]
lower = [0.5, {glo}]
upper = [1.0, {ghi}]

[spec]
formula = "F goal"
threshold = 0.5

[data]
path = "d.csv"

[modes.a]
A = [[1.0, 0.0], [0.0, 1.0]]
b = [0.0, 0.5]

[noise]
kind = "uniform"
bound = [0.01, 0.01]

[learning]
rkhs_bound = 0.1
lengthscale = 1.0
"""


def _parse(periodic, glo=0.0, ghi=1.0):
    import tomllib

    from robust_imdp.io.problem_file import parse_problem_dict

    return parse_problem_dict(tomllib.loads(TOML.format(periodic=periodic, glo=glo, ghi=ghi)), where="p.toml")


def test_problem_file_periodic():
    spec = _parse("periodic = [false, true]", 5.5, 7.0)
    assert spec["periodic"] == (False, True)
    assert _parse("periodic = [false, false]")["periodic"] is None and _parse("")["periodic"] is None
    with pytest.raises(ProblemFileError, match=r"p\.toml: \[space\]\.periodic must be a list of 2 booleans.*3 values"):
        _parse("periodic = [false, true, true]")
    with pytest.raises(ProblemFileError, match=r"p\.toml: region 'goal': \[regions\.goal\[0\]\] is 7 wide in dimension 2, which is periodic"):
        _parse("periodic = [false, true]", -0.5, 6.5)
    with pytest.raises(ProblemFileError, match="outside the space"):
        _parse("", 5.5, 7.0)


def test_controller_and_result_file_wrap(tmp_path):
    from robust_imdp.synthesis.controller import Controller

    part = Partition(Box([0.0], [1.0]), 0.25, periodic=[True])
    c = Controller(np.zeros((4, 1), dtype=np.int64), [[0, 0]], 0, [False], ["a"], np.zeros(4, dtype=np.int64),
                   part.breakpoints, [0.0], [1.0], periodic=part.periodic)
    assert c.locate(np.array([[1.1], [-0.1], [0.5]])).tolist() == [0, 3, 2]
    c.save(tmp_path / "ctl")
    assert Controller.load(tmp_path / "ctl").periodic == (True,)
    plain = Controller(np.zeros((4, 1), dtype=np.int64), [[0, 0]], 0, [False], ["a"], np.zeros(4, dtype=np.int64),
                       part.breakpoints, [0.0], [1.0])
    assert plain.locate(np.array([[1.1]])).tolist() == [-1]


@pytest.mark.parametrize("L,H,far", [(0.0, 2 * np.pi, 0), (0.0, 2 * np.pi, 100000), (0.1, 0.1 + 2 * np.pi, 100000),
                                     (-3.3, 1e3 / 7, 10 ** 9)])
def test_circle_gap_and_margin_are_lower_bounds_in_exact_arithmetic(L, H, far):
    """Random targets and images up to ``far`` periods away: the computed gap and margin are <= the exact
    ones (fractions.Fraction, the exact period fl(upper) - fl(lower)); catches rounding off."""
    from fractions import Fraction as F

    rng = np.random.default_rng(3)
    bp = np.linspace(L, H, 17)
    bp[-1] = H
    n = 400
    ell = rng.integers(0, 16, n)
    lo_t, hi_t = bp[ell], bp[ell + 1]
    a = rng.uniform(L, H, n) + rng.integers(-far, far + 1, n) * (H - L)
    b = a + rng.uniform(0, 0.5, n)
    g = circle_gap(lo_t, hi_t, a, b, L, H)
    m = circle_margin(lo_t, hi_t, a, b, L, H)
    T = F(H) - F(L)
    for i in range(n):
        A, B, lo, hi = F(a[i]), F(b[i]), F(lo_t[i]), F(hi_t[i])
        k0 = int(np.floor((a[i] + b[i] - lo_t[i] - hi_t[i]) / (2 * (H - L))))
        ks = range(k0 - 3, k0 + 4)
        assert F(g[i]) <= min(max(lo + k * T - B, A - hi - k * T) for k in ks)
        assert F(m[i]) <= max(min(A - lo - k * T, hi + k * T - B) for k in ks)


def test_shift_enclosure_contains_the_exact_multiple_of_the_period():
    """``_shift_bounds`` encloses the REAL ``k (H - L)``, although it gets the float ``fl(H - L)`` and
    rounds ``k T`` once (checked in exact rationals; an enclosure that keeps the float product misses
    it whenever ``H - L`` or ``k T`` is inexact, which is most draws)."""
    from fractions import Fraction

    from robust_imdp.abstraction.periodic import _shift_bounds

    rng = np.random.default_rng(11)
    inexact = 0
    for _ in range(3000):
        L = float(rng.uniform(-10, 10))
        H = float(L + rng.uniform(0.1, 10))
        k = float(rng.integers(-10**6, 10**6))
        lo, hi = _shift_bounds(np.array([k]), H - L)
        exact = Fraction(k) * (Fraction(H) - Fraction(L))
        assert Fraction(float(lo[0])) <= exact <= Fraction(float(hi[0]))
        inexact += Fraction(k * (H - L)) != exact
    assert inexact > 1000  # the draws do exercise the rounding


PENDULUM = """
[space]
lower = [-3.141592653589793, -2.0]
upper = [3.141592653589793, 2.0]
cell_size = [0.39269908169872414, 0.5]
periodic = [true, false]

[[regions.upright]]
lower = [{lo}, -0.5]
upper = [{hi}, 0.5]

[spec]
formula = "F upright"
threshold = 0.5

[data]
path = "d.csv"

[modes.a]
A = [[1.0, 0.1], [0.0, 1.0]]
b = [0.0, 0.0]

[noise]
kind = "uniform"
bound = [0.01, 0.01]

[learning]
rkhs_bound = 0.1
lengthscale = 1.0
"""


def _write_pendulum(d, lo, hi):
    rng = np.random.default_rng(0)
    x = np.c_[rng.uniform(-3.1, 3.1, 40), rng.uniform(-2, 2, 40)]
    xn = x @ np.array([[1.0, 0.1], [0.0, 1.0]]).T + 0.01 * np.sin(x)
    (d / "d.csv").write_text("x_1,x_2,u,x_next_1,x_next_2\n" + "".join(
        f"{a[0]:.17g},{a[1]:.17g},a,{b[0]:.17g},{b[1]:.17g}\n" for a, b in zip(x, xn)))
    (d / "p.toml").write_text(PENDULUM.format(lo=lo, hi=hi))
    return d / "p.toml"


def test_problem_file_region_across_the_seam_loads_and_labels_both_sides(tmp_path):
    # docs/periodic.md: a region box may cross the seam of a periodic dimension. The file's loader used to
    # check the grid on 1-D partitions without the periodic flag and refused it with an internal message
    # ("region 'upright' box Box(lower=[2.6], upper=[3.68]) must lie inside X").
    import warnings

    from robust_imdp.errors import RobustImdpWarning
    from robust_imdp.io.files import load_problem

    path = _write_pendulum(tmp_path, 2.6, 3.68)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        problem = load_problem(path)
    # the cut adds the breakpoints 2.6 and 3.68 - 2 pi (both off the grid of pi/8): the warning names them
    # and their region, with the wrapped value
    refined = [str(w.message) for w in seen if issubclass(w.category, RobustImdpWarning)]
    assert len(refined) == 1 and "16 -> 18 intervals" in refined[0] and "(upright)" in refined[0], refined
    assert f"{3.68 - 2 * np.pi:g}" in refined[0]
    part = Partition(Box(problem.space_lower, problem.space_upper), problem.cell_size,
                     [Region(n, [Box(lo, up) for lo, up in b]) for n, b in problem.regions.items()],
                     periodic=problem.periodic)
    labelled = [q for q, s in enumerate(part.label_sets()) if "upright" in s]
    centres = 0.5 * (part.cells_lower[labelled] + part.cells_upper[labelled])
    # labelled cells on both sides of the seam: theta in [2.6, pi] and in [-pi, 3.68 - 2 pi], |omega| <= 0.5
    assert np.any(centres[:, 0] > 2.6) and np.any(centres[:, 0] < 3.68 - 2 * np.pi)
    assert np.all((centres[:, 0] > 2.6) | (centres[:, 0] < 3.68 - 2 * np.pi))
    assert np.all(np.abs(centres[:, 1]) < 0.5)


@pytest.mark.parametrize("lo,hi,match", [
    # wider than the period on the periodic dimension
    (-3.5, 3.5, r"p\.toml: region 'upright': \[regions\.upright\[0\]\] is 7 wide in dimension 1, which is "
                r"periodic .* at most one period wide"),
])
def test_problem_file_refused_region_names_file_region_and_form(tmp_path, lo, hi, match):
    from robust_imdp.io.files import load_problem

    with pytest.raises(ProblemFileError, match=match):
        load_problem(_write_pendulum(tmp_path, lo, hi))


def test_problem_file_region_outside_a_non_periodic_dimension_says_the_expected_form(tmp_path):
    from robust_imdp.io.files import load_problem

    path = _write_pendulum(tmp_path, 2.6, 3.0)
    path.write_text(path.read_text().replace("upper = [3.0, 0.5]", "upper = [3.0, 2.5]"))
    with pytest.raises(ProblemFileError, match=r"p\.toml: region 'upright': \[regions\.upright\[0\]\] = .* lies "
                                               r"outside the space .* in dimension 2; expected lower and upper of 2 "
                                               r"numbers each .*only on a periodic dimension"):
        load_problem(path)


def test_overlap_warning_sees_regions_across_the_seam():
    # Two regions meeting only across the seam overlap there (the cells carry both labels); the warning
    # compared the uncut boxes and said nothing.
    import warnings

    from robust_imdp.errors import RegionOverlapWarning
    from robust_imdp.pipeline.preflight import _warn_overlaps
    from types import SimpleNamespace

    problem = SimpleNamespace(
        regions={"a": [(np.array([0.0, 5.5]), np.array([1.0, 7.0]))], "b": [(np.array([0.0, 0.0]), np.array([1.0, 0.5]))]},
        space_lower=np.array([0.0, 0.0]), space_upper=np.array([1.0, 2 * np.pi]), periodic=(False, True),
        dim_names=None, formula="F a & F b")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        _warn_overlaps(problem, SimpleNamespace(atoms=("a", "b")))
    assert [w.category for w in seen] == [RegionOverlapWarning], [str(w.message) for w in seen]
    assert "regions 'a' and 'b' overlap" in str(seen[0].message)
