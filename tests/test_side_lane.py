"""Side work in helper processes (``pipeline.parallel.SideLane``): the lane itself, the assumption check beside the
bound stage (the same checks bit for bit, the same refusal, early), a whole run with the lane against one core, and
the command line's figures drawn by helpers (the same PNG bytes; the run's process imports neither matplotlib nor
cvxpy)."""

from __future__ import annotations

import copy
import json
import math
import operator
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from robust_imdp.errors import AssumptionError
from robust_imdp.pipeline import bound_stage, parallel
from robust_imdp.pipeline.parallel import InProcess, SideLane, SideLaneError
from robust_imdp.pipeline.runtime import _Log, _Run

sys.path.insert(0, str(Path(__file__).parent))
from test_check_tasks import _problem  # noqa: E402  (the three-mode problem with 30 samples per mode)

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------------------- the lane
def test_the_lane_runs_tasks_in_helpers_and_returns_results_and_errors():
    with SideLane(2) as lane:
        futures = [lane.submit(math.factorial, k) for k in range(12)]
        assert [f.result(timeout=60) for f in futures] == [math.factorial(k) for k in range(12)]
        assert lane.submit("math:comb", 10, 3).result(timeout=60) == 120  # by name: imported by the helper only
        assert lane.submit(print, "a task's print goes to stderr").result(timeout=60) is None  # answers intact
        with pytest.raises(ZeroDivisionError) as err:
            lane.submit(operator.truediv, 1, 0).result(timeout=60)
        assert "side-work helper process" in "".join(getattr(err.value, "__notes__", []))
        pids = {lane.submit(os.getpid).result(timeout=60) for _ in range(6)}
        assert os.getpid() not in pids and 1 <= len(pids) <= 2


def test_a_helper_that_dies_fails_its_task_with_a_side_lane_error_and_close_cancels_the_queue():
    lane = SideLane(1)
    try:
        with pytest.raises(SideLaneError, match="helper process ended"):
            lane.submit(os._exit, 3).result(timeout=60)
        with pytest.raises(SideLaneError, match="every side-work helper ended"):
            lane.submit(math.factorial, 3)
    finally:
        lane.close()
    lane = SideLane(1)
    slow = lane.submit(time.sleep, 30)
    queued = lane.submit(math.factorial, 3)
    t0 = time.perf_counter()
    lane.close()
    assert time.perf_counter() - t0 < 20 and queued.cancelled()
    with pytest.raises(SideLaneError):
        slow.result(timeout=20)
    with pytest.raises(SideLaneError, match="closed"):
        lane.submit(math.factorial, 3)


def test_an_unpicklable_task_is_a_side_lane_error_not_a_dead_helper():
    with SideLane(1) as lane:
        with pytest.raises(SideLaneError, match="could not send"):
            lane.submit(math.factorial, lambda: 3).result(timeout=60)
        assert lane.submit(math.factorial, 4).result(timeout=60) == 24  # the helper is still there


# ---------------------------------------------------------------------------------------------- the check
def _two_core_run() -> _Run:
    run = _Run()
    run.sched = InProcess(threads=2)
    return run


def test_the_check_beside_the_bound_stage_gives_the_same_checks_bit_for_bit():
    p = _problem()
    data = bound_stage._residual_data(p)
    serial, nb = bound_stage._check_assumption(p, data, _Log(False))
    run = _two_core_run()
    try:
        pending = bound_stage._start_check(p, data, _Log(False), None, run, parallel.SIDE_MIN_CELL_MODES)
        assert pending._thread is not None and run.sched.lane is not None  # beside, in a helper process
        checks, nb2 = pending.result()
    finally:
        run.close()
    assert checks == serial and np.array_equal(nb, nb2)
    assert [np.float64(c.minimum).tobytes() for c in checks] == [np.float64(c.minimum).tobytes() for c in serial]
    # below the size that hides a helper's start-up the check runs at once, in this process
    small = _two_core_run()
    try:
        assert bound_stage._start_check(p, data, _Log(False), None, small, 1)._thread is None
        assert small.sched.lane is None
    finally:
        small.close()


def test_a_refused_assumption_beside_the_bound_stage_says_the_same_and_stops_it_early():
    p = _problem(rkhs_bound=0.5)
    data = bound_stage._residual_data(p)
    with pytest.raises(AssumptionError) as serial:
        bound_stage._check_assumption(p, data, _Log(False))
    run = _two_core_run()
    try:
        pending = bound_stage._start_check(p, data, _Log(False), None, run, parallel.SIDE_MIN_CELL_MODES)
        deadline = time.monotonic() + 120
        while not pending.done() and time.monotonic() < deadline:  # the bound stage's loop polls like this
            pending.raise_if_refused()  # never raises before the check has ended
            time.sleep(0.05)
        with pytest.raises(AssumptionError) as beside:
            pending.raise_if_refused()
    finally:
        run.close()
    assert str(beside.value) == str(serial.value)


# ---------------------------------------------------------------------------------------------- a whole run
def _arrays(result) -> dict:
    return {"p_low": result.p_low.tobytes(), "p_up": result.p_up.tobytes(), "error": result.error.tobytes(),
            "strategy": np.asarray(result.synthesis.strategy).tobytes(), "classes": result.classes.tolist(),
            "min_norm": [np.float64(c["minimum"]).tobytes() for c in result.diagnostics["assumption"]["min_norm"]]}


def test_a_run_with_the_side_lane_gives_the_one_core_result(monkeypatch):
    from robust_imdp.pipeline.run import synthesize_from_data

    p = _problem()
    one = synthesize_from_data(p, progress=False, workers=1, advice=False, margins=False)
    monkeypatch.setattr(parallel, "SIDE_MIN_CELL_MODES", 0)
    monkeypatch.setattr(parallel, "local_cores", lambda: 2)
    lanes = []
    original = parallel.InProcess.use_side_lane

    def spy(self):
        out = original(self)
        lanes.append(self.lane)
        return out

    monkeypatch.setattr(parallel.InProcess, "use_side_lane", spy)
    from robust_imdp.pipeline import nominal_stage

    pending = []
    start = nominal_stage.start_nominal
    monkeypatch.setattr(nominal_stage, "start_nominal", lambda *a: pending.append(start(*a)) or pending[-1])
    beside = synthesize_from_data(p, progress=False, advice=False, margins=False)
    assert lanes and lanes[0] is not None  # the check ran in a helper
    assert pending and pending[0] is not None and pending[0].future.done()  # so did the nominal model
    assert _arrays(beside) == _arrays(one)
    # the strategy above ranks modes of equal robust value by the nominal model: the one built beside must be
    # the one built in process, bit for bit
    nominal_one = nominal_stage.nominal_model(p, one.partition)
    nominal_beside = pending[0].future.result()
    for name in ("state_ptr", "row_ptr", "col", "lower", "upper", "floor", "actions"):
        assert getattr(nominal_one, name).tobytes() == getattr(nominal_beside, name).tobytes(), name
    with pytest.raises(AssumptionError) as refused_beside:
        synthesize_from_data(_problem(rkhs_bound=0.5), progress=False, advice=False, margins=False)
    with pytest.raises(AssumptionError) as refused_one:
        synthesize_from_data(_problem(rkhs_bound=0.5), progress=False, workers=1, advice=False, margins=False)
    assert str(refused_beside.value) == str(refused_one.value)


# ---------------------------------------------------------------------------------------------- the figures
_DRIVER = """
import json, sys
from robust_imdp.pipeline import parallel
parallel.SIDE_MIN_CELL_MODES = 0
parallel.local_cores = lambda: 2
from robust_imdp.cli import main
rc = main(sys.argv[1:])
print(json.dumps({"rc": rc, "matplotlib": "matplotlib" in sys.modules, "cvxpy": "cvxpy" in sys.modules}))
"""


def test_the_command_line_draws_the_figures_in_helpers_with_the_same_bytes(tmp_path):
    src = ROOT / "examples" / "problems"
    shutil.copy(src / "three_mode_linear_data.csv", tmp_path)
    text = (src / "three_mode_linear.toml").read_text().replace("cell_size = [0.125, 0.125]", "cell_size = [0.5, 0.5]")
    (tmp_path / "p.toml").write_text(text)
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    out = {}
    for name, extra in (("beside", []), ("one", ["--workers", "1"])):
        p = subprocess.run([sys.executable, "-c", _DRIVER, "run", str(tmp_path / "p.toml"), "--out", str(tmp_path / name),
                            "--quiet", "--advice", "off", *extra], capture_output=True, text=True, env=env,
                           cwd=tmp_path, timeout=900)
        assert p.returncode == 0, p.stderr[-3000:]
        out[name] = json.loads(p.stdout.strip().splitlines()[-1])
    # with helpers the run's process imported neither back-end: the check and the figures ran beside it
    assert out["beside"] == {"rc": 0, "matplotlib": False, "cvxpy": False}
    assert out["one"]["rc"] == 0 and out["one"]["matplotlib"] and out["one"]["cvxpy"]
    pngs = sorted(f.name for f in (tmp_path / "one").glob("*.png"))
    assert "b_margin.png" in pngs and "classes.png" in pngs  # drawn after the run and at the solve
    assert sorted(f.name for f in (tmp_path / "beside").glob("*.png")) == pngs
    for f in pngs:
        assert (tmp_path / "beside" / f).read_bytes() == (tmp_path / "one" / f).read_bytes(), f
    assert (tmp_path / "beside" / "result.npz").exists() and not list((tmp_path / "beside").glob(".*"))


class _Unreadable:
    """Pickles in the helper, fails to unpickle here."""

    def __reduce__(self):
        return (_refuse, ())


def _refuse():
    raise ValueError("cannot be rebuilt here")


def _make_unreadable():
    return _Unreadable()


def test_an_answer_that_cannot_be_read_back_fails_its_task_and_keeps_the_helper(monkeypatch):
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).parent))  # the helper imports this module for the task
    with SideLane(1) as lane:
        with pytest.raises(SideLaneError, match="could not be read back"):
            lane.submit(_make_unreadable).result(timeout=60)
        assert lane.submit(math.factorial, 5).result(timeout=60) == 120  # the helper is still there


def test_an_imdp_goes_through_a_helper_and_comes_back_the_same_and_read_only():
    from robust_imdp.models.imdp import IMDP

    m = IMDP.from_dense(lower=[[[0.5, 0.3]], [[0.0, 1.0]]], upper=[[[0.7, 0.5]], [[0.0, 1.0]]])
    with SideLane(1) as lane:
        back = lane.submit(copy.copy, m)  # pickled there and back
        c = back.result(timeout=60)
    assert isinstance(c, IMDP) and (c.n_states, c.n_choices) == (m.n_states, m.n_choices)
    for name in IMDP.__slots__[2:]:
        assert getattr(c, name).tobytes() == getattr(m, name).tobytes(), name
    with pytest.raises(ValueError):
        c.upper[0] = 1.0
    with pytest.raises(AttributeError):
        c.n_states = 3


def test_a_task_the_helper_cannot_read_fails_and_keeps_the_helper():
    with SideLane(1) as lane:  # this test module is not importable in the helper
        with pytest.raises(SideLaneError, match="could not be read by the helper"):
            lane.submit(_make_unreadable).result(timeout=60)
        assert lane.submit(math.factorial, 5).result(timeout=60) == 120


def test_the_margins_beside_the_advice_give_the_one_core_margins(monkeypatch):
    """The margins start when the solve is done and run beside the advice (the helper takes whole factors and row
    chunks; this process, once the advice is done, solves, takes row chunks and whole factors still waiting):
    the same b_margin and counts, bit for bit, as one core."""
    from robust_imdp.pipeline import margins as margins_stage
    from robust_imdp.pipeline.run import synthesize_from_data

    p = _problem()
    one = synthesize_from_data(p, progress=False, workers=1, advice=True, margins=True)
    monkeypatch.setattr(parallel, "SIDE_MIN_CELL_MODES", 0)
    monkeypatch.setattr(parallel, "local_cores", lambda: 2)
    started = []
    start = margins_stage.start_margins
    monkeypatch.setattr(margins_stage, "start_margins", lambda *a: started.append(start(*a)) or started[-1])
    beside = synthesize_from_data(p, progress=False, advice=True, margins=True)
    assert started and started[0] is not None  # submitted to the lane beside the advice
    pending = started[0]
    assert pending.futures and all(f.done() for f in pending.futures)  # the helper took part
    assert sorted(pending.values) == list(range(len(margins_stage.bound_scales())))
    assert np.asarray(beside.b_margin).tobytes() == np.asarray(one.b_margin).tobytes()
    keep = ("scales", "kept_yes", "kept_no", "solved")
    assert {k: beside.margins[k] for k in keep} == {k: one.margins[k] for k in keep}
    assert _arrays(beside) == _arrays(one)


def test_a_large_task_to_a_helper_still_starting_does_not_hold_the_caller():
    """Tasks are pickled and written by the helper's sender thread: a task larger than the pipe's buffer, sent to a
    helper still importing its modules (which reads nothing until then), returns from submit at once; before, the
    run's thread waited there for the helper's start-up (about 1.3 s outside every stage). The answer comes when
    the helper is ready, and the payload arrives whole."""
    with SideLane(1, preload=("robust_imdp.pipeline.run", "robust_imdp.plotting")) as lane:
        t0 = time.perf_counter()
        fut = lane.submit(len, bytes(32_000_000))
        submitted = time.perf_counter() - t0
        assert fut.result(timeout=120) == 32_000_000
        answered = time.perf_counter() - t0
    # the helper's start-up (imports of the run and of matplotlib) takes the answer past the submit by far; 0.5 s
    # leaves room for a loaded machine's scheduling of this thread (the sender pickles, not submit)
    assert submitted < 0.5 and answered > submitted
