"""Which mode among equals: the nominal model's value after the robust lower value (synthesis.ties).

Where the robust lower values of the modes tie (at 0 wherever the adversary can force a failure) the
optimistic value is 1 for several modes, and the old choice drove the newcomer's robot into the obstacle.
These tests pin: the nominal value picks the mode that goes round (hand-built, reach and safety, unbounded and
k steps), the chosen strategy never loses robust lower value (random models), its bounds are its own (Monte
Carlo on a concrete system inside the intervals), the nominal model's probabilities (closed form), and the
pipeline's hook (a robot through the Python API).
"""

import numpy as np
import pytest
from scipy.stats import norm, truncnorm

from robust_imdp.abstraction.nominal import cell_points, nominal_abstraction, points_per_axis, row_entries
from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.models.geometry import Box, Partition
from robust_imdp.models.imdp import IMDP
from robust_imdp.models.noise import GaussianNoise, TruncatedGaussianNoise
from robust_imdp.solvers import product
from robust_imdp.solvers.engine import _KEY_TOL, _key_rank
from robust_imdp.spec.dfa import ltlf_to_dfa
from robust_imdp.synthesis.core import synthesize

from test_synthesis import random_imdp

EAST, NORTH = 0, 1
S, U, OBST, GOAL, OUT = range(5)
ATOMS = ("goal", "obstacle")
LABELS = np.array([0, 0, 2, 1])  # s, u: nothing; the obstacle cell; the goal cell


# --------------------------------------------------------------------------- the keys' rank
def test_key_rank_is_lexicographic_with_a_grid_on_the_first_key():
    first = np.array([0.5, 0.5 + _KEY_TOL / 10, 0.7, -np.inf])
    second = np.array([0.2, 0.9, 0.1, 5.0])
    r = _key_rank([first, second])
    assert r[3] == -np.inf  # a row not evaluated stays out
    assert r[2] > r[1] > r[0]  # 0.7 first; 0.5 and 0.5 + 1e-8 tie on the first key, the second decides
    m = _key_rank([first, second], maximise=False)  # smaller is better for a minimising controller
    assert m[3] == -np.inf and m[0] > m[1] > m[2]
    assert _key_rank([first]) is first  # one key of a maximising controller: its values, compared exactly


# --------------------------------------------------------------------------- hand-built: round the obstacle
def _dense(n, a):
    return np.zeros((n, a, n)), np.zeros((n, a, n))


def obstacle_models():
    """Start s, detour u, obstacle, goal, outside (absorbing); modes east, north.

    Robust model (a learning error as wide as the step): from s, east may land in the goal or the obstacle,
    north in u or the obstacle, both [0, 1]; from u, east: goal or obstacle, north: stays in u. Every robust
    lower value is 0 and the optimistic value of both modes at s is 1; the optimistic solve's own mode at s is
    east (it reaches the goal in one step). Nominal model (point images): from s east goes into the obstacle,
    north to u; from u east to the goal. Concrete system (inside the robust intervals): s east -> obstacle 0.9,
    goal 0.1; s north -> u 0.95, obstacle 0.05; u east -> goal 0.95, obstacle 0.05; u north stays.
    """
    lo, up = _dense(5, 2)
    up[S, EAST, [GOAL, OBST]] = 1.0
    up[S, NORTH, [U, OBST]] = 1.0
    up[U, EAST, [GOAL, OBST]] = 1.0
    lo[U, NORTH, U] = up[U, NORTH, U] = 1.0
    for q in (OBST, GOAL, OUT):
        lo[q, :, q] = up[q, :, q] = 1.0
    robust = IMDP.from_dense(lo, up)
    nom = np.zeros((5, 2, 5))
    nom[S, EAST, OBST] = nom[S, NORTH, U] = nom[U, EAST, GOAL] = nom[U, NORTH, U] = 1.0
    for q in (OBST, GOAL, OUT):
        nom[q, :, q] = 1.0
    true = np.zeros((5, 2, 5))
    true[S, EAST, [OBST, GOAL]] = [0.9, 0.1]
    true[S, NORTH, [U, OBST]] = [0.95, 0.05]
    true[U, EAST, [GOAL, OBST]] = [0.95, 0.05]
    true[U, NORTH, U] = 1.0
    for q in (OBST, GOAL, OUT):
        true[q, :, q] = 1.0
    return robust, IMDP.from_dense(nom, nom), true


def _run(true, strategy, start, steps, rng, n_runs):
    """Satisfied runs of ``G !obstacle & F goal`` from ``start`` under ``strategy`` (mode per state) within
    ``steps`` steps of the concrete chain ``true``."""
    q = np.full(n_runs, start)
    for _ in range(steps):
        live = (q != GOAL) & (q != OBST) & (q != OUT)
        p = true[q[live], strategy[q[live]]]
        c = p.cumsum(axis=1)
        q[live] = np.minimum((rng.random(live.sum())[:, None] > c).sum(axis=1), 4)
    return int(np.count_nonzero(q == GOAL))


@pytest.mark.parametrize("horizon", [None, 3])
def test_nominal_value_goes_round_the_obstacle_where_lower_values_tie_at_zero(horizon):
    robust, nominal, true = obstacle_models()
    dfa = ltlf_to_dfa("G !obstacle & F goal")
    kw = dict(threshold=0.5, horizon=horizon, outside_state=4)
    old = synthesize(robust, LABELS, ATOMS, dfa, **kw)
    new = synthesize(robust, LABELS, ATOMS, dfa, nominal=nominal, **kw)
    first = (lambda r: r.strategy[:, S] if horizon is None else r.strategy[0, :, S])
    assert first(old)[old.initial_dfa_state[S]] == EAST  # the old choice: straight into the obstacle
    assert first(new)[new.initial_dfa_state[S]] == NORTH  # the nominal value: round it
    assert new.tie_keys == ("nominal", "optimistic") and old.tie_keys == ("optimistic",)
    # the guarantee is unchanged (0 everywhere: the adversary may always send the robot into the obstacle) and
    # both strategies may still succeed (p_up 1)
    np.testing.assert_array_equal(new.p_low, old.p_low)
    np.testing.assert_allclose(new.p_low[:2], 0.0, atol=1e-12)
    np.testing.assert_allclose(new.p_up[:2], 1.0, atol=1e-8)
    assert any(r.name == "nominal" for r in new.runs)


def test_the_chosen_strategy_succeeds_on_a_concrete_system_and_stays_inside_its_bounds():
    """Seeded Monte Carlo, 4,000 runs from s: old strategy 0.1 exactly (east: goal w.p. 0.1), new 0.95^2 =
    0.9025 (north, then east); each empirical rate within 5 standard errors (<= 0.024) of its exact value and
    inside [p_low, p_up]."""
    robust, nominal, true = obstacle_models()
    dfa = ltlf_to_dfa("G !obstacle & F goal")
    rng = np.random.default_rng(7)
    n = 4000
    for nom, exact in ((None, 0.1), (nominal, 0.9025)):
        res = synthesize(robust, LABELS, ATOMS, dfa, threshold=0.5, outside_state=4, nominal=nom)
        pi = np.append(res.strategy[np.arange(4), res.initial_dfa_state], 0)
        rate = _run(true, pi, S, 50, rng, n) / n
        se = np.sqrt(exact * (1 - exact) / n)
        assert abs(rate - exact) <= 5 * se, (nom is None, rate, exact)
        assert res.p_low[S] <= rate <= res.p_up[S]


# --------------------------------------------------------------------------- safety: the same keys, mirrored
def safety_models():
    """Start s, a safe region a, a bad cell, outside; modes 0 and 1; formula G !bad (safety reading).

    Robust: mode 0 from s: bad [0, 1] or s [0, 1]; mode 1: a [0, 1] or bad [0, 1]; a stays (both modes).
    Both modes' proven upper bound of reaching bad is 1 (the adversary can send s to bad), so they tie and the
    least-row rule took mode 0. Nominal: mode 0 -> bad, mode 1 -> a. Concrete: mode 0 -> bad 0.9, s 0.1;
    mode 1 -> a 0.9, bad 0.1.
    """
    lo, up = _dense(4, 2)
    up[0, 0, [2, 0]] = 1.0
    up[0, 1, [1, 2]] = 1.0
    lo[1, :, 1] = up[1, :, 1] = 1.0
    for q in (2, 3):
        lo[q, :, q] = up[q, :, q] = 1.0
    nom = np.zeros((4, 2, 4))
    nom[0, 0, 2] = nom[0, 1, 1] = 1.0
    nom[1, :, 1] = 1.0
    for q in (2, 3):
        nom[q, :, q] = 1.0
    return IMDP.from_dense(lo, up), IMDP.from_dense(nom, nom)


@pytest.mark.parametrize("horizon", [None, 4])
def test_safety_reading_takes_the_mode_the_nominal_model_keeps_safe(horizon):
    robust, nominal = safety_models()
    dfa = ltlf_to_dfa("G !bad")
    labels = np.array([0, 0, 1])
    kw = dict(threshold=0.5, horizon=horizon, outside_state=3, semantics="safety")
    old = synthesize(robust, labels, ("bad",), dfa, **kw)
    new = synthesize(robust, labels, ("bad",), dfa, nominal=nominal, **kw)
    pick = (lambda r: r.strategy[0] if horizon is None else r.strategy[0, 0])
    assert pick(old)[old.initial_dfa_state[0]] == 0 and pick(new)[new.initial_dfa_state[0]] == 1
    np.testing.assert_allclose(new.p_low, old.p_low, atol=1e-12)  # 0 at s: both modes may be sent to bad
    assert new.p_up[0] >= 1 - 1e-8  # under mode 1 the intervals allow s -> a, safe for ever
    assert new.semantics == "safety" and new.strategy_choice == "least"


# --------------------------------------------------------------------------- never costs lower value
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("horizon", [None, 3])
@pytest.mark.parametrize("semantics", ["reach", "safety"])
def test_nominal_choice_keeps_the_optimal_lower_value(seed, horizon, semantics):
    """Random robust models and an unrelated random nominal model (the worst case for the keys): p_low of the
    chosen strategy is the first-choice strategy's within 1e-9 (twice the brackets' tolerance at precision
    1e-10) on every cell, and no Q_yes cell is lost against the choice without a nominal model."""
    rng = np.random.default_rng(seed)
    n_cells = 8
    imdp = random_imdp(rng, n_cells + 1, 3, width=0.15)
    nominal = random_imdp(rng, n_cells + 1, 3, width=0.0)
    atoms = ("o", "d1", "d2")
    labels = rng.choice([0, 0, 1, 2, 4, 6], size=n_cells)
    formula = "G !o & F d1 & F d2" if semantics == "reach" else "G !o"
    dfa = ltlf_to_dfa(formula)
    kw = dict(threshold=0.3, horizon=horizon, outside_state=n_cells, precision=1e-10, semantics=semantics)
    try:
        old = synthesize(imdp, labels, atoms, dfa, **kw)
    except Exception as exc:  # a reading the labels decide alone (VacuousSpecificationError): nothing to choose
        pytest.skip(str(exc))
    new = synthesize(imdp, labels, atoms, dfa, nominal=nominal, **kw)
    letters = np.append(new.labels, 0)
    pk = dict(avoid=np.array([n_cells]), horizon=horizon, precision=1e-10, semantics=semantics)
    best = product.solve_product(imdp, letters, dfa, **pk)
    assert np.all(new.p_low >= np.asarray(best.initial_lower)[:n_cells] - 1e-9)
    assert np.all(new.p_low >= old.p_low - 1e-9)
    assert not np.any((old.classes == "yes") & (new.classes != "yes"))
    assert np.all(new.p_low <= new.p_up) and np.all(new.p_up <= new.p_up_star)


def test_nominal_must_have_the_models_states_and_modes():
    robust, nominal, _ = obstacle_models()
    dfa = ltlf_to_dfa("G !obstacle & F goal")
    with pytest.raises(InvalidInputError, match="nominal"):
        synthesize(robust, LABELS, ATOMS, dfa, threshold=0.5, outside_state=4, nominal=np.zeros(3))
    small = IMDP.from_dense(np.eye(4)[:, None, :].repeat(2, 1), np.eye(4)[:, None, :].repeat(2, 1))
    with pytest.raises(DimensionError, match="nominal must have the 5 states"):
        synthesize(robust, LABELS, ATOMS, dfa, threshold=0.5, outside_state=4, nominal=small)
    one = IMDP.from_dense(np.eye(5)[:, None, :], np.eye(5)[:, None, :])
    with pytest.raises(DimensionError, match="nominal must have the 2 modes"):
        synthesize(robust, LABELS, ATOMS, dfa, threshold=0.5, outside_state=4, nominal=one)


# --------------------------------------------------------------------------- the nominal model's probabilities
def test_points_of_a_cell():
    P = Partition(Box([0.0, 0.0], [1.0, 2.0]), [0.5, 1.0], {})
    c = cell_points(P, 1)
    np.testing.assert_allclose(c[:, 0], 0.5 * (P.cells_lower + P.cells_upper))
    p = cell_points(P, 2)
    assert p.shape == (P.n_cells, 4, 2)
    np.testing.assert_allclose(p.mean(axis=1), c[:, 0])  # midpoints of 2 x 2 sub-boxes: centred
    np.testing.assert_allclose(p[0], [[0.125, 0.25], [0.125, 0.75], [0.375, 0.25], [0.375, 0.75]])
    assert [points_per_axis(d) for d in (1, 2, 3, 4, 5)] == [16, 4, 2, 2, 1]
    with pytest.raises(InvalidInputError, match="per_axis"):
        cell_points(P, 0)


def _entries(ab, q, u):
    m = ab.imdp
    r = m.state_ptr[q] + u
    sl = slice(m.row_ptr[r], m.row_ptr[r + 1])
    return m.col[sl], m.lower[sl], m.upper[sl], m.floor[r]


@pytest.mark.parametrize("noise,law", [
    (TruncatedGaussianNoise([0.03], [0.06]), lambda t: truncnorm.cdf(t, -2.0, 2.0, scale=0.03)),
    (GaussianNoise([0.05]), lambda t: norm.cdf(t, scale=0.05)),
])
def test_mixture_probabilities_against_the_closed_form(noise, law):
    """1-D, cells of 0.1 on [0, 1]: each row is the average over the cell's points of P[y + v in z], with
    y the points' images (a shift 0.23 plus a slope); every listed entry's interval is within 1e-12 of the
    closed form (scipy) and at most 1e-9 wide plus the floor (the share of the points that do not list it),
    unlisted cells are below the floor, and the outside state gets the rest. A 0.1 % shrink of any bound breaks the first check."""
    P = Partition(Box([0.0], [1.0]), 0.1, {})
    pts = cell_points(P, 4)  # (10, 4, 1)
    images = np.stack([pts + 0.23 + 0.1 * pts, pts - 0.04])  # two modes
    ab = nominal_abstraction(P, images, noise)
    bp = np.linspace(0, 1, 11)
    for u in range(2):
        for q in range(P.n_cells):
            y = images[u, q, :, 0]
            exact = np.mean(law(bp[None, 1:] - y[:, None]) - law(bp[None, :-1] - y[:, None]), axis=0)
            out = 1.0 - np.mean(law(1.0 - y) - law(0.0 - y))
            col, lo, up, fl = _entries(ab, q, u)
            want = np.append(exact, out)[col]
            assert np.all(lo <= want + 1e-12) and np.all(want <= up + 1e-12)
            assert np.all(up - lo <= 1e-9 + fl)  # an entry some points do not list: their floor above
            unlisted = np.setdiff1d(np.arange(P.n_cells), col)
            assert np.all(exact[unlisted] <= fl + 1e-12)


def test_mixture_rows_are_the_average_of_the_point_rows():
    """2-D with Gaussian noise (floors): the mixture of two points is the mean of the two one-point models,
    entry by entry (an entry unlisted at one point counts 0 below and that row's floor above)."""
    P = Partition(Box([0.0, 0.0], [1.0, 1.0]), 0.25, {})
    noise = GaussianNoise([0.04, 0.06])
    rng = np.random.default_rng(3)
    ya, yb = rng.uniform(-0.1, 1.1, (2, 2, P.n_cells, 2))
    mix = nominal_abstraction(P, np.stack([ya, yb], axis=2), noise)
    a, b = nominal_abstraction(P, ya, noise), nominal_abstraction(P, yb, noise)
    n = P.n_cells + 1
    for q in range(P.n_cells):
        for u in range(2):
            dense = []
            for ab in (a, b):
                col, lo, up, fl = _entries(ab, q, u)
                L, H = np.zeros(n), np.full(n, fl)
                L[col], H[col] = lo, up
                dense.append((L, H))
            col, lo, up, fl = _entries(mix, q, u)
            L = 0.5 * (dense[0][0] + dense[1][0])
            H = 0.5 * (dense[0][1] + dense[1][1])
            np.testing.assert_allclose(lo, L[col], rtol=1e-12, atol=1e-300)
            np.testing.assert_allclose(up, H[col], rtol=1e-12, atol=1e-300)
            other = np.setdiff1d(np.arange(n), col)
            assert np.all(H[other] <= fl * (1 + 1e-12))
    assert row_entries(P, noise, 2) >= int(np.max(np.diff(mix.imdp.row_ptr)))


def test_nominal_abstraction_refuses_bad_images():
    P = Partition(Box([0.0], [1.0]), 0.5, {})
    noise = TruncatedGaussianNoise([0.03], [0.06])
    with pytest.raises(DimensionError, match="images"):
        nominal_abstraction(P, np.zeros((1, 3, 1)), noise)
    with pytest.raises(InvalidInputError, match="finite"):
        nominal_abstraction(P, np.full((1, 2, 1), np.nan), noise)
    with pytest.raises(InvalidInputError, match="form"):
        nominal_abstraction(P, np.zeros((1, 2, 1)), noise, form="dense")
    with pytest.raises(InvalidInputError, match="one point per cell"):
        nominal_abstraction(P, np.zeros((1, 2, 2, 1)), noise, form="factored")


# --------------------------------------------------------------------------- the pipeline: the robot
def _robot(cell=0.5, tau=0.1):
    """East / north / stay on [0, 5]^2, an obstacle in the middle, the goal in the corner; the dynamics known
    up to tau = 0.1 per component (misspecification), so that the robust lower values are 0 round the obstacle."""
    from robust_imdp import Problem

    steps = {"east": (0.3, 0.0), "north": (0.0, 0.3), "stay": (0.0, 0.0)}
    modes = {k: [f"x1 + {v[0]} + 0.05*sin(x2)", f"x2 + {v[1]} - 0.04*cos(x1)"] for k, v in steps.items()}
    return Problem.from_arrays(
        None, None, None, lower=[0, 0], upper=[5, 5], cell_size=cell,
        regions={"goal": ([4, 4], [5, 5]), "obstacle": ([1.5, 1.5], [3.5, 3.5])}, formula="G !obstacle & F goal",
        threshold=0.9, modes=modes, noise=TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02]), rkhs_bound=0,
        misspecification=tau)


class _RobotSystem:
    mode_names = ("east", "north", "stay")
    steps = np.array([[0.3, 0.0], [0.0, 0.3], [0.0, 0.0]])

    def step(self, x, modes, rng):
        drift = np.stack([0.05 * np.sin(x[:, 1]), -0.04 * np.cos(x[:, 0])], axis=1)
        noise = np.clip(rng.normal(0, 0.01, x.shape), -0.02, 0.02)  # within the noise model's bound
        return x + self.steps[modes] + drift + noise


def test_pipeline_controller_goes_round_the_obstacle():
    """The run ranks tied modes by its nominal model: at (1.0, 2.0), just left of the obstacle, north instead of
    east; seeded Monte Carlo (20 runs from each of the 100 cells): mean empirical satisfaction 0.21 before, 0.77
    after (measured); asserted: at least 0.3 higher (the standard error of each mean is below 0.011), runs
    inside [p_low, p_up] as chance allows, and the same Q_yes cells and p_low as without the nominal model."""
    import dataclasses

    from robust_imdp.pipeline.run import synthesize_from_data
    from robust_imdp.validate import validate

    res = synthesize_from_data(_robot(), progress=False, advice=False, margins=False)
    assert res.synthesis.tie_keys == ("nominal", "optimistic") and "nominal" in res.timings
    P = res.partition
    model = res.abstraction.model if hasattr(res.abstraction, "model") else res.abstraction.imdp  # factored or joint
    old = synthesize(model, P.labels, P.atoms, res.dfa, threshold=0.9,
                     outside_state=P.outside_state)
    before = dataclasses.replace(res, synthesis=old, class_names=np.asarray(old.classes).astype(str))
    x = np.array([1.0, 2.0])
    acts = []
    for r in (before, res):
        c = r.controller()
        c.reset(x)
        acts.append(c.act(x))
    assert acts == ["east", "north"]
    np.testing.assert_array_equal(res.synthesis.classes == "yes", old.classes == "yes")
    np.testing.assert_array_equal(res.synthesis.p_low, old.p_low)
    reps = [validate(r, _RobotSystem(), n_per_cell=20, rng=11) for r in (before, res)]
    assert reps[1].empirical.mean() >= reps[0].empirical.mean() + 0.3
    assert reps[1].passed and reps[0].passed


def test_factored_nominal_model_of_the_centres_is_the_joint_one():
    """On a grid with one point per cell the nominal law is a product of per-axis laws: the factored model
    (per-axis marginals of the degenerate boxes) expands to the joint model's intervals (each contains the
    point probabilities: the two agree to 1e-12 on every listed entry), and a synthesis with it as the nominal
    model takes the same mode at (1.0, 2.0) as with the joint one."""
    from robust_imdp.models.factored import FactoredIMDP
    from robust_imdp.pipeline.nominal_stage import nominal_images
    from robust_imdp.pipeline.run import synthesize_from_data

    problem = _robot()
    res = synthesize_from_data(problem, progress=False, advice=False, margins=False)
    P = res.partition
    y = nominal_images(problem, P, per_axis=1)
    fac = nominal_abstraction(P, y, problem.noise, form="factored")
    joint = nominal_abstraction(P, y, problem.noise).imdp
    assert isinstance(fac, FactoredIMDP)
    rows = P.n_cells * 3  # the cells' rows (the outside state has one choice in the factored expansion, 3 here)
    lo_f, up_f = (a[:rows] for a in fac.to_joint().to_dense())
    lo_j, up_j = (a[:rows] for a in joint.to_dense())
    listed = up_j > 1e-7
    np.testing.assert_allclose(lo_f[listed], lo_j[listed], atol=1e-12)
    np.testing.assert_allclose(up_f[listed], up_j[listed], atol=1e-12)
    model = res.abstraction.model if hasattr(res.abstraction, "model") else res.abstraction.imdp
    q = int(P.locate(np.array([[1.0, 2.0]]))[0])
    modes = []
    for nom in (joint, fac):
        syn = synthesize(model, P.labels, P.atoms, res.dfa, threshold=0.9, outside_state=P.outside_state, nominal=nom)
        modes.append(int(syn.strategy[q, syn.initial_dfa_state[q]]))
    assert modes == [1, 1]  # north
