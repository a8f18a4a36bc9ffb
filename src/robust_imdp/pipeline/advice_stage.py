"""The run's advice stage (``synthesis.advice.advise``): its inputs from the problem, its budget, its cache entry
and its re-solves on the run's scheduler.

* **Budget.** With ``advice="auto"`` the advice spends at most :data:`~robust_imdp.synthesis.advice.ADVICE_SHARE`
  (25 %) of the run's time before it (so at most a fifth of the whole run): the levers are estimated cheapest
  first while their predicted cost fits (the cost model is the run's own seconds of abstraction + solve per
  listed transition and of the bound stage per cell), and a re-solve still running at the end is abandoned
  between chunks of rows. Where the stages before came from the cache, the time they took when computed
  (saved in the advice's cache entry) counts. ``advice=True`` (``run --advice on``) has no budget.
* **Cache.** ``advice-<advice_key>.json`` in the run's cache holds every estimate as it completes; a re-run
  reuses them, and so does a run interrupted during the advice when it is started again (Ctrl-C there says
  how many estimates are kept).
* **Scheduler.** Where the run has several cores (a Dask cluster, or in process with the side lane's helper
  processes: :func:`side_by_side`) each lever's whole re-solve (rows and solve) is one task (:func:`_job_task`) and
  they run side by side (:func:`spread`: this process and the helpers take them from one queue). Otherwise (one
  lever at a time, or no lane) the re-solves' rows are tasks (:func:`_rows_task`), every lever's at once, on
  every core the run has (:func:`spread`: the scheduler's workers, or in process threads and the lane's
  helpers), and each solve runs in this process as soon as its rows are in. The shares are the same either way.
* **Assumptions per mode and component** (known components, periodic axes): the fit, the noise floor and
  the sub-box terms are per component; B is never a lever (``premise`` says what the guarantee needs).
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import numpy as np

from robust_imdp.errors import interrupt_in
from robust_imdp.pipeline.bound_rkhs import _pilot_task
from robust_imdp.pipeline.bound_stage import _cell_bounder, _failure_budget, _fitted, _residual_data
from robust_imdp.pipeline.cache import (
    _fingerprint,
    _load_bounds,
    _read_json,
    _write_json_entry,
    abstraction_key,
    bounds_key,
    read_cache_entry,
)
from robust_imdp.pipeline.problem import Problem, _settings
from robust_imdp.pipeline.runtime import _Log, _Run

__all__ = ["run_advice", "advice_key", "ADVICE_VERSION", "spread", "side_by_side"]

#: Version of the advice's estimates: cache entries of another version are not read.
ADVICE_VERSION = 2


def advice_key(problem: Problem) -> str:
    """Hash of everything the advice depends on: the abstraction's inputs, the formula, threshold, horizon and
    reading, and :data:`ADVICE_VERSION`."""
    h = hashlib.sha256(abstraction_key(problem).encode())
    spec = ["advice", ADVICE_VERSION, problem.formula, float(problem.threshold), problem.horizon]
    if getattr(problem, "semantics", "auto") != "auto":
        spec.append(problem.semantics)
    _fingerprint(h, spec)
    return h.hexdigest()[:20]


def _yes_share(partition, classes) -> float:
    vol = np.prod(np.asarray(partition.cells_upper) - np.asarray(partition.cells_lower), axis=1)
    return float(np.sum(vol[np.asarray(classes) == "yes"]) / np.sum(vol))


def _note_only(partition, classes, note: str, premise: str = "") -> dict:
    """The advice of a run where no lever can be estimated: why (printed as the advice line)."""
    return {"baseline_share": _yes_share(partition, classes), "levers": [], "winner": None, "note": note,
            "premise": premise}


def _premise(problem: Problem, diagnostics: dict) -> str:
    """What the guarantee needs of the assumption, against the data's certified minimum norm (B is not a lever:
    a smaller B decides more cells only by claiming more about g)."""
    st = _settings(problem)
    B = st.rkhs_bound
    if st.uniform:
        need = f"the guarantee needs ||g|| <= B = {float(B.max()):g} for every mode and component"
    else:
        known = int(np.sum(B == 0))
        need = (f"the guarantee needs ||g|| <= rkhs_bound of each mode and component (largest {float(B.max()):g}"
                + (f"; {known} known components, exact up to tau" if known else "") + ")")
    mins = diagnostics.get("assumption", {}).get("min_norm", [])
    worst = max(mins, key=lambda c: c["minimum"], default=None)
    data = ("" if worst is None else f"the data need ||g|| >= {worst['minimum']:.3g} (mode {worst['mode']}, "
            f"component {worst['component']}); ")
    return (f"{need}: an assumption, not a lever ({data}a smaller B would decide more cells only by claiming "
            "more about g; run `robust-imdp calibrate` for evidence on B)")


def _noise_floor(problem: Problem, data) -> np.ndarray:
    """(n_modes, n): the excess per side left with dense data: the data-noise bound plus tau (with iid noise the
    sub-Gaussian bound shrinks further, to tau), per mode and component."""
    from robust_imdp.bounds.rkhs import noise_bound_at_confidence

    data_fail, _ = _failure_budget(problem)
    noise_bound, _ = noise_bound_at_confidence(problem.noise, sum(x.shape[0] for x, _, _ in data),
                                               data_fail if data_fail > 0 else 0.5)
    tau = np.asarray(_settings(problem).misspecification, float)
    return tau if problem.iid_noise else np.asarray(noise_bound, float)[None, :] + tau


def _local_pools(problem: Problem, data):
    """``(k, m)`` when some mode's cells are certified with weights on its ``k`` nearest points (the bound
    stage's rule: ``local_points``, or ``LOCAL_DEFAULT`` above ``LOCAL_AUTO`` points per mode) and the largest
    mode has ``m`` points; None when every mode uses all its points or the method has no local weights."""
    from robust_imdp.pipeline.problem import pool_size

    if not problem.method.local_points:  # the method has no local weights (the GP route)
        return None
    sizes = [x.shape[0] for x, _, _ in data]
    pooled = [k for k in (pool_size(problem.local_points, m) for m in sizes) if k is not None]
    return (min(pooled), int(max(sizes))) if pooled else None


def _sub_box_terms(problem: Problem):
    """``terms(lower, upper) -> (k,)``: every cell's largest Taylor term ``B rho(t_max)`` over the modes and unknown
    components, with each component's own B and lengthscale as the bound stage computes it (inflated B,
    rounded-up ``t_max``: what ``rkhs.split_counts`` weighs against ``split_tol``); None where the run cannot split
    or already does (no sub-box lever)."""
    if problem.split_tol is not None or not problem.method.split:
        return None
    from robust_imdp._fp import up
    from robust_imdp._kernels import inv_l2_up, norm_inflation
    from robust_imdp.bounds.rkhs_model import cell_centres, split_term, t_max_up

    st = _settings(problem)
    d = int(np.size(problem.space_lower))
    groups = {(float(st.rkhs_bound[u, i]), tuple(st.lengthscale[u, i].tolist()))
              for u in range(st.rkhs_bound.shape[0]) for i in range(st.rkhs_bound.shape[1]) if st.rkhs_bound[u, i] > 0}
    if not groups:
        return None  # every component is known: nothing is certified on sub-boxes
    terms = [(float(up(B * norm_inflation(d))), inv_l2_up(np.asarray(L), d)) for B, L in sorted(groups)]

    def cell_terms(lower, upper):
        r = cell_centres(lower, upper)[1]
        return np.max([split_term(t_max_up(r, inv_l2), G) for G, inv_l2 in terms], axis=0)

    return cell_terms


# ---------------------------------------------------------------------------------------------- every core
#: Tasks of :func:`spread` that run at once in this process (threads; each holds one re-solve's rows in memory).
LOCAL_TASKS = 2


def spread(sched, fn, args, kwargs=None):
    """Yield ``(index, fn(*args[index], **kwargs))`` for every task, in order of completion, on every core the run
    has: a Dask cluster's workers (``sched.run``); in process on several cores :data:`LOCAL_TASKS` threads of this
    process *and* the side lane's helper processes if it has one (``pipeline.parallel.SideLane``, one BLAS and
    numba thread each), taking the tasks from one queue, so independent serial work (the margins' and the
    advice's re-solves: numpy's exact rows, one topological solve each) runs side by side (a task still waiting
    in the lane behind other side work, e.g. the figures, is taken back when this process has nothing else to
    do); on one core one after the other here.

    ``fn`` must be a module-level function of pure tasks: the caller assembles the results by index, so they do
    not depend on where each task ran (the solvers' and the abstraction's bits do not depend on the thread
    count; BLAS has one thread in the run and in the helpers). A task's exception is raised here. A consumer
    that stops iterating (``close()``) leaves the tasks not yet started unstarted; those running in a helper
    finish there and are dropped.
    """
    import queue
    import threading
    from concurrent.futures import CancelledError

    from robust_imdp.pipeline.parallel import InProcess, SideLaneError

    kw = dict(kwargs or {})
    local = isinstance(sched, InProcess) and sched.threads > 1
    lane = sched.lane if local else None
    if not local or len(args) < 2:
        yield from sched.run(fn, args, kw)
        return
    threads = sched.threads
    todo = list(range(len(args)))
    lock = threading.Lock()
    done: queue.Queue = queue.Queue()
    sent: dict = {}  # task index -> its future in the lane, while it waits or runs there

    def take():
        with lock:
            return todo.pop(0) if todo else None

    def feed():  # one per helper: its next task from the queue, until the queue is empty
        while True:
            i = take()
            if i is None:
                return
            try:
                fut = lane.submit(fn, *args[i], threads=1, **kw)
                with lock:
                    sent[i] = fut
                value = fut.result()
            except CancelledError:  # taken back by this process (the helper was busy with other side work)
                continue
            except SideLaneError:  # the lane is gone: the task goes back to this process
                with lock:
                    sent.pop(i, None)
                    todo.insert(0, i)
                return
            except BaseException as exc:  # the task's own failure: raised in the caller
                done.put((i, False, exc))
                continue
            done.put((i, True, value))

    def take_back():
        """A task still waiting in the lane (its helper busy with other side work, e.g. the figures), cancelled
        there to run here; None when every sent task has started."""
        with lock:
            waiting = [(i, f) for i, f in sent.items() if not f.running() and not f.done()]
        for i, f in waiting:
            if f.cancel():
                return i
        return None

    def work():  # a second thread of this process: numpy's loops and the solver kernels release the GIL
        while True:
            i = take()
            if i is None:
                return
            try:
                done.put((i, True, fn(*args[i], threads=threads, **kw)))
            except BaseException as exc:
                done.put((i, False, exc))

    feeders = [threading.Thread(target=feed, name="robust-imdp spread", daemon=True)
               for _ in (lane.helpers if lane is not None else ())]
    feeders += [threading.Thread(target=work, name="robust-imdp spread", daemon=True)
                for _ in range(min(LOCAL_TASKS, threads, len(args)) - 1)]
    for t in feeders:
        t.start()
    got = 0
    try:
        while got < len(args):
            try:
                item = done.get_nowait()
            except queue.Empty:
                i = take()
                if i is None:
                    i = take_back()
                if i is None:  # everything started: wait for the helpers' last tasks
                    if not any(t.is_alive() for t in feeders) and done.empty():
                        with lock:
                            if not todo:
                                raise RuntimeError("spread: a task was lost")  # pragma: no cover
                        continue
                    try:
                        item = done.get(timeout=0.05)
                    except queue.Empty:
                        continue
                else:
                    item = (i, True, fn(*args[i], threads=threads, **kw))
            i, ok, value = item
            if not ok:
                raise value
            got += 1
            yield i, value
    finally:
        with lock:
            todo.clear()  # a consumer that stopped: nothing more starts


def side_by_side(sched, cell_modes: int, *, need_lane: bool = False) -> bool:
    """Whether independent re-solves of ``cell_modes`` (cell, mode) pairs each run side by side (:func:`spread`):
    on a Dask cluster, or in process on several cores (threads, and the side lane's helpers: the lane is started
    here from ``pipeline.parallel.SIDE_MIN_CELL_MODES`` pairs on, where a helper's start-up is small against a
    re-solve); with ``need_lane`` in process only with a lane (smaller re-solves: one after the other, in the
    order the caller's budget and interrupt handling expect)."""
    from robust_imdp.pipeline.parallel import SIDE_MIN_CELL_MODES, DaskScheduler, InProcess

    if isinstance(sched, DaskScheduler):
        return True
    if not isinstance(sched, InProcess) or sched.threads < 2:
        return False
    if not sched.concurrent_side and cell_modes >= SIDE_MIN_CELL_MODES:
        sched.use_side_lane()
    return sched.concurrent_side or not need_lane


# ---------------------------------------------------------------------------------------------- re-solves
def _rows_task(partition, lower, upper, noise, k=None, *, threads=1, **options):
    """One chunk of rows of an advice re-solve (a module-level function, so that workers can import it); ``k``:
    the job's listed lengths per axis when its abstraction is factored (``advice.job_lengths``)."""
    from robust_imdp.synthesis.advice import job_rows

    return job_rows(partition, lower, upper, noise, options, k=k)


def _job_task(job, noise, k, options, dfa, threshold, horizon, semantics, *, threads=1):
    """One whole re-solve of the advice (a module-level function: it runs in helper processes and on workers): the
    job's rows in the chunks of :func:`_scheduled_solver` (``advice.ROW_CHUNK`` cells) and its Q_yes share."""
    from robust_imdp.synthesis.advice import ROW_CHUNK, job_rows, job_share

    pieces = [job_rows(job.partition, job.lower[:, s0:s0 + ROW_CHUNK], job.upper[:, s0:s0 + ROW_CHUNK], noise,
                       options, k=k) for s0 in range(0, job.partition.n_cells, ROW_CHUNK)]
    return job_share(job, pieces, dfa, threshold=threshold, horizon=horizon, semantics=semantics)


def _advice_options(problem: Problem) -> dict:
    """The abstraction options of the advice's re-solves: the run's, and its form (``form = "factored"`` where the
    run's grid abstraction is factored: the re-solves abstract their grids the same way)."""
    return {**problem.abstraction_options(), "form": problem.form_choice()[0]}


def _scheduled_solver(problem: Problem, dfa, run: _Run, log: _Log):
    """``solve(jobs, deadline)`` of ``advise``: every job's rows in chunks of ``advice.ROW_CHUNK`` cells as tasks of
    the run's scheduler, all jobs at once (in order: in process one after the other, on a cluster in parallel);
    a job's solve runs here as soon as its rows are in. Past ``deadline`` no further chunk is waited for and
    the unfinished jobs are yielded with share None."""
    from robust_imdp.synthesis.advice import ROW_CHUNK, job_lengths, job_share

    opts = _advice_options(problem)
    semantics = getattr(problem, "semantics", "auto")

    def solve(jobs, deadline):
        sched = run.scheduler(log)
        if len(jobs) > 1 and side_by_side(sched, max(j.partition.n_cells for j in jobs) * len(problem.mode_names),
                                          need_lane=True):
            # whole re-solves as tasks, side by side on every core (spread); the same rows and solves, so the
            # same shares; past the deadline no further one is waited for
            yield from _side_by_side_jobs(sched, jobs, deadline)
            return
        tasks, args = [], []
        for j, job in enumerate(jobs):
            k = job_lengths(job, problem.noise, opts)  # factored: every chunk lists the job's lengths
            # the partition goes with each task, not scattered: a scattered object's key is its content's hash,
            # so releasing it here would release the run's own scattered grid under the later stages' tasks
            for s0 in range(0, job.partition.n_cells, ROW_CHUNK):
                sl = slice(s0, s0 + ROW_CHUNK)
                tasks.append((j, s0))
                args.append((job.partition, job.lower[:, sl], job.upper[:, sl], problem.noise, k))
        need = {j: sum(1 for t in tasks if t[0] == j) for j in range(len(jobs))}
        pieces: dict = {j: {} for j in range(len(jobs))}
        finished = set()
        # in process on several cores the chunks run side by side (spread: threads and the lane's helpers); the
        # pieces are assembled by position, so the rows are the same bits in any order
        stream = spread(sched, _rows_task, args, opts)
        try:
            for i, rows in stream:
                j, s0 = tasks[i]
                pieces[j][s0] = rows
                if len(pieces[j]) == need[j]:
                    finished.add(j)
                    yield j, job_share(jobs[j], [pieces[j][s] for s in sorted(pieces[j])], dfa,
                                       threshold=problem.threshold, horizon=problem.horizon, semantics=semantics)
                if deadline is not None and time.perf_counter() > deadline:
                    break
        finally:
            stream.close()  # a cluster's remaining tasks are cancelled
        for j in range(len(jobs)):
            if j not in finished:
                yield j, None

    def _side_by_side_jobs(sched, jobs, deadline):
        args = [(job, problem.noise, job_lengths(job, problem.noise, opts), opts, dfa, problem.threshold,
                 problem.horizon, semantics) for job in jobs]
        finished = set()
        stream = spread(sched, _job_task, args)
        try:
            for j, share in stream:
                finished.add(j)
                yield j, share
                if deadline is not None and time.perf_counter() > deadline:
                    break
        finally:
            stream.close()  # nothing more starts
        for j in range(len(jobs)):
            if j not in finished:
                yield j, None

    return solve


# ---------------------------------------------------------------------------------------------- the stage
def _read_entry(path):
    """``(estimates by lever name, run seconds)`` of a saved advice entry, or ``({}, 0.0)``."""
    from robust_imdp.synthesis.advice import Lever

    doc = None if path is None else read_cache_entry(path, _read_json)
    if not isinstance(doc, dict) or doc.get("version") != ADVICE_VERSION:
        return {}, 0.0
    try:
        done = {name: Lever(**lv) for name, lv in doc.get("levers", {}).items()}
        return done, float(doc.get("run_s", 0.0))
    except (TypeError, ValueError):  # a foreign or older document: computed again
        return {}, 0.0


def _cost_model(problem: Problem, partition, abstraction, log: _Log) -> dict:
    """The run's own costs: seconds of abstraction + solve per listed transition (when both stages ran here),
    bound-stage seconds per cell and mode (when it ran here), and the IMDP's listed transitions."""
    t = log.timings
    nnz = float(np.sum(np.asarray(abstraction.nnz_per_row)))
    per_transition = ((t["abstract"] + t["synthesize"]) / nnz if "abstract" in t and "synthesize" in t and nnz > 0
                      else None)
    per_bound = (t["bound"] / (partition.n_cells * len(problem.mode_names)) if "bound" in t else None)
    return {"per_transition": per_transition, "per_bound": per_bound, "transitions": nnz}


def run_advice(problem: Problem, partition, abstraction, cell_bounds, dfa, classes, log: _Log, run: _Run, cache_dir,
               diagnostics: dict) -> dict:
    """The advice of the run as a JSON-able dict (:meth:`Advice.to_dict`), or ``{}`` when the run asks for none.

    Where no lever can be estimated (the method has no pilot bound stage, the boxes are not at hand) the dict
    holds only a ``note`` saying why. See the module docstring for the budget, the cache and the scheduler.
    """
    want = getattr(run, "advice", "auto")
    if want is False:
        return {}
    t_run = time.perf_counter() - log.t0  # the run's time before the advice
    saved: list = []
    path = None if cache_dir is None else Path(cache_dir) / f"advice-{advice_key(problem)}.json"
    try:
        with log.stage("advice"):  # everything the advice does is in its stage's time
            return _advice(problem, partition, abstraction, cell_bounds, dfa, classes, log, run, cache_dir,
                           diagnostics, want, t_run, path, saved)
    except BaseException as exc:
        if interrupt_in(exc) is not None:  # Ctrl-C: say what of the advice is kept, and where
            kept = len(saved)
            where = (f"kept in {cache_dir}: the same command reuses {'it' if kept == 1 else 'them'} and resumes the "
                     "advice" if path is not None else "not kept (no cache)")
            log.info(f"advice interrupted after the solve: {kept} estimate{'' if kept == 1 else 's'} {where}; "
                     "`--advice off` (advice=False) skips the advice")
        raise


def _advice(problem: Problem, partition, abstraction, cell_bounds, dfa, classes, log: _Log, run: _Run, cache_dir,
            diagnostics: dict, want, t_run: float, path, saved: list) -> dict:
    """:func:`run_advice` inside its stage; ``saved`` collects the names of the estimates saved (for the interrupt
    line), including those reused from the cache entry at ``path``."""
    from robust_imdp.jsonable import jsonable as _jsonable
    from robust_imdp.synthesis.advice import ADVICE_SHARE, MAX_CELLS, advice_line, advise

    premise = _premise(problem, diagnostics)
    if not problem.method.advice_pilot:
        out = _note_only(partition, classes, f"not estimated with error_bound = {problem.error_bound!r} (its image "
                         "boxes are not built by a bound stage the advice can run on pilot cells)", premise)
        log.info(advice_line(out))
        return out
    if cell_bounds is None and cache_dir is not None:  # the abstraction came from the cache: its boxes too
        loaded = read_cache_entry(Path(cache_dir) / f"bounds-{bounds_key(problem)}.npz", _load_bounds)
        if loaded is not None:  # None when absent or damaged
            cell_bounds = loaded[0]
    if cell_bounds is None:
        out = _note_only(partition, classes, "not estimated: the image boxes of this run are not at hand (the "
                         "bounds' cache entry is missing or damaged)", premise)
        log.info(advice_line(out))
        return out
    done, saved_run_s = _read_entry(path)
    saved.extend(done)
    run_s = max(t_run, saved_run_s)  # stages loaded from the cache count with the time they took
    doc = {"version": ADVICE_VERSION, "run_s": run_s, "levers": {n: lv.to_dict() | {"seconds": lv.seconds}
                                                                 for n, lv in done.items()}}
    written = []

    def on_lever(lv):
        doc["levers"][lv.name] = _jsonable(lv.to_dict() | {"seconds": lv.seconds})
        if path is not None:  # saved as it completes: an interrupted run resumes from here
            _write_json_entry(path, doc)
            saved.append(lv.name)
            written.append(lv.name)

    data = _residual_data(problem)
    costs = _cost_model(problem, partition, abstraction, log)
    bounders: dict = {}

    def bound_cells(lower, upper, split_tol=None, local_points=None):
        key = (split_tol, local_points)
        if key not in bounders:
            p = problem.replace(split_tol=problem.split_tol if split_tol is None else split_tol,
                                local_points=problem.local_points if local_points is None else local_points)
            bounders[key] = _cell_bounder(p, partition, _Log(False), run, task=_pilot_task)
        return bounders[key](lower, upper)

    adv = advise(partition, cell_bounds, _fitted(problem, data), problem.noise, dfa,
                 threshold=problem.threshold, horizon=problem.horizon, classes=classes,
                 noise_floor=_noise_floor(problem, data),
                 abstraction_options=_advice_options(problem),
                 bound_cells=bound_cells, max_cells=MAX_CELLS if want == "auto" else 2 ** 62,
                 progress=log.info if log.enabled else None, sub_box_terms=_sub_box_terms(problem),
                 local_pools=_local_pools(problem, data), semantics=getattr(problem, "semantics", "auto"),
                 budget_s=ADVICE_SHARE * run_s if want == "auto" else None,
                 solver=_scheduled_solver(problem, dfa, run, log), done=done, on_lever=on_lever,
                 premise=premise, **costs)
    if path is not None and not written and saved_run_s < run_s:
        _write_json_entry(path, doc)  # the run's time, for the budget of a later run from the cache
    out = _jsonable(adv.to_dict())
    if adv.reused:
        log.info(f"advice: {adv.reused} estimate{'' if adv.reused == 1 else 's'} reused from {path.name}")
    log.info(advice_line(out))
    return out
