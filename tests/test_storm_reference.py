"""Storm (stormpy, optional) as an external reference for our values and our exported files.

Storm's robust value iteration stops on a residual (precision 1e-10 here), so agreement is
asserted to 1e-6 (the brief's tolerance for this comparison); models have <= 12 states.
"""

from __future__ import annotations

import numpy as np
import pytest

from robust_imdp.solvers import api as solve
from robust_imdp.errors import InvalidInputError
from robust_imdp.io.formats import storm_reachability, to_stormpy, write_drn
from robust_imdp.models.imdp import IMDP
from robust_imdp.solvers.lp import nature_maximises, ordering_inner_dense, solve_reachability_lp

from soundness_checks import check_close, drop_upper, raise_lower

stormpy = pytest.importorskip("stormpy")
pytestmark = pytest.mark.stormpy

TOL = 1e-6
PREC = 1e-10


def random_imdp(rng, n, a, k, *, positive_lower, floor=0.0):
    lo = np.zeros((n, a, n))
    up = np.zeros((n, a, n))
    for s in range(n):
        for u in range(a):
            succ = rng.choice(n, size=k, replace=False)
            p = rng.dirichlet(np.ones(k))
            w = rng.uniform(0.0, 0.2, size=k)
            lo[s, u, succ] = np.minimum(np.clip(p - w, 0.01 if positive_lower else 0.0, 1.0), p)
            up[s, u, succ] = np.clip(p + w, 0.0, 1.0)
    m = IMDP.from_dense(lo, up)
    if floor:
        m = IMDP.from_csr(m.state_ptr, m.row_ptr, m.col, m.lower, m.upper, floor=np.full(m.n_choices, floor))
    return m


def bounded_reference(imdp, target, horizon, nature_max, ctrl_max):
    """k-step values by k dense ordering Bellman steps (the definition of bounded reachability)."""
    lo, up = imdp.to_dense()
    x = target.astype(float)
    for _ in range(horizon):
        q = ordering_inner_dense(lo, up, x, nature_max)
        v = np.full(imdp.n_states, -np.inf if ctrl_max else np.inf)
        (np.maximum if ctrl_max else np.minimum).at(v, imdp.row_state, q)
        x = np.where(target, 1.0, v)
    return x


@pytest.mark.slow
@pytest.mark.parametrize("adversary", ["pessimistic", "optimistic"])
@pytest.mark.parametrize("objective", ["maximize", "minimize"])
def test_unbounded_storm_matches_lp(adversary, objective):
    rng = np.random.default_rng(7)
    for _ in range(2):
        m = random_imdp(rng, 6, 2, 3, positive_lower=True)  # 64 strategies for the brute force
        tgt = np.zeros(6, bool)
        tgt[0] = True
        storm = storm_reachability(m, tgt, adversary=adversary, objective=objective, precision=PREC)
        lp = solve_reachability_lp(m, tgt, adversary=adversary, objective=objective)
        np.testing.assert_allclose(storm, 0.5 * (lp.lower + lp.upper), atol=TOL)


@pytest.mark.parametrize("adversary", ["pessimistic", "optimistic"])
def test_bounded_storm_with_zero_lower_bounds_and_floors(adversary):
    rng = np.random.default_rng(8)
    m = random_imdp(rng, 10, 3, 3, positive_lower=False, floor=0.01)
    tgt = np.zeros(10, bool)
    tgt[[1, 2]] = True
    storm = storm_reachability(m, tgt, adversary=adversary, horizon=6, precision=PREC)
    ref = bounded_reference(m, tgt, 6, nature_maximises(adversary, "maximize"), True)
    np.testing.assert_allclose(storm, ref, atol=TOL)


def test_written_drn_loads_in_storm(tmp_path):
    m = random_imdp(np.random.default_rng(9), 6, 2, 3, positive_lower=True)
    tgt = np.zeros(6, bool)
    tgt[5] = True
    write_drn(m, tmp_path / "m.drn", target=tgt)
    model = stormpy.build_model_from_drn[stormpy.Interval](str(tmp_path / "m.drn"))
    assert (model.nr_states, model.nr_choices) == (6, m.n_choices)
    from_file = storm_reachability(model, tgt, adversary="pessimistic", precision=PREC)
    in_memory = storm_reachability(to_stormpy(m, tgt), tgt, adversary="pessimistic", precision=PREC)
    np.testing.assert_allclose(from_file, in_memory, atol=1e-12)


def test_storm_refuses_zero_lower_bounds_unbounded():
    m = random_imdp(np.random.default_rng(1), 5, 2, 3, positive_lower=False, floor=0.01)
    with pytest.raises(InvalidInputError, match="zero lower bounds.*horizon=K"):
        storm_reachability(m, [0], adversary="pessimistic")


def solver_and_storm(seed=10, trials=3):
    """(ours, storm) value pairs on random 12-state models: unbounded and 5-step, both
    adversaries (max-min = robust, max-max = optimistic) and both objectives."""
    rng = np.random.default_rng(seed)
    for _ in range(trials):
        m = random_imdp(rng, 12, 3, 4, positive_lower=True)
        tgt = np.zeros(12, bool)
        tgt[[0, 1]] = True
        for adversary in ("pessimistic", "optimistic"):
            for objective in ("maximize", "minimize"):
                for horizon in (None, 5):
                    ours = solve.solve_reachability(m, tgt, adversary=adversary, objective=objective,
                                                    horizon=horizon, precision=1e-10)
                    storm = storm_reachability(m, tgt, adversary=adversary, objective=objective, horizon=horizon,
                                               precision=PREC)
                    yield (adversary, objective, horizon), ours, storm


def test_solver_matches_storm():
    """Both ends of our bracket agree with Storm's value to TOL, for max-min and max-max (and the
    minimising controller), unbounded and k-step: lower AND upper values are compared."""
    for case, ours, storm in solver_and_storm():
        assert check_close(ours.lower, ours.upper, storm, TOL) == 0, case


def test_storm_comparison_sees_shrunk_bounds():
    """Sensitivity of the comparison above: the upper ends x 0.99 (and x (1 - 1e-3)), or the lower
    ends x (1 + 1e-3), disagree with Storm in every case, on the states whose value exceeds 0.02
    (at least 2 per case; the shifts there are >= 2e-5 >> TOL)."""
    for case, ours, storm in solver_and_storm(trials=1):
        informative = storm > 0.02
        assert informative.sum() >= 2, case
        for lo, up in ((ours.lower, drop_upper(ours.upper, 0.01)), (ours.lower, drop_upper(ours.upper)),
                       (raise_lower(ours.lower), ours.upper)):
            assert check_close(lo[informative], up[informative], storm[informative], TOL) > 0, case


def test_to_stormpy_chunking_is_invisible():
    # chunks of 5 entries cut the matrix at many state boundaries; the model must not change
    m = random_imdp(np.random.default_rng(12), 9, 3, 3, positive_lower=True)
    tgt = np.zeros(9, bool)
    tgt[4] = True
    a = to_stormpy(m, tgt, chunk=5)
    b = to_stormpy(m, tgt)
    assert (a.nr_states, a.nr_choices, a.nr_transitions) == (9, 27, m.nnz)
    for s in range(9):
        assert a.transition_matrix.get_row_group_start(s) == m.state_ptr[s]
    np.testing.assert_array_equal(storm_reachability(a, tgt, precision=PREC), storm_reachability(b, tgt, precision=PREC))


def test_read_drn_reads_storms_own_export(tmp_path):
    from robust_imdp.io.formats import load_drn

    m = random_imdp(np.random.default_rng(13), 5, 2, 3, positive_lower=True)
    stormpy.io.export_to_drn(to_stormpy(m, [3]), str(tmp_path / "s.drn"))
    f = load_drn(tmp_path / "s.drn")
    for name in ("state_ptr", "row_ptr", "col", "actions"):
        np.testing.assert_array_equal(getattr(f.imdp, name), getattr(m, name))
    # Storm writes 10 significant digits, so the bounds come back to ~1e-10
    np.testing.assert_allclose(f.imdp.lower, m.lower, atol=1e-9)
    np.testing.assert_allclose(f.imdp.upper, m.upper, atol=1e-9)
    np.testing.assert_array_equal(np.flatnonzero(f.labels["target"]), [3])
