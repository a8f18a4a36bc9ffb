"""The two readings of a formula (README, "Two readings of a formula"): the DFA classification, the refusal of
vacuous readings, safety solved as one minus reaching a bad prefix (closed form, Storm, Monte Carlo), and the
reading through the pipeline, the result file, the controller and the validation."""

from __future__ import annotations

import itertools
import json
import warnings
from fractions import Fraction

import numpy as np
import pytest

from robust_imdp._fp import complement_down, complement_up
from robust_imdp.errors import ProblemFileError, SpecificationWarning, VacuousSpecificationError
from robust_imdp.models.imdp import IMDP
from robust_imdp.solvers.product import materialize_product, solve_product
from robust_imdp.spec.dfa import DFA, check_reading, classify, ltlf_to_dfa, resolve_semantics
from robust_imdp.spec.ltlf import holds, parse
from robust_imdp.synthesis.controller import Controller
from robust_imdp.synthesis.core import synthesize


# --------------------------------------------------------------------------- classification
CASES = [  # formula, co-safety, safety, auto reading
    ("F goal", True, False, "reach"),
    ("a U b", True, False, "reach"),
    ("F a & F b", True, False, "reach"),
    ("G safe", False, True, "safety"),
    ("G (a -> X b)", False, True, "safety"),
    ("G (a -> X X b)", False, True, "safety"),
    ("G (a -> WX b)", False, True, "safety"),
    ("a R b", False, True, "safety"),
    ("G !obs & F goal", False, False, "reach"),
    ("G !o & F d1 & F d2", False, False, "reach"),
    ("G !obs & F (des | X d_2)", False, False, "reach"),  # X inside F stays strong: a liveness part
    ("G (a -> F b)", False, False, "reach"),
    ("safe", True, True, "reach"),
]


@pytest.mark.parametrize("formula, co_safety, safety, reading", CASES)
def test_classification_of_known_formulas(formula, co_safety, safety, reading):
    kind = classify(ltlf_to_dfa(formula))
    assert (kind.co_safety, kind.safety, kind.reading) == (co_safety, safety, reading)


def _weak(text):
    """The formula's text with strong nexts outside eventualities weakened, as ``classify`` reads it (the cases
    above have no X inside an eventuality except ``F (des | X d_2)``, which is not weakened)."""
    return text if "F (" in text else text.replace("WX", "X").replace("X ", "WX ")


@pytest.mark.parametrize("formula, co_safety, safety, reading", CASES)
def test_classification_matches_the_language_by_brute_force(formula, co_safety, safety, reading):
    """Independent of the DFA: the LTLf semantics (``ltlf.holds``) on every trace of up to 4 letters.
    co-safety: an accepted trace stays accepted under any extension; safety: every prefix of an accepted
    trace (of the weakened formula) is accepted. The minimal DFAs have at most 6 states, so a violation of
    either property shows within 4 letters."""
    f, fw = parse(formula), parse(_weak(formula))
    atoms = sorted({a for a in ("a", "b", "safe", "goal", "obs", "o", "d1", "d2", "des", "d_2") if a in formula})
    letters = [frozenset(c) for r in range(len(atoms) + 1) for c in itertools.combinations(atoms, r)]
    traces = [list(t) for n in range(1, 5) for t in itertools.product(letters, repeat=n)]
    ext_closed = all(holds(f, t + [a]) for t in traces[:len(letters) ** 3 + 50] if holds(f, t) for a in letters)
    prefix_closed = all(holds(fw, t[:k]) for t in traces if holds(fw, t) for k in range(1, len(t)))
    assert (ext_closed, prefix_closed) == (co_safety, safety)


def test_a_table_dfa_without_formula_is_classified_as_it_is():
    # G a as a table: state 0 accepting, a keeps it, !a -> sink 1
    d = DFA.from_table(["a"], [[1, 0], [1, 1]], 0, [True, False])
    assert classify(d).reading == "safety"
    assert resolve_semantics(d, "reach")[0] == "reach"
    with pytest.raises(ValueError, match="semantics must be one of"):
        resolve_semantics(d, "always")


def test_vacuous_readings_are_refused_with_what_to_write():
    g = ltlf_to_dfa("G safe")
    safe_everywhere = np.ones(5, dtype=np.int64)
    with pytest.raises(VacuousSpecificationError, match=r'semantics = "safety"'):
        check_reading(g, safe_everywhere, "reach")
    with pytest.raises(VacuousSpecificationError, match="satisfied by the one-state trace of 3 of 5 cells"):
        check_reading(g, np.array([1, 1, 1, 0, 0]), "reach")
    check_reading(g, safe_everywhere, "safety")  # staying in X: a real requirement
    f = ltlf_to_dfa("F goal")
    with pytest.raises(VacuousSpecificationError, match=r'co-safety: write \[spec\].semantics = "reach"'):
        check_reading(f, np.array([0, 1, 0]), "safety")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_reading(f, np.array([0, 1, 0]), "reach")  # goal cells satisfy F goal: no warning
        check_reading(ltlf_to_dfa("G !obs & F goal"), np.array([0, 1, 2, 3]), "reach")


def test_partial_readings_warn():
    d = ltlf_to_dfa("G (a -> X b)", ("a", "b"))
    with pytest.warns(SpecificationWarning, match="2 of 3 cells satisfy it by their own label"):
        check_reading(d, np.array([0, 1, 2]), "reach")  # cells {}, {a}, {b}: {} and {b} accepted at once
    with pytest.warns(SpecificationWarning, match="eventualities"):
        check_reading(ltlf_to_dfa("G !obs & F goal"), np.array([0, 1, 2]), "safety")


def test_complements_are_outward_and_exact_where_possible():
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.random(3000), rng.random(3000) * 1e-9, [0.0, 1.0, 0.5, 2.0 ** -60]])
    lo, hi = complement_down(x), complement_up(x)
    exact = [1 - Fraction(float(v)) for v in x]
    assert all(Fraction(float(a)) <= e <= Fraction(float(b)) for a, b, e in zip(lo, hi, exact))
    # no wider than needed: equal where 1 - x is a double (x = 0, 1, 0.5 and every x >= 1/2: Sterbenz)
    sterbenz = x >= 0.5
    np.testing.assert_array_equal(lo[sterbenz], 1.0 - x[sterbenz])
    np.testing.assert_array_equal(hi[sterbenz], 1.0 - x[sterbenz])
    assert complement_down(0.0) == 1.0 and complement_up(1.0) == 0.0


# --------------------------------------------------------------------------- closed form: a 1-D random walk
def walk_imdp(n, *, with_exit_mode=False, p=0.5):
    """Cells 0..n-1 of a walk moving right w.p. p and left w.p. 1 - p (exact intervals), state n = outside X.
    ``with_exit_mode``: a second mode that leaves X at once (the minimising controller must never use it)."""
    a = 2 if with_exit_mode else 1
    P = np.zeros((n + 1, a, n + 1))
    for i in range(n):
        P[i, 0, i + 1 if i + 1 < n else n] += p
        P[i, 0, i - 1 if i > 0 else n] += 1 - p
        if with_exit_mode:
            P[i, 1, n] = 1.0
    P[n, :, n] = 1.0
    return IMDP.from_dense(P, P.copy())


def walk_survival(n, k, j):
    """P(the symmetric simple walk started at j + 1 stays in {1..n} for k steps), absorbed at 0 and n + 1:
    the spectral expansion of the killed walk, M = n + 1,
    ``sum_m (2/M) sin(m pi (j+1)/M) cos(m pi/M)^k sum_i sin(m pi i/M)`` (Feller, vol. 1, XIV.5)."""
    M = n + 1
    m = np.arange(1, M)
    i = np.arange(1, M)
    s = np.sin(np.outer(m, i) * np.pi / M).sum(axis=1)
    return float(np.sum(2.0 / M * np.sin(m * np.pi * (j + 1) / M) * np.cos(m * np.pi / M) ** k * s))


@pytest.mark.parametrize("horizon", [1, 2, 5, 10, 25])
def test_k_step_safety_of_a_walk_matches_the_closed_form(horizon):
    n = 7
    m = walk_imdp(n, with_exit_mode=True)
    r = synthesize(m, np.ones(n, dtype=np.int64), ("safe",), ltlf_to_dfa("G safe"), threshold=0.5, horizon=horizon,
                   outside_state=n)
    assert r.semantics == "safety"
    want = np.array([walk_survival(n, horizon, j) for j in range(n)])
    # exact intervals: the brackets are the k-step values up to rounding (1e-12: k <= 25 sweeps of rows of
    # 2 entries, each off by a few ulps); the spectral sum itself is accurate to ~1e-14
    for got in (r.p_low, r.p_up, r.p_up_star):
        np.testing.assert_allclose(got, want, atol=1e-12)
    assert np.all(r.strategy == 0)  # the exit mode is never chosen
    # teeth: a 0.1 % slower walk (p = 0.5005 right) changes the values by far more than the tolerance
    r2 = synthesize(walk_imdp(n, with_exit_mode=True, p=0.5005), np.ones(n, dtype=np.int64), ("safe",),
                    ltlf_to_dfa("G safe"), threshold=0.5, horizon=horizon, outside_state=n)
    assert horizon == 1 or np.max(np.abs(r2.p_low - want)) > 1e-6


def test_unbounded_safety_keeps_to_a_safe_loop():
    """Unbounded: a walk leaves X with probability 1, but a mode that stays put in cell 3 keeps it there for ever:
    safety 1 in cell 3, and elsewhere the probability of reaching cell 3 before leaving (gambler's ruin:
    (j + 1)/4 left of it, (n - j)/(n - 3) right of it). The nodes proven 0 (cell 3, layer safe) must take the
    staying row, not the first (walking) one."""
    n = 7
    P = np.zeros((n + 1, 2, n + 1))
    for i in range(n):
        for a in range(2):
            P[i, a, i + 1 if i + 1 < n else n] += 0.5
            P[i, a, i - 1 if i > 0 else n] += 0.5
    P[3, 1] = 0.0
    P[3, 1, 3] = 1.0  # mode 1 stays in cell 3
    P[n, :, n] = 1.0
    m = IMDP.from_dense(P, P.copy())
    r = synthesize(m, np.ones(n, dtype=np.int64), ("safe",), ltlf_to_dfa("G safe"), threshold=0.5,
                   outside_state=n, precision=1e-10)
    want = np.array([(j + 1) / 4 if j <= 3 else (n - j) / (n - 3) for j in range(n)])
    np.testing.assert_allclose(r.p_low, want, atol=1e-8)  # 1e-8: the unbounded solve's precision
    assert r.p_low[3] == 1.0 and r.strategy[3, r.initial_dfa_state[3]] == 1


# --------------------------------------------------------------------------- Storm on the exported product
def random_imdp(rng, n, a, k, closed=4):
    """Random intervals with positive lower bounds on k successors; action 0 of states ``0 .. closed-1``
    stays among them (a class a controller can keep to for ever, so unbounded safety is not all 0 or 1)."""
    lo = np.zeros((n, a, n))
    up = np.zeros((n, a, n))
    for s in range(n):
        for u in range(a):
            succ = rng.choice(closed, size=min(k, closed), replace=False) if (u == 0 and s < closed) else \
                rng.choice(n, size=k, replace=False)
            k = succ.size
            p = rng.dirichlet(np.ones(k))
            w = rng.uniform(0.0, 0.2, size=k)
            lo[s, u, succ] = np.minimum(np.clip(p - w, 0.01, 1.0), p)
            up[s, u, succ] = np.clip(p + w, 0.0, 1.0)
    return IMDP.from_dense(lo, up)


@pytest.mark.parametrize("formula", ["G safe", "G (a -> X b)"])
@pytest.mark.parametrize("horizon", [None, 6])
def test_safety_matches_storm_on_the_exported_product(formula, horizon):
    stormpy = pytest.importorskip("stormpy")  # noqa: F841
    from robust_imdp.io.formats import storm_reachability

    rng = np.random.default_rng(21)
    n = 10
    m = random_imdp(rng, n, 3, 4)  # positive lower bounds: Storm's unbounded queries need them
    two = formula.startswith("G (a")
    dfa = ltlf_to_dfa(formula, ("a", "b") if two else ("safe",))
    letters = rng.integers(0, 4 if two else 2, n)
    letters[:4] = 0 if two else 1  # the closed class: safe ({safe}; no a under G (a -> X b))
    if not two:
        letters[4:7] = 1  # 7 safe cells, 3 unsafe ones
    r = synthesize(m, letters, dfa.atoms, dfa, threshold=0.5, horizon=horizon, precision=1e-10)
    prod = materialize_product(m, letters, dfa, semantics="safety")
    init = prod.initial
    # Storm's robust VI stops on a residual of 1e-10 (tests/test_storm_reference.py): agreement to 1e-6
    bad_minmax = storm_reachability(prod.imdp, prod.target, adversary="pessimistic", objective="minimize",
                                    horizon=horizon, precision=1e-10)[init]
    bad_minmin = storm_reachability(prod.imdp, prod.target, adversary="optimistic", objective="minimize",
                                    horizon=horizon, precision=1e-10)[init]
    np.testing.assert_allclose(r.p_low, 1 - bad_minmax, atol=1e-6)
    np.testing.assert_allclose(r.p_up_star, 1 - bad_minmin, atol=1e-6)
    assert np.all(r.p_low <= r.p_up) and np.all(r.p_up <= r.p_up_star)
    assert np.ptp(r.p_low) > 0.05  # an informative model: not every value 0 or 1
    # the lazy product's safety solve is the same value as well
    lazy = solve_product(m, letters, dfa, adversary="pessimistic", horizon=horizon, precision=1e-10,
                         semantics="safety")
    np.testing.assert_allclose(lazy.initial_lower, r.p_low, atol=1e-8)


# --------------------------------------------------------------------------- pipeline, files, controller
class Contracting2D:
    """x+ = 0.8 x + (-+0.1, 0) + v, v truncated Gaussian (sigma 0.1, bound 0.3) per axis; two modes pushing left
    and right (the true system of the safety tests)."""

    mode_names = ("left", "right")
    sigma, bound = 0.1, 0.3

    def mean(self, x, modes):
        shift = np.where(np.asarray(modes)[:, None] == 0, -0.1, 0.1) * np.array([1.0, 0.0])
        return 0.8 * x + shift

    def step(self, x, modes, rng):
        from scipy.stats import truncnorm

        x = np.atleast_2d(x)
        c = self.bound / self.sigma
        return self.mean(x, modes) + truncnorm.rvs(-c, c, scale=self.sigma, size=x.shape, random_state=rng)


@pytest.fixture(scope="module")
def safety_run():
    """The 2-D contracting system on [-2, 2]^2 (8 x 8 cells), known part 0.8 x -+ 0.1, an unknown part (zero in
    truth) learned from 150 noisy samples per mode; G safe (safe = [-1, 1]^2) for 5 steps."""
    from robust_imdp.models.noise import TruncatedGaussianNoise
    from robust_imdp.pipeline.problem import Problem
    from robust_imdp.pipeline.run import synthesize_from_data

    sysm = Contracting2D()
    rng = np.random.default_rng(4)
    x = rng.uniform(-2, 2, (300, 2))
    u = np.repeat(np.array(["left", "right"]), 150)
    x_next = sysm.step(x, (u == "right").astype(int), rng)
    problem = Problem.from_arrays(
        x, u, x_next, lower=[-2, -2], upper=[2, 2], cell_size=0.5,
        regions={"safe": ([-1, -1], [1, 1])}, formula="G safe", threshold=0.9, horizon=5,
        modes={"left": (0.8 * np.eye(2), [-0.1, 0.0]), "right": (0.8 * np.eye(2), [0.1, 0.0])},
        noise=TruncatedGaussianNoise([sysm.sigma] * 2, [sysm.bound] * 2), rkhs_bound=0.05, lengthscale=1.0)
    return synthesize_from_data(problem, progress=False, advice=False), sysm


def test_pipeline_solves_safety_and_monte_carlo_agrees(safety_run, tmp_path):
    """Monte Carlo on a 2-D system: 64 cells x 300 runs of the true system under the controller, 99.99 %
    Wilson intervals; a correct result is flagged by chance in at most ``allowed_outside`` cells."""
    from dataclasses import replace

    from robust_imdp.io.files import load_result, save_result
    from robust_imdp.validate import validate

    res, sysm = safety_run
    assert res.semantics == "safety" and res.synthesis.semantics == "safety"
    syn = res.synthesis
    assert np.all(syn.p_low <= syn.p_up) and np.all(syn.p_up <= syn.p_up_star)
    safe = (res.partition.labels & (1 << res.partition.atoms.index("safe"))) > 0
    assert np.all(syn.p_up_star[~safe] == 0.0)  # x0 outside safe is a bad prefix at once
    assert np.all(syn.p_low[safe] > 0.05)  # not vacuous (nor 1: the noise reaches past safe's edge)
    save_result(res, tmp_path)
    doc = json.loads((tmp_path / "result.json").read_text())
    assert doc["semantics"] == "safety"
    loaded = load_result(tmp_path)
    assert loaded.semantics == "safety"
    rep = validate(loaded, sysm, n_per_cell=300, rng=7, confidence=0.9999)
    assert rep.passed, rep.summary()
    # the runs measure safety, not reach (under which every safe cell would be satisfied at once): a run is
    # satisfied only after the 5 steps of the horizon, and violated at once outside safe ...
    from robust_imdp.validate import SATISFIED, VIOLATED, simulate

    x0 = 0.5 * (loaded.cells_lower + loaded.cells_upper)
    traj = simulate(loaded, sysm, x0, rng=8)
    assert np.all(traj.steps[traj.outcome == SATISFIED] == 5) and np.all(traj.outcome[~safe] == VIOLATED)
    assert np.all(traj.steps[~safe] == 0) and np.all(rep.empirical[~safe] == 0.0)
    # ... and the check has teeth: p_low raised 0.2 above the measured frequency is flagged
    fake = replace(loaded, p_low=np.minimum(1.0, rep.empirical + 0.2), p_up=np.ones(loaded.n_cells))
    assert not validate(fake, sysm, n_per_cell=300, rng=7, confidence=0.9999).passed


def test_controller_runs_the_safety_reading(safety_run, tmp_path):
    res, sysm = safety_run
    ctrl = res.controller()
    assert ctrl.semantics == "safety"
    json_path, _ = ctrl.save(tmp_path / "c")
    assert json.loads(json_path.read_text())["semantics"] == "safety"
    back = Controller.load(tmp_path / "c")
    assert back.semantics == "safety"
    free = int(np.argmax(res.synthesis.p_low))
    x = 0.5 * (res.partition.cells_lower[free] + res.partition.cells_upper[free])
    rng = np.random.default_rng(3)
    back.reset(x)
    steps = 0
    while (u := back.act_index(x)) is not None:
        x = sysm.step(x[None], np.array([u]), rng)[0]
        steps += 1
    # a run stops only at a bad prefix, on leaving X, or at the horizon (then satisfied)
    assert (back.status == "satisfied" and steps == 5) or back.status == "violated"


def test_problem_file_semantics_key(tmp_path):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from problem_texts import write_one_d
    from robust_imdp.io.problem_file import load_problem

    p = write_one_d(tmp_path)
    text = p.read_text()
    p.write_text(text.replace('formula = "F des"', 'formula = "F des"\nsemantics = "reach"'))
    assert load_problem(p).semantics == "reach"
    p.write_text(text.replace('formula = "F des"', 'formula = "F des"\nsemantics = "safty"'))
    with pytest.raises(ProblemFileError, match=r"\[spec\].semantics must be one of auto, reach, safety.*"
                                               r"did you mean 'safety'"):
        load_problem(p)
    assert load_problem(write_one_d(tmp_path, "q.toml")).semantics == "auto"


def test_run_prints_the_reading_and_refuses_a_vacuous_one(tmp_path, capsys):
    from problem_texts import write_one_d
    from robust_imdp.io.problem_file import load_problem
    from robust_imdp.pipeline.run import synthesize_from_data

    p = write_one_d(tmp_path)
    p.write_text(p.read_text().replace("[[regions.des]]\nlower = [2.0]", "[[regions.des]]\nlower = [0.0]")
                 .replace("upper = [3.0]", "upper = [4.0]").replace('"F des"', '"G des"\nhorizon = 3'))
    res = synthesize_from_data(load_problem(p), advice=False)
    err = capsys.readouterr().err
    assert "semantics: safety (a path satisfies it when no prefix is a bad prefix and it stays in X, within 3 " \
           "steps; auto: 'G des' is safety" in err
    assert res.semantics == "safety" and np.all(res.p_low < 1.0)  # the edges leave X with positive probability
    assert "horizon 3 (safety reading)" in res.summary().splitlines()[0]
    with pytest.raises(VacuousSpecificationError, match="every cell would get p_low in"):
        synthesize_from_data(load_problem(p).replace(semantics="reach"), advice=False, progress=False)
