"""The error-radius diagnostic and the measured advice (finer grid / more data / sub-boxes / local pools).

* The error radius is the excess of each learned image box over the range of the data-fitted
  function over the cell. It must move with a component when the state components are permuted
  (the bound stage's old internal radius did not: 2-D double integrator below, component medians
  0.059 / 0.102 before the swap and 0.094 / 0.044 after it).
* The advice must name the lever that decides more cells: on hand-built boxes whose excess is 0
  only a finer grid can help, and on boxes with a large excess over the noise floor more data
  wins; on a small robot problem like the newcomer's robot2d (noise bound 0.02, 4 modes), the
  finer grid wins and a real run on the finer grid confirms the gain.
"""

import time

import numpy as np
import pytest

from robust_imdp.abstraction.rows import CellBounds
from robust_imdp.synthesis.advice import FittedModes, advice_line, advise, excess_radius, fit_modes
from robust_imdp.spec.dfa import ltlf_to_dfa
from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.models.geometry import Box, Partition, Region
from robust_imdp.models.noise import TruncatedGaussianNoise
from robust_imdp.pipeline.problem import Problem
from robust_imdp.pipeline.run import synthesize_from_data
from robust_imdp.models.system import AffineMap, Dataset


# =========================================================================== the fitted function
def _random_fit(d, n, seed, m=30):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, (m, d))
    maps = [AffineMap(rng.normal(size=(n, d)), rng.normal(size=n)) for _ in range(2)]
    data = [(x, rng.normal(size=(m, n))), (x[::-1] * 0.5, rng.normal(size=(m, n)))]
    return fit_modes(data, maps, rng.uniform(0.3, 2.0, d), 1e-2)


@pytest.mark.parametrize("d", [1, 2, 3])
def test_grid_ranges_equal_pointwise_ranges_over_the_3d_lattice(d):
    fit = _random_fit(d, d, seed=d)
    bps = [np.sort(np.r_[-1.0, np.random.default_rng(10 + j).uniform(-1, 1, 2 + j), 1.0]) for j in range(d)]
    grids = np.meshgrid(*[np.arange(len(b) - 1) for b in bps], indexing="ij")
    idx = np.stack([g.ravel() for g in grids], axis=1)  # C order, as geometry.Partition numbers cells
    lo = np.stack([bps[j][idx[:, j]] for j in range(d)], axis=1)
    up = np.stack([bps[j][idx[:, j] + 1] for j in range(d)], axis=1)
    glo, ghi = fit.grid_ranges(bps)
    clo, chi = fit.cell_ranges(lo, up)
    # the same 3^d points per cell, summed in a different order: agreement to rounding (1e-12)
    np.testing.assert_allclose(glo, clo, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ghi, chi, rtol=0, atol=1e-12)


def test_fit_without_residual_is_the_known_part_and_its_exact_range():
    # residuals 0 -> alpha = 0; the affine part's range over a box is attained at its vertices
    x = np.random.default_rng(0).uniform(0, 1, (20, 2))
    A, b = np.array([[1.0, -2.0], [0.5, 0.25]]), np.array([0.1, -0.3])
    fit = fit_modes([(x, np.zeros((20, 2)))], [AffineMap(A, b)], 1.0, 1e-2)
    glo, ghi = fit.grid_ranges([np.array([0.0, 0.5, 1.0]), np.array([0.0, 1.0])])
    # cell 0 = [0, 0.5] x [0, 1]: row 1 ranges over 0.1 + [0 - 2, 0.5 - 0] = [-1.9, 0.6]
    np.testing.assert_allclose(glo[0, 0], [-1.9, -0.3], atol=1e-12)
    np.testing.assert_allclose(ghi[0, 0], [0.6, -0.3 + 0.25 + 0.25], atol=1e-12)


def test_excess_radius_is_half_the_width_difference_and_never_negative():
    lo, hi = np.array([[[0.0, 0.0]]]), np.array([[[1.0, 0.2]]])
    flo, fhi = np.array([[[0.2, -0.5]]]), np.array([[[0.6, 0.5]]])
    # (1 - 0.4) / 2 = 0.3; the second fit is wider than its box: 0, not negative
    np.testing.assert_allclose(excess_radius(lo, hi, flo, fhi), [[[0.3, 0.0]]])


# =========================================================================== permutation
def _double_integrator(swap: bool) -> Problem:
    """x' = A x + b + (0, -0.1 sin v) on [-1, 1]^2 (position p, velocity v); swap: state (v, p)."""
    rng = np.random.default_rng(5)
    m = 120
    x = rng.uniform(-1, 1, (m, 2))
    A, b = np.array([[1.0, 0.25], [0.0, 1.0]]), np.array([0.0, 0.25])
    noise = np.clip(rng.normal(0, 0.01, (m, 2)), -0.02, 0.02)
    xn = x @ A.T + b + np.column_stack([np.zeros(m), -0.1 * np.sin(x[:, 1])]) + noise
    ls = np.array([4.0, 1.0])
    goal = (np.array([-0.25, -1.0]), np.array([0.25, 1.0]))
    p = [1, 0] if swap else [0, 1]
    return Problem(
        space_lower=np.full(2, -1.0), space_upper=np.full(2, 1.0), cell_size=np.full(2, 0.25),
        regions={"goal": [(goal[0][p], goal[1][p])]}, formula="F goal", threshold=0.9, horizon=None,
        data=Dataset(x[:, p], np.zeros(m, int), xn[:, p], modes=("a",)), mode_names=("a",),
        maps=(AffineMap(A[np.ix_(p, p)], b[p]),), noise=TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02]),
        rkhs_bound=1.0, gp_options={"lengthscale": ls[p]}, misspecification=0.001)


def test_error_radius_moves_with_the_component_when_components_are_swapped():
    one = synthesize_from_data(_double_integrator(False), progress=False, advice=False).diagnostics["eps"]
    two = synthesize_from_data(_double_integrator(True), progress=False, advice=False).diagnostics["eps"]
    by = {(r["mode"], r["component"]): r for r in two}
    for r in one:
        s = by[(r["mode"], 3 - r["component"])]
        # the image boxes agree to ~1e-11 (convex optima at tolerance 1e-9, cells in another order)
        # and the fit is the same function with its arguments swapped: 1e-8
        for key in ("median", "max", "median_over_half_cell"):
            assert s[key] == pytest.approx(r[key], abs=1e-8), (r, s)
    assert one[0]["median"] > 0 and one[1]["median"] > 0


# =========================================================================== the advice
ROBOT_STEPS = {"east": (0.3, 0.0), "west": (-0.3, 0.0), "north": (0.0, 0.3), "south": (0.0, -0.3)}


def _robot_setup(cell: float):
    """robot2d of the newcomer issue (4 x 0.3 steps, goal and obstacle) on [0, 4]^2, noise-free fit data."""
    rng = np.random.default_rng(1)
    data, maps = [], []
    for s in ROBOT_STEPS.values():
        x = rng.uniform(0, 4, (60, 2))
        data.append((x, np.zeros((60, 2))))  # known dynamics: the fit is the known part
        maps.append(AffineMap(np.eye(2), np.array(s)))
    fits = fit_modes(data, maps, 1.0, 1e-2)
    regions = [Region("goal", [Box([3.0, 3.0], [4.0, 4.0])]), Region("obstacle", [Box([1.5, 1.0], [2.5, 3.0])])]
    part = Partition(Box([0.0, 0.0], [4.0, 4.0]), cell, regions)
    return part, fits, ltlf_to_dfa("G !obstacle & F goal")


def _solve_classes(part, cb, noise, dfa):
    from robust_imdp.abstraction.rows import abstract
    from robust_imdp.synthesis.core import synthesize

    syn = synthesize(abstract(part, cb, noise).imdp, part.labels, part.atoms, dfa, threshold=0.9,
                     outside_state=part.outside_state)
    return np.where(np.asarray(syn.p_low) >= 0.9, "yes", "maybe")


def test_advice_names_the_finer_grid_when_the_boxes_have_no_excess():
    part, fits, dfa = _robot_setup(0.25)
    noise = TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02])
    flo, fhi = fits.grid_ranges(part.breakpoints)
    cb = CellBounds(flo, fhi, None)  # boxes exactly the function's range: nothing for data or B to remove
    adv = advise(part, cb, fits, noise, dfa, threshold=0.9, classes=_solve_classes(part, cb, noise, dfa),
                 noise_floor=[0.02, 0.02])
    gains = {lv.name: lv.gain for lv in adv.levers}
    assert adv.winner == "finer grid" and gains["finer grid"] > 0.2
    assert gains["more data"] == 0.0  # the same boxes, the same solve
    assert "advice: finer grid (cell_size [0.125, 0.125]) decides most" in advice_line(adv.to_dict())


def test_advice_names_more_data_when_the_excess_is_far_above_the_noise_floor():
    part, fits, dfa = _robot_setup(0.25)
    noise = TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02])
    flo, fhi = fits.grid_ranges(part.breakpoints)
    cb = CellBounds(flo - 0.2, fhi + 0.2, None)  # excess 0.2 per side, noise floor 0.02
    adv = advise(part, cb, fits, noise, dfa, threshold=0.9, classes=_solve_classes(part, cb, noise, dfa),
                 noise_floor=[0.02, 0.02])
    gains = {lv.name: lv.gain for lv in adv.levers}
    # more data: excess 0.02; finer grid: excess 0.2 kept on cells half as wide
    assert adv.winner == "more data" and gains["more data"] > gains["finer grid"]


def test_advice_pilots_cells_that_a_region_boundary_already_split():
    # cell_size 1 on [0, 2]^2 with a region edge at x = 0.5: the grid's cells [0, 0.5] x [., .] have
    # 2 sub-cells on the finer grid, not 4
    fits = fit_modes([(np.random.default_rng(0).uniform(0, 2, (20, 2)), np.zeros((20, 2)))],
                     [AffineMap(np.eye(2), np.array([0.4, 0.0]))], 1.0, 1e-2)
    part = Partition(Box([0.0, 0.0], [2.0, 2.0]), 1.0, [Region("goal", [Box([0.0, 0.0], [0.5, 2.0])])])
    assert part.n_cells == 6
    flo, fhi = fits.grid_ranges(part.breakpoints)
    seen = []

    def bound_cells(lower, upper, split_tol=None, local_points=None):  # a stand-in bound stage: fitted range +- 0.05
        seen.append(lower.shape[0])
        lo, hi = fits.cell_ranges(lower, upper)
        return lo - 0.05, hi + 0.05

    adv = advise(part, CellBounds(flo - 0.05, fhi + 0.05, None), fits, TruncatedGaussianNoise([0.01] * 2, [0.02] * 2),
                 ltlf_to_dfa("F goal"), threshold=0.9, classes=np.array(["maybe"] * 6), noise_floor=0.02,
                 bound_cells=bound_cells)
    assert seen == [4]  # 4 pilot cells (at least 4), one sub-cell each
    assert {lv.name: lv.excess_ratio for lv in adv.levers}["finer grid"] == pytest.approx(1.0)  # 0.05 / 0.05


def test_advice_checks_its_arguments():
    part, fits, dfa = _robot_setup(0.5)
    flo, fhi = fits.grid_ranges(part.breakpoints)
    with pytest.raises(DimensionError, match="classes must have shape"):
        advise(part, CellBounds(flo, fhi, None), fits, TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02]), dfa, threshold=0.9,
               classes=np.array(["yes"]), noise_floor=0.02)
    with pytest.raises(DimensionError, match="one entry per mode"):
        fit_modes([], [], 1.0, 1e-2)
    assert isinstance(fits, FittedModes)


# =========================================================================== end to end
@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_pipeline import tiny_problem

    cache = tmp_path_factory.mktemp("cache")
    # advice=True: every lever, no time budget (the budget makes "auto" depend on the machine's speed)
    first = synthesize_from_data(tiny_problem(), progress=False, abstraction_cache=cache, advice=True)
    again = synthesize_from_data(tiny_problem(), progress=False, abstraction_cache=cache, advice=True)  # cached
    off = synthesize_from_data(tiny_problem(), progress=False, abstraction_cache=cache, advice=False)
    return first, again, off, tmp_path_factory.mktemp("out")


def test_the_run_prints_and_saves_the_advice(tiny_runs):
    import json

    from robust_imdp.io.files import save_result
    from test_result_schema import SCHEMA, validate_schema

    first, again, off, out = tiny_runs
    adv = first.advice
    # all 40 points per mode are used, so there is no local-pools lever
    assert [lv["name"] for lv in adv["levers"]] == ["finer grid", "more data", "sub-boxes"]
    assert adv["baseline_share"] == pytest.approx(np.mean(first.class_names == "yes"))  # equal cells: share = count
    for lv in adv["levers"]:
        assert lv["gain"] is None or lv["gain"] == pytest.approx(lv["q_yes_share"] - adv["baseline_share"])
    assert "advice" in first.timings and first.summary().splitlines()[-2].startswith("advice: ")
    # the cached abstraction keeps the data-level diagnostics; the advice's estimates come from the cache too
    assert again.from_cache and again.diagnostics == first.diagnostics
    assert again.advice == adv  # the same estimates (no times in the advice itself)
    assert off.advice == {} and "advice" not in off.timings and "advice:" not in off.summary()
    save_result(first, out)
    doc = json.loads((out / "result.json").read_text())
    assert doc["diagnostics"]["advice"]["winner"] == adv["winner"]
    assert validate_schema(doc, SCHEMA) == []
    with pytest.raises(InvalidInputError, match="advice must be 'auto', True or False; got 'yes'"):
        synthesize_from_data(first.problem, progress=False, advice="yes")


# =========================================================================== the sub-box lever
def _lever_split_tol(lever: dict) -> float:
    assert lever["setting"].startswith("split_tol = ")
    return float(lever["setting"].split(",")[0].split("=")[1])


@pytest.fixture(scope="module")
def split_runs():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_pipeline import tiny_problem

    p = tiny_problem()  # l = 2 on cells of 0.5: r / l = 0.125, B = 6, a Taylor term far above SPLIT_TOL
    plain = synthesize_from_data(p, progress=False, advice=True)
    lever = {v["name"]: v for v in plain.advice["levers"]}["sub-boxes"]
    split = synthesize_from_data(p.replace(split_tol=_lever_split_tol(lever)), progress=False, advice=True)
    return plain, lever, split


def test_sub_box_lever_estimates_a_real_split_run(split_runs):
    from robust_imdp.bounds import rkhs

    plain, lv, split = split_runs
    base = plain.advice["baseline_share"]
    real = float(np.mean(split.class_names == "yes"))  # equal cells: share = count share
    assert real > base + 0.2  # sub-boxes decide many more cells here (0.25 -> 0.55 when written)
    # the lever halves the cells once per axis (the largest Taylor term / 2.25, at least SPLIT_TOL)
    tol = _lever_split_tol(lv)
    assert tol > rkhs.SPLIT_TOL and lv["setting"].endswith(" 4 sub-boxes per cell")
    # tighter boxes never lose Q_yes, and the estimate (the pilot cells' median excess ratio applied to
    # every split cell) lands within 0.1 of X of the real run at that split_tol (0.56 against 0.55 when written)
    assert lv["q_yes_share"] >= base and abs(lv["q_yes_share"] - real) <= 0.1
    assert 0 < lv["excess_ratio"] < 1
    # a run that already splits gets no sub-box lever
    assert "sub-boxes" not in [v["name"] for v in split.advice["levers"]]


def test_sub_box_lever_says_when_sub_boxes_change_nothing():
    # cells so small against the lengthscale that no cell is split: no pilot is bounded on sub-boxes
    # (bound_cells would fail), and the note says why
    part, fits, dfa = _robot_setup(0.25)
    noise = TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02])
    flo, fhi = fits.grid_ranges(part.breakpoints)
    cb = CellBounds(flo - 0.05, fhi + 0.05, None)

    def no_pilot(lower, upper, split_tol=None, local_points=None):
        assert split_tol is None, "no pilot is bounded on sub-boxes"
        lo, hi = fits.cell_ranges(lower, upper)
        return lo - 0.05, hi + 0.05

    adv = advise(part, cb, fits, noise, dfa, threshold=0.9, classes=_solve_classes(part, cb, noise, dfa),
                 noise_floor=[0.02, 0.02], bound_cells=no_pilot,
                 sub_box_terms=lambda lo, up: np.full(lo.shape[0], 1e-7))  # a Taylor term far below SPLIT_TOL
    lv = {v.name: v for v in adv.levers}["sub-boxes"]
    assert lv.gain is None and "change nothing" in lv.note and lv.setting.endswith("1 sub-boxes per cell")
    assert "sub-boxes: the Taylor term is below split_tol" in advice_line(adv.to_dict())


# =========================================================================== the local-pools lever
def test_local_pool_lever_estimates_a_real_run_with_all_points():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_pipeline import tiny_problem

    pooled = synthesize_from_data(tiny_problem(local_points=5), progress=False, advice=True)  # pools of 5 of 40
    lv = {v["name"]: v for v in pooled.advice["levers"]}["larger local pools"]
    assert lv["setting"] == "local_points = 40 (all points), now 5"  # at most POOL_ALL_MAX points: all of them
    full = synthesize_from_data(tiny_problem(), progress=False, advice=True)  # all 40 points (below LOCAL_AUTO)
    base = pooled.advice["baseline_share"]
    real = float(np.mean(full.class_names == "yes"))
    assert real > base + 0.05  # the pools cost Q_yes here (0.156 -> 0.25 when written)
    # the pilot cells' median excess ratio applied to every cell lands within 0.05 of X of the real run
    # (0.25 against 0.25 when written); tighter boxes never lose Q_yes
    assert lv["q_yes_share"] >= base and abs(lv["q_yes_share"] - real) <= 0.05
    assert 0 < lv["excess_ratio"] < 1
    # a run on all points gets no pool lever
    assert "larger local pools" not in [v["name"] for v in full.advice["levers"]]


def test_local_pool_rule_of_the_run_and_the_proposal():
    import sys
    from pathlib import Path

    from robust_imdp.pipeline.problem import LOCAL_AUTO, LOCAL_DEFAULT
    from robust_imdp.pipeline.advice_stage import _local_pools
    from robust_imdp.pipeline.run import _residual_data
    from robust_imdp.synthesis.advice import POOL_ALL_MAX, POOL_FACTOR, pool_proposal

    sys.path.insert(0, str(Path(__file__).parent))
    from test_pipeline import tiny_problem, tiny_gp_problem

    p = tiny_problem()
    data = _residual_data(p)
    assert _local_pools(p, data) is None  # 40 points per mode: all of them
    assert _local_pools(p.replace(local_points=40), data) is None  # a pool of every point is all points
    assert _local_pools(p.replace(local_points=7), data) == (7, 40)
    assert _local_pools(tiny_gp_problem(), _residual_data(tiny_gp_problem())) is None  # no local weights
    big = [(np.zeros((LOCAL_AUTO + 1, 2)), None, None), (np.zeros((10, 2)), None, None)]
    assert _local_pools(p, big) == (LOCAL_DEFAULT, LOCAL_AUTO + 1)  # the bound stage's automatic rule
    assert pool_proposal(100, POOL_ALL_MAX) == POOL_ALL_MAX
    assert pool_proposal(100, POOL_ALL_MAX + 1) == POOL_FACTOR * 100
    assert pool_proposal(3000, POOL_ALL_MAX + 1) == POOL_ALL_MAX + 1


def test_advice_line_names_the_tight_preset_only_when_its_levers_win():
    def adv(winner):
        levers = [{"name": n, "setting": "s", "gain": g, "q_yes_share": 0.1 + g, "note": ""}
                  for n, g in (("finer grid", 0.2), ("sub-boxes", 0.3), ("larger local pools", 0.25))]
        return {"winner": winner, "levers": levers, "baseline_share": 0.1}

    for w in ("sub-boxes", "larger local pools"):
        assert "`run --tight` (Problem.tightened())" in advice_line(adv(w))
    assert "--tight" not in advice_line(adv("finer grid"))
    assert "--tight" not in advice_line({**adv(None), "winner": None})


# =========================================================================== B is an assumption, not a lever
def test_b_is_never_a_lever_and_the_advice_says_what_the_guarantee_needs(tiny_runs):
    import re

    first = tiny_runs[0]
    adv = first.advice
    B = float(first.problem.rkhs_bound)  # 6; the data need 3.205, which the smaller-B lever once proposed
    line = first.summary().splitlines()[-2]
    assert all(lv["name"] != "smaller B" for lv in adv["levers"])
    # every B the advice prints is the problem's own: no value below it is offered, let alone one the check refuses
    printed = [float(v) for v in re.findall(r"\bB = ([0-9.eE+-]+)", line + " ".join(lv["setting"] for lv in adv["levers"]))]
    assert printed and all(v == B for v in printed), printed
    need = max(c["minimum"] for c in first.diagnostics["assumption"]["min_norm"])
    assert f"the data need ||g|| >= {need:.3g}" in adv["premise"] and "robust-imdp calibrate" in adv["premise"]
    assert "an assumption, not a lever" in line


def test_advice_line_states_the_budget_rule_and_the_premise():
    adv = {"baseline_share": 0.1, "winner": None, "premise": "the guarantee needs ||g|| <= B = 2",
           "budget_s": 12.0, "levers": [{"name": "finer grid", "setting": "s", "gain": None, "q_yes_share": None,
                                         "note": "about 40 s, more than the 12 s left"}]}
    line = advice_line(adv)
    assert "budget 12 s = 25 % of the run's time before the advice" in line
    assert "B: the guarantee needs ||g|| <= B = 2" in line and "finer grid: about 40 s" in line
    assert "no budget (advice on)" in advice_line({**adv, "budget_s": None})


# =========================================================================== the budget
def _excess_setup():
    part, fits, dfa = _robot_setup(0.25)
    noise = TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02])
    flo, fhi = fits.grid_ranges(part.breakpoints)
    cb = CellBounds(flo - 0.1, fhi + 0.1, None)  # excess 0.1 per side: "more data" changes every box
    return part, fits, dfa, noise, cb, _solve_classes(part, cb, noise, dfa)


def _instant(shares):
    """A stand-in solver: every job's share at once, the jobs it was given recorded."""
    seen = []

    def solve(jobs, deadline):
        for i, job in enumerate(jobs):
            seen.append(job.name)
            yield i, shares[job.name]

    return solve, seen


def test_a_lever_whose_predicted_cost_exceeds_the_budget_is_not_estimated_and_says_why():
    part, fits, dfa, noise, cb, classes = _excess_setup()
    solve, seen = _instant({"more data": 0.5, "finer grid": 0.6})
    # 1 s per listed transition: every re-solve is predicted to take hours, so none fits a 30 s budget
    adv = advise(part, cb, fits, noise, dfa, threshold=0.9, classes=classes, noise_floor=0.02, budget_s=30.0,
                 per_transition=1.0, transitions=1000.0, solver=solve)
    assert seen == [] and all(lv.gain is None for lv in adv.levers) and adv.winner is None
    for lv in adv.levers:
        assert "left of the advice's budget 30 s = 25 % of the run's time" in lv.note and "--advice on" in lv.note
        assert float(lv.note.split("about ")[1].split(" s")[0]) > 30  # what it would cost, in seconds
    assert adv.budget_s == 30.0 and "budget 30 s" in advice_line(adv.to_dict())
    # without a budget (advice=True) every lever is estimated, whatever it costs
    solve, seen = _instant({"more data": 0.5, "finer grid": 0.6})
    adv = advise(part, cb, fits, noise, dfa, threshold=0.9, classes=classes, noise_floor=0.02, budget_s=None,
                 per_transition=1.0, transitions=1000.0, solver=solve)
    assert seen == ["more data", "finer grid"] and adv.winner == "finer grid"


def test_the_finer_grid_is_planned_with_the_cost_measured_on_the_grid_s_own_levers():
    part, fits, dfa, noise, cb, classes = _excess_setup()
    # the run's cost model says 1 ms per transition: the grid's re-solve (1,000 transitions) 1 s, the finer
    # grid's (its sampled transitions, > 30,000) over 30 s, more than the 20 s budget; the re-solve of "more
    # data" then takes no time at all (a stand-in solver), and so is the finer grid predicted to
    solve, seen = _instant({"more data": 0.5, "finer grid": 0.6})
    adv = advise(part, cb, fits, noise, dfa, threshold=0.9, classes=classes, noise_floor=0.02, budget_s=20.0,
                 per_transition=1e-3, transitions=1000.0, solver=solve)
    assert seen == ["more data", "finer grid"] and adv.winner == "finer grid"


def test_a_re_solve_past_the_deadline_is_abandoned():
    from robust_imdp.synthesis.advice import SolveJob, serial_solver

    part, fits, dfa, noise, cb, classes = _excess_setup()
    solve = serial_solver(noise, dfa, threshold=0.9)
    job = SolveJob("more data", part, cb.image_lower, cb.image_upper, 1.0)
    assert list(solve([job, job], time.perf_counter() - 1.0)) == [(0, None), (1, None)]
    (i, share), = list(solve([job], None))
    assert i == 0 and share == pytest.approx(np.mean(classes == "yes"))  # the same boxes: the run's Q_yes
    # abandoned re-solves give levers that say so
    adv = advise(part, cb, fits, noise, dfa, threshold=0.9, classes=classes, noise_floor=0.02, budget_s=1e6,
                 solver=lambda jobs, deadline: ((i, None) for i in range(len(jobs))))
    assert all(lv.gain is None and "stopped at the end of the advice's budget" in lv.note for lv in adv.levers)


def test_the_finer_grid_s_transitions_are_predicted_from_a_sample():
    # Wide boxes and noise (a row spans many cells): the cost of the finer grid is its listed transitions,
    # 2^d times the cells with up to 2^d times the successors per row; 64 sampled sub-cells predict them
    from robust_imdp.abstraction.rows import abstract
    from robust_imdp.synthesis.advice import _sampled_transitions

    part, fits, dfa = _robot_setup(0.25)
    fine = Partition(part.space, 0.125, part.regions)
    flo, fhi = fits.grid_ranges(fine.breakpoints)
    noise = TruncatedGaussianNoise([0.05, 0.05], [0.15, 0.15])
    cb = CellBounds(flo - 0.1, fhi + 0.1, None)
    predicted, per = _sampled_transitions(fine, cb.image_lower, cb.image_upper, noise, {})
    real = float(np.sum(abstract(fine, cb, noise).nnz_per_row))
    assert per > 0 and abs(predicted / real - 1) < 0.15  # 64 of 1,024 cells, evenly spaced: within 15 %


# =========================================================================== cache, interrupt, resume
def _counting_job_share(monkeypatch, fail_at=None):
    import robust_imdp.synthesis.advice as advice_module

    real = advice_module.job_share
    calls = []

    def counted(job, *args, **kwargs):
        calls.append(job.name)
        if fail_at is not None and len(calls) == fail_at:
            raise KeyboardInterrupt
        return real(job, *args, **kwargs)

    monkeypatch.setattr(advice_module, "job_share", counted)
    return calls


def test_an_advice_interrupted_by_ctrl_c_resumes_from_the_estimates_it_saved(tmp_path, monkeypatch, capsys, tiny_runs):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_pipeline import tiny_problem

    whole = tiny_runs[0].advice  # the same problem, uninterrupted
    cache = tmp_path / "cache"
    calls = _counting_job_share(monkeypatch, fail_at=2)  # Ctrl-C in the second re-solve
    with pytest.raises(KeyboardInterrupt):
        synthesize_from_data(tiny_problem(), progress=True, abstraction_cache=cache, advice=True)
    err = capsys.readouterr().err
    assert f"advice interrupted after the solve: 1 estimate kept in {cache}: the same command reuses it" in err
    (entry,) = cache.glob("advice-*.json")
    calls = _counting_job_share(monkeypatch)
    again = synthesize_from_data(tiny_problem(), progress=True, abstraction_cache=cache, advice=True)
    assert len(calls) == 2  # the two estimates not saved; the first is reused
    assert "advice: 1 estimate reused from " + entry.name in capsys.readouterr().err
    assert again.advice == whole
    calls = _counting_job_share(monkeypatch)
    third = synthesize_from_data(tiny_problem(), progress=False, abstraction_cache=cache, advice=True)
    assert calls == [] and third.advice == whole  # a re-run re-solves nothing


def test_the_command_interrupted_in_the_advice_resumes_it(tmp_path, monkeypatch, capsys):
    from problem_texts import write_one_d

    from robust_imdp.cli import main

    path = write_one_d(tmp_path)
    out = tmp_path / "out"
    _counting_job_share(monkeypatch, fail_at=1)
    assert main(["run", str(path), "--out", str(out), "--no-figures", "--advice", "on"]) == 130
    err = capsys.readouterr().err
    assert "advice interrupted after the solve: 0 estimates kept" in err
    assert err.strip().splitlines()[-1].startswith(f"robust-imdp: interrupted; the finished chunks are saved in "
                                                   f"{out / 'cache'}: run the same command again to resume")
    calls = _counting_job_share(monkeypatch)
    assert main(["run", str(path), "--out", str(out), "--no-figures", "--advice", "on"]) == 0
    err = capsys.readouterr().err
    assert "reused abstraction" in err and calls  # the run resumes at the advice
    calls.clear()
    assert main(["run", str(path), "--out", str(out), "--no-figures", "--advice", "on"]) == 0
    assert calls == [] and "reused from" in capsys.readouterr().err


@pytest.mark.slow
def test_the_re_solves_on_a_two_process_cluster_give_the_same_estimates(tiny_runs):
    import sys
    from pathlib import Path

    distributed = pytest.importorskip("distributed")
    sys.path.insert(0, str(Path(__file__).parent))
    from test_pipeline import tiny_problem

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=50) as cluster, distributed.Client(cluster) as client:
        res = synthesize_from_data(tiny_problem(), progress=False, client=client, advice=True)
    assert res.advice == tiny_runs[0].advice  # the same rows, in any order of completion: the same estimates


def test_the_re_solves_spread_over_threads_and_helpers_give_the_one_core_estimates(tiny_runs, monkeypatch):
    """In process on several cores a lever's rows are chunks run side by side (threads of this process and the side
    lane's helper processes, ``advice_stage.spread``); on one core one after the other: the same estimates."""
    import sys
    from pathlib import Path

    from robust_imdp.pipeline import advice_stage, parallel

    sys.path.insert(0, str(Path(__file__).parent))
    from test_pipeline import tiny_problem

    one = synthesize_from_data(tiny_problem(), progress=False, workers=1, advice=True)
    assert one.advice == tiny_runs[0].advice
    monkeypatch.setattr(parallel, "SIDE_MIN_CELL_MODES", 0)  # helpers even for this small problem
    monkeypatch.setattr(parallel, "local_cores", lambda: 2)
    spread_calls = []
    original = advice_stage.spread

    def spy(sched, fn, args, kwargs=None):
        spread_calls.append((fn.__name__, len(args), getattr(getattr(sched, "lane", None), "helpers", None)))
        yield from original(sched, fn, args, kwargs)

    monkeypatch.setattr(advice_stage, "spread", spy)
    res = synthesize_from_data(tiny_problem(), progress=False, advice=True, margins=False)
    assert any(c[0] in ("_rows_task", "_job_task") and c[2] for c in spread_calls)  # with helpers
    assert res.advice == one.advice


# =========================================================================== assumptions per component
def test_advice_with_a_known_component_and_a_periodic_axis():
    # The cylinder of test_periodic_pipeline: rkhs_bound [0.3, 0] (the heading is known) and a periodic
    # heading. Such problems got no advice at all, without a word.
    from test_periodic_pipeline import PI, Cylinder

    system = Cylinder()
    rng = np.random.default_rng(0)
    n = 150
    x = np.column_stack([rng.uniform(0, 2, 2 * n), rng.uniform(-PI, PI, 2 * n)])
    modes = np.repeat([0, 1], n)
    x_next = system.step(x, modes, rng)
    x_next[:, 1] = (x_next[:, 1] + PI) % (2 * PI) - PI

    def problem(cell):
        return Problem.from_arrays(
            x, np.array(system.mode_names)[modes], x_next, lower=[0, -PI], upper=[2, PI], cell_size=cell,
            regions={"goal": ([0, -PI], [2, -2.4]), "obs": ([0, -0.6], [2, 0.6])}, formula="G !obs & F goal",
            threshold=0.5, modes={"plus": (np.eye(2), [0, 0.6]), "minus": (np.eye(2), [0, -0.6])},
            noise=TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02]), rkhs_bound=[0.3, 0.0], lengthscale=1.5,
            periodic=(False, True))

    coarse = synthesize_from_data(problem([0.5, 2 * PI / 8]), progress=False, advice=True)
    adv = coarse.advice
    levers = {lv["name"]: lv for lv in adv["levers"]}
    assert set(levers) >= {"finer grid", "more data"}
    assert levers["finer grid"]["gain"] is not None and levers["more data"]["gain"] is not None
    assert "rkhs_bound of each mode and component (largest 0.3; 2 known components" in adv["premise"]
    # the estimate of the finer grid, checked by a real run on it (0.5 -> 0.25 and 8 -> 16 headings)
    fine = synthesize_from_data(problem([0.25, 2 * PI / 16]), progress=False, advice=False)
    part = fine.partition
    vol = np.prod(part.cells_upper - part.cells_lower, axis=1)  # the regions cut some cells: shares of volume
    real = float(vol[fine.class_names == "yes"].sum() / vol.sum())
    # 0.123 -> about 0.436 estimated, 0.432 real when written
    assert real > adv["baseline_share"] + 0.2 and abs(levers["finer grid"]["q_yes_share"] - real) <= 0.05


def test_auto_advice_has_a_budget_of_a_quarter_of_the_run_before_it():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_pipeline import tiny_problem

    res = synthesize_from_data(tiny_problem(), progress=False)  # advice="auto"
    t = res.timings
    # the run's time before the advice: at least its stages before it, at most all but the advice
    assert 0.25 * sum(t[k] for k in ("check", "bound", "abstract", "synthesize")) <= res.advice["budget_s"]
    assert res.advice["budget_s"] <= 0.25 * (t["total"] - t["advice"])
    assert "budget" in res.summary().splitlines()[-2]
