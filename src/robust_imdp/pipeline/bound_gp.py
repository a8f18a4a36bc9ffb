"""The GP route's bound stage (error_bound 'chowdhury'): one GP posterior per mode and output
(``bounds.gp.learn``), certified image boxes of ``f_u + mu`` over the grid's cells (``bounds.gp_cells``)
and the probabilistic error models the abstraction folds in (Chowdhury & Gopalan 2017).

The :class:`robust_imdp.bounds.methods.CellBounder` of the route: :func:`learn_and_bound` (no bounder
of new cells: the route refines nothing and has no advice pilot). What every route shares is
``pipeline/bound_stage.py``'s.
"""

from __future__ import annotations

import numpy as np

from robust_imdp.pipeline.bound_stage import _diagnostics, _prepare, _residual_data
from robust_imdp.pipeline.problem import Problem
from robust_imdp.pipeline.runtime import _Log, _Run


def _statement(problem: Problem):
    """What the boxes and error models guarantee, and at which confidence (None: Thm 1 as printed)."""
    if problem.guarantee == "confidence":
        return (f"with probability >= {problem.confidence:g} over the data (Chowdhury-Gopalan error bound, "
                "union bound over the GPs), if every unknown component has RKHS norm <= rkhs_bound"), \
            float(problem.confidence)
    return ("Thm 1 as printed: mixes a probability over the data into the transition bounds; not a "
            "guarantee for one fixed system (docs/soundness_audit.md, F2)"), None


def learn_and_bound(problem: Problem, partition, log: _Log, run: "_Run | None" = None, cache_dir=None):
    """The GP route's bound stage over the grid's cells: ``(cell_bounds, error models, diagnostics)``.

    ``run`` is not used (the route bounds in this process); the assumption check and the diagnostics
    are ``bound_stage``'s.
    """
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.bounds.gp_cells import bound_image
    from robust_imdp.bounds.gp import learn

    _, _, checks, check_noise = _prepare(problem, partition, log, cache_dir)
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
    statement, conf = _statement(problem)
    diag = _diagnostics(problem, partition, boxes, _residual_data(problem), checks, check_noise,
                        conf if conf is not None else float("nan"), statement)
    if conf is None:
        diag["confidence"] = None
    return cell_bounds, learned.error_bounds, diag
