"""The check and bound stages: residual data, data-noise allowances, the assumption check, certified cell
bounds (chunked, resumable, on the run's scheduler), their diagnostics, and the bounder of new cells.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from robust_imdp.bounds.methods import get as _method
from robust_imdp.pipeline.problem import (
    CHECK_DELTA,
    LOCAL_AUTO,
    LOCAL_DEFAULT,
    Problem,
    _is_affine,
    _setting_text,
    _settings,
)
from robust_imdp.pipeline.runtime import _Log, _Run, _chunk_cells
from robust_imdp.pipeline.cache import (
    _load_npz,
    _read_checks,
    _savez,
    _write_json_entry,
    bounds_key,
    check_key,
    read_cache_entry,
    write_cache_entry,
)


def _residual_data(problem: Problem):
    """Per mode: inputs, residuals ``x_next - f_u(x)`` and the samples' rows in the data set."""
    u = np.asarray(problem.data.u)
    out = []
    for m in range(len(problem.mode_names)):
        x, xn = problem.data.by_mode(m)
        out.append((x, xn - problem.maps[m](x), np.flatnonzero(u == m)))
    return out


def _one_setting(problem: Problem) -> bool:
    """Affine known parts and one assumption for every mode and component: the original path, unchanged."""
    return all(_is_affine(m) for m in problem.maps) and _settings(problem).uniform


def _affine_part(problem: Problem, u: int):
    """(A, b) of mode ``u``'s affine known part, or zeros for a nonlinear one (its range is added to g's)."""
    m = problem.maps[u]
    if _is_affine(m):
        return m.A, m.b
    n = int(np.size(problem.space_lower))
    return np.zeros((n, n)), np.zeros(n)


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
            rb = m.residuals(x, xn).bound.max(axis=0)
            out[u] = np.nextafter(out[u] + rb, np.inf)
    return out


def _shared_allowance(problem: Problem, noise_bound) -> np.ndarray:
    """(n,) the largest data-noise allowance over the modes (the one-setting path's single noise bound)."""
    return np.max(_noise_allowance(problem, noise_bound), axis=0)


def _known_ranges(problem: Problem, cells_lower, cells_upper) -> list:
    """Per mode: None (affine) or the certified range of the nonlinear known part over the cells
    (``KnownDynamics.image_bounds``; raises ``ExpressionDomainError`` where f is undefined)."""
    return [None if _is_affine(m) else m.image_bounds(cells_lower, cells_upper) for m in problem.maps]


def _add_known_range(lower, upper, ranges) -> None:
    """``g``'s certified range plus ``f``'s, in place: the image of ``f_u + g_u`` over each cell is in the
    Minkowski sum of the two ranges; the sum is rounded outward (``assumptions.add_ranges``)."""
    from robust_imdp.bounds.assumptions import add_ranges

    lower[...], upper[...] = add_ranges(lower, upper, ranges.lower, ranges.upper)


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


def _known_gap(problem: Problem, partition, ranges, n_cells: int = 8) -> list:
    """Gap of the certified range of each nonlinear known part to the range it attains (sampling + IPOPT)
    on ``n_cells`` evenly spaced cells (``KnownDynamics.achieved_range``, ``gap_to``): a diagnostic."""
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
        gap = m.achieved_range(lo, up).gap_to(sub)
        for i in range(gap.shape[1]):
            rows.append({"mode": problem.mode_names[u], "component": i + 1, "expression": m.expressions[i],
                         "cells": int(pick.size), "gap_max": float(gap[:, i].max()),
                         "gap_over_cell_width_max": float(np.max(gap[:, i] / width))})
    return rows


def _failure_budget(problem: Problem):
    """Split ``1 - confidence`` between the data-noise bound and the iid event (route 'optimal'/'ridge')."""
    fail = 1.0 - float(problem.confidence)
    bounded = bool(getattr(problem.noise, "bounded", False))
    if bounded:
        return 0.0, (fail if problem.iid_noise else 0.0)
    return (fail / 2, fail / 2) if problem.iid_noise else (fail, 0.0)


def _check_assumption(problem: Problem, data, log: _Log, cache_dir=None):
    from robust_imdp.bounds.rkhs import check_assumption, noise_bound_at_confidence

    m_total = sum(x.shape[0] for x, _, _ in data)
    nb, _ = noise_bound_at_confidence(problem.noise, m_total, CHECK_DELTA)
    # The check only passes or raises, and its result depends on the data and the assumption only
    # (check_key): a passed check is saved and reused by every run on the same data and assumption.
    check_file = None if cache_dir is None else Path(cache_dir) / f"check-{check_key(problem)}.json"
    cached = None if check_file is None else read_cache_entry(check_file, _read_checks)
    if cached is not None:
        checks, nb = cached
    else:
        with log.stage("check"):
            if _one_setting(problem):
                checks = check_assumption([(x, y) for x, y, _ in data],
                                          lengthscale=problem.gp_options.get("lengthscale", 1.0),
                                          rkhs_bound=problem.rkhs_bound, noise_bound=_shared_allowance(problem, nb),
                                          misspecification=problem.misspecification, mode_names=problem.mode_names,
                                          sample_index=[idx for _, _, idx in data])
            else:  # per mode and component, with the residuals' rounding in the noise allowance
                from robust_imdp.bounds.assumptions import check_modes

                checks = check_modes([(x, y) for x, y, _ in data], _settings(problem), _noise_allowance(problem, nb),
                                     mode_names=problem.mode_names, sample_index=[idx for _, _, idx in data])
        if check_file is not None:
            _write_json_entry(check_file, {"checks": [asdict(c) for c in checks], "noise_bound": nb})
    worst = max(checks, key=lambda c: c.minimum)
    log.info(f"assumption check{' (reused from the cache)' if cached is not None else ''}: the data need RKHS "
             f"norm >= {worst.minimum:.4g} (mode {problem.mode_names[worst.mode]}, component {worst.output + 1}); "
             f"rkhs_bound = {_setting_text(problem.rkhs_bound)}")
    return checks, nb


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


def _bound_task(X, Y, A, b, lower, upper, local, mode=None, *, threads=1, **settings):
    """One chunk of the bound stage; ``local`` = (points, ridge lambda) of the mode or None; ``mode``: None
    (the problem-wide settings) or the mode's own (``assumptions.bound_mode_chunk``)."""
    return _bound_work(X, Y, A, b, lower, upper, local, mode, threads=threads, **settings)


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


def _local_settings(problem: Problem, data, partition, noise_bound):
    """Per mode: None (all points) or (points, ridge lambda) of the local weights."""
    from robust_imdp.bounds.rkhs import local_lambda

    out = []
    for x, _, _ in data:
        k = problem.local_points
        if k is None:
            k = None if x.shape[0] <= LOCAL_AUTO else LOCAL_DEFAULT
        if k is None or k >= x.shape[0]:
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


def _check_part(part: dict, k: int, n: int) -> dict:
    """A saved bound chunk, checked to hold ``k`` cells x ``n`` outputs (else ValueError: computed again)."""
    for key in ("lower", "upper", "eps", "support"):
        if key not in part or np.shape(part[key]) != (k, n):
            raise ValueError(f"{key} must have shape ({k}, {n}); got "
                             f"{np.shape(part[key]) if key in part else 'no such array'}")
    if "n_unconverged" not in part:
        raise ValueError("n_unconverged is missing")
    return part


def _learn_and_bound(problem: Problem, partition, log: _Log, run: "_Run | None" = None, cache_dir=None):
    from robust_imdp.abstraction.rows import CellBounds

    run = run if run is not None else _Run()
    data = _residual_data(problem)
    # the known parts' certified ranges first: a function undefined on part of X is refused before
    # the long stages (ExpressionDomainError names the mode, the component and the box)
    known_ranges = _known_ranges(problem, partition.cells_lower, partition.cells_upper)
    checks, check_noise = _check_assumption(problem, data, log, cache_dir)
    if _method(problem.error_bound).route == "gp":
        return _learn_and_bound_gp(problem, partition, log, checks, check_noise)
    from robust_imdp.bounds.rkhs import CELL_BLOCK, check_ranges, hoeffding_factor, noise_bound_at_confidence

    data_fail, iid_delta = _failure_budget(problem)
    m_total = sum(x.shape[0] for x, _, _ in data)
    noise_bound, _ = noise_bound_at_confidence(problem.noise, m_total, data_fail if data_fail > 0 else 0.5)
    M, n, N = len(problem.mode_names), len(problem.space_lower), partition.n_cells
    lo, up = partition.cells_lower, partition.cells_upper
    iid_theta = problem.noise.sub_gaussian_parameter() if problem.iid_noise else None
    settings = {**_base_settings(problem), "noise_bound": _shared_allowance(problem, noise_bound),
                "method": _method(problem.error_bound).weights, "iid_theta": iid_theta,
                "iid_factor": None if iid_theta is None else hoeffding_factor(M * n * N * 2 ** n, iid_delta)}
    chunk = _chunk_cells(run, N, 256)
    tasks = [(u, s0) for u in range(M) for s0 in range(0, N, chunk)]
    local = _local_settings(problem, data, partition, noise_bound)
    # one allowance for every mode (the largest), as on the one-setting path: equal settings, equal bytes
    extras = _mode_extras(problem, data, partition, _shared_allowance(problem, noise_bound), local)
    if any(loc is not None for loc in local):
        log.info("local weights: " + ", ".join(f"mode {problem.mode_names[u]}: "
                                               + ("all points" if loc is None else f"{loc[0]} nearest points")
                                               for u, loc in enumerate(local)))
    parts_dir = None if cache_dir is None else Path(cache_dir) / f"bounds-{bounds_key(problem)}.parts"
    results: dict = {}
    if parts_dir is not None and parts_dir.exists():
        for u, s0 in tasks:
            part = read_cache_entry(parts_dir / f"m{u}-c{s0}-{chunk}.npz",
                                    lambda f, k=min(chunk, N - s0): _check_part(_load_npz(f), k, n))
            if part is not None:
                results[(u, s0)] = part
        if results:
            log.info(f"resumed: {len(results)} of {len(tasks)} bound chunks from {parts_dir}")
    missing = [t for t in tasks if t not in results]
    with log.stage("bound"):
        work = None
        if missing:
            # Pre-flight: time a few blocks of cells in this process and extrapolate.
            from robust_imdp.bounds import rkhs

            x0, y0, _ = data[0]
            A0, b0 = _affine_part(problem, 0)
            # The kernels' first call in a process compiles them (no warm-up at install) or loads
            # them from numba's cache (about 1 s): a one-cell call takes that time, so that the
            # timed pilot below measures bounding only.
            first = dict(settings) if local[0] is None else dict(settings, local_points=local[0][0],
                                                                 local_lambda=local[0][1])
            compile_s = rkhs.bound_chunk(x0, y0, A0, b0, lo[:1], up[:1], threads=1, **first)["seconds"]
            if compile_s > 5.0:
                log.info(f"pre-flight: numba compiled the bound kernels in {compile_s:.0f} s (once: cached for later "
                         "runs; `python -m robust_imdp.warmup` does it at install)")
            sched = run.scheduler(log)
            # One block per thread of a task, on that many threads: in process, the numba threads
            # share the cores with whatever else runs, and this measures the speed the tasks get.
            threads = int(getattr(sched, "threads", 1))
            k = min(N, CELL_BLOCK * threads)
            pilot = _bound_task(x0, y0, A0, b0, lo[:k], up[:k], local[0], *_extra(extras[0]), threads=threads,
                                **settings)
            per_cell = pilot["seconds"] / k  # wall seconds per cell and mode, on ``threads`` threads
            lanes = max(1, sched.n_workers // threads)  # tasks running at once
            wall = per_cell * N * M * len(missing) / len(tasks) / lanes
            log.info(f"pre-flight: {N:,} cells x {M} modes x {n} outputs = {N * M * n:,} cell bounds; about "
                     f"{wall * sched.n_workers:.0f} s of work ({per_cell * threads * 1e3:.2f} ms per cell and mode "
                     f"on one core), about {wall:.0f} s on {sched.n_workers} core{'s' if sched.n_workers > 1 else ''}")
            shared = [(sched.share(np.ascontiguousarray(x)), sched.share(np.ascontiguousarray(y)))
                      for x, y, _ in data]  # sent to the workers once
            args = [(*shared[u], *_affine_part(problem, u), lo[s0:s0 + chunk], up[s0:s0 + chunk],
                     local[u], *_extra(extras[u])) for u, s0 in missing]
            t0 = time.perf_counter()
            for i, res in sched.run(_bound_task, args, settings):
                key = missing[i]
                results[key] = res
                if parts_dir is not None:  # saved as it completes: an interrupted run resumes from here
                    write_cache_entry(parts_dir / f"m{key[0]}-c{key[1]}-{chunk}.npz",
                                      lambda tmp, r=res: _savez(tmp, {k: np.asarray(v) for k, v in r.items()}))
                log.progress("bound", len(results), len(tasks), t0, resumed=len(tasks) - len(missing))
    lower = np.empty((M, N, n))
    upper = np.empty((M, N, n))
    support = np.empty((M, N, n), dtype=np.int64)
    unconv = 0
    for (u, s0), r in results.items():
        sl = slice(s0, min(N, s0 + chunk))
        lower[u, sl], upper[u, sl], support[u, sl] = r["lower"], r["upper"], r["support"]
        unconv += int(r["n_unconverged"])
    for u in range(M):
        check_ranges(lower[u], upper[u], u)
        if known_ranges[u] is not None:  # f_u's certified range plus g_u's (the chunks bounded g_u alone)
            _add_known_range(lower[u], upper[u], known_ranges[u])
    confidence = 1.0 - data_fail - (iid_delta if iid_theta is not None else 0.0)
    log.info(f"bounded images of {N} cells x {M} modes x {n} outputs ({problem.error_bound} weights)")
    if confidence >= 1.0:
        statement = ("with probability 1, if every unknown component is within the misspecification of a "
                     "function of RKHS norm <= rkhs_bound and the data noise is within its bound")
    else:
        events = []
        if data_fail > 0:
            events.append(f"the data noise within {np.round(noise_bound, 6).tolist()} (probability >= "
                          f"{1 - data_fail:g})")
        if iid_delta > 0:
            events.append(f"the sub-Gaussian bound of independent noise (probability >= {1 - iid_delta:g})")
        statement = (f"with probability >= {confidence:g} over the data ({'; '.join(events)}), if every "
                     "unknown component is within the misspecification of a function of RKHS norm <= rkhs_bound")
    cell_bounds = CellBounds(lower, upper, None)
    diag = _diagnostics(problem, partition, cell_bounds, data, checks, check_noise, confidence, statement)
    diag["support_median"] = float(np.median(support))
    if any(r is not None for r in known_ranges):
        diag["known_part_gap"] = _known_gap(problem, partition, known_ranges)
    if unconv:
        diag["unconverged_vertex_problems"] = int(unconv)
    return cell_bounds, None, diag


def _learn_and_bound_gp(problem: Problem, partition, log: _Log, checks, check_noise):
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.bounds.gp_cells import bound_image
    from robust_imdp.bounds.gp import learn

    theta = problem.noise.sub_gaussian_parameter()
    with log.stage("learn"):
        learned = learn(problem.data, list(problem.maps), rkhs_bound=problem.rkhs_bound,
                        noise_theta=theta, **problem.gp_options)
    n_modes, n = len(problem.mode_names), len(problem.space_lower)
    log.info(f"learned {n_modes} modes x {n} outputs from {len(problem.data.u)} points")
    lo, up = partition.cells_lower, partition.cells_upper
    with log.stage("bound"):
        images = [bound_image(learned.gps[u], problem.maps[u].A, problem.maps[u].b, lo, up,
                              tol=problem.bound_tol, max_boxes=problem.bound_max_boxes)
                  for u in range(n_modes)]
    log.info(f"bounded images of {partition.n_cells} cells x {n_modes} modes")
    cell_bounds = CellBounds(
        image_lower=np.stack([im.lower for im in images]),
        image_upper=np.stack([im.upper for im in images]),
        std_upper=np.stack([im.std_upper for im in images]),
    )
    boxes = cell_bounds  # the error radius is measured on the boxes that are abstracted
    if problem.guarantee == "confidence":
        from robust_imdp.abstraction.rows import confidence_cell_bounds

        boxes = confidence_cell_bounds(cell_bounds, learned.error_bounds, problem.confidence)
    if problem.guarantee == "confidence":
        statement = (f"with probability >= {problem.confidence:g} over the data (Chowdhury-Gopalan error bound, "
                     "union bound over the GPs), if every unknown component has RKHS norm <= rkhs_bound")
        conf = float(problem.confidence)
    else:
        statement = ("Thm 1 as printed: mixes a probability over the data into the transition bounds; not a "
                     "guarantee for one fixed system (docs/soundness_audit.md, F2)")
        conf = None
    diag = _diagnostics(problem, partition, boxes, _residual_data(problem), checks, check_noise,
                        conf if conf is not None else float("nan"), statement)
    if conf is None:
        diag["confidence"] = None
    return cell_bounds, learned.error_bounds, diag


def _pilot_task(*args, threads=1, **settings):
    """The advice's pilot cells: the work of :func:`_bound_task` (same arguments, including a mode's own
    settings) under its own name, so that progress does not count them as bound-stage chunks."""
    return _bound_work(*args, threads=threads, **settings)


def _cell_bounder(problem: Problem, partition, log: _Log, run: _Run, task=None):
    """``bound_cells(lower, upper) -> (image_lower, image_upper)`` for new cells: the bound stage's settings.

    The same data, noise bound (one event over the data, whatever the cells), weights and local
    pools as :func:`_learn_and_bound`, so a new cell's box holds on the same event as the grid's.
    """
    from robust_imdp.bounds.rkhs import check_ranges, noise_bound_at_confidence

    data = _residual_data(problem)
    data_fail, _ = _failure_budget(problem)
    m_total = sum(x.shape[0] for x, _, _ in data)
    noise_bound, _ = noise_bound_at_confidence(problem.noise, m_total, data_fail if data_fail > 0 else 0.5)
    settings = {**_base_settings(problem), "noise_bound": _shared_allowance(problem, noise_bound),
                "method": _method(problem.error_bound).weights, "iid_theta": None, "iid_factor": None}
    local = _local_settings(problem, data, partition, noise_bound)
    # one allowance for every mode (the largest), as on the one-setting path: equal settings, equal bytes
    extras = _mode_extras(problem, data, partition, _shared_allowance(problem, noise_bound), local)
    sched = run.scheduler(log)
    shared = [(sched.share(np.ascontiguousarray(x)), sched.share(np.ascontiguousarray(y))) for x, y, _ in data]
    M, n = len(problem.mode_names), len(problem.space_lower)

    def bound_cells(lower, upper):
        k = lower.shape[0]
        chunk = _chunk_cells(run, k, 256)
        tasks = [(u, s0) for u in range(M) for s0 in range(0, k, chunk)]
        args = [(*shared[u], *_affine_part(problem, u), lower[s0:s0 + chunk], upper[s0:s0 + chunk],
                 local[u], *_extra(extras[u])) for u, s0 in tasks]
        lo, hi = np.empty((M, k, n)), np.empty((M, k, n))
        for i, res in sched.run(task or _bound_task, args, settings):
            u, s0 = tasks[i]
            lo[u, s0:s0 + chunk], hi[u, s0:s0 + chunk] = res["lower"], res["upper"]
        known = _known_ranges(problem, lower, upper)
        for u in range(M):
            check_ranges(lo[u], hi[u], u)
            if known[u] is not None:  # f_u's certified range plus g_u's
                _add_known_range(lo[u], hi[u], known[u])
        return lo, hi

    return bound_cells
