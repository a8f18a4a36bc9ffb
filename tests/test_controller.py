"""Tests of the refined switching controller: DFA tracking, k-step time index, files."""

import json

import numpy as np
import pytest

from robust_imdp.synthesis.controller import Controller
from robust_imdp.spec.dfa import ltlf_to_dfa
from robust_imdp.errors import DimensionError, InvalidInputError, OutsideDomainError
from robust_imdp.models.geometry import Box, Partition, Region
from robust_imdp.synthesis.core import synthesize

from test_synthesis import ATOMS, LABELS, SPEC, reach_avoid_imdp


@pytest.fixture
def partition():
    """X = [0,3] x [0,1], three unit cells: 0 free, 1 obs, 2 des (atoms ("obs", "des"))."""
    X = Box(np.array([0.0, 0.0]), np.array([3.0, 1.0]))
    regions = [Region("obs", Box([1.0, 0.0], [2.0, 1.0])), Region("des", Box([2.0, 0.0], [3.0, 1.0]))]
    p = Partition(X, 1.0, regions)
    assert p.atoms == ATOMS and p.labels.tolist() == LABELS.tolist()
    return p


def make_result(horizon=None):
    return synthesize(reach_avoid_imdp(), LABELS, ATOMS, ltlf_to_dfa(SPEC), threshold=0.5,
                      horizon=horizon, outside_state=3)


FREE, OBS, DES, OUT = (0.5, 0.5), (1.5, 0.5), (2.5, 0.5), (3.5, 0.5)


def test_reach_goal_is_satisfied(partition):
    ctrl = make_result().controller(partition, mode_names=("stay", "go"))
    ctrl.reset(np.array(FREE))
    assert ctrl.status == "running" and ctrl.cell == 0 and ctrl.dfa_state == 0
    assert ctrl.act(np.array(FREE)) == "go"  # mode 1 is the robust choice in cell 0 (p_low 2/3)
    assert ctrl.act(np.array(FREE)) == "go"  # stayed in cell 0: same DFA state, same mode
    assert ctrl.time == 1
    assert ctrl.act(np.array(DES)) is None  # entered des: the DFA accepts
    assert ctrl.status == "satisfied" and ctrl.cell == 2 and ctrl.time == 2


def test_obstacle_and_leaving_X_are_violations(partition):
    ctrl = make_result().controller(partition)
    ctrl.reset(np.array(FREE))
    assert ctrl.act(np.array(FREE)) == 1  # mode index when no names are given
    assert ctrl.act(np.array(OBS)) is None and ctrl.status == "violated"
    ctrl.reset(np.array(FREE))
    ctrl.act(np.array(FREE))
    assert ctrl.act(np.array(OUT)) is None
    assert ctrl.status == "violated" and ctrl.cell == -1


def test_first_label_is_read_at_reset(partition):
    ctrl = make_result().controller(partition)
    ctrl.reset(np.array(DES))  # starting inside des satisfies F des at once
    assert ctrl.status == "satisfied" and ctrl.act(np.array(DES)) is None
    ctrl.reset(np.array(OBS))
    assert ctrl.status == "violated"


def test_bad_use_raises(partition):
    ctrl = make_result().controller(partition)
    with pytest.raises(InvalidInputError, match="before reset"):
        ctrl.act(np.array(FREE))
    with pytest.raises(OutsideDomainError, match=r"x0 must lie in X"):
        ctrl.reset(np.array(OUT))
    ctrl.reset(np.array(FREE))
    with pytest.raises(InvalidInputError, match="must be given the reset state \\(cell 0\\)"):
        ctrl.act(np.array(OBS))
    with pytest.raises(DimensionError, match=r"x must have shape \(2,\)"):
        ctrl.reset(np.zeros(3))
    with pytest.raises(InvalidInputError, match="modes must name at least the 2 modes"):
        make_result().controller(partition, mode_names=("only",))


def test_partition_must_match_result(partition):
    other = Partition(partition.space, 1.0, [Region("obs", Box([2.0, 0.0], [3.0, 1.0])),
                                             Region("des", Box([1.0, 0.0], [2.0, 1.0]))])
    with pytest.raises(InvalidInputError, match=r"partition labels differ .*\(first at cell 1\)"):
        make_result().controller(other)
    small = Partition(Box(np.array([0.0, 0.0]), np.array([2.0, 1.0])), 1.0, [])
    with pytest.raises(DimensionError, match="partition must have the result's 3 cells; got 2"):
        make_result().controller(small)


def test_k_step_strategy_uses_the_time_index(partition):
    res = make_result(horizon=2)
    ctrl = res.controller(partition)
    ctrl.reset(np.array(FREE))
    assert ctrl.act(np.array(FREE)) == 1  # time 0: mode 1 (see the hand-built k = 2 case)
    assert ctrl.act(np.array(FREE)) == 0  # time 1: mode 0
    assert ctrl.act(np.array(FREE)) is None  # horizon reached without des: bounded spec violated
    assert ctrl.status == "violated" and ctrl.time == 2
    ctrl.reset(np.array(FREE))
    ctrl.act(np.array(FREE))
    ctrl.act(np.array(FREE))
    assert ctrl.act(np.array(DES)) is None and ctrl.status == "satisfied"  # accepted at time k


def test_locate_matches_partition(partition):
    ctrl = make_result().controller(partition)
    rng = np.random.default_rng(0)
    x = rng.uniform([-0.5, -0.5], [3.5, 1.5], size=(2000, 2))
    grid = np.array([[a, b] for a in (0.0, 1.0, 2.0, 3.0) for b in (0.0, 0.5, 1.0)])  # faces, corners
    x = np.vstack([x, grid])
    np.testing.assert_array_equal(ctrl.locate(x), partition.locate(x))


def test_save_load_round_trip(partition, tmp_path):
    res = make_result(horizon=2)
    ctrl = res.controller(partition, mode_names=("stay", "go"))
    json_path, npz_path = ctrl.save(tmp_path / "ctrl")
    doc = json.loads(json_path.read_text())
    assert doc["format"] == "robust_imdp.controller" and doc["horizon"] == 2
    assert doc["modes"] == ["stay", "go"] and doc["atoms"] == ["des", "obs"]
    with np.load(npz_path, allow_pickle=False) as z:  # plain arrays only, no pickled objects
        assert set(z.files) >= {"strategy", "cell_letters", "breakpoints_0", "breakpoints_1", "p_low"}
        np.testing.assert_array_equal(z["strategy"], res.strategy)
    back = Controller.load(tmp_path / "ctrl")
    np.testing.assert_array_equal(back.p_low, res.p_low)
    np.testing.assert_array_equal(back.p_up_star, res.p_up_star)
    assert back.threshold == 0.5 and back.metadata["formula"] == SPEC
    for c in (ctrl, back):  # the same trajectory gives the same decisions
        c.reset(np.array(FREE))
    for x in (FREE, FREE, DES):
        assert ctrl.act(np.array(x)) == back.act(np.array(x))
    assert ctrl.status == back.status == "satisfied"
    (tmp_path / "bad.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(InvalidInputError, match="must be a 'robust_imdp.controller' version 1 file"):
        Controller.load(tmp_path / "bad")


def test_constructor_validation(partition):
    res = make_result()
    d = res.dfa
    args = (res.strategy, d.delta, d.initial, d.accepting, d.atoms, res.labels,
            partition.breakpoints, partition.space.lower, partition.space.upper)
    Controller(*args)
    with pytest.raises(DimensionError, match=r"strategy must end with shape \(n_cells, S\) = \(3, 3\)"):
        Controller(res.strategy[:2], *args[1:])
    with pytest.raises(DimensionError, match=r"cell_letters must have shape \(n_cells,\) = \(3,\)"):
        Controller(*args[:5], res.labels[:2], *args[6:])
    with pytest.raises(DimensionError, match=r"dfa_delta must have shape \(S, 4\)"):
        Controller(res.strategy, d.delta[:, :2], *args[2:])


def test_monte_carlo_satisfaction_lies_in_bounds(partition):
    """A true system inside the IMDP's intervals, run under the controller, satisfies the spec
    with a frequency inside [p_low, p_up] of its start cell (paper, Thm. 2).

    True chain from cell 0 under mode 1 ("go"): stay 0.3, des 0.5, leave X 0.2 (inside the
    intervals [0.2, 0.4], [0.4, 0.6], [0, 0.2]); satisfaction probability 0.5 / 0.7 = 0.714.
    Under mode 0: des 0.6, obs 0.4. N = 4000 runs: standard error <= 0.008, we allow 5 SE.
    """
    res = make_result()
    ctrl = res.controller(partition)
    rng = np.random.default_rng(12345)
    centres = {0: FREE, 2: DES, 1: OBS, -1: OUT}
    moves = {1: ([0, 2, -1], [0.3, 0.5, 0.2]), 0: ([2, 1], [0.6, 0.4])}
    n_runs, hits = 4000, 0
    for _ in range(n_runs):
        x = np.array(FREE)
        ctrl.reset(x)
        for _ in range(200):  # P(still running after 200 steps) = 0.3**200: negligible
            u = ctrl.act(x)
            if u is None:
                break
            cells, probs = moves[u]
            x = np.array(centres[int(rng.choice(cells, p=probs))])
        hits += ctrl.status == "satisfied"
    freq = hits / n_runs
    se = np.sqrt(0.714 * 0.286 / n_runs)
    assert abs(freq - 0.5 / 0.7) < 5 * se
    assert res.p_low[0] - 5 * se <= freq <= res.p_up[0] + 5 * se


def test_end_to_end_abstraction_synthesis_controller_monte_carlo():
    """Known contractive 1-D dynamics x' = a_u + 0.3 (x - a_u) + v, v ~ N(0, 0.35^2): abstraction
    (exact image boxes), synthesis of G !obs & F des, then the controller on the true system.
    The satisfaction frequency from uniform starts in a cell must lie in [p_low, p_up] up to
    5 standard errors (N = 400 runs per cell, SE <= 0.025)."""
    from robust_imdp.abstraction.rows import CellBounds, abstract
    from robust_imdp.models.noise import GaussianNoise

    X = Box(np.array([0.0]), np.array([4.0]))
    part = Partition(X, 0.5, [Region("des", Box([3.0], [4.0])), Region("obs", Box([1.0], [1.5]))])
    targets, c = np.array([0.25, 2.25, 3.5]), 0.3

    def f(x, u):
        return targets[u] + c * (x - targets[u])

    lo = np.stack([f(part.cells_lower, u) for u in range(3)])  # f is increasing: exact image box
    hi = np.stack([f(part.cells_upper, u) for u in range(3)])
    noise = GaussianNoise([0.35])
    ab = abstract(part, CellBounds(lo, hi), noise)
    res = synthesize(ab.imdp, part.labels, part.atoms, ltlf_to_dfa("G !obs & F des"), threshold=0.8,
                     outside_state=part.outside_state)
    assert np.all(res.p_low <= res.p_up) and np.all(res.p_up <= res.p_up_star)
    assert res.classes[2] == "no" and res.classes[7] == "yes"  # starts in obs / in des
    ctrl = res.controller(part)
    rng = np.random.default_rng(7)
    n_runs, se = 400, 0.5 / np.sqrt(400)
    for q in (0, 3, 5):
        hits = 0
        for _ in range(n_runs):
            x = rng.uniform(part.cells_lower[q], part.cells_upper[q])
            ctrl.reset(x)
            for _ in range(500):
                u = ctrl.act(x)
                if u is None:
                    break
                x = f(x, u) + noise.sample(1, rng)[0]
            hits += ctrl.status == "satisfied"
        assert res.p_low[q] - 5 * se <= hits / n_runs <= res.p_up[q] + 5 * se, (q, hits / n_runs)
