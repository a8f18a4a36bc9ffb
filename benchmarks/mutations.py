"""Mutation check of the test suite: does every soundness check catch a slightly unsound bound? (issue 14)

Each entry of ``MUTATIONS`` is a one-line source edit that makes one bound slightly unsound
(typically a shrink by 1e-3 = 0.1 %, or outward rounding switched off). For each, the working
tree is copied to a scratch directory (``git ls-files --cached --others --exclude-standard``:
tracked and new, not ignored, files; with ``--source head`` the last commit instead), the edit
is applied there (the original text must occur EXACTLY ONCE in the file, else the script stops:
keep the list current when the code moves),
and the test suite runs on the copy::

    PYTHONPATH=<scratch>/src python -m pytest -x -q -p no:cacheprovider     (cwd = <scratch>)

(first on the test files most likely to catch the mutation — the previous run's first failing
file, those of ``_LIKELY`` for the mutated file, an entry's own ``tests`` — and, when those pass,
on the whole suite: a mutation counts as not caught only when the whole suite passes.)

after checking, in the same environment, that ``import robust_imdp`` resolves to the scratch
copy. A mutation is *caught* when pytest fails (exit 1); the first failing test is recorded.
A baseline run of the unmutated copy (whole suite, no ``-x``) comes first: tests that already
fail there (someone's work in progress) are deselected from the mutation runs and listed in the
report; ``--strict-baseline`` stops instead.

Not run in CI (one full suite per mutation). Writes the table to ``docs/mutations.md`` with the
date and the command, and the raw results to ``benchmarks/results/mutations.json``.

Usage::

    python benchmarks/mutations.py [--jobs N] [--only NAME ...] [--list] [--no-write]

Adding an entry (e.g. for a new bound in rkhs.py): append a dict with ``name`` (unique, short),
``file`` (repository-relative path), ``original`` (exact text, usually one whole line with its
indentation; it must occur exactly once), ``replacement`` and ``description`` (what becomes
unsound and by how much). Prefer edits that keep the model internally consistent (e.g. cap a
raised lower bound at the upper bound), so that a catch comes from a soundness check and not
from an unrelated validation error.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "mutations.md"
RAW = ROOT / "benchmarks" / "results" / "mutations.json"

_ABS = "src/robust_imdp/abstraction/rows.py"
_ABS_CELLS = "src/robust_imdp/abstraction/cell_bounds.py"
_BOUNDS = "src/robust_imdp/bounds/gp_cells.py"
_GP_ERROR = "src/robust_imdp/bounds/gp_error.py"
_RKHS = "src/robust_imdp/bounds/rkhs.py"
_RKHS_MODEL = "src/robust_imdp/bounds/rkhs_model.py"
_RKHS_WEIGHTS = "src/robust_imdp/bounds/rkhs_weights.py"
_RKHS_CHECK = "src/robust_imdp/bounds/rkhs_check.py"
_RKHS_LOCAL = "src/robust_imdp/bounds/rkhs_local.py"
_KERNELS = "src/robust_imdp/_kernels.py"
_BOUND_STAGE = "src/robust_imdp/pipeline/bound_stage.py"
_SOLVE = "src/robust_imdp/solvers/engine.py"
_SYN = "src/robust_imdp/synthesis/core.py"
_KNOWN = "src/robust_imdp/models/known.py"
_INTERVALS = "src/robust_imdp/models/intervals.py"
_EXPRESSIONS = "src/robust_imdp/models/expressions.py"
_PIPE = "src/robust_imdp/pipeline/run.py"
_ASSUME = "src/robust_imdp/bounds/assumptions.py"
_PER = "src/robust_imdp/abstraction/periodic.py"
_MARG = "src/robust_imdp/abstraction/marginals.py"
_EXR = "src/robust_imdp/abstraction/exact_rows.py"
_MT = ["tests/test_marginals.py"]
_FAC = "src/robust_imdp/solvers/factored.py"
_FAC_K = "src/robust_imdp/solvers/factored_kernels.py"
_FAC_O = "src/robust_imdp/solvers/factored_order.py"
_FAC_M = "src/robust_imdp/models/factored.py"

_VI_RETURN = ("    return ReachabilityResult(lower=lo, upper=up, strategy=strat, iterations=it, "
              "precision=gap, converged=converged)")
_VI_K_RETURN = ("    return ReachabilityResult(lower=lo, upper=up, strategy=strat, iterations=k, "
                "precision=prec, converged=True)")
_SYN_CHECK = "    bad = np.flatnonzero(~(p_low <= p_up))"
_FLOOR = "        floors[u] = _complement_up(_combine_down(md.floor_p, md.floor_pv, combine))"
_LOCAL_OPT = ("                            cert = _certify(bidx, bw, nb, ys, b, eb, Kp, K_err, s0, "
              "a1[o], 0.0, G, sgn)")
_LOCAL_RIDGE_UP = ("                        val[q, jv, o, 0] = _certified_value(idx, w, k, ys, l1, l2, rr, a1[o], "
                   "a2[o], G, 1.0)[0]")
_LOCAL_RIDGE_LO = ("                        val[q, jv, o, 1] = _certified_value(idx, w, k, ys, l1, l2, rr, a1[o], "
                   "a2[o], G, -1.0)[0]")
_LOCAL_COMBINE = "    lo_all, up_all, taylor = _combine_vertices(lin_v, lin_err, su, sl, t_max, G_eff, tau)"

#: The mutations, in the order they are run. Keep each ``original`` unique in its file.
MUTATIONS = [
    # ------------------------------------------------------------------ abstraction (Thm 1)
    dict(name="outward-off", file="src/robust_imdp/_fp.py",
         original="    return np.where(err > 0, moved, x)",
         replacement="    return x",
         description="_fp.outward (the abstraction's probabilities and complements) returns x (outward rounding off)",
         tests=["tests/test_rounding.py", "tests/test_abstraction.py"]),
    dict(name="periodic-copy-0-dropped", file=_PER,
         original="_COPY_OFFSETS = (-1, 0, 1, 2)", replacement="_COPY_OFFSETS = (-1, 1, 2)",
         description="periodic dimensions: the gap/margin on the circle skips the nearest copy of the target",
         tests=["tests/test_periodic.py"]),
    dict(name="periodic-rounding-off", file=_PER,
         original="    return down((x + y) + z, gamma(2) * (np.abs(x) + np.abs(y) + np.abs(z)))",
         replacement="    return (x + y) + z",
         description="periodic dimensions: the gap/margin terms on the circle are not rounded down",
         tests=["tests/test_periodic.py"]),
    dict(name="periodic-shift-rounding-off", file=_PER,
         original="    return np.where(k == 0, 0.0, down(s, err)), np.where(k == 0, 0.0, up(s, err))",
         replacement="    return s, s",
         description="periodic dimensions: the shift k * period is not enclosed (the terms' rounding still is)",
         tests=["tests/test_periodic.py"]),
    dict(name="periodic-outside-through-seam", file=_ABS,
         original="            PX[:, j], PVX[:, j] = 1.0, 1.0\n            continue",
         replacement="            PX[:, j], PVX[:, j] = 1.0, 1.0",
         description="periodic dimensions: the outside state gets mass through a periodic axis (no gain in soundness: "
                     "tightness check)",
         tests=["tests/test_periodic.py"]),
    dict(name="floor-x0.99", file=_ABS, original=_FLOOR,
         replacement="        floors[u] = _complement_up(_combine_down(md.floor_p, md.floor_pv, combine)) * 0.99",
         description="every row's floor (upper bound of unlisted targets) x 0.99"),
    dict(name="floor-x0.5", file=_ABS, original=_FLOOR,
         replacement="        floors[u] = _complement_up(_combine_down(md.floor_p, md.floor_pv, combine)) * 0.5",
         description="every row's floor x 0.5"),
    dict(name="floor-shrink-1e-3", file=_ABS, original=_FLOOR,
         replacement="        floors[u] = _complement_up(_combine_down(md.floor_p, md.floor_pv, combine)) * (1 - 1e-3)",
         description="every row's floor x (1 - 1e-3)"),
    dict(name="listed-upper-shrink-1e-3", file=_ABS,
         original="    out.upper[dest] = _complement_up(G)",
         replacement="    out.upper[dest] = np.maximum(_complement_up(G) * (1 - 1e-3), low)",
         description="upper bounds of listed cell targets x (1 - 1e-3) (kept >= lower)"),
    dict(name="listed-lower-shrink-1e-3", file=_ABS,
         original="    out.lower[dest] = low",
         replacement="    out.lower[dest] = np.minimum(low * (1 + 1e-3), out.upper[dest])",
         description="lower bounds of listed cell targets x (1 + 1e-3) (kept <= upper)"),
    dict(name="outside-upper-shrink-1e-3", file=_ABS,
         original="    out.upper[dout] = up_out",
         replacement="    out.upper[dout] = np.maximum(up_out * (1 - 1e-3), low_out)",
         description="upper bound of the outside-X state x (1 - 1e-3) (kept >= lower)"),
    dict(name="outside-lower-shrink-1e-3", file=_ABS,
         original="    out.lower[dout] = low_out",
         replacement="    out.lower[dout] = np.minimum(low_out * (1 + 1e-3), out.upper[dout])",
         description="lower bound of the outside-X state x (1 + 1e-3) (kept <= upper)"),
    dict(name="confidence-eps-shrink-1e-3", file=_ABS_CELLS,
         original="            eps[u, :, i] = models[u][i].eps_for_prob(p_each, cell_bounds.std_upper[u, :, i])",
         replacement="            eps[u, :, i] = models[u][i].eps_for_prob(p_each, cell_bounds.std_upper[u, :, i]) * (1 - 1e-3)",
         description="confidence mode: GP error radius folded into the image boxes x (1 - 1e-3)"),
    dict(name="confidence-no-union-bound", file=_ABS_CELLS,
         original="    delta_each = down(down(1.0 - confidence) / (M * d))",
         replacement="    delta_each = down(1.0 - confidence)",
         description="confidence mode: each GP gets all of 1 - confidence (union bound over GPs dropped)"),
    # ------------------------------------------------------------------ GP bounds (gp_cells.py, gp_error.py)
    dict(name="gp-mean-lower-shrink-1e-3", file=_BOUNDS,
         original="        mean_lower=mean_lower,",
         replacement="        mean_lower=mean_lower + 1e-3 * (mean_upper - mean_lower),",
         description="certified lower bound of the posterior mean (image) over a box raised by 1e-3 of the box width"),
    dict(name="gp-mean-upper-shrink-1e-3", file=_BOUNDS,
         original="        mean_upper=mean_upper,",
         replacement="        mean_upper=mean_upper - 1e-3 * (mean_upper - mean_lower),",
         description="certified upper bound of the posterior mean (image) over a box lowered by 1e-3 of the box width"),
    dict(name="gp-std-upper-shrink-1e-3", file=_BOUNDS,
         original="        std_upper=std_upper,",
         replacement="        std_upper=std_upper * (1 - 1e-3),",
         description="certified upper bound of the posterior std over a box x (1 - 1e-3)"),
    dict(name="beta-shrink-1e-3", file=_GP_ERROR,
         original="        return _fp.up(beta * (1 + 16 * _EPS))",
         replacement="        return _fp.up(beta * (1 - 1e-3))",
         description="Chowdhury-Gopalan beta(delta) x (1 - 1e-3)"),
    # ------------------------------------------------------------------ RKHS cell bounds (rkhs.py, issue 9)
    dict(name="rkhs-taylor-shrink-1e-3", file=_RKHS_MODEL,
         original="    return _up(np.sqrt(R))",
         replacement="    return _up(np.sqrt(R)) * (1 - 1e-3)",
         description="feature-map Taylor remainder sqrt(R(t)) of (eq. T) x (1 - 1e-3)"),
    dict(name="rkhs-radius-shrink-1e-3", file=_RKHS_MODEL,
         original="    radius = (a1 * l1_up + a2 * l2_up + G * r_up) * (1.0 + 8.0 * u)",
         replacement="    radius = (a1 * l1_up + a2 * l2_up + G * r_up) * (1.0 - 1e-3)",
         description="certified radius of (eq. W) (noise and RKHS terms of the weights) x (1 - 1e-3)"),
    dict(name="rkhs-cell-range-shrink-1e-3", file=_RKHS,
         original=("    return CellRange(lower=lower_c, upper=upper_c, eps=eps, support=support, vertex_lower=vl, "
                   "vertex_upper=vu,"),
         replacement=("    return CellRange(lower=lower_c + 1e-3 * (upper_c - lower_c), upper=upper_c - 1e-3 * "
                      "(upper_c - lower_c), eps=eps, support=support, vertex_lower=vl, vertex_upper=vu,"),
         description="certified cell range of f_u + g (eq. C): each side moved inward by 1e-3 of its width"),
    dict(name="rkhs-tau-not-in-noise", file=_RKHS,
         original="    dbar = float(_up(float(noise_bound) + tau))  # |h(x_i) - y_i| <= dbar + tau",
         replacement="    dbar = float(_up(float(noise_bound)))",
         description="misspecification tau left out of the data-noise bound dbar' = dbar + tau"),
    dict(name="rkhs-tau-not-added", file=_RKHS_MODEL,
         original="        tay = _up(_up(G * rho) + tau, 4 * _U * (G * rho + tau))",
         replacement="        tay = _up(G * rho)",
         description="misspecification tau not added to the cell range (eq. C)"),
    dict(name="rkhs-hoeffding-shrink-1e-3", file=_RKHS,
         original="    return float(_up(math.sqrt(2.0 * math.log(2.0 * int(n_events) / float(delta))) * (1 + 1e-12)))",
         replacement="    return float(math.sqrt(2.0 * math.log(2.0 * int(n_events) / float(delta))) * (1 - 1e-3))",
         description="iid route: union-bound factor sqrt(2 ln(2N/delta)) x (1 - 1e-3)"),
    dict(name="rkhs-quadform-error-off", file=_RKHS_MODEL,
         original="    err = gam * mag + 2.0 * bw_err + K_err * wKw_abs",
         replacement="    err = 0.0 * (gam * mag + 2.0 * bw_err + K_err * wKw_abs)",
         description="certificate: no float-error bound on ||phi - Phi* w||^2 before the square root"),
    dict(name="rkhs-kernel-error-off", file=_KERNELS,
         original="    return float((math.expm1(x) + 2 * U) * (1 + 1e-6) + 4 * U)",
         replacement="    return 0.0",
         description="relative error bound of computed kernel values set to 0"),
    dict(name="rkhs-lengthscale-rounded-down", file=_KERNELS,
         original="    return up((1.0 / (ls * ls)) * (1.0 + 4 * U))",
         replacement="    return np.nextafter(1.0 / (ls * ls), -np.inf)",
         description="inverse squared lengthscales rounded down (a kernel with a longer lengthscale than assumed)"),
    dict(name="rkhs-cell-radius-inward", file=_RKHS_MODEL,
         original="    r = np.maximum(_up(upper - c), _up(c - lower))",
         replacement="    r = np.maximum(upper - c, c - lower) * (1 - 1e-3)",
         description="cell half-widths 0.1 % too small (the certified box misses the cell's edge)"),
    dict(name="rkhs-scaled-remainder-shrink-1e-3", file=_RKHS_MODEL,
         original="    out = _up(np.sqrt(np.maximum(np.maximum(f_t, f_0), 0.0)))",
         replacement="    out = _up(np.sqrt(np.maximum(np.maximum(f_t, f_0), 0.0))) * (1 - 1e-3)",
         description="scaled feature-map remainder rho(a) x (1 - 1e-3)"),
    dict(name="rkhs-min-norm-overclaim-1e-3", file=_RKHS_CHECK,
         original="            joint = float(_down(joint / infl))",
         replacement="            joint = float(joint / infl) * (1 + 1e-3)",
         description="data-implied minimum RKHS norm over-claimed by 0.1 % (refuses assumptions the data allow)"),
    # ------------------------------------------------------------------ RKHS local weights (rkhs._local_cells / _local_chunk)
    dict(name="rkhs-kernel-error-nb-off", file=_KERNELS,
         original="    return (math.expm1(x) + 2 * U) * (1 + 1e-6) + 4 * U",
         replacement="    return 0.0",
         description="numba twin of the kernel-value error bound (vertex functionals, local pools) set to 0"),
    dict(name="rkhs-local-optimal-noise-x0.99", file=_RKHS_LOCAL, original=_LOCAL_OPT,
         replacement=_LOCAL_OPT.replace("a1[o], 0.0, G, sgn)", "a1[o] * 0.99, 0.0, G, sgn)"),
         description="local optimal weights: noise term dbar' ||w||_1 of the certificate (eq. W) x 0.99"),
    dict(name="rkhs-local-optimal-noise-shrink-1e-3", file=_RKHS_LOCAL, original=_LOCAL_OPT,
         replacement=_LOCAL_OPT.replace("a1[o], 0.0, G, sgn)", "a1[o] * (1 - 1e-3), 0.0, G, sgn)"),
         description="local optimal weights: noise term of the certificate (eq. W) x (1 - 1e-3)"),
    dict(name="rkhs-local-optimal-rkhs-shrink-1e-3", file=_RKHS_LOCAL, original=_LOCAL_OPT,
         replacement=_LOCAL_OPT.replace("a1[o], 0.0, G, sgn)", "a1[o], 0.0, G * (1 - 1e-3), sgn)"),
         description="local optimal weights: RKHS term B ||phi_v - Phi* w|| of the certificate (eq. W) x (1 - 1e-3)"),
    dict(name="rkhs-local-ridge-noise-shrink-1e-3", file=_RKHS_LOCAL, original=_LOCAL_RIDGE_UP,
         replacement=_LOCAL_RIDGE_UP.replace("a1[o], a2[o], G, 1.0)", "a1[o] * (1 - 1e-3), a2[o], G, 1.0)"),
         description="local ridge weights, upper side: noise term of the certificate (eq. W) x (1 - 1e-3)"),
    dict(name="rkhs-local-ridge-rkhs-shrink-1e-3", file=_RKHS_LOCAL, original=_LOCAL_RIDGE_UP,
         replacement=_LOCAL_RIDGE_UP.replace("a1[o], a2[o], G, 1.0)", "a1[o], a2[o], G * (1 - 1e-3), 1.0)"),
         description="local ridge weights, upper side: RKHS term of the certificate (eq. W) x (1 - 1e-3)"),
    dict(name="rkhs-local-ridge-lower-shrink-1e-3", file=_RKHS_LOCAL, original=_LOCAL_RIDGE_LO,
         replacement=_LOCAL_RIDGE_LO.replace("a1[o], a2[o], G, -1.0)", "a1[o] * (1 - 1e-3), a2[o], G * (1 - 1e-3), -1.0)"),
         description="local ridge weights, lower side: noise and RKHS terms of the certificate (eq. W) x (1 - 1e-3)"),
    dict(name="rkhs-local-vertex-norm-shrink-1e-3", file=_RKHS_MODEL,
         original="    return t * (1.0 + (d + 8) * 2.220446049250313e-16)  # upper bound of <phi_v, phi_v>",
         replacement="    return t * (1.0 - 1e-3)",
         description="compiled vertex functionals (optimal, local and sub-box paths): <phi_v, phi_v> x (1 - 1e-3)"),
    dict(name="rkhs-local-taylor-shrink-1e-3", file=_RKHS_LOCAL, original=_LOCAL_COMBINE,
         replacement=_LOCAL_COMBINE.replace("t_max, G_eff, tau)", "t_max, G_eff * (1 - 1e-3), tau)"),
         description="local weights: Taylor remainder term B sqrt(R(t_max)) of the cell range (eq. C) x (1 - 1e-3)"),
    dict(name="rkhs-local-tau-not-added", file=_RKHS_LOCAL, original=_LOCAL_COMBINE,
         replacement=_LOCAL_COMBINE.replace("t_max, G_eff, tau)", "t_max, G_eff, 0.0)"),
         description="local weights: misspecification tau not added to the cell range (eq. C)"),
    dict(name="rkhs-local-tau-not-in-noise", file=_RKHS_LOCAL,
         original="    dbar = _up(np.broadcast_to(np.asarray(noise_bound, float), (n,)) + tau)",
         replacement="    dbar = _up(np.broadcast_to(np.asarray(noise_bound, float), (n,)))",
         description="local weights: misspecification tau left out of the data-noise bound dbar' = dbar + tau"),
    # ------------------------------------------------------------------ certification sub-boxes (rkhs.sub_boxes)
    dict(name="rkhs-split-edge-inward", file=_RKHS_MODEL,
         original="        e[:, :, -1] = upper[cells]  # (nc, d, s + 1)",
         replacement="        e[:, :, -1] = upper[cells] - 1e-3 * w  # (nc, d, s + 1)",
         description="certification sub-boxes stop 0.1 % of the cell width short of the cell's upper edge"),
    dict(name="rkhs-split-global-remainder-shrink-1e-3", file=_RKHS,
         original="    lower_c, upper_c, taylor = _combine_vertices(lin_v, lin_err, su, sl, t_max, G_eff, tau)",
         replacement="    lower_c, upper_c, taylor = _combine_vertices(lin_v, lin_err, su, sl, t_max, G_eff * (1 - 1e-3), tau)",
         description="global weights: Taylor remainder of every (sub-)box in the cell range (eq. C) x (1 - 1e-3)"),
    dict(name="rkhs-split-global-hull-first-box", file=_RKHS,
         original="        upper_c = np.maximum.reduceat(upper_c, starts)",
         replacement="        upper_c = upper_c[starts]",
         description="global weights: a split cell's upper bound from its first sub-box only (not the hull)"),
    dict(name="rkhs-split-local-hull-first-box", file=_RKHS_LOCAL,
         original='           "upper": np.ascontiguousarray(np.maximum.reduceat(up_all, starts, axis=1).T),',
         replacement='           "upper": np.ascontiguousarray(up_all[:, starts].T),',
         description="local weights: a split cell's upper bound from its first sub-box only (not the hull)"),
    # ------------------------------------------------------------------ value iteration (solve.py)
    dict(name="vi-upper-x0.99", file=_SOLVE, original=_VI_RETURN,
         replacement=_VI_RETURN.replace("upper=up,", "upper=up * 0.99,"),
         description="unbounded value iteration: upper end of every bracket x 0.99 (robust upper Bellman values)"),
    dict(name="vi-upper-shrink-1e-3", file=_SOLVE, original=_VI_RETURN,
         replacement=_VI_RETURN.replace("upper=up,", "upper=up * (1 - 1e-3),"),
         description="unbounded value iteration: upper end of every bracket x (1 - 1e-3)"),
    dict(name="vi-lower-shrink-1e-3", file=_SOLVE, original=_VI_RETURN,
         replacement=_VI_RETURN.replace("lower=lo,", "lower=np.minimum(lo * (1 + 1e-3), 1.0),"),
         description="unbounded value iteration: lower end of every bracket x (1 + 1e-3) (capped at 1)"),
    dict(name="vi-kstep-upper-shrink-1e-3", file=_SOLVE, original=_VI_K_RETURN,
         replacement=_VI_K_RETURN.replace("upper=up,", "upper=up * (1 - 1e-3),"),
         description="k-step value iteration: upper end of every bracket x (1 - 1e-3)"),
    dict(name="vi-kstep-lower-shrink-1e-3", file=_SOLVE, original=_VI_K_RETURN,
         replacement=_VI_K_RETURN.replace("lower=lo,", "lower=np.minimum(lo * (1 + 1e-3), 1.0),"),
         description="k-step value iteration: lower end of every bracket x (1 + 1e-3) (capped at 1)"),
    dict(name="kstep-trivial-upper-shrink-1e-3", file=_SOLVE,
         original="    up = V0.copy() if upper else np.where(sw.active, 1.0, V0)",
         replacement="    up = V0.copy() if upper else np.where(sw.active, 1.0 - 1e-3, V0)",
         description="k-step solve of some ends (need): the upper end not iterated is 1 - 1e-3 instead of 1",
         tests=["tests/test_step_reuse.py"]),
    # ------------------------------------------------------------------ synthesis (what the pipeline reports)
    dict(name="p_low-x1.01", file=_SYN, original=_SYN_CHECK,
         replacement="    p_low = np.minimum(p_low * 1.01, p_up); " + _SYN_CHECK.strip(),
         description="p_low x 1.01 (capped at p_up) in synthesis, i.e. in every pipeline result"),
    dict(name="p_low-shrink-1e-3", file=_SYN, original=_SYN_CHECK,
         replacement="    p_low = np.minimum(p_low * (1 + 1e-3), p_up); " + _SYN_CHECK.strip(),
         description="p_low x (1 + 1e-3) (capped at p_up)"),
    dict(name="p_up-shrink-1e-3", file=_SYN, original=_SYN_CHECK,
         replacement="    p_up = np.maximum(p_up * (1 - 1e-3), p_low); " + _SYN_CHECK.strip(),
         description="p_up x (1 - 1e-3) (kept >= p_low)"),
    dict(name="p_up_star-shrink-1e-3", file=_SYN,
         original="    p_up_star = np.array(optimistic.initial_upper, dtype=np.float64)[:n_cells]",
         replacement="    p_up_star = np.maximum(np.array(optimistic.initial_upper, dtype=np.float64)[:n_cells] * (1 - 1e-3), p_low)",
         description="p_up_star x (1 - 1e-3) (kept >= p_low; p_up = min(., p_up_star) follows)"),
    # ------------------------------------------------------------------ controller and Monte-Carlo validation
    dict(name="controller-next-mode", file="src/robust_imdp/synthesis/controller.py",
         original="        mode = int(table[self.cell, self.dfa_state])",
         replacement="        mode = (int(table[self.cell, self.dfa_state]) + 1) % max(self.n_modes, 1)",
         description="the refined controller applies the next mode (cyclically) instead of the strategy's"),
    dict(name="validate-next-mode", file="src/robust_imdp/validate.py",
         original="        modes = table[q[run], s[run]]",
         replacement="        modes = (table[q[run], s[run]] + 1) % len(res.modes)",
         description="Monte-Carlo validation simulates the next mode (cyclically) instead of the strategy's"),
    # ------------------------------------------------------------------ known nonlinear dynamics (known.py, intervals.py, expressions.py)
    dict(name="known-outward-off", file=_INTERVALS,
         original='    """Round-to-nearest result moved one ulp towards -inf (a sound lower bound)."""\n    return np.nextafter(x, -np.inf)',
         replacement='    """Round-to-nearest result moved one ulp towards -inf (a sound lower bound)."""\n    return x',
         description="known: lower ends of interval operations not rounded down (round-to-nearest only)"),
    dict(name="known-margin-off", file=_INTERVALS,
         original="    s = MARGIN_ULP * np.spacing(np.abs(r))",
         replacement="    s = 0.0 * np.spacing(np.abs(r))",
         description="known: no margin on transcendental results (only one nextafter)"),
    dict(name="known-add-shrink-1e-3", file=_INTERVALS,
         original="    return _dn(al + bl), _up(ah + bh), None",
         replacement="    return _dn(al + bl) + 1e-3 * (ah + bh - al - bl), _up(ah + bh), None",
         description="known: interval sum's lower end raised by 1e-3 of its width"),
    dict(name="known-mul-shrink-1e-3", file=_INTERVALS,
         original="        _up(np.maximum(np.maximum(p[0], p[1]), np.maximum(p[2], p[3]))), None",
         replacement="        _up(np.maximum(np.maximum(p[0], p[1]), np.maximum(p[2], p[3]))) * (1 - 1e-3), None",
         description="known: interval product's upper end x (1 - 1e-3)"),
    dict(name="known-div-shrink-1e-3", file=_INTERVALS,
         original="    return _dn(np.minimum(np.minimum(q[0], q[1]), np.minimum(q[2], q[3]))), \\",
         replacement="    return _dn(np.minimum(np.minimum(q[0], q[1]), np.minimum(q[2], q[3]))) * (1 - 1e-3), \\",
         description="known: interval quotient's lower end x (1 - 1e-3)"),
    dict(name="known-monotone-shrink-1e-3", file=_INTERVALS,
         original="    lo, _ = _widen(fun(al))",
         replacement="    lo, _ = _widen(fun(al) + 1e-3 * (fun(ah) - fun(al)))",
         description="known: exp/log/tanh/tan lower end raised by 1e-3 of the range"),
    dict(name="known-trig-max-missed", file=_INTERVALS,
         original="    hi = np.where(full | _grid_hit(al, ah, phase_max, _TWO_PI), 1.0, hi)",
         replacement="    hi = np.where(full, 1.0, hi)",
         description="known: sin/cos maximum inside the interval ignored (endpoint values only)"),
    dict(name="known-even-power-min-missed", file=_INTERVALS,
         original="    lo = np.where(inside, 0.0, np.minimum(l1, l2))",
         replacement="    lo = np.minimum(l1, l2)",
         description="known: x^(2k) over an interval holding 0 has its minimum at an end (not 0)"),
    dict(name="known-square-min-missed", file=_INTERVALS,
         original="    lo = np.where(inside, 0.0, _dn(np.minimum(lo2, hi2)))",
         replacement="    lo = _dn(np.minimum(lo2, hi2))",
         description="known: x*x over an interval holding 0 has its minimum at an end (not 0)"),
    dict(name="known-pow-corner-missed", file=_INTERVALS,
         original="        for y in (bl, bh):",
         replacement="        for y in (bl,):",
         description="known: x^y (non-integer y) from two of the four corners only"),
    dict(name="known-constant-as-double", file=_EXPRESSIONS,
         original="    if got == exact:",
         replacement="    if True:",
         description="known: decimal constants taken as their nearest double (0.1 is not enclosed)"),
    dict(name="known-centred-shrink-1e-3", file=_KNOWN,
         original="                    pl, ph, _ = _i_mul(jl[:, col], jh[:, col], dl[:, j], dh[:, j])",
         replacement="                    pl, ph, _ = _i_mul(jl[:, col] * (1 - 1e-3), jh[:, col] * (1 - 1e-3), dl[:, j], dh[:, j])",
         description="known: centred form's Jacobian enclosure x (1 - 1e-3)"),
    dict(name="known-bisection-drops-half", file=_KNOWN,
         original="            U = np.concatenate([left_U, Us])",
         replacement="            U = np.concatenate([left_U, left_U])",
         description="known: bisection keeps the left half twice (the right half's values not enclosed)"),
    dict(name="known-enclosure-shrink-1e-3", file=_KNOWN,
         original="        return ImageBounds(lower=out_lo, upper=out_hi, leaves=leaves)",
         replacement="        return ImageBounds(lower=out_lo + 1e-3 * (out_hi - out_lo), upper=out_hi - 1e-3 * (out_hi - out_lo), leaves=leaves)",
         description="known: every certified image range moved inward by 1e-3 of its width on each side"),
    dict(name="known-tan-pole-missed", file=_INTERVALS,
         original="    bad = ((ah - al) >= 3.14) | _grid_hit(al, ah, 0.5 * math.pi, math.pi)",
         replacement="    bad = (ah - al) >= 3.14",
         description="known: a tan pole inside a short interval not detected"),
    dict(name="known-residual-bound-off", file=_KNOWN,
         original="        return _up(np.maximum(hi - v, v - lo))",
         replacement="        return 0.0 * _up(np.maximum(hi - v, v - lo))",
         description="known: residual rounding bound |fl(f(x)) - f(x)| set to 0"),
    # ------------------------------------------------------------------ known parts in the pipeline
    dict(name="pipeline-f-range-shrink-1e-3", file=_BOUND_STAGE,
         original="    lower[...], upper[...] = add_ranges(lower, upper, ranges.lower, ranges.upper)",
         replacement=("    lower[...], upper[...] = add_ranges(lower, upper, ranges.lower + 1e-3 * (ranges.upper - "
                      "ranges.lower), ranges.upper - 1e-3 * (ranges.upper - ranges.lower))"),
         description="pipeline: the known part's certified range shrunk inward by 0.1 % of its width per side "
                     "before it is added to g's range"),
    dict(name="affine-residual-rounding-off", file="src/robust_imdp/models/system.py",
         original="        e = g * (np.abs(x) @ np.abs(self.A).T + np.abs(self.b)) + np.spacing(np.abs(y))",
         replacement="        e = 0.0 * (g * (np.abs(x) @ np.abs(self.A).T + np.abs(self.b)) + np.spacing(np.abs(y)))",
         description="system: the affine known part's residual rounding bound set to 0 (an a-priori gamma bound: "
                     "a 0.1 % shrink of it cannot be seen against exact arithmetic, its absence can)"),
    dict(name="pipeline-rounding-allowance-off", file=_BOUND_STAGE,
         original="            out[u] = np.nextafter(out[u] + rb, np.inf)",
         replacement="            out[u] = out[u] + 0.0 * rb",
         description="pipeline: the residual rounding bound of a nonlinear known part left out of the data-noise "
                     "allowance of the certificate and the assumption check"),
    dict(name="assumptions-add-ranges-nearest", file=_ASSUME,
         original="    return (np.nextafter(np.asarray(lo_a, float) + np.asarray(lo_b, float), -np.inf),",
         replacement="    return (np.asarray(lo_a, float) + np.asarray(lo_b, float),",
         description="assumptions.add_ranges: the lower end of f range + g range rounded to nearest (no ulp "
                     "outward)"),
    # ------------------------------------------------------------------ sub-box pruning and shared weight sums (issue 20)
    dict(name="rkhs-local-split-optimal-noise-shrink-1e-3", file="src/robust_imdp/bounds/rkhs_local.py",
         original="cert = _certify_parts(bidx, bw, nb, yo, Bg[j, jv], EBg[j, jv], K_err, s0g[j, jv], a1[o], 0.0, G,",
         replacement="cert = _certify_parts(bidx, bw, nb, yo, Bg[j, jv], EBg[j, jv], K_err, s0g[j, jv], a1[o] * 0.999, 0.0, G,",
         description="local weights, split cells: the noise term of the optimal sub-box certificate shrunk by 0.1 %", tests=["tests/test_rkhs_local.py"]),
    dict(name="rkhs-local-split-optimal-rkhs-shrink-1e-3", file="src/robust_imdp/bounds/rkhs_local.py",
         original="cert = _certify_parts(bidx, bw, nb, yo, Bg[j, jv], EBg[j, jv], K_err, s0g[j, jv], a1[o], 0.0, G,",
         replacement="cert = _certify_parts(bidx, bw, nb, yo, Bg[j, jv], EBg[j, jv], K_err, s0g[j, jv], a1[o], 0.0, G * 0.999,",
         description="local weights, split cells: the RKHS term of the optimal sub-box certificate shrunk by 0.1 %", tests=["tests/test_rkhs_local.py"]),
    dict(name="rkhs-optimal-cells-noise-shrink-1e-3", file="src/robust_imdp/bounds/rkhs_weights.py",
         original="cert = _certify_parts(bidx, bw, nb, y, B[j, jv], EB[j, jv], K_err, s0[j, jv], dbar, 0.0, G,",
         replacement="cert = _certify_parts(bidx, bw, nb, y, B[j, jv], EB[j, jv], K_err, s0[j, jv], dbar * 0.999, 0.0, G,",
         description="global optimal weights: the noise term of the optimised vertex certificate shrunk by 0.1 %", tests=["tests/test_rkhs_local.py"]),
    dict(name="rkhs-weight-parts-wKw-shrink-1e-3", file="src/robust_imdp/bounds/rkhs_model.py",
         original="l1_up, l2_up, r_up = _norms_from_parts(idx, w, n, b, eb, K_err, s0, parts[0], parts[1], parts[2], parts[3])",
         replacement="l1_up, l2_up, r_up = _norms_from_parts(idx, w, n, b, eb, K_err, s0, parts[0], parts[1], parts[2] * 0.999, parts[3])",
         description="shared weight sums (eq. W): w.K w shrunk by 0.1 %", tests=["tests/test_rkhs_local.py"]),
    # ------------------------------------------------------------------ assumption margins: eq. C at beta B, same weights
    dict(name="margins-added-upper-shrink-1e-3", file=_RKHS_MODEL,
         original="    add_u = _up(dG * cu)", replacement="    add_u = _up(dG * cu * (1 - 1e-3))",
         description="assumption margins: the RKHS term added at beta B, (G_beta - G) ||phi_v - Phi* w||, upper side x (1 - 1e-3)",
         tests=["tests/test_margins_bounds.py"]),
    dict(name="margins-added-lower-shrink-1e-3", file=_RKHS_MODEL,
         original="    add_l = _up(dG * cl)", replacement="    add_l = _up(dG * cl * (1 - 1e-3))",
         description="assumption margins: the RKHS term added at beta B, lower side x (1 - 1e-3)",
         tests=["tests/test_margins_bounds.py"]),
    dict(name="margins-taylor-shrink-1e-3", file=_RKHS_MODEL,
         original="        lo, up, _ = _combine_vertices(lin_v, lin_err, su_s, sl_s, t_max, float(Gs), tau)",
         replacement="        lo, up, _ = _combine_vertices(lin_v, lin_err, su_s, sl_s, t_max, float(Gs) * (1 - 1e-3), tau)",
         description="assumption margins: the Taylor term at beta B x (1 - 1e-3)", tests=["tests/test_margins_bounds.py"]),
    dict(name="margins-norm-bound-shrink-1e-3", file=_RKHS_MODEL,
         original="    return float(_up(_up(float(rkhs_bound) * scale) * norm_inflation(int(d))))",
         replacement="    return float(_up(_up(float(rkhs_bound) * scale) * norm_inflation(int(d)))) * (1 - 1e-3)",
         description="assumption margins: the certificate's norm bound at beta B x (1 - 1e-3) (added and Taylor terms)",
         tests=["tests/test_margins_bounds.py"]),
    dict(name="margins-optimal-coefficient-shrink-1e-3", file=_RKHS_WEIGHTS,
         original="                        cr = cert[2]", replacement="                        cr = cert[2] * (1 - 1e-3)",
         description="assumption margins, global optimal weights: the coefficient of G of an optimised vertex "
                     "(||phi_v - Phi* w||) x (1 - 1e-3)", tests=["tests/test_margins_bounds.py"]),
    dict(name="margins-ridge-coefficient-shrink-1e-3", file=_RKHS_WEIGHTS,
         original="    return up, lo, coef\n", replacement="    return up, lo, coef * (1 - 1e-3)\n",
         description="assumption margins, global ridge weights: the coefficient of G x (1 - 1e-3)",
         tests=["tests/test_margins_bounds.py"]),
    dict(name="margins-local-optimal-coefficient-shrink-1e-3", file=_RKHS_LOCAL,
         original="                            coef[q, jv, o, sd] = cert[2]",
         replacement="                            coef[q, jv, o, sd] = cert[2] * (1 - 1e-3)",
         description="assumption margins, local optimal weights: the coefficient of G x (1 - 1e-3)",
         tests=["tests/test_margins_bounds.py"]),
    dict(name="margins-local-ridge-coefficient-shrink-1e-3", file=_RKHS_LOCAL,
         original="                        coef[q, jv, o, 0] = rr  # both sides: the same weights and functional",
         replacement="                        coef[q, jv, o, 0] = rr * (1 - 1e-3)",
         description="assumption margins, local ridge weights: the upper side's coefficient of G x (1 - 1e-3)",
         tests=["tests/test_margins_bounds.py"]),
    # ------------------------------------------------------------------ unicycle assumption, known-dynamics candidate path (issue 21)
    dict(name="unicycle-known-B-below-certified-norm", file="src/robust_imdp/casestudies/systems.py",
         original="    rkhs_bound=(0.074, 0.0, 0.0),",
         replacement="    rkhs_bound=(0.0736, 0.0, 0.0),",
         description="unicycle_3d_known: B below the certified norm 0.07367 of the drift's RKHS approximant (an unsound shipped assumption)", tests=["tests/test_unicycle_known.py"]),
    dict(name="known-dynamics-short-path-eps-shrink", file="src/robust_imdp/abstraction/probabilities.py",
         original="E = np.broadcast_to(self.eps[0, i, :], (t.size, 1))",
         replacement="E = np.broadcast_to(self.eps[0, i, :] - 1e-4, (t.size, 1))",
         description="abstraction: the known-dynamics single-candidate path's eps shrunk by 1e-4 (a larger noise share than Thm 1 allows)", tests=["tests/test_abstraction_known_candidates.py"]),
    # ------------------------------------------------------------------ improve (issue 22)
    dict(name="improve-intersection-shrink", file="src/robust_imdp/improve.py",
         original="        ilo[u, q], ihi[u, q] = np.maximum(lo, ilo[u, q]), np.minimum(hi, ihi[u, q])",
         replacement=("        w_ = np.minimum(hi, ihi[u, q]) - np.maximum(lo, ilo[u, q])\n"
                      "        ilo[u, q], ihi[u, q] = np.maximum(lo, ilo[u, q]) + 0.0005 * w_, "
                      "np.minimum(hi, ihi[u, q]) - 0.0005 * w_"),
         description="improve: the intersection of a kept box and its re-bounded box shrunk by 0.1 % of its width",
         tests=["tests/test_improve.py"]),
    dict(name="incremental-check-tolerance-loose", file="src/robust_imdp/improve.py",
         original="if np.all(witness_residuals(prev.witness, X[n0:], y[n0:]) <= dbar):",
         replacement="if np.all(witness_residuals(prev.witness, X[n0:], y[n0:]) <= dbar * 1.001):",
         description="improve: a kept witness of the assumption may miss new samples by 0.1 % more than the "
                     "check's allowance (a refuting round could pass)",
         tests=["tests/test_improve_check.py"]),
    # ------------------------------------------------------------------ the 4-D vehicle's reference boxes (issue 21)
    dict(name="vehicle-product-max-shrunk", file="src/robust_imdp/casestudies/vehicle.py",
         original="hi = upper[:, pos] + corners.max(axis=0)",
         replacement="hi = upper[:, pos] + 0.999 * corners.max(axis=0)",
         description="vehicle reference (V1/V2): upper end of v cos/sin theta shrunk 0.1 %", tests=["tests/test_vehicle.py"]),
    dict(name="vehicle-product-min-shrunk", file="src/robust_imdp/casestudies/vehicle.py",
         original="lo = lower[:, pos] + corners.min(axis=0)",
         replacement="lo = lower[:, pos] + 0.999 * corners.min(axis=0)",
         description="vehicle reference (V1/V2): lower end of v cos/sin theta shrunk 0.1 %", tests=["tests/test_vehicle.py"]),
    dict(name="vehicle-trig-peak-dropped", file="src/robust_imdp/casestudies/vehicle.py",
         original="fmax = np.where(has(peak) | wide, 1.0, fmax)",
         replacement="fmax = np.where(wide, 1.0, fmax)",
         description="vehicle reference: trig_range ignores an interior maximum", tests=["tests/test_vehicle.py"]),
    dict(name="vehicle-trig-trough-dropped", file="src/robust_imdp/casestudies/vehicle.py",
         original="fmin = np.where(has(trough) | wide, -1.0, fmin)",
         replacement="fmin = np.where(wide, -1.0, fmin)",
         description="vehicle reference: trig_range ignores an interior minimum", tests=["tests/test_vehicle.py"]),
    dict(name="vehicle-heading-shift-shrunk", file="src/robust_imdp/casestudies/vehicle.py",
         original="_outward(lower[:, 2] + w, upper[:, 2] + w, mag)",
         replacement="_outward(lower[:, 2] + w, upper[:, 2] + 0.999 * w, mag)",
         description="vehicle reference (V3): theta + omega upper end shrunk 0.1 % of omega", tests=["tests/test_vehicle.py"]),
    dict(name="vehicle-drag-critical-dropped", file="src/robust_imdp/casestudies/vehicle.py",
         original="inside = (lo - slack <= vc) & (vc <= hi + slack)",
         replacement="inside = (lo - slack <= vc) & (vc <= hi + slack) & False",
         description="vehicle reference (V4): interior critical speeds of the speed map ignored", tests=["tests/test_vehicle.py"]),
    dict(name="vehicle-drag-shrunk", file="src/robust_imdp/casestudies/vehicle.py",
         original="return k * v + a - c * v * np.abs(v)",
         replacement="return k * v + a - 1.001 * c * v * np.abs(v)",
         description="vehicle reference (V4): the drag term of the image enlarged 0.1 % (an end moves inward)", tests=["tests/test_vehicle.py"]),
    # ------------------------------------------------------------------ factored IMDP (models/factored.py, solvers/factored*.py)
    dict(name="factored-cap-shrink-1e-3", file=_FAC,
         original='        parts["cap"].append((up - lo).reshape(-1))  # rounded: its error is part of LEVEL_ERR',
         replacement='        parts["cap"].append(((up - lo) * (1 - 1e-3)).reshape(-1))',
         description="factored operator: every listed interval's width upper - lower x (1 - 1e-3) (uppers shrunk)",
         tests=["tests/test_factored.py"]),
    dict(name="factored-lower-raise-1e-3", file=_FAC,
         original='        parts["lower"].append(lo.reshape(-1))',
         replacement='        parts["lower"].append((lo * (1 + 1e-3)).reshape(-1))',
         description="factored operator: listed lower bounds x (1 + 1e-3)", tests=["tests/test_factored.py"]),
    dict(name="factored-out-lower-raise-1e-3", file=_FAC,
         original='        parts["ol"].append(ol)',
         replacement='        parts["ol"].append(ol * (1 + 1e-3))',
         description="factored operator: lower bound of leaving X on an axis x (1 + 1e-3)", tests=["tests/test_factored.py"]),
    dict(name="factored-out-upper-shrink-1e-3", file=_FAC,
         original='        parts["ocap"].append(ax.out_upper.reshape(-1)[first] - ol)',
         replacement='        parts["ocap"].append((ax.out_upper.reshape(-1)[first] - ol) * (1 - 1e-3))',
         description="factored operator: width of the outside interval x (1 - 1e-3) (out_upper shrunk)",
         tests=["tests/test_factored.py"]),
    dict(name="factored-rest-shrink-1e-3", file=_FAC,
         original='        parts["rcap"].append(ax.rest_upper.reshape(-1)[first])',
         replacement='        parts["rcap"].append(ax.rest_upper.reshape(-1)[first] * (1 - 1e-3))',
         description="factored operator: rest_upper (unlisted in-grid mass) x (1 - 1e-3)", tests=["tests/test_factored.py"]),
    dict(name="factored-free-mass-shrink-1e-3", file=_FAC,
         original='        parts["rem0"].append(1.0 - lo.sum(axis=1) - ol)  # rounded: part of LEVEL_ERR',
         replacement='        parts["rem0"].append((1.0 - lo.sum(axis=1) - ol) * (1 - 1e-3))',
         description="factored operator: the mass left after the lower bounds x (1 - 1e-3) (a law summing to < 1)",
         tests=["tests/test_factored.py"]),
    dict(name="factored-rest-valued-at-mean", file=_FAC,
         original="    w_rest = float(w.max() if (adv_max or support) else w.min())",
         replacement="    w_rest = float(w.max() if (adv_max or support) else w.mean())",
         description="factored operator: unlisted mass valued at the mean successor value, not the least (minimising)",
         tests=["tests/test_factored.py"]),
    dict(name="factored-order-lower-raise-1e-3", file=_FAC_O,
         original="        val += mg.lower[e0 + j] * x",
         replacement="        val += mg.lower[e0 + j] * 1.001 * x",
         description="factored ordered pass, one row: listed lower bounds x (1 + 1e-3)",
         tests=["tests/test_factored_order.py"]),
    dict(name="factored-order-rounding-off", file=_FAC_O,
         original="    return _finish(val, rem, k, direction)",
         replacement="    return _finish(val, rem, k, 0)",
         description="factored ordered pass, one row: no LEVEL_ERR margin on either side (round to nearest)",
         tests=["tests/test_factored_order.py"]),
    dict(name="factored-order-rest-shrink-1e-3", file=_FAC_O,
         original="        m = _insert(keys, caps, m, -w_rest if adv_max else w_rest, mg.rcap[mm])",
         replacement="        m = _insert(keys, caps, m, -w_rest if adv_max else w_rest, mg.rcap[mm] * (1 - 1e-3))",
         description="factored ordered pass, one row: rest_upper (unlisted in-grid mass) x (1 - 1e-3)",
         tests=["tests/test_factored_order.py"]),
    dict(name="factored-order-stale-rest-wrong-side", file=_FAC,
         original="    pick = np.max if lay.adv_max else np.min",
         replacement="    pick = np.min if lay.adv_max else np.max",
         description="factored ordered pass: the unlisted rest valued at the layer's max for a minimising adversary "
                     "(min for a maximising one)", tests=["tests/test_factored_order.py"]),
    dict(name="factored-order-ovi-check-loose-1e-3", file=_FAC_O,
         original="        if v > up[node]:\n            return False",
         replacement="        if v > up[node] * (1 + 1e-3):\n            return False",
         description="factored ordered pass: an upper guess accepted although a value rose by up to 0.1 %",
         tests=["tests/test_factored_order.py"]),
    dict(name="factored-order-ovi-no-restore", file=_FAC_O,
         original="                        up[nodes[i]] = saved[i - c0]  # refuted: back to the last proven vector",
         replacement="                        pass",
         description="factored ordered pass: a refuted upper guess kept", tests=["tests/test_factored_order.py"]),
    dict(name="factored-level-rounding-down-off", file=_FAC_K,
         original="        val -= level_err(k)",
         replacement="        val -= 0.0 * level_err(k)",
         description="factored operator: no LEVEL_ERR margin on the lower side (round to nearest)",
         tests=["tests/test_factored.py"]),
    dict(name="factored-level-rounding-up-off", file=_FAC_K,
         original="        val += level_err(k) + rem",
         replacement="        val += 0.0 * level_err(k) + rem",
         description="factored operator: no LEVEL_ERR margin on the upper side (round to nearest)",
         tests=["tests/test_factored.py"]),
    dict(name="factored-vi-upper-shrink-1e-3", file=_FAC,
         original="    return ReachabilityResult(lower=lo, upper=up, strategy=strat, iterations=it, precision=gap, converged=converged)",
         replacement="    return ReachabilityResult(lower=lo, upper=up * (1 - 1e-3), strategy=strat, iterations=it, precision=gap, converged=converged)",
         description="factored unbounded value iteration: upper end of every bracket x (1 - 1e-3)",
         tests=["tests/test_factored.py"]),
    dict(name="factored-kstep-lower-raise-1e-3", file=_FAC,
         original="    return ReachabilityResult(lower=lo, upper=up, strategy=strat, iterations=k, precision=prec, converged=True)",
         replacement="    return ReachabilityResult(lower=np.minimum(lo * (1 + 1e-3), 1.0), upper=up, strategy=strat, iterations=k, precision=prec, converged=True)",
         description="factored k-step value iteration: lower end of every bracket x (1 + 1e-3) (capped at 1)",
         tests=["tests/test_factored.py"]),
    dict(name="factored-kstep-budget-off", file=_FAC,
         original="        E = float(up_rounded(E * lip + delta, 3))",
         replacement="        E = 0.0",
         description="factored k-step values: no rounding budget (the plain float iterate as both ends; an a-priori "
                     "bound: a 0.1 % shrink of it cannot be seen, its absence can)", tests=["tests/test_factored.py"]),
    dict(name="factored-safety-complement-inward", file=_FAC,
         original="        lo = np.clip(np.nextafter(1.0 - res.upper, -np.inf), 0.0, 1.0)",
         replacement="        lo = np.clip(np.nextafter(1.0 - res.upper, -np.inf) * (1 + 1e-3), 0.0, 1.0)",
         description="factored safety reading: lower end 1 - P(reach bad) x (1 + 1e-3)", tests=["tests/test_factored.py"]),
    dict(name="to-joint-lower-raise-1e-3", file=_FAC_M,
         original="        plo = np.broadcast_to(_down(plo, g_rel), full).reshape(R, -1)",
         replacement="        plo = np.broadcast_to(np.minimum(_down(plo, g_rel) * (1 + 1e-3), 1.0), full).reshape(R, -1)",
         description="FactoredIMDP.to_joint: lower bounds of listed joint successors x (1 + 1e-3)",
         tests=["tests/test_factored.py"]),
    dict(name="to-joint-upper-shrink-1e-3", file=_FAC_M,
         original="        phi = np.broadcast_to(np.minimum(_up(phi, g_rel), 1.0), full).reshape(R, -1)",
         replacement="        phi = np.broadcast_to(np.maximum(np.minimum(_up(phi, g_rel), 1.0) * (1 - 1e-3), plo), full).reshape(R, -1)",
         description="FactoredIMDP.to_joint: upper bounds of listed joint successors x (1 - 1e-3) (kept >= lower)",
         tests=["tests/test_factored.py"]),
    dict(name="to-joint-outside-lower-raise-1e-3", file=_FAC_M,
         original="        out_lo = np.clip(np.nextafter(1.0 - prod_hi, -np.inf), 0.0, 1.0)",
         replacement="        out_lo = np.clip(np.nextafter(1.0 - prod_hi, -np.inf) * (1 + 1e-3), 0.0, 1.0)",
         description="FactoredIMDP.to_joint: lower bound of the outside state x (1 + 1e-3)", tests=["tests/test_factored.py"]),
    dict(name="to-joint-outside-upper-shrink-1e-3", file=_FAC_M,
         original="        out_hi = np.clip(np.nextafter(1.0 - prod_lo, np.inf), 0.0, 1.0)",
         replacement="        out_hi = np.maximum(np.clip(np.nextafter(1.0 - prod_lo, np.inf), 0.0, 1.0) * (1 - 1e-3), out_lo)",
         description="FactoredIMDP.to_joint: upper bound of the outside state x (1 - 1e-3) (kept >= lower)",
         tests=["tests/test_factored.py"]),
    dict(name="to-joint-floor-shrink-1e-3", file=_FAC_M,
         original="        floor = np.minimum(_up(floor, g_rel), 1.0) * (floor > 0)",
         replacement="        floor = np.minimum(_up(floor, g_rel), 1.0) * (floor > 0) * (1 - 1e-3)",
         description="FactoredIMDP.to_joint: the floor of unlisted joint successors x (1 - 1e-3)",
         tests=["tests/test_factored.py"]),
    # ------------------------------------------------------------------ exact transition bounds (docs/abstraction.md)
    dict(name="exact-axis-lower-raise-1e-3", file=_MARG,
         original="    lower = np.minimum(_p_lower(noise, i, l, h, a, a), _p_lower(noise, i, l, h, b, b))",
         replacement="    lower = np.minimum(_p_lower(noise, i, l, h, a, a), _p_lower(noise, i, l, h, b, b)) * (1 + 1e-3)",
         description="exact per-axis lower bound (min over the image at its ends) x (1 + 1e-3)", tests=_MT),
    dict(name="exact-axis-upper-shrink-1e-3", file=_MARG,
         original="    upper = _p_upper(noise, i, l, h, np.clip(m_lo, a, b), np.clip(m_hi, a, b))  # y* = clip(m, a, b) in there",
         replacement="    upper = _p_upper(noise, i, l, h, np.clip(m_lo, a, b), np.clip(m_hi, a, b)) * (1 - 1e-3)",
         description="exact per-axis upper bound (max over the image at clip(m, a, b)) x (1 - 1e-3)", tests=_MT),
    dict(name="exact-axis-max-at-ends", file=_MARG,
         original="    upper = _p_upper(noise, i, l, h, np.clip(m_lo, a, b), np.clip(m_hi, a, b))  # y* = clip(m, a, b) in there",
         replacement="    upper = np.maximum(_p_upper(noise, i, l, h, a, a), _p_upper(noise, i, l, h, b, b))",
         description="exact per-axis upper bound from the image's ends only (the interior maximum at the target's "
                     "centre missed)", tests=_MT),
    dict(name="exact-circle-centre-missed", file=_MARG,
         original="        upper = np.where(self.contains(a, b, m_lo, m_hi), self.mass(l, h, m_lo, m_hi, True),",
         replacement="        upper = np.where(False, self.mass(l, h, m_lo, m_hi, True),",
         description="periodic axis: the maximum at the arc centre missed (the ends only)", tests=_MT),
    dict(name="exact-circle-antipode-missed", file=_MARG,
         original="        lower = np.where(self.contains(a, b, an_lo, an_hi), self.mass(l, h, an_lo, an_hi, False),",
         replacement="        lower = np.where(False, self.mass(l, h, an_lo, an_hi, False),",
         description="periodic axis: the minimum at the antipode missed (the ends only)", tests=_MT),
    dict(name="exact-circle-tail-dropped", file=_MARG,
         original="        return np.minimum(_sum_up(np.concatenate([terms, below, above], axis=-1)), 1.0)  # safe: a probability",
         replacement="        return np.minimum(_sum_up(terms), 1.0)",
         description="periodic axis: the mass of the copies beyond the summed ones left out of the upper bound",
         tests=_MT),
    dict(name="exact-outside-upper-shrink-1e-3", file=_MARG,
         original="    out_upper = np.minimum(np.maximum(tails_up(a), tails_up(b)), 1.0)  # safe: a probability",
         replacement="    out_upper = np.minimum(np.maximum(tails_up(a), tails_up(b)), 1.0) * (1 - 1e-3)",
         description="exact per-axis upper bound of leaving X x (1 - 1e-3)", tests=_MT),
    dict(name="exact-outside-lower-raise-1e-3", file=_MARG,
         original="    return np.minimum(out_lower, out_upper), out_upper",
         replacement="    return np.minimum(out_lower * (1 + 1e-3), out_upper), out_upper",
         description="exact per-axis lower bound of leaving X x (1 + 1e-3) (kept <= upper)", tests=_MT),
    dict(name="exact-rest-shrink-1e-3", file=_MARG,
         original="    return np.minimum(total, 1.0)  # safe: a probability",
         replacement="    return np.minimum(total, 1.0) * (1 - 1e-3)",
         description="rest_upper (mass of the unlisted intervals of an axis) x (1 - 1e-3)", tests=_MT),
    dict(name="exact-ndtr-allowance-shrink-1e-3", file="src/robust_imdp/models/noise.py",
         original="    return (32.0 + 8.0 * t2) * U * np.abs(value) + NDTR_ABS",
         replacement="    return ((32.0 + 8.0 * t2) * U * np.abs(value) + NDTR_ABS) * (1 - 1e-3)",
         description="the error allowance of scipy's ndtr x (1 - 1e-3)", tests=_MT),
    dict(name="exact-uniform-rounding-off", file="src/robust_imdp/models/noise.py",
         original="            val = up(up(hi - lo) / (2.0 * c))",
         replacement="            val = (hi - lo) / (2.0 * c)",
         description="uniform noise: the interval probability's upper bound rounded to nearest (no ulp outward)",
         tests=_MT),
    dict(name="exact-joint-upper-shrink-1e-3", file=_EXR,
         original="        upp = np.minimum(_prod_up(np.broadcast_to(phi, shape_full).reshape(B, K), d - 1), 1.0)  # safe: <= 1",
         replacement="        upp = np.minimum(_prod_up(np.broadcast_to(phi, shape_full).reshape(B, K), d - 1), 1.0) * (1 - 1e-3)",
         description="exact joint rows (grid): upper bounds of listed cells x (1 - 1e-3)", tests=_MT),
    dict(name="exact-joint-lower-raise-1e-3", file=_EXR,
         original="        low = _prod_down(np.broadcast_to(plo, shape_full).reshape(B, K), d - 1)",
         replacement="        low = _prod_down(np.broadcast_to(plo, shape_full).reshape(B, K), d - 1) * (1 + 1e-3)",
         description="exact joint rows (grid): lower bounds of listed cells x (1 + 1e-3)", tests=_MT),
    dict(name="exact-joint-outside-upper-shrink-1e-3", file=_EXR,
         original="        out_hi = _fold_out(o_hi, True)",
         replacement="        out_hi = _fold_out(o_hi, True) * (1 - 1e-3)",
         description="exact joint rows: upper bound of the outside state x (1 - 1e-3)", tests=_MT),
    dict(name="exact-joint-outside-lower-raise-1e-3", file=_EXR,
         original="        out_lo = _fold_out(o_lo, False)",
         replacement="        out_lo = _fold_out(o_lo, False) * (1 + 1e-3)",
         description="exact joint rows: lower bound of the outside state x (1 + 1e-3) (kept <= upper)", tests=_MT),
    dict(name="exact-joint-floor-shrink-1e-3", file=_EXR,
         original="    return low, upp, np.minimum(floor, 1.0), out_lo, out_hi",
         replacement="    return low, upp, np.minimum(floor, 1.0) * (1 - 1e-3), out_lo, out_hi",
         description="exact joint rows: the floor of unlisted cells x (1 - 1e-3)", tests=_MT),
    dict(name="exact-joint-prune-above-floor", file=_EXR,
         original="    keep[:, :K] = listed & (upp > floor[:, None])  # at most the floor: covered by it as an unlisted cell",
         replacement="    keep[:, :K] = listed & (upp > 2 * floor[:, None])",
         description="exact joint rows: entries up to twice the floor dropped (the floor no longer covers them)",
         tests=_MT),
    dict(name="exact-gp-mixture-complement-dropped", file=_EXR,
         original="    return np.minimum(up(up(upp * pg) + up(1.0 - pg)), 1.0)",
         replacement="    return np.minimum(up(upp * pg), 1.0)",
         description="exact rows, GP route: the upper bound P_g upper + (1 - P_g) without the failure branch",
         tests=_MT),
    dict(name="nominal-mixture-upper-shrink-1e-3", file="src/robust_imdp/abstraction/nominal.py",
         original="        upper = np.minimum(up(up_sum / S, gamma(S + 3) * (up_listed + 2.0 * fl_row) / S), 1.0)",
         replacement="        upper = np.minimum(up(up_sum / S, gamma(S + 3) * (up_listed + 2.0 * fl_row) / S), 1.0) * (1 - 1e-3)",
         description="nominal mixture rows (several points per cell): upper bounds x (1 - 1e-3)",
         tests=["tests/test_anaesthesia_rows.py", "tests/test_nominal_ties.py"]),
    dict(name="nominal-mixture-lower-raise-1e-3", file="src/robust_imdp/abstraction/nominal.py",
         original="        lower = np.maximum(down(lo_sum / S, gamma(S + 1) * lo_sum / S), 0.0)",
         replacement="        lower = np.maximum(down(lo_sum / S, gamma(S + 1) * lo_sum / S), 0.0) * (1 + 1e-3)",
         description="nominal mixture rows (several points per cell): lower bounds x (1 + 1e-3)",
         tests=["tests/test_anaesthesia_rows.py", "tests/test_nominal_ties.py"]),
    # ------------------------------------------------------------------ the safety reading, known dynamics
    dict(name="safety-complement-down-off", file="src/robust_imdp/_fp.py",
         original="    return np.where(e < 0, np.nextafter(s, -np.inf), s)",
         replacement="    return s",
         description="_fp.complement_down (p_low = 1 - P(bad prefix)) keeps fl(1 - x) where it rounded up",
         tests=["tests/test_semantics.py"]),
    dict(name="safety-evaluation-adversary-not-swapped", file="src/robust_imdp/solvers/product.py",
         original='    adv_max = (enum_value(Adversary, adversary, "adversary") is Adversary.OPTIMISTIC) != safety',
         replacement='    adv_max = enum_value(Adversary, adversary, "adversary") is Adversary.OPTIMISTIC',
         description="safety reading: a strategy's pessimistic evaluation lets the adversary minimise the probability "
                     "of a bad prefix (p_low = 1 - that, too high)",
         tests=["tests/test_semantics.py"]),
    dict(name="known-tau-shrink-1e-3", file="src/robust_imdp/pipeline/bound_stage.py",
         original="        t = np.broadcast_to(tau[u], (k, n))",
         replacement="        t = np.broadcast_to(tau[u] * (1 - 1e-3), (k, n))",
         description="known dynamics: the misspecification allowance tau of every known component x (1 - 1e-3)",
         tests=["tests/test_known_systems.py"]),
    # ------------------------------------------------------------------ the factored form in the pipeline (abstraction/factored.py, synthesis/core.py)
    dict(name="factored-pipeline-chunk-listed-short", file="src/robust_imdp/abstraction/factored.py",
         original="                                                 np.full(start[:, sl].shape, kj), kj)):",
         replacement="                                                 np.full(start[:, sl].shape, kj) - 1, kj)):",
         description="factored abstraction: each row's last listed interval stored as [0, 0] (its mass only in the "
                     "rest): an upper bound of 0 for an interval the noise reaches", tests=["tests/test_factored_pipeline.py"]),
    dict(name="factored-one-mode-optimistic-as-robust", file="src/robust_imdp/synthesis/core.py",
         original="        return optimistic, robust, robust, optimistic, np.asarray(robust.strategy), \\",
         replacement="        return optimistic, robust, optimistic, optimistic, np.asarray(robust.strategy), \\",
         description="synthesis of a one-mode factored model: p_low read from the optimistic evaluation",
         tests=["tests/test_factored_pipeline.py"]),
    dict(name="factored-evaluate-adversary-flipped", file="src/robust_imdp/synthesis/core.py",
         original="        return solve_factored_product(m, letters, dfa, adversary=adversary, strategy=strategy, control=\"maximize\",",
         replacement="        return solve_factored_product(m, letters, dfa, adversary=\"optimistic\", strategy=strategy, control=\"maximize\",",
         description="synthesis on a factored model: the strategy evaluated against the optimistic adversary for p_low",
         tests=["tests/test_factored_pipeline.py"]),
    # ------------------------------------------------------------------ graph pre-computations (solvers/graph.py)
    dict(name="graph-positive-attractor-strict", file="src/robust_imdp/solvers/graph.py",
         original="                    hit = down < 1.0",
         replacement="                    hit = down < 1.0 - 1e-3",
         description="positive attractor (minimising adversary), near a sum of 1: a row counts as forcing mass onto W "
                     "only when at most 0.999 can stay outside: nodes of positive value fixed to 0",
         tests=["tests/test_graph_lanes.py"]),
    dict(name="graph-positive-attractor-no-band", file="src/robust_imdp/solvers/graph.py",
         original="                band = (nOut + 4.0) * 8.0 * U * (1.0 + stay)",
         replacement="                band = 0.0",
         description="positive attractor (minimising adversary): the rounded-to-nearest mass outside W decides alone "
                     "(a sum rounded above 1 whose exact value is below 1: a node of positive value fixed to 0)",
         tests=["tests/test_graph_lanes.py"]),
    dict(name="graph-almost-sure-no-slack", file="src/robust_imdp/solvers/graph.py",
         original="                good = lowX > 0.0 or rest + _sum_slack(nNotX, fl and unlNotX > 0) < 1.0",
         replacement="                good = lowX > 0.0 or rest < 1.0",
         description="almost-sure set (minimising adversary): the rounded-to-nearest mass outside X compared with 1 "
                     "without its rounding slack: nodes of value < 1 fixed to 1", tests=["tests/test_graph_lanes.py"]),
    dict(name="graph-sure-lanes-skip-units", file="src/robust_imdp/solvers/graph.py",
         original="            u = fetch_add(taken, 0, 1)\n            if u >= nu:\n                break\n"
                  "            for idx in range(u * _UNIT, min(N, (u + 1) * _UNIT)):\n"
                  "                node = N - 1 - idx if back else idx\n                if X[node]",
         replacement="            u = fetch_add(taken, 0, 2)\n            if u >= nu:\n                break\n"
                     "            for idx in range(u * _UNIT, min(N, (u + 1) * _UNIT)):\n"
                     "                node = N - 1 - idx if back else idx\n                if X[node]",
         description="almost-sure set on several threads: the lanes take every other unit of nodes from the shared "
                     "counter (half the nodes never tested: nodes of value 1 left out)",
         tests=["tests/test_graph_lanes.py"]),
    dict(name="bellman-parallel-skip-blocks", file="src/robust_imdp/solvers/kernels.py",
         original="            b = fetch_add(taken, 0, 1)\n            if b >= n_blocks:\n                break\n"
                  "            for q in range(b * PAR_BLOCK",
         replacement="            b = fetch_add(taken, 0, 2)\n            if b >= n_blocks:\n                break\n"
                     "            for q in range(b * PAR_BLOCK",
         description="threaded Jacobi sweep: the threads take every other block of states from the shared counter "
                     "(half the states keep stale values)",
         tests=["tests/test_solve.py::test_parallel_jacobi_sweeps_give_the_serial_results_bit_for_bit"]),
    dict(name="local-pieces-no-wait", file="src/robust_imdp/bounds/rkhs_local.py",
         original="            while not full():",
         replacement="            while False:",
         description="local weights on several threads: eq. C of a piece runs without waiting for the kernel to "
                     "write its blocks (ranges from unwritten values)", tests=["tests/test_bound_lanes.py"]),
]


# --------------------------------------------------------------------------- machinery
def _read(file: str, source: str) -> str | None:
    """Text of repository file ``file`` in the working tree or at HEAD (None if absent)."""
    if source == "head":
        r = subprocess.run(["git", "-C", str(ROOT), "show", f"HEAD:{file}"], capture_output=True, text=True)
        return r.stdout if r.returncode == 0 else None
    path = ROOT / file
    return path.read_text() if path.is_file() else None


def _check_list(mutations, source: str = "worktree") -> list[str]:
    """Problems with the list: duplicate names, missing files, original not exactly once."""
    problems, seen = [], set()
    for m in mutations:
        missing = {"name", "file", "original", "replacement", "description"} - set(m)
        if missing:
            problems.append(f"{m.get('name', '?')}: missing keys {sorted(missing)}")
            continue
        if m["name"] in seen:
            problems.append(f"{m['name']}: duplicate name")
        seen.add(m["name"])
        text = _read(m["file"], source)
        if text is None:
            problems.append(f"{m['name']}: file {m['file']} does not exist")
            continue
        n = text.count(m["original"])
        if n != 1:
            problems.append(f"{m['name']}: original text occurs {n} times in {m['file']} (must be exactly once): "
                            f"{m['original']!r}")
        if m["original"] == m["replacement"]:
            problems.append(f"{m['name']}: replacement equals the original")
    return problems


def _tree_files() -> list[str]:
    out = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                         capture_output=True, check=True).stdout.decode()
    return sorted({f for f in out.split("\0") if f and (ROOT / f).is_file()})


def _copy_tree(dest: Path, files) -> None:
    """``files``: a list of paths (copy the working tree) or ``"HEAD"`` (the last commit)."""
    if files == "HEAD":
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", "HEAD"], capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)
        for f in (p for p in dest.rglob("*") if p.is_file()):
            src = ROOT / f.relative_to(dest)
            if src.is_file() and src.read_bytes() == f.read_bytes():
                shutil.copystat(src, f)  # same bytes: same mtime, so numba's cache (below) applies
    else:
        for f in files:
            target = dest / f
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / f, target)  # keeps mtimes: numba's cache (below) stays valid
    # numba's on-disk cache (keyed by the source file's mtime and size): reusing it saves the
    # compile time; the mutated file's new mtime invalidates its own entries only.
    for cache in (ROOT / "src").rglob("__pycache__"):
        for f in cache.glob("*.nb[ic]"):
            target = dest / f.relative_to(ROOT)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, target)


def _apply(dest: Path, m: dict) -> None:
    path = dest / m["file"]
    text = path.read_text()
    n = text.count(m["original"])
    if n != 1:
        raise RuntimeError(f"mutation {m['name']}: original text occurs {n} times in {m['file']}")
    path.write_text(text.replace(m["original"], m["replacement"], 1))


def _warm(snapshot: Path) -> None:
    """Compile the snapshot's numba kernels once (``python -m robust_imdp.warmup``) so that every
    scratch copy starts with them cached: copies keep the sources' mtimes, which is what numba's
    cache index checks. Mutated code is never loaded from this cache (:func:`_drop_kernel_caches`)."""
    subprocess.run([sys.executable, "-m", "robust_imdp.warmup", "--quiet"], cwd=snapshot, env=_env(snapshot),
                   capture_output=True, text=True)


def _drop_kernel_caches(dest: Path, mutated: str) -> None:
    """Delete the numba caches a mutation could make stale. numba keys a kernel's cache by its own
    file only, and a kernel compiled with callees from another file keeps their old code; numba
    kernels call each other only within one subpackage (and use the top-level helpers), so: the
    mutated file's subpackage, or every cache when a top-level module is mutated."""
    rel = Path(mutated).relative_to("src/robust_imdp")
    root = dest / "src" / "robust_imdp"
    where = root / rel.parts[0] if len(rel.parts) > 1 else root
    for pattern in ("*.nbi", "*.nbc"):
        for f in where.rglob(pattern):
            f.unlink()


def _env(dest: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(dest / "src")
    env.pop("PYTHONHOME", None)
    env.setdefault("MPLBACKEND", "Agg")
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def _failures(output: str) -> list[str]:
    """Test ids of the short summary's FAILED / ERROR lines."""
    out = []
    for line in output.splitlines():
        if line.startswith(("FAILED ", "ERROR ")):
            out.append(line.split(" ", 1)[1].split(" - ")[0].strip())
    return out


def _first_failure(output: str) -> str | None:
    f = _failures(output)
    return f[0] if f else None


#: Test files tried first for a mutation of a file under these paths (then the whole suite).
_LIKELY = {
    "src/robust_imdp/abstraction/": ["tests/test_abstraction.py", "tests/test_rounding.py", "tests/test_sensitivity.py",
                                     "tests/test_confidence_mode.py"],
    "src/robust_imdp/bounds/rkhs": ["tests/test_rkhs.py", "tests/test_rkhs_local.py", "tests/test_margins_bounds.py"],
    "src/robust_imdp/_kernels": ["tests/test_rkhs.py", "tests/test_rkhs_local.py"],
    "src/robust_imdp/bounds/gp": ["tests/test_gp.py", "tests/test_bounds.py"],
    "src/robust_imdp/bounds/assumptions": ["tests/test_known_pipeline.py"],
    "src/robust_imdp/models/known": ["tests/test_known.py", "tests/test_known_pipeline.py"],
    "src/robust_imdp/models/intervals": ["tests/test_known.py", "tests/test_known_pipeline.py"],
    "src/robust_imdp/models/expressions": ["tests/test_known.py", "tests/test_known_pipeline.py"],
    "src/robust_imdp/models/system": ["tests/test_affine_residuals.py"],
    "src/robust_imdp/pipeline/": ["tests/test_known_pipeline.py", "tests/test_affine_residuals.py"],
    "src/robust_imdp/solvers/factored": ["tests/test_factored.py"],
    "src/robust_imdp/models/factored": ["tests/test_factored.py"],
    "src/robust_imdp/solvers/": ["tests/test_solve.py", "tests/test_sensitivity.py"],
    "src/robust_imdp/synthesis/": ["tests/test_synthesis.py", "tests/test_controller.py"],
}


def _likely_tests(m: dict) -> list:
    """The previous run's first failing test file for ``m`` (benchmarks/results/mutations.json), then
    the files of ``_LIKELY`` for its source file, then the entry's own ``tests``."""
    out = list(m.get("tests", ()))
    try:
        prev = {r["name"]: r for r in json.loads(RAW.read_text()).get("results", [])}
    except (OSError, ValueError):
        prev = {}
    ff = (prev.get(m["name"]) or {}).get("first_failure")
    if ff:
        out.append(ff.split("::")[0])
    for prefix, tests in _LIKELY.items():
        if m["file"].startswith(prefix):
            out += tests
    return list(dict.fromkeys(out))


def _pytest(cmd, cwd, env, timeout):
    """(exit code or None on timeout, output) of one pytest run."""
    try:
        proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
        return proc.returncode, proc.stdout + proc.stderr
    except subprocess.TimeoutExpired as exc:
        return None, (exc.stdout or b"").decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")


def run_one(m: dict | None, snapshot: Path, timeout: float, deselect=()) -> dict:
    """Copy the snapshot, mutate (``m`` None: baseline), check the import path, run pytest."""
    name = "baseline" if m is None else m["name"]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix=f"mut-{name}-") as tmp:
        dest = Path(tmp)
        shutil.copytree(snapshot, dest, symlinks=True, dirs_exist_ok=True)  # copy2: mtimes kept
        if m is not None:
            _apply(dest, m)
            _drop_kernel_caches(dest, m["file"])
        env = _env(dest)
        probe = subprocess.run([sys.executable, "-c", "import robust_imdp; print(robust_imdp.__file__)"],
                               cwd=dest, env=env, capture_output=True, text=True)
        where = probe.stdout.strip()
        if probe.returncode != 0 or not Path(where).resolve().is_relative_to(dest.resolve()):
            raise RuntimeError(f"{name}: robust_imdp imports from {where or probe.stderr.strip()!r}, "
                               f"not from the scratch copy {dest}")
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
        cmd += [] if m is None else ["-x"]  # baseline: every failure, to deselect them below
        for test_id in deselect:
            cmd += ["--deselect", test_id]
        rc, out = None, ""
        first = [] if m is None else [t for t in _likely_tests(m) if (dest / t).exists()]
        if first:  # the test files most likely to catch it first: a failure there is a catch
            rc, out = _pytest(cmd + first, dest, env, timeout)
        if rc != 1:  # not caught there (or no likely tests): the whole suite decides
            rc, out = _pytest(cmd, dest, env, timeout)
    last = [line for line in out.splitlines() if line.strip()][-1:] if out else []
    if rc == 0:
        status = "not caught"
    elif rc == 1:
        status = "caught"
    elif rc is None:
        status = f"timeout ({timeout:.0f} s)"
    else:
        status = f"error (pytest exit {rc})"
    return {"name": name, "status": status, "returncode": rc, "first_failure": _first_failure(out),
            "failures": _failures(out) if m is None else None,
            "summary": last[0].strip("= ") if last else "", "seconds": time.perf_counter() - t0,
            "file": None if m is None else m["file"], "description": "unmutated copy" if m is None
            else m["description"]}


def _commit(source: str) -> str:
    sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                         text=True).stdout.strip() or "unknown"
    if source == "head":
        return sha
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=normal"],
                           capture_output=True, text=True).stdout.strip()
    return sha + (" + uncommitted changes in the working tree" if dirty else "")


def write_doc(results, baseline, command, elapsed, deselected, code) -> None:
    caught = sum(r["status"] == "caught" for r in results)
    lines = [
        "# Mutation check of the test suite (`benchmarks/mutations.py`)", "",
        f"Run {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} with `{command}` "
        f"({elapsed / 60:.1f} min) on commit {code}. Baseline (unmutated copy): {baseline['status'].replace('not caught', 'passes')}"
        f" ({baseline['summary']}).", "",
        "Each row is a one-line edit that makes one bound slightly unsound, applied to a scratch copy of "
        "the working tree; the whole suite then runs on the copy (`pytest -x`). **caught** = some test fails "
        "(the first one is named); **not caught** = the suite passes although the bound is unsound, i.e. a "
        "missing soundness check (issue 14). The list of mutations is `MUTATIONS` at the top of the script.", "",
        *([f"Tests failing already in the baseline, deselected from the mutation runs: "
           f"{', '.join(f'`{t}`' for t in deselected)}.", ""] if deselected else []),
        f"**{caught} of {len(results)} caught.**", "",
        "| mutation | file | what is made unsound | result | first failing test | s |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        res = f"**{r['status']}**" if r["status"] != "caught" else "caught"
        ff = f"`{r['first_failure'].removeprefix('FAILED ').removeprefix('ERROR ')}`" if r["first_failure"] else "-"
        lines.append(f"| `{r['name']}` | {Path(r['file']).name} | {r['description']} | {res} | {ff} | "
                     f"{r['seconds']:.0f} |")
    DOC.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=1, help="mutations run in parallel (default 1)")
    ap.add_argument("--only", nargs="+", metavar="NAME",
                    help="run only these mutations (merged into the last run's json and table)")
    ap.add_argument("--list", action="store_true", help="print the mutations and check the list, run nothing")
    ap.add_argument("--no-write", action="store_true", help="do not write docs/mutations.md and the json")
    ap.add_argument("--no-baseline", action="store_true", help="skip the unmutated run")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per pytest run")
    ap.add_argument("--source", choices=("worktree", "head"), default="worktree",
                    help="copy the working tree (tracked + new files; default) or the last commit (HEAD), "
                         "e.g. while others have half-done edits in the working tree")
    ap.add_argument("--strict-baseline", action="store_true",
                    help="stop when the unmutated suite fails (default: deselect its failing tests)")
    args = ap.parse_args(argv)

    selected = MUTATIONS
    if args.only:
        unknown = sorted(set(args.only) - {m["name"] for m in MUTATIONS})
        if unknown:
            print(f"--only: unknown mutations {unknown}; known: {[m['name'] for m in MUTATIONS]}", file=sys.stderr)
            return 2
        selected = [m for m in MUTATIONS if m["name"] in args.only]
    problems = _check_list(selected, args.source)
    if problems:
        print("the mutation list is out of date:\n  " + "\n  ".join(problems), file=sys.stderr)
        return 2
    if args.list:
        for m in selected:
            print(f"{m['name']:32s} {m['file']:34s} {m['description']}")
        return 0

    command = "python benchmarks/mutations.py" + "".join(
        f" {a}" for a in (sys.argv[1:] if argv is None else argv))
    files = _tree_files() if args.source == "worktree" else "HEAD"
    code = _commit(args.source)
    t0 = time.perf_counter()
    # One snapshot for all runs: others may edit the working tree while the mutations run.
    with tempfile.TemporaryDirectory(prefix="mut-snapshot-") as snap:
        snapshot = Path(snap)
        _copy_tree(snapshot, files)
        problems = []
        for m in selected:  # the tree may have changed since the check above
            n = (snapshot / m["file"]).read_text().count(m["original"])
            if n != 1:
                problems.append(f"{m['name']}: original text occurs {n} times in the snapshot's {m['file']}")
        if problems:
            print("the mutation list is out of date:\n  " + "\n  ".join(problems), file=sys.stderr)
            return 2
        _warm(snapshot)
        out = _run_all(args, selected, snapshot)
        if isinstance(out, int):
            return out
        results, baseline, deselected = out
    elapsed = time.perf_counter() - t0
    caught = sum(r["status"] == "caught" for r in results)
    print(f"{caught} of {len(results)} mutations caught ({elapsed / 60:.1f} min)")
    if not args.no_write:
        if args.only and RAW.exists():
            # merge into the last full run: the other mutations keep their earlier results
            prev = json.loads(RAW.read_text())
            mine = {r["name"] for r in results}
            order = {m["name"]: i for i, m in enumerate(MUTATIONS)}
            results = sorted([r for r in prev["results"] if r["name"] not in mine] + results,
                             key=lambda r: order.get(r["name"], len(order)))
            command = f"{prev['command']}`, then `{command}"
            code = f"{prev['code']}, then {code} for {len(mine)} mutations"
            if args.no_baseline:
                baseline, deselected = prev["baseline"], prev["deselected"]
            elapsed += float(prev.get("elapsed", sum(r["seconds"] for r in prev["results"])))
        write_doc(results, baseline, command, elapsed, deselected, code)
        RAW.parent.mkdir(parents=True, exist_ok=True)
        RAW.write_text(json.dumps({"command": command, "code": code, "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                                   "elapsed": elapsed, "baseline": baseline, "deselected": deselected,
                                   "results": results},
                                  indent=1))
    return 0 if caught == len(results) else 1


def _run_all(args, selected, snapshot):
    """Baseline, then every mutation: (results, baseline, deselected) or an exit status."""
    baseline = {"status": "not run", "summary": "skipped"}
    deselected = []
    if not args.no_baseline:
        baseline = run_one(None, snapshot, args.timeout)
        print(f"baseline: {baseline['summary']} ({baseline['seconds']:.0f} s)", flush=True)
        if baseline["status"] != "not caught":
            deselected = baseline["failures"] or []
            if args.strict_baseline or baseline["returncode"] != 1 or not deselected:
                print(f"the unmutated suite does not pass ({baseline['status']}, failures {deselected}): "
                      "fix that first", file=sys.stderr)
                return 3
            print(f"WARNING: {len(deselected)} tests fail without any mutation; deselected: {deselected}",
                  file=sys.stderr, flush=True)

    def one(m):
        r = run_one(m, snapshot, args.timeout, deselected)
        print(f"{r['name']:32s} {r['status']:12s} {r['first_failure'] or '-'} ({r['seconds']:.0f} s)", flush=True)
        return r

    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        results = list(pool.map(one, selected))
    return results, baseline, deselected


if __name__ == "__main__":
    sys.exit(main())
