"""Why cells are undecided, measured: the excess radius and the advice on which lever to pull.

A learned image box must contain ``{f_u(x) + g_u(x) : x in cell}``. Two things make it wide:

* the **spread** of the function itself over the cell (it shrinks with the cell), estimated by the
  range of a data-fitted function ``f_u + g_hat_u`` (:class:`FittedModes`; ``g_hat`` is the
  kernel-ridge fit of the residuals with the problem's SE kernel);
* the **excess**: what the box adds on top of that spread because ``g`` is only known through
  noisy data and ``||g|| <= B`` (it shrinks with more data down to the noise floor).

:func:`excess_radius` is half the difference of the two widths, computed the same way for every
mode and component from the boxes and the fit alone, so it moves with a component when the
components are permuted (the boxes and the fit do; tested).

:func:`advise` estimates, for one solved problem, how much of X each lever would move into Q_yes:

* **finer grid** (cell_size / 2): boxes of the sub-cells = fitted range over the sub-cell plus
  the parent's excess per side, scaled by the sub-cell / parent excess ratio measured on a few
  pilot cells bounded for real (``bound_cells``);
* **more data**: the excess shrunk to its noise floor (``noise_floor``: the data noise bound plus
  tau, the limit of the deterministic bound when data are dense: a constant offset of the noise
  cannot be told apart from ``g``);
* **sub-boxes** (only where the run did not split): ``split_tol`` set so the cells with the largest
  Taylor term are halved once per axis; the excess scaled by the ratio measured on pilot cells
  certified on those sub-boxes; the setting names the grid's mean number of sub-boxes per cell (the
  bound stage's cost grows about with it);
* **larger local pools** (only where a mode's cells are certified with weights on their ``k`` nearest
  data points, ``local_points``): all of a mode's points where it has at most :data:`POOL_ALL_MAX`,
  else ``POOL_FACTOR k``; the excess scaled by the ratio measured on the pilot cells bounded with those
  pools.

``rkhs_bound`` (B) is not a lever: it is an assumption about the true system, and a smaller B gives more
Q_yes only by claiming more about ``g``. The advice states what the guarantee needs instead (``premise``,
written by the caller: ``||g|| <= B`` against the data's certified minimum norm); evidence on B comes from
``robust-imdp calibrate``.

Each estimate re-abstracts (Thm 1, ``abstraction.abstract_rows``) and re-solves (``synthesis.synthesize``)
with the modified boxes; the bound stage runs only on the pilot cells. The estimates are estimates: they
say which lever to try, not what a run will certify (the printed bounds of a run come only from its own
bound stage).

**Cost and budget.** A re-solve costs about the listed transitions of its IMDP times the run's own seconds
per transition. The finer grid has ``2^d`` times the cells and, where the noise or the boxes span many
cells, up to ``2^d`` times the successors per row: 16x the transitions of the run in 2-D, and more seconds
per transition at that size (robot2d_dense of ``benchmarks/advice_cost.py``: 140 million transitions,
136 s, against 4.4 s for the run's 9.6 million). Its transitions are predicted from
:data:`SAMPLE_CELLS` sub-cells abstracted for real. With ``budget_s`` the levers are estimated cheapest
first while their predicted cost fits what is left of the budget; a re-solve still running at its end is
abandoned between chunks of rows; a lever not estimated says why and what it would cost.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from robust_imdp.bounds.fit import FIT_POINTS, FittedModes, _excess_sides, excess_radius, fit_modes  # noqa: F401
from robust_imdp.errors import DimensionError

__all__ = ["FittedModes", "fit_modes", "excess_radius", "Lever", "Advice", "SolveJob", "advise", "advice_line",
           "serial_solver", "job_rows", "job_share", "LEVERS", "MAX_CELLS", "FIT_POINTS", "PILOT_CELLS", "MIN_GAIN",
           "ADVICE_SHARE", "ROW_CHUNK", "SAMPLE_CELLS"]

#: Undecided cells (at most) bounded for real to calibrate an estimate (per lever that needs a pilot).
PILOT_CELLS = 16
#: The pilot takes at most 1/_PILOT_FRACTION of the grid's cells (so it costs at most about
#: 1/_PILOT_FRACTION of the bound stage per lever, times the lever's factor), but at least _PILOT_MIN of them.
_PILOT_FRACTION = 16
_PILOT_MIN = 4
#: Largest number of cells an estimate abstracts and solves with ``advice="auto"`` (the finer grid has 2^d
#: times the cells).
MAX_CELLS = 65536
#: ``advice="auto"`` spends at most this share of the run's time before the advice on it (the budget); the
#: advice is then at most 1/5 of the whole run.
ADVICE_SHARE = 0.25
#: The levers, in the order the advice lists them.
LEVERS = ("finer grid", "more data", "sub-boxes", "larger local pools")
#: The order in which they are estimated, in two rounds: the grid's own levers, then the finer grid (2^d times
#: the cells), planned with the seconds per transition measured on the first round.
_GROUPS = (("more data", "sub-boxes", "larger local pools"), ("finer grid",))
#: The levers the ``tight`` preset (``pipeline.problem.tight_settings``) pulls: the advice line names it when
#: one of them wins.
TIGHT_LEVERS = ("sub-boxes", "larger local pools")
#: A lever wins only if it is estimated to move at least this share of X into Q_yes.
MIN_GAIN = 0.005
#: The local-pools lever (and the ``tight`` preset, ``pipeline.problem.tight_settings``) proposes all of a
#: mode's points up to this many points per mode: in 3-D at 1,024 points, all points cost less than pools of
#: 400 (benchmarks/results/local_pool_size.md) and meet the slack target with sub-boxes (local_auto.md);
#: above it, POOL_FACTOR times today's pool.
POOL_ALL_MAX = 2048
POOL_FACTOR = 4
#: Cells per chunk of rows of a re-solve (the budget is checked between chunks).
ROW_CHUNK = 4096
#: Sub-cells of the finer grid abstracted for real to predict its listed transitions.
SAMPLE_CELLS = 64
#: Seconds per listed transition of a re-solve of at least _LARGE_TRANSITIONS transitions (half a gigabyte of
#: rows), over those measured on smaller ones: memory traffic (robot2d_dense of benchmarks/advice_cost.py, the
#: finer grid's 140 million transitions: 0.97 us each, against 0.46 us for the grid's 9.6 million).
_LARGE_FACTOR = 2.0
_LARGE_TRANSITIONS = 20_000_000
#: Without the run's own seconds per transition (its abstraction came from the cache), a re-solve is taken to
#: cost this many times the rows of the sampled cells (rows are about half of a re-solve at large sizes).
_ROWS_SHARE = 2.0


# ============================================================================ the advice
@dataclass(frozen=True)
class Lever:
    """One lever's estimate: Q_yes share of X (volume) after pulling it, and the gain."""

    name: str
    setting: str
    q_yes_share: float | None
    gain: float | None
    n_cells: int
    excess_ratio: float | None = None
    seconds: float = 0.0
    note: str = ""

    def to_dict(self) -> dict:
        """JSON-able, without ``seconds`` (a result file differs from another only in its timings)."""
        return {"name": self.name, "setting": self.setting, "q_yes_share": self.q_yes_share, "gain": self.gain,
                "n_cells": self.n_cells, "excess_ratio": self.excess_ratio, "note": self.note}


@dataclass(frozen=True)
class Advice:
    """The measured advice: baseline Q_yes share, one :class:`Lever` per lever, the winner.

    ``premise``: what the guarantee needs of the assumption (B is not a lever); ``budget_s``: the seconds the
    advice could spend (None: no budget); ``reused``: estimates taken from an earlier run (the cache)."""

    baseline_share: float
    levers: tuple = field(default_factory=tuple)
    winner: str | None = None
    seconds: float = 0.0
    note: str = ""
    premise: str = ""
    budget_s: float | None = None
    reused: int = 0

    def to_dict(self) -> dict:
        """JSON-able, without ``seconds`` and ``reused`` (the run's ``timings["advice"]`` has the time)."""
        return {"baseline_share": self.baseline_share, "levers": [lv.to_dict() for lv in self.levers],
                "winner": self.winner, "note": self.note, "premise": self.premise, "budget_s": self.budget_s}


def budget_text(budget_s) -> str:
    """The budget rule in words (the advice line and the progress lines)."""
    if budget_s is None:
        return "no budget (advice on)"
    return f"budget {_secs(budget_s)} = {100 * ADVICE_SHARE:.0f} % of the run's time before the advice"


def _secs(x: float) -> str:
    return f"{x:.1f} s" if x < 10 else f"{x:.0f} s"


def advice_line(adv: dict) -> str:
    """One line naming the lever that decides most (from :meth:`Advice.to_dict`)."""
    if not adv:
        return ""
    premise = f"; B: {adv['premise']}" if adv.get("premise") else ""
    if adv.get("winner") is None and not adv.get("levers"):
        return f"advice: {adv.get('note', '')}".rstrip() + premise

    def pct(v):
        return f"{100 * v:.1f} %"

    est = [lv for lv in adv["levers"] if lv["gain"] is not None]
    others = "; ".join(f"{lv['name']} ({lv['setting']}) {100 * lv['gain']:+.1f} points" for lv in est
                       if lv["name"] != adv.get("winner"))
    skipped = "; ".join(f"{lv['name']}: {lv['note']}" for lv in adv["levers"] if lv["gain"] is None)
    if adv.get("winner") is None:
        text = (f"advice: no lever is estimated to move {pct(MIN_GAIN)} of X into Q_yes (now "
                f"{pct(adv['baseline_share'])})" + (f": {others}" if others else ""))
    else:
        w = next(lv for lv in adv["levers"] if lv["name"] == adv["winner"])
        text = (f"advice: {w['name']} ({w['setting']}) decides most: Q_yes {pct(adv['baseline_share'])} -> about "
                f"{pct(w['q_yes_share'])} of X" + (f"; {others}" if others else ""))
        if w["name"] in TIGHT_LEVERS:
            text += "; `run --tight` (Problem.tightened()) sets sub-boxes and larger local pools together"
    if skipped:
        text += f"; not estimated: {skipped}"
    budget = f"; {budget_text(adv['budget_s'])}" if "budget_s" in adv else ""
    return text + premise + f" (estimated by re-solving with modified image boxes{budget})"


def _share(partition, yes) -> float:
    vol = np.prod(np.asarray(partition.cells_upper) - np.asarray(partition.cells_lower), axis=1)
    return float(np.sum(vol[yes]) / np.sum(vol))


# ============================================================================ re-solves
@dataclass(frozen=True, eq=False)
class SolveJob:
    """One re-solve of the advice: the Q_yes share of X of the abstraction of these image boxes.

    Attributes
    ----------
    name : str
        The lever.
    partition : geometry.Partition
    lower, upper : (n_modes, n_cells, n) float arrays
        The modified image boxes.
    transitions : float
        Its predicted listed transitions (the cost model's unit).
    """

    name: str
    partition: object
    lower: np.ndarray
    upper: np.ndarray
    transitions: float


def _factored(partition, options: dict) -> bool:
    """Whether a re-solve on ``partition`` is factored (``options["form"]``, on a grid; docs/factored.md)."""
    from robust_imdp.models.geometry import Partition

    return options.get("form") == "factored" and isinstance(partition, Partition)


def job_lengths(job: "SolveJob", noise, options: dict):
    """The listed lengths per axis of a factored job (``abstraction.factored.axis_lengths`` of all its cells), which
    every chunk of its rows takes; None for a joint one."""
    if not _factored(job.partition, options):
        return None
    from robust_imdp.abstraction.factored import axis_lengths
    from robust_imdp.abstraction.rows import CellBounds

    return axis_lengths(job.partition, CellBounds(job.lower, job.upper, None), noise)


def job_rows(partition, lower, upper, noise, options: dict, k=None):
    """The IMDP rows (``abstraction.abstract_rows`` with the run's options) of the cells whose boxes ``[lower,
    upper]`` ``(n_modes, k, n)`` are given: one chunk of a :class:`SolveJob`. With ``options["form"] ==
    "factored"`` on a grid: the chunk's per-axis marginals (``abstraction.factored.factored_rows``) with the job's
    listed lengths ``k`` (:func:`job_lengths`; None: those of these cells)."""
    from robust_imdp.abstraction.rows import CellBounds, abstract_rows

    cb = CellBounds(lower, upper, None)
    if _factored(partition, options):
        from robust_imdp.abstraction.factored import axis_lengths, factored_rows

        return factored_rows(partition, cb, noise, axis_lengths(partition, cb, noise) if k is None else k)
    return abstract_rows(partition, cb, noise, None, **{k_: v for k_, v in options.items() if k_ != "form"})


def _entries(rows) -> int:
    """Listed transitions of a chunk of rows (joint: its entries; factored: its interval entries)."""
    if hasattr(rows, "col"):
        return int(np.asarray(rows.col).size)
    return int(rows.n_modes * rows.n_cells * sum(k + 1 for k in rows.k))


def job_share(job: SolveJob, pieces, dfa, *, threshold: float, horizon=None, semantics: str = "auto") -> float:
    """Q_yes share (volume) of ``job`` from its rows' chunks in cell order, after the robust solve (its lower value
    alone: ``synthesis.core.robust_lower``, the one solve of a synthesis that Q_yes reads)."""
    from robust_imdp.abstraction.factored import FactoredRows, abstraction_model, assemble_factored
    from robust_imdp.abstraction.rows import assemble_abstraction
    from robust_imdp.synthesis.core import robust_lower

    part = job.partition
    pieces = list(pieces)
    assemble = assemble_factored if pieces and isinstance(pieces[0], FactoredRows) else assemble_abstraction
    ab = assemble(part, pieces)
    kw = {} if semantics == "auto" else {"semantics": semantics}
    low = robust_lower(abstraction_model(ab), part.labels, part.atoms, dfa, horizon=horizon,
                       outside_state=part.outside_state, **kw)
    return _share(part, low >= threshold)  # Q_yes: p_low >= threshold (Sec. 5)


def serial_solver(noise, dfa, *, threshold: float, horizon=None, options=None, semantics: str = "auto"):
    """``solve(jobs, deadline)``: the re-solves one after the other in this process.

    Yields ``(index, share)`` per job, ``share`` None for a job abandoned because ``time.perf_counter()``
    passed ``deadline`` (None: no deadline) between two chunks of its rows.
    """
    opts = dict(options or {})

    def solve(jobs, deadline):
        for i, job in enumerate(jobs):
            pieces = []
            k = job_lengths(job, noise, opts)
            for s0 in range(0, job.partition.n_cells, ROW_CHUNK):
                if deadline is not None and time.perf_counter() > deadline:
                    break
                sl = slice(s0, s0 + ROW_CHUNK)
                pieces.append(job_rows(job.partition, job.lower[:, sl], job.upper[:, sl], noise, opts, k=k))
            else:
                yield i, job_share(job, pieces, dfa, threshold=threshold, horizon=horizon, semantics=semantics)
                continue
            yield i, None

    return solve


def _shrunk(lower, upper, fit_lower, fit_upper, e_lo, e_hi):
    """Boxes ``[fit_lower - e_lo, fit_upper + e_hi]`` kept inside ``[lower, upper]`` (non-empty)."""
    lo = np.clip(fit_lower - e_lo, lower, upper)
    hi = np.clip(fit_upper + e_hi, lower, upper)
    return lo, np.maximum(hi, lo)


def _pilot(candidates, k: int) -> np.ndarray:
    c = np.asarray(candidates)
    if c.size <= k:
        return c
    return c[np.unique(np.linspace(0, c.size - 1, k).round().astype(int))]


def _ratio(num, den) -> np.ndarray:
    """Per (mode, component): median excess of the pilot boxes over the median of the reference, in [0, 1]."""
    a = np.median(num, axis=1)
    b = np.median(den, axis=1)
    return np.clip(np.where(b > 0, a / np.where(b > 0, b, 1.0), 1.0), 0.0, 1.0)


def _sampled_transitions(partition, lower, upper, noise, options, k: int = SAMPLE_CELLS):
    """(predicted listed transitions of the whole partition, seconds per transition of the sampled rows): the
    rows of ``k`` evenly spaced cells abstracted for real, scaled to all cells."""
    n = partition.n_cells
    idx = np.unique(np.linspace(0, n - 1, min(int(k), n)).round().astype(np.int64))
    t0 = time.perf_counter()
    rows = job_rows(partition, lower[:, idx], upper[:, idx], noise, options)
    dt = time.perf_counter() - t0
    nnz = max(_entries(rows), 1)
    return nnz * n / idx.size, dt / nnz


# ============================================================================ the estimate
def advise(partition, cell_bounds, fits: FittedModes, noise, dfa, *, threshold: float, horizon=None,
           classes, noise_floor, abstraction_options=None, bound_cells=None, max_cells: int = MAX_CELLS,
           pilot_cells: int = PILOT_CELLS, progress=None, sub_box_terms=None, local_pools=None,
           semantics: str = "auto", budget_s: float | None = None, per_transition: float | None = None,
           per_bound: float | None = None, transitions: float | None = None, solver=None, done=None,
           on_lever=None, premise: str = "") -> Advice:
    """Estimate the Q_yes share of X that a finer grid, more data, sub-boxes or larger local pools would give.

    Parameters
    ----------
    partition : geometry.Partition
        The grid that was solved.
    cell_bounds : abstraction.CellBounds
        Its image boxes ``(n_modes, n_cells, n)`` (as abstracted).
    fits : FittedModes
        Or any object with its ``grid_ranges`` / ``cell_ranges`` (``assumptions.ComponentFits``).
    noise : noise model of the abstraction
    dfa : dfa.DFA
    threshold, horizon, semantics
        As solved (``semantics``: the reading of the formula, ``synthesis.synthesize``).
    classes : (n_cells,) str array
        The solved classes (``"yes"`` / ``"no"`` / ``"maybe"``); the pilot cells are undecided ones.
    noise_floor : (n,) or (n_modes, n) float array
        Excess per side left with dense data: the data-noise bound plus tau (per mode and component where
        tau differs).
    abstraction_options : dict
        ``eta``, ``eps_rule``, ``combine`` of the run.
    bound_cells : callable ``(lower (k, d), upper (k, d), split_tol=None, local_points=None) -> (lower, upper)``
        of shape ``(n_modes, k, n)``, optional
        The run's bound stage for a few pilot cells (None: the run's own setting); without it the excess ratio
        of the finer grid is 1, and sub-boxes and pools are not estimated.
    sub_box_terms : callable ``(lower (k, d), upper (k, d)) -> (k,)``, optional
        Every cell's largest Taylor term ``B rho(t_max)`` over the modes and unknown components (what
        ``rkhs.split_counts`` weighs against ``split_tol``); None: the run cannot split or already does.
    local_pools : (int, int), optional
        ``(k, m)``: the run certifies some mode's cells with weights on ``k`` nearest points, and the
        largest mode has ``m`` points; None: every mode uses all its points (no pool estimate).
    max_cells : int
        An estimate that would abstract more cells than this is skipped (its note says so).
    pilot_cells : int
        Parent cells bounded for real per estimate.
    progress : callable str -> None, optional
    budget_s : float, optional
        Seconds the advice may spend (None: every lever is estimated). Levers are planned cheapest first while
        their predicted cost fits; a re-solve still running at the end is abandoned.
    per_transition : float, optional
        The run's seconds of abstraction + solve per listed transition (None: from the sampled rows).
    per_bound : float, optional
        The run's bound-stage seconds per cell and mode (None: pilots are not predicted).
    transitions : float, optional
        Listed transitions of the run's IMDP (None: sampled).
    solver : callable ``(jobs, deadline) -> iterator of (index, share or None)``, optional
        Runs the re-solves (:func:`serial_solver` by default; the pipeline's runs them on its scheduler).
    done : dict name -> Lever, optional
        Estimates of an earlier run of the same inputs (the cache): reused where the setting is the same.
    on_lever : callable Lever -> None, optional
        Called with every estimate as it completes (the pipeline saves it).
    premise : str
        What the guarantee needs of the assumption (shown with the advice; B is not a lever).

    Returns
    -------
    Advice
    """
    t_all = time.perf_counter()
    lo, hi = np.asarray(cell_bounds.image_lower), np.asarray(cell_bounds.image_upper)
    classes = np.asarray(classes).astype(str)
    if classes.shape != (partition.n_cells,):
        raise DimensionError(f"classes must have shape ({partition.n_cells},); got {classes.shape}")
    base = _share(partition, classes == "yes")
    budget = None if budget_s is None else max(float(budget_s), 0.0)
    open_cells = np.flatnonzero(classes == "maybe")
    if open_cells.size == 0:
        open_cells = np.flatnonzero(classes != "yes")
    if open_cells.size == 0:
        return Advice(base, (), None, time.perf_counter() - t_all, "every cell is in Q_yes", premise, budget)
    opts = dict(abstraction_options or {})
    flo, fhi = fits.grid_ranges(partition.breakpoints)
    e_lo, e_hi = _excess_sides(lo, hi, flo, fhi)
    # a few undecided cells (a small share of the grid, so the pilot costs a small share of the bound stage)
    pilot = _pilot(open_cells, min(int(pilot_cells), max(_PILOT_MIN, partition.n_cells // _PILOT_FRACTION)))
    ctx = _Context(partition, lo, hi, flo, fhi, e_lo, e_hi, pilot, base, noise, opts, bound_cells, max_cells)

    def say(text):
        if progress is not None:
            progress(text)

    M, n = lo.shape[0], lo.shape[2]
    floor = np.broadcast_to(np.asarray(noise_floor, float), (M, n))
    # the plans, made when their round comes (the finer grid's ranges and sampled rows cost something)
    makers = {"finer grid": lambda: _finer_grid(ctx, fits), "more data": lambda: _more_data(ctx, floor)}
    if sub_box_terms is not None:
        makers["sub-boxes"] = lambda: _sub_boxes(ctx, sub_box_terms)
    if local_pools is not None:
        makers["larger local pools"] = lambda: _larger_pools(ctx, *local_pools)

    # the cost model: seconds per listed transition of a re-solve, and the run's transitions
    if transitions is None or per_transition is None:
        t_base, rows_s = _sampled_transitions(partition, lo, hi, noise, opts)
        transitions = t_base if transitions is None else transitions
        per_transition = _ROWS_SHARE * rows_s if per_transition is None else per_transition
    cost = _Cost(float(per_transition), per_bound, float(transitions), M, pilot.size)
    deadline = None if budget is None else t_all + budget
    solve = solver or serial_solver(noise, dfa, threshold=threshold, horizon=horizon, options=opts,
                                    semantics=semantics)
    levers: dict = {}
    reused = 0
    for group in _GROUPS:  # the grid's own levers first; the finer grid then, with the cost measured on them
        todo = []
        for name in [m for m in group if m in makers]:
            prev = (done or {}).get(name)
            if name == "finer grid" and not (prev is not None and prev.setting == _finer_setting(partition)):
                # at least 2^d times the run's rows, each with at least its parent's successors: when even that
                # does not fit, the finer grid's boxes are not computed at all
                least = _finer_cells(partition) / partition.n_cells * cost.transitions * cost.per_transition
                left = math.inf if deadline is None else deadline - time.perf_counter()
                if _finer_cells(partition) <= max_cells and least > left:
                    levers[name] = Lever(name, _finer_setting(partition), None, None, _finer_cells(partition), note=(
                        f"at least about {_secs(least)}, more than the {_secs(max(left, 0.0))} left of the "
                        f"advice's {budget_text(budget)}; `--advice on` (advice=True) estimates it anyway"))
                    say(f"advice: {name} not estimated: {levers[name].note}")
                    continue
            plan = makers[name]()
            if plan.skip:
                levers[name] = Lever(name, plan.setting, None, None, plan.n_cells, note=plan.skip)
            elif prev is not None and prev.setting == plan.setting and prev.gain is not None:
                levers[name] = prev
                reused += 1
                say(f"advice: {name} reused from the cache (Q_yes {100 * prev.q_yes_share:.1f} % of X)")
            else:
                todo.append(plan)
        accepted = _within_budget(todo, cost, deadline, budget, levers, say)
        jobs, meta = [], []
        for plan in accepted:
            t0 = time.perf_counter()
            if deadline is not None and t0 > deadline:
                levers[plan.name] = Lever(plan.name, plan.setting, None, None, plan.n_cells,
                                          note=f"not estimated: the advice's {budget_text(budget)} was spent")
                continue
            part, blo, bhi, ratio, note = plan.build()
            cost.pilot_done(plan, time.perf_counter() - t0)
            if part is partition and np.array_equal(blo, lo) and np.array_equal(bhi, hi):
                # the lever leaves every box as solved: the same abstraction, the same Q_yes, no re-solve
                lv = Lever(plan.name, plan.setting, base, 0.0, plan.n_cells, ratio, time.perf_counter() - t0,
                           note or "the boxes do not change")
                levers[plan.name] = lv
                _announce(lv, say, on_lever)
                continue
            jobs.append(SolveJob(plan.name, part, blo, bhi, cost.rows(plan)))
            meta.append((plan, ratio, note, time.perf_counter() - t0))
        if not jobs:
            continue
        t_jobs = t_prev = time.perf_counter()
        solved = 0.0
        for i, share in solve(jobs, deadline):
            plan, ratio, note, pilot_s = meta[i]
            spent, t_prev = time.perf_counter() - t_prev, time.perf_counter()
            if share is None:
                levers[plan.name] = Lever(plan.name, plan.setting, None, None, plan.n_cells, ratio, spent, (
                    f"stopped at the end of the advice's {budget_text(budget)}"))
                say(f"advice: {plan.name} {levers[plan.name].note}")
                continue
            solved += jobs[i].transitions
            lv = Lever(plan.name, plan.setting, share, share - base, plan.n_cells, ratio, pilot_s + spent, note)
            levers[plan.name] = lv
            _announce(lv, say, on_lever)
        if solved > 0:  # seconds per transition as this machine runs the re-solves now (load, workers)
            cost.per_transition = (time.perf_counter() - t_jobs) / solved
    ordered = tuple(levers[m] for m in LEVERS if m in levers)
    est = [lv for lv in ordered if lv.gain is not None and lv.gain >= MIN_GAIN]
    winner = max(est, key=lambda lv: lv.gain).name if est else None
    return Advice(base, ordered, winner, time.perf_counter() - t_all, premise=premise, budget_s=budget,
                  reused=reused)


def _within_budget(todo, cost, deadline, budget, levers, say) -> list:
    """The plans of ``todo`` (cheapest first) whose predicted seconds fit what is left before ``deadline``; the
    others get a lever saying what they would cost."""
    left = math.inf if deadline is None else deadline - time.perf_counter()
    accepted = []
    for plan in todo:
        need = cost.of(plan)
        if need > left:
            levers[plan.name] = Lever(plan.name, plan.setting, None, None, plan.n_cells, note=(
                f"about {_secs(need)}, more than the {_secs(max(left, 0.0))} left of the advice's "
                f"{budget_text(budget)}; `--advice on` (advice=True) estimates it anyway"))
            say(f"advice: {plan.name} not estimated: {levers[plan.name].note}")
        else:
            left -= need
            accepted.append(plan)
    if accepted:
        say(f"advice: estimating {', '.join(p.name for p in accepted)} (about "
            f"{_secs(sum(cost.of(p) for p in accepted))}; {budget_text(budget)})")
    return accepted


def _announce(lv: Lever, say, on_lever) -> None:
    say(f"advice: {lv.name} ({lv.setting}) -> Q_yes {100 * lv.q_yes_share:.1f} % of X ({lv.seconds:.1f} s)")
    if on_lever is not None:
        on_lever(lv)


class _Cost:
    """Predicted seconds of a lever: its pilot cells through the bound stage and its re-solve. The seconds per
    transition and per bound-stage cell start as the run's own and become those the advice measures."""

    def __init__(self, per_transition: float, per_bound, transitions: float, n_modes: int, n_pilot: int):
        self.per_transition, self.per_bound = float(per_transition), per_bound
        self.transitions, self.n_modes, self.n_pilot = float(transitions), int(n_modes), int(n_pilot)

    def rows(self, plan) -> float:
        """The plan's predicted listed transitions (None: those of the run's grid)."""
        return self.transitions if plan.transitions is None else plan.transitions

    def pilot_cells(self, plan) -> float:
        return self.n_pilot * self.n_modes * plan.pilot_factor

    def of(self, plan) -> float:
        pilot = 0.0 if self.per_bound is None else self.per_bound * self.pilot_cells(plan)
        large = _LARGE_FACTOR if self.rows(plan) >= _LARGE_TRANSITIONS else 1.0
        return pilot + self.rows(plan) * self.per_transition * large

    def pilot_done(self, plan, seconds: float) -> None:
        if self.pilot_cells(plan) > 0:
            self.per_bound = seconds / self.pilot_cells(plan)


@dataclass(frozen=True, eq=False)
class _Plan:
    """One lever before it is estimated: its setting, why it is not estimated (``skip``), its pilot cost in
    bound-stage cells per pilot cell and mode (``pilot_factor``, 0: no pilot), its predicted transitions (None:
    those of the run's grid), and
    ``build() -> (partition, lower, upper, excess ratio or None, note)`` (the pilot and the modified boxes)."""

    name: str
    setting: str
    n_cells: int
    skip: str = ""
    pilot_factor: float = 0.0
    transitions: float | None = None
    build: Callable | None = None


@dataclass(frozen=True, eq=False)
class _Context:
    """What every lever of :func:`advise` reads: the solved grid, its image boxes ``[lo, hi]``, the
    fitted function's ranges ``[flo, fhi]`` per cell, the excess per side, the pilot cells, the
    Q_yes share solved (``base``) and the run's solve settings."""

    partition: object
    lo: np.ndarray
    hi: np.ndarray
    flo: np.ndarray
    fhi: np.ndarray
    e_lo: np.ndarray
    e_hi: np.ndarray
    pilot: np.ndarray
    base: float
    noise: object
    opts: dict
    bound_cells: object
    max_cells: int

    def pilot_ratio(self, plo, phi) -> np.ndarray:
        """Per (mode, component): the excess ratio of the pilot cells' boxes ``[plo, phi]`` (bounded with a
        lever's setting) over their boxes as solved (:func:`_ratio`)."""
        s_lo, s_hi = _excess_sides(plo, phi, self.flo[:, self.pilot], self.fhi[:, self.pilot])
        return _ratio(np.concatenate([s_lo, s_hi], axis=1),
                      np.concatenate([self.e_lo[:, self.pilot], self.e_hi[:, self.pilot]], axis=1))

    def scaled(self, r, where=None):
        """The solved boxes with their excess scaled by ``r`` (n_modes, n) (only in the cells ``where``)."""
        elo, ehi = r[:, None] * self.e_lo, r[:, None] * self.e_hi
        if where is not None:
            w = np.asarray(where)[None, :, None]
            elo, ehi = np.where(w, elo, self.e_lo), np.where(w, ehi, self.e_hi)
        return _shrunk(self.lo, self.hi, self.flo, self.fhi, elo, ehi)

    def no_pilot(self) -> str:
        """Why the pilot cells cannot be bounded (no bound stage, or too many cells to re-solve), or ``""``."""
        if self.bound_cells is None:
            return "no pilot bound stage"
        n = self.partition.n_cells
        return f"{n:,} cells > {self.max_cells:,}" if n > self.max_cells else ""

    def too_many(self) -> str:
        n = self.partition.n_cells
        return f"{n:,} cells > {self.max_cells:,}" if n > self.max_cells else ""


def _finer_setting(partition) -> str:
    return f"cell_size {np.round(np.asarray(partition.cell_size, float) / 2, 6).tolist()}"


def _finer_cells(partition) -> int:
    """Cells of the 2x finer grid (regions that cut a cell cut its children the same way)."""
    return partition.n_cells * 2 ** partition.dim


def _finer_grid(ctx: _Context, fits) -> _Plan:
    """Lever (a), a finer grid: every cell split in 2^d; the excess scaled by the pilot sub-cells' ratio. Its
    transitions are predicted from :data:`SAMPLE_CELLS` sub-cells abstracted for real."""
    from robust_imdp.models.geometry import Partition

    partition = ctx.partition
    h2 = np.asarray(partition.cell_size, float) / 2
    n_fine = _finer_cells(partition)
    setting = _finer_setting(partition)
    if n_fine > ctx.max_cells:
        return _Plan("finer grid", setting, n_fine, f"{n_fine:,} cells > {ctx.max_cells:,}: run it on a sub-box of X")
    fine = Partition(partition.space, h2, partition.regions, periodic=getattr(partition, "periodic", None))
    parent = np.asarray(partition.locate(0.5 * (fine.cells_lower + fine.cells_upper)))
    glo, ghi = fits.grid_ranges(fine.breakpoints)

    def boxes(r):
        return _shrunk(ctx.lo[:, parent], ctx.hi[:, parent], glo, ghi, r[:, None] * ctx.e_lo[:, parent],
                       r[:, None] * ctx.e_hi[:, parent])

    ones = np.ones((ctx.lo.shape[0], ctx.lo.shape[2]))
    transitions, _ = _sampled_transitions(fine, *boxes(ones), ctx.noise, ctx.opts)

    def build():
        if ctx.bound_cells is None:
            return (fine, *boxes(ones), None, "excess ratio 1 (no pilot)")
        # one sub-cell per pilot cell, its position cycling through the children (2^d, or fewer
        # where a region's boundary already split the cell)
        kids = [np.flatnonzero(parent == q) for q in ctx.pilot]
        sub = np.array([c[k % c.size] for k, c in enumerate(kids)])
        blo, bhi = ctx.bound_cells(fine.cells_lower[sub], fine.cells_upper[sub])
        s_lo, s_hi = _excess_sides(blo, bhi, glo[:, sub], ghi[:, sub])
        r = _ratio(np.concatenate([s_lo, s_hi], axis=1),
                   np.concatenate([ctx.e_lo[:, parent[sub]], ctx.e_hi[:, parent[sub]]], axis=1))
        return (fine, *boxes(r), float(np.median(r)), "")

    return _Plan("finer grid", setting, fine.n_cells, pilot_factor=0.0 if ctx.bound_cells is None else 1.0,
                 transitions=transitions, build=build)


def _more_data(ctx: _Context, floor) -> _Plan:
    """Lever (b), more data: the excess down to its noise floor ``(n_modes, n)``."""
    partition = ctx.partition
    setting = f"excess at the noise floor {np.round(floor.max(axis=0), 6).tolist()}"
    if ctx.too_many():
        return _Plan("more data", setting, partition.n_cells, ctx.too_many())
    f = floor[:, None, :]

    def build():
        return (partition, *_shrunk(ctx.lo, ctx.hi, ctx.flo, ctx.fhi, np.minimum(ctx.e_lo, f),
                                    np.minimum(ctx.e_hi, f)), None, "")

    return _Plan("more data", setting, partition.n_cells, build=build)


def _pieces(terms, tol: float, d: int) -> np.ndarray:
    """Pieces per axis of the sub-boxes ``rkhs.split_counts`` chooses for Taylor terms ``terms``."""
    from robust_imdp.bounds.rkhs_model import MAX_SUB

    s = np.ceil(np.sqrt(np.asarray(terms, float) / float(tol)))
    s_max = max(1, int(math.floor(MAX_SUB ** (1.0 / d) + 1e-9)))
    return np.clip(np.nan_to_num(s, nan=1.0, posinf=s_max), 1, s_max).astype(np.int64)


def _sub_boxes(ctx: _Context, cell_terms) -> _Plan:
    """Lever (c), sub-box certification: one halving per axis where the Taylor term of eq. C is largest
    (``split_tol`` = the grid's largest term / 2.25, so ``s = ceil(sqrt(term / split_tol)) = 2`` there,
    but at least ``rkhs.SPLIT_TOL``); the excess scaled by the ratio measured on the pilot cells certified
    on those sub-boxes. The grid, and so the abstraction's size, stay as they are.

    Why one halving: it divides the term by about 4, and that took most of the gain where measured (a
    newcomer system, B = 6, r/l 0.125: Q_yes 141 unsplit, 171 with s = 2 at about 3x the bound time,
    174 with the s = 10 of ``SPLIT_TOL`` at about 30x; ``benchmarks/results/advice_sub_boxes.md``)."""
    from robust_imdp.bounds.rkhs_model import SPLIT_TOL

    partition, pilot = ctx.partition, ctx.pilot
    terms = np.asarray(cell_terms(partition.cells_lower, partition.cells_upper), float)
    tol = max(SPLIT_TOL, float(np.max(terms, initial=0.0)) / 2.25 * (1 + 1e-9))
    n_sub = _pieces(terms, tol, partition.dim) ** partition.dim
    setting = f"split_tol = {tol:.3g}, {float(np.mean(n_sub)):.3g} sub-boxes per cell"
    if np.all(n_sub[pilot] <= 1):
        return _Plan("sub-boxes", setting, partition.n_cells,
                     "the Taylor term is below split_tol in the undecided cells: sub-boxes change nothing")
    if ctx.no_pilot():
        return _Plan("sub-boxes", setting, partition.n_cells, ctx.no_pilot())

    def build():
        r = ctx.pilot_ratio(*ctx.bound_cells(partition.cells_lower[pilot], partition.cells_upper[pilot],
                                             split_tol=tol))
        # cells the rule leaves whole keep their boxes
        return (partition, *ctx.scaled(r, n_sub > 1), float(np.median(r)), "")

    return _Plan("sub-boxes", setting, partition.n_cells, pilot_factor=float(np.mean(n_sub[pilot])),
                 build=build)


def pool_proposal(k: int, m: int) -> int:
    """The local-pools lever's ``local_points``: all ``m`` points up to :data:`POOL_ALL_MAX`, else
    ``POOL_FACTOR k`` (at most ``m``)."""
    return int(m) if int(m) <= POOL_ALL_MAX else int(min(int(m), POOL_FACTOR * int(k)))


def _larger_pools(ctx: _Context, k: int, m: int) -> _Plan:
    """Lever (d), larger local pools (``local_points`` = :func:`pool_proposal`): the excess scaled by the ratio
    measured on the pilot cells bounded with those pools. In 3-D the pools, not the certificate, are most of
    the slack over the optimal range (``benchmarks/results/local_auto.md``: 0.0047 with pools of 100 against
    0.0006 with all 1,024 points at r/l 0.03)."""
    partition, pilot = ctx.partition, ctx.pilot
    K = pool_proposal(k, m)
    setting = (f"local_points = {K} (all points)" if K >= m else f"local_points = {K}") + f", now {int(k)}"
    if K <= k:
        return _Plan("larger local pools", setting, partition.n_cells,
                     "the pools already hold the proposed number of points")
    if ctx.no_pilot():
        return _Plan("larger local pools", setting, partition.n_cells, ctx.no_pilot())

    def build():
        r = ctx.pilot_ratio(*ctx.bound_cells(partition.cells_lower[pilot], partition.cells_upper[pilot],
                                             local_points=K))
        return (partition, *ctx.scaled(r), float(np.median(r)), "")

    return _Plan("larger local pools", setting, partition.n_cells, pilot_factor=K / max(int(k), 1),
                 build=build)
