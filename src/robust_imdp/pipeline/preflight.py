"""Before the long stages: resource estimates, the memory pre-flight, region-overlap and atom checks.
"""

from __future__ import annotations

import warnings

import numpy as np

from robust_imdp.errors import UnknownAtomError

from robust_imdp.pipeline.problem import Problem
from robust_imdp.pipeline.runtime import _Log, _Run


def _region_objects(problem: Problem):
    from robust_imdp.models.geometry import Box, Region

    return [Region(name, [Box(lo, up) for lo, up in boxes]) for name, boxes in problem.regions.items()]


def _warn_overlaps(problem: Problem, dfa) -> None:
    """Warn when two regions the formula names overlap: the cells there carry both labels.

    Regions the formula does not name are left alone (the paper's case study defines ``d2``
    equal to ``des`` on purpose). Boxes that share only a face do not overlap.
    """
    import warnings

    from robust_imdp.errors import RegionOverlapWarning
    from robust_imdp.models.geometry import Box, region_overlaps, wrap_region_boxes

    # seam-crossing boxes of periodic dimensions are compared as the partition labels them: cut into X
    used = wrap_region_boxes([r for r in _region_objects(problem) if r.name in dfa.atoms],
                             Box(problem.space_lower, problem.space_upper), problem.periodic, problem.dim_names)
    found = region_overlaps(used)
    pairs = list(dict.fromkeys((a, b) for a, b, _ in found))
    for a, b in pairs:
        boxes = [box for x, y, box in found if (x, y) == (a, b)]
        where = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in zip(boxes[0].lower, boxes[0].upper))
        more = f" (and {len(boxes) - 1} more boxes)" if len(boxes) > 1 else ""
        warnings.warn(
            f"regions {a!r} and {b!r} overlap in the box {where}{more}: cells there are labelled with both, "
            f"and the formula {problem.formula!r} reads both labels there; check the regions' boxes "
            "([[regions.NAME]] lower / upper)", RegionOverlapWarning, stacklevel=3)


def _check_atoms(dfa, problem: Problem) -> None:
    unknown = sorted(set(dfa.atoms) - set(problem.regions))
    if unknown:
        raise UnknownAtomError(
            f"formula {problem.formula!r} names regions {unknown} that are not defined; "
            f"known regions: {sorted(problem.regions)}"
        )


# --------------------------------------------------------------------------- entry points
def estimate_resources(problem: Problem, n_dfa_states: int = 4, form: str | None = None) -> dict:
    """Pre-flight estimate of a run's size and peak memory, before any heavy work.

    The cell count is that of the plain grid (regions that do not fit it add a few cells).
    Memory of the joint form: IMDP rows of ``~3^n`` listed successors (Thm 1) or
    :func:`exact_successors` (24 bytes each: column, lower, upper) held about three times during
    assembly, the image boxes and their error radii, the partition, and the product solver's value
    arrays. Calibrated on the case studies and the 3-D study (``benchmarks/scale.py``) to
    over-estimate. The factored form (``form="factored"``): :func:`factored_bytes`.

    Parameters
    ----------
    problem : Problem
    n_dfa_states : int
    form : {"joint", "factored"}, optional
        The abstraction's form; default: the problem's (``Problem.form_choice``).

    Returns
    -------
    dict with ``n_cells``, ``n_modes``, ``n_outputs``, ``form``, ``bytes`` (estimated peak), ``joint_bytes``
    (the joint form's estimate, for comparison) and ``available`` (bytes the machine has free now, or None if
    unknown); the factored form adds ``listed_per_axis`` (the estimated ``k_i``).
    """
    n = int(np.size(problem.space_lower))
    N = problem.n_grid_cells
    M = len(problem.mode_names)
    form = problem.form_choice()[0] if form is None and hasattr(problem, "form_choice") else (form or "joint")
    succ = 3 ** n + 1 if getattr(problem, "transitions", "thm1") == "thm1" else exact_successors(problem) + 1
    imdp = N * M * (succ * 24 + 48)
    boxes = N * M * n * 8 * 8
    part = N * n * 8 * 6
    solver = N * M * max(int(n_dfa_states), 1) * 8 * 6
    joint = int(3 * imdp + boxes + part + solver + 2e8)
    out = {"n_cells": N, "n_modes": M, "n_outputs": n, "form": form, "bytes": joint, "joint_bytes": joint,
           "available": _available_memory()}
    if form == "factored":
        k = factored_lengths(problem)
        # the synthesis of a factored model takes a nominal model only without a horizon, with several modes and
        # under the reach reading (synthesis.ties.takes_nominal; "auto" counted as reach: the larger estimate)
        takes = problem.horizon is None and M > 1 and getattr(problem, "semantics", "auto") != "safety"
        out.update(bytes=factored_bytes(N, M, k, n_dfa_states, nominal=_nominal_bytes(problem, k) if takes else 0),
                   listed_per_axis=list(k))
    return out


#: ``pipeline.nominal_stage.MAX_NOMINAL_ENTRIES`` (that module is listed after this one in docs/ARCHITECTURE.md;
#: tests/test_takes_nominal.py checks that the two agree).
NOMINAL_ENTRIES = 30_000_000


def _nominal_bytes(problem: Problem, k) -> int:
    """Bytes of the nominal model (``pipeline.nominal_stage.nominal_model``) held through a factored synthesis:
    the joint mixture of ``s^d`` points per cell where its entries fit ``MAX_NOMINAL_ENTRIES`` (24 bytes each, held
    twice while it is assembled; ``abstraction.nominal.row_entries`` on the grid's cell widths; the cap
    :data:`NOMINAL_ENTRIES`), else the factored
    model of the centres (the robust model's size)."""
    from robust_imdp.abstraction.marginals import AXIS_TOL
    from robust_imdp.abstraction.nominal import points_per_axis

    N, M = problem.n_grid_cells, len(problem.mode_names)
    w = np.asarray(problem.cell_size, float).reshape(-1) * np.ones(np.size(problem.space_lower))
    R = np.asarray(problem.noise.listing_radius(AXIS_TOL), float)
    s = points_per_axis(w.size)
    while True:
        entries = M * N * (int(np.prod(np.floor(((1.0 - 1.0 / s) * w + 2.0 * R) / w) + 2.0)) + 1)
        if entries <= NOMINAL_ENTRIES or s == 1:
            break
        s -= 1
    if entries <= NOMINAL_ENTRIES:
        return int(2 * 24 * entries)
    return int(N * M * np.sum(16 * np.asarray(k, dtype=np.int64) + 32))


#: Bytes of the process before the run's arrays (Python, numpy, scipy, numba and the package imported), and the
#: factored form's multipliers, fitted to the peak RSS of benchmarks/factored_pipeline.py's runs
#: (benchmarks/results/factored_pipeline.md, "Pre-flight": small runs peak at 191-195 MB; linear 5-D / 6-D at 8 per
#: axis 247 / 802 MB, the model held about twice while it is assembled).
FACTORED_BASE = 1.95e8
FACTORED_MODEL_COPIES = 2.0
FACTORED_TREE_BYTES = 8 * 9


def factored_lengths(problem: Problem, tol: float = 1e-9) -> tuple:
    """The listed intervals per axis of the factored form (``abstraction.marginals``), estimated before the bound
    stage: an image of one cell's width (the image is not known yet) widened by the listing radius of ``tol``
    (``marginals.AXIS_TOL``) on each side, placed at its worst against the grid, capped by the axis's intervals."""
    h = np.asarray(problem.cell_size, float).reshape(-1)
    lo, up = np.asarray(problem.space_lower, float), np.asarray(problem.space_upper, float)
    R = np.asarray(problem.noise.listing_radius(tol), float)
    n_j = np.rint((up - lo) / h).astype(np.int64)
    return tuple(int(min(n, np.ceil((hj + 2 * r) / hj) + 1)) for n, hj, r in zip(n_j, h, R))


def factored_bytes(n_cells: int, n_modes: int, k, n_dfa_states: int = 4, nominal: int = 0) -> int:
    """Estimated peak bytes of a factored run (docs/factored.md, "In the pipeline").

    :data:`FACTORED_BASE` for the process, the partition's corners and labels and the image boxes, and the larger
    of two stages' peaks: the assembly (the model's arrays -- per (cell, mode) and axis a start, ``k_i`` lower and
    ``k_i`` upper bounds and three scalars, ``16 k_i + 32`` bytes -- held :data:`FACTORED_MODEL_COPIES` times:
    the chunks and the concatenation) and the synthesis (the model, the solver's traversal tree: about
    ``n_cells x d`` nodes of :data:`FACTORED_TREE_BYTES` bytes and ``d`` box ends per mode, the value iteration's
    vectors per DFA state and mode, and the ``nominal`` model's bytes where the synthesis takes one)."""
    k = np.asarray(k, dtype=np.int64)
    d = int(k.size)
    R = int(n_cells) * int(n_modes)
    model = R * int(np.sum(16 * k + 32))
    tree = R * d * (FACTORED_TREE_BYTES + 8 * d)
    part = int(n_cells) * d * 8 * 4
    boxes = R * d * 8 * 4
    values = int(n_cells) * max(int(n_dfa_states), 1) * 8 * 8 + R * 8 * 4
    stage = max(FACTORED_MODEL_COPIES * model, model + tree + values + int(nominal))
    return int(FACTORED_BASE + part + boxes + stage)


def load_text(cores_used: int) -> str:
    """What the bound stage's time estimate assumes about the machine, for its pre-flight line.

    The estimate is a short pilot's speed, measured under the load of the moment, times the work: it
    holds while the load stays as it is. On a shared machine the load changes during a long stage (a
    newcomer's runs found the estimate 40-70 % low as others' jobs started; at a steady load average of
    9-11 on 2 cores it was 1.6 and 1.05 times the stage's time on examples/newcomer's robot2d_32 and
    unicycle3d_16), so the line names the load it was measured at, and the progress lines re-estimate from
    the rate measured since.

    Parameters
    ----------
    cores_used : int
        The cores the stage runs on (threads of this process, or local workers).
    """
    import os

    cores = os.cpu_count() or 1
    try:
        load = float(os.getloadavg()[0])
    except (OSError, AttributeError):  # pragma: no cover - no load average (Windows)
        return "at the speed measured now (the time changes with the machine's load)"
    # more runnable threads than cores (the average counts this process too): others' work shares the cores
    busy = " (busy: others' work shares the cores)" if load > cores + 0.5 else ""
    return (f"at the speed measured now, load average {load:.1f} on {cores} cores{busy}: it holds while the load "
            "stays; the progress lines re-estimate from the measured rate")


def exact_successors(problem: Problem, floor_tol: float = 1e-6) -> int:
    """Listed successors per row of the exact transitions (``transitions = "exact"``), estimated on one cell.

    A cell of ``cell_size`` whose image is a cell of the same size (the image is not known before the bound
    stage), on grid intervals of ``cell_size`` around it: the per-axis upper bounds (``abstraction.marginals``)
    and the joint entries whose product exceeds the rows' least floor ``floor_tol / 20`` (a product of factors
    <= 1 stays below the floor once a partial product is: counted axis by axis), capped by the grid.
    """
    from robust_imdp.abstraction.marginals import interval_bounds

    h = np.asarray(problem.cell_size, float).reshape(-1)
    lo, up = np.asarray(problem.space_lower, float), np.asarray(problem.space_upper, float)
    R = problem.noise.listing_radius(floor_tol / 20)
    level = floor_tol / 20
    partial = np.ones(1)
    for j in range(h.size):
        n_j = int(round((up[j] - lo[j]) / h[j]))
        K = int(min(np.ceil(R[j] / h[j]) + 2, n_j))
        t = np.arange(-K, K + 1)
        _, hi = interval_bounds(problem.noise, j, 0.0, h[j], t * h[j], (t + 1) * h[j])
        hi = hi[np.argsort(-hi)][:n_j]  # at most the grid's intervals
        prod = (partial[:, None] * hi[None, :]).ravel()
        partial = prod[prod > level]
        if partial.size == 0:
            return 1
    return int(partial.size)


def _available_memory() -> int | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover - non-Linux
        pass
    return None


def _preflight(problem: Problem, dfa, log: _Log, run: _Run) -> None:
    from robust_imdp.errors import ResourceError

    est = estimate_resources(problem, dfa.n_states)
    gb = est["bytes"] / 1e9
    avail = est["available"]
    factored = est["form"] == "factored"
    log.info(f"pre-flight: {est['n_cells']:,} cells x {est['n_modes']} modes x {est['n_outputs']} outputs, "
             f"peak memory about {gb:.2f} GB" + (f" of {avail / 1e9:.1f} GB available" if avail else "")
             + (f" (factored form; the joint IMDP: about {est['joint_bytes'] / 1e9:.2f} GB)" if factored else ""))
    if run.check_resources and avail is not None and est["bytes"] > 0.9 * avail:
        coarser = np.round(np.asarray(problem.cell_size, float) * 2, 6).tolist()
        raise ResourceError(
            f"pre-flight: {est['n_cells']:,} cells x {est['n_modes']} modes need about {gb:.1f} GB, more than the "
            f"{avail / 1e9:.1f} GB available: use a coarser [space].cell_size (e.g. {coarser}, which divides the "
            f"cells by {2 ** est['n_outputs']}); --scheduler moves the bound stage to a Dask cluster but not the "
            "abstraction; --yes runs anyway" + _factored_hint(problem, est))


def _factored_hint(problem: Problem, est: dict) -> str:
    """The pre-flight's pointer to the factored form where a joint run would fit it and does not use it."""
    if est["form"] == "factored" or not hasattr(problem, "factored_reason"):
        return ""
    exact = problem.replace(transitions="exact", form="auto")
    if exact.factored_reason() is not None:
        return ""
    need = factored_bytes(est["n_cells"], est["n_modes"], factored_lengths(exact))
    return (f"; [abstraction].transitions = 'exact' stores the factored form (docs/factored.md), about "
            f"{need / 1e9:.2f} GB")
