"""The RKHS route's bound stage (error_bound 'optimal' / 'ridge', ``bounds.rkhs``): the grid's cells in chunks
(resumable, on the run's scheduler, timed by a pre-flight pilot) and the bounder of new cells (refinement,
advice) on the same event as the grid's.

The :class:`robust_imdp.bounds.methods.CellBounder` of the route: :func:`learn_and_bound` and
:func:`cell_bounder`; ``bounds.methods`` names them by their dotted path. What every route shares (residual
data, allowances, the assumption check, diagnostics) is ``pipeline/bound_stage.py``'s.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from robust_imdp.bounds.methods import get as _method
from robust_imdp.pipeline.bound_stage import (
    _add_known_range,
    _diagnostics,
    _failure_budget,
    _known_gap,
    _known_ranges,
    _one_setting,
    _prepare_beside,
    _residual_data,
    _shared_allowance,
)
from robust_imdp.pipeline.cache import _load_npz, _savez, bounds_key, read_cache_entry, write_cache_entry
from robust_imdp.pipeline.problem import Problem, _is_affine, _settings, pool_size
from robust_imdp.pipeline.runtime import _Log, _Run, _chunk_cells

#: Cells per bound task unless the run says otherwise (``chunk_cells``; rounded to rkhs.CELL_BLOCK).
CHUNK_CELLS = 256
#: The same in process (two tasks at a time, each on every core: ``InProcess.run_overlapping``): fewer, larger tasks
#: cost less Python per cell (the result does not depend on the chunking); on a Dask cluster the tasks are spread
#: over the workers: :data:`CHUNK_CELLS`.
CHUNK_CELLS_IN_PROCESS = 1024
#: Without a data failure budget (bounded noise) the noise bound is taken at this level (it does not use it).
_NO_BUDGET_DELTA = 0.5
#: A kernel compilation longer than this many seconds is reported (the pre-flight's one-cell call).
_COMPILE_NOTE_S = 5.0


# ---------------------------------------------------------------------------------------------- settings
def _affine_part(problem: Problem, u: int):
    """(A, b) of mode ``u``'s affine known part, or zeros for a nonlinear one (its range is added to g's)."""
    m = problem.maps[u]
    if _is_affine(m):
        return m.A, m.b
    n = int(np.size(problem.space_lower))
    return np.zeros((n, n)), np.zeros(n)


def _base_settings(problem: Problem, settings=None) -> dict:
    """The bound stage's problem-wide settings: the problem's own values with one assumption (as before);
    otherwise stand-ins (the largest B, the first lengthscale) that every mode's groups override."""
    if _settings(problem).uniform:
        return {"lengthscale": problem.gp_options.get("lengthscale", 1.0), "rkhs_bound": problem.rkhs_bound,
                "misspecification": problem.misspecification}
    st = _settings(problem) if settings is None else settings
    B = st.rkhs_bound
    return {"lengthscale": st.lengthscale[0, 0], "rkhs_bound": float(B.max()) if np.any(B > 0) else 1.0,
            "misspecification": float(st.misspecification.max())}


def _data_noise_bound(problem: Problem, data, data_fail: float):
    """The data-noise bound of the certificate: one event over all the data, at the failure budget ``data_fail``."""
    from robust_imdp.bounds.rkhs import noise_bound_at_confidence

    m_total = sum(x.shape[0] for x, _, _ in data)
    noise_bound, _ = noise_bound_at_confidence(problem.noise, m_total,
                                               data_fail if data_fail > 0 else _NO_BUDGET_DELTA)
    return noise_bound


def _chunk_settings(problem: Problem, noise_bound, iid_theta=None, iid_factor=None) -> dict:
    """The keyword settings of every bound task (``rkhs.bound_chunk``): the problem-wide assumption, the
    largest allowance over the modes, the method's weights, the iid event (None: without it)."""
    out = {**_base_settings(problem), "noise_bound": _shared_allowance(problem, noise_bound),
           "method": _method(problem.error_bound).weights, "iid_theta": iid_theta, "iid_factor": iid_factor}
    if getattr(problem, "split_tol", None) is not None:  # only then: the tasks' arguments are otherwise as before
        out["split_tol"] = float(problem.split_tol)  # sub-box certificates (rkhs.cell_ranges, eq. C on each)
    return out


def _local_settings(problem: Problem, data, partition, noise_bound):
    """Per mode: None (all points) or (points, ridge lambda) of the local weights."""
    from robust_imdp.bounds.rkhs import local_lambda

    out = []
    for x, _, _ in data:
        k = pool_size(problem.local_points, x.shape[0])
        if k is None:
            out.append(None)
            continue
        lam = None
        if _method(problem.error_bound).local_lambda:
            base = _base_settings(problem)
            lam = local_lambda(x, partition.cells_lower, partition.cells_upper,
                               lengthscale=base["lengthscale"], rkhs_bound=base["rkhs_bound"],
                               noise_l1=float(np.max(noise_bound)) + float(base["misspecification"]), k=k)
        out.append((int(k), lam))
    return out


def _mode_extras(problem: Problem, data, partition, allowance, local) -> list:
    """Per mode: None (the original path) or the dict of ``assumptions.bound_mode_chunk``."""
    if _one_setting(problem):
        return [None] * len(problem.mode_names)
    from robust_imdp.bounds.rkhs import local_lambda

    st = _settings(problem)
    out = []
    for u in range(len(problem.mode_names)):
        extra = {"noise_bound": np.asarray(allowance, float)}
        if not st.uniform:
            extra["groups"] = st.groups(u)
            if _method(problem.error_bound).local_lambda and local[u] is not None:
                # one ridge lambda per group, for all chunks (as _local_settings does per mode)
                extra["local_lambda"] = [
                    None if B == 0 else local_lambda(data[u][0], partition.cells_lower, partition.cells_upper,
                                                     lengthscale=L, rkhs_bound=B,
                                                     noise_l1=float(np.max(allowance[u][idx])) + tau, k=local[u][0])
                    for idx, B, L, tau in extra["groups"]]
        out.append(extra)
    return out


def _extra(mode) -> tuple:
    """The task's optional last argument: nothing on the original path (the tasks' arguments as before)."""
    return () if mode is None else (mode,)


def _mode_settings(problem: Problem, data, partition, noise_bound):
    """Per mode: the local weights (:func:`_local_settings`) and the mode's own settings (:func:`_mode_extras`)."""
    local = _local_settings(problem, data, partition, noise_bound)
    # one allowance for every mode (the largest), as on the one-setting path: equal settings, equal bytes
    extras = _mode_extras(problem, data, partition, _shared_allowance(problem, noise_bound), local)
    return local, extras


# ---------------------------------------------------------------------------------------------- tasks
def _bound_task(X, Y, A, b, lower, upper, local, mode=None, *, threads=1, **settings):
    """One chunk of the bound stage; ``local`` = (points, ridge lambda) of the mode or None; ``mode``: None
    (the problem-wide settings) or the mode's own (``assumptions.bound_mode_chunk``)."""
    return _bound_work(X, Y, A, b, lower, upper, local, mode, threads=threads, **settings)


def _pilot_task(*args, threads=1, **settings):
    """The advice's pilot cells: the work of :func:`_bound_task` (same arguments, including a mode's own
    settings) under its own name, so that progress does not count them as bound-stage chunks."""
    return _bound_work(*args, threads=threads, **settings)


def _bound_work(X, Y, A, b, lower, upper, local, mode=None, *, threads=1, **settings):
    """The work of :func:`_bound_task` and :func:`_pilot_task`."""
    from robust_imdp.bounds.rkhs import bound_chunk

    if mode is not None:
        from robust_imdp.bounds.assumptions import bound_mode_chunk

        t0 = time.perf_counter()
        out = bound_mode_chunk(X, Y, A, b, lower, upper, local, mode, threads=threads, **settings)
        out["seconds"] = time.perf_counter() - t0
        return out

    if local is not None:
        settings = dict(settings, local_points=local[0], local_lambda=local[1])
    return bound_chunk(X, Y, A, b, lower, upper, threads=threads, **settings)


def _share_data(sched, data) -> list:
    """Per mode: the scheduler's handles of the inputs and residuals (sent to the workers once)."""
    return [(sched.share(np.ascontiguousarray(x)), sched.share(np.ascontiguousarray(y))) for x, y, _ in data]


def _task_args(problem: Problem, shared, lower, upper, local, extras, tasks, chunk) -> list:
    """The positional arguments of :func:`_bound_task` for each ``(mode, first cell)`` of ``tasks``."""
    return [(*shared[u], *_affine_part(problem, u), lower[s0:s0 + chunk], upper[s0:s0 + chunk],
             local[u], *_extra(extras[u])) for u, s0 in tasks]


def _finish_ranges(lower, upper, known_ranges) -> None:
    """Check every mode's bounded ranges (``rkhs.check_ranges``) and add the known part's certified range
    (the chunks bounded g_u alone), in place."""
    from robust_imdp.bounds.rkhs import check_ranges

    for u in range(len(known_ranges)):
        check_ranges(lower[u], upper[u], u)
        if known_ranges[u] is not None:  # f_u's certified range plus g_u's
            _add_known_range(lower[u], upper[u], known_ranges[u])


def _has_scales(part: dict, scales, k: int, n: int) -> bool:
    """Whether a saved chunk holds the boxes at exactly ``scales`` (``rkhs.bound_chunk``'s ``scaled_*``)."""
    shape = (len(scales), k, n)
    return ("scales" in part and np.array_equal(np.asarray(part["scales"], float), np.asarray(scales, float))
            and all(np.shape(part.get(key)) == shape for key in ("scaled_lower", "scaled_upper")))


def _check_part(part: dict, k: int, n: int) -> dict:
    """A saved bound chunk, checked to hold ``k`` cells x ``n`` outputs (else ValueError: computed again)."""
    for key in ("lower", "upper", "eps", "support"):
        if key not in part or np.shape(part[key]) != (k, n):
            raise ValueError(f"{key} must have shape ({k}, {n}); got "
                             f"{np.shape(part[key]) if key in part else 'no such array'}")
    if "n_unconverged" not in part:
        raise ValueError("n_unconverged is missing")
    return part


# ---------------------------------------------------------------------------------------------- the grid's cells
def _resume(parts_dir, tasks, chunk: int, N: int, n: int, log: _Log, scales=None) -> dict:
    """The chunks an interrupted run saved under ``parts_dir`` (checked; a damaged one is computed again). With
    ``scales`` (the assumption margins' boxes) a chunk saved without the boxes of those scales is computed again."""
    results: dict = {}
    if parts_dir is not None and parts_dir.exists():
        for u, s0 in tasks:
            part = read_cache_entry(parts_dir / f"m{u}-c{s0}-{chunk}.npz",
                                    lambda f, k=min(chunk, N - s0): _check_part(_load_npz(f), k, n))
            if part is not None and scales is not None and not _has_scales(part, scales, min(chunk, N - s0), n):
                part = None  # saved by a run without margins (or with other scales): bounded again
            if part is not None:
                results[(u, s0)] = part
        if results:
            log.info(f"resumed: {len(results)} of {len(tasks)} bound chunks from {parts_dir}")
    return results


def _preflight(problem: Problem, data, partition, settings, local, extras, run: _Run, n_missing: int, n_tasks: int,
               log: _Log):
    """Time a few blocks of cells in this process and log the extrapolated work (``n_missing`` of
    ``n_tasks`` tasks still to run); the run's scheduler, opened after the kernels are compiled."""
    from robust_imdp.bounds import rkhs

    M, n, N = len(problem.mode_names), len(problem.space_lower), partition.n_cells
    lo, up = partition.cells_lower, partition.cells_upper
    x0, y0, _ = data[0]
    A0, b0 = _affine_part(problem, 0)
    # The kernels' first call in a process compiles them (no warm-up at install) or loads
    # them from numba's cache (about 1 s): a one-cell call takes that time, so that the
    # timed pilot below measures bounding only.
    first = dict(settings) if local[0] is None else dict(settings, local_points=local[0][0],
                                                         local_lambda=local[0][1])
    compile_s = rkhs.bound_chunk(x0, y0, A0, b0, lo[:1], up[:1], threads=1, **first)["seconds"]
    if compile_s > _COMPILE_NOTE_S:
        log.info(f"pre-flight: numba compiled the bound kernels in {compile_s:.0f} s (once: cached for later "
                 "runs; `python -m robust_imdp.warmup` does it at install)")
    sched = run.scheduler(log)
    # One block per thread of a task, on that many threads: in process, the numba threads
    # share the cores with whatever else runs, and this measures the speed the tasks get.
    threads = int(getattr(sched, "threads", 1))
    k = min(N, rkhs.CELL_BLOCK * threads)
    pilot = _bound_task(x0, y0, A0, b0, lo[:k], up[:k], local[0], *_extra(extras[0]), threads=threads,
                        **settings)
    per_cell = pilot["seconds"] / k  # wall seconds per cell and mode, on ``threads`` threads
    lanes = max(1, sched.n_workers // threads)  # tasks running at once
    wall = per_cell * N * M * n_missing / n_tasks / lanes
    from robust_imdp.pipeline.preflight import load_text

    # the pilot's speed is this machine's at its load now (not known for a remote cluster)
    remote = run.client is not None or run.scheduler_address is not None
    log.info(f"pre-flight: {N:,} cells x {M} modes x {n} outputs = {N * M * n:,} cell bounds; about "
             f"{wall * sched.n_workers:.0f} s of work ({per_cell * threads * 1e3:.2f} ms per cell and mode "
             f"on one core), about {wall:.0f} s on {sched.n_workers} core{'s' if sched.n_workers > 1 else ''}"
             + ("" if remote else f" {load_text(sched.n_workers)}"))
    return sched


class _PartWriter:
    """Saves the bound chunks (``write_cache_entry``: written, flushed to disk, renamed) in one thread beside the
    stage, in the order they complete, so the stage's thread does not wait for the disk (about 7 ms of fsync per
    chunk) while the cores idle. :meth:`put` raises the first failed write (as a write in the loop did), and waits
    while :data:`QUEUED` chunks are not yet on disk (memory); :meth:`close` waits for every queued write and raises
    a failure; it is called also when the stage stops early, so every chunk computed until then is kept."""

    QUEUED = 16

    def __init__(self):
        import queue
        import threading

        self._q = queue.Queue(maxsize=self.QUEUED)
        self.error = None
        self._thread = threading.Thread(target=self._loop, daemon=True, name="robust-imdp bound chunks writer")
        self._thread.start()

    def _loop(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            if self.error is None:
                path, res = item
                try:
                    write_cache_entry(path, lambda tmp, r=res: _savez(tmp, {k: np.asarray(v) for k, v in r.items()}))
                except BaseException as exc:  # raised in the stage's thread (put / close)
                    self.error = exc

    def put(self, path, res) -> None:
        if self.error is not None:
            raise self.error
        self._q.put((path, res))

    def close(self, raise_error: bool = True) -> None:
        self._q.put(None)
        self._thread.join()
        if raise_error and self.error is not None:
            raise self.error


def _run_missing(problem: Problem, data, partition, settings, local, extras, tasks, missing, chunk: int,
                 results: dict, parts_dir, run: _Run, log: _Log, check=None) -> None:
    """Bound the ``missing`` chunks on the run's scheduler into ``results``, each saved as it completes; ``check``:
    the assumption check running beside them (``bound_stage._PendingCheck``), whose refusal stops the stage."""
    sched = _preflight(problem, data, partition, settings, local, extras, run, len(missing), len(tasks), log)
    shared = _share_data(sched, data)
    args = _task_args(problem, shared, partition.cells_lower, partition.cells_upper, local, extras, missing, chunk)
    t0 = time.perf_counter()
    writer = None if parts_dir is None else _PartWriter()
    ok = False
    try:
        for i, res in sched.run_overlapping(_bound_task, args, settings):  # thread-safe tasks
            key = missing[i]
            if "scales" in settings:  # saved with the chunk: a resumed chunk says which scales it holds
                res = dict(res, scales=np.asarray(settings["scales"], float))
            results[key] = res
            if writer is not None:  # saved as it completes (beside): an interrupted run resumes from here
                writer.put(parts_dir / f"m{key[0]}-c{key[1]}-{chunk}.npz", res)
            log.progress("bound", len(results), len(tasks), t0, resumed=len(tasks) - len(missing))
            if check is not None:
                check.raise_if_refused()
        ok = True
    finally:
        if writer is not None:  # every chunk computed is on disk before the stage ends or stops
            writer.close(raise_error=ok)


def _assemble(results: dict, M: int, N: int, n: int, chunk: int):
    """The chunks' ranges as (M, N, n) arrays in task order, and the count of unconverged vertex problems."""
    lower = np.empty((M, N, n))
    upper = np.empty((M, N, n))
    support = np.empty((M, N, n), dtype=np.int64)
    unconv = 0
    for (u, s0), r in results.items():
        sl = slice(s0, min(N, s0 + chunk))
        lower[u, sl], upper[u, sl], support[u, sl] = r["lower"], r["upper"], r["support"]
        unconv += int(r["n_unconverged"])
    return lower, upper, support, unconv


def _assemble_scaled(results: dict, scales, M: int, N: int, n: int, chunk: int):
    """The chunks' boxes at every scale of B as (n_scales, M, N, n) arrays (``rkhs.bound_chunk``'s ``scaled_*``)."""
    lower = np.empty((len(scales), M, N, n))
    upper = np.empty((len(scales), M, N, n))
    for (u, s0), r in results.items():
        sl = slice(s0, min(N, s0 + chunk))
        lower[:, u, sl], upper[:, u, sl] = r["scaled_lower"], r["scaled_upper"]
    return lower, upper


def _statement(confidence: float, noise_bound, data_fail: float, iid_delta: float) -> str:
    """What the boxes guarantee, on which events over the data."""
    if confidence >= 1.0:
        return ("with probability 1, if every unknown component is within the misspecification of a "
                "function of RKHS norm <= rkhs_bound and the data noise is within its bound")
    events = []
    if data_fail > 0:
        events.append(f"the data noise within {np.round(noise_bound, 6).tolist()} (probability >= "
                      f"{1 - data_fail:g})")
    if iid_delta > 0:
        events.append(f"the sub-Gaussian bound of independent noise (probability >= {1 - iid_delta:g})")
    return (f"with probability >= {confidence:g} over the data ({'; '.join(events)}), if every "
            "unknown component is within the misspecification of a function of RKHS norm <= rkhs_bound")


def _grid_chunk(run: _Run) -> int:
    """The bound stage's default cells per task: :data:`CHUNK_CELLS_IN_PROCESS` where the run's scheduler is this
    process (``parallel.open_scheduler``: no client, no address, ``workers`` None or 1), else :data:`CHUNK_CELLS`."""
    in_process = (run.client is None and run.scheduler_address is None
                  and (run.workers is None or int(run.workers) == 1))
    return CHUNK_CELLS_IN_PROCESS if in_process else CHUNK_CELLS


def learn_and_bound(problem: Problem, partition, log: _Log, run: "_Run | None" = None, cache_dir=None):
    """The RKHS route's bound stage over the grid's cells: ``(cell_bounds, None, diagnostics)``.

    Chunks of :data:`CHUNK_CELLS` cells per mode (in process :data:`CHUNK_CELLS_IN_PROCESS`), saved under the bounds' cache key as they complete
    (an interrupted run resumes from them); the assumption check and the diagnostics are
    ``bound_stage``'s.
    """
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.bounds.rkhs import hoeffding_factor

    run = run if run is not None else _Run()
    # the assumption check runs beside the bound stage where the scheduler can (bound_stage._start_check)
    data, known_ranges, check = _prepare_beside(problem, partition, log, cache_dir, run)
    data_fail, iid_delta = _failure_budget(problem)
    noise_bound = _data_noise_bound(problem, data, data_fail)
    M, n, N = len(problem.mode_names), len(problem.space_lower), partition.n_cells
    iid_theta = problem.noise.sub_gaussian_parameter() if problem.iid_noise else None
    settings = _chunk_settings(problem, noise_bound, iid_theta,
                               None if iid_theta is None else hoeffding_factor(M * n * N * 2 ** n, iid_delta))
    # the assumption margins (pipeline/margins.py): the boxes at scale * B from the same weights, when asked
    scales = getattr(run, "margin_scales", None)
    if scales is not None:
        settings["scales"] = tuple(float(s) for s in scales)
    chunk = _chunk_cells(run, N, _grid_chunk(run))
    tasks = [(u, s0) for u in range(M) for s0 in range(0, N, chunk)]
    local, extras = _mode_settings(problem, data, partition, noise_bound)
    if any(loc is not None for loc in local):
        log.info("local weights: " + ", ".join(f"mode {problem.mode_names[u]}: "
                                               + ("all points" if loc is None else f"{loc[0]} nearest points")
                                               for u, loc in enumerate(local)))
    parts_dir = None if cache_dir is None else Path(cache_dir) / f"bounds-{bounds_key(problem)}.parts"
    results = _resume(parts_dir, tasks, chunk, N, n, log, settings.get("scales"))
    missing = [t for t in tasks if t not in results]
    with log.stage("bound"):
        if missing:
            _run_missing(problem, data, partition, settings, local, extras, tasks, missing, chunk, results,
                         parts_dir, run, log, check)
    checks, check_noise = check.result()
    lower, upper, support, unconv = _assemble(results, M, N, n, chunk)
    _finish_ranges(lower, upper, known_ranges)
    if scales is not None:  # the margins' boxes: the known part's range added at every scale too
        s_lower, s_upper = _assemble_scaled(results, settings["scales"], M, N, n, chunk)
        for j in range(len(settings["scales"])):
            _finish_ranges(s_lower[j], s_upper[j], known_ranges)
        run.scaled_bounds = (settings["scales"], s_lower, s_upper)
    confidence = 1.0 - data_fail - (iid_delta if iid_theta is not None else 0.0)
    log.info(f"bounded images of {N} cells x {M} modes x {n} outputs ({problem.error_bound} weights)")
    statement = _statement(confidence, noise_bound, data_fail, iid_delta)
    cell_bounds = CellBounds(lower, upper, None)
    diag = _diagnostics(problem, partition, cell_bounds, data, checks, check_noise, confidence, statement)
    diag["support_median"] = float(np.median(support))
    if any(r is not None for r in known_ranges):
        diag["known_part_gap"] = _known_gap(problem, partition, known_ranges)
    if unconv:
        diag["unconverged_vertex_problems"] = int(unconv)
    return cell_bounds, None, diag


# ---------------------------------------------------------------------------------------------- new cells
def cell_bounder(problem: Problem, partition, log: _Log, run: _Run, task=None):
    """``bound_cells(lower, upper) -> (image_lower, image_upper)`` for new cells: the bound stage's settings.

    The same data, noise bound (one event over the data, whatever the cells), weights and local
    pools as :func:`learn_and_bound`, so a new cell's box holds on the same event as the grid's.
    ``task``: the function each chunk runs (:func:`_bound_task`; the advice passes :func:`_pilot_task`).
    """
    data = _residual_data(problem)
    data_fail, _ = _failure_budget(problem)
    noise_bound = _data_noise_bound(problem, data, data_fail)
    settings = _chunk_settings(problem, noise_bound)
    # the assumption margins of a refined result (pipeline/margins.py): the run's own problem's new cells are
    # certified at the larger factors of B too (not the advice's pilots, whose problems differ)
    scales = getattr(run, "margin_scales", None) if getattr(run, "margin_problem", None) is problem else None
    if scales is not None:
        settings["scales"] = tuple(scales)
        if not hasattr(run, "scaled_new_cells"):
            run.scaled_new_cells = {}
    local, extras = _mode_settings(problem, data, partition, noise_bound)
    sched = run.scheduler(log)
    shared = _share_data(sched, data)
    M, n = len(problem.mode_names), len(problem.space_lower)

    def bound_cells(lower, upper):
        k = lower.shape[0]
        chunk = _chunk_cells(run, k, CHUNK_CELLS)
        tasks = [(u, s0) for u in range(M) for s0 in range(0, k, chunk)]
        args = _task_args(problem, shared, lower, upper, local, extras, tasks, chunk)
        lo, hi = np.empty((M, k, n)), np.empty((M, k, n))
        if scales is not None:
            slo, shi = np.empty((len(scales), M, k, n)), np.empty((len(scales), M, k, n))
        for i, res in sched.run(task or _bound_task, args, settings):
            u, s0 = tasks[i]
            lo[u, s0:s0 + chunk], hi[u, s0:s0 + chunk] = res["lower"], res["upper"]
            if scales is not None:
                slo[:, u, s0:s0 + chunk], shi[:, u, s0:s0 + chunk] = res["scaled_lower"], res["scaled_upper"]
        known = _known_ranges(problem, lower, upper)
        _finish_ranges(lo, hi, known)
        if scales is not None:  # kept by the cell's bounds for the margins of the refined cells
            for j in range(len(scales)):
                _finish_ranges(slo[j], shi[j], known)
            for q in range(k):
                run.scaled_new_cells[(np.asarray(lower[q], float).tobytes(), np.asarray(upper[q], float).tobytes())] = (
                    slo[:, :, q].copy(), shi[:, :, q].copy())
        return lo, hi

    return bound_cells
