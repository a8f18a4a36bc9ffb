"""Known nonlinear parts and per-mode/per-component assumptions, end to end (the pipeline's wiring).

The bounds here hold with probability 1 (bounded noise, no iid intersection), so the Monte-Carlo
checks allow 0 violations: a single point outside its box is a soundness bug, not chance.
"""

from __future__ import annotations

import json
from fractions import Fraction

import numpy as np
import pytest

from robust_imdp.pipeline import bound_stage as pl_bound_stage
from robust_imdp.pipeline import preflight as pl_preflight
from robust_imdp.pipeline import runtime as pl_runtime
from robust_imdp import Problem, TruncatedGaussianNoise, UniformNoise
from robust_imdp.pipeline import run as pipeline
from robust_imdp.bounds.assumptions import add_ranges, resolve
from robust_imdp.errors import AssumptionError, InvalidInputError, ProblemFileError
from robust_imdp.models.geometry import Box, Partition
from robust_imdp.models.known import KnownDynamics

F = {"a": ["x1 + 0.2*cos(x2)", "x2 + 0.1*sin(3*x1)"], "b": ["0.9*x1 - 0.1*x2^2", "x2 - 0.2*tanh(x1)"]}
LENGTHSCALE = 1.0
# g_u^(i)(x) = amp * k(x, z): an element of the SE kernel's RKHS with norm exactly |amp|
AMP = {"a": [0.05, 0.02], "b": [0.03, 0.0]}
Z = np.array([0.3, -0.4])
BOUND = 0.01


def _g(x, amps):
    k = np.exp(-0.5 * np.sum((x - Z) ** 2, axis=1) / LENGTHSCALE ** 2)
    return k[:, None] * np.asarray(amps)[None, :]


def _true_next(x, mode):
    """f_u(x) + g_u(x), without noise."""
    return KnownDynamics(F[mode]).evaluate(x) + _g(x, AMP[mode])


def _data(m=120, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1, 1, (2 * m, 2))
    u = np.repeat(["a", "b"], m)
    xn = np.empty_like(x)
    for mode in ("a", "b"):
        s = u == mode
        xn[s] = _true_next(x[s], mode) + rng.uniform(-BOUND, BOUND, (m, 2))
    return x, u, xn


def _problem(rkhs_bound=0.1, modes=None, cell=0.5, **kw):
    x, u, xn = _data()
    return Problem.from_arrays(
        x, u, xn, lower=[-1, -1], upper=[1, 1], cell_size=cell, regions={"goal": ([0.0, 0.0], [0.5, 0.5])},
        formula="F goal", threshold=0.9, modes=F if modes is None else modes,
        noise=UniformNoise([BOUND, BOUND]), rkhs_bound=rkhs_bound, lengthscale=LENGTHSCALE, **kw)


def _bounds(problem):
    part = Partition(Box(problem.space_lower, problem.space_upper), problem.cell_size,
                     pl_preflight._region_objects(problem))
    cb, _, diag = pl_bound_stage._learn_and_bound(problem, part, pl_runtime._Log(False), pl_runtime._Run(workers=1))
    return part, cb, diag


def _violations(part, cb, modes, n_points=200, seed=1):
    """True one-step images (no noise) outside their boxes, at the cell vertices and n_points
    uniform points per cell (seeded)."""
    rng = np.random.default_rng(seed)
    bad = 0
    lo, up = part.cells_lower, part.cells_upper
    corners = np.array([[0, 0], [0, 1], [1, 0], [1, 1]], float)
    for q in range(part.n_cells):
        pts = np.vstack([lo[q] + corners * (up[q] - lo[q]), rng.uniform(lo[q], up[q], (n_points, 2))])
        for u, mode in enumerate(modes):
            y = _true_next(pts, mode)
            bad += int(np.sum((y < cb.image_lower[u, q]) | (y > cb.image_upper[u, q])))
    return bad


# ----------------------------------------------------------------------------- soundness
def test_monte_carlo_containment_with_a_nonlinear_known_part():
    # B per component above the true norms (0.05, 0.02 | 0.03, 0): different B per component
    p = _problem(rkhs_bound={"a": [0.08, 0.04], "b": [0.05, 0.02]})
    part, cb, _ = _bounds(p)
    assert _violations(part, cb, ("a", "b")) == 0
    # the boxes are informative: narrower than a cell plus the f spread would allow (not [-inf, inf])
    assert np.all(np.isfinite(cb.image_lower)) and np.max(cb.image_upper - cb.image_lower) < 1.2


def test_image_is_the_outward_sum_of_the_f_range_and_the_g_range():
    # Computed independently: known.image_bounds of f plus rkhs.bound_chunk of g (A = 0, b = 0) with
    # the noise allowance (noise bound + residual rounding), summed with one ulp outward.
    from robust_imdp.bounds.rkhs import bound_chunk

    # The allowance is the largest over the modes (one noise bound for every mode, as the one-setting
    # path has): dbar plus each mode's largest rounding bound, rounded up, then the maximum.
    p = _problem()
    part, cb, _ = _bounds(p)
    nb = np.max([np.nextafter(BOUND + KnownDynamics(F[m]).residuals(*p.data.by_mode(u)).bound.max(axis=0), np.inf)
                 for u, m in enumerate(("a", "b"))], axis=0)
    for u, mode in enumerate(("a", "b")):
        f = KnownDynamics(F[mode])
        fr = f.image_bounds(part.cells_lower, part.cells_upper)
        x, xn = p.data.by_mode(u)
        res = f.residuals(x, xn)
        g = bound_chunk(x, res.y, np.zeros((2, 2)), np.zeros(2), part.cells_lower, part.cells_upper,
                        lengthscale=LENGTHSCALE, rkhs_bound=0.1, noise_bound=nb)
        lo, hi = add_ranges(g["lower"], g["upper"], fr.lower, fr.upper)
        np.testing.assert_array_equal(cb.image_lower[u], lo)
        np.testing.assert_array_equal(cb.image_upper[u], hi)
        # outward: strictly beyond the round-to-nearest sum wherever that sum is not exact
        assert np.all(lo < g["lower"] + fr.lower) and np.all(hi > g["upper"] + fr.upper)


def test_rounding_allowance_covers_the_residual_rounding_exactly():
    p = _problem()
    allowance = pl_bound_stage._noise_allowance(p, np.array([BOUND, BOUND]))
    for u, mode in enumerate(("a", "b")):
        x, xn = p.data.by_mode(u)
        rb = KnownDynamics(F[mode]).residuals(x, xn).bound.max(axis=0)
        assert np.all(rb > 0)
        for i in range(2):  # exact rational arithmetic: allowance >= noise bound + rounding bound
            assert Fraction(float(allowance[u, i])) >= Fraction(BOUND) + Fraction(float(rb[i]))


def test_known_components_get_the_known_range_plus_tau():
    # component 2 of mode b has g = 0: declared known, its box is f's certified range widened by tau
    tau = 0.002
    p = _problem(rkhs_bound={"a": [0.08, 0.04], "b": [0.05, 0.0]}, misspecification=tau)
    part, cb, diag = _bounds(p)
    fr = KnownDynamics(F["b"]).image_bounds(part.cells_lower, part.cells_upper)
    # outward of the certified f range + [-tau, tau] (any inward shrink of either fails here) ...
    assert np.all(cb.image_lower[1, :, 1] <= fr.lower[:, 1] - tau)
    assert np.all(cb.image_upper[1, :, 1] >= fr.upper[:, 1] + tau)
    # ... and exact up to a few ulps: the box is the f range, not widened by a learned radius
    assert np.max(fr.lower[:, 1] - tau - cb.image_lower[1, :, 1]) < 1e-15
    assert np.max(cb.image_upper[1, :, 1] - fr.upper[:, 1] - tau) < 1e-15
    assert _violations(part, cb, ("a", "b")) == 0
    rows = {(r["mode"], r["component"]): r for r in diag["assumption"]["per_component"]}
    assert rows[("b", 2)]["known"] and not rows[("b", 1)]["known"]


def test_affine_known_component_is_its_exact_vertex_range():
    # f = x1 (affine, A = I): known component 2 of mode "e" moves by 0.1 only
    rng = np.random.default_rng(3)
    x = rng.uniform(-1, 1, (80, 2))
    xn = x + np.array([0.1, 0.1]) + rng.uniform(-BOUND, BOUND, (80, 2))
    xn[:, 0] += 0.02 * np.sin(x[:, 1])
    p = Problem.from_arrays(x, np.full(80, "e"), xn, lower=[-1, -1], upper=[1, 1], cell_size=0.5,
                            regions={"goal": ([0, 0], [0.5, 0.5])}, formula="F goal", threshold=0.9,
                            modes={"e": (np.eye(2), [0.1, 0.1])}, noise=UniformNoise([BOUND, BOUND]),
                            rkhs_bound=[0.1, 0.0], lengthscale=1.0)
    part, cb, _ = _bounds(p)
    exact_lo = part.cells_lower[:, 1] + 0.1
    exact_hi = part.cells_upper[:, 1] + 0.1
    assert np.all(cb.image_lower[0, :, 1] <= exact_lo) and np.all(cb.image_upper[0, :, 1] >= exact_hi)
    assert np.max(exact_lo - cb.image_lower[0, :, 1]) < 1e-14 and np.max(cb.image_upper[0, :, 1] - exact_hi) < 1e-14


# ----------------------------------------------------------------------------- per component
def _affine_problem(rkhs_bound, **kw):
    rng = np.random.default_rng(4)
    x = rng.uniform(-1, 1, (160, 2))
    u = np.repeat(["e", "n"], 80)
    xn = x + np.where(u[:, None] == "e", [0.2, 0.0], [0.0, 0.2]) + 0.03 * np.sin(x) \
        + rng.uniform(-BOUND, BOUND, (160, 2))
    return Problem.from_arrays(x, u, xn, lower=[-1, -1], upper=[1, 1], cell_size=0.5,
                               regions={"goal": ([0.5, 0.5], [1, 1])}, formula="F goal", threshold=0.9,
                               modes={"e": (np.eye(2), [0.2, 0]), "n": (np.eye(2), [0, 0.2])},
                               noise=TruncatedGaussianNoise([0.005, 0.005], [BOUND, BOUND]), rkhs_bound=rkhs_bound,
                               lengthscale=1.0, **kw)


def test_equal_per_component_bounds_give_the_same_bytes_as_one_bound():
    _, one, _ = _bounds(_affine_problem(0.2))
    _, per, _ = _bounds(_affine_problem({"e": [0.2, 0.2], "n": 0.2}, misspecification=[0.0, 0.0]))
    assert one.image_lower.tobytes() == per.image_lower.tobytes()
    assert one.image_upper.tobytes() == per.image_upper.tobytes()


def test_a_per_component_bound_changes_only_that_component():
    _, one, _ = _bounds(_affine_problem(0.2))
    _, per, _ = _bounds(_affine_problem({"e": [0.2, 0.4], "n": 0.2}))
    same = np.ones(one.image_lower.shape, bool)
    same[0, :, 1] = False
    np.testing.assert_array_equal(per.image_lower[same], one.image_lower[same])
    np.testing.assert_array_equal(per.image_upper[same], one.image_upper[same])
    # a larger B widens mode e's component 2 on every cell
    assert np.all(per.image_upper[0, :, 1] - per.image_lower[0, :, 1] > one.image_upper[0, :, 1] - one.image_lower[0, :, 1])


def test_per_component_lengthscale_changes_only_that_component():
    _, one, _ = _bounds(_affine_problem(0.2))
    p = _affine_problem(0.2).replace(gp_options={"lengthscale": [1.0, [0.5, 2.0]]})
    _, per, _ = _bounds(p)
    np.testing.assert_array_equal(per.image_lower[:, :, 0], one.image_lower[:, :, 0])
    assert not np.array_equal(per.image_lower[:, :, 1], one.image_lower[:, :, 1])


def test_resolve_messages_name_the_setting_and_the_mode():
    with pytest.raises(InvalidInputError, match=r"\[gp\]\.rkhs_bound must be a number or a list of 2 numbers .*got 3"):
        resolve([0.1, 0.2, 0.3], 1.0, 0.0, ["a", "b"], 2, prefix="[gp].")
    with pytest.raises(InvalidInputError, match=r"rkhs_bound names modes \['c'\] that are not defined"):
        resolve({"a": 0.1, "c": 0.2}, 1.0, 0.0, ["a", "b"], 2)
    with pytest.raises(InvalidInputError, match=r"must give every mode; missing \['b'\]"):
        resolve({"a": 0.1}, 1.0, 0.0, ["a", "b"], 2)
    with pytest.raises(InvalidInputError, match=r"\[gp\]\.lengthscale\.a\[2\] must be a number or a list of 2"):
        resolve(0.1, {"a": [1.0, [1.0, 2.0, 3.0]], "b": 1.0}, 0.0, ["a", "b"], 2, prefix="[gp].")
    with pytest.raises(InvalidInputError, match=r"misspecification must be finite and >= 0"):
        resolve(0.1, 1.0, [0.0, -1.0], ["a", "b"], 2)
    with pytest.raises(InvalidInputError, match=r"known must be a list of 2 true/false"):
        resolve(0.1, 1.0, 0.0, ["a", "b"], 2, known=[True])
    st = resolve(0.1, [1.0, 2.0], 0.0, ["a", "b"], 2, known={"a": [False, True], "b": [False, False]})
    assert st.rkhs_bound.tolist() == [[0.1, 0.0], [0.1, 0.1]] and not st.uniform
    assert st.lengthscale[1, 0].tolist() == [1.0, 2.0]  # a list of numbers stays per input dimension
    assert resolve(0.1, [1.0, 2.0], 0.0, ["a"], 2).uniform


def test_known_component_refused_when_residuals_exceed_noise_plus_tau():
    # mode a, component 2 has g = 0.02 k(x, z): declaring it known contradicts the data
    p = _problem(rkhs_bound={"a": [0.08, 0.0], "b": [0.05, 0.02]})
    with pytest.raises(AssumptionError, match=r"declares component 2 of mode 'a' known .* beyond the noise bound"):
        _bounds(p)


def test_gp_route_refuses_a_nonlinear_known_part():
    with pytest.raises(InvalidInputError, match=r"error_bound 'chowdhury' .* affine .* modes \['a', 'b'\]"):
        _problem(error_bound="chowdhury")
    with pytest.raises(InvalidInputError, match=r"chowdhury.*per-mode or per-component"):
        _affine_problem([0.2, 0.3], error_bound="chowdhury")


def test_casadi_expression_per_mode():
    ca = pytest.importorskip("casadi")
    xs = ca.SX.sym("x", 2)
    expr = ca.vertcat(xs[0] + 0.2 * ca.cos(xs[1]), xs[1] + 0.1 * ca.sin(3 * xs[0]))
    p = _problem(modes={"a": (expr, xs), "b": F["b"]})
    q = _problem()
    assert isinstance(p.maps[0], KnownDynamics)
    np.testing.assert_allclose(p.maps[0](np.array([[0.1, 0.2]])), q.maps[0](np.array([[0.1, 0.2]])), rtol=0,
                               atol=1e-15)


# ----------------------------------------------------------------------------- problem files
TOML = """
[space]
lower = [-1.0, -1.0]
upper = [1.0, 1.0]
cell_size = [0.5, 0.5]

[[regions.goal]]
lower = [0.0, 0.0]
upper = [0.5, 0.5]

[spec]
formula = "F goal"
threshold = 0.9

[data]
path = "data.csv"

[modes.a]
{mode_a}
[modes.b]
f = ["0.9*x1 - 0.1*x2^2", "x2 - 0.2*tanh(x1)"]

[noise]
kind = "uniform"
bound = [0.01, 0.01]

[learning]
{gp}
lengthscale = 1.0
"""
MODE_A = 'f = ["x1 + 0.2*cos(x2)", "x2 + 0.1*sin(3*x1)"]'


def _write(tmp_path, mode_a=MODE_A, gp="rkhs_bound = 0.1"):
    from robust_imdp.io.files import write_data_file

    x, u, xn = _data()
    write_data_file(tmp_path / "data.csv", x, u, xn)
    path = tmp_path / "p.toml"
    path.write_text(TOML.format(mode_a=mode_a, gp=gp))
    return path


def _cli(args, capsys):
    from robust_imdp.cli import main

    code = main(args)
    return code, capsys.readouterr().err


def test_problem_file_with_f_runs_end_to_end(tmp_path, capsys):
    path = _write(tmp_path, gp='rkhs_bound = {a = [0.08, 0.04], b = [0.05, 0.02]}')
    out = tmp_path / "out"
    code, err = _cli(["run", str(path), "--out", str(out), "--no-figures", "--quiet", "--advice", "off"], capsys)
    assert code == 0, err
    doc = json.loads((out / "result.json").read_text())
    assert doc["parameters"]["known_parts"]["a"] == ["x1 + 0.2*cos(x2)", "x2 + 0.1*sin(3*x1)"]
    assert doc["parameters"]["rkhs_bound"] == {"a": [0.08, 0.04], "b": [0.05, 0.02]}
    from test_result_schema import SCHEMA, validate_schema

    assert validate_schema(doc, SCHEMA) == []
    gaps = doc["diagnostics"]["known_part_gap"]
    assert len(gaps) == 4 and max(r["gap_over_cell_width_max"] for r in gaps) < 1e-2
    # the same problem in Python gives the same boxes as the file
    from robust_imdp.io.files import load_problem

    p = load_problem(path)
    assert isinstance(p.maps[0], KnownDynamics) and p.maps[0].name.endswith("[modes.a]")


def test_advice_runs_with_a_nonlinear_known_part(tmp_path, capsys):
    """The advice's pilot cells go through the bound task of a mode with its own known part (its
    extra arguments once crashed the pilot task); the advice is written and names the levers."""
    path = _write(tmp_path)
    out = tmp_path / "out"
    code, err = _cli(["run", str(path), "--out", str(out), "--no-figures", "--quiet", "--advice", "on"], capsys)
    assert code == 0, err
    adv = json.loads((out / "result.json").read_text())["diagnostics"]["advice"]
    assert adv and "internal error" not in err


@pytest.mark.parametrize("mode_a, match", [
    ('f = ["x1 + * 2", "x2"]', r"p\.toml: \[modes\.a\]: f\[1\] = \"x1 \+ \* 2\": unexpected '\*' at position 5"),
    ('f = ["x1", "x3 + 1"]', r"p\.toml: \[modes\.a\]: f\[2\] = \"x3 \+ 1\": .*x3.*x1\.\.x2"),
    ('f = ["x1"]', r"p\.toml: \[modes\.a\]\.f must be a list of 2 expressions in x1\.\.x2 .*got 1 entries"),
    ('f = ["x1", 2.0]', r"\[modes\.a\]\.f must be a list of 2 expressions"),
    ('f = ["x1", "x2"]\nA = [[1.0, 0.0], [0.0, 1.0]]', r"\[modes\.a\] must give either f .* or A and b"),
    ('A = [[1.0, 0.0], [0.0, 1.0]]', r"\[modes\.a\] is missing required key 'b' \(or give f = \[\.\.\.\]"),
])
def test_problem_file_errors_in_f(tmp_path, capsys, mode_a, match):
    from robust_imdp.io.files import parse_problem_file

    path = _write(tmp_path, mode_a=mode_a)
    with pytest.raises(ProblemFileError, match=match):
        parse_problem_file(path)
    out = tmp_path / "out"
    code, err = _cli(["run", str(path), "--out", str(out), "--no-figures", "--quiet"], capsys)
    assert code == 1 and "Traceback" not in err and err.startswith("robust-imdp: error: ")
    assert not (out / "result.json").exists()


@pytest.mark.parametrize("gp, match", [
    ("rkhs_bound = [0.1, 0.2, 0.3]", r"\[learning\]\.rkhs_bound must be a number or a list of 2 numbers"),
    ("rkhs_bound = {a = 0.1, c = 0.2}", r"\[learning\]\.rkhs_bound names modes \['c'\] that are not defined"),
    ("rkhs_bound = 0.1\nmisspecification = {a = [0.0], b = 0.0}", r"\[learning\]\.misspecification\.a must be a number"),
    ("rkhs_bound = 0.1\nknown = [true]", r"\[learning\]\.known must be a list of 2 true/false values"),
])
def test_problem_file_errors_per_component(tmp_path, capsys, gp, match):
    from robust_imdp.io.files import parse_problem_file

    path = _write(tmp_path, gp=gp)
    with pytest.raises(ProblemFileError, match=match):
        parse_problem_file(path)
    code, err = _cli(["run", str(path), "--out", str(tmp_path / "out"), "--no-figures", "--quiet"], capsys)
    assert code == 1 and "Traceback" not in err


def test_known_component_refused_at_load_naming_the_line(tmp_path):
    from robust_imdp.io.files import load_problem

    path = _write(tmp_path, gp="rkhs_bound = 0.1\nknown = {a = [false, true], b = [false, false]}")
    with pytest.raises(AssumptionError, match=r"declares component 2 of mode 'a' known .*data\.csv, line \d+"):
        load_problem(path)


def test_function_undefined_on_x_is_refused_before_the_long_stages(tmp_path, capsys):
    path = _write(tmp_path, mode_a='f = ["x1 + 0.1*log(x1 + 1.5)", "x2 + 0.1*log(x2 + 1)"]')
    out = tmp_path / "out"
    code, err = _cli(["run", str(path), "--out", str(out), "--no-figures"], capsys)
    assert code == 1 and "Traceback" not in err
    assert "[modes.a]: f[2] = \"x2 + 0.1*log(x2 + 1)\" is undefined on the box" in err
    assert "bound ..." not in err and "check ..." not in err  # refused before the check and bound stages
    assert not (out / "result.json").exists()
