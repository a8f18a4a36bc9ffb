"""Ctrl-C: whatever stage it stops, the command prints its one interrupt line and exits 130."""

import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from robust_imdp.cli import main
from robust_imdp.errors import InvalidInputError, interrupt_in

FINE = """
[space]
lower = [0.0, 0.0]
upper = [4.0, 4.0]
cell_size = [0.03125, 0.03125]
[[regions.goal]]
lower = [3.0, 3.0]
upper = [4.0, 4.0]
[spec]
formula = "F goal"
threshold = 0.9
[data]
path = "d.csv"
[modes.east]
A = [[1.0, 0.0], [0.0, 1.0]]
b = [0.3, 0.0]
[noise]
kind = "uniform"
bound = [0.02, 0.02]
[learning]
rkhs_bound = 0.2
"""


def _write_fine_problem(d):
    # 60 points: the assumption check is quick; 128 x 128 cells: the bound stage takes seconds
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 4, (60, 2))
    xn = x + [0.3, 0.0] + 0.05 * np.sin(x[:, ::-1]) + rng.uniform(-0.02, 0.02, (60, 2))
    (d / "d.csv").write_text("x_1,x_2,u,x_next_1,x_next_2\n" + "".join(
        f"{a[0]:.17g},{a[1]:.17g},east,{b[0]:.17g},{b[1]:.17g}\n" for a, b in zip(x, xn)))
    (d / "p.toml").write_text(FINE)


@pytest.mark.slow
def test_sigint_in_the_bound_stage_exits_130_with_the_interrupt_line(tmp_path):
    # The bound stage spends its time in numba kernels; a Ctrl-C there used to surface as
    # "internal error (SystemError: CPUDispatcher(<function _optimal_cells ...>) returned a
    # result with an exception set)" and exit 3.
    _write_fine_problem(tmp_path)
    # SIGINT back to its default in the child: a shell's background job (nohup, `cmd &`) inherits it
    # ignored, and Python then installs no handler, so Ctrl-C would never arrive
    proc = subprocess.Popen([sys.executable, "-m", "robust_imdp.cli", "run", "p.toml", "--out", "out",
                             "--no-figures"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = []
    try:
        for line in proc.stderr:
            seen.append(line)
            if "bound: 1/" in line:  # the first finished chunk: the stage is running
                proc.send_signal(signal.SIGINT)
                break
        rest = proc.stderr.read()
        code = proc.wait(timeout=60)
    finally:
        proc.kill()
    assert any("bound: 1/" in s for s in seen), "".join(seen)
    assert "bounded images of" not in rest, "the signal came after the bound stage"
    assert code == 130, rest
    assert rest.strip().splitlines()[-1] == (
        "robust-imdp: interrupted; the finished chunks are saved in out/cache: run the same command "
        "again to resume")
    assert "internal error" not in rest and "Traceback" not in rest
    assert list((tmp_path / "out" / "cache").glob("bounds-*.parts/m0-c*.npz")), "finished chunks are kept"


def _systemerror_from_interrupt():
    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as ki:
            raise SystemError("CPUDispatcher(<function _optimal_cells>) returned a result with an "
                              "exception set") from ki
    except SystemError as exc:
        return exc


def test_interrupt_in_follows_cause_and_context():
    se = _systemerror_from_interrupt()
    assert isinstance(interrupt_in(se), KeyboardInterrupt)
    try:
        try:
            raise se
        except SystemError:
            raise InvalidInputError("--true-system f.py:S: step(x, modes, rng) raised SystemError")
    except InvalidInputError as wrapped:  # implicit chaining (__context__)
        assert isinstance(interrupt_in(wrapped), KeyboardInterrupt)
    assert interrupt_in(ValueError("x")) is None and interrupt_in(None) is None


@pytest.mark.parametrize("stage", ["check", "bound", "abstract", "synthesize", "refine"])
def test_every_pipeline_stage_turns_an_interrupt_in_compiled_code_into_keyboardinterrupt(stage):
    from robust_imdp.pipeline.runtime import _Log

    log = _Log(False)
    with pytest.raises(KeyboardInterrupt, match=f"during the {stage} stage") as info:
        with log.stage(stage):
            raise _systemerror_from_interrupt()
    assert isinstance(info.value.__cause__, SystemError)
    assert stage in log.timings  # the stage's time is still recorded
    with pytest.raises(ValueError):  # other errors pass unchanged
        with log.stage(stage):
            raise ValueError("bad")


@pytest.mark.parametrize("wrap", [False, True])
def test_cli_exits_130_for_an_interrupt_seen_as_another_exception(tmp_path, monkeypatch, capsys, wrap):
    # Outside the pipeline's stages (a user's step(), plotting, saving) the command itself
    # recognises the interrupt behind a SystemError or behind an error raised from one.
    import robust_imdp.pipeline.run as pipeline

    def interrupted(*a, **k):
        exc = _systemerror_from_interrupt()
        if wrap:
            raise InvalidInputError("user code failed") from exc
        raise exc

    monkeypatch.setattr(pipeline, "synthesize_from_data", interrupted)
    root = __import__("pathlib").Path(__file__).parents[1]
    problem = root / "examples" / "problems" / "three_mode_linear.toml"
    code = main(["run", str(problem), "--out", str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 130, err
    assert err.strip().startswith("robust-imdp: interrupted;") and "internal error" not in err
