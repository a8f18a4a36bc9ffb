"""Input grids (``models.inputs``): a quantised input as the modes, dynamics written once as ``f(x, u)``, data with
input columns, the controller's input vector, result files naming inputs by value."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from robust_imdp.errors import ExpressionError, InvalidInputError, ProblemFileError
from robust_imdp.models.inputs import InputGrid, InputMode, input_modes, input_name
from robust_imdp.models.known import KnownDynamics

sys.path.insert(0, str(Path(__file__).parent))


# --------------------------------------------------------------------------- the grid
def test_grid_from_box_values_names_and_order():
    g = InputGrid.from_box([-1, -1], [1, 1], [0.1, 0.1])
    assert g.n_points == 441 and g.shape == (21, 21) and g.names == ("u1", "u2")
    # C order: the last input fastest; decimal steps give the decimals written (0.3, and 0 exactly)
    assert g.mode_names[:2] == ("u=(-1, -1)", "u=(-1, -0.9)") and g.mode_names[220] == "u=(0, 0)"
    assert g.values[0][13] == 0.3 and g.values[0][10] == 0.0
    np.testing.assert_array_equal(g.points[22], [-0.9, -0.9])
    assert g.index([[0.3, -1.0], [1.0, 1.0]]).tolist() == [13 * 21, 440]
    v = InputGrid.from_values([[20, 17, 18, 19]], names=["u"])
    assert v.mode_names == ("u=(17)", "u=(18)", "u=(19)", "u=(20)") and v.names == ("u",)
    assert input_name([0.5, -1e-5]) == "u=(0.5, -1e-05)"


@pytest.mark.parametrize("make, match", [
    (lambda: InputGrid.from_box([0], [1], [0.3]), r"input 1 \(u1\): \(upper - lower\) / step = .* whole number"),
    (lambda: InputGrid.from_box([0, 0], [1], [0.5]), "one value per input"),
    (lambda: InputGrid.from_box([1], [0], [0.5]), "lower <= upper and step > 0"),
    (lambda: InputGrid.from_values([[1, 2, 2]]), r"values of input 1 \(u1\) must be distinct; 2 appears twice"),
    (lambda: InputGrid.from_values([[]]), "non-empty list of finite numbers"),
    (lambda: InputGrid.from_values([[1, 2]], names=["a", "b"]), "names must be 1 distinct non-empty names, one per input"),
    (lambda: InputGrid.from_box([0, 0], [1000, 1000], [1, 1]), "more than 100,000"),
])
def test_grid_errors(make, match):
    with pytest.raises(InvalidInputError, match=match):
        make()


def test_off_grid_inputs_are_refused_with_the_row():
    g = InputGrid.from_box([-1], [1], [0.5])
    assert g.locate([[0.5], [0.25], [np.nan]]).tolist() == [3, -1, -1]
    with pytest.raises(InvalidInputError, match=r"u: row 1 has input u=\(0.25\), not a point of the grid"):
        g.index([[0.5], [0.25]])


# --------------------------------------------------------------------------- f(x, u)
def test_expressions_in_x_and_u():
    with pytest.raises(ExpressionError, match=r"unknown symbol 'u3' \(there are 2 inputs\).*expected x1..x2, u1..u2"):
        KnownDynamics(["x1 + u3", "x2"], n_inputs=2)
    with pytest.raises(ExpressionError, match=r"unknown symbol 'u1' \(no inputs"):
        KnownDynamics(["x1 + u1"])
    f = KnownDynamics(["x1 + 10*u1*cos(u2)", "x2 + 10*u1*sin(u2)"], n_inputs=2)
    np.testing.assert_allclose(f([[1.0, 2.0, 0.5, 0.3]]), [[1 + 5 * np.cos(0.3), 2 + 5 * np.sin(0.3)]], rtol=1e-15)
    assert f.jacobian([[1.0, 2.0, 0.5, 0.3]]).shape == (1, 2, 4)
    with pytest.raises(ValueError, match=r"shape \(m, 4\) \(x1..x2, then u1..u2\)"):
        f([[1.0, 2.0]])
    assert f.fingerprint() != KnownDynamics(["x1 + 10*x2", "x2"]).fingerprint()


def test_input_mode_bounds_contain_the_images_and_match_a_constant_input():
    """Independent checks: (a) f(x, u_k) at 3,000 points of each cell lies in the mode's box; (b) the box equals
    (up to the constant's rounding) that of the expression with u written as a number; (c) the vectorised
    bound of all modes at once (bound_stage.known_images) is the per-mode one, bit for bit."""
    from robust_imdp.pipeline.bound_stage import known_images

    grid = InputGrid.from_values([[0.5, 1.0], [0.25, 1.5]])
    modes = input_modes(["x1 + 10*u1*cos(u2)", "x2 + 10*u1*sin(u2) - 0.1*x1*x2"], grid)
    rng = np.random.default_rng(0)
    lo = rng.uniform(-2, 1, (12, 2))
    hi = lo + rng.uniform(0.1, 0.8, (12, 2))
    together = known_images(modes, lo, hi)
    for k, m in enumerate(modes):
        r = m.image_bounds(lo, hi)
        np.testing.assert_array_equal(together[k].lower, r.lower)
        np.testing.assert_array_equal(together[k].upper, r.upper)
        for q in range(lo.shape[0]):
            x = lo[q] + rng.random((3000, 2)) * (hi[q] - lo[q])
            y = m(x)
            assert np.all(y >= r.lower[q]) and np.all(y <= r.upper[q])
        u1, u2 = (repr(float(v)) for v in grid.points[k])
        const = KnownDynamics([f"x1 + 10*{u1}*cos({u2})", f"x2 + 10*{u1}*sin({u2}) - 0.1*x1*x2"])
        c = const.image_bounds(lo, hi)
        np.testing.assert_allclose(r.lower, c.lower, atol=1e-12)
        np.testing.assert_allclose(r.upper, c.upper, atol=1e-12)


def test_input_mode_interface():
    grid = InputGrid.from_values([[17.0, 18.0]])
    m = input_modes(["0.5*x1 + 0.1*u1"], grid)[1]
    assert isinstance(m, InputMode) and m.dim == 1 and m.expressions == ("0.5*x1 + 0.1*u1 at u=(18)",)
    np.testing.assert_allclose(m([[2.0]]), [[2.8]])
    r = m.residuals([[2.0]], [[3.0]])
    np.testing.assert_allclose(r.y, [[0.2]], atol=1e-15)
    assert m.fingerprint() != input_modes(["0.5*x1 + 0.1*u1"], grid)[0].fingerprint()


# --------------------------------------------------------------------------- problem files
GRID_1D = """[space]
lower = [0.0]
upper = [4.0]
cell_size = [0.5]
[[regions.goal]]
lower = [3.0]
upper = [4.0]
[spec]
formula = "F goal"
threshold = 0.5
horizon = 4
[inputs]
names = ["push"]
lower = [0.0]
upper = [2.2]
step = [1.1]
[dynamics]
f = ["0.5*x1 + u1"]
[noise]
kind = "uniform"
bound = [0.05]
"""


def _write(tmp_path, text, name="p.toml"):
    (tmp_path / name).write_text(text)
    return tmp_path / name


def test_problem_file_inputs_make_the_modes(tmp_path):
    from robust_imdp.io.problem_file import load_problem

    p = load_problem(_write(tmp_path, GRID_1D))
    assert p.mode_names == ("u=(0)", "u=(1.1)", "u=(2.2)") and p.inputs.names == ("push",) and p.known
    assert p.inputs.values[0].tolist() == [0.0, 1.1, 2.2]  # 2 * 1.1 = 2.2000000000000002 is written as 2.2
    v = load_problem(_write(tmp_path, GRID_1D.replace("lower = [0.0]\nupper = [2.2]\nstep = [1.1]",
                                                      "values = [[0, 1.1, 2.2]]"), "v.toml"))
    assert v.mode_names == p.mode_names


@pytest.mark.parametrize("edit, match", [
    (lambda t: t + "[modes.a]\nA = [[1.0]]\nb = [0.0]\n", "either \\[modes.NAME\\] tables or an \\[inputs\\] grid"),
    (lambda t: t.replace('[dynamics]\nf = ["0.5*x1 + u1"]\n', ""), "missing \\[dynamics\\]"),
    (lambda t: t.replace("step = [1.1]", "step = [1.0]"), "\\[inputs\\]: input 1 \\(push\\).*whole number"),
    (lambda t: t.replace("step = [1.1]", "step = [1.1]\nvalues = [[1]]"), "either values .* or lower, upper and step"),
    (lambda t: t.replace("step = [1.1]\n", ""), "missing \\['step'\\]"),
    (lambda t: t.replace('f = ["0.5*x1 + u1"]', 'f = ["x1 + u2"]'), "unknown symbol 'u2' \\(there are 1 inputs\\)"),
    (lambda t: t.replace('f = ["0.5*x1 + u1"]', 'f = ["x1", "u1"]'), "must be a list of 1 expressions in x1..x1, u1..u1"),
    (lambda t: t.replace("[inputs]", "[inputs]\nstpe = 1"), "\\[inputs\\] has unknown key 'stpe'"),
])
def test_problem_file_input_errors_name_the_file_and_table(tmp_path, edit, match):
    from robust_imdp.io.problem_file import load_problem

    with pytest.raises(ProblemFileError, match=f"p.toml.*{match}"):
        load_problem(_write(tmp_path, edit(GRID_1D)))


def test_data_with_input_columns(tmp_path):
    """An unknown part on an input grid: the data carry the input value per sample (columns u_1..u_m)."""
    from robust_imdp.io.problem_file import load_problem
    from robust_imdp.pipeline.run import synthesize_from_data

    rng = np.random.default_rng(1)
    rows = []
    for u in (0.0, 1.1, 2.2):
        x = rng.uniform(0, 4, 30)
        xn = 0.5 * x + u + 0.05 * np.sin(x) + rng.uniform(-0.05, 0.05, 30)
        rows += [f"{float(a)!r},{u!r},{float(b)!r}\n" for a, b in zip(x, xn)]
    (tmp_path / "d.csv").write_text("x_1,u_1,x_next_1\n" + "".join(rows))
    text = GRID_1D + '[data]\npath = "d.csv"\n[learning]\nrkhs_bound = 0.1\nlengthscale = 1.0\n'
    p = load_problem(_write(tmp_path, text))
    assert not p.known and np.bincount(p.data.u).tolist() == [30, 30, 30]
    res = synthesize_from_data(p, progress=False, advice=False)
    assert res.p_low.shape == (8,) and np.all(res.p_low <= res.p_up)
    # an input off the grid is named with its line
    (tmp_path / "d.csv").write_text("x_1,u_1,x_next_1\n" + "".join(rows[:5]) + "1.0,0.25,1.2\n")
    with pytest.raises(ProblemFileError, match=r"d.csv: line 7: the input u=\(0.25\) is not a point of the \[inputs\]"):
        load_problem(tmp_path / "p.toml")
    (tmp_path / "d.csv").write_text("x_1,u,x_next_1\n1.0,u=(0),1.0\n")
    with pytest.raises(ProblemFileError, match="line 1: header must be x_1,u_1,x_next_1"):
        load_problem(tmp_path / "p.toml")


@pytest.fixture(scope="module")
def grid_run():
    from robust_imdp.io.problem_file import load_problem
    from robust_imdp.pipeline.run import synthesize_from_data
    import tempfile

    with tempfile.TemporaryDirectory() as d:  # one step: only push 2.2 takes [2, 2.5] into the goal at once
        p = load_problem(_write(Path(d), GRID_1D.replace("horizon = 4", "horizon = 1")))
    return synthesize_from_data(p, progress=False)


def test_controller_returns_the_input_vector(grid_run, tmp_path):
    from robust_imdp.synthesis.controller import Controller

    c = grid_run.controller()
    assert c.input_names == ("push",) and c.inputs.shape == (3, 1)
    x = np.array([2.25])  # push 2.2 takes [2, 2.5] into [3.2, 3.45] +- 0.05, inside the goal [3, 4]; 0 or 1.1 do not
    assert grid_run.p_low[4] > 0.999  # 1 up to the rounding of the abstraction
    c.reset(x)
    name = c.act(x)
    c.reset(x)
    u = c.act_input(x)
    assert name == input_name(u) and name in grid_run.mode_names  # act keeps the mode names
    assert u.tolist() == [2.2]
    c.save(tmp_path / "c")
    back = Controller.load(tmp_path / "c")
    np.testing.assert_array_equal(back.inputs, c.inputs)
    assert back.input_names == ("push",)
    plain = Controller(np.zeros((1, 2), dtype=np.int64), [[0, 1], [1, 1]], 0, [False, True], ["g"], [0],
                       [[0.0, 1.0]], [0.0], [1.0])  # one cell, F g: state 0 waits, state 1 accepts
    with pytest.raises(InvalidInputError, match="act_input needs a controller of an input grid"):
        plain.reset([0.5]).act_input([0.5])


def test_result_files_name_inputs_by_value(grid_run, tmp_path):
    from robust_imdp.io.files import load_result, save_result
    from test_result_schema import SCHEMA, validate_schema

    save_result(grid_run, tmp_path)
    doc = json.loads((tmp_path / "result.json").read_text())
    assert doc["modes"] == ["u=(0)", "u=(1.1)", "u=(2.2)"]
    assert doc["inputs"] == {"names": ["push"], "values": [[0.0, 1.1, 2.2]], "points": [[0.0], [1.1], [2.2]]}
    assert validate_schema(doc, SCHEMA) == []
    back = load_result(tmp_path)
    np.testing.assert_array_equal(back.inputs, [[0.0], [1.1], [2.2]])
    assert back.input_names == ("push",)
    # the saved result's controller knows the inputs too
    from robust_imdp.synthesis.controller import Controller

    c = Controller.from_result(back)
    x = np.array([2.25])
    assert c.reset(x).act_input(x).tolist() == [2.2]


def test_from_arrays_with_inputs():
    from robust_imdp import Problem, UniformNoise

    grid = InputGrid.from_values([[-0.5, 0.0, 0.5]])
    kw = dict(lower=[0.0], upper=[4.0], cell_size=0.5, regions={"goal": ([3.0], [4.0])}, formula="F goal",
              threshold=0.5, modes=["x1 + u1"], noise=UniformNoise([0.05]), inputs=grid)
    p = Problem.from_arrays(None, None, None, rkhs_bound=0, **kw)
    assert p.mode_names == grid.mode_names and p.inputs is grid
    x = np.array([[1.0], [2.0], [3.0]])
    q = Problem.from_arrays(x, np.array([[0.5], [-0.5], [0.0]]), x + 0.1, rkhs_bound=0.2, **kw)
    assert q.data.u.tolist() == [2, 0, 1]  # input vectors -> their grid points
    with pytest.raises(InvalidInputError, match="row 0 has input u=\\(0.3\\)"):
        Problem.from_arrays(x[:1], np.array([[0.3]]), x[:1], rkhs_bound=0.2, **kw)
    with pytest.raises(InvalidInputError, match="with inputs, modes must be the dynamics f\\(x, u\\)"):
        Problem.from_arrays(None, None, None, rkhs_bound=0, **{**kw, "modes": {"a": (np.eye(1), [0.0])}})
