"""The run's assumption-margins stage (docs/margins.md): per cell, the largest factor of B at which it keeps its class.

The bound stage certifies, besides the image boxes at B, the boxes at every factor of
``synthesis.margins.MARGIN_SCALES`` with the same certificate weights (``bounds/rkhs_model.scaled_ranges``;
nothing is optimised again). This stage gets those boxes (from the bound stage of this run, else from the
cache, else by running the bound stage once more with them), abstracts them through the pipeline's own
abstraction function (the one the run used, so ``[abstraction]`` options such as ``transitions`` apply),
evaluates the run's controller on each (``synthesis.margins.strategy_bounds``) and stops when no cell
keeps its class (``synthesis.margins.assumption_margins``). In process with the side lane's helper processes the
margins start beside the advice (:func:`start_margins`, :class:`PendingMargins`: whole factors in the helpers,
row chunks wherever a core is free, docs/margins.md "On several cores"); on a Dask cluster (or a refined run on
several cores) every factor's abstraction and evaluation is one task (:func:`_margin_task`) and they run side
by side (``pipeline.advice_stage.spread``), all started when the first factor is asked for. The results are
the same bits as one after the other.

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
from robust_imdp.pipeline.runtime import MAX_ROW_CELLS, _Log, _Run

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


def _save_scaled(path: Path, boxes) -> None:
    """Save ``(scales, lower, upper)`` as the cache entry ``path``."""
    write_cache_entry(path, lambda tmp: _savez(tmp, {"scales": np.asarray(boxes[0]), "lower": boxes[1],
                                                     "upper": boxes[2]}))


def _scaled_bounds(problem: Problem, grid, log: _Log, run: _Run, cache_dir, learn_and_bound):
    """``(scales, lower, upper)``, each box array ``(n_scales, n_modes, n_grid_cells, n)``: from this run's bound
    stage, the cache, or the bound stage run again with the scales (once: saved in the cache)."""
    scales = bound_scales()
    shape = (len(problem.mode_names), grid.n_cells, int(np.size(problem.space_lower)))
    path = _cache_file(problem, cache_dir)
    got = getattr(run, "scaled_bounds", None)
    if got is not None and tuple(got[0]) == scales:
        if path is not None:
            _save_scaled(path, got)
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
        _save_scaled(path, got)
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
    and the bounds ``(p_low, p_up)`` of the run's controller on it: :func:`_rows_task` for every chunk of
    ``MAX_ROW_CELLS`` cells, as the run's abstraction stage builds them, then :func:`_solve_pieces`. The rows do
    not depend on the chunking (tests/test_chunks.py); in one chunk the temporaries of every cell at once cost
    twice the time (unicycle 64^3 at 4 B: 18.4 s against 9.0 s, most of it the first touch of fresh memory)."""
    k = None
    if form == "factored":  # the listed lengths of all the cells, for every chunk
        from robust_imdp.abstraction.cell_bounds import CellBounds
        from robust_imdp.abstraction.factored import axis_lengths

        k = axis_lengths(partition, CellBounds(lower, upper, None), noise)
    pieces = [_rows_task(partition, lower[:, s:s + MAX_ROW_CELLS], upper[:, s:s + MAX_ROW_CELLS], noise, form,
                         options, k) for s in range(0, partition.n_cells, MAX_ROW_CELLS)]
    return _solve_pieces(partition, form, pieces, dfa, controller)


#: Row tasks of a factor built piece by piece (:class:`PendingMargins`): about this many per factor, each of at least
#: ``MAX_ROW_CELLS`` cells (the partition travels with every task sent to a helper: 12.6 MB at 64^3).
FACTOR_PIECES = 16
MIN_PIECE_CELLS = 4096
#: Factors whose row chunks a helper takes, while this process runs the advice, before it takes whole factors.
BESIDE_PIECEWISE = 2


def _rows_task(partition, lower, upper, noise, form, options, k, *, threads=1):
    """The rows of one chunk of cells of a factor's abstraction (a module-level function: it runs in helper processes
    too): ``abstract_rows`` of the boxes ``lower``/``upper`` (n_modes, n_chunk_cells, n) in the run's form, the
    listed lengths ``k`` of every cell where it is factored. The rows do not depend on the chunking
    (tests/test_chunks.py): assembled in cell order they are the abstraction of :func:`_margin_task`."""
    from robust_imdp.abstraction.cell_bounds import CellBounds

    cb = CellBounds(lower, upper, None)
    if form == "factored":
        from robust_imdp.abstraction.factored import AXIS_TOL, factored_rows

        return factored_rows(partition, cb, noise, k, tol=AXIS_TOL)
    from robust_imdp.abstraction.rows import abstract_rows

    return abstract_rows(partition, cb, noise, None, **options)


def _solve_pieces(partition, form, pieces, dfa, controller):
    """``(p_low, p_up)`` of the run's controller on the abstraction assembled from a factor's row chunks (in cell
    order): the same model, so the same bits, as :func:`_margin_task`."""
    from robust_imdp.abstraction.factored import abstraction_model
    from robust_imdp.synthesis.margins import strategy_bounds

    if form == "factored":
        from robust_imdp.abstraction.factored import assemble_factored as assemble
    else:
        from robust_imdp.abstraction.rows import assemble_abstraction as assemble
    abstraction = assemble(partition, pieces)
    return strategy_bounds(abstraction_model(abstraction), partition.labels, partition.atoms, dfa, controller,
                           outside_state=partition.outside_state)


class _Piecewise:
    """A factor built here from row chunks (:class:`PendingMargins`): the chunks not yet claimed, the rows in."""

    def __init__(self, n_cells: int):
        size = max(MIN_PIECE_CELLS, -(-n_cells // FACTOR_PIECES))
        self.starts = list(range(0, n_cells, size))
        self.size = size
        self.todo = list(range(len(self.starts)))
        self.pieces: dict = {}
        self.k = None  # the factored form's listed lengths, once computed
        self.solving = False


class PendingMargins:
    """The margins' factors of an unrefined run, worked on beside the advice (:func:`start_margins`) and read by
    :func:`run_margins` (``pending=``): one list of work that the side lane's helpers and, once the advice is done,
    this process take from (docs/margins.md, "On several cores").

    The largest factor first (its abstraction lists the most transitions and its solves iterate longest). A
    helper takes a whole factor (its abstraction and the three solves there: nothing large comes back) while two
    or more factors are not started, except while this process still runs the advice, whose own tasks queue in
    the lane behind the helper's: then row chunks of up to :data:`BESIDE_PIECEWISE` factors first. The last
    factor is built here piece by piece: its row chunks go to whoever is
    free (a helper's come back through the pipe), its solves run here. This process, once the advice is done,
    solves the factors whose rows are in, takes row chunks, starts the next factor piece by piece, or takes back
    a whole factor still waiting in the lane behind other side work (the figures). Every factor's rows and solves
    are those of :func:`_margin_task`, so the results are the same bits wherever they ran.
    """

    def __init__(self, scales, lane, prepare):
        import threading

        self.scales = tuple(scales)
        self.lane = lane
        self.args: list | None = None  # per factor, :func:`_margin_task`'s arguments (from ``prepare``)
        self.values: dict = {}  # factor -> (p_low, p_up)
        self.error: BaseException | None = None
        self.unavailable = False  # the boxes at the larger factors are not at hand: run_margins bounds them
        self._cond = threading.Condition()
        self._unstarted = list(reversed(range(len(self.scales))))  # largest factor first
        self._sent: dict = {}  # work item -> its future in the lane, while it waits or runs there
        self.futures: list = []  # every task sent to the lane
        self._piecewise: dict = {}  # factor -> _Piecewise, in the order started
        self._closed = False
        self._joined = False  # this process works on the list (the advice is done)
        self._prepare = prepare
        self._starter = threading.Thread(target=self._start, name="robust-imdp margins", daemon=True)
        self._starter.start()

    # ------------------------------------------------------------------------------------------ the helpers' side
    def _start(self) -> None:
        """(A thread of its own.) The factors' arguments (reading or saving the boxes at larger B: I/O beside the
        advice), then one feeder per helper."""
        import threading

        try:
            self.args = self._prepare()
        except BaseException as exc:  # noqa: BLE001 - raised in run_margins' thread
            with self._cond:
                self.error = exc
                self._cond.notify_all()
            return
        with self._cond:
            if self.args is None:
                self.unavailable = True
            self._cond.notify_all()
        if self.args is None:
            return
        for h in self.lane.helpers:
            threading.Thread(target=self._feed, name="robust-imdp margins feeder", daemon=True).start()

    def _helper_item(self):
        """The next work of a helper (with the lock held): ``("whole", j)``, ``("rows", j, c)`` or None (none left
        that a helper can do: the solves run here)."""
        if self._closed or self.error is not None:
            return None
        # while this process runs the advice, the advice's own tasks queue in the lane behind the helper's: row
        # chunks (short) for up to BESIDE_PIECEWISE factors, before whole factors
        small = not self._joined and len(self._piecewise) < BESIDE_PIECEWISE
        if len(self._unstarted) >= 2 and not small:
            j = self._unstarted.pop(0)
            return ("whole", j)
        item = self._claim_rows()
        if item is None and self._unstarted:
            item = self._start_piecewise(self._unstarted.pop(0))
        return item

    def _claim_rows(self):
        for j, pw in self._piecewise.items():
            if pw.todo:
                return ("rows", j, pw.todo.pop(0))
        return None

    def _start_piecewise(self, j: int):
        pw = self._piecewise[j] = _Piecewise(self.args[j][0].n_cells)
        return ("rows", j, pw.todo.pop(0))

    def _rows_args(self, j: int, c: int) -> tuple:
        partition, lower, upper, noise, form, options, _, _ = self.args[j]
        pw = self._piecewise[j]
        if form == "factored" and pw.k is None:
            from robust_imdp.abstraction.cell_bounds import CellBounds
            from robust_imdp.abstraction.factored import axis_lengths

            k = axis_lengths(partition, CellBounds(lower, upper, None), noise)  # of every cell, for every chunk
            with self._cond:
                pw.k = k if pw.k is None else pw.k
        s0 = pw.starts[c]
        sl = slice(s0, s0 + pw.size)
        return (partition, lower[:, sl], upper[:, sl], noise, form, options, pw.k)

    def _feed(self) -> None:
        """(One thread per helper.) Send the helper its next work when it is done with the last, until none is
        left; work the lane cannot run goes back to the list (this process does it)."""
        from robust_imdp.pipeline.parallel import SideLaneError

        while True:
            with self._cond:
                item = self._helper_item()
                if item is None:
                    return
            try:
                if item[0] == "whole":
                    fut = self.lane.submit(_margin_task, *self.args[item[1]])
                else:
                    fut = self.lane.submit(_rows_task, *self._rows_args(item[1], item[2]))
                with self._cond:
                    self._sent[item] = fut
                self.futures.append(fut)
                value = fut.result()
            except CancelledError:  # taken back by this process (it waited in the lane behind other side work)
                continue
            except SideLaneError:  # the lane is gone: the work goes back to this process
                self._give_back(item)
                return
            except BaseException as exc:  # noqa: BLE001 - the task's own failure: raised in run_margins' thread
                with self._cond:
                    self._sent.pop(item, None)
                    self.error = self.error or exc
                    self._cond.notify_all()
                return
            self._record(item, value)

    def _give_back(self, item) -> None:
        with self._cond:
            self._sent.pop(item, None)
            if item[0] == "whole":
                self._unstarted.insert(0, item[1])
            else:
                self._piecewise[item[1]].todo.insert(0, item[2])
            self._cond.notify_all()

    def _record(self, item, value) -> None:
        with self._cond:
            self._sent.pop(item, None)
            if item[0] == "whole":
                self.values[item[1]] = value
            else:
                self._piecewise[item[1]].pieces[item[2]] = value
            self._cond.notify_all()

    # ------------------------------------------------------------------------------------------ this process
    def _local_item(self):
        """This process's next work (with the lock held), or None (wait for the helpers)."""
        for j, pw in self._piecewise.items():  # a factor whose rows are all in: its solves
            if not pw.solving and j not in self.values and len(pw.pieces) == len(pw.starts):
                pw.solving = True
                return ("solve", j)
        item = self._claim_rows()
        if item is None and self._unstarted:
            item = self._start_piecewise(self._unstarted.pop(0))
        if item is None:  # work still waiting in the lane (its helper busy with other side work): taken back
            for sent, fut in sorted(self._sent.items(), key=lambda kv: kv[0][0] != "rows"):
                if fut.cancel():
                    del self._sent[sent]
                    item = sent if sent[0] == "rows" else self._start_piecewise(sent[1])
                    break
        return item

    def value(self, j: int):
        """Factor ``j``'s ``(p_low, p_up)``: this process works on the list (solves, row chunks, whole factors taken
        back) until it is in. Raises a task's exception."""
        self._starter.join()
        with self._cond:
            if self.args is None:
                raise self.error if self.error is not None else RuntimeError("the margins' boxes are not at hand")
            self._joined = True
        while True:
            with self._cond:
                if self.error is not None:
                    raise self.error
                if j in self.values:
                    return self.values[j]
                item = self._local_item()
                if item is None:
                    self._cond.wait(timeout=1.0)
                    continue
            if item[0] == "solve":
                jj = item[1]
                pw = self._piecewise[jj]
                partition, _, _, _, form, _, dfa, controller = self.args[jj]
                value = _solve_pieces(partition, form, [pw.pieces[c] for c in range(len(pw.starts))], dfa,
                                      controller)
                with self._cond:
                    self.values[jj] = value
                    pw.pieces.clear()  # the rows are in the model, which is dropped
            else:
                self._record(item, _rows_task(*self._rows_args(item[1], item[2])))

    def wait_ready(self) -> bool:
        """Wait for the factors' arguments; False when the boxes at the larger factors are not at hand."""
        self._starter.join()
        return not self.unavailable

    def cancel(self) -> None:
        """Nothing more starts; work still waiting in the lane is cancelled (what runs there is dropped)."""
        with self._cond:
            self._closed = True
            self._unstarted.clear()
            for pw in self._piecewise.values():
                pw.todo.clear()
            futures = list(self._sent.values())
            self._cond.notify_all()
        for f in futures:
            f.cancel()


def start_margins(problem: Problem, grid, synthesis, classes, dfa, log: _Log, run: _Run, cache_dir):
    """Start the margins of an unrefined run beside the advice (:class:`PendingMargins`): the side lane's helpers
    take whole factors and row chunks while the advice keeps this process's cores (as on one core, so its time
    budget and the levers it estimates are those of the run without margins beside it). None where the run has
    no lane (one core, a Dask cluster, a problem below ``parallel.SIDE_MIN_CELL_MODES`` pairs) or no margins.
    The boxes at the larger factors come from this run's bound stage or the cache (read beside the advice); when
    neither has them, :func:`run_margins` bounds them."""
    from robust_imdp.pipeline.parallel import SIDE_MIN_CELL_MODES, InProcess

    if skip_reason(problem) is not None or grid.n_cells * len(problem.mode_names) < SIDE_MIN_CELL_MODES:
        return None
    sched = run.scheduler(log)
    if not isinstance(sched, InProcess) or not sched.use_side_lane():
        return None
    scales = bound_scales()
    shape = (len(problem.mode_names), grid.n_cells, int(np.size(problem.space_lower)))
    path = _cache_file(problem, cache_dir)
    got = getattr(run, "scaled_bounds", None)
    if got is not None and tuple(got[0]) != scales:
        got = None
    if got is None and path is None:
        return None

    def prepare():
        boxes = got
        if boxes is not None:
            if path is not None:  # the run's, saved in the cache (beside the advice)
                _save_scaled(path, boxes)
        else:
            boxes = read_cache_entry(path, lambda f: _read_scaled(f, scales, shape))
            if boxes is None:
                return None
        return _factor_args(problem, grid, synthesis, boxes[1], boxes[2], dfa)

    pending = PendingMargins(scales, sched.lane, prepare)
    pending.from_cache = got is None
    return pending


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
        if pending is not None and pending.wait_ready():  # started beside the advice: this process joins in
            if pending.from_cache:
                log.info(f"margins: reused the boxes at {', '.join(f'{s:g}' for s in pending.scales)} x B "
                         f"({_cache_file(problem, cache_dir).name})")
            index = {s: j for j, s in enumerate(pending.scales)}
            try:
                margins = assumption_margins(classes, lambda scale: pending.value(index[float(scale)]),
                                             problem.threshold, (1.0,) + pending.scales)
            finally:
                pending.cancel()  # factors past the last one read are not needed
            return _margins_result(margins, 0, log)
        if pending is not None:  # the boxes at larger B were in neither the run nor the cache: bounded below
            pending.cancel()
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
