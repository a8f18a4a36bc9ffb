"""Tests of the robust-imdp command: help, exit codes, messages without tracebacks."""

import json
import subprocess
import sys

import pytest

from robust_imdp.cli import main

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
[gp]
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


def test_stale_result_is_removed_when_a_run_fails(tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    (out / "result.json").write_text("{}")
    code, _, _ = _run(["run", str(tmp_path / "missing.toml"), "--out", str(out)], capsys)
    assert code == 1 and not (out / "result.json").exists()


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
    assert code == 0, err
    assert "Monte-Carlo validation: 16 cells x 5 runs" in out
    assert (tmp_path / "validation.json").exists() and (tmp_path / "trajectories.png").exists()
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
    from robust_imdp.casestudies import get_case_study, problem_toml
    from robust_imdp.io import write_data_file

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
