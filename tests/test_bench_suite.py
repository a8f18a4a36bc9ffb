"""benchmarks/ as a suite: the field's problem files state their sources' systems, the ARCH runner runs end to end
(and reports instead of crashing), the suite entry point names runnable scripts, and archived experiments still
import."""

from __future__ import annotations

import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).parents[1]
BENCH = ROOT / "benchmarks"
PROBLEMS = BENCH / "arch" / "problems"


def _module(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up while the class is made
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def arch():
    return _module(BENCH / "arch" / "run.py", "arch_run_under_test")


@pytest.fixture(scope="module")
def suites():
    return _module(BENCH / "run.py", "bench_suites_under_test")


# Cell counts the sources state (shared/notes/field-benchmarks.md, IMPaCT Table 1 for the lattice rows) or the
# problem file's header derives: name -> (grid cells, modes).
COUNTS = {"bas4d": (1225, 4), "robot2d_reach": (400, 121), "robot2d_reach_avoid": (1600, 441),
          "car_parking": (1600, 9), "vdp_arch20": (10_000, 1), "vdp_gaussian": (2704, 11),
          "vdp_gaussian_peer": (2704, 11), "integrator2": (10_000, 3), "integrator3": (64_000, 3),
          "integrator4": (160_000, 3), "anaesthesia3d": (8000, 3), "vehicle3d": (7938, 30), "bas7d": (107_163, 1),
          "linear6d": (8 ** 6, 1), "linear7d": (8 ** 7, 1)}


def _load(path):
    import warnings

    from robust_imdp.io.problem_file import load_problem

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # vdp_gaussian's target refines its grid (said in its header)
        return load_problem(path)


def test_every_problem_file_is_listed_here_and_by_the_runner(arch):
    files = {p.stem for p in PROBLEMS.glob("*.toml")}
    assert files == set(COUNTS)
    assert {b.file[:-5] for b in arch.BENCHMARKS} == files


@pytest.mark.parametrize("stem", sorted(COUNTS))
def test_problem_file_is_its_source_system(stem, arch):
    """Each file loads with the stated size, and its f(x, u) expressions equal the runner's true system, which is
    written again in numpy from the source (the vehicle with atan as IMPaCT writes it) on random states of X."""
    p = _load(PROBLEMS / f"{stem}.toml")
    cells, modes = COUNTS[stem]
    assert len(p.mode_names) == modes and p.known and p.data is None
    n_cells = p.n_grid_cells if stem not in ("vdp_gaussian", "vdp_gaussian_peer") else None
    if n_cells is not None:
        assert n_cells == cells
    bench = next(b for b in arch.BENCHMARKS if b.file == f"{stem}.toml" and not b.edits)
    sys_ = arch.true_system(bench.system, p)
    rng = np.random.default_rng(0)
    lower, upper = np.asarray(p.space_lower, float), np.asarray(p.space_upper, float)
    x = rng.uniform(lower, upper, (30, lower.size))
    for k in rng.choice(len(p.mode_names), size=min(6, len(p.mode_names)), replace=False):
        u = np.repeat(sys_.inputs[k][None], len(x), axis=0)
        # 1e-12 relative: double evaluation of the same formulas in another order (the vehicle: an identity)
        np.testing.assert_allclose(p.maps[k](x), sys_.f(x, u), rtol=1e-12, atol=1e-12)
    # the noise the file states is the source's (variances, or the uniform bound)
    if sys_.sd is not None:
        np.testing.assert_allclose(p.noise.sigma, sys_.sd, rtol=1e-14)
    else:
        np.testing.assert_allclose(p.noise.bound, sys_.uniform, rtol=1e-14)


def test_headers_name_source_variants_and_published_numbers():
    for path in PROBLEMS.glob("*.toml"):
        head = "\n".join(line for line in path.read_text().splitlines() if line.startswith("#"))
        assert "Published" in head, path.name
        assert re.search(r"ARCH-COMP|IMPaCT|HSCC 2025", head), path.name
    assert "3.3378" in (PROBLEMS / "bas4d.toml").read_text()              # Q1's printed variant named
    assert "inverse variances" in (PROBLEMS / "bas7d.toml").read_text().replace("INVERSE", "inverse")
    assert "(1 - x1)^2" in (PROBLEMS / "vdp_gaussian_peer.toml").read_text().splitlines()[0]


def test_runner_quick_runs_one_benchmark_end_to_end_and_writes_its_table(tmp_path):
    """bas4d's coarse variant (16 cells, 2 steps) in a child process: a row with the run's numbers, its Monte
    Carlo from the numpy BAS passing, and the markdown table; a second --only run keeps the first row."""
    cmd = [sys.executable, str(BENCH / "arch" / "run.py"), "--quick", "--only", "bas4d", "--out", str(tmp_path),
           "--mc-cells", "16", "--mc-runs", "100", "--timeout", "600", "--no-warm"]
    subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True, text=True)
    data = json.loads((tmp_path / "arch_quick.json").read_text())
    (row,) = data["rows"]
    assert row["status"] == "ok" and row["cells"] == 16 and row["modes"] == 4 and row["semantics"] == "safety"
    assert row["p_low"]["min"] <= row["p_low"]["mean"] <= row["p_low"]["max"] <= row["p_up"]["max"] <= 1.0
    assert row["p_low"]["min"] > 0.0 and row["sound_order"]
    assert row["q_yes"] + row["q_no"] + row["q_maybe"] == 16
    assert row["monte_carlo"]["passed"] and row["monte_carlo"]["cells"] == 16
    assert row["peak_mb"] > 0 and row["wall_seconds"] > 0
    md = (tmp_path / "arch_quick.md").read_text()
    assert "| bas4d | 16 x 4 |" in md and "python benchmarks/run.py arch --quick" in md


def test_runner_reports_pending_and_timeout_rows_instead_of_crashing(arch, tmp_path, monkeypatch):
    monkeypatch.setattr(arch, "factored_available", lambda: "not here (test)")
    assert arch.main(["--only", "linear7d", "--out", str(tmp_path), "--no-warm"]) == 0
    row = json.loads((tmp_path / "arch.json").read_text())["rows"][0]
    assert row["status"] == "pending" and "factored" in row["why"]
    assert "**pending**" in (tmp_path / "arch.md").read_text()
    # a child stopped at --timeout: its process group is killed and the row says so; the pending row is kept
    assert arch.main(["--only", "bas4d", "--quick", "--out", str(tmp_path), "--timeout", "0.5", "--no-warm"]) == 0
    row = json.loads((tmp_path / "arch_quick.json").read_text())["rows"][0]
    assert row["status"] == "timeout" and row["wall_seconds"] < 30
    assert json.loads((tmp_path / "arch.json").read_text())["rows"][0]["status"] == "pending"


def test_runner_refuses_unknown_names_and_edits_that_do_not_apply(arch):
    with pytest.raises(SystemExit):
        arch.main(["--only", "no_such_benchmark"])
    bad = arch.Bench("x", "bas4d.toml", "bas4d", edits={"horizon = 99": "horizon = 1"})
    with pytest.raises(ValueError, match="horizon = 99"):
        arch.problem_text(bad, quick=False)
    for b in arch.BENCHMARKS:  # every row's edits apply exactly once
        arch.problem_text(b, quick=False)
        if b.quick is not None:
            arch.problem_text(b, quick=True)


def test_suite_entry_point_lists_its_suites_and_their_scripts_exist(suites):
    out = subprocess.run([sys.executable, str(BENCH / "run.py"), "--list"], capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout
    for name in ("perf", "solver", "casestudies", "family", "arch", "scale", "cold_start", "newcomer", "sampling"):
        assert f"{name}:" in out
    for suite in suites.SUITES:
        for step in suite.steps:
            script = BENCH / step.script
            assert script.exists(), step.script
            text = script.read_text()
            for arg in (*step.args, *(step.quick or ())):  # every option a step passes is one the script takes
                if arg.startswith("--"):
                    assert f'"{arg}"' in text, (step.script, arg)
    dry = subprocess.run([sys.executable, str(BENCH / "run.py"), "anchors", "--quick", "--dry-run"],
                         capture_output=True, text=True, check=True, cwd=ROOT).stdout
    assert "arch/run.py --quick" in dry
    bad = subprocess.run([sys.executable, str(BENCH / "run.py"), "nope"], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and "unknown suite" in bad.stderr


def test_make_bench_and_readme_commands_name_real_suites(suites):
    make = (ROOT / "Makefile").read_text()
    assert "benchmarks/run.py perf" in make.split("bench: venv", 1)[1].split("\n\n", 1)[0]
    readme = (ROOT / "README.md").read_text()
    named = re.findall(r"benchmarks/run\.py (\w+)", readme)
    assert named, "the README names no suite command"
    for name in named:
        assert name in suites.BY_NAME or name in suites.ALIASES, name


def test_archived_scripts_still_import_and_the_index_lists_them():
    archive = BENCH / "archive"
    scripts = sorted(p.stem for p in archive.glob("*.py"))
    index = (archive / "INDEX.md").read_text()
    assert scripts and all(f"`{s}.py`" in index for s in scripts)
    listed = re.findall(r"^\| `([a-z_]+)\.py` \|", index, flags=re.M)
    assert sorted(listed) == scripts
    for s in scripts:  # importing runs their module level: the shared helpers of benchmarks/ must resolve
        _module(archive / f"{s}.py", f"archived_{s}")
    for s in scripts:  # archived, so no longer beside the suites' scripts
        assert not (BENCH / f"{s}.py").exists()
