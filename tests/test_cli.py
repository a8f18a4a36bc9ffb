"""Tests of the robust-imdp command: help, exit codes, messages without tracebacks."""

import json
import subprocess
import sys

import pytest

from robust_imdp.cli import main
from problem_texts import write_one_d

GOOD_HEAD = """
[space]
lower = [-2.0, -2.0]
upper = [2.0, 2.0]
cell_size = [0.5, 0.5]
[[regions.des]]
lower = [0.0, 0.0]
upper = [1.0, 1.0]
[spec]
formula = "F des"
threshold = 0.9
[data]
path = "data.csv"
[modes.a]
A = [[0.0, 0.0], [0.0, 0.0]]
b = [0.0, 0.0]
[noise]
kind = "truncated_gaussian"
sigma = [0.01, 0.01]
bound = [0.01, 0.01]
[learning]
rkhs_bound = 10.0
"""


def _run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("argv", [["--help"], ["run", "--help"], ["simulate", "--help"],
                                  ["example", "--help"]])
def test_help_everywhere(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 0
    assert "usage: robust-imdp" in capsys.readouterr().out


def test_usage_error_exits_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["run"])  # PROBLEM and --out missing
    assert exc.value.code == 2


def test_misspelt_key_exit_1_no_traceback(tmp_path, capsys):
    p = tmp_path / "p.toml"
    p.write_text(GOOD_HEAD.replace("cell_size", "cellsize"))
    code, out, err = _run(["run", str(p), "--out", str(tmp_path / "o")], capsys)
    assert code == 1
    assert "did you mean 'cell_size'" in err and "Traceback" not in err
    assert not (tmp_path / "o" / "result.json").exists()


def test_bad_data_file_exit_1(tmp_path, capsys):
    p = tmp_path / "p.toml"
    p.write_text(GOOD_HEAD)
    (tmp_path / "data.csv").write_text("x_1,x_2,u,x_next_1,x_next_2\n0,0,zz,0,0\n")
    code, _, err = _run(["run", str(p), "--out", str(tmp_path / "o")], capsys)
    assert code == 1 and "modes ['zz'] that are not in [modes" in err
    (tmp_path / "data.csv").unlink()
    code, _, err = _run(["run", str(p), "--out", str(tmp_path / "o")], capsys)
    assert code == 1 and "file not found" in err


def test_a_failed_run_leaves_the_previous_result_as_it_was(tmp_path, capsys):
    # The previous result is replaced only by a complete new one (tests/test_result_outputs.py has every
    # failure kind); a failed run neither removes nor changes it.
    out = tmp_path / "o"
    out.mkdir()
    (out / "result.json").write_text("{}")
    code, _, _ = _run(["run", str(tmp_path / "missing.toml"), "--out", str(out)], capsys)
    assert code == 1 and (out / "result.json").read_text() == "{}"


def test_example_then_simulate_on_a_saved_result(tmp_path, capsys):
    code, out, _ = _run(["example", "three_mode_linear", "--out", str(tmp_path)], capsys)
    assert code == 0 and (tmp_path / "three_mode_linear.toml").exists()
    code, _, err = _run(["example", "nope", "--out", str(tmp_path)], capsys)
    assert code == 1 and "case study must be one of" in err
    # simulate needs a result: use the synthetic one of test_plotting (modes 1, 2, 3)
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    from test_plotting import grid_doc

    (tmp_path / "result.json").write_text(json.dumps(grid_doc(h=1.0)))
    code, out, err = _run(["simulate", str(tmp_path), "--true-system", "three_mode_linear",
                           "--n-per-cell", "5", "--max-steps", "20", "--paths", "3"], capsys)
    # grid_doc's bounds are random, not the case study's: the system contradicts them, so the
    # command says so and exits 1, after writing its report and figure
    assert code == 1, err
    assert "validation failed: 2 of 16 cells are flagged, more than the 1 that chance allows" in err
    assert "Monte-Carlo validation: 16 cells x 5 runs" in out and "FAILED: 2 cells flagged" in out
    assert (tmp_path / "validation.json").exists() and (tmp_path / "trajectories.png").exists()
    assert json.loads((tmp_path / "validation.json").read_text())["passed"] is False
    code, _, err = _run(["simulate", str(tmp_path), "--true-system", "pendulum"], capsys)
    assert code == 1 and "case study must be one of" in err


def test_console_script_no_traceback(tmp_path):
    # The installed entry point behaves like main(): message, status 1, no traceback.
    proc = subprocess.run([sys.executable, "-m", "robust_imdp.cli", "run", str(tmp_path / "x.toml"),
                           "--out", str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode == 1
    assert "robust-imdp: error:" in proc.stderr and "Traceback" not in proc.stderr


def test_unknown_region_in_formula_exit_1(tmp_path, capsys):
    # Fails at the specify stage, before any learning; names the region and the known ones.
    root = __import__("pathlib").Path(__file__).parents[1]
    problem = root / "examples" / "problems" / "three_mode_linear.toml"
    code, _, err = _run(["run", str(problem), "--out", str(tmp_path), "--formula", "F goal",
                         "--quiet"], capsys)
    assert code == 1
    assert "regions ['goal'] that are not defined" in err and "Traceback" not in err


@pytest.mark.slow
def test_run_end_to_end_on_a_coarse_problem(tmp_path, capsys):
    # Tiny run through the command line: 64 cells, 40 points per mode; writes the contract files.
    from robust_imdp.casestudies.systems import get_case_study, problem_toml
    from robust_imdp.io.files import write_data_file

    case = get_case_study("three_mode_linear")
    x, u, xn = case.system.sample_dataset(40, case.lower, case.upper, rng=1)
    write_data_file(tmp_path / "d.csv", x, u, xn, modes=case.system.mode_names)
    text = problem_toml(case, "G !obs & F des", "d.csv").replace(
        "cell_size = [0.125, 0.125]", "cell_size = [0.5, 0.5]")
    (tmp_path / "p.toml").write_text(text)
    out = tmp_path / "out"
    code, stdout, err = _run(["run", str(tmp_path / "p.toml"), "--out", str(out)], capsys)
    assert code == 0, err
    assert "cells: 64" in stdout and "stage times:" in stdout
    assert "[robust-imdp] bound" in err  # progress lines go to stderr
    doc = json.loads((out / "result.json").read_text())
    assert len(doc["classes"]) == 64 and doc["modes"] == ["1", "2", "3"]
    for png in ("partition", "classes", "p_low", "error"):
        assert (out / f"{png}.png").exists()
    # same data, new threshold: the abstraction comes from OUT/cache
    code, stdout, _ = _run(["run", str(tmp_path / "p.toml"), "--out", str(out), "--threshold",
                            "0.5", "--no-figures", "--quiet"], capsys)
    assert code == 0 and "reused from cache" in stdout


# --------------------------------------------------------------------------- options (issue 12)
def test_version(capsys):
    import robust_imdp

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"robust-imdp {robust_imdp.__version__}"


def test_debug_also_after_the_command(tmp_path, capsys):
    from robust_imdp.errors import ProblemFileError

    for argv in (["--debug", "run", str(tmp_path / "x.toml"), "--out", str(tmp_path / "o")],
                 ["run", str(tmp_path / "x.toml"), "--out", str(tmp_path / "o"), "--debug"]):
        with pytest.raises(ProblemFileError, match="cannot be read"):  # --debug re-raises: a traceback
            main(argv)
    code, _, err = _run(["run", str(tmp_path / "x.toml"), "--out", str(tmp_path / "o")], capsys)
    assert code == 1 and "Traceback" not in err  # without it: one line


@pytest.mark.parametrize("argv,match", [
    (["run", "P.toml", "--out", "O", "--threshold", "1.5"], "argument --threshold: must be a probability in"),
    (["run", "P.toml", "--out", "O", "--threshold", "nan"], "argument --threshold: must be a probability in"),
    (["run", "P.toml", "--out", "O", "--threshold", "high"], "argument --threshold: must be a probability in"),
    (["run", "P.toml", "--out", "O", "--workers", "0"], r"argument --workers: must be an integer >= 1; got 0"),
    (["simulate", "D", "--true-system", "x", "--n-per-cell", "0"], "argument --n-per-cell: must be an integer >= 1"),
    (["simulate", "D", "--true-system", "x", "--confidence", "1"], r"argument --confidence: must lie in \(0, 1\)"),
    (["simulate", "D", "--true-system", "x", "--seed", "-1"], "argument --seed: must be an integer >= 0"),
    (["export", "D", "--format", "dot", "--out", "F"], r"argument --format: invalid choice: 'dot'"),
])
def test_bad_option_values_stop_before_any_work(tmp_path, monkeypatch, capsys, argv, match):
    import re

    monkeypatch.chdir(tmp_path)  # P.toml, D and O do not exist: the values fail first
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert re.search(match, capsys.readouterr().err)
    assert not (tmp_path / "O").exists()


def test_bad_overrides_fail_before_the_data_are_read(tmp_path, capsys):
    # The data file does not exist: a formula error reported first proves nothing was read.
    p = tmp_path / "p.toml"
    p.write_text(GOOD_HEAD)
    code, _, err = _run(["run", str(p), "--out", str(tmp_path / "o"), "--formula", "F (des"], capsys)
    assert code == 1 and "formula" in err.lower() and "data" not in err
    out_file = tmp_path / "file"
    out_file.write_text("")
    code, _, err = _run(["run", str(p), "--out", str(out_file)], capsys)
    assert code == 1 and "--out must be a directory you can write to" in err


def test_problem_refuses_a_bad_threshold_when_made():
    # The Python API: Problem.replace(threshold=1.5) fails at once, not after learning and solving.
    from pathlib import Path

    from robust_imdp.errors import InvalidInputError
    from robust_imdp.io.files import load_problem

    problem = load_problem(Path(__file__).parents[1] / "examples" / "problems" / "three_mode_linear.toml")
    with pytest.raises(InvalidInputError, match=r"threshold must be a probability in \[0, 1\]; got 1.5"):
        problem.replace(threshold=1.5)
    with pytest.raises(InvalidInputError, match=r"horizon must be None \(unbounded\) or an integer >= 1; got 0"):
        problem.replace(horizon=0)


def test_warnings_read_like_errors(tmp_path, capsys):
    # 3 samples warn at load time; the unknown region then stops the run at the specify stage.
    p = tmp_path / "p.toml"
    p.write_text(GOOD_HEAD)
    (tmp_path / "data.csv").write_text("x_1,x_2,u,x_next_1,x_next_2\n0,0,a,0,0\n1,1,a,0,0\n0,1,a,0,0\n")
    code, _, err = _run(["run", str(p), "--out", str(tmp_path / "o"), "--formula", "F goal", "--quiet"], capsys)
    assert code == 1
    lines = err.strip().splitlines()
    assert lines[0].startswith("robust-imdp: warning: data file ") and "mode 'a' has 3 samples" in lines[0]
    assert lines[1].startswith("robust-imdp: error: ") and len(lines) == 2  # no source line, no "warnings.warn("



def test_former_gp_table_warns_on_the_cli(tmp_path, capsys):
    p = tmp_path / "p.toml"
    p.write_text(GOOD_HEAD.replace("[learning]", "[gp]"))
    (tmp_path / "data.csv").write_text("x_1,x_2,u,x_next_1,x_next_2\n" + "".join(f"{k / 10},0,a,0,0\n" for k in range(12)))
    code, _, err = _run(["run", str(p), "--out", str(tmp_path / "o"), "--formula", "F goal", "--quiet"], capsys)
    assert code == 1
    lines = err.strip().splitlines()
    assert lines[0] == (f"robust-imdp: warning: {p}: table [gp] is now called [learning] (same keys; the default "
                        "route is not a GP): rename [gp] to [learning]")
    assert lines[1].startswith("robust-imdp: error: ") and len(lines) == 2


# --------------------------------------------------------------------------- simulate a user's system
STILL_SYSTEM = '''
import numpy as np


class Still:
    """Never moves: x_next = x (modes named like the synthetic result's)."""

    mode_names = ("1", "2", "3")

    def step(self, x, modes, rng):
        return np.array(x, dtype=float)


still = Still()


class NeedsArgs:
    mode_names = ("1", "2", "3")

    def __init__(self, speed):
        self.speed = speed

    def step(self, x, modes, rng):
        return x


class WrongShape(Still):
    def step(self, x, modes, rng):
        return x[:, :1]


class Broken(Still):
    def step(self, x, modes, rng):
        raise ZeroDivisionError("user bug")


class NoStep:
    mode_names = ("1", "2", "3")


class OtherModes(Still):
    mode_names = ("a", "b")
'''


@pytest.fixture
def synthetic_result(tmp_path):
    sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
    from test_plotting import grid_doc

    doc = grid_doc(h=1.0)  # 16 cells; G !obs & F des
    (tmp_path / "result.json").write_text(json.dumps(doc))
    (tmp_path / "mysys.py").write_text(STILL_SYSTEM)
    return tmp_path, doc


@pytest.mark.parametrize("name", ["Still", "still"])  # a class built with no arguments, or an object
def test_simulate_a_users_system_from_a_file(synthetic_result, capsys, name):
    d, doc = synthetic_result
    code, out, err = _run(["simulate", str(d), "--true-system", f"{d / 'mysys.py'}:{name}", "--n-per-cell", "4",
                           "--max-steps", "3", "--paths", "2"], capsys)
    assert code == 0, err
    rep = json.loads((d / "validation.json").read_text())
    # A system that never moves: the DFA reads the start cell's label at once, so des cells are
    # satisfied (4 of 4 runs), obs cells violated (0), and all other runs stay undecided (capped).
    des = np.array(["des" in lab for lab in doc["labels"]])
    obs = np.array(["obs" in lab for lab in doc["labels"]])
    assert rep["satisfied"] == (4 * des).tolist()
    assert rep["capped"] == (4 * (~des & ~obs)).tolist()


import numpy as np  # noqa: E402  (used by the tests below and above)


@pytest.mark.parametrize("spec,match", [
    ("mysys.py:Nope", r"mysys.py defines no 'Nope' \(it defines \['Broken', 'NeedsArgs',"),
    ("missing.py:Still", r"file .*missing.py not found"),
    ("mysys.py:NeedsArgs", r"the class must be constructible with no arguments"),
    ("mysys.py:NoStep", r"must have a method step\(x \(k, n\), modes \(k,\) int, rng\) -> \(k, n\)"),
    # 16 cells x 1 run; the 2 des and 4 obs cells are decided at reset, so 10 runs are stepped
    ("mysys.py:WrongShape", r"true_system.step\(x, modes, rng\) must return the next states, shape \(k, n\) = "
                            r"\(10, 2\) like x; got \(10, 1\)"),
    ("mysys.py:Broken", r"mysys.py:Broken: step\(x, modes, rng\) raised ZeroDivisionError: user bug"),
    ("mysys.py:OtherModes", r"true_system has no modes \['1', '2', '3'\]; it has \['a', 'b'\]"),
    ("mysys.py", r"must be a case study name or FILE.py:NAME"),
])
def test_simulate_user_system_errors_name_the_file_and_the_interface(synthetic_result, capsys, spec, match):
    import re

    d, _ = synthetic_result
    path = f"{d / spec}" if not spec.startswith("missing") else str(d / spec)
    code, _, err = _run(["simulate", str(d), "--true-system", path, "--n-per-cell", "1", "--max-steps", "2",
                         "--no-figures"], capsys)
    assert code == 1 and re.search(match, err), err
    assert "Traceback" not in err




@pytest.mark.slow
def test_run_a_one_d_problem_writes_its_figure(tmp_path, capsys):
    # x+ = 0.5 x + 1 + 0.1 sin(x) + v: contracts towards x = 2.2 inside des = [2, 3].
    write_one_d(tmp_path)
    code, out, err = _run(["run", str(tmp_path / "p.toml"), "--out", str(tmp_path / "o"), "--quiet"], capsys)
    assert code == 0, err
    assert "cells: 16" in out and "1 figures in" in out
    assert (tmp_path / "o" / "bounds.png").stat().st_size > 5000


# --------------------------------------------------------------------------- leftovers (issue 19)
def test_run_replaces_the_previous_results_outputs_but_not_other_files(tmp_path, capsys):
    # The old result's validation and figures must not sit beside the new result; a failed run (here: the
    # data file is missing) leaves all of them as they were.
    out = tmp_path / "o"
    out.mkdir()
    stale = ["result.json", "result.npz", "validation.json", "trajectories.png", "classes.png", "p_low.png",
             "error.png", "partition.png", "bounds.png"]
    for name in stale + ["notes.txt"]:
        (out / name).write_text("old")
    p = tmp_path / "p.toml"
    p.write_text(GOOD_HEAD)
    code, _, err = _run(["run", str(p), "--out", str(out)], capsys)
    assert code == 1 and "file not found" in err
    assert sorted(f.name for f in out.iterdir()) == sorted(stale + ["notes.txt"])
    write_one_d(tmp_path, "one.toml")  # a run that succeeds: its outputs replace every one of the old ones
    code, _, err = _run(["run", str(tmp_path / "one.toml"), "--out", str(out), "--quiet", "--advice", "off"], capsys)
    assert code == 0, err
    assert sorted(f.name for f in out.iterdir()) == ["bounds.png", "cache", "notes.txt", "result.json", "result.npz"]
    assert (out / "notes.txt").read_text() == "old" and (out / "bounds.png").read_bytes()[:4] == b"\x89PNG"


def test_a_failed_run_leaves_no_empty_directories(tmp_path, capsys):
    p = tmp_path / "p.toml"
    p.write_text(GOOD_HEAD)  # data.csv is missing: the run fails when the data are read
    code, _, err = _run(["run", str(p), "--out", str(tmp_path / "new" / "out")], capsys)
    assert code == 1 and "file not found" in err
    assert not (tmp_path / "new").exists()  # neither out/, out/cache/ nor their new parent
    code, _, _ = _run(["run", str(p), "--out", str(tmp_path / "o2"), "--cache", str(tmp_path / "c" / "d")], capsys)
    assert code == 1 and not (tmp_path / "o2").exists() and not (tmp_path / "c").exists()
    (tmp_path / "mine").mkdir()  # a directory that existed before the run stays
    code, _, _ = _run(["run", str(p), "--out", str(tmp_path / "mine")], capsys)
    assert code == 1 and (tmp_path / "mine").is_dir() and not (tmp_path / "mine" / "cache").exists()


def test_out_below_a_file_is_refused_before_any_work(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("")
    p = tmp_path / "p.toml"
    p.write_text(GOOD_HEAD)
    code, _, err = _run(["run", str(p), "--out", str(f / "sub")], capsys)
    assert code == 1 and "--out must be a directory you can write to" in err and "data" not in err
