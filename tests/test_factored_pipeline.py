"""The factored form end to end (docs/factored.md, "In the pipeline"): the chunked abstraction against the one-pass
marginals, synthesis on a FactoredIMDP against the joint exact IMDP of the same problem (never below it on any cell,
Theorem 2 up to the unlisted rest mass), Monte Carlo of the true system, the form's selection and its messages, the
cache, result files and the deployed controller, refinement, export, the advice, the margins and suggest."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from robust_imdp.errors import InvalidInputError, ProblemFileError, ResourceError

# The factored value is never below the joint exact IMDP's when every axis lists its whole support (Theorem 2).
# Real marginals leave an unlisted rest of at most ~AXIS_TOL / 2 = 5e-10 per axis, valued at the global extreme:
# over a 10-step horizon in 2-D that moves a value by at most 10 * 2 * 5e-10 = 1e-8; the unbounded solves stop at
# precision 1e-8. So "never below" is checked to 2e-8, far below any class change we could miss (the
# tests also count the Q_yes cells lost: 0).
RANK_TOL = 2e-8


# --------------------------------------------------------------------------- problems
def _car_problem(cell=2.0, horizon=6, threshold=0.3, formula="G !avoid & F target", **kw):
    """Car parking (x' = 0.9 x + 0.7 u + w, w ~ N(0, I)) on a coarse grid: known dynamics, noise wider than a cell."""
    from robust_imdp import GaussianNoise, Problem

    inputs = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)]
    modes = {f"u{a:+d}{b:+d}": (0.9 * np.eye(2), 0.7 * np.array([a, b], float)) for a, b in inputs}
    return Problem.from_arrays(
        None, None, None, lower=[-10, -10], upper=[10, 10], cell_size=cell,
        regions={"target": ([4, -4], [10, 0]), "avoid": ([4, 0], [10, 4])}, formula=formula, threshold=threshold,
        horizon=horizon, modes=modes, noise=GaussianNoise([1.0, 1.0]), rkhs_bound=0.0, transitions="exact", **kw)


class _Car:
    """The true car-parking system (``validate``'s duck type)."""

    def __init__(self, problem):
        self.mode_names = tuple(problem.mode_names)
        self.u = np.array([[int(n[1:3]), int(n[3:5])] for n in self.mode_names], float)

    def step(self, x, modes, rng):
        return 0.9 * x + 0.7 * self.u[modes] + rng.standard_normal(x.shape)


def _learned_problem(**kw):
    """A 2-D data-driven problem (RKHS route): x' = 0.8 x + 0.05 sin(x) + u + v, v uniform in [-0.05, 0.05], two modes."""
    from robust_imdp import Problem, UniformNoise

    rng = np.random.default_rng(3)
    x = rng.uniform(-2, 2, (160, 2))
    u = np.repeat(["left", "right"], 80)
    shift = np.where(u[:, None] == "left", [-0.3, 0.0], [0.3, 0.0])
    xn = 0.8 * x + 0.05 * np.sin(x) + shift + rng.uniform(-0.05, 0.05, x.shape)
    modes = {"left": (0.8 * np.eye(2), np.array([-0.3, 0.0])), "right": (0.8 * np.eye(2), np.array([0.3, 0.0]))}
    return Problem.from_arrays(
        x, u, xn, lower=[-2, -2], upper=[2, 2], cell_size=0.5, regions={"goal": ([1, -1], [2, 1])},
        formula="F goal", threshold=0.5, horizon=5, modes=modes, noise=UniformNoise([0.05, 0.05]), rkhs_bound=0.2,
        lengthscale=1.0, misspecification=0.0, transitions="exact", **kw)


def _run(problem, **kw):
    from robust_imdp.pipeline.run import synthesize_from_data

    kw = {"progress": False, "advice": False, **kw}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return synthesize_from_data(problem, **kw)


# --------------------------------------------------------------------------- the abstraction in chunks
def test_chunked_factored_rows_equal_the_one_pass_marginals():
    """Chunks of any size, assembled, give the arrays of marginals.axis_marginals bit for bit (periodic axis
    included): the k of all cells goes to every chunk. A chunk's own k is refused when too short."""
    from robust_imdp import GaussianNoise
    from robust_imdp.abstraction.cell_bounds import CellBounds
    from robust_imdp.abstraction.factored import assemble_factored, axis_lengths, factored_rows
    from robust_imdp.abstraction.marginals import axis_marginals
    from robust_imdp.models.geometry import Box, Partition

    part = Partition(Box([-1, -1], [1, 1]), [0.25, 0.5], periodic=(False, True))
    rng = np.random.default_rng(0)
    centre = 0.5 * (part.cells_lower + part.cells_upper)
    lo = np.stack([0.8 * part.cells_lower, 0.7 * part.cells_lower + 0.1]) - rng.uniform(0, 0.2, (2, 32, 2))
    hi = np.stack([0.8 * part.cells_upper, 0.7 * part.cells_upper + 0.1]) + rng.uniform(0, 0.2, (2, 32, 2))
    lo[0, 5] = hi[0, 5] = 0.9 * centre[5]  # a point image
    noise = GaussianNoise([0.1, 0.3])
    ref = axis_marginals(part, lo, hi, noise)
    cb = CellBounds(lo, hi, None)
    k = axis_lengths(part, cb, noise)
    for size in (1, 5, 32):
        chunks = [factored_rows(part, CellBounds(lo[:, s:s + size], hi[:, s:s + size], None), noise, k)
                  for s in range(0, 32, size)]
        ab = assemble_factored(part, chunks)
        for a, b in zip(ref, ab.model.axes):
            for name in ("start", "lower", "upper", "out_lower", "out_upper", "rest_upper"):
                assert np.array_equal(getattr(a, name), getattr(b, name)), (size, name)
    wide = np.argmax(hi[:, :, 0] - lo[:, :, 0])
    with pytest.raises(InvalidInputError, match="exceeds k"):
        factored_rows(part, CellBounds(lo, hi, None), noise, (1, k[1]))
    assert wide >= 0


def test_factored_abstraction_file_round_trip_and_refusals(tmp_path):
    from robust_imdp.abstraction.factored import FactoredAbstraction, abstract_factored, is_factored_file
    from robust_imdp.abstraction.rows import abstract
    from robust_imdp.errors import InvalidModelError
    from robust_imdp.pipeline.cache import load_abstraction_file

    p = _car_problem(cell=4.0)
    from robust_imdp.models.geometry import Box, Partition

    part = Partition(Box(p.space_lower, p.space_upper), p.cell_size)
    from robust_imdp.pipeline.bound_stage import known_cell_bounds
    from robust_imdp.abstraction.cell_bounds import CellBounds

    cb = CellBounds(*known_cell_bounds(p, part.cells_lower, part.cells_upper), None)
    fa = abstract_factored(part, cb, p.noise)
    fa.save(tmp_path / "f.npz")
    back = load_abstraction_file(tmp_path / "f.npz")
    assert isinstance(back, FactoredAbstraction) and back.partition.to_dict() == part.to_dict()
    for a, b in zip(fa.model.axes, back.model.axes):
        assert np.array_equal(a.lower, b.lower) and np.array_equal(a.rest_upper, b.rest_upper)
    joint = abstract(part, cb, p.noise, transitions="exact")
    joint.save(tmp_path / "j.npz")
    assert not is_factored_file(tmp_path / "j.npz")
    assert load_abstraction_file(tmp_path / "j.npz").imdp.n_states == part.n_cells + 1
    with pytest.raises(InvalidModelError, match="not a factored abstraction"):
        FactoredAbstraction.load(tmp_path / "j.npz")


# --------------------------------------------------------------------------- synthesis on a FactoredIMDP
@pytest.mark.parametrize("formula,horizon", [("G !avoid & F target", 6), ("F target", None), ("G !avoid", 6)])
def test_synthesis_on_the_factored_model_is_never_below_the_joint_exact_one(formula, horizon):
    """Same boxes, same marginals: the factored p_low >= the joint exact IMDP's on every cell (reach, unbounded,
    safety); and >= the joint expansion of the factored model itself (Theorem 2, its own joint polytope)."""
    from robust_imdp.abstraction.cell_bounds import CellBounds
    from robust_imdp.abstraction.factored import abstract_factored
    from robust_imdp.abstraction.rows import abstract
    from robust_imdp.models.geometry import Box, Partition, Region
    from robust_imdp.pipeline.bound_stage import known_cell_bounds
    from robust_imdp.spec.api import to_dfa
    from robust_imdp.synthesis.core import synthesize

    p = _car_problem(cell=2.5)
    part = Partition(Box(p.space_lower, p.space_upper), p.cell_size,
                     [Region(n, [Box(lo, up) for lo, up in b]) for n, b in p.regions.items()])
    cb = CellBounds(*known_cell_bounds(p, part.cells_lower, part.cells_upper), None)
    fa = abstract_factored(part, cb, p.noise)
    ja = abstract(part, cb, p.noise, transitions="exact")
    dfa = to_dfa(formula)
    kw = dict(threshold=0.3, horizon=horizon, outside_state=part.outside_state)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unbounded factored solves may report an end component (docs)
        f = synthesize(fa.model, part.labels, part.atoms, dfa, **kw)
        j = synthesize(ja.imdp, part.labels, part.atoms, dfa, **kw)
        e = synthesize(fa.to_joint(), part.labels, part.atoms, dfa, **kw)
    assert f.semantics == j.semantics and f.strategy.shape == j.strategy.shape and f.n_modes == 9
    assert np.all(f.p_low >= j.p_low - RANK_TOL), float(np.min(f.p_low - j.p_low))
    assert np.all(f.p_low >= e.p_low - RANK_TOL), float(np.min(f.p_low - e.p_low))
    assert np.all(f.p_low <= f.p_up) and np.all(f.p_up <= f.p_up_star)
    yes_f, yes_j = f.p_low >= 0.3, j.p_low >= 0.3
    assert not np.any(yes_j & ~yes_f)
    if horizon is not None:  # the product set is strictly smaller here: some cell gains (a check with teeth)
        assert np.max(f.p_low - j.p_low) > 1e-3


def test_one_mode_takes_two_solves_and_gives_the_same_bounds_as_four():
    """With one mode every strategy is that mode: the factored synthesis skips the two evaluations; its bounds
    equal the explicit evaluation of the only strategy against both adversaries."""
    from robust_imdp.models.factored import AxisMarginals, FactoredIMDP
    from robust_imdp.solvers.factored import solve_factored_product
    from robust_imdp.spec.api import to_dfa
    from robust_imdp.synthesis.core import synthesize

    rng = np.random.default_rng(1)
    n, k = 6, 3
    axes = []
    for i in range(2):
        lo = rng.uniform(0.05, 0.2, (1, n * n, k))  # sum of lowers <= 0.6; of uppers + 0.2 outside >= 1.1
        up = lo + rng.uniform(0.3, 0.4, (1, n * n, k))
        start = rng.integers(0, n - k + 1, (1, n * n))
        out_lo = np.zeros((1, n * n))
        out_up = np.full((1, n * n), 0.2)
        axes.append(AxisMarginals(n=n, periodic=False, start=start, lower=lo, upper=np.minimum(up, 1.0),
                                  out_lower=out_lo, out_upper=out_up, rest_upper=np.zeros((1, n * n)), axis=i))
    m = FactoredIMDP(shape=(n, n), axes=tuple(axes))
    labels = np.zeros(n * n, dtype=np.int64)
    labels[:4] = 1
    dfa = to_dfa("F a")
    syn = synthesize(m, labels, ("a",), dfa, threshold=0.5, horizon=4, outside_state=n * n)
    assert len(syn.runs) == 4 and syn.n_modes == 1
    letters = np.r_[labels, 0]
    pi = np.zeros((4, dfa.n_states, n * n + 1), dtype=np.int64)
    lo = solve_factored_product(m, letters, dfa, avoid=[n * n], horizon=4, strategy=pi, adversary="pessimistic")
    up = solve_factored_product(m, letters, dfa, avoid=[n * n], horizon=4, strategy=pi, adversary="optimistic")
    np.testing.assert_array_equal(syn.p_low, lo.initial_lower[:n * n])
    np.testing.assert_array_equal(syn.p_up, np.minimum(up.initial_upper[:n * n], syn.p_up_star))


def test_unbounded_factored_iteration_stops_at_its_fixed_point():
    """An end component keeps the upper side at 1 (no deflation): the iteration stops when a sweep changes
    nothing, says converged=False, and does not run to max_iterations."""
    from robust_imdp.errors import ConvergenceWarning
    from robust_imdp.models.factored import AxisMarginals, FactoredIMDP
    from robust_imdp.solvers.factored import solve_factored_reachability

    ax = AxisMarginals(n=2, periodic=False, start=np.array([[0, 1], [1, 1]]),
                       lower=np.array([[[1.0], [1.0]], [[0.5], [1.0]]]), upper=np.array([[[1.0], [1.0]], [[0.5], [1.0]]]),
                       out_lower=np.array([[0.0, 0.0], [0.5, 0.0]]), out_upper=np.array([[0.0, 0.0], [0.5, 0.0]]),
                       rest_upper=np.zeros((2, 2)))
    m = FactoredIMDP(shape=(2,), axes=(ax,))
    with pytest.warns(ConvergenceWarning, match="sound but loose"):
        r = solve_factored_reachability(m, [1], avoid=[2], precision=1e-9, max_iterations=10 ** 7)
    # the ordered pass (solvers/factored.py): two sweeps and one refuted upper guess (the self-loop keeps 1), then
    # one whole-model sweep that changes nothing: 4, far from max_iterations
    assert not r.converged and r.iterations <= 5
    assert r.lower[0] == pytest.approx(0.5, abs=1e-12) and r.upper[0] == 1.0  # 1/2: mode 1; 1: the self-loop


# --------------------------------------------------------------------------- the pipeline
def test_pipeline_factored_against_joint_and_monte_carlo(tmp_path):
    """synthesize_from_data with form 'factored' and 'joint' (exact transitions, same grid): the factored p_low is
    >= the joint one on every cell, no Q_yes cell is lost, and 200 runs per cell of the true system under the
    factored controller stay inside [p_low, p_up] (validate's Wilson test)."""
    from robust_imdp.validate import validate

    p = _car_problem(cell=2.0, horizon=6)
    f = _run(p.replace(form="factored"))
    j = _run(p.replace(form="joint"))
    from robust_imdp.abstraction.factored import is_factored

    assert is_factored(f.abstraction) and not is_factored(j.abstraction)
    assert f.parameters["form"] == "factored" and "form" not in j.parameters
    assert f.diagnostics["factored"]["numbers_per_row"] == f.abstraction.numbers_per_row
    assert np.all(f.p_low >= j.p_low - RANK_TOL)
    assert not np.any((j.p_low >= p.threshold) & (f.p_low < p.threshold))
    assert f.counts["yes"] > j.counts["yes"]  # wide noise: the product set certifies more (car parking: 381 vs 315)
    rep = validate(f, _Car(p), n_per_cell=200, rng=7)
    assert rep.passed, (len(rep.outside), rep.allowed_outside)


def test_form_selection_and_its_messages(capsys):
    from robust_imdp.pipeline.cache import abstraction_key

    p = _car_problem()
    form, why = p.form_choice()
    assert form == "factored" and "numbers per row" in why  # noise wider than a cell: long joint rows
    assert p.replace(form="joint").form_choice() == ("joint", "[abstraction].form = 'joint'")
    thm1 = p.replace(transitions="thm1")
    form, why = thm1.form_choice()
    assert form == "joint" and "transitions = 'thm1'" in why
    # the key: factored differs; a joint one is the key the joint form had before (no form in it)
    assert abstraction_key(p) != abstraction_key(p.replace(form="joint"))
    assert abstraction_key(thm1) == abstraction_key(thm1.replace(form="joint"))
    # explicit 'factored' where it does not apply: refused, naming the setting
    with pytest.raises(InvalidInputError, match="transitions"):
        p.replace(form="factored", transitions="thm1")
    with pytest.raises(InvalidInputError, match="combine"):
        p.replace(form="factored", combine="union")
    with pytest.raises(InvalidInputError, match="form must be one of"):
        p.replace(form="sparse")
    # narrow noise (the case studies' regime): short joint rows, the joint form under auto
    from robust_imdp import GaussianNoise

    narrow = p.replace(noise=GaussianNoise([0.05, 0.05]))
    form, why = narrow.form_choice()
    assert form == "joint" and "short" in why
    # no horizon and joint rows at most FACTORED_MIN_RATIO x the factored numbers (car parking: about 3.4 x): the
    # joint form, whose unbounded solve goes component by component; with a horizon, factored
    from robust_imdp.abstraction.factored import row_sizes
    from robust_imdp.pipeline.problem import FACTORED_MIN_RATIO

    joint, numbers = row_sizes(p.space_lower, p.space_upper, p.cell_size, p.noise)
    assert numbers < joint <= FACTORED_MIN_RATIO * numbers
    form, why = p.replace(horizon=None).form_choice()
    assert form == "joint" and "no horizon" in why
    assert p.replace(horizon=3).form_choice()[0] == "factored"
    assert p.replace(horizon=None, form="factored").form_choice()[0] == "factored"
    # the run prints the form and why
    q = p.replace(horizon=2)
    _run(q, progress=True)
    assert f"abstraction form: factored ({q.form_choice()[1]})" in capsys.readouterr().err


def test_problem_file_form_key_and_writer(tmp_path):
    from robust_imdp.io.problem_file import load_problem
    from robust_imdp.io.problem_writer import problem_to_toml

    text = (
        "[space]\nlower = [-10.0, -10.0]\nupper = [10.0, 10.0]\ncell_size = [5.0, 5.0]\n"
        "[[regions.target]]\nlower = [5.0, -5.0]\nupper = [10.0, 0.0]\n"
        "[spec]\nformula = \"F target\"\nthreshold = 0.5\nhorizon = 3\n"
        "[modes.a]\nA = [[0.9, 0.0], [0.0, 0.9]]\nb = [0.0, 0.0]\n"
        "[noise]\nkind = \"gaussian\"\nsigma = [1.0, 1.0]\n[learning]\nrkhs_bound = 0.0\n"
        "[abstraction]\ntransitions = \"exact\"\nform = \"FORM\"\n")
    f = tmp_path / "p.toml"
    f.write_text(text.replace("FORM", "factored"))
    p = load_problem(f)
    assert p.form == "factored" and p.form_choice()[0] == "factored"
    written = problem_to_toml(p)
    assert 'form = "factored"' in written  # problem_to_toml parses what it writes (its own check)
    assert 'transitions = "thm1"' in problem_to_toml(p.replace(transitions="thm1", form="auto"))
    f.write_text(text.replace("FORM", "dense"))
    with pytest.raises(ProblemFileError, match=r"\[abstraction\]\.form must be one of auto, factored, joint"):
        load_problem(f)
    f.write_text(text.replace("FORM", "factored").replace('transitions = "exact"', 'transitions = "thm1"'))
    with pytest.raises((ProblemFileError, InvalidInputError), match="transitions"):
        load_problem(f)


def test_cache_result_files_controller_and_resynthesize(tmp_path):
    """The factored abstraction is cached (and reused with the same bytes), a result saved and loaded back gives
    the same deployable controller, and resynthesize solves a new formula on the same factored abstraction."""
    from robust_imdp.abstraction.factored import is_factored
    from robust_imdp.io.result_file import load_result, save_result
    from robust_imdp.pipeline.run import resynthesize

    p = _car_problem(cell=4.0, horizon=4, form="factored")
    a = _run(p, abstraction_cache=tmp_path / "c")
    files = sorted(x.name for x in (tmp_path / "c").glob("abstraction-*.npz"))
    assert len(files) == 1 and files[0] == f"abstraction-{a.parameters['abstraction_key']}.npz"
    b = _run(p, abstraction_cache=tmp_path / "c")
    assert b.from_cache and is_factored(b.abstraction)
    np.testing.assert_array_equal(a.p_low, b.p_low)
    np.testing.assert_array_equal(a.strategy, b.strategy)
    save_result(a, tmp_path / "out")
    back = load_result(tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "result.json").read_text())
    assert doc["parameters"]["form"] == "factored"
    rng = np.random.default_rng(0)
    x = rng.uniform(-10, 10, (200, 2))
    runs1, runs2 = a.controller().start_batch(x), back.controller().start_batch(x)
    car = _Car(p)
    for _ in range(4):  # the same modes along the same trajectories (time-varying strategy, DFA state)
        m1, m2 = runs1.act_index(x), runs2.act_index(x)
        np.testing.assert_array_equal(m1, m2)
        x = car.step(x, np.maximum(m1, 0), rng)
    r = resynthesize(a, formula="F target", progress=False)
    assert r.abstraction is a.abstraction and r.n_cells == a.n_cells
    assert np.all(r.p_low >= a.p_low - RANK_TOL)  # reaching target without avoiding: at least as likely


def test_refinement_converts_to_joint_rows_or_is_refused(monkeypatch):
    from robust_imdp.abstraction.factored import is_factored
    from robust_imdp.models.geometry import BoxPartition
    from robust_imdp.synthesis import refine as refine_mod

    p = _car_problem(cell=4.0, horizon=3, refine={"max_cells": 60, "max_rounds": 2}, form="factored")
    lines = []
    from robust_imdp.pipeline.runtime import _Log

    monkeypatch.setattr(_Log, "info", lambda self, text: lines.append(text))
    r = _run(p, progress=True)
    assert isinstance(r.partition, BoxPartition) and not is_factored(r.abstraction)
    assert r.partition.n_cells > 48  # 48 grid cells (the regions split the 5 x 5 grid)
    assert any("factored abstraction becomes joint rows" in t for t in lines)
    monkeypatch.setattr(refine_mod, "MAX_JOINT_ENTRIES", 10)
    with pytest.raises(ResourceError, match="refinement works on joint rows"):
        _run(p)


def test_export_writes_the_joint_expansion_or_refuses(tmp_path, monkeypatch):
    from robust_imdp.cli import main
    from robust_imdp.io.formats import load_drn
    from robust_imdp.io.result_file import save_result

    p = _car_problem(cell=4.0, horizon=3, form="factored")
    r = _run(p, abstraction_cache=tmp_path / "out" / "cache")
    save_result(r, tmp_path / "out")
    assert main(["export", str(tmp_path / "out"), "--format", "drn", "--out", str(tmp_path / "m.drn")]) == 0
    model = load_drn(tmp_path / "m.drn")
    joint = r.abstraction.to_joint()
    assert model.imdp.n_states == joint.n_states == r.n_cells + 1 and model.imdp.n_choices == joint.n_choices
    assert "factored" in json.loads((tmp_path / "m.states.json").read_text())["form"]
    from robust_imdp.models import factored as factored_mod

    monkeypatch.setattr(factored_mod, "MAX_JOINT_ENTRIES", 10)
    assert main(["export", str(tmp_path / "out"), "--format", "drn", "--out", str(tmp_path / "n.drn")]) != 0


def test_learned_problem_advice_margins_and_suggest():
    """The RKHS route in the factored form: the advice re-abstracts its levers' boxes factored, the margins
    re-abstract the boxes at beta B factored and evaluate the controller there, suggest reads the factored rows."""
    p = _learned_problem(form="factored")
    r = _run(p, advice=True, margins=True)
    from robust_imdp.abstraction.factored import is_factored

    assert is_factored(r.abstraction)
    levers = r.advice["levers"]
    assert levers and all(lv.get("q_yes_share") is None or 0.0 <= lv["q_yes_share"] <= 1.0 for lv in levers)
    assert any(lv.get("q_yes_share") is not None for lv in levers)
    assert r.b_margin is not None and r.b_margin.shape == (r.n_cells,)
    kept = r.b_margin[r.classes == "yes"]
    assert np.all(kept >= 1.0)  # at beta = 1 every cell keeps its class (the run's own abstraction)
    joint = _run(p.replace(form="joint"), margins=False)
    assert np.all(r.p_low >= joint.p_low - RANK_TOL)
    samples = r.suggest_samples(5)
    assert 0 < len(samples) <= 5


def test_preflight_estimates_the_factored_form():
    from robust_imdp.pipeline.preflight import estimate_resources, factored_lengths

    p = _car_problem(cell=0.5)
    est = estimate_resources(p, 3)
    assert est["form"] == "factored" and est["joint_bytes"] > est["bytes"] > 0
    # the estimate of the listed lengths is the measured one on car parking (40 x 40: 27 per axis)
    assert factored_lengths(p) == (27, 27)
    assert estimate_resources(p.replace(form="joint"), 3)["form"] == "joint"


def test_improve_keeps_the_factored_form_and_equals_a_fresh_abstraction():
    """The sampling loop in the factored form: each round re-abstracts only the re-bounded cells' marginals
    (``abstraction.factored.replace_cells``); the assembled model equals the factored rows of all cells from the
    loop's final boxes with the same listed lengths (bit for bit), and the loop's result is factored."""
    from robust_imdp.abstraction.cell_bounds import CellBounds
    from robust_imdp.abstraction.factored import axis_lengths, factored_rows, is_factored
    from robust_imdp.improve import improve

    class Truth:
        mode_names = ("left", "right")

        def step(self, x, modes, rng):
            shift = np.where(np.asarray(modes)[:, None] == 0, [-0.3, 0.0], [0.3, 0.0])
            return np.clip(0.8 * x + 0.05 * np.sin(x) + shift + rng.uniform(-0.05, 0.05, x.shape), -2, 2)

    p = _learned_problem(form="factored")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = improve(p, Truth(), 20, rounds=2, progress=False, keep_history=True, seed=1)
    r = out.result
    assert is_factored(r.abstraction) and len(out.rounds) == 3
    lo, hi = out.history[-1]
    assert not (np.array_equal(out.history[0][0], lo) and np.array_equal(out.history[0][1], hi))  # boxes moved
    cb = CellBounds(lo, hi, None)
    k = r.abstraction.model.k  # round 0's listed lengths; later boxes are inside, so their runs fit
    assert all(a <= b for a, b in zip(axis_lengths(r.partition, cb, p.noise), k))
    fresh = factored_rows(r.partition, cb, p.noise, k)
    for a, b in zip(r.abstraction.model.axes, fresh.axes):
        for name, arr in zip(("start", "lower", "upper", "out_lower", "out_upper", "rest_upper"), b):
            np.testing.assert_array_equal(getattr(a, name), arr, err_msg=name)
