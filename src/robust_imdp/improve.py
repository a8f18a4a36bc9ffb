"""The sampling loop: suggest samples, simulate them, re-bound only the cells the new data can tighten, re-solve.

:func:`improve` starts from a problem's data (or from an interrupted loop's state) and repeats, round by round:

1. **suggest** ``budget / rounds`` sample requests (``synthesis.suggest.suggest_samples``);
2. **simulate** one step of the user's true system from each request (``step(x, modes, rng)``, the
   interface of ``validate.simulate``); a simulator that raises, returns another shape, NaN / inf
   or states outside X is refused with a message naming the round and the request;
3. **append** the samples to the loop's data file with their ``round`` (written under a temporary
   name and renamed: the file is never half-written);
4. **check** the assumption with *all* the data (new data may refute the RKHS bound B);
5. **re-bound** only the cells whose certificates the new points can change: with local weights
   the cells whose pool of nearest points now holds a new point, otherwise the cells whose error
   radius the new points shrink by more than :data:`REBOUND_TOL` of the cell's half-width (the power
   function of ``synthesis.suggest``, with and without them); each new box is intersected with the
   cell's previous box;
6. **re-abstract** the rows of the re-bounded cells (a row depends only on its own cell's image
   box and the partition: ``abstraction.rows.abstract_rows``) and **re-solve**.

Soundness. The route is the deterministic bound under bounded noise (``error_bound`` ``"optimal"``
or ``"ridge"``, ``iid_noise = false``): a cell's certificate holds for *any* subset of the data and
for inputs chosen in any way, adaptively from earlier data included. So a box kept from an earlier
round (certified from fewer data) stays valid, a new box is valid, and so is their intersection.
The iid route assumes inputs chosen independently of the noise, which adaptive requests are not:
it is refused (``io.data_file.ADAPTIVE_IID_MESSAGE``); unbounded noise too (its data-noise event
depends on the number of samples, so the events of boxes of different rounds do not combine into
the stated confidence). ``diagnostics.statement`` says so.

Interrupting and resuming. After each round the cell boxes are saved (``improve-state.npz``) and
``result.json`` is rewritten, both atomically, after the data file: the last complete round's
result stays valid. Run again with the same output directory: samples already in the data file
but not yet bounded (interrupted after the append) are bounded first, then the remaining rounds run.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["ImproveRound", "ImproveResult", "improve", "REBOUND_TOL", "STATE_FILE", "DATA_FILE"]

#: Without local weights, a cell is re-bounded when the new points lower the RKHS term of its error
#: radius at its centre by more than this fraction of its smallest half-width (the power-function
#: estimate of ``synthesis.suggest``, eq. S2); the others keep their box: sound for any subset of the
#: data, and the new points barely move them.
REBOUND_TOL = 0.01
#: Most points of a mode used for that estimate (an evenly spaced subset beyond it, as in suggest).
MAX_POWER_POINTS = 2000
#: The loop's saved state (cell boxes, last complete round) and its data file, in the output directory.
STATE_FILE = "improve-state.npz"
DATA_FILE = "data.csv"
#: Cells per bound task of a round (the new cells of one mode).
ROUND_CHUNK = 256
#: What the statement adds about the adaptively chosen inputs.
ADAPTIVE_NOTE = ("; inputs of rounds > 0 were chosen from earlier data (robust-imdp improve): the deterministic "
                 "bound holds for any inputs, and a cell's box kept from an earlier round was certified from a "
                 "subset of the data")


@dataclass(frozen=True)
class ImproveRound:
    """One round of :func:`improve` (round 0: the starting data).

    Attributes
    ----------
    round, added, n_data : int
        Round number, samples added in the round, samples in the data after it.
    counts : dict ``{"yes", "no", "maybe"} -> int`` (cells)
    rebound : int
        Cell bounds (cells x modes) recomputed in the round.
    seconds : dict
        ``suggest``, ``simulate``, ``write``, ``check``, ``bound``, ``abstract``, ``solve``, ``total``.
    """

    round: int
    added: int
    n_data: int
    counts: dict
    rebound: int
    seconds: dict

    def line(self) -> str:
        c, s = self.counts, self.seconds
        return (f"round {self.round}: +{self.added} samples ({self.n_data} in all), {self.rebound} cell bounds "
                f"re-bounded; Q_yes {c['yes']}  Q_no {c['no']}  Q_? {c['maybe']}; {s['total']:.1f} s (bound "
                f"{s['bound']:.1f}, solve {s['solve']:.1f})")

    def to_dict(self) -> dict:
        return {"round": self.round, "added": self.added, "n_data": self.n_data, "counts": dict(self.counts),
                "rebound": self.rebound, "seconds": dict(self.seconds)}


@dataclass(frozen=True, eq=False)
class ImproveResult:
    """Output of :func:`improve`: the last round's result, its cell boxes, the rounds and why the loop stopped."""

    result: object
    cell_bounds: object
    rounds: tuple
    stopped: str
    data_file: Path | None = None
    history: list = field(default_factory=list, repr=False)  # per round: (image_lower, image_upper) if kept


# ---------------------------------------------------------------------------------------------- checks
def _refuse_unsupported(problem) -> None:
    """The loop needs the deterministic bound under bounded noise on the grid (see the module docstring)."""
    from robust_imdp.io.data_file import ADAPTIVE_IID_MESSAGE

    if problem.iid_noise:
        raise InvalidInputError("improve: " + ADAPTIVE_IID_MESSAGE)
    if problem.error_bound not in ("optimal", "ridge"):
        raise InvalidInputError(f"improve needs error_bound 'optimal' or 'ridge' (the deterministic bound, valid for "
                                f"adaptively chosen inputs); got {problem.error_bound!r}")
    if not getattr(problem.noise, "bounded", False):
        raise InvalidInputError(
            "improve needs bounded noise: with unbounded noise the data-noise event depends on the number of samples, "
            "so boxes certified in different rounds do not share one event")
    if problem.refine is not None:
        raise InvalidInputError("improve works on the grid: remove [refine] (refine the improved result afterwards)")


def _request_text(k: int, x, mode: str) -> str:
    return f"request {k + 1} (x = {np.asarray(x).tolist()}, mode {mode!r})"


def _simulate(true_system, xs, modes, names, rng, rnd: int, lower, upper, allow_outside: bool) -> np.ndarray:
    """One step of ``true_system`` from every request, checked; errors name the round and the request."""
    sys_names = list(true_system.mode_names)
    missing = [m for m in names if m not in sys_names]
    if missing:
        raise InvalidInputError(f"improve: the true system has no modes {missing}; it has {sys_names}")
    to_sys = np.array([sys_names.index(m) for m in names], dtype=np.int64)
    k, n = xs.shape
    try:
        raw = true_system.step(xs.copy(), to_sys[modes], rng)
    except KeyboardInterrupt:
        raise
    except Exception as exc:
        raise InvalidInputError(f"improve round {rnd}: the true system's step raised {type(exc).__name__}: {exc} "
                                f"(on the round's {k} requests; the first is {_request_text(0, xs[0], names[modes[0]])}"
                                "); the previous round's result is kept") from exc
    try:
        xn = np.asarray(raw, dtype=float)
    except (TypeError, ValueError):
        xn = np.asarray(None)
    if xn.shape != (k, n):
        raise DimensionError(f"improve round {rnd}: the true system's step must return the next states as a ({k}, "
                             f"{n}) float array, one row per request; got {type(raw).__name__} of shape "
                             f"{getattr(xn, 'shape', None)}; the previous round's result is kept")
    bad = np.flatnonzero(~np.all(np.isfinite(xn), axis=1))
    if bad.size:
        r = int(bad[0])
        raise InvalidInputError(f"improve round {rnd}: the true system returned NaN or inf for {bad.size} of {k} "
                                f"requests (first: {_request_text(r, xs[r], names[modes[r]])} -> {xn[r].tolist()}); "
                                "the previous round's result is kept")
    out = np.flatnonzero(np.any((xn < lower) | (xn > upper), axis=1))
    if out.size and not allow_outside:
        r = int(out[0])
        raise InvalidInputError(f"improve round {rnd}: the true system returned states outside X = [{lower.tolist()}, "
                                f"{upper.tolist()}] for {out.size} of {k} requests (first: "
                                f"{_request_text(r, xs[r], names[modes[r]])} -> {xn[r].tolist()}); pass "
                                "allow_outside=True (--allow-outside) if the system can leave X; the previous "
                                "round's result is kept")
    return xn


# ---------------------------------------------------------------------------------------------- files
def _write_data(path: Path, data, rounds, names) -> None:
    """The loop's data file with its ``round`` column, written under a temporary name and renamed."""
    from robust_imdp.io.data_file import write_data_file

    tmp = path.with_name(path.name + ".tmp")
    write_data_file(tmp, data.x, data.u, data.x_next, modes=names, rounds=rounds)
    os.replace(tmp, path)


def _save_state(out: Path, cell_bounds, rnd: int, n_data: int, rounds: list, diagnostics: dict) -> None:
    import json

    from robust_imdp.jsonable import jsonable
    from robust_imdp.pipeline.cache import _savez, write_cache_entry

    doc = json.dumps([r.to_dict() for r in rounds])
    write_cache_entry(out / STATE_FILE, lambda tmp: _savez(tmp, {
        "image_lower": cell_bounds.image_lower, "image_upper": cell_bounds.image_upper,
        "round": np.array(rnd), "n_data": np.array(n_data), "rounds": np.array(doc),
        "diagnostics": np.array(json.dumps(jsonable(diagnostics)))}))


def _load_state(out: Path, n_modes: int, n_cells: int, dim: int):
    """(CellBounds, last round, samples bounded, rounds, diagnostics) of an interrupted loop, or None."""
    import json

    from robust_imdp.abstraction.rows import CellBounds

    f = out / STATE_FILE
    if not (f.exists() and (out / DATA_FILE).exists()):
        return None
    with np.load(f, allow_pickle=False) as z:
        lo, hi = np.array(z["image_lower"]), np.array(z["image_upper"])
        rnd, n_data, doc = int(z["round"]), int(z["n_data"]), json.loads(str(z["rounds"]))
        diagnostics = json.loads(str(z["diagnostics"]))
    if lo.shape != (n_modes, n_cells, dim):
        raise InvalidInputError(f"improve: {f} holds boxes of shape {lo.shape}, not ({n_modes}, {n_cells}, {dim}) "
                                "of this problem's grid; use another output directory")
    rounds = [ImproveRound(d["round"], d["added"], d["n_data"], d["counts"], d["rebound"], d["seconds"]) for d in doc]
    return CellBounds(lo, hi, None), rnd, n_data, rounds, diagnostics


def _read_loop_data(out: Path, problem):
    from robust_imdp.io.data_file import read_data_file, read_rounds
    from robust_imdp.models.system import Dataset

    names = list(problem.mode_names)
    x, u, xn, _ = read_data_file(out / DATA_FILE, names, len(problem.space_lower))
    return Dataset(x, u, xn, modes=tuple(names)), read_rounds(out / DATA_FILE)


# ---------------------------------------------------------------------------------------------- re-bounding
def _power(points, data, inv_l2, lam: float) -> np.ndarray:
    """The power function at ``points`` (:func:`robust_imdp.synthesis.suggest.power_function`)."""
    from robust_imdp.synthesis.suggest import power_function

    return power_function(points, data, inv_l2, lam, MAX_POWER_POINTS)


def _affected(problem, partition, data, n_old: int) -> list:
    """Per mode: the cells whose certificate the samples ``n_old..`` of ``data`` can change (module step 5)."""
    from robust_imdp.bounds.rkhs_local import local_pools
    from robust_imdp.pipeline.bound_rkhs import _base_settings, _data_noise_bound, _local_settings
    from robust_imdp.pipeline.bound_stage import _failure_budget, _residual_data
    from robust_imdp.synthesis.suggest import _assumption

    res = _residual_data(problem)
    local = _local_settings(problem, res, partition, _data_noise_bound(problem, res, _failure_budget(problem)[0]))
    B, inv_l2, floor = _assumption(problem)
    lo, up = partition.cells_lower, partition.cells_upper
    centre, tol = 0.5 * (lo + up), REBOUND_TOL * 0.5 * np.min(up - lo, axis=1)
    new = np.arange(data.u.shape[0]) >= n_old
    out = []
    for u in range(len(problem.mode_names)):
        x = res[u][0]
        fresh = np.flatnonzero(new[data.u == u])
        if fresh.size == 0 or B[u] <= 0:
            out.append(np.zeros(0, np.int64))
        elif local[u] is not None:  # the cells whose pool gained a point
            pools = local_pools(x, lo, up, _base_settings(problem)["lengthscale"], local[u][0])
            out.append(np.flatnonzero(np.any(pools >= fresh.min(), axis=1)))
        else:
            lam = max((floor[u] / B[u]) ** 2, 1e-10)
            before = np.sqrt(_power(centre, x[:fresh.min()], inv_l2[u], lam))
            after = np.sqrt(_power(centre, x, inv_l2[u], lam))
            out.append(np.flatnonzero(B[u] * (before - after) > tol))
    return out


def _rebound(problem, partition, cell_bounds, cells: list, log, run):
    """New boxes of ``cells[u]`` under mode u (all data), intersected with the previous ones: (CellBounds, count)."""
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.bounds.rkhs import check_ranges
    from robust_imdp.pipeline.bound_rkhs import (_bound_task, _chunk_settings, _data_noise_bound, _mode_settings,
                                                 _share_data, _task_args)
    from robust_imdp.pipeline.bound_stage import _add_known_range, _failure_budget, _known_ranges, _residual_data

    data = _residual_data(problem)
    noise_bound = _data_noise_bound(problem, data, _failure_budget(problem)[0])
    settings = _chunk_settings(problem, noise_bound)
    local, extras = _mode_settings(problem, data, partition, noise_bound)
    sched = run.scheduler(log)
    shared = _share_data(sched, data)
    ilo, ihi = cell_bounds.image_lower.copy(), cell_bounds.image_upper.copy()
    for u, q in enumerate(cells):
        if q.size == 0:
            continue
        lower, upper = partition.cells_lower[q], partition.cells_upper[q]
        starts = list(range(0, q.size, ROUND_CHUNK))
        args = _task_args(problem, shared, lower, upper, local, extras, [(u, s0) for s0 in starts], ROUND_CHUNK)
        lo, hi = np.empty((q.size, ilo.shape[2])), np.empty((q.size, ilo.shape[2]))
        for i, res in sched.run(_bound_task, args, settings):
            sl = slice(starts[i], starts[i] + ROUND_CHUNK)
            lo[sl], hi[sl] = res["lower"], res["upper"]
        check_ranges(lo, hi, u)
        known = _known_ranges(problem, lower, upper)[u]
        if known is not None:
            _add_known_range(lo, hi, known)
        # both boxes contain the image of f_u + g_u over the cell: so does their intersection (max/min are exact)
        ilo[u, q], ihi[u, q] = np.maximum(lo, ilo[u, q]), np.minimum(hi, ihi[u, q])
    return CellBounds(ilo, ihi, None), int(sum(q.size for q in cells))


def _rebuild(partition, rows, cell_bounds, cells, problem):
    """The abstraction's rows with those of ``cells`` recomputed from their new boxes (every other row kept)."""
    from robust_imdp.abstraction.rows import CellBounds, abstract_rows, join_rows, select_rows

    N = partition.n_cells
    redo = np.unique(np.concatenate(cells)) if cells else np.zeros(0, np.int64)
    if redo.size == 0:
        return rows
    keep = np.setdiff1d(np.arange(N), redo)
    new_rows = abstract_rows(partition, CellBounds(cell_bounds.image_lower[:, redo], cell_bounds.image_upper[:, redo],
                                                   None), problem.noise, None, **_abstraction_options(problem))
    joined = join_rows([select_rows(rows, keep), new_rows]) if keep.size else new_rows
    order = np.empty(N, dtype=np.int64)
    order[np.concatenate([keep, redo])] = np.arange(N)
    return select_rows(joined, order)


def _abstraction_options(problem) -> dict:
    return {"eta": problem.eta, "eps_rule": problem.eps_rule, "combine": problem.combine}


# ---------------------------------------------------------------------------------------------- the loop
@dataclass
class _Loop:
    """The loop's fixed parts and its current state."""

    problem: object
    partition: object
    dfa: object
    log: object
    run: object
    out: Path | None
    cell_bounds: object = None
    rows: object = None
    rounds: list = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    result: object = None
    data_rounds: np.ndarray = None

    def solve(self, timer: dict):
        """Assemble the rows, solve, and the Result with the rounds in its diagnostics."""
        from robust_imdp.abstraction.rows import assemble_abstraction
        from robust_imdp.pipeline.result import Result
        from robust_imdp.pipeline.run import _parameters, _synthesize

        t0 = time.perf_counter()
        abstraction = assemble_abstraction(self.partition, [self.rows])
        timer["abstract"] = timer.get("abstract", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        syn, classes = _synthesize(self.problem, self.partition, abstraction, self.dfa, self.log)
        timer["solve"] = time.perf_counter() - t0
        self.result = Result(problem=self.problem, partition=self.partition, abstraction=abstraction, dfa=self.dfa,
                             synthesis=syn, class_names=classes, timings=dict(self.log.timings),
                             parameters=_parameters(self.problem, abstraction), diagnostics=self.diagnostics)
        return self.result

    def record(self, rnd: int, added: int, rebound: int, timer: dict) -> ImproveRound:
        from robust_imdp.io.files import save_result

        c = np.asarray(self.result.class_names)
        timer["total"] = sum(v for k, v in timer.items() if k != "total")
        r = ImproveRound(rnd, added, int(self.problem.data.u.shape[0]),
                         {k: int(np.sum(c == k)) for k in ("yes", "no", "maybe")}, rebound, dict(timer))
        self.rounds.append(r)
        self.diagnostics["improve"] = {"rounds": [x.to_dict() for x in self.rounds],
                                       "data_file": None if self.out is None else str(self.out / DATA_FILE)}
        if self.out is not None:  # the boxes first, then result.json: a result on disk always has its state
            _save_state(self.out, self.cell_bounds, rnd, r.n_data, self.rounds, self.diagnostics)
            save_result(self.result, self.out)
        self.log.info(r.line())
        return r


def _start(loop: _Loop, resume) -> int:
    """Round 0 (bound the grid, abstract, solve) or the interrupted loop's state; returns the last round."""
    from robust_imdp.abstraction.rows import abstract_rows
    from robust_imdp.pipeline.bound_stage import _learn_and_bound

    problem = loop.problem
    timer: dict = {}
    if resume is None:
        t0 = time.perf_counter()
        cache = None if loop.out is None else loop.out / "cache"
        loop.cell_bounds, _, diag = _learn_and_bound(problem, loop.partition, loop.log, loop.run, cache)
        timer["bound"] = time.perf_counter() - t0
        loop.diagnostics = dict(diag)
        last, added = 0, 0
    else:
        loop.cell_bounds, last, _, loop.rounds, loop.diagnostics = resume
        added = None
    t0 = time.perf_counter()
    loop.rows = abstract_rows(loop.partition, loop.cell_bounds, problem.noise, None, **_abstraction_options(problem))
    timer["abstract"] = time.perf_counter() - t0
    loop.solve(timer)
    if added is not None:
        loop.record(0, 0, loop.partition.n_cells * len(problem.mode_names), timer)
    return last


def _update(loop: _Loop, data, n_old: int, rnd: int, timer: dict) -> int:
    """Steps 4-6 for the samples ``n_old..`` of ``data``: check, re-bound, re-abstract, re-solve."""
    from robust_imdp.pipeline.bound_stage import _check_assumption, _diagnostics, _residual_data, _failure_budget
    from robust_imdp.pipeline.bound_rkhs import _data_noise_bound, _statement

    problem = loop.problem = loop.problem.replace(data=data)
    t0 = time.perf_counter()
    res = _residual_data(problem)
    checks, check_noise = _check_assumption(problem, res, loop.log, None)  # all data: new ones may refute B
    timer["check"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    cells = _affected(problem, loop.partition, data, n_old)
    loop.cell_bounds, rebound = _rebound(problem, loop.partition, loop.cell_bounds, cells, loop.log, loop.run)
    timer["bound"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    loop.rows = _rebuild(loop.partition, loop.rows, loop.cell_bounds, cells, problem)
    timer["abstract"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    data_fail = _failure_budget(problem)[0]
    statement = _statement(1.0 - data_fail, _data_noise_bound(problem, res, data_fail), data_fail, 0.0)
    loop.diagnostics = _diagnostics(problem, loop.partition, loop.cell_bounds, res, checks, check_noise,
                                    1.0 - data_fail, statement + ADAPTIVE_NOTE)
    timer["diagnostics"] = time.perf_counter() - t0
    loop.solve(timer)
    return rebound


def _append(data, xs, us, xn):
    from robust_imdp.models.system import Dataset

    return Dataset(np.vstack([data.x, xs]), np.concatenate([data.u, us]), np.vstack([data.x_next, xn]),
                   modes=data.mode_names)


def _per_round(budget: int, rounds: int, rnd: int) -> int:
    """Samples of round ``rnd`` (1-based): ``budget // rounds``, the remainder spread over the first rounds."""
    return budget // rounds + (1 if rnd <= budget % rounds else 0)


def improve(problem, true_system, budget: int, *, rounds: int = 1, out=None, seed: int = 0, progress: bool = True,
            allow_outside: bool = False, keep_history: bool = False, workers: int | None = None,
            on_round=None) -> ImproveResult:
    """Collect ``budget`` samples in ``rounds`` rounds where they help most, re-bounding incrementally.

    Parameters
    ----------
    problem : Problem
        Its data are the starting data (ignored when ``out`` holds an interrupted loop).
    true_system : object
        ``mode_names`` (sequence of str) and ``step(x (k, n), modes (k,) int, rng) -> (k, n)``
        (``modes`` index ``true_system.mode_names``), as for ``validate.simulate``.
    budget, rounds : int
        Samples to add in all, and in how many rounds (``budget // rounds`` each, the remainder
        to the first rounds).
    out : str or Path, optional
        Directory of the loop's data file (``data.csv``, with a ``round`` column), its state and
        ``result.json`` (rewritten after every round); an interrupted loop resumes from it.
    seed : int
        Round r simulates with ``np.random.default_rng([seed, r])`` (the same after a resume).
    allow_outside : bool
        Accept next states outside X (otherwise refused as a simulator error).
    keep_history : bool
        Keep every round's image boxes in ``ImproveResult.history`` (for tests and benchmarks).
    on_round : callable ``(ImproveRound, Result) -> None``, optional
        Called after every completed round (round 0 included), after its files are written.

    Returns
    -------
    ImproveResult
    """
    from robust_imdp.models.geometry import Box, Partition
    from robust_imdp.pipeline.preflight import _check_atoms, _region_objects
    from robust_imdp.pipeline.runtime import _Log, _Run
    from robust_imdp.spec.api import to_dfa
    from robust_imdp.synthesis.suggest import suggest_samples

    for name, v, least in (("budget", budget, 1), ("rounds", rounds, 1)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < least:
            raise InvalidInputError(f"improve: {name} must be an integer >= {least}; got {v!r}")
    _refuse_unsupported(problem)
    out = None if out is None else Path(out)
    log = _Log(progress)
    dfa = to_dfa(problem.formula)
    _check_atoms(dfa, problem)
    partition = Partition(Box(problem.space_lower, problem.space_upper), problem.cell_size, _region_objects(problem),
                          names=problem.dim_names, periodic=problem.periodic)
    M, n = len(problem.mode_names), len(problem.space_lower)
    resume = None if out is None else _load_state(out, M, partition.n_cells, n)
    if resume is not None:
        data, data_rounds = _read_loop_data(out, problem)
        problem = problem.replace(data=data)
        log.info(f"improve: resuming after round {resume[1]} from {out}")
    else:
        data_rounds = np.zeros(problem.data.u.shape[0], dtype=np.int64)
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            _write_data(out / DATA_FILE, problem.data, data_rounds, problem.mode_names)
    run = _Run(workers=workers)
    loop = _Loop(problem, partition, dfa, log, run, out, data_rounds=data_rounds)
    history = []
    try:
        if resume is not None:  # bound what the data file has beyond the state (at most one round's samples)
            loop.problem = problem.replace(data=_first(data, resume[2]))
        last = _start(loop, resume)
        if resume is not None and data.u.shape[0] > resume[2]:
            timer: dict = {}
            rebound = _update(loop, data, resume[2], last + 1, timer)
            last += 1
            loop.record(last, data.u.shape[0] - resume[2], rebound, timer)
        elif resume is not None:
            loop.problem = problem
        if keep_history:
            history.append((loop.cell_bounds.image_lower.copy(), loop.cell_bounds.image_upper.copy()))
        if on_round is not None:
            on_round(loop.rounds[-1], loop.result)
        stopped = "budget spent"
        names = list(problem.mode_names)
        for rnd in range(last + 1, rounds + 1):
            timer = {}
            t0 = time.perf_counter()
            reqs = suggest_samples(loop.result, _per_round(budget, rounds, rnd))
            timer["suggest"] = time.perf_counter() - t0
            if not reqs:
                stopped = "no undecided cells"
                break
            xs = np.array([r.x for r in reqs], dtype=float)
            us = np.array([names.index(r.mode) for r in reqs], dtype=np.int64)
            t0 = time.perf_counter()
            xn = _simulate(true_system, xs, us, names, np.random.default_rng([int(seed), rnd]), rnd,
                           np.asarray(problem.space_lower, float), np.asarray(problem.space_upper, float),
                           allow_outside)
            timer["simulate"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            n_old = loop.problem.data.u.shape[0]
            data = _append(loop.problem.data, xs, us, xn)
            loop.data_rounds = np.concatenate([loop.data_rounds, np.full(len(us), rnd, dtype=np.int64)])
            if out is not None:
                _write_data(out / DATA_FILE, data, loop.data_rounds, names)
            timer["write"] = time.perf_counter() - t0
            rebound = _update(loop, data, n_old, rnd, timer)
            loop.record(rnd, len(us), rebound, timer)
            if keep_history:
                history.append((loop.cell_bounds.image_lower.copy(), loop.cell_bounds.image_upper.copy()))
            if on_round is not None:
                on_round(loop.rounds[-1], loop.result)
    finally:
        run.close()
    return ImproveResult(result=loop.result, cell_bounds=loop.cell_bounds, rounds=tuple(loop.rounds), stopped=stopped,
                         data_file=None if out is None else out / DATA_FILE, history=history)


def _first(data, m: int):
    """The first ``m`` samples of ``data``."""
    from robust_imdp.models.system import Dataset

    return Dataset(data.x[:m], data.u[:m], data.x_next[:m], modes=data.mode_names)


def command(args, true_system) -> int:
    """``robust-imdp improve``: the loop with the command's options; one line per round on stdout."""
    from robust_imdp.io.files import load_problem

    problem = load_problem(args.problem)
    args.interrupt_note = (f"interrupted; the completed rounds are saved in {args.out}: run the same command "
                           "again to resume")
    out = improve(problem, true_system, args.budget, rounds=args.rounds, out=args.out, seed=args.seed,
                  progress=not args.quiet, allow_outside=args.allow_outside,
                  on_round=lambda r, _: print(r.line(), flush=True))
    print(f"improve stopped ({out.stopped}) after round {out.rounds[-1].round}; wrote {args.out / 'result.json'} "
          f"and {out.data_file}")
    return 0
