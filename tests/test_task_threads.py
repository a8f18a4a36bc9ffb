"""In process, a task's numba threads leave a core to every side-lane helper that runs a task
(``pipeline.parallel.InProcess.task_threads``), and the caller's numba setting is the same after the task."""

from __future__ import annotations

import numba
import pytest

from robust_imdp.pipeline.parallel import InProcess


class _Lane:
    def __init__(self, busy):
        self.n = busy

    def busy(self):
        return self.n


def _task(x, *, threads):
    numba.set_num_threads(threads)  # as rkhs.bound_chunk does
    return x, threads, numba.get_num_threads()


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs 2 numba threads")
@pytest.mark.parametrize("busy, expected", [(0, 2), (1, 1), (3, 1)])
def test_tasks_leave_a_core_to_each_busy_helper(busy, expected):
    sched = InProcess(threads=2)
    sched.lane = _Lane(busy)
    numba.set_num_threads(2)
    out = list(sched.run(_task, [(7,), (8,)]))
    assert [r[1][:2] for r in out] == [(7, expected), (8, expected)]
    assert [r[1][2] for r in out] == [expected, expected]  # the task ran on that many threads
    assert numba.get_num_threads() == 2  # and the caller's setting is back


def test_without_a_lane_every_task_gets_the_threads():
    sched = InProcess(threads=3)
    assert sched.task_threads() == 3
    assert InProcess(threads=1).task_threads() == 1
