"""``synthesis.core.robust_lower``: the robust solve's lower value alone (what the advice's re-solves read for
Q_yes) against the full synthesis's ``p_low`` on joint and factored models, both readings, with and without a
horizon; the advice's estimates from it."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from robust_imdp.abstraction.factored import abstraction_model
from robust_imdp.pipeline.run import synthesize_from_data
from robust_imdp.spec.api import to_dfa
from robust_imdp.synthesis.core import robust_lower, synthesize

sys.path.insert(0, str(Path(__file__).parent))
from test_pipeline import tiny_problem  # noqa: E402

#: synthesize's p_low is the evaluation of its tie-broken strategy, which keeps the robust lower value to the
#: brackets' widths: both are proven lower values within the solver's precision (1e-8) of the optimum; 4x it
#: covers the two brackets and their outward rounding
TOL = 4e-8


@pytest.fixture(scope="module")
def models():
    out = {}
    for form in ("joint", "factored"):
        res = synthesize_from_data(tiny_problem(form=form), progress=False, advice=False, margins=False)
        out[form] = (abstraction_model(res.abstraction), res.partition)
    return out


@pytest.mark.parametrize("form", ["joint", "factored"])
@pytest.mark.parametrize("formula, horizon", [("G !obs & F des", None), ("G !obs & F des", 6), ("G !obs", None),
                                              ("G !obs", 5)])
def test_robust_lower_is_the_synthesis_p_low_to_the_solver_precision(models, form, formula, horizon):
    model, part = models[form]
    dfa = to_dfa(formula)
    syn = synthesize(model, part.labels, part.atoms, dfa, threshold=0.9, horizon=horizon,
                     outside_state=part.outside_state)
    low = robust_lower(model, part.labels, part.atoms, dfa, horizon=horizon, outside_state=part.outside_state)
    assert low.shape == (part.n_cells,) and not low.flags.writeable
    p_low, p_up_star = np.asarray(syn.p_low), np.asarray(syn.p_up_star)
    assert np.all(np.abs(low - p_low) <= TOL), float(np.max(np.abs(low - p_low)))
    assert np.all(low <= p_up_star + TOL)  # a lower value: an optimistic solve in its place would exceed p_low
    assert np.any(p_up_star - p_low > 10 * TOL)  # the problem separates the two (the check above has teeth)
    far = np.abs(p_low - 0.9) > TOL  # Q_yes the same wherever p_low is not within the tolerance of the threshold
    assert np.array_equal((low >= 0.9)[far], (p_low >= 0.9)[far])
