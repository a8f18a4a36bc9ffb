"""The run's assumption-margins stage (docs/margins.md): per cell, the largest factor of B at which it keeps its class.

The bound stage certifies, besides the image boxes at B, the boxes at every factor of
``synthesis.margins.MARGIN_SCALES`` with the same certificate weights (``bounds/rkhs_model.scaled_ranges``;
nothing is optimised again). This stage gets those boxes (from the bound stage of this run, else from the
cache, else by running the bound stage once more with them), abstracts them through the pipeline's own
abstraction function (the one the run used, so ``[abstraction]`` options such as ``transitions`` apply),
evaluates the run's controller on each (``synthesis.margins.strategy_bounds``) and stops when no cell
keeps its class (``synthesis.margins.assumption_margins``). Where the run has several cores (a Dask cluster, or
in process with the side lane's helper processes) every factor's abstraction and evaluation is one task
(:func:`_margin_task`) and they run side by side (``pipeline.advice_stage.spread``), all started when the first
factor is asked for; the results are the same bits as one after the other.

Refined results (``BoxPartition``): a cell created by refinement uses the boxes the refinement's bounder
certified for it at each factor when this run bounded it, else those of its grid cell (it lies inside it,
so the grid cell's box at ``beta B`` contains its image: sound, looser; its margin is then a lower bound).
"""

from __future__ import annotations

from concurrent.futures import CancelledError
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robust_imdp.pipeline.advice_stage import side_by_side, spread
from robust_imdp.pipeline.cache import _load_npz, _savez, bounds_key, read_cache_entry, write_cache_entry
from robust_imdp.pipeline.problem import Problem
from robust_imdp.pipeline.runtime import _Log, _Run

__all__ = ["skip_reason", "bound_scales", "run_margins", "start_margins", "PendingMargins"]


def bound_scales() -> tuple:
    """The factors of B the bound stage certifies besides B itself (``MARGIN_SCALES`` without 1)."""
    from robust_imdp.synthesis.margins import MARGIN_SCALES

    return tuple(float(s) for s in MARGIN_SCALES[1:])


def skip_reason(problem: Problem) -> str | None:
    """Why this problem gets no margins, or None: known dynamics have no B; a method without re-usable
    certificate weights (the GP route) has none to re-evaluate."""
    if getattr(problem, "known", False):  # Problem.known: every component known (no data)
        return "known dynamics: every component is known (rkhs_bound = 0), there is no B to scale"
    if not problem.method.margins:
        return (f"error_bound '{problem.error_bound}' bounds g with a GP posterior and Chowdhury & Gopalan's beta; "
                "its boxes have no certificate weights to re-evaluate at a larger B (margins are computed on the "
                "RKHS route, error_bound 'optimal' or 'ridge')")
    return None


def _cache_file(problem: Problem, cache_dir) -> Path | None:
    return None if cache_dir is None else Path(cache_dir) / f"scaled-{bounds_key(problem)}.npz"


def _read_scaled(path: Path, scales, shape):
    """``(scales, lower, upper)`` of a saved entry holding exactly ``scales`` and boxes of ``shape`` (else ValueError)."""
    z = _load_npz(path)
    if not np.array_equal(np.asarray(z["scales"], float), np.asarray(scales, float)):
        raise ValueError(f"scales {z['scales'].tolist()} are not {list(scales)}")
    for key in ("lower", "upper"):
        if z[key].shape != (len(scales),) + tuple(shape):
            raise ValueError(f"{key} must have shape {(len(scales),) + tuple(shape)}; got {z[key].shape}")
    return tuple(scales), z["lower"], z["upper"]


def _scaled_bounds(problem: Problem, grid, log: _Log, run: _Run, cache_dir, learn_and_bound):
    """``(scales, lower, upper)``, each box array ``(n_scales, n_modes, n_grid_cells, n)``: from this run's bound
    stage, the cache, or the bound stage run again with the scales (once: saved in the cache)."""
    scales = bound_scales()
    shape = (len(problem.mode_names), grid.n_cells, int(np.size(problem.space_lower)))
    path = _cache_file(problem, cache_dir)
    got = getattr(run, "scaled_bounds", None)
    if got is not None and tuple(got[0]) == scales:
        if path is not None:
            write_cache_entry(path, lambda tmp: _savez(tmp, {"scales": np.asarray(scales), "lower": got[1],
                                                             "upper": got[2]}))
        return got
    if path is not None:
        got = read_cache_entry(path, lambda f: _read_scaled(f, scales, shape))
        if got is not None:
            log.info(f"margins: reused the boxes at {', '.join(f'{s:g}' for s in scales)} x B ({path.name})")
            return got
    log.info("margins: the learned cell bounds were reused from a cache written without the boxes at larger B; "
             "bounding the grid again with them (once: they are saved in the cache)")
    run.margin_scales = scales
    learn_and_bound(problem, grid, log, run, cache_dir)
    got = run.scaled_bounds
    if path is not None:
        write_cache_entry(path, lambda tmp: _savez(tmp, {"scales": np.asarray(scales), "lower": got[1],
                                                         "upper": got[2]}))
    return got


def _cell_boxes(partition, lower, upper, new_cells: dict):
    """The boxes of ``partition``'s cells at every factor ``(n_scales, n_modes, n_cells, n)`` from the grid's:
    the grid's own for an unrefined partition; for a ``BoxPartition``, a refined cell's own certified boxes
    (``new_cells``, keyed by its bounds) where the run bounded it, else its grid cell's (a superset: sound).
    Returns the boxes and the number of refined cells that fell back to their grid cell."""
    base_cell = getattr(partition, "base_cell", None)
    if base_cell is None:
        return lower, upper, 0
    base_cell = np.asarray(base_cell, dtype=np.int64)
    lo, hi = lower[:, :, base_cell].copy(), upper[:, :, base_cell].copy()
    refined = np.flatnonzero(np.asarray(partition.depth) > 0)
    fallback = 0
    for q in refined:
        key = (partition.cells_lower[q].tobytes(), partition.cells_upper[q].tobytes())
        own = new_cells.get(key)
        if own is None:
            fallback += 1
        else:
            lo[:, :, q], hi[:, :, q] = own
    return lo, hi, fallback


@dataclass(frozen=True)
class _Controller:
    """What :func:`robust_imdp.synthesis.margins.strategy_bounds` reads of the run's synthesis (sent to helpers)."""

    strategy: np.ndarray
    horizon: int | None
    precision: float
    semantics: str


def _abstraction_form(problem: Problem, partition) -> str:
    """The form of the run's abstraction of ``partition`` (``pipeline.run._form_of``): the problem's choice on a
    grid, joint on refined cells."""
    from robust_imdp.models.geometry import Partition

    return problem.form_choice()[0] if isinstance(partition, Partition) else "joint"


def _factor_args(problem: Problem, partition, synthesis, lower, upper, dfa) -> list:
    """The arguments of :func:`_margin_task` for every factor (``lower`` / ``upper``: ``(n_scales, n_modes, n_cells,
    n)``): the run's form and abstraction options, its controller as a picklable :class:`_Controller`."""
    ctrl = _Controller(np.asarray(synthesis.strategy), synthesis.horizon, float(synthesis.precision),
                       getattr(synthesis, "semantics", "reach"))
    form = _abstraction_form(problem, partition)
    return [(partition, lower[j], upper[j], problem.noise, form, problem.abstraction_options(), dfa, ctrl)
            for j in range(len(lower))]


def _margin_task(partition, lower, upper, noise, form, options, dfa, controller, *, threads=1):
    """One factor of the margins (a module-level function: it runs in helper processes and on workers): the
    abstraction of ``partition`` with the boxes ``lower``/``upper`` (n_modes, n_cells, n) in the run's ``form``
    (all cells in one chunk: the rows do not depend on the chunking, tests/test_chunks.py) and the bounds
    ``(p_low, p_up)`` of the run's controller on it (``synthesis.margins.strategy_bounds``)."""
    from robust_imdp.abstraction.cell_bounds import CellBounds
    from robust_imdp.abstraction.factored import abstraction_model
    from robust_imdp.synthesis.margins import strategy_bounds

    cb = CellBounds(lower, upper, None)
    if form == "factored":
        from robust_imdp.abstraction.factored import AXIS_TOL, assemble_factored, axis_lengths, factored_rows

        k = axis_lengths(partition, cb, noise)
        abstraction = assemble_factored(partition, [factored_rows(partition, cb, noise, k, tol=AXIS_TOL)])
    else:
        from robust_imdp.abstraction.rows import abstract_rows, assemble_abstraction

        abstraction = assemble_abstraction(partition, [abstract_rows(partition, cb, noise, None, **options)])
    return strategy_bounds(abstraction_model(abstraction), partition.labels, partition.atoms, dfa, controller,
                           outside_state=partition.outside_state)


class PendingMargins:
    """Every factor's task of the margins submitted to the side lane's helpers (:func:`start_margins`), to run
    beside the advice; :func:`run_margins` (``pending=``) reads them."""

    def __init__(self, scales, futures: list, args: list):
        self.scales, self.futures, self.args = tuple(scales), futures, args
        self.local: dict = {}  # factor -> its value, computed in this process

    def take_back(self) -> None:
        """Run here, last first, the factors still waiting in the lane (its helpers busy with the first ones or with
        other side work), so that this process, done with the advice, shares the rest."""
        for j in reversed(range(len(self.futures))):
            if j not in self.local and self.futures[j].cancel():
                self.local[j] = _margin_task(*self.args[j])

    def value(self, j: int):
        """Factor ``j``'s ``(p_low, p_up)``: the helper's answer, or computed here (taken back, or the lane could not
        run it: the same task, the same bits)."""
        from robust_imdp.pipeline.parallel import SideLaneError

        if j in self.local:
            return self.local[j]
        try:
            return self.futures[j].result()
        except (SideLaneError, CancelledError):
            self.local[j] = _margin_task(*self.args[j])
            return self.local[j]

    def cancel(self) -> None:
        for f in self.futures:
            f.cancel()


def start_margins(problem: Problem, grid, synthesis, classes, dfa, log: _Log, run: _Run, cache_dir):
    """Submit the margins' factors of an unrefined run to the side lane's helper processes, so that they run beside
    the advice (the advice keeps this process's cores, as on one core, so its time budget and the levers it
    estimates are those of the run without margins beside it); None where the run has no lane (one core, a
    Dask cluster, a problem below ``parallel.SIDE_MIN_CELL_MODES`` pairs), has no margins, or the boxes at the
    larger factors are not at hand (from the cache: :func:`run_margins` bounds them)."""
    from robust_imdp.pipeline.parallel import SIDE_MIN_CELL_MODES, InProcess, SideLaneError

    if skip_reason(problem) is not None or grid.n_cells * len(problem.mode_names) < SIDE_MIN_CELL_MODES:
        return None
    got = getattr(run, "scaled_bounds", None)
    if got is None or tuple(got[0]) != bound_scales():
        return None
    sched = run.scheduler(log)
    if not isinstance(sched, InProcess) or not sched.use_side_lane():
        return None
    scales, lower, upper = got
    args = _factor_args(problem, grid, synthesis, lower, upper, dfa)
    futures = []
    try:
        for a in args:
            futures.append(sched.lane.submit(_margin_task, *a))
    except SideLaneError:
        for f in futures:
            f.cancel()
        return None
    return PendingMargins(scales, futures, args)


def run_margins(problem: Problem, grid, partition, synthesis, classes, dfa, log: _Log, run: _Run, cache_dir, *,
                abstract, learn_and_bound, pending: "PendingMargins | None" = None) -> tuple:
    """The margins of a run: ``(b_margin (n_cells,) float array or None, Result.margins' dict)``.

    Parameters
    ----------
    problem : Problem
    grid : geometry.Partition
        The grid the bound stage bounded.
    partition : geometry.Partition or BoxPartition
        The result's cells (``grid``, or the refined partition).
    synthesis : synthesis.core.SynthesisResult
        The run's solve on ``partition`` (its controller is evaluated at every factor).
    classes : (n_cells,) str array
    dfa : DFA
    log, run, cache_dir
        The run's log, scheduler options and cache directory.
    abstract : callable(partition, cell_bounds) -> abstraction
        The pipeline's abstraction function (the run's options).
    learn_and_bound : callable(problem, partition, log, run, cache_dir)
        The run's bound stage (used only when no boxes at larger B are at hand).
    pending : PendingMargins, optional
        The factors :func:`start_margins` submitted beside the advice (an unrefined run: ``partition`` is
        ``grid``); the stage then waits for their answers.

    Returns
    -------
    b_margin : (n_cells,) float array (NaN for Q_? cells) or None when skipped
    doc : dict
        ``Result.margins``: ``synthesis.margins.Margins.to_dict()`` plus ``statement`` and, for a refined
        partition, ``refined_from_grid_cell``; or ``{"skipped": reason}``.
    """
    from robust_imdp.abstraction.cell_bounds import CellBounds
    from robust_imdp.abstraction.factored import abstraction_model
    from robust_imdp.synthesis.margins import assumption_margins, strategy_bounds

    why = skip_reason(problem)
    if why is not None:
        log.info(f"assumption margins: not computed ({why})")
        return None, {"skipped": why}
    with log.stage("margins"):
        if pending is not None:  # submitted beside the advice: read the helpers' answers
            _scaled_bounds(problem, grid, log, run, cache_dir, learn_and_bound)  # the run's, saved in the cache
            pending.take_back()
            index = {s: j for j, s in enumerate(pending.scales)}
            margins = assumption_margins(classes, lambda scale: pending.value(index[float(scale)]),
                                         problem.threshold, (1.0,) + pending.scales)
            pending.cancel()  # factors past the last one read are not needed
            return _margins_result(margins, 0, log)
        scales, lower, upper = _scaled_bounds(problem, grid, log, run, cache_dir, learn_and_bound)
        lower, upper, fallback = _cell_boxes(partition, lower, upper, getattr(run, "scaled_new_cells", {}))
        index = {s: j for j, s in enumerate(scales)}
        sched = run.scheduler(log)
        if side_by_side(sched, partition.n_cells * len(problem.mode_names)):
            # every factor's abstraction and evaluation is a task, side by side on every core (advice_stage.spread):
            # the first factor asked for starts them all, the results are the same bits as one after the other
            done: dict = {}

            def evaluate(scale):
                if not done:
                    args = _factor_args(problem, partition, synthesis, lower, upper, dfa)
                    done.update(spread(sched, _margin_task, args))
                return done[index[float(scale)]]
        else:
            def evaluate(scale):
                j = index[float(scale)]
                abstraction = abstract(partition, CellBounds(lower[j], upper[j], None))  # the run's form
                return strategy_bounds(abstraction_model(abstraction), partition.labels, partition.atoms, dfa,
                                       synthesis, outside_state=partition.outside_state)

        margins = assumption_margins(classes, evaluate, problem.threshold, (1.0,) + tuple(scales))
    return _margins_result(margins, fallback, log)


def _margins_result(margins, fallback: int, log: _Log) -> tuple:
    """:func:`run_margins`' return value from ``synthesis.margins.assumption_margins``' margins (and its line)."""
    doc = margins.to_dict()
    doc["statement"] = ("b_margin: per cell the largest factor beta of (1, 1.25, 1.5, 2, 3, 4) such that the run's "
                        "controller keeps the cell's class (Q_yes: p_low >= threshold; Q_no: p_up < threshold) with "
                        "every rkhs_bound B replaced by beta B (known components stay known), at that factor and "
                        "every smaller one; null for Q_? cells")
    if fallback:
        doc["refined_from_grid_cell"] = int(fallback)
    from robust_imdp.synthesis.margins import margins_line

    log.info(margins_line(doc) + f" ({margins.seconds:.1f} s, {len(margins.solved)} abstractions solved)")
    return margins.b_margin, doc
