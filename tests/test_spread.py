"""The margins' and the advice's re-solves side by side (pipeline.advice_stage.spread: this process and the side
lane's helpers taking tasks from one queue) give the results of one after the other, bit for bit.

The run is the coarse three-mode study (64 cells), with the side lane forced on (its threshold set to 0) on
two cores, against the same run on one core (``workers=1``: everything in order in this process)."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from robust_imdp.pipeline import advice_stage, margins as margins_mod, parallel
from robust_imdp.pipeline.parallel import InProcess, SideLane

ROOT = Path(__file__).resolve().parents[1]


def _problem():
    from robust_imdp.io.files import load_problem

    p = load_problem(ROOT / "examples" / "problems" / "three_mode_linear.toml")
    return dataclasses.replace(p, cell_size=np.array([0.5, 0.5]))


def _run(workers, monkeypatch=None):
    from robust_imdp.pipeline.run import synthesize_from_data

    return synthesize_from_data(_problem(), progress=False, advice=True, margins=True, workers=workers)


def _levers(result):
    return {lv["name"]: lv.get("share") for lv in result.advice.get("levers", [])}


def test_margins_and_advice_side_by_side_equal_one_core(monkeypatch):
    calls = []
    real = advice_stage.spread

    def counting(sched, fn, args, kwargs=None):
        calls.append((fn.__name__, isinstance(sched, InProcess) and sched.lane is not None, len(args)))
        return real(sched, fn, args, kwargs)

    one = _run(1)
    assert not calls  # one core: no side lane, the re-solves one after the other as before
    monkeypatch.setattr(parallel, "SIDE_MIN_CELL_MODES", 0)
    monkeypatch.setattr(parallel, "local_cores", lambda: 2)
    monkeypatch.setattr(advice_stage, "spread", counting)
    monkeypatch.setattr(margins_mod, "spread", counting)
    started = []
    start = margins_mod.start_margins
    monkeypatch.setattr(margins_mod, "start_margins", lambda *a: started.append(start(*a)) or started[-1])
    two = _run(None)
    # the advice's re-solves went side by side through a lane; the margins' factors were submitted to it beside
    # the advice (pipeline.margins.start_margins), not through spread
    assert {c[0] for c in calls} <= {"_job_task", "_rows_task"} and calls and all(c[1] for c in calls)
    assert started and started[0] is not None and all(f.done() for f in started[0].futures)
    assert np.array_equal(one.b_margin, two.b_margin, equal_nan=True)
    for key in ("scales", "kept_yes", "kept_no", "solved"):
        assert one.margins[key] == two.margins[key]
    assert _levers(one) and _levers(one) == _levers(two)
    for name in ("p_low", "p_up", "strategy"):
        assert np.array_equal(getattr(one.synthesis, name), getattr(two.synthesis, name))


def _partition_and_boxes():
    from robust_imdp.models.geometry import Box, Partition

    part = Partition(Box([0.0, 0.0], [2.0, 2.0]), [0.5, 0.5], {"goal": [Box([1.5, 1.5], [2.0, 2.0])]})
    rng = np.random.default_rng(3)
    lo = part.cells_lower[None] + rng.uniform(-0.1, 0.1, (2, part.n_cells, 2))
    return part, lo, lo + rng.uniform(0.05, 0.3, (2, part.n_cells, 2))


def test_spread_order_errors_and_close():
    """spread yields every task once with its index (results as from a plain loop), raises a task's exception,
    and after close() starts nothing more."""
    from robust_imdp.models.noise import UniformNoise
    from robust_imdp.spec.api import to_dfa

    part, lo, up = _partition_and_boxes()
    dfa = to_dfa("F goal", part.atoms)
    ctrl = margins_mod._Controller(np.zeros((part.n_cells, dfa.n_states), dtype=np.int64), None, 1e-8, "reach")
    noise = UniformNoise([0.05, 0.05])
    args = [(part, lo * (1 + 0.01 * i), up * (1 + 0.01 * i), noise, "joint", {}, dfa, ctrl) for i in range(5)]
    plain = [margins_mod._margin_task(*a) for a in args]
    sched = InProcess(threads=2)
    threads_only = dict(advice_stage.spread(sched, margins_mod._margin_task, args))  # no lane: two threads here
    for i, (p_low, p_up) in enumerate(plain):
        assert np.array_equal(threads_only[i][0], p_low) and np.array_equal(threads_only[i][1], p_up)
    with SideLane(1) as lane:
        sched.lane = lane
        got = dict(advice_stage.spread(sched, margins_mod._margin_task, args))
        assert sorted(got) == list(range(5))
        for i, (p_low, p_up) in enumerate(plain):
            assert np.array_equal(got[i][0], p_low) and np.array_equal(got[i][1], p_up)
        bad = args[:2] + [(part, lo, up[:, :3], noise, "joint", {}, dfa, ctrl)]  # boxes of the wrong shape
        with pytest.raises(Exception):
            list(advice_stage.spread(sched, margins_mod._margin_task, bad))
        stream = advice_stage.spread(sched, margins_mod._margin_task, args)
        next(stream)
        stream.close()
        sched.lane = None
    assert math.isfinite(float(np.sum(plain[0][0])))


def test_spread_takes_back_tasks_waiting_behind_other_side_work():
    """With the lane's only helper busy (other side work: here a 30 s sleep), the tasks sent to it are cancelled
    there and run in this process: spread ends long before the helper is free."""
    from robust_imdp.models.noise import UniformNoise
    from robust_imdp.spec.api import to_dfa

    part, lo, up = _partition_and_boxes()
    dfa = to_dfa("F goal", part.atoms)
    ctrl = margins_mod._Controller(np.zeros((part.n_cells, dfa.n_states), dtype=np.int64), None, 1e-8, "reach")
    args = [(part, lo, up * (1 + 0.01 * i), UniformNoise([0.05, 0.05]), "joint", {}, dfa, ctrl) for i in range(3)]
    sched = InProcess(threads=2)
    with SideLane(1) as lane:
        busy = lane.submit("time:sleep", 30.0)
        sched.lane = lane
        got = dict(advice_stage.spread(sched, margins_mod._margin_task, args))
        assert sorted(got) == [0, 1, 2] and not busy.done()
        sched.lane = None
