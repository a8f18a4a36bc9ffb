"""The check and bound stages' shared part and their dispatch: residual data, data-noise allowances, the known
parts' ranges, the assumption check, diagnostics; the bound stage and the bounder of new cells of the
problem's error-bound method (``bounds.methods``: each method names its :class:`~robust_imdp.bounds.methods.CellBounder`
by a dotted path, e.g. ``pipeline/bound_rkhs.py``, ``pipeline/bound_gp.py``, which build on this module).
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from robust_imdp.bounds.methods import get as _method
from robust_imdp.models.geometry import wrap_residuals
from robust_imdp.pipeline.problem import (
    CHECK_DELTA,
    Problem,
    _is_affine,
    _setting_text,
    _settings,
)
from robust_imdp.pipeline.runtime import _Log, _Run
from robust_imdp.pipeline.cache import _read_checks, _write_json_entry, check_key, read_cache_entry


def _residual_data(problem: Problem):
    """Per mode: inputs, residuals ``x_next - f_u(x)`` and the samples' rows in the data set."""
    u = np.asarray(problem.data.u)
    out = []
    for m in range(len(problem.mode_names)):
        x, xn = problem.data.by_mode(m)
        y = xn - problem.maps[m](x)
        if getattr(problem, "periodic", None) is not None:  # modulo the period: docs/periodic.md
            y = wrap_residuals(y, 0.0, problem.space_lower, problem.space_upper, problem.periodic)[0]
        out.append((x, y, np.flatnonzero(u == m)))
    return out


def _one_setting(problem: Problem) -> bool:
    """Affine known parts and one assumption for every mode and component: the original path, unchanged."""
    return all(_is_affine(m) for m in problem.maps) and _settings(problem).uniform


def _noise_allowance(problem: Problem, noise_bound) -> np.ndarray:
    """(n_modes, n) data-noise bound of the certificate per mode: the noise bound plus the residuals' rounding.

    Eq. W (docs/rkhs_bounds.md, section 1) needs ``|h(x_i) - y_i| <= dbar + tau`` for the residuals
    it is given. For a nonlinear known part the computed residual ``fl(x_next - fl(f(x)))`` is within
    ``r_i`` of the exact ``y_i`` (``KnownDynamics.residuals``, ``AffineMap.residuals`` for an affine
    part), so the certificate and the assumption check take ``dbar + max_i r_i`` per component,
    rounded up.
    """
    M, n = len(problem.mode_names), int(np.size(problem.space_lower))
    out = np.array(np.broadcast_to(np.asarray(noise_bound, float), (M, n)))
    for u, m in enumerate(problem.maps):
        x, xn = problem.data.by_mode(u)
        if x.shape[0]:
            r = m.residuals(x, xn)  # on a periodic dimension the wrap's float error joins the bound
            rb = wrap_residuals(r.y, r.bound, problem.space_lower, problem.space_upper,
                                getattr(problem, "periodic", None))[1].max(axis=0)
            out[u] = np.nextafter(out[u] + rb, np.inf)
    return out


def _shared_allowance(problem: Problem, noise_bound) -> np.ndarray:
    """(n,) the largest data-noise allowance over the modes (the one-setting path's single noise bound)."""
    return np.max(_noise_allowance(problem, noise_bound), axis=0)


def _known_ranges(problem: Problem, cells_lower, cells_upper) -> list:
    """Per mode: None (affine) or the certified range of the nonlinear known part over the cells
    (``KnownDynamics.image_bounds``; raises ``ExpressionDomainError`` where f is undefined). The modes of an
    input grid that share one ``f(x, u)`` are bounded in one call (:func:`known_images`)."""
    nonlinear = [u for u, m in enumerate(problem.maps) if not _is_affine(m)]
    out = [None] * len(problem.maps)
    for u, r in zip(nonlinear, known_images([problem.maps[u] for u in nonlinear], cells_lower, cells_upper)):
        out[u] = r
    return out


def known_images(maps, cells_lower, cells_upper, **options) -> list:
    """The certified range of each known part of ``maps`` over the cells (``image_bounds``), one
    ``known.ImageBounds`` per map.

    Maps of one input grid (``models.inputs.InputMode``: one ``f(x, u)`` at different inputs) are bounded
    together, in one vectorised call over every (mode, cell) box ``cell x {u}`` (chunked by ``image_bounds``),
    so 441 inputs cost one pass over 441 x n_cells boxes instead of 441 passes with their set-up each.
    ``options`` go to every ``image_bounds`` (e.g. ``form="natural"``: the load-time domain check).
    """
    from robust_imdp.models.known import ImageBounds

    out = [None] * len(maps)
    groups: dict = {}
    for u, m in enumerate(maps):
        key = id(m.dynamics) if hasattr(m, "dynamics") and hasattr(m, "input") else None
        if key is None:
            out[u] = m.image_bounds(cells_lower, cells_upper, **options)
        else:
            groups.setdefault(key, []).append(u)
    lo, hi = np.asarray(cells_lower, float), np.asarray(cells_upper, float)
    N = lo.shape[0]
    for members in groups.values():
        dyn = maps[members[0]].dynamics
        U = np.stack([np.asarray(maps[u].input, float) for u in members])  # (G, m)
        blo = np.concatenate([np.tile(lo, (len(members), 1)), np.repeat(U, N, axis=0)], axis=1)
        bhi = np.concatenate([np.tile(hi, (len(members), 1)), np.repeat(U, N, axis=0)], axis=1)
        r = dyn.image_bounds(blo, bhi, **options)
        for g, u in enumerate(members):
            sl = slice(g * N, (g + 1) * N)
            out[u] = ImageBounds(r.lower[sl], r.upper[sl], r.leaves[sl])
    return out


def known_cell_bounds(problem: Problem, cells_lower, cells_upper):
    """Known dynamics (``problem.known``): ``(lower, upper)``, (n_modes, k, n), the certified image of ``f_u``
    over each cell widened by the misspecification ``tau`` of each component: ``f_u(x) + g_u(x)`` with
    ``|g_u| <= tau`` lies in ``range(f_u) + [-tau, tau]``, rounded outward (``assumptions.add_ranges``)."""
    from robust_imdp.bounds.assumptions import add_ranges

    tau = _settings(problem).misspecification  # (M, n)
    M, n, k = len(problem.maps), int(np.size(problem.space_lower)), np.shape(cells_lower)[0]
    lower, upper = np.empty((M, k, n)), np.empty((M, k, n))
    for u, r in enumerate(known_images(problem.maps, cells_lower, cells_upper)):
        if not np.any(tau[u] > 0):  # exactly known: the certified range as it is
            lower[u], upper[u] = r.lower, r.upper
            continue
        t = np.broadcast_to(tau[u], (k, n))
        lower[u], upper[u] = add_ranges(r.lower, r.upper, -t, t)
    return lower, upper


#: What a result of known dynamics states (``diagnostics.statement``; the summary's line).
KNOWN_STATEMENT = ("known dynamics: every component of every mode is known (rkhs_bound = 0); nothing is learned, no "
                   "data are used and no assumption is checked; the bounds hold with probability 1 under the noise "
                   "model")


def known_stage(problem: Problem, partition, log: _Log, run: "_Run | None" = None, cache_dir=None):
    """The bound stage of known dynamics: ``(cell_bounds, None, diagnostics)`` with the known parts' certified
    ranges over the grid's cells (:func:`known_cell_bounds`), no data and no assumption check."""
    from robust_imdp.abstraction.cell_bounds import CellBounds

    with log.stage("bound"):
        lower, upper = known_cell_bounds(problem, partition.cells_lower, partition.cells_upper)
    M, N = lower.shape[:2]
    log.info(f"known dynamics: certified images of {N} cells x {M} modes (no data, no assumption check)")
    diag = {"error_bound": "known", "confidence": 1.0, "statement": KNOWN_STATEMENT, "dynamics": "known",
            "cell_half_width": (0.5 * np.asarray(problem.cell_size, float)).tolist()}
    nonlinear = [u for u, m in enumerate(problem.maps) if not _is_affine(m)]
    if nonlinear:  # the gap of the certified range to the attained one, on a few cells of at most 4 modes
        pick = [nonlinear[i] for i in np.unique(np.linspace(0, len(nonlinear) - 1, min(4, len(nonlinear)))
                                                .round().astype(np.int64))]
        ranges = [None] * M
        for u, r in zip(pick, known_images([problem.maps[u] for u in pick], partition.cells_lower,
                                           partition.cells_upper)):
            ranges[u] = r
        # sampling only: IPOPT's seconds would dominate a known system's run (the abstraction takes a second)
        diag["known_part_gap"] = _known_gap(problem, partition, ranges, optimise=False)
    return CellBounds(lower, upper, None), None, diag


def known_bounder(problem: Problem, partition, log: _Log, run: "_Run | None" = None, task=None):
    """``bound_cells(lower, upper) -> (image_lower, image_upper)`` of new cells for known dynamics
    (refinement): :func:`known_cell_bounds`."""

    def bound_cells(lower, upper):
        return known_cell_bounds(problem, lower, upper)

    return bound_cells


def _add_known_range(lower, upper, ranges) -> None:
    """``g``'s certified range plus ``f``'s, in place: the image of ``f_u + g_u`` over each cell is in the
    Minkowski sum of the two ranges; the sum is rounded outward (``assumptions.add_ranges``)."""
    from robust_imdp.bounds.assumptions import add_ranges

    lower[...], upper[...] = add_ranges(lower, upper, ranges.lower, ranges.upper)


def _known_gap(problem: Problem, partition, ranges, n_cells: int = 8, optimise: bool = True) -> list:
    """Gap of the certified range of each nonlinear known part to the range it attains (sampling + IPOPT; without
    ``optimise`` sampling only, an upper bound of that gap, and the rows say ``"optimised": false``) on
    ``n_cells`` evenly spaced cells (``KnownDynamics.achieved_range``, ``gap_to``): a diagnostic."""
    rows = []
    N = partition.n_cells
    pick = np.unique(np.linspace(0, N - 1, min(n_cells, N)).round().astype(np.int64))
    lo, up = partition.cells_lower[pick], partition.cells_upper[pick]
    width = np.max(up - lo, axis=1)
    for u, (m, r) in enumerate(zip(problem.maps, ranges)):
        if r is None:
            continue
        from robust_imdp.models.known import ImageBounds

        sub = ImageBounds(r.lower[pick], r.upper[pick], r.leaves[pick])
        gap = m.achieved_range(lo, up, optimise=optimise).gap_to(sub)
        for i in range(gap.shape[1]):
            rows.append({"mode": problem.mode_names[u], "component": i + 1, "expression": m.expressions[i],
                         "cells": int(pick.size), "gap_max": float(gap[:, i].max()),
                         "gap_over_cell_width_max": float(np.max(gap[:, i] / width)),
                         **({} if optimise else {"optimised": False})})
    return rows


def _failure_budget(problem: Problem):
    """Split ``1 - confidence`` between the data-noise bound and the iid event (route 'optimal'/'ridge')."""
    fail = 1.0 - float(problem.confidence)
    bounded = bool(getattr(problem.noise, "bounded", False))
    if bounded:
        return 0.0, (fail if problem.iid_noise else 0.0)
    return (fail / 2, fail / 2) if problem.iid_noise else (fail, 0.0)


def _scheduled_norms(run: "_Run | None", log: _Log):
    """The check's ``norms`` (``rkhs_check.check_assumption``): one task per mode and component on the run's
    scheduler (``Scheduler.run_beside``), the results in the jobs' order (the same SOCPs as in this process, so
    the same bits); without a run (None) in this process."""
    if run is None:
        return None
    from robust_imdp.bounds.rkhs_check import norm_task

    def norms(jobs):
        return run.scheduler(log).run_beside(norm_task, jobs)

    return norms


def _compute_checks(problem: Problem, data, nb, norms) -> tuple:
    """The assumption check's ``NormCheck``s (raises ``AssumptionError`` for a refuted assumption): one setting
    (``rkhs_check.check_assumption``) or per mode and component with the residuals' rounding in the noise
    allowance (``assumptions.check_modes``)."""
    if _one_setting(problem):
        from robust_imdp.bounds.rkhs import check_assumption

        return check_assumption([(x, y) for x, y, _ in data], lengthscale=problem.gp_options.get("lengthscale", 1.0),
                                rkhs_bound=problem.rkhs_bound, noise_bound=_shared_allowance(problem, nb),
                                misspecification=problem.misspecification, mode_names=problem.mode_names,
                                sample_index=[idx for _, _, idx in data], norms=norms)
    from robust_imdp.bounds.assumptions import check_modes

    return check_modes([(x, y) for x, y, _ in data], _settings(problem), _noise_allowance(problem, nb),
                       mode_names=problem.mode_names, sample_index=[idx for _, _, idx in data], norms=norms)


class _PendingCheck:
    """The assumption check of a run, computed at once or in a thread beside the bound stage.

    :meth:`result` gives ``(checks, noise bound)`` (raising the check's ``AssumptionError``), saves a passed
    check in the cache and logs it; :meth:`raise_if_refused` raises that error as soon as the check has refused,
    so a run whose assumption the data refute stops within one bound task of the check's end.
    """

    def __init__(self, problem: Problem, log: _Log, check_file, nb, compute=None, beside: bool = False,
                 cached=None):
        import threading

        self.problem, self.log, self.check_file, self.nb = problem, log, check_file, nb
        self.checks, self.error, self.cached, self._reported = None, None, cached is not None, False
        self._thread = None
        if cached is not None:
            self.checks, self.nb = cached
        elif beside:
            self._thread = threading.Thread(target=self._compute, args=(compute,), daemon=True,
                                            name="robust-imdp assumption check")
            self._thread.start()
        else:
            with log.stage("check"):
                self._compute(compute)

    def _compute(self, compute) -> None:
        try:
            self.checks = compute()
        except BaseException as exc:  # raised in the caller's thread by result()
            self.error = exc

    def done(self) -> bool:
        return self._thread is None or not self._thread.is_alive()

    def raise_if_refused(self) -> None:
        """Raise the check's error if it has ended with one (never waits)."""
        if self.done() and self.error is not None:
            self.result()

    def result(self) -> tuple:
        if self._thread is not None and self._thread.is_alive():
            with self.log.stage("check"):  # the time the run waits for it
                self._thread.join()
        if self.error is not None:
            raise self.error
        if not self._reported:
            self._reported = True
            if self.check_file is not None and not self.cached:
                _write_json_entry(self.check_file, {"checks": [asdict(c) for c in self.checks], "noise_bound": self.nb})
            worst = max(self.checks, key=lambda c: c.minimum)
            self.log.info(f"assumption check{' (reused from the cache)' if self.cached else ''}: the data need RKHS "
                          f"norm >= {worst.minimum:.4g} (mode {self.problem.mode_names[worst.mode]}, component "
                          f"{worst.output + 1}); rkhs_bound = {_setting_text(self.problem.rkhs_bound)}")
        return self.checks, self.nb


def _start_check(problem: Problem, data, log: _Log, cache_dir=None, run: "_Run | None" = None,
                 beside_cell_modes: int = 0) -> _PendingCheck:
    """Start the assumption check (reused from the cache when it passed before); its components run as tasks on
    ``run``'s scheduler (None: in this process). With ``beside_cell_modes`` >= ``parallel.SIDE_MIN_CELL_MODES``
    (the bound stage's cells x modes) and a scheduler that runs side work concurrently (a Dask cluster; in
    process on several cores, its side lane) the check runs beside the bound stage: call the pending check's
    ``result()`` when its checks are needed."""
    from robust_imdp.bounds.rkhs import noise_bound_at_confidence

    m_total = sum(x.shape[0] for x, _, _ in data)
    nb, _ = noise_bound_at_confidence(problem.noise, m_total, CHECK_DELTA)
    # The check only passes or raises, and its result depends on the data and the assumption only
    # (check_key): a passed check is saved and reused by every run on the same data and assumption.
    check_file = None if cache_dir is None else Path(cache_dir) / f"check-{check_key(problem)}.json"
    cached = None if check_file is None else read_cache_entry(check_file, _read_checks)
    if cached is not None:
        return _PendingCheck(problem, log, check_file, nb, cached=cached)
    norms = _scheduled_norms(run, log)
    beside = False
    if run is not None and beside_cell_modes > 0:
        from robust_imdp.pipeline.parallel import SIDE_MIN_CELL_MODES

        if beside_cell_modes >= SIDE_MIN_CELL_MODES:
            beside = run.scheduler(log).use_side_lane()
    if beside:
        log.info("assumption check: beside the bound stage (" + run.scheduler(log).side_description + ")")
    return _PendingCheck(problem, log, check_file, nb, lambda: _compute_checks(problem, data, nb, norms), beside)


def _check_assumption(problem: Problem, data, log: _Log, cache_dir=None, run: "_Run | None" = None):
    """The assumption check (``(checks, noise bound)``), reused from the cache when it passed before; its
    components run as tasks on ``run``'s scheduler (None: in this process)."""
    return _start_check(problem, data, log, cache_dir, run).result()


def _fitted(problem: Problem, data):
    """The data-fitted function of every mode (``advice.fit_modes``): known part plus a kernel-ridge fit."""
    from robust_imdp.synthesis.advice import fit_modes

    sigma = np.asarray(problem.noise.sub_gaussian_parameter(), float)
    if not _settings(problem).uniform:
        from robust_imdp.bounds.assumptions import fit_components

        return fit_components([(x, y) for x, y, _ in data], problem.maps, _settings(problem), sigma)
    # ridge parameter sigma^2 / B^2: the GP posterior mean with prior variance B^2 (kept >= 1e-6)
    lam = np.maximum(sigma / float(problem.rkhs_bound), 1e-3) ** 2
    return fit_modes([(x, y) for x, y, _ in data], problem.maps, problem.gp_options.get("lengthscale", 1.0), lam)


def _diagnostics(problem: Problem, partition, cell_bounds, data, checks, check_noise, confidence: float,
                 statement: str) -> dict:
    from robust_imdp.synthesis.advice import excess_radius

    half = 0.5 * np.asarray(problem.cell_size, float)
    # The error radius is the excess of each learned image box over the range of the data-fitted
    # function over the cell (advice.excess_radius): the same computation for every mode and
    # component, from the boxes and the fit alone (the bound stage's internal vertex radius depends
    # on which vertex problems its pruning solved, so on the component's position).
    flo, fhi = _fitted(problem, data).grid_ranges(partition.breakpoints)
    eps = excess_radius(np.asarray(cell_bounds.image_lower), np.asarray(cell_bounds.image_upper), flo, fhi)
    rows = []
    for u, name in enumerate(problem.mode_names):
        for i in range(eps.shape[2]):
            e = eps[u, :, i]
            rows.append({"mode": name, "component": i + 1, "median": float(np.median(e)), "max": float(np.max(e)),
                         "median_over_half_cell": float(np.median(e) / half[i])})
    return {
        "error_bound": problem.error_bound,
        "confidence": float(confidence),
        "statement": statement,
        "cell_half_width": half.tolist(),
        "eps": rows,
        "assumption": {
            **_assumption_diagnostics(problem, len(half)),
            "check_noise_bound": np.asarray(check_noise, float).tolist(),
            "min_norm": [{"mode": problem.mode_names[c.mode], "component": c.output + 1, "minimum": c.minimum,
                          "n_points": c.n_points} for c in checks],
        },
    }


def _assumption_diagnostics(problem: Problem, n: int) -> dict:
    """rkhs_bound, lengthscale, misspecification of the diagnostics (as before with one setting); per mode and
    component in ``per_component`` otherwise, with the largest B and tau and the smallest lengthscales on top."""
    st = _settings(problem)
    if st.uniform:
        return {"rkhs_bound": float(problem.rkhs_bound),
                "lengthscale": np.broadcast_to(np.asarray(problem.gp_options.get("lengthscale", 1.0), float),
                                               (n,)).tolist(),
                "misspecification": float(problem.misspecification)}
    return {"rkhs_bound": float(st.rkhs_bound.max()), "lengthscale": st.lengthscale.min(axis=(0, 1)).tolist(),
            "misspecification": float(st.misspecification.max()), "per_component": st.to_rows(problem.mode_names)}


def _prepare(problem: Problem, partition, log: _Log, cache_dir=None, run: "_Run | None" = None):
    """What every method's bound stage does first: ``(data, known_ranges, checks, check_noise)``.

    The residual data (:func:`_residual_data`), the known parts' certified ranges over the grid's cells
    (a function undefined on part of X is refused before the long stages: ``ExpressionDomainError``
    names the mode, the component and the box), then the assumption check (:func:`_check_assumption`, on
    ``run``'s scheduler when given).
    """
    data = _residual_data(problem)
    known_ranges = _known_ranges(problem, partition.cells_lower, partition.cells_upper)
    checks, check_noise = _check_assumption(problem, data, log, cache_dir, run)
    return data, known_ranges, checks, check_noise


def _prepare_beside(problem: Problem, partition, log: _Log, cache_dir=None, run: "_Run | None" = None):
    """:func:`_prepare` with the assumption check started beside the bound stage where the run's scheduler can
    (:func:`_start_check`): ``(data, known_ranges, pending check)``; its ``result()`` gives ``(checks,
    check_noise)``, its ``raise_if_refused()`` stops the bound stage early for a refuted assumption."""
    data = _residual_data(problem)
    known_ranges = _known_ranges(problem, partition.cells_lower, partition.cells_upper)
    check = _start_check(problem, data, log, cache_dir, run, partition.n_cells * len(problem.mode_names))
    return data, known_ranges, check


def _learn_and_bound(problem: Problem, partition, log: _Log, run: "_Run | None" = None, cache_dir=None):
    """The bound stage of the problem's error-bound method: ``(cell_bounds, error models or None, diagnostics)``
    (its ``BoundMethod.stage()``); for known dynamics (``problem.known``) :func:`known_stage`."""
    if problem.known:
        return known_stage(problem, partition, log, run, cache_dir)
    return _method(problem.error_bound).stage()(problem, partition, log, run, cache_dir)


def _cell_bounder(problem: Problem, partition, log: _Log, run: _Run, task=None):
    """``bound_cells(lower, upper) -> (image_lower, image_upper)`` for new cells, on the same event as the
    grid's (refinement, the advice's pilot cells; ``task``: the function each chunk runs): the method's
    ``BoundMethod.new_cells_stage()``; for known dynamics :func:`known_bounder`."""
    if problem.known:
        return known_bounder(problem, partition, log, run, task=task)
    return _method(problem.error_bound).new_cells_stage()(problem, partition, log, run, task=task)
