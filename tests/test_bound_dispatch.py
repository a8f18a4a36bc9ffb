"""The bound stage dispatches through the registry: each method names its bounder by a dotted path."""

import pytest

from robust_imdp.bounds import methods as M
from robust_imdp.errors import InvalidInputError
from robust_imdp.pipeline import bound_gp, bound_rkhs, bound_stage


def test_every_method_resolves_its_bounders():
    assert M.get("optimal").stage() is bound_rkhs.learn_and_bound
    assert M.get("ridge").new_cells_stage() is bound_rkhs.cell_bounder
    assert M.get("chowdhury").stage() is bound_gp.learn_and_bound
    for method in M.METHODS.values():
        if method.refine or method.advice_pilot:
            assert callable(method.new_cells_stage())
    with pytest.raises(InvalidInputError, match="no bounder of new cells"):
        M.get("chowdhury").new_cells_stage()


def test_a_method_that_refines_needs_a_bounder_of_new_cells():
    with pytest.raises(ValueError, match="new_cells"):
        M.BoundMethod("x", route="rkhs", bounder="robust_imdp.pipeline.bound_rkhs:learn_and_bound", refine=True)


def test_bound_stage_calls_the_methods_bounder(monkeypatch):
    seen = []
    fake = M.BoundMethod("fake", route="rkhs", bounder="robust_imdp.pipeline.bound_stage:_fake_stage")
    monkeypatch.setitem(M.METHODS, "fake", fake)
    monkeypatch.setattr(bound_stage, "_fake_stage", lambda *a: seen.append(a) or ("cb", None, {}), raising=False)

    class P:
        error_bound = "fake"
        known = False  # a data-driven problem (known systems go to bound_stage.known_stage)

    assert bound_stage._learn_and_bound(P, "partition", "log", "run", "cache") == ("cb", None, {})
    assert seen == [(P, "partition", "log", "run", "cache")]
