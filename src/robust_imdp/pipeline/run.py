"""From data and a requirement to a controller with guarantees, in one call.

``synthesize_from_data(problem)`` chains the stages of the paper (Jackson et al., HSCC 2021):

1. **specify** -- the specification to a minimal DFA (``spec.to_dfa``); checked first, so an
   unknown region fails before any expensive work;
2. **partition** -- grid over X respecting the labelled regions (``geometry.Partition``);
3. **check** -- the data-implied minimum RKHS norm of every mode and output
   (``rkhs.check_assumption``): a ``rkhs_bound`` the data refute is refused before any work;
4. **learn + bound** -- certified image boxes of ``f_u + g_u`` over every cell. Default
   (``error_bound="optimal"``): the optimal deterministic bound under bounded noise
   (``rkhs.image_ranges``; ``"ridge"`` is its cheaper closed form). ``"chowdhury"``: one GP
   per mode and output with the error bound of Chowdhury & Gopalan (2017, Thm 2)
   (``gp.learn``) and certified bounds of ``f_u + mu`` and of the posterior std
   (``bounds.bound_image``);
5. **abstract** -- the interval MDP of the paper's Thm 1 (``abstraction.abstract``);
6. **synthesize** -- product with the DFA, robust strategy, ``p_low``, ``p_up``, ``p_up_star``,
   ``error`` and the classes Q_yes / Q_no / Q_? (``synthesis.synthesize``).

Stages 3-5 depend only on the data, modes, noise, grid, regions and GP / abstraction options;
with ``abstraction_cache=DIR`` the learned cell bounds (stages 3-4) and the abstraction (5) are
saved under hashes of exactly their inputs: the abstraction is reused when only the formula,
threshold or horizon changes (:func:`resynthesize` does the same in memory), the cell bounds
also when only eta, the eps rule or the combination rule change."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from robust_imdp._blas import blas_threads
from robust_imdp.errors import InvalidInputError

from robust_imdp.pipeline.problem import Problem, _is_affine, _setting_value, _settings
from robust_imdp.pipeline.result import Result, diagnostics_line
from robust_imdp.pipeline.runtime import MAX_ROW_CELLS, _Log, _Run, _chunk_cells, _serial
from robust_imdp.pipeline.cache import (
    _load_abstraction_entry,
    _load_bounds,
    _save_abstraction_entry,
    _save_bounds,
    _write_json_entry,
    abstraction_key,
    bounds_key,
    read_cache_entry,
    refined_key,
    write_cache_entry,
)
from robust_imdp.pipeline.preflight import (
    _check_atoms,
    _preflight,
    _region_objects,
    _warn_overlaps,
    estimate_resources,
)
from robust_imdp.pipeline.bound_stage import (
    _cell_bounder,
    _failure_budget,
    _fitted,
    _learn_and_bound,
    _residual_data,
)
from robust_imdp.pipeline.advice_stage import run_advice, spread


__all__ = ["Problem", "Result", "synthesize_from_data", "resynthesize", "abstraction_key",
           "bounds_key", "estimate_resources"]



def _parameters(problem: Problem, abstraction) -> dict:
    noise = problem.noise
    params = {
        "space": {"lower": problem.space_lower, "upper": problem.space_upper},
        "cell_size": problem.cell_size,
        "n_data": 0 if problem.data is None else int(np.asarray(problem.data.u).shape[0]),
        "rkhs_bound": _setting_value(problem.rkhs_bound),
        "gp_options": {k: v for k, v in problem.gp_options.items()},
        "bound_tol": float(problem.bound_tol),
        "bound_max_boxes": int(problem.bound_max_boxes),
        "noise": {"kind": type(noise).__name__,
                  **{k: v for k, v in vars(noise).items() if not k.startswith("_")}}
        if hasattr(noise, "__dict__") else repr(noise),
        "eta": None if problem.eta is None else problem.eta,
        "eta_used": getattr(abstraction, "eta", None),
        "eps_rule": problem.eps_rule,
        "combine": problem.combine,
        "transitions": problem.transitions,
        "guarantee": problem.guarantee,
        "confidence": float(problem.confidence) if problem.guarantee == "confidence" else None,
        "error_bound": problem.error_bound,
        "misspecification": _setting_value(problem.misspecification),
        "iid_noise": bool(problem.iid_noise),
        "local_points": problem.local_points,
        **({} if getattr(problem, "split_tol", None) is None else {"split_tol": float(problem.split_tol)}),
        "abstraction_key": abstraction_key(problem),
        **(_form_parameters(problem, abstraction)),
        **({} if all(_is_affine(m) for m in problem.maps) else
           {"known_parts": {name: (None if _is_affine(m) else list(m.expressions))
                            for name, m in zip(problem.mode_names, problem.maps)}}),
        "refine": None if problem.refine is None else problem.refine.to_dict(),
    }
    from robust_imdp.jsonable import jsonable as _jsonable

    return _jsonable(params)


def _form_parameters(problem: Problem, abstraction) -> dict:
    """``form`` and ``form_reason`` of a factored result's parameters (joint results' parameters are unchanged)."""
    from robust_imdp.abstraction.factored import is_factored

    if abstraction is None or not is_factored(abstraction):
        return {}
    return {"form": "factored", "form_reason": problem.form_choice()[1],
            "numbers_per_row": int(abstraction.numbers_per_row)}


def _abstract_task(partition, cell_bounds, noise, *, threads=1, **options):
    """One chunk of the abstraction stage (a module-level function, so that workers can import it)."""
    from robust_imdp.abstraction.rows import abstract_rows

    return abstract_rows(partition, cell_bounds, noise, None, **options)


def _factored_task(partition, cell_bounds, noise, *, threads=1, k, tol):
    """One chunk of the factored abstraction stage: its cells' per-axis marginals (``abstraction.factored``)."""
    from robust_imdp.abstraction.factored import factored_rows

    return factored_rows(partition, cell_bounds, noise, k, tol=tol)


def _form_of(problem: Problem, partition) -> str:
    """The form of the abstraction of ``partition``: the problem's choice on a grid, joint on refined cells."""
    from robust_imdp.models.geometry import Partition

    return problem.form_choice()[0] if isinstance(partition, Partition) else "joint"


def _chunked_abstract(problem: Problem, partition, cell_bounds, log: _Log, run: _Run, chunk: int, form=None):
    """``abstraction.abstract`` for known image boxes, chunk by chunk on the run's scheduler; with ``form =
    "factored"`` (default: :func:`_form_of`) the factored abstraction (``abstraction.factored``) instead: the listed
    lengths of all cells first, then the chunks' marginals."""
    from robust_imdp.abstraction.rows import CellBounds, assemble_abstraction

    form = _form_of(problem, partition) if form is None else form
    N = partition.n_cells
    starts = list(range(0, N, chunk))
    sched = run.sched
    if form == "factored":
        from robust_imdp.abstraction.factored import AXIS_TOL, assemble_factored, axis_lengths

        task, assemble = _factored_task, assemble_factored
        opts = {"k": axis_lengths(partition, cell_bounds, problem.noise), "tol": AXIS_TOL}
    else:
        task, assemble, opts = _abstract_task, assemble_abstraction, problem.abstraction_options()
    args = []
    part = partition if sched is None else sched.share(partition)
    for s0 in starts:
        sl = slice(s0, min(N, s0 + chunk))
        args.append((part, CellBounds(cell_bounds.image_lower[:, sl], cell_bounds.image_upper[:, sl], None),
                     problem.noise))
    pieces = [None] * len(args)
    t0 = time.perf_counter()
    runner = sched if sched is not None else _serial()
    # in process on several cores the chunks run side by side (threads and the side lane's helpers); the pieces
    # are assembled by position: the same model in any order
    for i, piece in spread(runner, task, args, opts):
        pieces[i] = piece
        log.progress("abstract", sum(p is not None for p in pieces), len(pieces), t0)
    return assemble(partition, pieces)


def _build_abstraction(problem: Problem, partition, log: _Log, cache_dir=None, run: "_Run | None" = None):
    """Learn + bound (or load them from the cache) and abstract.

    Returns (abstraction, diagnostics, image boxes abstracted or None when the GP error enters
    the probabilities).
    """
    from robust_imdp.abstraction.rows import abstract, confidence_cell_bounds

    run = run if run is not None else _Run()

    bounds_file = None
    if cache_dir is not None:
        bounds_file = Path(cache_dir) / f"bounds-{bounds_key(problem)}.npz"
    loaded = None
    if bounds_file is not None and bounds_file.exists():
        with log.stage("load_bounds"):
            loaded = read_cache_entry(bounds_file, _load_bounds)
        if loaded is not None:
            log.info(f"reused learned cell bounds {bounds_file.name}")
    if loaded is not None:
        cell_bounds, error_models, diagnostics = loaded
    else:
        cell_bounds, error_models, diagnostics = _learn_and_bound(problem, partition, log, run, cache_dir)
        if bounds_file is not None:
            _save_bounds(bounds_file, cell_bounds, error_models, diagnostics)
    with log.stage("abstract"):
        if problem.guarantee == "confidence" and error_models is not None:
            # One data-confidence event for all GPs: the error is folded into the image boxes
            # and the abstraction is built as for known dynamics (eps = 0, P_g = 1).
            cell_bounds = confidence_cell_bounds(cell_bounds, error_models, problem.confidence)
            error_models = None
        if error_models is None:
            # at most MAX_ROW_CELLS cells per task, and at least two tasks per worker on a cluster
            # (the rows do not depend on the chunk size: tests/test_chunks.py)
            from robust_imdp.pipeline.parallel import DaskScheduler

            workers = run.sched.n_workers if isinstance(run.sched, DaskScheduler) else 1
            per_task = MAX_ROW_CELLS if workers <= 1 else min(MAX_ROW_CELLS, -(-partition.n_cells // (2 * workers)))
            abstraction = _chunked_abstract(problem, partition, cell_bounds, log, run,
                                            _chunk_cells(run, partition.n_cells, per_task))
        else:
            abstraction = abstract(partition, cell_bounds, problem.noise, error_models,
                                   **problem.abstraction_options())
    diagnostics = dict(diagnostics)
    from robust_imdp.abstraction.factored import is_factored

    if is_factored(abstraction):
        m = abstraction.model
        diagnostics["factored"] = {"numbers_per_row": int(m.numbers_per_row), "entries_per_row": int(m.entries_per_row),
                                   "listed_per_axis": list(m.k), "bytes": int(m.nbytes)}
        log.info(f"factored IMDP: {m.n_states} states, {m.n_modes} modes, {m.numbers_per_row} stored numbers per row "
                 f"({' + '.join(str(k + 1) for k in m.k)} interval entries per axis), {m.nbytes / 1e6:.1f} MB")
    else:
        diagnostics["successors_per_row"] = float(np.mean(abstraction.nnz_per_row))
        log.info(f"IMDP: {abstraction.imdp.n_states} states, {int(np.sum(abstraction.nnz_per_row))} "
                 f"listed transitions ({diagnostics['successors_per_row']:.1f} per row)")
    return abstraction, diagnostics, (cell_bounds if error_models is None else None)


def _synthesize(problem: Problem, partition, abstraction, dfa, log: _Log, nominal_beside=None):
    """The solve of the run (``synthesis.core.synthesize``) with its nominal model (``nominal_stage.run_nominal``;
    ``nominal_beside``: the one ``nominal_stage.start_nominal`` started beside the bound stage): ``(syn, classes)``."""
    from robust_imdp.abstraction.factored import abstraction_model
    from robust_imdp.pipeline.nominal_stage import run_nominal
    from robust_imdp.spec.api import resolve_semantics
    from robust_imdp.synthesis.core import synthesize
    from robust_imdp.synthesis.ties import takes_nominal

    model = abstraction_model(abstraction)
    nominal = None  # ranks modes of equal robust value (synthesis.ties); not built where the synthesis takes none
    if takes_nominal(model, horizon=problem.horizon, semantics=resolve_semantics(dfa, problem.semantics)[0]):
        nominal = run_nominal(problem, partition, log, beside=nominal_beside)
    with log.stage("synthesize"):
        syn = synthesize(model, partition.labels, partition.atoms, dfa,
                         threshold=problem.threshold, horizon=problem.horizon,
                         outside_state=partition.outside_state, semantics=problem.semantics, nominal=nominal)
    classes = _class_names(syn.classes, syn, problem.threshold)
    return syn, classes


def _reading_line(problem: Problem, dfa) -> str:
    """Which reading of the formula the run uses and why (README, "Two readings of a formula")."""
    from robust_imdp.spec.api import resolve_semantics

    reading, kind = resolve_semantics(dfa, problem.semantics)
    what = ("a path satisfies it when some prefix is accepted" if reading == "reach" else
            "a path satisfies it when no prefix is a bad prefix and it stays in X")
    scope = f"within {problem.horizon} steps" if problem.horizon is not None else "with no horizon"
    why = f"auto: {kind.reason}" if problem.semantics == "auto" else "[spec].semantics"
    return f"semantics: {reading} ({what}, {scope}; {why})"


def _check_reading(problem: Problem, partition, dfa) -> None:
    """Refuse, before the long stages, a formula the cells' labels decide alone under the reading in use
    (``spec.dfa.check_reading``; its warnings come with the solve)."""
    import warnings

    from robust_imdp.spec.api import check_reading, resolve_semantics
    from robust_imdp.synthesis.controller import remap_letters

    reading, kind = resolve_semantics(dfa, problem.semantics)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_reading(dfa, remap_letters(partition.labels, partition.atoms, dfa.atoms), reading, kind)


def _class_names(classes, syn, threshold) -> np.ndarray:
    """Per-cell "yes"/"no"/"maybe" from whatever form SynthesisResult.classes has."""
    c = np.asarray(classes)
    if c.dtype.kind in "US":
        return c.astype(str)
    if c.dtype == object:
        return np.array([str(getattr(v, "value", v)).lower() for v in c])
    # Fall back to the definition (paper, Sec. 5): yes iff p_low >= threshold, no iff p_up < threshold.
    p_low, p_up = np.asarray(syn.p_low), np.asarray(syn.p_up)
    return np.where(p_low >= threshold, "yes", np.where(p_up < threshold, "no", "maybe"))


def synthesize_from_data(problem: Problem, *, progress: bool = True, abstraction_cache=None, client=None,
                         workers: int | None = None, scheduler: str | None = None, chunk_cells: int | None = None,
                         check_resources: bool = True, advice="auto", margins: bool = True,
                         on_solved=None) -> Result:
    """Learn, bound, abstract and synthesize: data and formula in, guarantees out.

    Parameters
    ----------
    problem : Problem
    progress : bool
        Print one line per stage (and counts, progress, time estimates) to stderr.
    abstraction_cache : str or Path, optional
        Directory where the abstraction is saved as ``abstraction-<key>.npz``; an existing file
        with the same key (see :func:`abstraction_key`) is loaded instead of re-running learn,
        bound and abstract. Finished chunks of the bound stage are saved there as they complete,
        so an interrupted run resumes where it stopped.
    client : distributed.Client, optional
        Run the chunked stages on this Dask cluster (the data are sent to the workers once).
    workers : int, optional
        Local cores: 1 runs in this process on one core, N > 1 starts a local Dask cluster of N
        processes (call it under ``if __name__ == "__main__":`` in scripts); None (default) runs in
        this process with numba threads on all cores.
    scheduler : str, optional
        Address of a running Dask scheduler (``"tcp://host:8786"``).
    chunk_cells : int, optional
        Cells per task (rounded up to a multiple of 16). The result does not depend on it, nor
        on the number of workers.
    check_resources : bool
        Refuse (``ResourceError``) when the pre-flight memory estimate exceeds the memory free.
    advice : {"auto", True, False}
        After the solve, estimate which lever (a 2x finer grid, more data, sub-boxes, larger local pools) would
        move most of X into Q_yes (``pipeline/advice_stage.py``, :func:`robust_imdp.synthesis.advice.advise`;
        ``result.advice``, the summary's ``advice:`` line and ``result.json``'s ``diagnostics.advice``).
        ``"auto"``: within a budget of ``advice.ADVICE_SHARE`` (25 %) of the run's time before it, cheapest
        lever first, each re-solve of at most ``advice.MAX_CELLS`` cells; True: every lever, no budget; False:
        none. Its estimates are saved in ``abstraction_cache`` as they complete and reused by a later run.
    margins : bool
        Assumption margins (``pipeline/margins.py``, docs/margins.md): per cell the largest factor of
        ``synthesis.margins.MARGIN_SCALES`` (1 .. 4) at which the run's controller keeps the cell's class with
        every B scaled by it (``result.b_margin``, the summary's ``assumption margins:`` line). The bound stage
        certifies the larger-B boxes with the same weights (no new optimisation); each factor costs one
        abstraction and one evaluation of the controller. Not computed for known dynamics and the GP route.
    on_solved : callable, optional
        Called with the :class:`Result` as it stands right after the solve, when its cells, classes and
        bounds are final (not with ``[refine]``, whose rounds change them): no advice, no margins (the stages
        that follow). It runs in the run's thread; the command line starts drawing the figures there, in
        helper processes, while the advice and the margins run (``pipeline.parallel.SideLane``).

    Returns
    -------
    Result
    """
    from robust_imdp.spec.api import to_dfa

    if advice not in ("auto", True, False):
        raise InvalidInputError(f"advice must be 'auto', True or False; got {advice!r}")
    if margins not in (True, False):
        raise InvalidInputError(f"margins must be True or False; got {margins!r}")
    from robust_imdp._blas import quiet_openmp_waits

    quiet_openmp_waits()  # idle numba threads sleep soon, leaving the cores to the side work (robust_imdp._blas)
    log = _Log(progress)
    run = _Run(client=client, workers=workers, scheduler=scheduler, chunk_cells=chunk_cells,
               check_resources=check_resources)
    run.advice = advice
    if on_solved is not None and not callable(on_solved):
        raise InvalidInputError(f"on_solved must be callable or None; got {type(on_solved).__name__}")
    run.on_solved = on_solved
    run.margins = margins
    if margins:  # the bound stage certifies the boxes at the larger factors of B too (pipeline/margins.py)
        from robust_imdp.pipeline.margins import bound_scales, skip_reason

        if skip_reason(problem) is None:
            run.margin_scales, run.margin_problem = bound_scales(), problem
    with log.stage("specify"):
        dfa = to_dfa(problem.formula)
        _check_atoms(dfa, problem)
    log.info(f"DFA: {dfa.n_states} states over atoms {list(dfa.atoms)}")
    log.info(_reading_line(problem, dfa))
    _warn_overlaps(problem, dfa)
    _preflight(problem, dfa, log, run)
    try:
        with blas_threads(1):  # LAPACK's bits depend on its thread count: one, for the same bits on any core count
            return _synthesize_run(problem, dfa, log, run, abstraction_cache)
    finally:
        run.close()


def _synthesize_run(problem: Problem, dfa, log: _Log, run: _Run, abstraction_cache) -> Result:
    from robust_imdp.models.geometry import Box, Partition

    with log.stage("partition"):
        partition = Partition(Box(problem.space_lower, problem.space_upper), problem.cell_size,
                              _region_objects(problem), names=problem.dim_names, periodic=problem.periodic)
    log.info(f"partition: {partition.n_cells} cells")
    _check_reading(problem, partition, dfa)
    form, why = problem.form_choice()
    log.info(f"abstraction form: {form} ({why})")

    abstraction, from_cache, diagnostics, cell_bounds = None, False, {}, None
    cache_file = diag_file = nominal = saving = None
    if abstraction_cache is not None:
        cache_file = Path(abstraction_cache) / f"abstraction-{abstraction_key(problem)}.npz"
        diag_file = cache_file.with_suffix(".json")
        if cache_file.exists():
            with log.stage("load_abstraction"):
                entry = _load_abstraction_entry(cache_file)
            if entry is not None:
                abstraction, diagnostics = entry
                from_cache = True
                log.info(f"reused abstraction {cache_file.name}")
    if abstraction is None:
        from robust_imdp.pipeline.nominal_stage import start_nominal

        nominal = start_nominal(problem, partition, dfa, run, log)  # beside the bound stage where it can
        abstraction, diagnostics, cell_bounds = _build_abstraction(problem, partition, log, abstraction_cache, run)
        if cache_file is not None:
            saving = _save_abstraction_beside(cache_file, abstraction, diagnostics, run)
    try:
        result = _solve_and_finish(problem, dfa, log, run, abstraction_cache, partition, abstraction, from_cache,
                                   diagnostics, cell_bounds, nominal)
    except BaseException:  # the run's own error is the one raised; the cache entry is complete or absent
        if saving is not None:
            saving.wait(raise_error=False)
        raise
    if saving is not None:  # the cache entry is complete when the run returns
        saving.wait()
    return result


def _solve_and_finish(problem: Problem, dfa, log: _Log, run: _Run, abstraction_cache, partition, abstraction,
                      from_cache: bool, diagnostics, cell_bounds, nominal) -> Result:
    """:func:`_synthesize_run` from the abstraction on: synthesis, advice, refinement, margins, the result."""
    why = diagnostics_line(diagnostics)
    if why:
        log.info(why)
    syn, classes = _synthesize(problem, partition, abstraction, dfa, log, nominal)
    _notify_solved(problem, partition, abstraction, dfa, syn, classes, run, from_cache, diagnostics)
    # without refinement the margins read the solve's cells: started now, in helpers, beside the advice
    pending = _start_margins(problem, partition, syn, classes, dfa, log, run, abstraction_cache)
    try:
        # known dynamics: no data and no assumption, nothing the advice's levers could change
        advice = {} if problem.known else run_advice(problem, partition, abstraction, cell_bounds, dfa, classes, log,
                                                     run, abstraction_cache, diagnostics)
    except BaseException:
        if pending is not None:
            pending.cancel()
        raise
    parameters = _parameters(problem, abstraction)
    grid = partition
    if problem.refine is not None:  # adaptive refinement of the undecided cells (see docs/refinement.md)
        partition, abstraction, syn, classes, diagnostics, parameters["abstraction_key"] = _refine(
            problem, partition, abstraction, syn, cell_bounds, dfa, log, run, abstraction_cache, diagnostics)
    b_margin, margins_doc = _margins(problem, grid, partition, syn, classes, dfa, log, run, abstraction_cache, pending)
    log.timings["total"] = time.perf_counter() - log.t0
    result = Result(problem=problem, partition=partition, abstraction=abstraction, dfa=dfa,
                    synthesis=syn, class_names=classes, timings=dict(log.timings),
                    parameters=parameters, from_cache=from_cache,
                    diagnostics=diagnostics, advice=advice, b_margin=b_margin, margins=margins_doc)
    return result


class _WriteBeside:
    """A cache entry written in a thread beside the run (:func:`_save_abstraction_beside`); :meth:`wait` joins it and
    raises its error."""

    def __init__(self, fn, *args):
        import threading

        self.error = None

        def body():
            try:
                fn(*args)
            except BaseException as exc:  # raised in the run's thread by wait()
                self.error = exc

        self._thread = threading.Thread(target=body, name="robust-imdp cache writer")
        self._thread.start()

    def wait(self, raise_error: bool = True) -> None:
        self._thread.join()
        if raise_error and self.error is not None:
            raise self.error


def _save_abstraction_beside(cache_file: Path, abstraction, diagnostics: dict, run: _Run):
    """The abstraction's cache entry (``cache._save_abstraction_entry``: the JSON document first, the abstraction
    last): on several cores the abstraction's compressed file is written in a thread beside the synthesis (5.3 s of
    a core at 64^3, zlib and the checksum without the GIL) and this returns its :class:`_WriteBeside`; on one core
    it is written here and this returns None. The JSON document is written here in both cases (the diagnostics
    gain keys later; the abstraction's arrays are read-only)."""
    sched = run.sched
    if sched is None or getattr(sched, "n_workers", 1) <= 1:
        _save_abstraction_entry(cache_file, abstraction, diagnostics)
        return None
    _write_json_entry(cache_file.with_suffix(".json"), diagnostics)
    return _WriteBeside(write_cache_entry, cache_file, abstraction.save)


def _notify_solved(problem: Problem, partition, abstraction, dfa, syn, classes, run: _Run, from_cache: bool,
                   diagnostics: dict) -> None:
    """``on_solved`` of :func:`synthesize_from_data` with the result after the solve, when no refinement
    follows (the advice and the margins add to the result; they change none of its cells, classes or bounds)."""
    callback = getattr(run, "on_solved", None)
    if callback is None or problem.refine is not None:
        return
    callback(Result(problem=problem, partition=partition, abstraction=abstraction, dfa=dfa, synthesis=syn,
                    class_names=classes, timings={}, parameters=_parameters(problem, abstraction),
                    from_cache=from_cache, diagnostics=diagnostics))


def _start_margins(problem: Problem, partition, syn, classes, dfa, log: _Log, run: _Run, cache_dir):
    """The margins started in the side lane beside the advice (``pipeline.margins.start_margins``; without an advice
    they are worked on at once, by the lane's helpers and this process) when the run asks for margins and has no
    refinement (whose rounds change the cells); else None."""
    if not getattr(run, "margins", False) or problem.refine is not None or problem.known:
        return None
    from robust_imdp.pipeline.margins import start_margins

    return start_margins(problem, partition, syn, classes, dfa, log, run, cache_dir)


def _margins(problem: Problem, grid, partition, syn, classes, dfa, log: _Log, run: _Run, cache_dir, pending=None):
    """The assumption margins (``pipeline.margins.run_margins``) when the run asks for them: ``(b_margin or None,
    Result.margins' dict or {})``; the margins' abstractions go through :func:`_chunked_abstract`, as the run's
    (``pending``: the factors :func:`_start_margins` submitted)."""
    if not getattr(run, "margins", False):
        return None, {}
    from robust_imdp.pipeline.margins import run_margins

    quiet = _Log(False)

    def abstract(part, cell_bounds):
        return _chunked_abstract(problem, part, cell_bounds, quiet, run, _chunk_cells(run, part.n_cells, MAX_ROW_CELLS))

    return run_margins(problem, grid, partition, syn, classes, dfa, log, run, cache_dir, abstract=abstract,
                       learn_and_bound=_learn_and_bound, pending=pending)


def _refine(problem: Problem, partition, abstraction, syn, cell_bounds, dfa, log: _Log, run: _Run, cache_dir,
            diagnostics):
    """Refinement rounds from the grid's result (``refine.refine``); cached under :func:`refined_key`."""
    from robust_imdp.models.geometry import BoxPartition
    from robust_imdp.jsonable import jsonable as _jsonable
    from robust_imdp.synthesis.refine import refine

    key = refined_key(problem)
    diagnostics = dict(diagnostics)
    cache_file = None if cache_dir is None else Path(cache_dir) / f"abstraction-{key}.npz"
    entry = None
    if cache_file is not None and cache_file.exists():
        with log.stage("load_abstraction"):
            entry = _load_abstraction_entry(cache_file)
    if entry is not None:
        abstraction, doc = entry
        diagnostics["refinement"] = doc.get("refinement")
        log.info(f"reused refined abstraction {cache_file.name}")
        partition = abstraction.partition
        syn, classes = _synthesize(problem, partition, abstraction, dfa, log)
        return partition, abstraction, syn, classes, diagnostics, key
    with log.stage("refine"):
        if cell_bounds is None:  # the grid's abstraction came from the cache: its boxes too
            cell_bounds = _build_abstraction(problem, partition, _Log(False), cache_dir, run)[2]
        out = refine(BoxPartition(partition), cell_bounds, _cell_bounder(problem, partition, log, run),
                     problem.noise, dfa, threshold=problem.threshold, horizon=problem.horizon,
                     options=problem.refine, abstraction=abstraction, synthesis=syn,
                     synthesize=_refine_solver(problem, dfa),
                     abstraction_options=problem.abstraction_options(),
                     progress=log.info if log.enabled else None)
    diagnostics["refinement"] = _jsonable({"stopped": out.stopped, "options": problem.refine.to_dict(),
                                           "rounds": [r.to_dict() for r in out.rounds]})
    log.info(f"refinement stopped ({out.stopped}) at {out.partition.n_cells} cells")
    if cache_file is not None:
        _save_abstraction_entry(cache_file, out.abstraction, {"refinement": diagnostics["refinement"]})
    classes = _class_names(out.synthesis.classes, out.synthesis, problem.threshold)
    return out.partition, out.abstraction, out.synthesis, classes, diagnostics, key


def _refine_solver(problem: Problem, dfa):
    """``(abstraction, partition) -> SynthesisResult`` of the refinement rounds: the run's solve, with its reading."""
    from robust_imdp.pipeline.nominal_stage import nominal_dynamics, nominal_model
    from robust_imdp.synthesis.core import synthesize

    dynamics = []  # the nominal model's dynamics, computed once for every round

    def solve(ab, part):
        if not dynamics:
            dynamics.append(nominal_dynamics(problem))
        return synthesize(ab.imdp, part.labels, part.atoms, dfa, threshold=problem.threshold, horizon=problem.horizon,
                          outside_state=part.outside_state, semantics=problem.semantics,
                          nominal=nominal_model(problem, part, dynamics[0]))

    return solve


def resynthesize(result: Result, *, formula: str | None = None, threshold: float | None = None,
                 horizon="keep", progress: bool = True, semantics: str | None = None) -> Result:
    """Solve a new formula / threshold / horizon / reading (``semantics``) on ``result``'s abstraction (no
    re-learning)."""
    from robust_imdp.spec.api import to_dfa

    changes = {} if semantics is None else {"semantics": semantics}
    if formula is not None:
        changes["formula"] = formula
    if threshold is not None:
        changes["threshold"] = threshold
    if horizon != "keep":
        changes["horizon"] = horizon
    problem = result.problem.replace(**changes)
    log = _Log(progress)
    with log.stage("specify"):
        dfa = to_dfa(problem.formula)
        _check_atoms(dfa, problem)
    log.info(_reading_line(problem, dfa))
    syn, classes = _synthesize(problem, result.partition, result.abstraction, dfa, log)
    log.timings["total"] = time.perf_counter() - log.t0
    out = Result(problem=problem, partition=result.partition, abstraction=result.abstraction,
                 dfa=dfa, synthesis=syn, class_names=classes, timings=dict(log.timings),
                 parameters=result.parameters, from_cache=True, diagnostics=result.diagnostics)
    return out
