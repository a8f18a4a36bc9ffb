"""Known dynamics: every component of every mode known (``rkhs_bound = 0``), no data, no learning, no assumption
check; the problem file's [data] and [learning] tables are optional then, and the result says so."""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from robust_imdp.errors import InvalidInputError, ProblemFileError, RobustImdpWarning

sys.path.insert(0, str(Path(__file__).parent))

KNOWN_1D = """[space]
lower = [0.0]
upper = [4.0]
cell_size = [0.25]
[[regions.safe]]
lower = [0.5]
upper = [3.5]
[spec]
formula = "G safe"
threshold = 0.9
horizon = 5
[modes.a]
A = [[0.5]]
b = [1.0]
[modes.b]
f = ["0.9*x1 + 0.1*sin(x1)"]
[noise]
kind = "gaussian"
sigma = [0.1]
"""


def _write(tmp_path, text, name="k.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_known_problem_file_needs_neither_data_nor_learning(tmp_path):
    from robust_imdp.io.problem_file import load_problem

    p = load_problem(_write(tmp_path, KNOWN_1D))
    assert p.known and p.data is None
    assert "known dynamics (no data)" in repr(p)
    # a scalar rkhs_bound = 0 says the same
    q = load_problem(_write(tmp_path, KNOWN_1D + "[learning]\nrkhs_bound = 0\nmisspecification = 0.01\n", "q.toml"))
    assert q.known and q.data is None and float(q.misspecification) == 0.01


def test_known_problem_file_errors_name_the_table_and_file(tmp_path):
    from robust_imdp.io.problem_file import load_problem

    (tmp_path / "d.csv").write_text("x_1,u,x_next_1\n1.0,a,1.5\n")
    f = _write(tmp_path, KNOWN_1D + '[data]\npath = "d.csv"\n', "nolearn.toml")
    with pytest.raises(ProblemFileError, match=r"nolearn.toml: \[data\] is given but there is no \[learning\] table"):
        load_problem(f)
    f = _write(tmp_path, KNOWN_1D + "[learning]\nrkhs_bound = 0.5\n", "nodata.toml")
    with pytest.raises(ProblemFileError, match=r"nodata.toml: missing required table \[data\].*rkhs_bound = 0"):
        load_problem(f)
    f = _write(tmp_path, KNOWN_1D + "[learning]\nrkhs_bound = -1\n", "neg.toml")
    with pytest.raises(ProblemFileError, match=r"neg.toml: \[learning\].rkhs_bound must be > 0, or 0 for known"):
        load_problem(f)
    # per component: one unknown component needs data
    f = _write(tmp_path, KNOWN_1D + '[learning]\nrkhs_bound = {"a" = [0.0], "b" = [0.3]}\n', "partial.toml")
    with pytest.raises(ProblemFileError, match="missing required table"):
        load_problem(f)


def test_known_problem_with_data_warns_that_they_are_unused(tmp_path):
    from robust_imdp.io.problem_file import load_problem

    (tmp_path / "d.csv").write_text("x_1,u,x_next_1\n1.0,a,9.0\n")  # a residual no noise bound explains: unchecked
    f = _write(tmp_path, KNOWN_1D + '[learning]\nrkhs_bound = 0\n[data]\npath = "d.csv"\n', "withdata.toml")
    with pytest.warns(RobustImdpWarning, match="is not used; remove \\[data\\]"):
        p = load_problem(f)
    assert p.known and p.data is None


def test_from_arrays_without_data():
    from robust_imdp import GaussianNoise, Problem

    kw = dict(lower=[0.0], upper=[4.0], cell_size=0.5, regions={"safe": ([0.5], [3.5])}, formula="G safe",
              threshold=0.9, modes={"a": (np.eye(1) * 0.5, [1.0])}, noise=GaussianNoise([0.1]))
    p = Problem.from_arrays(None, None, None, rkhs_bound=0, **kw)
    assert p.known and p.data is None and p.tightened() is p
    with pytest.raises(InvalidInputError, match=r"data are needed for the unknown components .*'a' 1"):
        Problem.from_arrays(None, None, None, rkhs_bound=0.5, **kw)
    with pytest.raises(InvalidInputError, match="x, u and x_next must all be given"):
        Problem.from_arrays(np.zeros((2, 1)), None, None, rkhs_bound=0, **kw)


def test_known_bounds_contain_the_images_and_add_tau():
    """Independent check: f at 2,000 points of each cell lies in the cell's box; with tau the box grows by at
    least tau per side (and by at most tau plus a few ulps)."""
    from robust_imdp import GaussianNoise, Problem
    from robust_imdp.pipeline.bound_stage import known_cell_bounds

    modes = {"a": (np.array([[0.9, 0.2], [-0.1, 0.8]]), [0.1, -0.2]),
             "b": ["x1 + 0.3*cos(x2)", "0.7*x2 + 0.1*x1*x2"]}
    kw = dict(lower=[-1.0, -1.0], upper=[1.0, 1.0], cell_size=0.5, regions={"s": ([-0.5, -0.5], [0.5, 0.5])},
              formula="G s", threshold=0.9, modes=modes, noise=GaussianNoise([0.1, 0.1]))
    p0 = Problem.from_arrays(None, None, None, rkhs_bound=0, **kw)
    p1 = Problem.from_arrays(None, None, None, rkhs_bound=0, misspecification=0.05, **kw)
    from robust_imdp.models.geometry import Box, Partition

    part = Partition(Box(p0.space_lower, p0.space_upper), p0.cell_size, [])
    lo0, hi0 = known_cell_bounds(p0, part.cells_lower, part.cells_upper)
    lo1, hi1 = known_cell_bounds(p1, part.cells_lower, part.cells_upper)
    rng = np.random.default_rng(0)
    for q in range(part.n_cells):
        x = part.cells_lower[q] + rng.random((2000, 2)) * (part.cells_upper[q] - part.cells_lower[q])
        for u, m in enumerate(p0.maps):
            y = m(x)
            assert np.all(y >= lo0[u, q]) and np.all(y <= hi0[u, q])
            # with tau: f + g for any |g| <= tau, i.e. f -+ tau at the extremes
            assert np.all(y - 0.05 >= lo1[u, q]) and np.all(y + 0.05 <= hi1[u, q])
    np.testing.assert_allclose(lo1, lo0 - 0.05, atol=1e-12)  # tau and an ulp, no more
    np.testing.assert_allclose(hi1, hi0 + 0.05, atol=1e-12)
    # teeth: the affine mode's box is tight: its extremes are attained at the cells' corners, so the box shrunk
    # by 0.1 % of its width on either side misses a corner's image in every cell and component
    corners = np.array([[0, 0], [0, 1], [1, 0], [1, 1]])
    x = part.cells_lower[:, None, :] + corners[None] * (part.cells_upper - part.cells_lower)[:, None, :]
    y = np.einsum("ij,qkj->qki", p0.maps[0].A, x) + p0.maps[0].b  # (cells, 4, 2)
    shrink = 0.001 * (hi0[0] - lo0[0])
    assert np.all(y.max(axis=1) > hi0[0] - shrink) and np.all(y.min(axis=1) < lo0[0] + shrink)


class Known2D:
    """x+ = f_u(x) + v, v ~ N(0, 0.1^2 I) (untruncated): f_left = 0.8 x - (0.1, 0), f_right = 0.8 x + 0.1 sin."""

    mode_names = ("left", "right")

    def step(self, x, modes, rng):
        x = np.atleast_2d(x)
        f = np.where(np.asarray(modes)[:, None] == 0, 0.8 * x - np.array([0.1, 0.0]),
                     0.8 * x + 0.1 * np.sin(x))
        return f + rng.normal(0.0, 0.1, x.shape)


@pytest.fixture(scope="module")
def known_run():
    from robust_imdp import GaussianNoise, Problem
    from robust_imdp.pipeline.run import synthesize_from_data

    p = Problem.from_arrays(None, None, None, lower=[-2, -2], upper=[2, 2], cell_size=0.5,
                            regions={"safe": ([-1, -1], [1, 1])}, formula="G safe", threshold=0.8, horizon=4,
                            modes={"left": (0.8 * np.eye(2), [-0.1, 0.0]),
                                   "right": ["0.8*x1 + 0.1*sin(x1)", "0.8*x2 + 0.1*sin(x2)"]},
                            noise=GaussianNoise([0.1, 0.1]), rkhs_bound=0)
    return synthesize_from_data(p, progress=False)


def test_known_run_states_known_dynamics_and_checks_nothing(known_run, tmp_path):
    from robust_imdp.io.files import save_result
    from test_result_schema import SCHEMA, validate_schema

    r = known_run
    assert "check" not in r.timings and r.advice == {}
    assert r.diagnostics["dynamics"] == "known" and r.diagnostics["statement"].startswith("known dynamics")
    assert "known dynamics: no data, no learning, no assumption check" in r.summary()
    save_result(r, tmp_path)
    doc = json.loads((tmp_path / "result.json").read_text())
    assert doc["parameters"]["n_data"] == 0 and doc["diagnostics"]["error_bound"] == "known"
    assert validate_schema(doc, SCHEMA) == []


def test_known_run_monte_carlo(known_run):
    """Monte Carlo of the true system (64 cells x 300 runs, 99.99 % Wilson): the bounds hold."""
    from robust_imdp.validate import validate

    rep = validate(known_run, Known2D(), n_per_cell=300, rng=3, confidence=0.9999)
    assert rep.passed, rep.summary()
    safe = (known_run.partition.labels & 1) > 0
    assert np.max(known_run.p_low[safe]) > 0.1  # informative, not vacuous


def test_known_run_never_calls_the_assumption_check(monkeypatch):
    import robust_imdp.pipeline.bound_stage as bs
    from robust_imdp import GaussianNoise, Problem
    from robust_imdp.pipeline.run import synthesize_from_data

    def refuse(*a, **k):
        raise AssertionError("the assumption check ran")

    monkeypatch.setattr(bs, "_check_assumption", refuse)
    monkeypatch.setattr(bs, "_residual_data", refuse)
    p = Problem.from_arrays(None, None, None, lower=[0.0], upper=[4.0], cell_size=0.5,
                            regions={"g": ([3.0], [4.0])}, formula="F g", threshold=0.5,
                            modes={"a": (np.eye(1), [0.5])}, noise=GaussianNoise([0.1]), rkhs_bound=0,
                            refine={"max_cells": 12, "max_rounds": 1})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = synthesize_from_data(p, progress=False)
    assert r.diagnostics["dynamics"] == "known" and r.diagnostics.get("refinement") is not None


def test_a_known_problem_with_a_reading_is_written_without_data_and_read_back(tmp_path):
    # save_problem of a known system: no [data] table and no data file, the misspecification and the formula's
    # reading kept; the file reads back to the same problem (the same abstraction key and spec)
    from robust_imdp.io.problem_file import load_problem
    from robust_imdp.io.problem_writer import save_problem
    from robust_imdp.pipeline.cache import abstraction_key

    p = load_problem(_write(tmp_path, KNOWN_1D + "[learning]\nrkhs_bound = 0\nmisspecification = 0.01\n"))
    p = p.replace(semantics="safety")
    out = save_problem(p, tmp_path / "w" / "k.toml")
    text = out.read_text()
    assert "[data]" not in text and 'semantics = "safety"' in text
    assert sorted(f.name for f in out.parent.iterdir()) == ["k.toml"]
    back = load_problem(out)
    assert back.known and back.data is None and back.semantics == "safety"
    assert float(back.misspecification) == 0.01
    assert (back.formula, back.threshold, back.horizon) == (p.formula, p.threshold, p.horizon)
    assert abstraction_key(back) == abstraction_key(p)
