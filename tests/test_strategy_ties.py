"""Which action the strategy takes among equals (lexicographic: lower value, then optimistic value).

Where every action has the same robust lower value -- 0 wherever the adversary can always force
a failure -- the first mode used to win the tie, and on the newcomer's 2-D robot it drove
into the obstacle or off the map although going round was possible (``p_up_star = 1``).  These
tests pin the lexicographic choice, that it never costs lower value (the proven bound of the
returned strategy), and the result fields that separate "no under this controller" from "no
controller can".
"""

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from robust_imdp.solvers import product
from robust_imdp.abstraction.rows import CellBounds, abstract
from robust_imdp.spec.dfa import ltlf_to_dfa
from robust_imdp.models.geometry import Box, Partition, Region
from robust_imdp.models.imdp import IMDP
from robust_imdp.models.noise import TruncatedGaussianNoise
from robust_imdp.solvers.api import evaluate_strategy, solve_reachability
from robust_imdp.synthesis.core import synthesize

sys.path.insert(0, str(Path(__file__).parent))
from test_io import _fake_result  # noqa: E402  (a hand-built 2-cell result)
from test_synthesis import random_imdp  # noqa: E402


# --------------------------------------------------------------------------- hand-built models
def _dense(n, a):
    return np.zeros((n, a, n)), np.zeros((n, a, n))


def zero_region_with_self_loop():
    """States a=0, b=1, target t=2, trap x=3; two actions.

    a, action 0: stays in a (self-loop [1, 1]);  a, action 1: -> b [1, 1]
    b, both actions: -> t [0, 1], -> x [0, 1]  (the adversary may send everything to x)
    So the robust lower value is 0 everywhere; the optimistic value is 1 at a and b under any
    action of b, and at a only under action 1: the self-loop ties in ``max_p p.U`` (U(a) = 1)
    but never reaches t.
    """
    lo, up = _dense(4, 2)
    lo[0, 0, 0] = up[0, 0, 0] = 1.0
    lo[0, 1, 1] = up[0, 1, 1] = 1.0
    up[1, :, 2] = up[1, :, 3] = 1.0
    for q in (2, 3):
        lo[q, :, q] = up[q, :, q] = 1.0
    return IMDP.from_dense(lo, up)


def positive_tie():
    """a=0 with two actions of equal robust lower value 0.5 (t=1 target, x=2 trap):
    action 0: -> t [0.5, 0.5], -> x [0.5, 0.5] (optimistic value 0.5);
    action 1: -> t [0.5, 1.0], -> x [0.0, 0.5] (optimistic value 1)."""
    lo, up = _dense(3, 2)
    lo[0, 0, 1] = up[0, 0, 1] = lo[0, 0, 2] = up[0, 0, 2] = 0.5
    lo[0, 1, 1], up[0, 1, 1], up[0, 1, 2] = 0.5, 1.0, 0.5
    for q in (1, 2):
        lo[q, :, q] = up[q, :, q] = 1.0
    return IMDP.from_dense(lo, up)


def tie_with_cycle():
    """a=0 (t=1 target, x=2 trap): action 0 is a self-loop, action 1 -> t [0.5, 1], -> x [0, 0.5].
    At the fixed point both rows have lower value 0.5 (the self-loop's is a's own value) and
    optimistic value 1: a choice by values alone may take the loop (value 0); the attractor must
    take action 1."""
    lo, up = _dense(3, 2)
    lo[0, 0, 0] = up[0, 0, 0] = 1.0
    lo[0, 1, 1], up[0, 1, 1], up[0, 1, 2] = 0.5, 1.0, 0.5
    for q in (1, 2):
        lo[q, :, q] = up[q, :, q] = 1.0
    return IMDP.from_dense(lo, up)


def _lexicographic(imdp, target, avoid):
    opt = solve_reachability(imdp, target, avoid=avoid, adversary="optimistic")
    rob = solve_reachability(imdp, target, avoid=avoid, adversary="pessimistic", tie_break=opt)
    low = evaluate_strategy(imdp, target, rob.strategy, avoid=avoid, adversary="pessimistic")
    up = evaluate_strategy(imdp, target, rob.strategy, avoid=avoid, adversary="optimistic")
    return rob, low, up


def test_zero_lower_value_takes_the_progressing_optimistic_action():
    imdp = zero_region_with_self_loop()
    rob, low, up = _lexicographic(imdp, [2], [3])
    assert rob.strategy[0] == 1  # not the first action, not the self-loop that ties in U
    np.testing.assert_allclose(low.lower[:2], [0, 0], atol=1e-12)  # 0: the adversary sends b's mass to x
    np.testing.assert_allclose(up.upper[:2], [1, 1], atol=1e-8)  # a -> b -> t when the intervals allow
    # without the optimistic solve the tie goes to the first action: the loop, optimistic value 0
    first = solve_reachability(imdp, [2], avoid=[3], adversary="pessimistic")
    assert first.strategy[0] == 0
    assert evaluate_strategy(imdp, [2], first.strategy, avoid=[3], adversary="optimistic").upper[0] < 1e-8


def test_positive_tie_broken_by_the_optimistic_value():
    rob, low, up = _lexicographic(positive_tie(), [1], [2])
    assert rob.strategy[0] == 1
    np.testing.assert_allclose(low.lower[0], 0.5, atol=1e-12)  # 0.5 to t whatever the adversary does
    np.testing.assert_allclose(up.upper[0], 1.0, atol=1e-12)  # action 0 would give 0.5


def test_tie_through_a_cycle_keeps_the_lower_value():
    rob, low, _ = _lexicographic(tie_with_cycle(), [1], [2])
    assert rob.strategy[0] == 1
    np.testing.assert_allclose(low.lower[0], 0.5, atol=1e-8)  # the loop would give 0


def test_k_step_ties_use_the_optimistic_value():
    # every step: the lower values tie at 0.5, the optimistic ones are 0.5 and 1
    imdp = positive_tie()
    opt = solve_reachability(imdp, [1], avoid=[2], adversary="optimistic", horizon=2)
    rob = solve_reachability(imdp, [1], avoid=[2], adversary="pessimistic", horizon=2, tie_break=opt)
    assert rob.strategy[:, 0].tolist() == [1, 1]
    up = evaluate_strategy(imdp, [1], rob.strategy, avoid=[2], adversary="optimistic", horizon=2)
    np.testing.assert_allclose(up.upper[0], 1.0, atol=1e-12)


def test_tie_break_must_come_from_the_same_model():
    imdp = positive_tie()
    opt = solve_reachability(imdp, [1], avoid=[2], adversary="optimistic")
    with pytest.raises(Exception, match="tie_break"):
        solve_reachability(zero_region_with_self_loop(), [2], avoid=[3], tie_break=opt)
    with pytest.raises(Exception, match="tie_break"):
        solve_reachability(imdp, [1], avoid=[2], tie_break=np.zeros(3))


# --------------------------------------------------------------------------- never costs lower value
@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("horizon", [None, 3])
def test_lexicographic_strategy_keeps_the_optimal_lower_value(seed, horizon):
    """On random models (many exact ties: zero-probability entries, sinks) the returned strategy's
    proven p_low is the first-choice strategy's within 1e-9 (twice the tolerance of both
    brackets, precision 1e-10), on every cell; no Q_yes cell is lost."""
    rng = np.random.default_rng(seed)
    n_cells = 8
    imdp = random_imdp(rng, n_cells + 1, 3, width=0.15)
    atoms = ("o", "d1", "d2")
    labels = rng.choice([0, 0, 1, 2, 4, 6], size=n_cells)
    dfa = ltlf_to_dfa("G !o & F d1 & F d2")
    kw = dict(avoid=np.array([n_cells]), horizon=horizon, precision=1e-10)
    res = synthesize(imdp, labels, atoms, dfa, threshold=0.3, horizon=horizon, outside_state=n_cells,
                     precision=1e-10)
    letters = np.append(res.labels, 0)
    first = product.solve_product(imdp, letters, dfa, **kw)
    ev = product.evaluate_product_strategy(imdp, letters, dfa, first.strategy, adversary="pessimistic", **kw)
    old = np.asarray(ev.initial_lower)[:n_cells]
    assert np.all(res.p_low >= old - 1e-9)
    assert np.all(res.p_low >= np.asarray(first.initial_lower)[:n_cells] - 1e-9)  # the optimum's lower end
    assert not np.any((old >= 0.3) & (res.classes != "yes"))
    assert res.strategy_choice == "lexicographic"


# --------------------------------------------------------------------------- the newcomer's robot
def robot_16x16():
    """The newcomer's 16 x 16 robot (shared/newcomer/robot2d_16.toml) with the learned part
    replaced by a fixed box: the known steps of 0.3 (east, west, north, south), the data
    generator's drift (0.05 sin x2, -0.04 cos x1) bounded over each cell (9 x 9 samples plus a
    Lipschitz margin) and widened by 0.045 (the learned eps median of the real run), truncated
    Gaussian noise sigma 0.01, bound 0.02.  The real run's numbers: Q_no 161, 128 of them
    outside the obstacle at p_up_star = 1 under east; this variant: 156 and 124."""
    P = Partition(Box([0, 0], [4, 4]), 0.25, {"goal": Region("goal", Box([3, 3], [4, 4])),
                                              "obstacle": Region("obstacle", Box([1.5, 1.0], [2.5, 3.0]))})
    L, U = P.cells_lower, P.cells_upper
    steps = np.array([[0.3, 0.0], [-0.3, 0.0], [0.0, 0.3], [0.0, -0.3]])
    g = np.linspace(0, 1, 9)
    xs = L[:, None, :] + (U - L)[:, None, :] * np.stack(np.meshgrid(g, g), -1).reshape(1, -1, 2)
    d = np.stack([0.05 * np.sin(xs[..., 1]), -0.04 * np.cos(xs[..., 0])], -1)
    lip = np.array([0.05, 0.04]) * 0.25 / 16  # Lipschitz constant x half the sample spacing
    margin = 0.045
    lo = np.stack([L + s + d.min(1) - lip for s in steps]) - margin
    hi = np.stack([U + s + d.max(1) + lip for s in steps]) + margin
    ab = abstract(P, CellBounds(lo, hi), TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02]))
    dfa = ltlf_to_dfa("G !obstacle & F goal")
    return P, ab, dfa


def test_newcomer_robot_no_q_no_cell_where_a_controller_might_succeed():
    P, ab, dfa = robot_16x16()
    n = P.n_cells
    res = synthesize(ab.imdp, P.labels, P.atoms, dfa, threshold=0.9, outside_state=P.outside_state)
    obstacle = (np.asarray(P.labels) >> P.atoms.index("obstacle")) & 1 == 1
    mode = res.strategy[np.arange(n), res.initial_dfa_state]
    no = res.classes == "no"
    # before: 124 cells outside the obstacle were Q_no with p_up_star = 1, all under east (mode 0)
    could = no & ~obstacle & (res.p_up_star >= 0.9)
    assert np.count_nonzero(could) == 0, (np.count_nonzero(could), np.bincount(mode[could], minlength=4))
    # where no action has a positive lower value the strategy is not the first mode everywhere
    # (before: east in all of them), and it can still succeed (p_up >= threshold, before 0)
    zero = (res.p_low == 0) & ~obstacle & (res.p_up_star >= 0.9)
    assert zero.sum() > 50 and np.unique(mode[zero]).size >= 3
    assert np.all(res.p_up[zero] >= 0.9)
    # the bottom-right corner cell [3.75, 4] x [0, 0.25]: east leaves X; the robot goes north instead
    corner = int(np.flatnonzero(np.all(np.isclose(P.cells_lower, [3.75, 0.0]), axis=1))[0])
    assert mode[corner] == 2 and res.p_up[corner] >= 0.9
    # the cells that are "no" are those where no controller can meet the threshold
    assert np.array_equal(no & ~obstacle, ~obstacle & (res.p_up_star < 0.9))
    # no guarantee lost: the first-choice strategy's p_low (same model) is matched on every cell
    letters = np.append(res.labels, 0)
    first = product.solve_product(ab.imdp, letters, dfa, avoid=[n])
    ev = product.evaluate_product_strategy(ab.imdp, letters, dfa, first.strategy, avoid=[n])
    np.testing.assert_array_less(np.asarray(ev.initial_lower)[:n] - 1e-8, res.p_low + 1e-300)
    assert np.count_nonzero(res.classes == "yes") == np.count_nonzero(np.asarray(ev.initial_lower)[:n] >= 0.9)


# --------------------------------------------------------------------------- result fields
def test_result_file_and_summary_separate_no_controller_can():
    res = _fake_result()  # cell 1: "no", p_up_star 0.5 < threshold 0.9
    from robust_imdp.io.files import result_to_dict

    doc = result_to_dict(res)
    assert doc["no_strategy_can"] == [False, True]
    res.synthesis.p_up_star = np.array([1.0, 0.95])  # cell 1 "no" under this controller only
    assert result_to_dict(res)["no_strategy_can"] == [False, False]


def test_result_npz_json_and_read_back(tmp_path):
    from robust_imdp.io.files import load_result, save_result

    res = _fake_result()
    save_result(res, tmp_path)
    assert json.loads((tmp_path / "result.json").read_text())["no_strategy_can"] == [False, True]
    with np.load(tmp_path / "result.npz") as z:
        assert z["no_strategy_can"].tolist() == [False, True]
    assert load_result(tmp_path).no_strategy_can.tolist() == [False, True]


def test_pipeline_summary_splits_q_no():
    from robust_imdp.pipeline.result import Result

    syn = SimpleNamespace(p_low=np.array([1.0, 0.0, 0.0]), p_up=np.array([1.0, 0.0, 0.5]),
                          p_up_star=np.array([1.0, 0.95, 0.5]), error=np.array([0.0, 0.95, 0.5]))
    problem = SimpleNamespace(formula="F goal", threshold=0.9, horizon=None, mode_names=("a",))
    r = Result(problem=problem, partition=None, abstraction=None, dfa=None, synthesis=syn,
               class_names=np.array(["yes", "no", "no"]), timings={"total": 1.0}, parameters={})
    text = r.summary()
    assert "Q_no 2" in text
    assert "Q_no: 1 where no controller can meet the threshold (p_up_star < 0.9), 1 under this controller only" \
        in text
    assert r.no_strategy_can.tolist() == [False, False, True]
