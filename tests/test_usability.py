"""What new users tripped over (smaller things): dimension names, 1-based dimension numbers in
messages, figure slices through the cells that matter, overlapping regions, the Python API
(act / act_index, Result shortcuts and repr, Problem.from_arrays, py.typed, one step cap), and the
newcomer problems shipped in examples/newcomer/."""

import inspect
import json
import shutil
import subprocess
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.colors import to_rgba  # noqa: E402

from robust_imdp import plotting  # noqa: E402
from robust_imdp.errors import (  # noqa: E402
    DimensionError, InvalidInputError, ProblemFileError, RegionOverlapWarning, RobustImdpWarning,
)
from robust_imdp.models.geometry import Box, Partition, Region, region_overlaps  # noqa: E402
from robust_imdp.io.files import ResultFile, load_problem, load_result, parse_problem_file, save_result  # noqa: E402
from robust_imdp.models.noise import TruncatedGaussianNoise  # noqa: E402
from robust_imdp.pipeline.problem import Problem
from robust_imdp.pipeline.result import Result  # noqa: E402
from robust_imdp.models.system import AffineMap, Dataset  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from test_io import GOOD, _fake_result  # noqa: E402
from test_result_schema import SCHEMA, validate_schema  # noqa: E402

ROOT = Path(__file__).parents[1]
NEWCOMER = ROOT / "examples" / "newcomer"


def _two_mode_csv(path: Path, n: int = 12, seed: int = 0) -> None:
    """Data for GOOD's modes a (x' = 0) and b (x' = x + (0.1, 0)) on [-2, 2]^2, noise-free."""
    rng = np.random.default_rng(seed)
    rows = []
    for name in ("a", "b"):
        x = rng.uniform(-2, 2, (n, 2))
        xn = np.zeros_like(x) if name == "a" else x + [0.1, 0.0]
        rows += [f"{p[0]:.6f},{p[1]:.6f},{name},{q[0]:.6f},{q[1]:.6f}" for p, q in zip(x, xn)]
    path.write_text("x_1,x_2,u,x_next_1,x_next_2\n" + "\n".join(rows) + "\n")


# =========================================================================== [space].names
def test_space_names_are_read_checked_and_reach_the_problem(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text(GOOD.replace("cell_size = [0.5, 0.5]", 'cell_size = [0.5, 0.5]\nnames = ["px", "py"]'))
    assert parse_problem_file(p)["names"] == ("px", "py")
    _two_mode_csv(tmp_path / "data.csv")
    assert load_problem(p).dim_names == ("px", "py")
    p.write_text(GOOD)
    assert parse_problem_file(p)["names"] is None  # optional
    for bad, got in (('["px"]', r"\['px'\]"), ('["px", "py", "pz"]', "'pz'"), ('["px", "px"]', "'px', 'px'"),
                     ('[1, 2]', r"\[1, 2\]"), ('"px"', "'px'"), ('["px", ""]', "''")):
        p.write_text(GOOD.replace("cell_size = [0.5, 0.5]", f"cell_size = [0.5, 0.5]\nnames = {bad}"))
        with pytest.raises(ProblemFileError, match=r"\[space\]\.names must be a list of 2 distinct non-empty "
                                                   rf"names, one per dimension; got .*{got}"):
            parse_problem_file(p)


def test_problem_checks_its_dimension_names():
    problem = _tiny_problem(dim_names=("px", "py"))
    assert problem.dim_names == ("px", "py")
    with pytest.raises(InvalidInputError, match=r"dim_names must be 2 distinct non-empty names .*got \('px',\)"):
        _tiny_problem(dim_names=("px",))


def test_result_json_carries_the_names_and_follows_the_schema(tmp_path):
    res = _fake_result()
    res.dim_names = ("px", "py")
    doc = json.loads(save_result(res, tmp_path / "named").read_text())
    assert doc["space"]["names"] == ["px", "py"]
    assert validate_schema(doc, SCHEMA) == []
    assert load_result(tmp_path / "named").dim_names == ("px", "py")
    plain = json.loads(save_result(_fake_result(), tmp_path / "plain").read_text())
    assert "names" not in plain["space"] and validate_schema(plain, SCHEMA) == []
    assert load_result(tmp_path / "plain").dim_names is None
    bad = dict(doc, space=dict(doc["space"], names=[1, 2]))
    assert validate_schema(bad, SCHEMA) != []  # names are strings


def test_figures_label_the_axes_with_the_names():
    doc = _doc_nd(2)
    ax = plotting.plot_classes(doc)
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("$x_1$", "$x_2$")  # no names: x_j, numbered from 1
    doc["space"]["names"] = ["px", "py"]
    ax = plotting.plot_classes(doc)
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("px", "py")
    doc3 = _doc_nd(3)
    doc3["space"]["names"] = ["px", "py", "theta"]
    fig = plotting.plot_slices(doc3, "classes")
    shown = [a for a in fig.axes if a.get_visible()]
    assert all(a.get_xlabel() == "px" and a.get_ylabel() == "py" for a in shown)
    assert all(a.get_title().startswith("theta = ") for a in shown)
    plt.close("all")


# =========================================================================== 1-based messages
def test_grid_messages_number_dimensions_from_one_and_use_the_names():
    with pytest.raises(InvalidInputError) as exc:
        Partition(Box([0.0, 0.0], [4.0, 4.0]), [0.5, 0.3], names=("px", "py"))
    msg = str(exc.value)
    assert "cell_size in dimension 2 (py) is 0.3" in msg and "does not divide the width 4" in msg
    assert "cell_size[1]" not in msg and "dimension 1 " not in msg
    with pytest.raises(InvalidInputError, match=r"cell_size in dimension 1 is 0\.3, .*width 4"):
        Partition(Box([0.0, 0.0], [4.0, 4.0]), [0.3, 0.5])
    with pytest.raises(InvalidInputError, match=r"lower < upper in every dimension; got lower = 1\.0 >= "
                                                r"upper = 0\.5 in dimension 2"):
        Box([0.0, 1.0], [1.0, 0.5])


def test_load_time_warnings_name_the_dimension(tmp_path):
    p = tmp_path / "p.toml"
    text = GOOD.replace("cell_size = [0.5, 0.5]", 'cell_size = [0.5, 0.5]\nnames = ["px", "py"]')
    p.write_text(text.replace("upper = [1.0, 1.0]\n[spec]", "upper = [1.0, 1.2]\n[spec]"))  # des off the grid in y
    _two_mode_csv(tmp_path / "data.csv")
    with pytest.warns(RobustImdpWarning, match=r"dimension 2 \(py\): 8 -> 9 intervals"):
        load_problem(p)


# =========================================================================== slices of d >= 3
def _doc_nd(d, h=0.5):
    """Result document on [-2, 2]^d: des = [0, 1]^d, Q_yes inside des, Q_no elsewhere."""
    lo = np.stack(np.meshgrid(*[np.arange(-2.0, 2.0, h)] * d, indexing="ij"), -1).reshape(-1, d)
    up = lo + h
    des = np.all(lo >= 0, axis=1) & np.all(up <= 1, axis=1)
    p_low = des.astype(float)
    return {
        "format": "robust_imdp.result/1", "space": {"lower": [-2.0] * d, "upper": [2.0] * d},
        "cells": {"lower": lo.tolist(), "upper": up.tolist()}, "labels": [["des"] if a else [] for a in des],
        "modes": ["1"], "dfa": {"atoms": ["des"], "initial": 0, "accepting": [1], "delta": [[0, 1], [1, 1]]},
        "strategy": [["1", "1"]] * len(lo), "strategy_by_time": None, "p_low": p_low.tolist(),
        "p_up": p_low.tolist(), "p_up_star": p_low.tolist(), "error": [0.0] * len(lo),
        "classes": np.where(des, "yes", "no").tolist(), "formula": "F des", "threshold": 0.9, "horizon": None,
        "parameters": {}, "diagnostics": {}, "timings": {},
    }


def _four_d_goal_doc():
    """The 4-D newcomer problem's layout (di4d_8.toml): X = [-1, 1]^4, 8^4 cells, goal = |x_1| <= 0.25 and
    |x_3| <= 0.25 (x_2, x_4 free); its 256 goal cells are the Q_yes cells, every other cell is Q_no."""
    b = np.arange(-1.0, 1.0, 0.25)
    lo = np.stack(np.meshgrid(b, b, b, b, indexing="ij"), -1).reshape(-1, 4)
    up = lo + 0.25
    goal = (lo[:, 0] >= -0.25) & (up[:, 0] <= 0.25) & (lo[:, 2] >= -0.25) & (up[:, 2] <= 0.25)
    doc = _doc_nd(1)
    doc.update({"space": {"lower": [-1.0] * 4, "upper": [1.0] * 4},
                "cells": {"lower": lo.tolist(), "upper": up.tolist()},
                "labels": [["goal"] if g else [] for g in goal], "strategy": [["1", "1"]] * len(lo),
                "dfa": {"atoms": ["goal"], "initial": 0, "accepting": [1], "delta": [[0, 1], [1, 1]]},
                "p_low": goal.astype(float).tolist(), "p_up": goal.astype(float).tolist(),
                "p_up_star": goal.astype(float).tolist(), "error": [0.0] * len(lo),
                "classes": np.where(goal, "yes", "no").tolist(), "formula": "F goal"})
    assert int(goal.sum()) == 256
    return doc


def _yes_patches(fig) -> int:
    """Number of cells drawn in the Q_yes colour over the figure's visible panels."""
    yes = np.array(to_rgba(plotting.CLASS_COLOURS["yes"]))
    n = 0
    for ax in fig.axes:
        if ax.get_visible():
            for coll in ax.collections:
                fc = coll.get_facecolors()
                if len(fc) and fc.shape[1] == 4:
                    n += int(np.sum(np.all(np.isclose(fc, yes), axis=1)))
    return n


def test_default_four_d_slices_go_through_the_q_yes_cells():
    doc = _four_d_goal_doc()
    fig = plotting.plot_slices(doc, "classes")
    titles = [a.get_title() for a in fig.axes if a.get_visible()]
    # the rule: x_4 through the interval met by most Q_yes cells (all tie at 32; nearest the centre of X,
    # lower first: [-0.25, 0), midpoint -0.125); the 4 spread x_3 slices at the midpoints -0.875, -0.375,
    # 0.375, 0.875 have the one nearest to the best x_3 interval (again -0.125) moved onto it
    assert titles == ["x_3 = -0.875, x_4 = -0.125", "x_3 = -0.125, x_4 = -0.125",
                      "x_3 = 0.375, x_4 = -0.125", "x_3 = 0.875, x_4 = -0.125"]
    # the goal meets the plane x_3 = -0.125, x_4 = -0.125 in 2 (x_1) x 8 (x_2) cells, all Q_yes;
    # before, the slices at x_4 = 0 (a face: the cells above it) and x_3 far from the goal showed none
    assert _yes_patches(fig) == 16
    plt.close(fig)


def test_default_three_d_slices_include_the_best_interval():
    fig = plotting.plot_slices(_doc_nd(3), "classes")
    titles = [a.get_title() for a in fig.axes if a.get_visible()]
    # Q_yes = des = [0, 1]^3: x_3 in [0, 0.5) and [0.5, 1) tie with 4 cells each; nearest the centre 0
    # is [0, 0.5): 0.25 replaces the nearest spread value 0.75
    assert titles == ["x_3 = -1.75", "x_3 = -0.75", "x_3 = 0.25", "x_3 = 1.75"]
    assert _yes_patches(fig) == 4
    plt.close(fig)


def test_slice_argument_fixes_coordinates_by_number_or_name():
    doc = _four_d_goal_doc()
    fig = plotting.plot_slices(doc, "classes", slice={"x3": 0.1, "x_4": 0.5})
    assert [a.get_title() for a in fig.axes if a.get_visible()] == ["x_3 = 0.1, x_4 = 0.5"]
    assert _yes_patches(fig) == 16
    plt.close(fig)
    doc["space"]["names"] = ["p1", "v1", "p2", "v2"]
    fig = plotting.plot_slices(doc, "classes", slice={"v2": 0.9})  # panels over p2, v2 fixed
    titles = [a.get_title() for a in fig.axes if a.get_visible()]
    assert len(titles) == 4 and all(t.endswith("v2 = 0.9") and t.startswith("p2 = ") for t in titles)
    plt.close(fig)
    fig = plotting.plot_slices(doc, "classes", slice={"p1": 0.1, "v1": 0.0})  # then the panel shows p2, v2
    ax = [a for a in fig.axes if a.get_visible()][0]
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("p2", "v2")
    assert _yes_patches(fig) == 2 * 8  # x_1 = 0.1 is in the goal: x_3 in 2 cells of it, x_4 free
    plt.close(fig)
    for bad, match in (({"x9": 0.0}, r"slice: 'x9' is not a dimension; use x1 \.\. x4 or p1, v1, p2, v2"),
                       ({"x1": 0.0, "x2": 0.0, "x3": 0.0}, r"slice fixes 3 of 4 dimensions; at most 2"),
                       ({"x1": 3.0}, r"slice: x1 = 3 lies outside X, \[-1, 1\] in dimension 1 \(p1\)")):
        with pytest.raises(InvalidInputError, match=match):
            plotting.plot_slices(doc, "classes", slice=bad)
    plt.close("all")


def test_save_figures_passes_the_slice(tmp_path):
    doc = _doc_nd(3, h=2.0)
    written = plotting.save_figures(doc, tmp_path, dpi=40, slice={"x3": -1.0})
    assert [p.name for p in written] == ["partition.png", "classes.png", "p_low.png", "error.png"]
    with pytest.raises(InvalidInputError, match="slice"):
        plotting.save_figures(_doc_nd(2, h=2.0), tmp_path, slice={"x3": 0.0})  # a 2-D result has no slices


def test_cli_slice_option_is_parsed_checked_and_passed_to_the_figures(tmp_path, monkeypatch, capsys):
    from robust_imdp import cli
    from robust_imdp.io import files as io
    from robust_imdp.pipeline import run as pipeline

    args = cli._parser().parse_args(["run", "p.toml", "--out", "o", "--slice", "x3=0.5,x4=0"])
    assert args.slice == {"x3": 0.5, "x4": 0.0}
    with pytest.raises(SystemExit) as exc:
        cli._parser().parse_args(["run", "p.toml", "--out", "o", "--slice", "x3:0.5"])
    assert exc.value.code == 2 and "NAME=VALUE" in capsys.readouterr().err
    problem = SimpleNamespace(space_lower=np.array([-2.0] * 3), space_upper=np.array([2.0] * 3),
                              dim_names=("px", "py", "theta"), n_grid_cells=8, mode_names=("a",))
    calls = []
    monkeypatch.setattr(io, "load_problem", lambda path: problem)
    monkeypatch.setattr(pipeline, "synthesize_from_data", lambda *a, **k: calls.append("synthesize") or
                        SimpleNamespace(summary=lambda: "summary"))
    monkeypatch.setattr(io, "save_result", lambda result, out: Path(out) / "result.json")
    monkeypatch.setattr(plotting, "save_figures", lambda result, out, **kw: calls.append(kw) or [])
    assert cli.main(["run", "p.toml", "--out", str(tmp_path / "o"), "--slice", "theta=0.5"]) == 0
    assert calls == ["synthesize", {"slice": {"theta": 0.5}}]
    calls.clear()
    # a slice that does not fit the problem fails before the long stages
    assert cli.main(["run", "p.toml", "--out", str(tmp_path / "o"), "--slice", "x5=0"]) == 1
    assert calls == [] and "'x5' is not a dimension" in capsys.readouterr().err


# =========================================================================== overlapping regions
def test_region_overlaps_are_boxes_of_positive_volume():
    goal = Region("goal", (Box([3.0, 3.0], [4.0, 4.0]),))
    obstacle = Region("obstacle", (Box([1.5, 1.0], [2.5, 3.0]), Box([2.0, 2.0], [3.5, 3.5])))
    touching = Region("wall", (Box([0.0, 0.0], [1.5, 1.0]),))  # shares only a corner with obstacle
    found = region_overlaps([goal, obstacle, touching])
    assert [(a, b) for a, b, _ in found] == [("goal", "obstacle")]
    assert found[0][2] == Box([3.0, 3.0], [3.5, 3.5])


def test_overlapping_formula_regions_warn_before_the_long_stages(monkeypatch):
    from robust_imdp.pipeline import run as pipeline

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):
        raise Stop

    monkeypatch.setattr(pipeline, "_preflight", stop)  # stop after the specify stage
    regions = {"des": [((0.0, 0.0), (1.0, 1.0))], "obs": [((0.5, -1.0), (1.5, 0.5))],
               "far": [((0.0, 0.0), (1.0, 1.0))]}  # "far" overlaps des too, but the formula does not use it
    with pytest.warns(RegionOverlapWarning) as record, pytest.raises(Stop):
        pipeline.synthesize_from_data(_tiny_problem(regions=regions, formula="G !obs & F des"), progress=False)
    msgs = [str(w.message) for w in record if issubclass(w.category, RegionOverlapWarning)]
    assert len(msgs) == 1
    assert ("regions 'des' and 'obs' overlap in the box [0.5, 1] x [0, 0.5]" in msgs[0]
            and "labelled with both" in msgs[0])
    with warnings.catch_warnings():  # regions that only share faces: no warning
        warnings.simplefilter("error", RegionOverlapWarning)
        with pytest.raises(Stop):
            pipeline.synthesize_from_data(_tiny_problem(), progress=False)


# =========================================================================== Python API
def _tiny_problem(**changes):
    rng = np.random.default_rng(0)
    x = rng.uniform(-2, 2, (20, 2))
    values = dict(space_lower=np.array([-2.0, -2.0]), space_upper=np.array([2.0, 2.0]),
                  cell_size=np.array([1.0, 1.0]),
                  regions={"des": [((0.0, 0.0), (1.0, 1.0))], "obs": [((-2.0, -2.0), (-1.0, -1.0))]},
                  formula="G !obs & F des", threshold=0.9, horizon=None,
                  data=Dataset(x, np.arange(20) % 2, 0.5 * x, modes=("a", "b")), mode_names=("a", "b"),
                  maps=(AffineMap.zero(2), AffineMap.zero(2)),
                  noise=TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02]), rkhs_bound=2.0)
    values.update(changes)
    return Problem(**values)


def test_problem_from_arrays_builds_the_same_problem():
    rng = np.random.default_rng(0)
    x = rng.uniform(-2, 2, (20, 2))
    names = np.array(["a", "b"] * 10)
    noise = TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02])
    p = Problem.from_arrays(
        x, names, 0.5 * x, lower=[-2, -2], upper=[2, 2], cell_size=1.0,
        regions={"des": ([0, 0], [1, 1]), "obs": [([-2, -2], [-1, -1])]},
        formula="G !obs & F des", threshold=0.9,
        modes={"a": (np.zeros((2, 2)), [0, 0]), "b": AffineMap.zero(2)}, noise=noise, rkhs_bound=2.0,
        lengthscale=1.5, names=("px", "py"), misspecification=0.001)
    assert p.mode_names == ("a", "b") and p.dim_names == ("px", "py")
    np.testing.assert_array_equal(p.cell_size, [1.0, 1.0])
    np.testing.assert_array_equal(p.data.u, np.arange(20) % 2)  # names -> indices in modes order
    assert [len(v) for v in p.regions.values()] == [1, 1]  # one box each, a single box given bare
    np.testing.assert_array_equal(p.regions["des"][0][1], [1.0, 1.0])
    assert p.gp_options == {"lengthscale": 1.5} and p.misspecification == 0.001
    assert isinstance(p.maps[0], AffineMap) and p.horizon is None
    with pytest.raises(InvalidInputError, match=r"modes must give \(A, b\) or an AffineMap for mode 'b'; got 3"):
        Problem.from_arrays(x, names, x, lower=[-2, -2], upper=[2, 2], cell_size=1.0, regions={},
                            formula="F des", threshold=0.9, modes={"a": AffineMap.zero(2), "b": 3},
                            noise=noise, rkhs_bound=2.0)
    with pytest.raises(InvalidInputError, match=r"regions\['des'\] must be a box \(lower, upper\) or a list of "
                                                r"boxes of 2 numbers each; got"):
        Problem.from_arrays(x, names, x, lower=[-2, -2], upper=[2, 2], cell_size=1.0,
                            regions={"des": [0, 1]}, formula="F des", threshold=0.9,
                            modes={"a": AffineMap.zero(2), "b": AffineMap.zero(2)}, noise=noise, rkhs_bound=2.0)
    import doctest  # the docstring's example runs as written

    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    for test in doctest.DocTestFinder().find(Problem.from_arrays, "from_arrays", globs={}):
        runner.run(test)
    assert runner.tries >= 6 and runner.failures == 0


def test_problem_and_result_reprs_are_a_few_lines():
    p = _tiny_problem()
    text = repr(p)
    assert len(text) < 400 and text.count("\n") <= 3, text
    assert "16 cells" in text and "'G !obs & F des'" in text and "20 samples" in text
    res = _stub_result(p)
    text = repr(res)
    assert len(text) < 400 and text.count("\n") <= 4, text
    assert "Q_yes 1" in text and "Q_no 2" in text and "Q_? 1" in text and "'G !obs & F des'" in text


def _stub_result(problem):
    syn = SimpleNamespace(strategy=np.array([[0, 1], [1, 1], [0, 0], [1, 0]]),
                          p_low=np.array([1.0, 0.0, 0.2, 0.5]), p_up=np.array([1.0, 0.1, 0.3, 0.95]),
                          p_up_star=np.array([1.0, 0.2, 0.95, 0.97]), error=np.array([0.0, 0.2, 0.75, 0.47]),
                          classes=np.array(["yes", "no", "no", "maybe"]))
    part = SimpleNamespace(n_cells=4, cells_lower=np.zeros((4, 2)), cells_upper=np.ones((4, 2)))
    return Result(problem=problem, partition=part, abstraction=None, dfa=None, synthesis=syn,
                  class_names=np.array(["yes", "no", "no", "maybe"]), timings={"total": 1.0}, parameters={})


def test_result_shortcuts_read_the_synthesis():
    res = _stub_result(_tiny_problem(dim_names=("px", "py")))
    for name in ("p_low", "p_up", "p_up_star", "error", "strategy"):
        assert getattr(res, name) is getattr(res.synthesis, name)
    np.testing.assert_array_equal(res.classes, ["yes", "no", "no", "maybe"])
    assert res.n_cells == 4 and res.dim_names == ("px", "py")
    assert res.cells_lower is res.partition.cells_lower and res.cells_upper is res.partition.cells_upper


def test_controller_act_gives_names_and_act_index_gives_indices():
    from robust_imdp.synthesis.controller import Controller

    # 2 cells on [0, 2] (cell 1 = des), DFA of "F des": 0 waiting, 1 accepted
    kw = dict(dfa_delta=[[0, 1], [1, 1]], dfa_initial=0, dfa_accepting=[False, True], atoms=["des"],
              cell_letters=[0, 1], breakpoints=[[0.0, 1.0, 2.0]], space_lower=[0.0], space_upper=[2.0])
    named = Controller([[1, 1], [0, 0]], modes=("left", "right"), **kw)
    assert named.mode_names == ("left", "right")
    named.reset([0.5])
    assert named.act_index([0.5]) == 1  # the index, whatever the names
    named.reset([0.5])
    assert named.act([0.5]) == "right"  # the name when the controller knows the names
    plain = Controller([[1, 1], [0, 0]], **kw)
    assert plain.mode_names is None
    plain.reset([0.5])
    assert plain.act_index([0.5]) == 1
    plain.reset([0.5])
    assert plain.act([0.5]) == 1  # no names known: act gives the index too
    assert "act_index" in Controller.act.__doc__ and "name" in Controller.act.__doc__


def test_package_ships_py_typed():
    import tomllib

    assert (ROOT / "src" / "robust_imdp" / "py.typed").is_file()
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "py.typed" in cfg["tool"]["setuptools"]["package-data"]["robust_imdp"]


def test_one_step_cap_for_validate_simulate_and_the_cli(monkeypatch):
    from robust_imdp import cli, validate
    from robust_imdp.io import files as io

    cap = validate.MAX_STEPS
    assert inspect.signature(validate.validate).parameters["max_steps"].default == cap
    assert inspect.signature(validate.simulate).parameters["max_steps"].default == cap
    seen = []

    def record(*args, **kwargs):  # stop the command at its validate() call
        seen.append(kwargs["max_steps"])
        raise RuntimeError("stop")

    monkeypatch.setattr(io, "load_result", lambda path: None)
    monkeypatch.setattr(validate, "validate", record)
    cli.main(["simulate", "out", "--true-system", "three_mode_linear"])
    cli.main(["simulate", "out", "--true-system", "three_mode_linear", "--max-steps", "7"])
    assert seen == [cap, 7]


# =========================================================================== examples/newcomer
NEWCOMER_PROBLEMS = [("robot2d_16.toml", "robot2d_data.py", []), ("robot2d_32.toml", "robot2d_data.py", []),
                     ("unicycle3d_16.toml", "unicycle3d_data.py", ["plain", "uni.csv"]),
                     ("di4d_8.toml", "di4d_data.py", [])]


def test_newcomer_examples_are_the_shared_files_unchanged():
    shared = Path("/work/shared/newcomer")
    names = sorted(p.name for p in NEWCOMER.iterdir() if p.name != "README.md")
    assert names == sorted({t for t, _, _ in NEWCOMER_PROBLEMS} | {g for _, g, _ in NEWCOMER_PROBLEMS}
                           | {"robot2d_system.py"})
    assert (NEWCOMER / "README.md").is_file()
    if not shared.is_dir():
        pytest.skip("the shared newcomer folder is not on this machine")
    for name in names:
        assert (NEWCOMER / name).read_bytes() == (shared / name).read_bytes(), name


@pytest.mark.parametrize("toml, generator, argv", NEWCOMER_PROBLEMS)
def test_newcomer_problem_files_load(tmp_path, toml, generator, argv):
    shutil.copy(NEWCOMER / toml, tmp_path / toml)
    subprocess.run([sys.executable, str(NEWCOMER / generator), *argv], cwd=tmp_path, check=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RobustImdpWarning)  # the shipped problems load without a warning
        problem = load_problem(tmp_path / toml)
    assert problem.data.n_samples == 300 * len(problem.mode_names)
    assert problem.space_lower.shape == (int(toml.split("d_")[0][-1]),)


def test_newcomer_true_system_runs():
    sys.path.insert(0, str(NEWCOMER))
    try:
        from robot2d_system import Robot
    finally:
        sys.path.remove(str(NEWCOMER))
    x = np.full((4, 2), 2.0)
    nxt = Robot().step(x, np.arange(4), np.random.default_rng(0))
    # one step of each mode: +-0.3 along one axis, plus a drift below 0.05 and noise below 0.02 per axis
    np.testing.assert_allclose(nxt - x, Robot.steps, atol=0.05 + 0.02)
