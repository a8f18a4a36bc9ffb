"""The assumption check runs on the run's scheduler, one task per mode and component, with the same
checks (bit for bit) and the same refusal as in this process."""

from __future__ import annotations

import numpy as np
import pytest

from robust_imdp.bounds.rkhs_check import norm_task
from robust_imdp.casestudies.systems import get_case_study
from robust_imdp.errors import AssumptionError
from robust_imdp.models.noise import TruncatedGaussianNoise
from robust_imdp.models.system import AffineMap, Dataset
from robust_imdp.pipeline import bound_stage
from robust_imdp.pipeline.parallel import InProcess
from robust_imdp.pipeline.problem import Problem
from robust_imdp.pipeline.runtime import _Log, _Run

CASE = get_case_study("three_mode_linear")


def _problem(**kw):
    sysm = CASE.system
    x, u, xn = sysm.sample_dataset(30, CASE.lower, CASE.upper, rng=5)
    base = dict(space_lower=np.array(CASE.lower), space_upper=np.array(CASE.upper), cell_size=np.array([1.0, 1.0]),
                regions=CASE.regions, formula="G !obs & F des", threshold=0.9, horizon=None,
                data=Dataset(x, u, xn, modes=sysm.mode_names), mode_names=sysm.mode_names,
                maps=tuple(AffineMap.zero(2) for _ in range(3)),
                noise=TruncatedGaussianNoise(sysm.sigma, sysm.bound), rkhs_bound=CASE.rkhs_bound,
                gp_options={"lengthscale": 2.0}, misspecification=CASE.misspecification)
    base.update(kw)
    return Problem(**base)


class _Recording(InProcess):
    """In process, recording each task's function (and running them in reverse order: the caller must
    put the results back in the jobs' order)."""

    def __init__(self):
        super().__init__(threads=1)
        self.calls = []

    def run(self, fn, args, kwargs=None):
        self.calls.append((fn, len(args)))
        for i in reversed(range(len(args))):
            yield i, fn(*args[i], threads=1, **dict(kwargs or {}))


class _RunWith(_Run):
    def __init__(self, sched):
        super().__init__(workers=1)
        self.sched = sched


@pytest.mark.parametrize("kw", [{}, {"rkhs_bound": {"1": [6.0, 5.0], "2": [6.0, 6.0], "3": [5.5, 6.0]}}],
                         ids=["one_setting", "per_component"])
def test_the_check_runs_one_task_per_mode_and_component_with_the_same_checks(kw):
    p = _problem(**kw)
    data = bound_stage._residual_data(p)
    serial, nb = bound_stage._check_assumption(p, data, _Log(False))
    sched = _Recording()
    tasks, nb2 = bound_stage._check_assumption(p, data, _Log(False), None, _RunWith(sched))
    assert sched.calls == [(norm_task, 6)]  # 3 modes x 2 components
    assert tasks == serial and np.array_equal(nb, nb2)
    assert [np.float64(c.minimum).tobytes() for c in tasks] == [np.float64(c.minimum).tobytes() for c in serial]


def test_a_refused_assumption_says_the_same_on_the_scheduler():
    p = _problem(rkhs_bound=0.5)
    data = bound_stage._residual_data(p)
    with pytest.raises(AssumptionError) as serial:
        bound_stage._check_assumption(p, data, _Log(False))
    with pytest.raises(AssumptionError) as tasks:
        bound_stage._check_assumption(p, data, _Log(False), None, _RunWith(_Recording()))
    assert str(tasks.value) == str(serial.value)
