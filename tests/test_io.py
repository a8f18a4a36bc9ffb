"""Tests of io.py: problem-file validation, data files, result files (contract + atomicity)."""

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from robust_imdp.casestudies.systems import problem_toml, get_case_study, write_problem_files
from robust_imdp.errors import ProblemFileError
from robust_imdp.io.files import (
    load_result, parse_problem_file, read_data_file, save_result, write_data_file,
)

GOOD = """
[space]
lower = [-2.0, -2.0]
upper = [2.0, 2.0]
cell_size = [0.5, 0.5]
[[regions.obs]]
lower = [-2.0, -2.0]
upper = [-1.0, -1.0]
[[regions.des]]
lower = [0.0, 0.0]
upper = [1.0, 1.0]
[spec]
formula = "G !obs & F des"
threshold = 0.95
[data]
path = "data.csv"
[modes.a]
A = [[0.0, 0.0], [0.0, 0.0]]
b = [0.0, 0.0]
[modes.b]
A = [[1.0, 0.0], [0.0, 1.0]]
b = [0.1, 0.0]
[noise]
kind = "truncated_gaussian"
sigma = [0.01, 0.01]
bound = [0.01, 0.01]
[learning]
rkhs_bound = 10.0
"""


def _write(tmp_path, text, name="p.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_good_file_parses(tmp_path):
    spec = parse_problem_file(_write(tmp_path, GOOD))
    assert list(spec["modes"]) == ["a", "b"]  # file order kept: mode index = table order
    assert spec["regions"]["obs"][0][1].tolist() == [-1.0, -1.0]
    assert spec["horizon"] is None and spec["threshold"] == 0.95
    assert spec["data_file"] == str((tmp_path / "data.csv").resolve())
    assert spec["abstraction"] == {"eta": None, "eps_rule": "optimized", "combine": "product",
                                   "guarantee": "confidence", "confidence": 0.99}


@pytest.mark.parametrize("old,new,match", [
    ("cell_size = [0.5, 0.5]\n", "", r"\[space\] is missing required key 'cell_size'"),
    ("cell_size =", "cellsize =", r"\[space\] has unknown key 'cellsize' \(did you mean 'cell_size'\?\)"),
    ("[spec]", "[spek]", r"unknown key 'spek' \(did you mean 'spec'\?\)"),
    ("rkhs_bound", "rkhs_bnd", r"\[learning\] has unknown key 'rkhs_bnd' \(did you mean 'rkhs_bound'\?\)"),
    ("threshold = 0.95", 'threshold = "high"', r"\[spec\].threshold must be a number; got 'high'"),
    ("threshold = 0.95", "threshold = 1.5", r"threshold must lie in \[0.0, 1.0\]"),
    ("threshold = 0.95", "threshold = 0.9\nhorizon = 2.5", r"horizon must be an integer"),
    ("upper = [2.0, 2.0]", "upper = [2.0]", r"\[space\].upper must be 2 numbers"),
    ('kind = "truncated_gaussian"', 'kind = "truncated_gausian"', r"did you mean 'truncated_gaussian'"),
    ("bound = [0.01, 0.01]\n", "", r"\[noise\] is missing required key 'bound'"),
    ("A = [[1.0, 0.0], [0.0, 1.0]]", "A = [[1.0, 0.0]]", r"\[modes.b\].A must be a finite 2x2 matrix"),
    ("upper = [-1.0, -1.0]", "upper = [-1.0, 3.0]", r"\[regions.obs\[0\]\].*lies outside the space"),
    ("cell_size = [0.5, 0.5]", "cell_size = [0.5, -0.5]", r"cell_size must be > 0"),
    ("rkhs_bound = 10.0", "rkhs_bound = -1.0", r"rkhs_bound must be > 0"),
    ("rkhs_bound = 10.0", 'rkhs_bound = 10.0\n[abstraction]\nguarantee = "papr"',
     r"\[abstraction\].guarantee must be one of confidence, paper; got 'papr'"),
    ("rkhs_bound = 10.0", "rkhs_bound = 10.0\n[abstraction]\nconfidence = 1.0",
     r"\[abstraction\].confidence must lie in \(0, 1\)"),
])
def test_problem_file_errors_name_the_key(tmp_path, old, new, match):
    assert old in GOOD
    with pytest.raises(ProblemFileError, match=match):
        parse_problem_file(_write(tmp_path, GOOD.replace(old, new, 1)))


def test_not_toml_and_missing_file(tmp_path):
    with pytest.raises(ProblemFileError, match="not valid TOML"):
        parse_problem_file(_write(tmp_path, "[space\nlower = 1"))
    with pytest.raises(ProblemFileError, match="cannot be read"):
        parse_problem_file(tmp_path / "nope.toml")


def _csv(tmp_path, text):
    p = tmp_path / "d.csv"
    p.write_text(text)
    return p


def test_csv_round_trip_and_npz(tmp_path):
    rng = np.random.default_rng(0)
    x, xn = rng.normal(size=(7, 2)), rng.normal(size=(7, 2))
    u = np.array([0, 1, 1, 0, 1, 0, 0])
    for name in ("d.csv", "d.npz"):
        write_data_file(tmp_path / name, x, u, xn, modes=("a", "b"))
        x2, u2, xn2, modes = read_data_file(tmp_path / name, ["a", "b"], n_dims=2)
        np.testing.assert_array_equal(x2, x)  # repr() round-trips floats exactly
        np.testing.assert_array_equal(xn2, xn)
        np.testing.assert_array_equal(u2, u)
        assert modes == ("a", "b")


HEAD = "x_1,x_2,u,x_next_1,x_next_2\n"


@pytest.mark.parametrize("text,match", [
    ("x_1,x_2,u,y_1,y_2\n0,0,a,0,0\n", r"line 1: header must be x_1,x_2,u,x_next_1,x_next_2"),
    # lines are 1-based and count the header and blank lines: the bad sample is on line 4
    (HEAD + "0,0,a,0,0\n\n0,nan,a,0,0\n", r"must be finite; 1 sample is not \(line 4\)"),
    (HEAD + "0,0,a,0,0\n0,0,a,0,0\n0,0,c,0,0\n", r"modes \['c'\] that are not in \[modes.*line 4\)"),
    (HEAD + "0,0,a,0\n", r"line 2 has 4 fields; expected 5"),
    (HEAD + "0,0,a,0,0\n0,zero,a,0,0\n", r"line 3, column x_2 is not a number: 'zero'"),
    (HEAD + "0,0,a,,0\n", r"line 2, column x_next_1 is empty"),
    (HEAD + "0,0,a,0,0\n0,0, ,0,0\n", r"line 3, column u is empty"),
    (HEAD, r"no data rows"),
    # a semicolon file: the hint names the dimension of [space] (2), not the 1 the header implies
    ("x_1;x_2;u;x_next_1;x_next_2\n0;0;a;0;0\n",
     r"header must be x_1,x_2,u,x_next_1,x_next_2 \(2 state dimensions like \[space\]\).*"
     r"separated by ';': use commas"),
])
def test_data_file_errors(tmp_path, text, match):
    with pytest.raises(ProblemFileError, match=match):
        read_data_file(_csv(tmp_path, text), ["a", "b"], n_dims=2)


def test_data_file_other_errors(tmp_path):
    with pytest.raises(ProblemFileError, match="file not found"):
        read_data_file(tmp_path / "none.csv")
    np.savez(tmp_path / "d.npz", x=np.zeros((2, 2)), u=np.array(["a", "a"]))
    with pytest.raises(ProblemFileError, match=r"missing arrays \['x_next'\]"):
        read_data_file(tmp_path / "d.npz")
    (tmp_path / "d.txt").write_text("x")
    with pytest.raises(ProblemFileError, match="expected a .csv or .npz"):
        read_data_file(tmp_path / "d.txt")
    p = _csv(tmp_path, "x_1,u,x_next_1\n0,a,0\n")  # a 1-D file for a 2-D [space]
    with pytest.raises(ProblemFileError, match=r"header must be x_1,x_2,u,x_next_1,x_next_2 \(2 state "
                                               r"dimensions like \[space\]\); got 'x_1,u,x_next_1'"):
        read_data_file(p, ["a"], n_dims=2)
    np.savez(tmp_path / "d1.npz", x=np.zeros((2, 1)), u=np.array(["a", "a"]), x_next=np.zeros((2, 1)))
    with pytest.raises(ProblemFileError, match="must have 2 columns"):
        read_data_file(tmp_path / "d1.npz", ["a"], n_dims=2)
    np.savez(tmp_path / "d2.npz", x=np.array([[0.0, np.nan]]), u=np.array(["a"]), x_next=np.zeros((1, 2)))
    with pytest.raises(ProblemFileError, match=r"1 sample is not \(row 0 \(0-based, of the arrays"):
        read_data_file(tmp_path / "d2.npz", ["a"], n_dims=2)


def test_case_study_problem_files_parse(tmp_path):
    for name in ("three_mode_linear", "four_mode_nonlinear"):
        spec = parse_problem_file(write_problem_files(name, tmp_path, seed=1))
        case = get_case_study(name)
        x, u, xn, _ = read_data_file(spec["data_file"], list(spec["modes"]), 2)
        assert x.shape == (case.n_per_mode * len(case.system.mode_names), 2)
        assert np.bincount(u).tolist() == [case.n_per_mode] * len(case.system.mode_names)
        assert set(spec["regions"]) == set(case.regions)
    assert 'formula = "F des"' in problem_toml(get_case_study("four_mode_nonlinear"), "F des", "d.csv")


# --------------------------------------------------------------------------- result files
def _fake_result(parameters=None):
    """A stand-in with the attributes result_to_dict reads (2x1 grid on [0,2]x[0,1])."""
    part = SimpleNamespace(
        atoms=("obs", "des"), labels=np.array([2, 1]),  # cell 0 in des (bit 1), cell 1 in obs
        cells_lower=np.array([[0.0, 0.0], [1.0, 0.0]]), cells_upper=np.array([[1.0, 1.0], [2.0, 1.0]]),
    )
    # DFA of "G !obs & F des" over atoms (des, obs): 0 = waiting, 1 = accepted, 2 = sink
    delta = np.array([[0, 1, 2, 2], [1, 1, 1, 1], [2, 2, 2, 2]])
    dfa = SimpleNamespace(atoms=("des", "obs"), initial=0, accepting=np.array([False, True, False]),
                          delta=delta)
    syn = SimpleNamespace(strategy=np.array([[0, 1, 0], [1, 1, 1]]), p_low=np.array([1.0, 0.0]),
                          p_up=np.array([1.0, 0.25]), p_up_star=np.array([1.0, 0.5]),
                          error=np.array([0.0, 0.5]))
    return SimpleNamespace(partition=part, dfa=dfa, synthesis=syn, mode_names=("m1", "m2"),
                           space_lower=np.array([0.0, 0.0]), space_upper=np.array([2.0, 1.0]),
                           class_names=np.array(["yes", "no"]), formula="G !obs & F des",
                           threshold=0.9, horizon=None,
                           parameters=parameters or {"eta": np.array([0.01, 0.01])},
                           timings={"total": 1.5})


def test_result_json_contract_and_round_trip(tmp_path):
    res = _fake_result()
    path = save_result(res, tmp_path / "out")
    doc = json.loads(path.read_text())
    for key in ("cells", "labels", "modes", "dfa", "strategy", "p_low", "p_up", "p_up_star",
                "error", "classes", "parameters", "timings"):
        assert key in doc
    assert doc["labels"] == [["des"], ["obs"]]  # partition bits mapped to names
    assert doc["strategy"] == [["m1", "m2", "m1"], ["m2", "m2", "m2"]]
    assert doc["dfa"]["delta"][0] == [0, 1, 2, 2] and doc["dfa"]["accepting"] == [1]
    assert doc["classes"] == ["yes", "no"] and doc["parameters"]["eta"] == [0.01, 0.01]
    loaded = load_result(tmp_path / "out")
    np.testing.assert_array_equal(loaded.strategy, res.synthesis.strategy)
    np.testing.assert_array_equal(loaded.p_up_star, [1.0, 0.5])
    # letters re-expressed in the DFA's atom order: des = bit 0, obs = bit 1
    assert loaded.label_letters.tolist() == [1, 2]
    with np.load(tmp_path / "out" / "result.npz") as z:
        np.testing.assert_array_equal(z["p_low"], [1.0, 0.0])
        assert z["classes"].tolist() == ["yes", "no"]


def test_failed_write_leaves_no_complete_result(tmp_path):
    bad = _fake_result(parameters={"x": object()})  # not JSON-serialisable
    with pytest.raises(TypeError):
        save_result(bad, tmp_path)
    assert not (tmp_path / "result.json").exists()
    assert not list(tmp_path.glob("*.part"))  # temporary files cleaned up


def test_load_result_errors(tmp_path):
    with pytest.raises(ProblemFileError, match="cannot be read"):
        load_result(tmp_path)
    (tmp_path / "result.json").write_text('{"format": "other"}')
    with pytest.raises(ProblemFileError, match="expected format 'robust_imdp.result/1'"):
        load_result(tmp_path)


def test_committed_example_problems_load():
    from robust_imdp.io.files import load_problem

    root = Path(__file__).parents[1] / "examples" / "problems"
    for name, n_modes in (("three_mode_linear", 3), ("four_mode_nonlinear", 4),
                          ("four_mode_nonlinear_two_goals", 4)):
        p = load_problem(root / f"{name}.toml")
        assert len(p.mode_names) == n_modes and p.data.x.shape[1] == 2
        assert p.threshold == 0.95 and p.rkhs_bound > 0


# --------------------------------------------------------------------------- load-time checks
ONE_MODE = """
[space]
lower = [-2.0, -2.0]
upper = [2.0, 2.0]
cell_size = [0.25, 0.25]
[[regions.des]]
lower = [0.0, 0.0]
upper = [1.0, 1.0]
[spec]
formula = "F des"
threshold = 0.9
[data]
path = "d.csv"
[modes.a]
A = [[0.0, 0.0], [0.0, 0.0]]
b = [0.0, 0.0]
[noise]
kind = "truncated_gaussian"
sigma = [0.01, 0.01]
bound = [0.05, 0.05]
[learning]
rkhs_bound = 3.0
"""


def _one_mode(tmp_path, residuals, text=ONE_MODE):
    """Problem file + data: sample k at x = (k/10, 0) with x_next = (residuals[k], 0) (f_a = 0)."""
    lines = ["x_1,x_2,u,x_next_1,x_next_2"] + [f"{k / 10},0,a,{r},0" for k, r in enumerate(residuals)]
    (tmp_path / "d.csv").write_text("\n".join(lines) + "\n")
    return _write(tmp_path, text)


@pytest.mark.parametrize("r,refused", [(3.06, True), (3.04, False), (-3.06, True)])
def test_impossible_sample_is_refused_at_load_like_the_assumption_check(tmp_path, r, refused):
    # |g| <= B + tau = 3 everywhere (unit-amplitude kernel) and |noise| <= 0.05, so a residual
    # with |r| > 3.05 cannot come from the stated system; 3.04 can.
    from robust_imdp.errors import AssumptionError
    from robust_imdp.io.files import load_problem
    from robust_imdp.bounds.rkhs import check_assumption

    residuals = [0.1] * 11 + [r] + [0.2] * 3  # the bad sample is data row 12: file line 13
    path = _one_mode(tmp_path, residuals)
    if refused:
        with pytest.raises(AssumptionError, match=r"\[learning\].rkhs_bound = 3 is refuted by the data: mode 'a', component "
                                                  r"1 .* sample 11 \(data file .*d.csv, line 13\): its residual "
                                                  rf"{r:g} in component 1 is impossible under the assumption, since "
                                                  r".* = 3.05 everywhere"):
            load_problem(path)
    else:
        assert load_problem(path).data.x.shape == (15, 2)
    # the pipeline's assumption check (single points, the same noise bound) draws the same line
    x = np.c_[np.arange(15) / 10, np.zeros(15)]
    y = np.c_[residuals, np.zeros(15)]
    try:
        check_assumption([(x, y)], lengthscale=1.0, rkhs_bound=3.0, noise_bound=[0.05, 0.05], solver=False)
        pipeline_refuses = False
    except AssumptionError as exc:
        pipeline_refuses = "alone" in str(exc)
    assert pipeline_refuses == refused


def test_other_impossible_samples_are_counted(tmp_path):
    from robust_imdp.errors import AssumptionError
    from robust_imdp.io.files import load_problem

    path = _one_mode(tmp_path, [0.0] * 10 + [99.0, 5.0, -4.0])  # lines 12, 13, 14; 99 is the worst
    # a single sample needs ||g|| >= |99| - 0.05 = 98.95 (|h(x)| <= ||h|| for the unit-amplitude kernel)
    with pytest.raises(AssumptionError, match=r"at least 98.95 .* sample 10 \(data file .*, line 12\): its "
                                              r"residual 99 .*; 2 more samples of this mode and component are "
                                              r"impossible too \(lines 13, 14\)\. Choose rkhs_bound >= 98.95"):
        load_problem(path)


def test_few_samples_warn_and_ten_do_not(tmp_path):
    from robust_imdp.errors import RobustImdpWarning
    from robust_imdp.io.files import FEW_SAMPLES, load_problem

    assert FEW_SAMPLES == 10
    with pytest.warns(RobustImdpWarning, match=r"mode 'a' has 3 samples \(fewer than 10\)"):
        load_problem(_one_mode(tmp_path, [0.1, 0.2, 0.3]))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning fails the test
        load_problem(_one_mode(tmp_path, [0.1] * 10))


def test_region_off_the_grid_warns_with_the_partitions_cell_count(tmp_path):
    from robust_imdp.errors import RobustImdpWarning
    from robust_imdp.models.geometry import Box, Partition, Region
    from robust_imdp.io.files import load_problem

    text = ONE_MODE.replace("upper = [1.0, 1.0]", "upper = [1.1, 1.0]").replace(
        "[spec]", "[[regions.obs]]\nlower = [-1.3, -1.0]\nupper = [-1.0, 0.3]\n[spec]")
    with pytest.warns(RobustImdpWarning) as rec:
        p = load_problem(_one_mode(tmp_path, [0.1] * 10, text))
    msg = str(rec[0].message)
    # 16 x 16 uniform cells; x_1 gains -1.3 (obs) and 1.1 (des), x_2 gains 0.3 (obs): 18 x 17 = 306
    part = Partition(Box(p.space_lower, p.space_upper), p.cell_size,
                     [Region(k, [Box(lo, up) for lo, up in v]) for k, v in p.regions.items()])
    assert part.n_cells == 306
    assert "refine it from 256 to 306 cells" in msg
    assert "dimension 1: 16 -> 18 intervals, at -1.3 (obs), 1.1 (des); dimension 2: 16 -> 17 intervals, at 0.3 (obs)" in msg


def test_committed_examples_load_without_warnings():
    import warnings

    from robust_imdp.io.files import load_problem

    root = Path(__file__).parents[1] / "examples" / "problems"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_problem(root / "three_mode_linear.toml")


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_result_files_get_the_mode_of_every_other_output(tmp_path, umask):
    # result.json / result.npz are written under a temporary name (mkstemp: 0600) and renamed;
    # they must end with the mode a plain open() gives (the PNGs, validation.json): 0666 & ~umask.
    import os

    old = os.umask(umask)
    try:
        save_result(_fake_result(), tmp_path)
        (tmp_path / "plain.txt").write_text("x")
    finally:
        os.umask(old)
    want = 0o666 & ~umask  # 0644 or 0600
    modes = {name: (tmp_path / name).stat().st_mode & 0o777 for name in ("result.json", "result.npz", "plain.txt")}
    assert modes == {"result.json": want, "result.npz": want, "plain.txt": want}


# --------------------------------------------------------------------------- [learning], formerly [gp]
def _fields(problem):
    """Every attribute of a Problem as comparable plain values (arrays as lists)."""
    from dataclasses import fields

    out = {}
    for f in fields(problem):
        v = getattr(problem, f.name)
        out[f.name] = repr(v) if f.name in ("data", "maps", "noise", "regions") else (
            np.asarray(v).tolist() if isinstance(v, np.ndarray) else v)
    return out


def test_former_table_name_gp_warns_and_gives_the_same_problem(tmp_path):
    from robust_imdp.io.files import load_problem

    residuals = [0.1] * 12
    new = load_problem(_one_mode(tmp_path, residuals))
    with pytest.warns(DeprecationWarning, match=r"p\.toml: table \[gp\] is now called \[learning\] .*rename \[gp\] to "
                                                r"\[learning\]"):
        old = load_problem(_one_mode(tmp_path, residuals, ONE_MODE.replace("[learning]", "[gp]")))
    assert _fields(old) == _fields(new)
    np.testing.assert_array_equal(old.data.x, new.data.x)
    np.testing.assert_array_equal(old.data.x_next, new.data.x_next)
    assert old.data.u.tolist() == new.data.u.tolist()
    # messages of an old file keep naming the table as written
    with pytest.warns(DeprecationWarning), pytest.raises(ProblemFileError, match=r"\[gp\] has unknown key 'rkhs_bnd'"):
        parse_problem_file(_write(tmp_path, GOOD.replace("[learning]", "[gp]").replace("rkhs_bound", "rkhs_bnd")))


def test_both_learning_and_gp_tables_are_an_error_naming_the_file(tmp_path):
    text = GOOD + "[gp]\nrkhs_bound = 1.0\n"
    with pytest.raises(ProblemFileError, match=r"p\.toml: tables \[learning\] and \[gp\] are both given"):
        parse_problem_file(_write(tmp_path, text))


def test_a_missing_learning_table_is_named():
    from robust_imdp.io.files import parse_problem_dict
    import tomllib

    doc = tomllib.loads(GOOD)
    del doc["learning"]
    # [learning] is optional only for known dynamics (no [data] either): with [data] it is named as missing
    with pytest.raises(ProblemFileError, match=r"p.toml: \[data\] is given but there is no \[learning\] table"):
        parse_problem_dict(doc, where="p.toml")


@pytest.mark.parametrize("table", ["learning", "gp"])
def test_method_rules_name_the_learning_table_as_written(tmp_path, table):
    # the rules come from the method registry (bounds.methods); the file's messages name its table
    import warnings

    text = GOOD.replace("[learning]", f"[{table}]")
    cases = [("rkhs_bound = 10.0", "rkhs_bound = 10.0\noptimize = true",
              rf"\[{table}\]\.optimize applies only to error_bound = \"chowdhury\""),
             ("rkhs_bound = 10.0", 'rkhs_bound = 10.0\nerror_bound = "chowdhury"\nlocal_points = 5',
              rf"\[{table}\]\.local_points applies to error_bound = \"optimal\" or \"ridge\" only"),
             ("rkhs_bound = 10.0", 'rkhs_bound = 10.0\nerror_bound = "optimol"',
              rf"\[{table}\]\.error_bound must be one of optimal, ridge, chowdhury; got 'optimol' \(did you mean"),
             ("rkhs_bound = 10.0", 'rkhs_bound = 10.0\niid_noise = true\n[refine]\nmax_cells = 9',
              rf"\[refine\] needs \[{table}\]\.error_bound = \"optimal\" or \"ridge\" without iid_noise")]
    for old, new, match in cases:
        assert old in text
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            with pytest.raises(ProblemFileError, match=match):
                parse_problem_file(_write(tmp_path, text.replace(old, new, 1)))
