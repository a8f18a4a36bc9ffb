"""The run's nominal model (:mod:`robust_imdp.abstraction.nominal`): the dynamics the run believes, at a few
points of every cell, with the noise; the synthesis ranks the modes of equal robust value by it
(:mod:`robust_imdp.synthesis.ties`, README "What the controller does").

The dynamics: for known dynamics (``problem.known``) the known parts themselves; otherwise the data-fitted
function of the run (``pipeline.bound_stage._fitted``: the known part plus the kernel-ridge fit of the
residuals, per mode, or per mode and component with per-component assumptions), the same function the bound
diagnostics and the advice read. It is evaluated at :func:`~robust_imdp.abstraction.nominal.cell_points` of
every cell, on a grid through the separable kernel's lattice (``FittedModes.lattice``), elsewhere point by
point in blocks.
"""

from __future__ import annotations

import numpy as np

from robust_imdp.pipeline.bound_stage import _fitted, _residual_data
from robust_imdp.pipeline.problem import Problem

__all__ = ["nominal_dynamics", "nominal_images", "nominal_model", "run_nominal", "start_nominal", "MAX_NOMINAL_ENTRIES"]

#: Points evaluated at once by a dynamics without a lattice (memory only).
_BLOCK_POINTS = 1 << 15
#: The most listed entries of a joint nominal model (about 1 GB with its solve): beyond, fewer points per cell,
#: then the factored form of the centre (a grid), else no nominal model.
MAX_NOMINAL_ENTRIES = 30_000_000


class _KnownParts:
    """The known parts of every mode as one callable ``x (k, d) -> (n_modes, k, n)``."""

    def __init__(self, maps):
        self.maps = tuple(maps)

    def __call__(self, x):
        return np.stack([np.asarray(m(x), dtype=np.float64) for m in self.maps])


def nominal_dynamics(problem: Problem):
    """The dynamics of the nominal model: a callable ``x (k, d) -> (n_modes, k, n)`` (module docstring)."""
    if problem.known:
        return _KnownParts(problem.maps)
    return _fitted(problem, _residual_data(problem))


def nominal_images(problem: Problem, partition, dynamics=None, per_axis: int | None = None) -> np.ndarray:
    """The images of every cell's points under every mode: ``(n_modes, n_cells, per_axis ** d, d)``.

    Parameters
    ----------
    problem : Problem
    partition : Partition or BoxPartition
        The cells (the robust abstraction's, in its order).
    dynamics : callable, optional
        :func:`nominal_dynamics` of the problem (computed when not given).
    per_axis : int, optional
        Points per axis (default :func:`~robust_imdp.abstraction.nominal.points_per_axis` of the dimension).
    """
    from robust_imdp.abstraction.nominal import cell_points, points_per_axis
    from robust_imdp.models.geometry import Partition

    dynamics = nominal_dynamics(problem) if dynamics is None else dynamics
    d = partition.dim
    s = points_per_axis(d) if per_axis is None else int(per_axis)
    if isinstance(partition, Partition) and hasattr(dynamics, "lattice"):
        # the points of a grid's cells form a tensor grid: per axis s points in each interval
        f = (2.0 * np.arange(s) + 1.0) / (2.0 * s)
        axes = [(bp[:-1, None] + f[None, :] * np.diff(bp)[:, None]).reshape(-1) for bp in
                (np.asarray(b, float) for b in partition.breakpoints)]
        V = dynamics.lattice(axes)  # (M, n, n_0 s, ..., n_{d-1} s)
        M, n = V.shape[:2]
        V = V.reshape((M, n) + tuple(x for k in partition.shape for x in (k, s)))
        # (M, n, k_0, s, k_1, s, ...) -> (M, k_0, k_1, ..., s, s, ..., n): cells and points in C order
        order = (0,) + tuple(2 + 2 * j for j in range(d)) + tuple(3 + 2 * j for j in range(d)) + (1,)
        return np.ascontiguousarray(V.transpose(order).reshape(M, partition.n_cells, s ** d, n))
    pts = cell_points(partition, s).reshape(-1, d)
    out = [np.asarray(dynamics(pts[b:b + _BLOCK_POINTS]), dtype=np.float64)
           for b in range(0, pts.shape[0], _BLOCK_POINTS)]
    y = np.concatenate(out, axis=1)
    return y.reshape(y.shape[0], partition.n_cells, s ** d, y.shape[2])


def nominal_model(problem: Problem, partition, dynamics=None, per_axis: int | None = None):
    """The nominal model of ``partition`` for ``synthesis.core.synthesize(nominal=...)``: the joint mixture's
    IMDP (the robust IMDP's states and choices) with the most points per cell (up to ``per_axis``, default
    :func:`~robust_imdp.abstraction.nominal.points_per_axis`) within :data:`MAX_NOMINAL_ENTRIES`; beyond, the
    factored model of the centres on a grid (a ``FactoredIMDP``); None when neither fits."""
    from robust_imdp.abstraction.nominal import nominal_abstraction, points_per_axis, row_entries
    from robust_imdp.models.geometry import Partition

    M, N = len(problem.mode_names), partition.n_cells
    s = points_per_axis(partition.dim) if per_axis is None else int(per_axis)
    while s > 1 and M * N * row_entries(partition, problem.noise, s) > MAX_NOMINAL_ENTRIES:
        s -= 1
    if M * N * row_entries(partition, problem.noise, s) <= MAX_NOMINAL_ENTRIES:
        images = nominal_images(problem, partition, dynamics, per_axis=s)
        return nominal_abstraction(partition, images, problem.noise).imdp
    if not isinstance(partition, Partition):
        return None
    images = nominal_images(problem, partition, dynamics, per_axis=1)
    return nominal_abstraction(partition, images, problem.noise, form="factored")


def _nominal_task(problem: Problem, partition, *, threads=1):
    """:func:`nominal_model` as a side-lane task (a module-level function: it runs in a helper process)."""
    return nominal_model(problem, partition)


def _wanted(problem: Problem, partition, dfa) -> bool:
    """Whether the synthesis of this run will take a nominal model (``synthesis.ties.takes_nominal`` of the model
    the run is about to build, read from the problem before it exists: the form of the grid's abstraction
    (``Problem.form_choice``; refined cells are joint), the modes, the horizon and the reading)."""
    from robust_imdp.models.geometry import Partition
    from robust_imdp.spec.api import resolve_semantics

    form = problem.form_choice()[0] if isinstance(partition, Partition) else "joint"
    if form != "factored":
        return True
    return (len(problem.mode_names) > 1 and problem.horizon is None
            and resolve_semantics(dfa, problem.semantics)[0] != "safety")


class _Beside:
    """A nominal model computed in a side-lane helper process (:func:`start_nominal`): :meth:`result` waits for it
    and returns ``(True, model or None)``, or ``(False, None)`` when the lane could not run it (the caller then
    builds it in process); the task's own failure is raised."""

    def __init__(self, future):
        self.future = future

    def result(self) -> tuple:
        from robust_imdp.pipeline.parallel import SideLaneError

        try:
            return True, self.future.result()
        except SideLaneError:  # the lane is gone (a helper ended): built again in process
            return False, None


def start_nominal(problem: Problem, partition, dfa, run, log):
    """Start the run's nominal model beside the bound stage (in the side lane's helper process, one numba and
    BLAS thread: the same bits as in process, ``tests/test_side_lane.py``) where the run has one: on several local
    cores from ``parallel.SIDE_MIN_CELL_MODES`` (cell, mode) pairs on, when the synthesis will take one
    (:func:`_wanted`). Returns a pending model for :func:`run_nominal` (``beside=``), or None (built in process
    when the synthesis asks for it). The nominal model depends on the problem and the cells only, not on the
    bound stage: run beside it, its seconds leave the run's serial part (README, "Big problems")."""
    from robust_imdp.pipeline.parallel import SIDE_MIN_CELL_MODES, InProcess, SideLaneError

    if partition.n_cells * len(problem.mode_names) < SIDE_MIN_CELL_MODES or not _wanted(problem, partition, dfa):
        return None
    sched = run.scheduler(log)
    if not isinstance(sched, InProcess) or not sched.use_side_lane():
        return None
    try:
        return _Beside(sched.lane.submit(_nominal_task, problem, partition))
    except SideLaneError:
        return None


def run_nominal(problem: Problem, partition, log, dynamics=None, beside=None):
    """The run's stage ``nominal``: :func:`nominal_model` of ``partition``, timed, with a line when the run has
    none (too large). ``beside``: the pending model of :func:`start_nominal` (its stage time is the wait)."""
    with log.stage("nominal"):
        got, model = (False, None) if beside is None else beside.result()
        if not got:
            model = nominal_model(problem, partition, dynamics)
    if model is None:
        log.info(f"no nominal model: more than {MAX_NOMINAL_ENTRIES} entries; modes of equal robust value are "
                 "ranked by their optimistic value")
    return model
