"""How many flagged cells chance allows, the simulate command's exit status, and checks of a user's step()."""

import json

import numpy as np
import pytest
from scipy.stats import binom

from robust_imdp.cli import main
from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.validate import allowed_outside, flag_probability, simulate, validate, wilson_interval


def coin_doc(n_start: int, p_low: float, p_up: float):
    """1-D result: cells 0..n_start-1 start, cell n_start = des, n_start+1 = obs; formula F des & G !obs."""
    c = n_start + 2
    lo = np.arange(c, dtype=float)[:, None]
    labels = [[] for _ in range(n_start)] + [["des"], ["obs"]]
    pl = [p_low] * n_start + [1.0, 0.0]
    pu = [p_up] * n_start + [1.0, 0.0]
    return {
        "format": "robust_imdp.result/1", "space": {"lower": [0.0], "upper": [float(c)]},
        "cells": {"lower": lo.tolist(), "upper": (lo + 1).tolist()}, "labels": labels, "modes": ["a"],
        # over (des, obs): 0 wait, 1 accept, 2 sink
        "dfa": {"atoms": ["des", "obs"], "initial": 0, "accepting": [1],
                "delta": [[0, 1, 2, 2], [1, 1, 1, 1], [2, 2, 2, 2]]},
        "strategy": [["a", "a", "a"]] * c, "p_low": pl, "p_up": pu, "p_up_star": pu,
        "error": (np.array(pu) - np.array(pl)).tolist(), "classes": ["maybe"] * c, "formula": "F des & G !obs",
        "threshold": 0.5, "horizon": None, "parameters": {}, "timings": {},
    }


class Coin:
    """One step from any start cell: into des (cell n) with probability p, else into obs (cell n + 1)."""

    mode_names = ("a",)

    def __init__(self, n_start: int, p: float):
        self.n, self.p = n_start, p

    def step(self, x, modes, rng):
        hit = rng.random(len(x)) < self.p
        return np.where(hit, self.n + 0.5, self.n + 1.5)[:, None]


# --------------------------------------------------------------------------- the chance of a flag
def test_flag_probability_by_hand():
    # n = 50 at 99.9 %: the Wilson upper end after 49 of 50 is 0.99843 < 0.999, so a cell with
    # p_low = 0.999 is flagged whenever one run fails: 1 - 0.999^50 = 0.0488 (not 0.001)
    _, wu = wilson_interval(49, 50, 0.999)
    assert 0.9984 < wu < 0.9985
    a = flag_probability([0.999, 0.0, 1.0], [0.999, 1.0, 1.0], 50, 0.999)
    np.testing.assert_allclose(a[0], 1 - 0.999 ** 50, rtol=1e-8)  # rtol: the 1e-9 outward margin
    assert a[1] == 0.0 and a[2] == 0.0  # [0, 1] cannot be contradicted; p = 1 always gives 50 of 50


@pytest.mark.parametrize("n,confidence,p_low,p_up,p", [
    (20, 0.9, 0.7, 0.7, 0.7), (20, 0.9, 0.95, 0.95, 0.95), (20, 0.9, 0.3, 0.6, 0.45),
    (50, 0.999, 0.999, 0.999, 0.999), (50, 0.99, 0.02, 0.1, 0.02), (5, 0.9, 0.5, 0.9, 0.9),
])
def test_flag_probability_bounds_the_flag_rate_of_correct_bounds(n, confidence, p_low, p_up, p):
    # Seeded Monte Carlo of validate's two checks (no capped runs) with the true p inside
    # [p_low, p_up]: the flag frequency stays below the bound + 4 standard errors, and equals the
    # bound within 4 standard errors where the bound is attained (p = p_low = p_up).
    rng = np.random.default_rng(7)
    trials = 200_000
    s = rng.binomial(n, p, trials)
    wl, wu = wilson_interval(s, n, confidence)
    rate = np.mean((p_low > wu) | (p_up < wl))
    bound = float(flag_probability([p_low], [p_up], n, confidence)[0])
    se = np.sqrt(max(bound * (1 - bound), 1e-6) / trials)
    assert rate <= bound + 4 * se, (rate, bound)
    if p_low == p_up == p:
        assert rate >= bound - 4 * se, (rate, bound)


def test_allowed_outside_is_the_binomial_tail_quantile():
    # 1024 cells at 0.001: P(Bin(1024, 0.001) > 5) = 6e-4 <= 0.001 < P(> 4) = 3.5e-3
    assert allowed_outside(np.full(1024, 1e-3), 0.999) == 5
    assert binom.sf(5, 1024, 1e-3) <= 1e-3 < binom.sf(4, 1024, 1e-3)
    assert allowed_outside(np.zeros(7), 0.999) == 0 and allowed_outside([], 0.999) == 0
    assert allowed_outside(np.full(10, 1.0), 0.999) == 10


def test_correct_bounds_pass_even_where_wilson_is_poor_and_wrong_ones_fail():
    # 200 cells whose runs succeed with probability 0.999 exactly, reported as p_low = p_up = 0.999:
    # about 200 * 0.049 = 10 cells are flagged by chance, far above the nominal 200 * 0.001.
    n_start = 200
    doc = coin_doc(n_start, 0.999, 0.999)
    good = validate(doc, Coin(n_start, 0.999), n_per_cell=50, rng=3)
    assert 0 < len(good.outside) <= good.allowed_outside and good.passed
    assert good.expected_outside > 0.2 * n_start * 0.001 * 10  # the sum of the cells' flag probabilities
    assert "passed:" in good.summary()
    # the same bounds on a system that succeeds with probability 0.9: contradicted
    bad = validate(doc, Coin(n_start, 0.9), n_per_cell=50, rng=3)
    assert not bad.passed and len(bad.outside) > 150
    assert "FAILED" in bad.summary() and "more than chance allows" in bad.summary()


# --------------------------------------------------------------------------- the command
COIN_FILE = '''
import numpy as np


class Coin:
    mode_names = ("a",)
    p = {p}

    def step(self, x, modes, rng):
        hit = rng.random(len(x)) < self.p
        return np.where(hit, {n} + 0.5, {n} + 1.5)[:, None]
'''


@pytest.mark.parametrize("p,code", [(0.999, 0), (0.9, 1)])
def test_simulate_exits_1_when_more_cells_are_flagged_than_chance_allows(tmp_path, capsys, p, code):
    (tmp_path / "result.json").write_text(json.dumps(coin_doc(100, 0.999, 0.999)))
    (tmp_path / "coin.py").write_text(COIN_FILE.format(p=p, n=100))
    got = main(["simulate", str(tmp_path), "--true-system", f"{tmp_path / 'coin.py'}:Coin", "--n-per-cell", "50",
                "--seed", "1"])
    out, err = capsys.readouterr()
    assert got == code, err
    rep = json.loads((tmp_path / "validation.json").read_text())
    assert rep["passed"] is (code == 0) and rep["allowed_outside"] >= 0
    if code:
        assert err.startswith(f"robust-imdp: validation failed: {len(rep['outside'])} of 102 cells are flagged, more "
                              f"than the {rep['allowed_outside']} that chance allows at confidence 0.999")
    else:
        assert err == "" and "passed:" in out


# --------------------------------------------------------------------------- a user's step()
class Returns:
    mode_names = ("a", "b")

    def __init__(self, make):
        self.make = make

    def step(self, x, modes, rng):
        return self.make(np.array(x, float), modes)


def _two_mode_doc():
    doc = coin_doc(4, 0.0, 1.0)
    doc["modes"] = ["a", "b"]
    doc["strategy"] = [["a", "a", "a"], ["b", "b", "b"]] * 3  # cells 1, 3, 5 use mode b
    return doc


def _nan_in_b(x, modes):
    x[modes == 1] = np.nan
    return x


@pytest.mark.parametrize("make,error,match", [
    (_nan_in_b, InvalidInputError,
     r"must return finite next states; call 1 \(step 1 .*\) returned NaN or inf for 2 of 4 states, in mode 'b' "
     r"\(first: row 1, mode 'b', x = \[1\.\d+\] -> \[nan\]\)"),
    (lambda x, m: np.where(m[:, None] == 0, np.inf, x), InvalidInputError, r"NaN or inf for 2 of 4 states, in mode 'a'"),
    (lambda x, m: np.hstack([x, x]), DimensionError,
     r"shape \(k, n\) = \(4, 1\) like x; got \(4, 2\) \(states of dimension 2, not 1\), in call 1 .*"
     r"modes in the call: 'a', 'b'"),
    (lambda x, m: x[:3], DimensionError, r"= \(4, 1\) like x; got \(3, 1\), in call 1"),
    (lambda x, m: None, InvalidInputError, r"as a \(4, 1\) float array; call 1 .* returned NoneType"),
])
def test_a_bad_step_result_is_refused_naming_the_call_and_the_mode(make, error, match):
    with pytest.raises(error, match=match):
        simulate(_two_mode_doc(), Returns(make), np.array([[0.5], [1.5], [2.5], [3.5]]), rng=0)


NAN_FILE = '''
import numpy as np


class Nan:
    mode_names = ("a",)

    def step(self, x, modes, rng):
        return np.full_like(x, np.nan)
'''


def test_simulate_command_refuses_a_step_that_returns_nan(tmp_path, capsys):
    (tmp_path / "result.json").write_text(json.dumps(coin_doc(3, 0.0, 1.0)))
    (tmp_path / "nan.py").write_text(NAN_FILE)
    code = main(["simulate", str(tmp_path), "--true-system", f"{tmp_path / 'nan.py'}:Nan", "--n-per-cell", "2"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert "true_system.step(x, modes, rng) must return finite next states; call 1" in err and "mode 'a'" in err
