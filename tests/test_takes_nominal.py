"""The pipeline builds no nominal model where the synthesis would not use it (``synthesis.ties.takes_nominal``): a
factored robust model with one mode, with a horizon, or under the safety reading. Skipping it changes nothing:
the same p_low, p_up and strategy as a synthesis given the nominal model."""

from __future__ import annotations

import numpy as np
import pytest

from robust_imdp.synthesis.ties import takes_nominal


def _car(horizon, formula="G !avoid & F target", form="factored", n_modes=9):
    """Car parking (x' = 0.9 x + 0.7 u + w, w ~ N(0, I)) on a 10 x 10 grid: known dynamics, 9 modes (or the first
    ``n_modes``)."""
    from robust_imdp import GaussianNoise, Problem

    inputs = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)][:n_modes]
    modes = {f"u{a:+d}{b:+d}": (0.9 * np.eye(2), 0.7 * np.array([a, b], float)) for a, b in inputs}
    return Problem.from_arrays(
        None, None, None, lower=[-10, -10], upper=[10, 10], cell_size=2.0,
        regions={"target": ([4, -4], [10, 0]), "avoid": ([4, 0], [10, 4])}, formula=formula, threshold=0.3,
        horizon=horizon, modes=modes, noise=GaussianNoise([1.0, 1.0]), rkhs_bound=0.0, transitions="exact",
        form=form)


def test_takes_nominal_rules():
    """Factored: only with several modes, no horizon and the reach reading; joint: always."""
    from robust_imdp.abstraction.factored import abstraction_model
    from robust_imdp.pipeline.run import synthesize_from_data

    fac = abstraction_model(synthesize_from_data(_car(3), progress=False, advice=False, margins=False).abstraction)
    assert fac.n_modes == 9
    assert takes_nominal(fac, horizon=None, semantics="reach")
    assert not takes_nominal(fac, horizon=3, semantics="reach")
    assert not takes_nominal(fac, horizon=None, semantics="safety")
    one = abstraction_model(synthesize_from_data(_car(None, n_modes=1), progress=False, advice=False,
                                                 margins=False).abstraction)
    assert one.n_modes == 1 and not takes_nominal(one, horizon=None, semantics="reach")
    joint = fac.to_joint()
    assert takes_nominal(joint, horizon=3, semantics="reach") and takes_nominal(joint, horizon=None,
                                                                               semantics="safety")


@pytest.mark.parametrize("formula", ["G !avoid & F target", "G !avoid"])
def test_skipped_nominal_model_changes_nothing(formula):
    """A factored run with a horizon (reach and safety readings) has no 'nominal' stage, and its bounds and strategy
    are bit for bit those of a synthesis given the nominal model the stage would have built."""
    from robust_imdp.pipeline.nominal_stage import nominal_model
    from robust_imdp.pipeline.run import synthesize_from_data
    from robust_imdp.synthesis.core import synthesize

    problem = _car(4, formula)
    res = synthesize_from_data(problem, progress=False, advice=False, margins=False)
    assert res.parameters.get("form") == "factored"
    assert "nominal" not in res.timings
    P = res.partition
    nominal = nominal_model(problem, P)
    assert nominal is not None
    full = synthesize(res.abstraction.model, P.labels, P.atoms, res.dfa, threshold=problem.threshold,
                      horizon=problem.horizon, outside_state=P.outside_state, semantics=problem.semantics,
                      nominal=nominal)
    np.testing.assert_array_equal(res.p_low, full.p_low)
    np.testing.assert_array_equal(res.p_up, full.p_up)
    np.testing.assert_array_equal(np.asarray(res.strategy), np.asarray(full.strategy))


def test_unbounded_factored_run_still_builds_it():
    """Without a horizon (reach reading, 9 modes) the factored synthesis takes the nominal key: the stage runs."""
    from robust_imdp.pipeline.run import synthesize_from_data

    res = synthesize_from_data(_car(None), progress=False, advice=False, margins=False)
    assert res.parameters.get("form") == "factored" and "nominal" in res.timings


def test_preflight_counts_the_nominal_model_of_an_unbounded_factored_run():
    """The pre-flight's cap on the nominal mixture is the nominal stage's, and an unbounded factored run with
    several modes is estimated above the same run with a horizon (its synthesis holds a nominal model)."""
    from robust_imdp.pipeline.nominal_stage import MAX_NOMINAL_ENTRIES
    from robust_imdp.pipeline.preflight import NOMINAL_ENTRIES, estimate_resources

    assert NOMINAL_ENTRIES == MAX_NOMINAL_ENTRIES
    unbounded, bounded = _car(None), _car(4)
    assert estimate_resources(unbounded, 3)["bytes"] > estimate_resources(bounded, 3)["bytes"]
