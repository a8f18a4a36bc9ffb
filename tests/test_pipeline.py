"""A tiny end-to-end run (coarse grid, few points) of the whole pipeline, caching and validation."""

import numpy as np
import pytest

from robust_imdp.casestudies.systems import get_case_study
from robust_imdp.errors import InvalidInputError, UnknownAtomError
from robust_imdp.io.files import load_result, save_result
from robust_imdp.models.noise import TruncatedGaussianNoise
from robust_imdp.pipeline.cache import abstraction_key, bounds_key
from robust_imdp.pipeline.problem import Problem
from robust_imdp.pipeline.run import resynthesize, synthesize_from_data
from robust_imdp.models.system import AffineMap, Dataset
from robust_imdp.validate import validate

CASE = get_case_study("three_mode_linear")


def tiny_problem(formula="G !obs & F des", **changes):
    """3-mode linear system, 40 points per mode, 0.5 grid (64 cells)."""
    sysm = CASE.system
    x, u, x_next = sysm.sample_dataset(40, CASE.lower, CASE.upper, rng=3)
    values = dict(
        space_lower=np.array(CASE.lower), space_upper=np.array(CASE.upper),
        cell_size=np.array([0.5, 0.5]), regions=CASE.regions, formula=formula, threshold=0.9,
        horizon=None, data=Dataset(x, u, x_next, modes=sysm.mode_names),
        mode_names=sysm.mode_names, maps=tuple(AffineMap.zero(2) for _ in range(3)),
        noise=TruncatedGaussianNoise(sysm.sigma, sysm.bound), rkhs_bound=CASE.rkhs_bound,
        gp_options={"lengthscale": 2.0}, misspecification=CASE.misspecification,
    )
    values.update(changes)
    return Problem(**values)


def tiny_gp_problem(**changes):
    """The same data with the GP route (Chowdhury-Gopalan error bound) of the paper."""
    return tiny_problem(error_bound="chowdhury", rkhs_bound=10.0, misspecification=0.0,
                        gp_options={"lengthscale": 4.0, "signal_variance": 10.0}, bound_tol=1e-2,
                        bound_max_boxes=200, **changes)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    return synthesize_from_data(tiny_problem(), progress=False, abstraction_cache=cache), cache


def test_end_to_end_bounds_and_classes(run):
    res, _ = run
    syn = res.synthesis
    assert res.partition.n_cells == 64
    assert np.all(syn.p_low <= syn.p_up) and np.all(syn.p_up <= syn.p_up_star)
    cls = res.class_names
    assert np.all((cls == "yes") == (syn.p_low >= 0.9))  # paper Sec. 5 definition of Q_yes
    assert np.all((cls == "no") == ((syn.p_up < 0.9) & (syn.p_low < 0.9)))
    # first-label semantics: a cell inside des (and not obs) satisfies G !obs & F des at once
    des_bit = 1 << res.partition.atoms.index("des")
    in_des = (res.partition.labels & des_bit) > 0
    assert np.all(syn.p_low[in_des] == 1.0)
    obs_bit = 1 << res.partition.atoms.index("obs")
    assert np.all(syn.p_up[(res.partition.labels & obs_bit) > 0] == 0.0)  # starts in an obstacle
    for stage in ("specify", "partition", "check", "bound", "abstract", "synthesize", "total"):
        assert res.timings[stage] >= 0.0
    assert "Q_yes" in res.summary() and not res.from_cache
    # the "why undecided" line: error radius against the cell, successors, assumption margin
    assert "error radius eps" in res.summary() and "data need ||g|| >=" in res.summary()
    diag = res.diagnostics
    assert diag["confidence"] == 1.0 and diag["error_bound"] == "optimal"
    assert len(diag["eps"]) == 3 * 2 and all(0 < r["median"] <= r["max"] for r in diag["eps"])
    mins = [r["minimum"] for r in diag["assumption"]["min_norm"]]
    assert len(mins) == 6 and 0 < max(mins) <= res.problem.rkhs_bound
    assert diag["successors_per_row"] >= 1.0


def test_cache_reused_for_a_new_formula(run):
    res, cache = run
    again = synthesize_from_data(tiny_problem("F des"), progress=False, abstraction_cache=cache)
    assert again.from_cache and "bound" not in again.timings
    assert again.diagnostics == res.diagnostics  # kept with the cached abstraction
    mem = resynthesize(res, formula="F des", progress=False)
    np.testing.assert_array_equal(again.synthesis.p_low, mem.synthesis.p_low)
    # F des is implied by G !obs & F des, so its lower bound can only be larger
    assert np.all(mem.synthesis.p_low >= res.synthesis.p_low - 1e-12)


def test_cache_keys():
    p = tiny_problem()
    assert abstraction_key(p) == abstraction_key(p.replace(formula="F des", threshold=0.5))
    assert abstraction_key(p) != abstraction_key(p.replace(eta=np.array([0.009, 0.009])))
    assert bounds_key(p) == bounds_key(p.replace(eta=np.array([0.009, 0.009])))
    assert bounds_key(p) != bounds_key(p.replace(rkhs_bound=20.0))


def test_problem_views_by_table_read_the_flat_attributes():
    # problem.space / .spec / .learning / .abstraction mirror the problem file's tables; the flat
    # attributes stay the storage (constructor, replace, cache keys unchanged)
    p = tiny_problem()
    assert p.space.cell_size is p.cell_size and p.space.lower is p.space_lower and p.space.names is None
    assert (p.spec.formula, p.spec.threshold, p.spec.horizon) == ("G !obs & F des", 0.9, None)
    assert p.spec.regions is p.regions
    lr = p.learning
    assert (lr.rkhs_bound, lr.lengthscale, lr.error_bound, lr.iid_noise, lr.local_points) == (
        CASE.rkhs_bound, 2.0, "optimal", False, None)
    assert lr.gp_options is p.gp_options and (lr.bound_tol, lr.bound_max_boxes) == (1e-3, 2000)
    assert lr.method is p.method and p.method.name == "optimal" and p.method.advice_pilot
    ab = p.abstraction
    assert (ab.eta, ab.eps_rule, ab.combine, ab.guarantee, ab.confidence) == (None, "optimized", "product",
                                                                               "confidence", 0.99)
    q = p.replace(cell_size=np.array([1.0, 1.0]), error_bound="ridge")
    assert q.space.cell_size.tolist() == [1.0, 1.0] and q.learning.error_bound == "ridge"
    assert not tiny_gp_problem().method.confidence_in_bounds
    with pytest.raises(AttributeError):
        p.space.cell_size = np.array([1.0, 1.0])  # read-only: change the Problem with replace


def test_result_files_and_monte_carlo_containment(run, tmp_path):
    res, _ = run
    save_result(res, tmp_path)
    loaded = load_result(tmp_path)
    np.testing.assert_array_equal(loaded.p_low, res.synthesis.p_low)
    np.testing.assert_array_equal(loaded.strategy, res.synthesis.strategy)
    assert loaded.classes.tolist() == res.class_names.tolist()
    # Soundness: the true probability from each cell lies in [p_low, p_up]. 64 cells x 200 runs,
    # 99.99 % Wilson intervals: a correct result is flagged with probability < 64 * 1e-4 < 1 %.
    rep = validate(loaded, CASE.system, n_per_cell=200, max_steps=60, rng=5, confidence=0.9999)
    assert rep.outside.size == 0, rep.summary()


def test_unknown_region_fails_before_learning():
    with pytest.raises(UnknownAtomError, match=r"regions \['goal'\] that are not defined"):
        synthesize_from_data(tiny_problem("F goal"), progress=False)


def test_library_controller_agrees_with_the_result_tables(run):
    # controller.py and the table-driven simulation in validate.py are written independently;
    # from the same start state they must choose the same first mode.
    from robust_imdp.io.files import result_to_dict
    from robust_imdp.validate import ResultFile

    res, _ = run
    tables = ResultFile.from_dict(result_to_dict(res))
    locate = tables.locator()
    rng = np.random.default_rng(11)
    ctrl = res.controller()
    for x0 in rng.uniform(-2.0, 2.0, size=(30, 2)):
        q = int(locate(x0[None])[0])
        s = tables.dfa_delta[tables.dfa_initial, tables.label_letters[q]]
        if tables.dfa_accepting[s] or tables.dfa_sink()[s]:
            continue  # decided at once: no mode is applied
        ctrl.reset(x0)
        assert ctrl.act(x0) == tables.modes[tables.strategy[q, s]]


def test_k_step_result_files_and_validation(run, tmp_path):
    # k-step: time-varying strategy (k, n_cells, S) -> strategy_by_time in result.json; runs
    # undecided at the horizon count as not satisfied (exactly the k-step semantics).
    res, _ = run
    k = resynthesize(res, formula="F des", horizon=3, progress=False)
    save_result(k, tmp_path)
    loaded = load_result(tmp_path)
    assert loaded.horizon == 3 and loaded.strategy_by_time.shape[0] == 3
    np.testing.assert_array_equal(loaded.strategy_by_time, k.synthesis.strategy)
    rep = validate(loaded, CASE.system, n_per_cell=100, max_steps=50, rng=7, confidence=0.9999)
    assert rep.max_steps == 3 and int(rep.capped.sum()) == 0
    assert rep.outside.size == 0, rep.summary()


def test_guarantee_modes_and_validation():
    """The confidence mode (default, confidence 0.99) and the paper mode build different
    abstractions, so their cache keys differ (also across confidence levels) and neither reuses
    the other's cache; unknown guarantee names and confidences outside (0, 1) are refused.
    (The brackets of the confidence mode are checked end to end by the tests above.)"""
    p = tiny_gp_problem()
    assert p.guarantee == "confidence" and p.confidence == 0.99
    assert abstraction_key(p) != abstraction_key(p.replace(guarantee="paper"))
    assert abstraction_key(p) != abstraction_key(p.replace(confidence=0.9))
    with pytest.raises(InvalidInputError, match="guarantee 'paper'.*needs error_bound 'chowdhury'"):
        tiny_problem(guarantee="paper")
    with pytest.raises(InvalidInputError, match="guarantee must be one of"):
        p.replace(guarantee="bogus")
    with pytest.raises(InvalidInputError, match="confidence must lie in"):
        p.replace(confidence=1.0)


def test_result_reports_the_synthesis_of_its_own_abstraction(run):
    """The pipeline passes synthesize()'s numbers through unchanged: re-solving the result's own
    abstraction gives bit-identical p_low / p_up / p_up_star and strategy. (The numbers of
    synthesize() itself are checked against brute force and Monte Carlo in test_synthesis.py,
    test_sensitivity.py and test_tight_monte_carlo.py; together this catches, e.g., a p_low
    scaled by 1.01 between synthesis and the result.) The run's nominal model, which ranks the modes of equal
    robust value, is built again from the problem (synthesis.ties)."""
    from robust_imdp.pipeline.nominal_stage import nominal_model
    from robust_imdp.synthesis.core import synthesize

    res, _ = run
    part = res.partition
    again = synthesize(res.abstraction.imdp, part.labels, part.atoms, res.dfa, threshold=res.problem.threshold,
                       horizon=res.problem.horizon, outside_state=part.outside_state,
                       nominal=nominal_model(res.problem, part))
    for name in ("p_low", "p_up", "p_up_star", "strategy"):
        np.testing.assert_array_equal(getattr(res.synthesis, name), getattr(again, name), err_msg=name)


def test_a_scalar_cell_size_in_replace_means_every_axis():
    # Problem.replace(cell_size=0.5) (the dataclass, not from_arrays) crashed in the bound stage's diagnostics;
    # one number is the same width on every axis: the same problem, key and result as the per-axis list
    from robust_imdp.pipeline.cache import abstraction_key

    p = tiny_problem()
    q = p.replace(cell_size=float(p.cell_size[0]))
    np.testing.assert_array_equal(q.cell_size, p.cell_size)
    assert abstraction_key(q) == abstraction_key(p)
    r = synthesize_from_data(q, progress=False, advice=False, margins=False)
    assert r.partition.n_cells == 64
