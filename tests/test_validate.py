"""Tests of validate.py: Wilson intervals, the table-driven controller and containment checks."""

import numpy as np
import pytest
from scipy.stats import binomtest

from robust_imdp.errors import InvalidInputError, OutsideDomainError
from robust_imdp.validate import ResultFile, simulate, validate, wilson_interval


def test_wilson_known_value():
    # Wilson (1927) at 95 %: k=8, n=10 -> [0.4902, 0.9433] (textbook value, e.g. Agresti & Coull 1998;
    # also what statsmodels' proportion_confint(method="wilson") returns); tolerance = rounding of 4 d.p.
    lo, up = wilson_interval(8, 10, 0.95)
    assert lo == pytest.approx(0.4902, abs=1e-4)
    assert up == pytest.approx(0.9433, abs=1e-4)


def test_wilson_matches_scipy_and_is_vectorised():
    k = np.array([0, 3, 50, 100])
    lo, up = wilson_interval(k, 100, 0.999)
    for ki, l, u in zip(k, lo, up):
        ci = binomtest(int(ki), 100).proportion_ci(0.999, method="wilson")
        assert (l, u) == pytest.approx((ci.low, ci.high), abs=1e-11)  # same closed form, widened by 1e-12
    assert lo[0] == 0.0 and up[-1] == 1.0


def test_wilson_bad_input():
    with pytest.raises(InvalidInputError, match="confidence"):
        wilson_interval(1, 10, 1.5)
    with pytest.raises(InvalidInputError, match="successes"):
        wilson_interval(11, 10)


def _two_cell_doc(p_low, p_up):
    """X = [0,2]x[0,1]; cell 0 = [0,1]x[0,1] labelled des, cell 1 = [1,2]x[0,1]; F des."""
    return {
        "format": "robust_imdp.result/1",
        "space": {"lower": [0.0, 0.0], "upper": [2.0, 1.0]},
        "cells": {"lower": [[0.0, 0.0], [1.0, 0.0]], "upper": [[1.0, 1.0], [2.0, 1.0]]},
        "labels": [["des"], []],
        "modes": ["a", "b"],
        # F des: state 0 waits, state 1 accepts; letter bit 0 = des
        "dfa": {"atoms": ["des"], "initial": 0, "accepting": [1], "delta": [[0, 1], [1, 1]]},
        "strategy": [["a", "a"], ["a", "b"]],
        "p_low": list(p_low), "p_up": list(p_up), "p_up_star": list(p_up),
        "error": [u - lo for lo, u in zip(p_low, p_up)],
        "classes": ["yes", "maybe"], "formula": "F des", "threshold": 0.5, "horizon": None,
        "parameters": {}, "timings": {},
    }


class CoinSystem:
    """Mode a: with prob 0.7 shift x1 by -1 (into des), else leave X. Mode b: stay put."""

    mode_names = ("b", "a")  # deliberately in another order than the result's modes

    def step(self, x, modes, rng):
        x = x.copy()
        move = modes == 1
        hit = rng.random(len(x)) < 0.7
        x[move & hit, 0] -= 1.0
        x[move & ~hit, 0] += 5.0
        return x


def test_simulate_outcomes_follow_the_tables():
    res = ResultFile.from_dict(_two_cell_doc([1.0, 0.6], [1.0, 0.8]))
    x0 = np.array([[0.5, 0.5], [1.5, 0.5]])
    tr = simulate(res, CoinSystem(), x0, max_steps=5, rng=1, record=True)
    assert tr.outcome[0] == 1 and tr.steps[0] == 0  # starts in des: first label read, satisfied
    assert tr.outcome[1] in (1, 2) and tr.steps[1] == 1  # one coin flip decides
    assert tr.paths[1].shape == (2, 2)
    with pytest.raises(OutsideDomainError, match="x0"):
        simulate(res, CoinSystem(), [[3.0, 0.5]], max_steps=2, rng=0)


def test_validate_contains_true_probability_and_flags_a_wrong_bound():
    # P(sat | cell 1) = 0.7 exactly; [0.6, 0.8] must contain it, [0.8, 0.9] must be flagged
    # (n = 2000: the 99.9 % Wilson half-width is ~0.034, so 0.7 vs 0.8 is ~10 sd apart).
    good = validate(_two_cell_doc([1.0, 0.6], [1.0, 0.8]), CoinSystem(), n_per_cell=2000,
                    max_steps=3, rng=2)
    assert good.outside.size == 0 and good.containment_rate == 1.0
    assert abs(good.empirical[1] - 0.7) < 0.05
    bad = validate(_two_cell_doc([1.0, 0.8], [1.0, 0.9]), CoinSystem(), n_per_cell=2000,
                   max_steps=3, rng=2)
    assert bad.outside.tolist() == [1]
    assert "OUTSIDE cell 1" in bad.summary()


def test_capped_runs_count_conservatively():
    # Mode b keeps cell 1 in place forever: every run is capped. Capped runs count as satisfied
    # against p_low and as not satisfied against p_up, so neither [0.9, 1] nor [0, 0.1] is flagged.
    doc = _two_cell_doc([1.0, 0.9], [1.0, 1.0])
    doc["strategy"] = [["a", "a"], ["b", "b"]]
    rep = validate(doc, CoinSystem(), n_per_cell=50, max_steps=4, cells=[1], rng=0)
    assert rep.capped.tolist() == [50] and rep.outside.size == 0
    doc["p_low"], doc["p_up"] = [1.0, 0.0], [1.0, 0.1]
    rep = validate(doc, CoinSystem(), n_per_cell=50, max_steps=4, cells=[1], rng=0)
    assert rep.outside.size == 0
    assert "capped runs: 50 of 50" in rep.summary()


def test_locator_and_sink():
    res = ResultFile.from_dict(_two_cell_doc([1.0, 0.6], [1.0, 0.8]))
    loc = res.locator()
    assert loc([[0.2, 0.2], [1.2, 0.9], [2.0, 1.0], [2.1, 0.0]]).tolist() == [0, 1, 1, -1]
    assert res.dfa_sink().tolist() == [False, False]


def test_bad_documents():
    doc = _two_cell_doc([1.0, 0.6], [1.0, 0.8])
    del doc["dfa"]
    with pytest.raises(InvalidInputError, match="contract"):
        ResultFile.from_dict(doc)
    with pytest.raises(InvalidInputError, match="true_system has no modes"):
        class Other:
            mode_names = ("x",)
        simulate(_two_cell_doc([1, 0], [1, 1]), Other(), [[0.5, 0.5]])


def test_case_study_true_systems_match_the_paper():
    from robust_imdp.casestudies.systems import true_system

    rng = np.random.default_rng(0)
    x = rng.uniform(-2, 2, size=(500, 2))
    lin = true_system("three_mode_linear")
    A = [np.array([[0.4, 0.1], [0, 0.5]]), np.array([[0.4, 0.5], [0, 0.5]]),
         np.array([[0.4, 0], [0.5, 0.5]])]
    for u in range(3):
        v = lin.step(x, np.full(500, u), rng) - x @ A[u].T
        assert np.all(np.abs(v) <= 0.01)  # truncated to [-sigma, sigma]
        assert 0.004 < np.std(v) < 0.007  # N(0, 0.01^2) truncated at 1 sd: sd = 0.0054
    non = true_system("four_mode_nonlinear")
    s1, s2, c1, c2 = np.sin(x[:, 0]), np.sin(x[:, 1]), np.cos(x[:, 0]), np.cos(x[:, 1])
    g = [np.c_[0.5 + 0.2 * s2, 0.4 * c1], np.c_[-0.5 + 0.2 * s2, 0.4 * c1],
         np.c_[0.4 * c2, 0.5 + 0.2 * s1], np.c_[0.4 * c2, -0.5 + 0.2 * s1]]
    for u in range(4):
        v = non.step(x, np.full(500, u), rng) - x - g[u]
        assert np.all(np.abs(v) <= 0.01)
