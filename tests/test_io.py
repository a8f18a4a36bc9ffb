"""Tests of io.py: problem-file validation, data files, result files (contract + atomicity)."""

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from robust_imdp.casestudies import problem_toml, get_case_study, write_problem_files
from robust_imdp.errors import ProblemFileError
from robust_imdp.io import (
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
[gp]
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
    ("rkhs_bound", "rkhs_bnd", r"\[gp\] has unknown key 'rkhs_bnd' \(did you mean 'rkhs_bound'\?\)"),
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


@pytest.mark.parametrize("text,match", [
    ("x_1,x_2,u,y_1,y_2\n0,0,a,0,0\n", r"header must be x_1,x_2,u,x_next_1,x_next_2"),
    ("x_1,x_2,u,x_next_1,x_next_2\n0,nan,a,0,0\n", r"must be finite; 1 rows are not"),
    ("x_1,x_2,u,x_next_1,x_next_2\n0,0,c,0,0\n", r"modes \['c'\] that are not in \[modes"),
    ("x_1,x_2,u,x_next_1,x_next_2\n0,0,a,0\n", r"line 2 has 4 fields; expected 5"),
    ("x_1,x_2,u,x_next_1,x_next_2\n0,zero,a,0,0\n", r"non-numeric"),
    ("x_1,x_2,u,x_next_1,x_next_2\n", r"no data rows"),
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
    p = _csv(tmp_path, "x_1,u,x_next_1\n0,a,0\n")
    with pytest.raises(ProblemFileError, match="must have 2 columns"):
        read_data_file(p, ["a"], n_dims=2)


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
    from robust_imdp.io import load_problem

    root = Path(__file__).parents[1] / "examples" / "problems"
    for name, n_modes in (("three_mode_linear", 3), ("four_mode_nonlinear", 4),
                          ("four_mode_nonlinear_two_goals", 4)):
        p = load_problem(root / f"{name}.toml")
        assert len(p.mode_names) == n_modes and p.data.x.shape[1] == 2
        assert p.threshold == 0.95 and p.rkhs_bound > 0
