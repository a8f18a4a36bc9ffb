"""Tests of non-uniform cells (geometry.BoxPartition), their abstraction and the refinement loop (issue 13).

Independent checks used here:
* geometry: brute force over all cells (closed-box tests) for locate and the spatial index;
  labels against the region boxes directly (inside every point, or no interior point in common);
* abstraction: a BoxPartition that is a grid gives the rectilinear IMDP bit for bit (unsplit:
  same order; split everywhere: the finer grid, up to the cell permutation); on refined
  partitions the same closed-form / Monte-Carlo soundness checks as tests/test_abstraction.py,
  and each check sees a 0.1 % shrink of a tight bound;
* refinement: the incrementally rebuilt IMDP equals a fresh abstraction of the final cells;
  budgets and stop reasons; end-to-end validate containment on a refined result.
"""

import numpy as np
import pytest
from scipy import special

from robust_imdp.abstraction.rows import Abstraction, CellBounds, abstract
from robust_imdp.spec.dfa import ltlf_to_dfa
from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.models.geometry import Box, BoxPartition, Partition, Region, partition_from_dict
from robust_imdp.models.noise import GaussianNoise, TruncatedGaussianNoise, UniformNoise
from robust_imdp.synthesis.refine import RefineOptions, refine, select_cells

from soundness_checks import (
    KINDS, check_intervals, check_unlisted_mass, dense_rows, gauss_interval, interval_kinds, shrink_kind, wilson,
)
from test_abstraction import TailModel


def _regions2():
    # one region on the grid, one off it (refines the base breakpoints), one union of two boxes
    return [Region("a", (Box([0.0, 0.0], [0.5, 0.5]),)), Region("b", (Box([-0.8, 0.1], [-0.3, 0.35]),)),
            Region("c", (Box([0.5, -1.0], [1.0, -0.5]), Box([0.5, -0.5], [0.75, 0.0])))]


def _random_refined(rng, rounds=4, base=None):
    """A BoxPartition split at random: bisections along random axes and quad-tree steps."""
    P = BoxPartition(base or Partition(Box([-1, -1], [1, 1]), 0.25, _regions2()))
    for r in range(rounds):
        cells = rng.choice(P.n_cells, size=max(1, P.n_cells // 6), replace=False)
        P = P.split(cells, None if r % 2 else rng.integers(0, P.dim, cells.size))
    return P


# ============================================================================ geometry
def test_locate_agrees_with_the_boxes():
    rng = np.random.default_rng(0)
    P = _random_refined(rng)
    assert P.n_cells > 150 and P.depth.max() >= 3
    assert np.isclose(P.volumes().sum(), 4.0)  # the cells tile X ...
    x = np.concatenate([rng.uniform(-1, 1, (20000, 2)),
                        P.cells_lower, P.cells_upper, 0.5 * (P.cells_lower + P.cells_upper),  # faces, corners
                        [[1.0, 1.0], [-1.0, 1.0], [1.0, -1.0]]])
    c = P.locate(x)
    assert np.all(c >= 0)
    inside = np.all((P.cells_lower[c] <= x) & (x <= P.cells_upper[c]), axis=1)
    assert inside.all()  # ... and every point lies in the closed box of its cell
    # interior points lie in exactly one closed box (... without overlaps)
    xi = rng.uniform(-1, 1, (3000, 2))
    hits = np.all((P.cells_lower[None] <= xi[:, None]) & (xi[:, None] <= P.cells_upper[None]), axis=2)
    assert np.all(hits.sum(axis=1) == 1)
    np.testing.assert_array_equal(np.argmax(hits, axis=1), P.locate(xi))
    # half-open convention of Partition.locate: a point on a shared face goes to the upper cell
    q = int(np.flatnonzero(P.cells_lower[:, 0] > -1)[0])
    face = np.array([[P.cells_lower[q, 0], 0.5 * (P.cells_lower[q, 1] + P.cells_upper[q, 1])]])
    assert P.cells_lower[P.locate(face)[0], 0] == face[0, 0]
    assert np.all(P.locate([[1.5, 0.0], [0.0, -1.01]]) == -1)
    # the deployment table of all faces gives the same cells
    bps, table = P.grid_index()
    idx = tuple(np.clip(np.searchsorted(bps[j], x[:, j], side="right") - 1, 0, len(bps[j]) - 2) for j in range(2))
    np.testing.assert_array_equal(table[idx], c)


def test_unsplit_box_partition_is_the_grid():
    base = Partition(Box([-1, -1], [1, 1]), 0.25, _regions2())
    P = BoxPartition(base)
    for name in ("cells_lower", "cells_upper", "labels"):
        np.testing.assert_array_equal(getattr(P, name), getattr(base, name))
    assert P.atoms == base.atoms and P.outside_state == base.n_cells == P.n_cells
    x = np.random.default_rng(1).uniform(-1.2, 1.2, (5000, 2))
    np.testing.assert_array_equal(P.locate(x), base.locate(x))


def test_labels_are_exact():
    """Bit i set iff the cell lies in a box of region i; else no interior point is in the region."""
    rng = np.random.default_rng(2)
    P = _random_refined(rng, rounds=5)
    lo, up = P.cells_lower, P.cells_upper
    for i, r in enumerate(P.regions):
        inside = np.any([np.all((lo >= b.lower) & (up <= b.upper), axis=1) for b in r.boxes], axis=0)
        np.testing.assert_array_equal((P.labels >> i) & 1 == 1, inside)
        # interior of unlabelled cells: disjoint from every box (open-closed overlap test)
        meets = np.any([np.all((lo < b.upper) & (up > b.lower), axis=1) for b in r.boxes], axis=0)
        assert not np.any(meets & ~inside)
    assert {frozenset(s) for s in P.label_sets()} >= {frozenset(), frozenset({"a"}), frozenset({"c"})}


def test_intersecting_matches_brute_force():
    rng = np.random.default_rng(3)
    P = _random_refined(rng)
    c = rng.uniform(-1.4, 1.4, (400, 2))
    w = rng.uniform(0, 0.3, (400, 2)) * (rng.random((400, 1)) > 0.1)  # some point queries
    lo, hi = c - w, c + w
    lo[:5] = P.cells_lower[:5]  # queries exactly on cell faces
    hi[:5] = P.cells_lower[:5]
    q, cell = P.intersecting(lo, hi)
    meet = np.all((P.cells_lower[None] <= hi[:, None]) & (P.cells_upper[None] >= lo[:, None]), axis=2)
    qb, cb = np.nonzero(meet)
    np.testing.assert_array_equal(q, qb)
    np.testing.assert_array_equal(cell, cb)


def test_split_numbering_and_round_trip(tmp_path):
    base = Partition(Box([0, 0], [1, 1]), 0.5)
    P = BoxPartition(base).split([1, 2])  # quad-tree step: cells 4..9 appended, three per split cell
    assert P.n_cells == 10
    np.testing.assert_array_equal(P.cells_lower[1], [0.0, 0.5])  # cell 1 keeps its lower child
    np.testing.assert_array_equal(P.cells_upper[1], [0.25, 0.75])
    np.testing.assert_array_equal(P.cells_lower[4:7], [[0.0, 0.75], [0.25, 0.5], [0.25, 0.75]])  # C order
    np.testing.assert_array_equal(P.cells_lower[7:10], [[0.5, 0.25], [0.75, 0.0], [0.75, 0.25]])
    Q = P.split([4], axes=[1])
    np.testing.assert_array_equal(Q.cells_upper[4], [0.25, 0.875])
    np.testing.assert_array_equal(Q.cells_lower[10], [0.0, 0.875])
    R = partition_from_dict(Q.to_dict())
    assert isinstance(R, BoxPartition)
    for name in ("cells_lower", "cells_upper", "labels", "depth", "base_cell"):
        np.testing.assert_array_equal(getattr(R, name), getattr(Q, name))
    assert isinstance(partition_from_dict(base.to_dict()), Partition)
    # an abstraction on it saves and loads
    N = Q.n_cells
    cb = CellBounds(np.stack([Q.cells_lower * 0.9]), np.stack([Q.cells_upper * 0.9]))
    ab = abstract(Q, cb, UniformNoise([0.01, 0.01]))
    ab.save(tmp_path / "a.npz")
    ab2 = Abstraction.load(tmp_path / "a.npz")
    assert isinstance(ab2.partition, BoxPartition) and ab2.partition.n_cells == N
    for k in ("col", "lower", "upper", "floor", "row_ptr"):
        np.testing.assert_array_equal(getattr(ab.imdp, k), getattr(ab2.imdp, k))


def test_bad_input_messages():
    P = BoxPartition(Partition(Box([0, 0], [1, 1]), 0.5))
    with pytest.raises(InvalidInputError, match="distinct indices"):
        P.split([0, 0])
    with pytest.raises(InvalidInputError, match="one axis"):
        P.split([0], axes=[2])
    ulp = np.nextafter(1.0, 2.0) - 1.0
    tiny = BoxPartition(Partition(Box([1.0], [1.0 + ulp]), ulp))  # no float strictly between the ends
    with pytest.raises(InvalidInputError, match="too small to bisect"):
        tiny.split([0], axes=[0])
    with pytest.raises(DimensionError, match="lower and upper"):
        P.intersecting(np.zeros((2, 2)), np.zeros((2, 3)))
    with pytest.raises(InvalidInputError, match="base must be a Partition"):
        BoxPartition("grid")
    with pytest.raises(AttributeError, match="immutable"):
        P.n_cells = 3
    with pytest.raises(InvalidInputError, match="invalid split"):
        BoxPartition(P.base, (np.array([0, -1, -1, -1, -1, -1]), np.array([2.0] + [np.nan] * 5),
                              np.array([4, -1, -1, -1, -1, -1]), np.array([-1, 1, 2, 3, 0, 4])))


# ============================================================================ abstraction: grids
NOISES = {"gauss": GaussianNoise([0.03, 0.06]), "trunc": TruncatedGaussianNoise([0.05, 0.05], [0.02, 0.1]),
          "unif": UniformNoise([0.05, 0.01])}


@pytest.mark.parametrize("kind", sorted(NOISES))
@pytest.mark.parametrize("rule", ["optimized", "paper"])
@pytest.mark.parametrize("combine", ["product", "union"])
@pytest.mark.parametrize("learned", [True, False], ids=["gp", "known"])
def test_unsplit_box_partition_gives_the_rectilinear_imdp_bit_for_bit(kind, rule, combine, learned):
    rng = np.random.default_rng(4)
    base = Partition(Box([-1, -1], [1, 1]), 0.25, _regions2())
    N = base.n_cells
    centre = rng.uniform(-1.4, 1.4, (3, N, 2))  # some images partly or fully outside X
    width = rng.uniform(0, 0.3, (3, N, 2))
    cb = CellBounds(centre - width, centre + width, rng.uniform(0, 0.05, (3, N, 2)) if learned else None)
    models = [[TailModel()] * 2] * 3 if learned else None
    a = abstract(base, cb, NOISES[kind], models, eps_rule=rule, combine=combine)
    b = abstract(BoxPartition(base), cb, NOISES[kind], models, eps_rule=rule, combine=combine)
    for k in ("state_ptr", "row_ptr", "col", "lower", "upper", "floor"):
        np.testing.assert_array_equal(getattr(a.imdp, k), getattr(b.imdp, k))
    for k in ("lower_eps", "lower_eta", "containing_cell", "floor_eps", "floor_eta", "nnz_per_row"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


@pytest.mark.parametrize("split", ["all", "axes"])
def test_split_everywhere_gives_the_finer_grid(split):
    rng = np.random.default_rng(5)
    X = Box([-1, -1], [1, 1])
    fine = Partition(X, 0.25)
    B = BoxPartition(Partition(X, 0.5))
    if split == "all":
        B = B.split(np.arange(B.n_cells))
    else:
        B = B.split(np.arange(B.n_cells), np.zeros(B.n_cells, int))
        B = B.split(np.arange(B.n_cells), np.ones(B.n_cells, int))
    perm = fine.locate(0.5 * (B.cells_lower + B.cells_upper))  # box cell i is fine cell perm[i]
    np.testing.assert_array_equal(fine.cells_lower[perm], B.cells_lower)
    N, M = fine.n_cells, 2
    centre = rng.uniform(-1.2, 1.2, (M, N, 2))
    width = rng.uniform(0, 0.2, (M, N, 2))
    std = rng.uniform(0, 0.04, (M, N, 2))
    models = [[TailModel()] * 2] * M
    noise = GaussianNoise([0.03, 0.05])
    a = abstract(fine, CellBounds(centre - width, centre + width, std), noise, models)
    b = abstract(B, CellBounds((centre - width)[:, perm], (centre + width)[:, perm], std[:, perm]), noise, models)
    (la, ua), (lb, ub) = dense_rows(a), dense_rows(b)
    cols = np.append(perm, N)  # the outside state stays last
    np.testing.assert_array_equal(la[:, perm][:, :, cols], lb)
    np.testing.assert_array_equal(ua[:, perm][:, :, cols], ub)
    np.testing.assert_array_equal(a.imdp.floor[:N * M].reshape(N, M)[perm], b.imdp.floor[:N * M].reshape(N, M))


# ============================================================================ abstraction: soundness
def _setpoint_problem(sigma, setpoints, P):
    """x' = c_u + v, v ~ N(0, sigma^2), on a refined 1-D partition: exact T for every cell.

    Every cell's image under mode u is the point c_u, so T does not depend on x and Thm 1 is
    tight where the event is symmetric about c_u (tests/test_sensitivity.py's construction).
    """
    c = np.asarray(setpoints, dtype=float)
    M, N = c.size, P.n_cells
    img = c[:, None, None] * np.ones((M, N, 1))
    ab = abstract(P, CellBounds(img, img), GaussianNoise([sigma]))
    lo, up = P.cells_lower[:, 0], P.cells_upper[:, 0]
    T = gauss_interval((lo[None] - c[:, None]) / sigma, (up[None] - c[:, None]) / sigma)
    out = special.ndtr((-1.0 - c) / sigma) + special.ndtr((c - 1.0) / sigma)
    T = np.concatenate([T, out[:, None]], axis=1)
    return ab, np.broadcast_to(T[:, None, :], (M, N, N + 1))


def _refined_1d():
    """[-1, 1]: base cells of 0.5 and a region cell [0.6, 0.7]; cells split to widths 0.25 .. 0.0625."""
    base = Partition(Box([-1.0], [1.0]), 0.5, [Region("n", (Box([0.6], [0.7]),))])
    P = BoxPartition(base)
    P = P.split([0])  # [-1, -0.75], [-0.75, -0.5]
    P = P.split([P.n_cells - 1])  # [-0.75, -0.625], [-0.625, -0.5]
    P = P.split([int(P.locate([[0.25]])[0]), int(P.locate([[0.9]])[0])])  # [0, .25], [.25, .5]; [.7, .85], ..
    return P


# Tight entries on the refined partition (cf. tests/test_sensitivity.py):
#   sigma 0.035, c = 0.375 (centre of the split cell [0.25, 0.5], margin 3.57 sigma): listed upper 1
#     vs truth 0.99964; c = -0.5625 (centre of [-0.625, -0.5]): listed lower = truth
#   sigma 0.4, c = 0 and c = 2.5: outside upper / lower as there
SETPOINT_PROBLEMS = [(0.035, [0.375, -0.5625, 0.65]), (0.4, [0.0, 2.5])]
TOL_T = 1e-13


@pytest.mark.parametrize("kind", [k for k in KINDS if k != "floor"])
def test_refined_1d_bounds_enclose_exact_probabilities_and_a_shrink_is_caught(kind):
    P = _refined_1d()
    assert len(np.unique(np.round(P.volumes(), 9))) >= 3  # really non-uniform
    real, shrunk = 0, 0
    for sigma, setpoints in SETPOINT_PROBLEMS:
        ab, T = _setpoint_problem(sigma, setpoints, P)
        low, up = dense_rows(ab)
        kinds = interval_kinds(ab)
        real += sum(check_intervals(low, up, T, T, kinds, TOL_T).values())
        floor = ab.imdp.floor[:P.n_cells * len(setpoints)].reshape(P.n_cells, -1).T
        real += check_unlisted_mass(floor, kinds["floor"], T[:, :, None, :], TOL_T)
        low, up = shrink_kind(low, up, kinds, kind)
        shrunk += check_intervals(low, up, T, T, kinds, TOL_T)[kind]
    assert real == 0
    assert shrunk > 0


def test_refined_1d_linear_bounds_enclose_exact_probabilities_at_every_point():
    """x' = a x + c + v with Gaussian and truncated noise: bounds vs the exact T on 201 points per cell."""
    P = _refined_1d()
    modes = [(0.8, 0.0), (1.05, 0.3)]
    lo = np.stack([a * P.cells_lower + c for a, c in modes])
    hi = np.stack([a * P.cells_upper + c for a, c in modes])
    for noise in (GaussianNoise([0.05]), TruncatedGaussianNoise([0.05], [0.08])):
        ab = abstract(P, CellBounds(lo, hi), noise)
        low, up = dense_rows(ab)
        N = P.n_cells
        T = np.empty((2, N, 201, N + 1))
        cdf = lambda z: noise.prob_interval(np.full((z.size, 1), -np.inf), z[:, None])[:, 0]  # noqa: E731
        for u, (a, c) in enumerate(modes):
            for q in range(N):
                mean = a * np.linspace(P.cells_lower[q, 0], P.cells_upper[q, 0], 201) + c
                T[u, q] = np.stack([cdf(P.cells_upper[k, 0] - mean) - cdf(P.cells_lower[k, 0] - mean)
                                    for k in range(N)] + [1 - (cdf(1.0 - mean) - cdf(-1.0 - mean))], axis=1)
        kinds = interval_kinds(ab)
        assert check_intervals(low, up, T.min(axis=2), T.max(axis=2), kinds, 1e-13) == dict.fromkeys(kinds, 0)
        floor = ab.imdp.floor[:N * 2].reshape(N, 2).T
        assert check_unlisted_mass(floor, kinds["floor"], T, 1e-13) == 0


def test_refined_2d_monte_carlo_containment():
    """As test_abstraction's 2-D check, on a randomly refined partition (cells 0.25 .. 0.03125).

    8 cells x 4 points x 2 modes x (N + 1) states; Wilson at z = 5 (5.7e-7 per side): we require 0.
    """
    from test_abstraction import f_true, nonlinear_cell_bounds

    rng = np.random.default_rng(6)
    P = _random_refined(rng, rounds=4, base=Partition(Box([-1, -1], [1, 1]), 0.25))
    cb, models = nonlinear_cell_bounds(P.cells_lower, P.cells_upper)
    noise = GaussianNoise([0.05, 0.05])
    ab = abstract(P, cb, noise, models)
    low, up = dense_rows(ab)
    n, failures = 4000, 0
    small = np.flatnonzero(P.depth >= 2)
    for q in np.concatenate([rng.choice(small, 5, replace=False), rng.choice(P.n_cells, 3, replace=False)]):
        for x in rng.uniform(P.cells_lower[q], P.cells_upper[q], (4, 2)):
            for u in range(2):
                idx = P.locate(f_true(x, u) + noise.sample(n, rng))
                counts = np.bincount(np.where(idx < 0, P.n_cells, idx), minlength=P.n_cells + 1)
                wl, wh = wilson(counts, n, 5.0)
                failures += int(np.sum(wh < low[u, q]) + np.sum(wl > up[u, q]))
    assert failures == 0


# ============================================================================ refinement loop
def _linear_study():
    """2-D: x' = A_u x + b_u + v (uniform noise 0.02), reach 'g' avoiding 'o'; exact image boxes."""
    A = [np.array([[0.8, 0.1], [-0.1, 0.8]]), np.array([[0.9, 0.0], [0.0, 0.7]])]
    b = [np.array([0.15, 0.0]), np.array([0.0, 0.12])]
    regions = [Region("g", (Box([0.5, 0.5], [1.0, 1.0]),)), Region("o", (Box([-0.5, 0.0], [0.0, 0.25]),))]
    base = Partition(Box([-1, -1], [1, 1]), 0.25, regions)

    def bound_cells(lower, upper):  # exact box of an affine image: centre +- |A| radius
        c, r = 0.5 * (lower + upper), 0.5 * (upper - lower)
        lo = np.stack([c @ a.T + bb - r @ np.abs(a).T for a, bb in zip(A, b)])
        hi = np.stack([c @ a.T + bb + r @ np.abs(a).T for a, bb in zip(A, b)])
        return np.nextafter(lo - 1e-12, -np.inf), np.nextafter(hi + 1e-12, np.inf)

    return base, A, b, bound_cells, UniformNoise([0.02, 0.02])


def test_incremental_abstraction_equals_a_fresh_one():
    base, _, _, bound_cells, noise = _linear_study()
    lo, hi = bound_cells(base.cells_lower, base.cells_upper)
    dfa = ltlf_to_dfa("G !o & F g")
    opts = RefineOptions(max_cells=260, max_rounds=4, growth=0.2)
    res = refine(base, CellBounds(lo, hi), bound_cells, noise, dfa, threshold=0.9, options=opts)
    assert len(res.rounds) >= 3 and res.partition.n_cells > base.n_cells
    assert res.partition.n_cells <= 260
    assert sum(r.rows_rebuilt for r in res.rounds[1:]) < sum(r.n_cells for r in res.rounds[1:])  # rows were kept
    fresh = abstract(res.partition, res.cell_bounds, noise)
    for k in ("state_ptr", "row_ptr", "col", "lower", "upper", "floor"):
        np.testing.assert_array_equal(getattr(res.abstraction.imdp, k), getattr(fresh.imdp, k))
    # the children's boxes are their own bounds intersected with the parents' (both sound)
    own_lo, own_hi = bound_cells(res.partition.cells_lower, res.partition.cells_upper)
    assert np.all(res.cell_bounds.image_lower >= own_lo) and np.all(res.cell_bounds.image_upper <= own_hi)
    for r in res.rounds:
        assert sum(r.shares.values()) == pytest.approx(1.0)
        assert sum(r.counts.values()) == r.n_cells
    assert res.rounds[-1].shares["maybe"] < res.rounds[0].shares["maybe"]


def test_budgets_and_stop_reasons():
    base, _, _, bound_cells, noise = _linear_study()
    lo, hi = bound_cells(base.cells_lower, base.cells_upper)
    cb, dfa = CellBounds(lo, hi), ltlf_to_dfa("G !o & F g")
    res = refine(base, cb, bound_cells, noise, dfa, threshold=0.9, options=RefineOptions(max_cells=70, split="all"))
    assert res.stopped == "cell budget" and res.partition.n_cells <= 70
    res = refine(base, cb, bound_cells, noise, dfa, threshold=0.9, options=RefineOptions(max_cells=10_000, max_rounds=1))
    assert res.stopped == "max_rounds" and len(res.rounds) == 2
    res = refine(base, cb, bound_cells, noise, dfa, threshold=0.9,
                 options=RefineOptions(max_cells=10_000, min_cell_size=0.2))  # no half of 0.25 is >= 0.2
    assert res.stopped == "nothing to split" and res.partition.n_cells == base.n_cells
    res = refine(base, cb, bound_cells, noise, dfa, threshold=0.9,
                 options=RefineOptions(max_cells=10_000, time_budget=1e-9))
    assert res.stopped == "time budget"
    res = refine(base, cb, bound_cells, noise, dfa, threshold=0.0, options=RefineOptions(max_cells=10_000))
    assert res.stopped == "no undecided cells"  # threshold 0: every cell is Q_yes


def test_selection_scores_undecided_cells_and_their_successors():
    base, _, _, bound_cells, noise = _linear_study()
    lo, hi = bound_cells(base.cells_lower, base.cells_upper)
    P = BoxPartition(base)
    ab = abstract(P, CellBounds(lo, hi), noise)
    from robust_imdp.synthesis.core import synthesize

    syn = synthesize(ab.imdp, P.labels, P.atoms, ltlf_to_dfa("G !o & F g"), threshold=0.9, outside_state=P.n_cells)
    score = select_cells(P, ab.imdp, syn, 2)
    maybe = syn.classes == "maybe"
    assert maybe.any() and np.all(score[maybe & (syn.error > 0)] > 0)
    assert np.all(score[syn.error == 0] == 0)  # exact values (e.g. obstacles) are never split


def test_selection_scores_by_hand():
    """Cells [0,1], [1,2], [2,4] (volumes 1, 1, 2), one mode; cell 0 is undecided and its row lists
    cell 0 [0, 0.6], cell 1 [0.1, 0.5], cell 2 [0, 0.2] and the outside state [0, 0.1]."""
    from types import SimpleNamespace

    from robust_imdp.models.imdp import IMDP

    P = BoxPartition(Partition(Box([0.0], [4.0]), [2.0], [Region("r", (Box([0.0], [1.0]),))]))  # 0, 1, 2, 4
    assert P.n_cells == 3 and np.allclose(P.volumes(), [1, 1, 2])
    m = IMDP.from_csr([0, 1, 2, 3, 4], [0, 4, 5, 6, 7], [0, 1, 2, 3, 1, 2, 3],
                      [0.0, 0.1, 0.0, 0.0, 1.0, 1.0, 1.0], [0.6, 0.5, 0.2, 0.1, 1.0, 1.0, 1.0])
    syn = SimpleNamespace(classes=np.array(["maybe", "yes", "no"]), error=np.array([0.3, 0.4, 0.25]),
                          p_up_star=np.array([0.95, 1.0, 0.5]), threshold=0.9,
                          strategy=np.zeros((3, 1), int), initial_dfa_state=np.zeros(3, int))
    score = select_cells(P, m, syn, 1)
    # own volume + volume x upper into itself, times the error; successors: 1 x upper x error
    np.testing.assert_allclose(score, [(1 + 0.6) * 0.3, 0.5 * 0.4, 0.2 * 0.25])
    np.testing.assert_array_equal(select_cells(P, m, syn, 1, "undecided"), score)  # cell 2 cannot become Q_yes
    syn.p_up_star[2] = 0.92  # now it can (its strategy's p_up is below 0.9, the best one's is not)
    np.testing.assert_allclose(select_cells(P, m, syn, 1), score + [0, 0, (2 + 2 * 1.0) * 0.25])  # row: itself, [1, 1]
    np.testing.assert_array_equal(select_cells(P, m, syn, 1, "undecided"), score)


def test_options_from_the_problem_table():
    o = RefineOptions.from_dict({"max_cells": 100, "min_cell_size": [0.1, 0.2]})
    assert o.max_rounds == 8 and o.to_dict()["min_cell_size"] == [0.1, 0.2]
    with pytest.raises(InvalidInputError, match="unknown keys"):
        RefineOptions.from_dict({"max_cells": 10, "max_cell": 3})
    with pytest.raises(InvalidInputError, match="needs max_cells"):
        RefineOptions.from_dict({})
    with pytest.raises(InvalidInputError, match="max_cells"):
        RefineOptions(max_cells=0)
    with pytest.raises(InvalidInputError, match="split"):
        RefineOptions(max_cells=10, split="octree")


# ============================================================================ end to end
@pytest.mark.slow
def test_pipeline_refinement_end_to_end(tmp_path):
    """[refine] through synthesize_from_data: a BoxPartition result that validates, a controller
    that locates like the partition, result.json with every cell's box, and the cache."""
    from test_pipeline import CASE, tiny_problem

    from robust_imdp.synthesis.controller import Controller
    from robust_imdp.io.files import load_result, save_result
    from robust_imdp.pipeline.run import synthesize_from_data
    from robust_imdp.validate import validate

    problem = tiny_problem(refine={"max_cells": 160, "max_rounds": 3, "growth": 0.5})
    cache = tmp_path / "cache"
    res = synthesize_from_data(problem, progress=False, abstraction_cache=cache)
    P = res.partition
    assert isinstance(P, BoxPartition) and 64 < P.n_cells <= 160 and P.depth.max() >= 1
    info = res.diagnostics["refinement"]
    assert [r["n_cells"] for r in info["rounds"]][0] == 64 and info["rounds"][-1]["n_cells"] == P.n_cells
    assert info["rounds"][-1]["shares"]["maybe"] <= info["rounds"][0]["shares"]["maybe"]
    assert res.parameters["refine"]["max_cells"] == 160
    syn = res.synthesis
    assert np.all(syn.p_low <= syn.p_up) and np.all(syn.p_up <= syn.p_up_star)
    # labels of refined cells are exact against the problem's region boxes
    for i, atom in enumerate(P.atoms):
        inside = np.any([np.all((P.cells_lower >= lo) & (P.cells_upper <= up), axis=1)
                         for lo, up in problem.regions[atom]], axis=0)
        np.testing.assert_array_equal((P.labels >> i) & 1 == 1, inside)
    # result.json lists every cell's box; the Monte-Carlo check passes on the refined cells
    save_result(res, tmp_path / "out")
    loaded = load_result(tmp_path / "out")
    np.testing.assert_array_equal(loaded.cells_lower, P.cells_lower)
    x = np.random.default_rng(0).uniform(-2, 2, (4000, 2))
    np.testing.assert_array_equal(loaded.locator()(x), P.locate(x))
    small = np.flatnonzero(P.depth >= 1)
    rep = validate(loaded, CASE.system, n_per_cell=200, max_steps=60, rng=5, confidence=0.9999,
                   cells=np.concatenate([small, np.arange(0, 64, 4)]))
    assert rep.outside.size == 0, rep.summary()
    # the deployable controller finds the refined cells, also after save / load
    ctrl = res.controller()
    np.testing.assert_array_equal(ctrl.locate(x), P.locate(x))
    ctrl.save(tmp_path / "ctrl")
    np.testing.assert_array_equal(Controller.load(tmp_path / "ctrl").locate(x), P.locate(x))
    # a second run reuses the refined abstraction from the cache
    again = synthesize_from_data(problem, progress=False, abstraction_cache=cache)
    assert "refine" not in again.timings and again.partition.n_cells == P.n_cells
    np.testing.assert_array_equal(again.synthesis.p_low, syn.p_low)
    assert again.diagnostics["refinement"] == info


def test_refine_table_in_the_problem_file():
    import tomllib

    from robust_imdp.errors import ProblemFileError
    from robust_imdp.io.files import parse_problem_dict

    base = (__import__("pathlib").Path(__file__).parent.parent / "examples/problems/three_mode_linear.toml").read_text()
    spec = parse_problem_dict(tomllib.loads(base))
    assert spec["refine"] is None  # no table: no refinement
    spec = parse_problem_dict(tomllib.loads(base + "\n[refine]\nmax_cells = 2048\nmin_cell_size = 0.01\n"
                                                   "split = \"all\"\nfocus = \"undecided\"\n"))
    assert spec["refine"]["max_cells"] == 2048 and spec["refine"]["min_cell_size"].tolist() == [0.01, 0.01]
    opts = RefineOptions.from_dict(spec["refine"])
    assert opts.split == "all" and opts.focus == "undecided" and opts.max_rounds == 8
    for extra, match in (("max_cell = 3", "unknown key 'max_cell' .*did you mean 'max_cells'"),
                         ("max_cells = 0", "max_cells must lie in"), ("max_cells = 9\nsplit = \"oct\"", "split"),
                         ("max_cells = 9\ngrowth = 1.5", "growth"), ("max_cells = 9\ntime_budget = 0", "time_budget"),
                         ("max_rounds = 2", "missing required key 'max_cells'")):
        with pytest.raises(ProblemFileError, match=match):
            parse_problem_dict(tomllib.loads(base + "\n[refine]\n" + extra + "\n"))
    gp = base.replace("[learning]\n", "[learning]\niid_noise = true\n")
    with pytest.raises(ProblemFileError, match=r"\[refine\] needs"):
        parse_problem_dict(tomllib.loads(gp + "\n[refine]\nmax_cells = 9\n"))
