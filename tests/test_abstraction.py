"""Tests of robust_imdp.abstraction.rows: soundness against closed forms and Monte Carlo.

Independent checks used here:
* 1-D linear system with Gaussian noise: T(q'|x) = Phi((b - a x - c)/s) - Phi((a' - a x - c)/s)
  exactly; the bounds must enclose its values on a dense grid of every cell.
* 2-D nonlinear system (monotone parts, so image boxes are exact from the corners) with a
  bounded unknown part g and unbounded Gaussian noise: Monte-Carlo frequencies per start point
  with Wilson intervals.
* The paper's printed complement vs the Monte-Carlo truth (n = 2, Gaussian noise).
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from robust_imdp.abstraction.rows import Abstraction, CellBounds, _check_rows, abstract
from robust_imdp.errors import DimensionError, InvalidInputError, SoundnessError
from robust_imdp.models.geometry import Box, Partition, Region
from robust_imdp.models.noise import GaussianNoise, TruncatedGaussianNoise, UniformNoise

from soundness_checks import (
    check_intervals, check_unlisted_mass, dense_rows, drop_upper, gauss_interval, interval_kinds, shrink_kind,
)


class TailModel:
    """Stand-in GP error model: P[sup |g - mu| <= eps] >= 1 - 2 exp(-(eps/s)^2 / 2).

    Consistent with any deterministic g with |g - mu| <= s * sqrt(2 ln 2) (= 1.177 s): for
    smaller eps the claimed probability is <= 0.
    """

    def prob_within(self, eps, std_upper):
        eps, s = np.broadcast_arrays(np.asarray(eps, float), np.asarray(std_upper, float))
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(s > 0, eps / s, np.inf)
        p = 1.0 - 2.0 * np.exp(-0.5 * r * r)
        return np.clip(np.where(p < 1, np.nextafter(p - 1e-15, -np.inf), 1.0), 0.0, 1.0)

    def eps_for_prob(self, p, std_upper):
        return np.asarray(std_upper, float) * np.sqrt(2.0 * np.log(2.0 / (1.0 - np.asarray(p, float))))


def dense(ab: Abstraction):
    """(lower, upper) of shape (n_modes, n_cells, n_states), floors expanded."""
    lo, up = ab.imdp.to_dense()
    M, N = ab.n_modes, ab.partition.n_cells
    return lo[: N * M].reshape(N, M, N + 1).transpose(1, 0, 2), up[: N * M].reshape(N, M, N + 1).transpose(1, 0, 2)


# ============================================================================ 1-D closed form
LIN_MODES = [(0.8, 0.0), (1.05, 0.3)]  # x' = a x + c + v


def _lin_setup(cell=0.1):
    P = Partition(Box([-1.0], [1.0]), cell)
    lo = np.stack([a * P.cells_lower + c for a, c in LIN_MODES])
    hi = np.stack([a * P.cells_upper + c for a, c in LIN_MODES])
    return P, CellBounds(lo, hi)


@pytest.mark.parametrize("rule", ["optimized", "paper"])
@pytest.mark.parametrize("combine", ["product", "union"])
@pytest.mark.parametrize("noise", [GaussianNoise([0.05]), TruncatedGaussianNoise([0.05], [0.08])], ids=["gauss", "trunc"])
def test_1d_linear_bounds_enclose_exact_transition_probabilities(rule, combine, noise):
    P, cb = _lin_setup()
    ab = abstract(P, cb, noise, eps_rule=rule, combine=combine)
    low, up = dense(ab)
    bp = P.breakpoints[0]
    M, N = len(LIN_MODES), P.n_cells
    T = np.empty((M, N, 401, N + 1))
    cdf = lambda z: noise.prob_interval(np.full((z.size, 1), -np.inf), z[:, None])[:, 0]  # noqa: E731
    for u, (a, c) in enumerate(LIN_MODES):
        for q in range(N):
            x = np.linspace(P.cells_lower[q, 0], P.cells_upper[q, 0], 401)  # includes both ends
            mean = a * x + c
            T[u, q] = np.stack([cdf(bp[k + 1] - mean) - cdf(bp[k] - mean) for k in range(N)]
                               + [1 - (cdf(1.0 - mean) - cdf(-1.0 - mean))], axis=1)  # (401, N+1)
    # soundness implies lower <= min_grid and upper >= max_grid for every kind of entry (no
    # tolerance needed beyond the 1e-13 accuracy of the closed form evaluated in float64)
    kinds = interval_kinds(ab)
    assert check_intervals(low, up, T.min(axis=2), T.max(axis=2), kinds, 1e-13) == dict.fromkeys(kinds, 0)
    # and the floor's derivation: all unlisted cells together get at most the floor
    floor = ab.imdp.floor[: N * M].reshape(N, M).T
    assert check_unlisted_mass(floor, kinds["floor"], T, 1e-13) == 0


def test_1d_bounds_are_informative():
    P, cb = _lin_setup()
    ab = abstract(P, cb, TruncatedGaussianNoise([0.01], [0.01]))
    low, up = dense(ab)
    # mode 0 (x' = 0.8 x) maps cell [0.3, 0.4] into [0.24, 0.32]: not one cell -> lower 0 there,
    # but cell [-0.05..] style images inside a cell give lower 1 with bounded noise:
    # cell 10 = [0, 0.1] -> [0, 0.08] touches the boundary 0; cell 12 = [0.2, 0.3] -> [0.16, 0.24]
    q = 12
    assert low[0, q].max() == 0.0
    assert np.isclose(up[0, q].sum(), 2.0)  # two cells [0.1,0.2],[0.2,0.3] are possible, each <= 1
    # deterministic-in-a-cell image with margin > bound: exact [1, 1]
    cb2 = CellBounds(np.array([P.cells_lower * 0 + 0.52]), np.array([P.cells_lower * 0 + 0.55]))
    ab2 = abstract(P, cb2, UniformNoise([0.01]))
    l2, u2 = dense(ab2)
    target = P.locate([[0.53]])[0]
    assert np.all(l2[0, :, target] == 1.0) and np.all(u2[0, :, target] == 1.0)
    others = np.delete(u2[0], target, axis=1)
    assert np.all(others == 0.0)  # bounded noise + known dynamics: exact zeros, floor 0


@pytest.mark.parametrize("d", [1, 2])
def test_floor_is_tight_for_the_unlisted_cells(d):
    """A problem where the floor is exercised: known dynamics mapping every cell to the point 0,
    v ~ N(0, 0.05^2 I), and cell boundaries at +-(e_f + 1e-9) on every axis, so the listed
    targets are the middle cell (and the outside state) and the unlisted cells are exactly the
    complement of Im + e_f in X. The floor 1 - prod_j P[|v_j| <= e_f,j] (about 1e-7) is then
    the exact probability of the union of the unlisted cells, up to 1e-5 relative.

    * check_unlisted_mass: 0 violations; the floor x (1 - 1e-3) is flagged (so are the issue's
      x 0.99 and x 0.5 mutations);
    * the per-target check (what the IMDP semantics needs): 0 violations; it can only see a
      shrink below x 0.5 -- with symmetric noise one cell collects at most one of the two tails
      the floor pays for (here the largest single unlisted cell gets floor / (2 d)) -- and it
      does see x 0.45 in 1-D.
    """
    sigma, delta = 0.05, 1e-9
    noise = GaussianNoise([sigma] * d)
    X = Box(-np.ones(d), np.ones(d))
    zero = lambda N: np.zeros((1, N, d))  # noqa: E731  the image of every cell: the point 0
    ab0 = abstract(Partition(X, 2.0), CellBounds(zero(1), zero(1)), noise)
    e = ab0.floor_eps[0, 0] + ab0.floor_eta[0, 0]  # (d,), known dynamics: eps = 0
    part = Partition(X, 2.0, [Region("m", (Box(-(e + delta), e + delta),))])
    N = part.n_cells
    assert N == 3**d
    ab = abstract(part, CellBounds(zero(N), zero(N)), noise)
    np.testing.assert_array_equal(ab.floor_eta[0], np.broadcast_to(e, (N, d)))  # same floor pair
    # exact probabilities of the 3 intervals per axis, product over axes; outside X ~ 1e-88
    edges = np.array([-1.0, -(e[0] + delta), e[0] + delta, 1.0])
    p1 = gauss_interval(edges[:-1] / sigma, edges[1:] / sigma)
    Tc = p1
    for _ in range(d - 1):
        Tc = np.multiply.outer(Tc, p1)
    T = np.broadcast_to(np.append(Tc.ravel(), 1.0 - np.sum(Tc)), (1, N, N + 1))
    low, up = dense_rows(ab)
    kinds = interval_kinds(ab)
    unl = kinds["floor"]
    assert np.all(unl.sum(axis=2) == N - 1)  # only the middle cell (and outside) listed
    floor = ab.imdp.floor[:N].reshape(1, N)
    union = np.sum(np.where(unl, T, 0.0), axis=2)
    assert np.all(union <= floor) and np.all(union >= (1 - 1e-5) * floor)  # tight
    T4 = T[:, :, None, :]
    assert check_unlisted_mass(floor, unl, T4, 1e-15) == 0
    assert check_intervals(low, up, T, T, kinds, 1e-15)["floor"] == 0
    for rel in (1e-3, 0.01, 0.5):
        assert check_unlisted_mass(drop_upper(floor, rel), unl, T4, 1e-15) == N
    assert np.max(np.where(unl, T, 0.0)) <= floor.max() / (2 * d) * (1 + 1e-5)  # one tail of 2 d
    if d == 1:
        l45, u45 = shrink_kind(low, up, kinds, "floor", rel=0.55)  # floor x 0.45
        assert check_intervals(l45, u45, T, T, kinds, 1e-15)["floor"] > 0


# ============================================================================ 2-D Monte Carlo
def f_true(x, u):
    f = np.stack([0.8 * x[..., 0] + 0.1 * x[..., 1] ** 3, 0.9 * x[..., 1] - 0.1 * x[..., 0] ** 3], axis=-1)
    g = 0.01 * np.stack([np.sin(3 * x[..., 0]), np.cos(2 * x[..., 1])], axis=-1)  # |g| <= 0.01 = std
    return f + g + (np.array([0.2, -0.1]) if u == 1 else 0.0)


def _nonlinear_setup():
    P = Partition(Box([-1, -1], [1, 1]), 0.25)
    return (P, *nonlinear_cell_bounds(P.cells_lower, P.cells_upper))


def nonlinear_cell_bounds(L, U):
    """(CellBounds, models) of ``f_true`` over the cells [L, U]: image boxes widened by 1e-12, GP
    std 0.01, tail models."""
    lo, hi = [], []
    for u in range(2):
        shift = np.array([0.2, -0.1]) if u == 1 else 0.0
        # f1 increasing in x1 and x2, f2 increasing in x2 and decreasing in x1 (mu = 0)
        lo.append(np.stack([0.8 * L[:, 0] + 0.1 * L[:, 1] ** 3, 0.9 * L[:, 1] - 0.1 * U[:, 0] ** 3], 1) + shift - 1e-12)
        hi.append(np.stack([0.8 * U[:, 0] + 0.1 * U[:, 1] ** 3, 0.9 * U[:, 1] - 0.1 * L[:, 0] ** 3], 1) + shift + 1e-12)
    cb = CellBounds(np.array(lo), np.array(hi), std_upper=np.full((2, L.shape[0], 2), 0.01))
    models = [[TailModel(), TailModel()] for _ in range(2)]
    return cb, models


def _wilson(k, n, z):
    p = k / n
    den = 1 + z**2 / n
    centre = (p + z**2 / (2 * n)) / den
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / den
    return centre - half, centre + half


@pytest.mark.parametrize("rule", ["optimized", "paper"])
def test_2d_nonlinear_monte_carlo_containment(rule):
    """Per start point x: frequency of landing in each state vs [lower, upper].

    6 cells x 5 points x 2 modes x 65 states = 3,900 comparisons; Wilson intervals at z = 5
    (two-sided 5.7e-7 each) -> expected number of false failures 0.002; we require zero.
    """
    P, cb, models = _nonlinear_setup()
    noise = GaussianNoise([0.05, 0.05])
    ab = abstract(P, cb, noise, models, eps_rule=rule)
    low, up = dense(ab)
    rng = np.random.default_rng(7)
    n = 4000
    failures = 0
    for q in rng.choice(P.n_cells, 6, replace=False):
        xs = rng.uniform(P.cells_lower[q], P.cells_upper[q], (5, 2))
        for u in range(2):
            for x in xs:
                nxt = f_true(x, u) + noise.sample(n, rng)
                idx = P.locate(nxt)
                counts = np.bincount(np.where(idx < 0, P.n_cells, idx), minlength=P.n_cells + 1)
                wl, wh = _wilson(counts, n, 5.0)
                failures += int(np.sum(wh < low[u, q]) + np.sum(wl > up[u, q]))
    assert failures == 0


def test_paper_printed_complement_is_unsound_for_two_gaussian_dims():
    """Known dynamics mapping everything to ~(0, 0); target [0.3, 1] x [-1, 1]; v ~ N(0, 0.1^2 I).

    Printed upper (Thm 1 as printed, P_g = 1): P_g (0 * P_v + prod_i P[|v_i| > eta_i]) + 0
    = 0.01 * 0.01 = 1e-4 with eta at the 0.99 quantile. The truth is
    (Phi(10) - Phi(3)) (Phi(10) - Phi(-10)) ~ 1.35e-3: the printed bound is 13x too small.
    """
    P = Partition(Box([-1, -1], [1, 1]), [1.0, 2.0], [Region("t", (Box([0.3, -1], [1, 1]),))])
    assert P.shape == (3, 1)
    target = 2
    cb = CellBounds(np.full((1, 3, 2), -1e-6), np.full((1, 3, 2), 1e-6))
    noise = GaussianNoise([0.1, 0.1])
    eta = noise.default_eta()
    p_fail = 1 - noise.prob_abs_le(eta)
    printed = np.prod(p_fail)  # P_g = 1 (known dynamics), indicator 0
    assert printed == pytest.approx(1e-4, rel=1e-9)
    x = np.zeros((1, 2)) + noise.sample(400_000, np.random.default_rng(11))
    k = int(np.sum(P.locate(x) == target))
    wl, _ = _wilson(k, x.shape[0], 5.0)
    assert wl > printed  # the printed "upper bound" is below the truth at z = 5
    truth = (stats.norm.cdf(10) - stats.norm.cdf(3)) * (stats.norm.cdf(10) - stats.norm.cdf(-10))
    assert printed < truth
    for rule in ("paper", "optimized"):
        _, up = dense(abstract(P, cb, noise, eps_rule=rule))
        assert np.all(up[0, :, target] >= truth)  # the corrected complement is sound


# ============================================================================ structure / rules
@settings(deadline=None, max_examples=12)
@given(st.integers(0, 2**31 - 1), st.sampled_from(["optimized", "paper"]), st.sampled_from(["product", "union"]),
       st.sampled_from(["gauss", "trunc", "unif"]))
def test_row_sums_and_interval_order(seed, rule, combine, kind):
    rng = np.random.default_rng(seed)
    P = Partition(Box([-1, -1], [1, 1]), 0.25, [Region("g", (Box([0.1, -0.3], [0.6, 0.2]),))])
    N = P.n_cells
    centre = rng.uniform(-1.4, 1.4, (3, N, 2))  # some images partly or fully outside X
    width = rng.uniform(0, 0.3, (3, N, 2))
    std = rng.uniform(0, 0.05, (3, N, 2))
    noise = {"gauss": GaussianNoise([0.03, 0.06]), "trunc": TruncatedGaussianNoise([0.05, 0.05], [0.02, 0.1]),
             "unif": UniformNoise([0.05, 0.01])}[kind]
    ab = abstract(P, CellBounds(centre - width, centre + width, std), noise,
                  [[TailModel()] * 2] * 3, eps_rule=rule, combine=combine)
    m = ab.imdp
    assert m.n_states == N + 1 and m.n_choices == 3 * (N + 1)
    s_low = np.add.reduceat(m.lower, m.row_ptr[:-1])
    s_up = np.add.reduceat(m.upper, m.row_ptr[:-1]) + m.floor * m.n_unlisted
    assert np.all(s_low <= 1 + 1e-12) and np.all(s_up >= 1 - 1e-12)
    assert np.all((0 <= m.lower) & (m.lower <= m.upper) & (m.upper <= 1))
    # every cell row lists the outside state last; the outside state is absorbing
    assert np.all(m.col[m.row_ptr[1:] - 1] == N)
    out_rows = slice(m.state_ptr[N], m.state_ptr[N + 1])
    np.testing.assert_array_equal(m.lower[m.row_ptr[:-1][out_rows]], 1.0)


@pytest.mark.parametrize("noise", [GaussianNoise([0.04, 0.04]), TruncatedGaussianNoise([0.05, 0.05], [0.05, 0.05])],
                         ids=["gauss", "trunc"])
def test_optimised_rule_is_never_looser_than_paper_rule(noise):
    P, cb, models = _nonlinear_setup()
    lo_p, up_p = dense(abstract(P, cb, noise, models, eps_rule="paper"))
    lo_o, up_o = dense(abstract(P, cb, noise, models, eps_rule="optimized"))
    assert np.all(lo_o >= lo_p) and np.all(up_o <= up_p)
    assert np.sum(lo_o > lo_p) + np.sum(up_o < up_p) > 0  # and strictly tighter somewhere


def test_separation_needs_a_gap_on_some_axis():
    # a long thin image overlapping the target on every axis: upper must be 1 (the authors'
    # code used a max over all axes, which declares this pair separated)
    P = Partition(Box([0, 0], [1, 1]), 0.5)
    cb = CellBounds(np.array([[[0.0, 0.45]] * 4]), np.array([[[1.0, 0.46]] * 4]))
    _, up = dense(abstract(P, cb, UniformNoise([0.001, 0.001])))
    assert np.all(up[0, :, :4][:, [0, 2]] == 1.0)  # cells (0,0) and (1,0) overlap the image
    assert np.all(up[0, :, :4][:, [1, 3]] == 0.0)  # separated along axis 1 by 0.04 > 0.002


def test_save_load_round_trip(tmp_path):
    P, cb, models = _nonlinear_setup()
    ab = abstract(P, cb, GaussianNoise([0.05, 0.05]), models)
    ab.save(tmp_path / "abs.npz")
    ab2 = Abstraction.load(tmp_path / "abs.npz")
    for k in ("col", "lower", "upper", "floor", "row_ptr", "state_ptr"):
        np.testing.assert_array_equal(getattr(ab.imdp, k), getattr(ab2.imdp, k))
    np.testing.assert_array_equal(ab.partition.labels, ab2.partition.labels)
    assert ab2.eps_rule == "optimized" and ab2.eta is None
    np.testing.assert_array_equal(ab.floor_eps, ab2.floor_eps)


def test_bad_input_messages():
    P, cb, models = _nonlinear_setup()
    noise = GaussianNoise([0.05, 0.05])
    with pytest.raises(InvalidInputError, match="eta must be finite and > 0"):
        abstract(P, cb, noise, models, eta=[0.1, 0.0])
    with pytest.raises(DimensionError, match="eta must be a float or have shape"):
        abstract(P, cb, noise, models, eta=[0.1, 0.1, 0.1])
    with pytest.raises(InvalidInputError, match="eps_rule must be"):
        abstract(P, cb, noise, models, eps_rule="greedy")
    with pytest.raises(InvalidInputError, match="combine must be"):
        abstract(P, cb, noise, models, combine="max")
    with pytest.raises(InvalidInputError, match="error_models must be given exactly"):
        abstract(P, cb, noise)
    with pytest.raises(DimensionError, match="error_models must have shape"):
        abstract(P, cb, noise, [[TailModel()] * 2])
    with pytest.raises(InvalidInputError, match=r"error_models\[0\]\[1\] must have prob_within"):
        abstract(P, cb, noise, [[TailModel(), object()]] * 2)
    with pytest.raises(DimensionError, match="noise must have dimension 2"):
        abstract(P, cb, GaussianNoise([0.05]), models)
    with pytest.raises(DimensionError, match="cell_bounds must have shape"):
        abstract(Partition(Box([-1, -1], [1, 1]), 0.5), cb, noise, models)
    with pytest.raises(DimensionError, match="image_upper must have shape"):
        CellBounds(np.zeros((1, 4, 2)), np.zeros((1, 4, 3)))
    with pytest.raises(InvalidInputError, match="image_lower must be <= image_upper"):
        CellBounds(np.ones((1, 4, 2)), np.zeros((1, 4, 2)))
    with pytest.raises(InvalidInputError, match="std_upper must be finite and >= 0"):
        CellBounds(np.zeros((1, 4, 2)), np.ones((1, 4, 2)), -np.ones((1, 4, 2)))


def test_soundness_check_names_the_row():
    row_ptr = np.array([0, 2, 3])
    lower = np.array([0.7, 0.5, 1.0])  # row 0: sum(lower) = 1.2 > 1
    upper = np.array([0.8, 0.6, 1.0])
    with pytest.raises(SoundnessError, match=r"row 0 \(state 0, mode 0\)"):
        _check_rows(row_ptr, lower, upper, np.zeros(2), 2, 2)
