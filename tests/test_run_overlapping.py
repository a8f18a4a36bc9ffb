"""``InProcess.run_overlapping``: the bound stage's chunks two at a time in one process on several cores.

Both tasks run at once (a barrier of two must pass), every result comes back once under its own index in task order,
a task's error reaches the caller and stops the tasks not yet started, one thread runs the plain loop in the caller's
thread, and schedulers without it (the base class, Dask) run the tasks as :meth:`Scheduler.run` does. That the bound
stage gives the same numbers this way is checked end to end in ``test_side_lane.py`` (a run on 2 threads against
one core) and here on one chunked grid.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from robust_imdp.pipeline import parallel
from robust_imdp.pipeline.parallel import InProcess, Scheduler


def _square(x, *, threads, offset=0):
    return x * x + offset, threads, threading.current_thread().name


def test_results_in_task_order_each_once_with_the_tasks_threads():
    out = list(InProcess(threads=2).run_overlapping(_square, [(i,) for i in range(7)], {"offset": 1}))
    assert [i for i, _ in out] == list(range(7))
    assert [r[0] for _, r in out] == [i * i + 1 for i in range(7)]
    assert {r[1] for _, r in out} == {2}  # every task gets the scheduler's numba threads
    assert all(r[2] != threading.current_thread().name for _, r in out)  # run beside the caller


def test_two_tasks_run_at_the_same_time():
    barrier = threading.Barrier(2, timeout=20)  # broken (an error) if the second task waits for the first

    def meet(i, *, threads):
        if i < 2:
            barrier.wait()
        return i

    assert [r for _, r in InProcess(threads=2).run_overlapping(meet, [(i,) for i in range(4)])] == [0, 1, 2, 3]


def test_an_error_reaches_the_caller_and_stops_the_tasks_not_started():
    started = []
    lock = threading.Lock()

    def task(i, *, threads):
        with lock:
            started.append(i)
        if i == 1:
            raise ValueError("task 1 failed")
        return i

    got = []
    with pytest.raises(ValueError, match="task 1 failed"):
        for i, r in InProcess(threads=2).run_overlapping(task, [(i,) for i in range(40)]):
            got.append(r)
    assert got == [0]
    assert len(started) <= 4  # at most two in flight when the error came back, none started after it


def test_one_thread_is_the_plain_loop_in_the_callers_thread():
    out = list(InProcess(threads=1).run_overlapping(_square, [(i,) for i in range(3)]))
    assert [r[2] for _, r in out] == [threading.current_thread().name] * 3


def test_other_schedulers_run_the_tasks_as_run_does():
    class Loop(Scheduler):
        def run(self, fn, args, kwargs=None):
            for i, a in enumerate(args):
                yield i, fn(*a, threads=1, **(kwargs or {}))

    assert list(Loop().run_overlapping(_square, [(2,), (3,)])) == [(0, (4, 1, threading.current_thread().name)),
                                                                   (1, (9, 1, threading.current_thread().name))]


def test_the_bound_stage_overlapped_gives_the_one_at_a_time_numbers(monkeypatch):
    # the local-weights route (pieces of eq. C beside the kernel) and the all-points route, chunks two at a time
    # against one at a time on the same scheduler
    from robust_imdp.bounds import rkhs_local
    from robust_imdp.pipeline import bound_rkhs

    rng = np.random.default_rng(3)  # seeded data
    d, m = 2, 120
    X = rng.uniform(-1.5, 1.5, (m, d))
    Y = np.column_stack([np.sin(2 * X[:, 0]), X[:, 1] ** 2]) + rng.uniform(-0.01, 0.01, (m, 2))
    g = np.linspace(-1.5, 1.5, 13)
    lo = np.array([[a, b] for a in g[:-1] for b in g[:-1]])
    up = lo + (g[1] - g[0])
    monkeypatch.setattr(rkhs_local, "PIECE_BLOCKS", 2)
    kw = dict(lengthscale=0.7, rkhs_bound=2.0, noise_bound=0.01, misspecification=1e-3, method="optimal")
    for local in (None, (12, None)):
        args = [(X, Y, np.eye(2), np.zeros(2), lo[s:s + 48], up[s:s + 48], local) for s in range(0, lo.shape[0], 48)]
        sched = InProcess(threads=2)
        one = [r for _, r in sched.run(bound_rkhs._bound_task, args, kw)]
        two = [r for _, r in sched.run_overlapping(bound_rkhs._bound_task, args, kw)]
        assert len(one) == len(two) == 3
        for a, b in zip(one, two):
            for key in ("lower", "upper", "eps", "support"):
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
