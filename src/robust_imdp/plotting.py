"""Figures (the only matplotlib importer; nothing else in the library imports this module).

Every function takes a result (a :class:`~robust_imdp.io.files.ResultFile`, a pipeline
``Result``, a result dict or a path to ``result.json``) and an optional ``ax``; it draws and
returns the Axes. :func:`save_figures` writes the standard set of PNGs for any dimension:

* 1-D: ``bounds.png`` -- p_low and p_up against x over the cells' classes (:func:`plot_bounds_1d`);
* 2-D: ``partition.png``, ``classes.png``, ``p_low.png``, ``error.png``, ``b_margin.png`` (the assumption
  margins, :func:`plot_margins`, where the run computed them) (and ``trajectories.png``);
  simulated paths of any other dimension: :func:`plot_trajectory_panels` (1-D: state against step;
  3-D and more: projections on pairs of coordinates);
* 3-D and more: the same four as panels of 2-D slices x_3 = c at a few values c
  (:func:`plot_slices`): one of them, and every further coordinate, goes through the grid
  interval met by the most Q_yes cells (:func:`best_slice_value`); ``slice=`` (the command
  line's ``--slice x3=0.5,x4=0``) fixes coordinates instead.

Axes are labelled with the dimension names (``[space].names``) when the result has them, else
``x_1 .. x_n``.

Maps carry the region outlines with their names; heat maps of probabilities also carry the
threshold contour (the boundary of ``value >= threshold``).
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import Normalize
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.patheffects import withStroke
from scipy import ndimage

from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.io.files import ResultFile, as_result_file as _as_result_file
from robust_imdp.validate import RUNNING, SATISFIED, VIOLATED

__all__ = [
    "plot_partition",
    "plot_classes",
    "plot_values",
    "plot_margins",
    "plot_trajectories",
    "plot_trajectory_panels",
    "plot_eta_sweep",
    "plot_bounds_1d",
    "plot_slices",
    "slice_result",
    "resolve_slice",
    "best_slice_value",
    "threshold_segments",
    "seam_segments",
    "save_figures",
    "figure_names",
    "plot_calibration",
    "save_calibration_figure",
]

CLASS_COLOURS = {"yes": "#2ca25f", "maybe": "#fec44f", "no": "#de2d26"}
CLASS_TEXT = {"yes": "Q_yes (p_low >= threshold)", "maybe": "Q_? (undecided)",
              "no": "Q_no (p_up < threshold)"}
_REGION_COLOURS = ["#3182bd", "#636363", "#e6550d", "#756bb1", "#31a354", "#d6616b"]
THRESHOLD_COLOUR = "#e7298a"  # the threshold contour: magenta reads on viridis, magma and the class colours
_PROBABILITIES = ("p_low", "p_up", "p_up_star")


def _result(result, dims: int | None = 2) -> ResultFile:
    res = _as_result_file(result)
    if dims is not None and res.cells_lower.shape[1] != dims:
        hint = {1: "plot_bounds_1d", 2: "plot_classes / plot_values"}.get(res.cells_lower.shape[1],
                                                                          "plot_slices (or slice_result)")
        raise DimensionError(
            f"this plot needs a {dims}-D state space; got cells of dimension {res.cells_lower.shape[1]} "
            f"(use {hint}, or save_figures for any dimension)"
        )
    return res


def _ax(ax):
    if ax is None:
        _, ax = plt.subplots(figsize=(5.2, 4.6), constrained_layout=True)
    return ax


def _rects(res: ResultFile) -> np.ndarray:
    lo, up = res.cells_lower, res.cells_upper
    return np.stack([lo, np.c_[up[:, 0], lo[:, 1]], up, np.c_[lo[:, 0], up[:, 1]]], axis=1)


def _frame(ax, res: ResultFile, title: str) -> None:
    ax.set_xlim(res.space_lower[0], res.space_upper[0])
    ax.set_ylim(res.space_lower[1], res.space_upper[1])
    ax.set_aspect("equal")
    names = res.parameters.get("_axis_names") or (_axis_text(res, 0, tex=True), _axis_text(res, 1, tex=True))
    ax.set_xlabel(names[0])
    ax.set_ylabel(names[1])
    ax.set_title(title, fontsize=10)


def _region_raster(res: ResultFile, atom: str):
    """Indicator of ``atom`` on the breakpoint grid; returns (bps_x, bps_y, ind (nx, ny))."""
    return _raster(res, np.array([atom in lab for lab in res.labels], dtype=bool))


def _raster(res: ResultFile, has: np.ndarray):
    """Indicator of the cells ``has`` on the breakpoint grid; returns (bps_x, bps_y, ind (nx, ny))."""
    bx = np.unique(np.r_[res.cells_lower[:, 0], res.cells_upper[:, 0]])
    by = np.unique(np.r_[res.cells_lower[:, 1], res.cells_upper[:, 1]])
    ind = np.zeros((len(bx) - 1, len(by) - 1), dtype=bool)
    i0 = np.searchsorted(bx, res.cells_lower[has, 0])
    i1 = np.searchsorted(bx, res.cells_upper[has, 0])
    j0 = np.searchsorted(by, res.cells_lower[has, 1])
    j1 = np.searchsorted(by, res.cells_upper[has, 1])
    for a, b, c, d in zip(i0, i1, j0, j1):
        ind[a:b, c:d] = True
    return bx, by, ind


def _outline_segments(bx, by, ind) -> list:
    """Boundary segments of the union of raster boxes where ``ind`` is True (vectorised)."""
    pad = np.pad(ind, 1)
    segs = []
    vi, vj = np.nonzero(pad[1:, 1:-1] != pad[:-1, 1:-1])  # vertical edges at x = bx[vi]
    segs += [((bx[i], by[j]), (bx[i], by[j + 1])) for i, j in zip(vi, vj)]
    hi, hj = np.nonzero(pad[1:-1, 1:] != pad[1:-1, :-1])  # horizontal edges at y = by[hj]
    segs += [((bx[i], by[j]), (bx[i + 1], by[j])) for i, j in zip(hi, hj)]
    return _merge_collinear(segs)


def _merge_collinear(segs) -> list:
    """Join axis-parallel segments that continue each other (refined cells make many short ones,
    whose haloes would overlap at every joint and stripe the line)."""
    out, runs = [], {}
    for (x0, y0), (x1, y1) in segs:
        key = ("v", x0) if x0 == x1 else ("h", y0)
        runs.setdefault(key, []).append((y0, y1) if x0 == x1 else (x0, x1))
    for (kind, c), spans in runs.items():
        spans.sort()
        a, b = spans[0]
        for lo, hi in spans[1:] + [(np.inf, np.inf)]:
            if lo == b:
                b = hi
                continue
            out.append(((c, a), (c, b)) if kind == "v" else ((a, c), (b, c)))
            a, b = lo, hi
    return out


def _draw_regions(ax, res: ResultFile, *, fill: bool, label_text: bool = True, lw: float = 1.6,
                  only=None):
    groups: list = []  # regions covering exactly the same cells are drawn once, named together
    for atom in sorted({a for lab in res.labels for a in lab if only is None or a in only}):
        bx, by, ind = _region_raster(res, atom)
        for g in groups:
            if np.array_equal(g[3], ind):
                g[0].append(atom)
                break
        else:
            groups.append(([atom], bx, by, ind))
    handles = []
    for k, (names, bx, by, ind) in enumerate(groups):
        colour = _REGION_COLOURS[k % len(_REGION_COLOURS)]
        atom = " = ".join(names)
        if fill:
            has = np.array([names[0] in lab for lab in res.labels])
            ax.add_collection(PolyCollection(_rects(res)[has], facecolors=colour, alpha=0.35,
                                             edgecolors="none"))
        if fill:
            ax.add_collection(LineCollection(_outline_segments(bx, by, ind), colors=colour,
                                             linewidths=lw))
        else:  # over coloured maps: a white line with a black halo reads on any colour
            ax.add_collection(LineCollection(
                _outline_segments(bx, by, ind), colors="white", linewidths=lw,
                path_effects=[withStroke(linewidth=lw + 1.6, foreground="black")]))
        if label_text:
            comp, n_comp = ndimage.label(ind)
            for c in range(1, n_comp + 1):
                ii, jj = np.nonzero(comp == c)
                cx = 0.5 * (bx[ii].min() + bx[ii.max() + 1])
                cy = 0.5 * (by[jj].min() + by[jj.max() + 1])
                # black on an opaque white box, edged in the region's colour: reads on every cell
                # colour, and sits above paths and markers (zorder)
                ax.text(cx, cy, atom, ha="center", va="center", fontsize=9, weight="bold",
                        color="black", zorder=6, bbox=dict(boxstyle="round,pad=0.2", fc="white",
                                                           ec=colour, lw=1.2, alpha=0.95))
        handles.append(Patch(facecolor=colour if fill else "none", edgecolor=colour,
                             alpha=0.6 if fill else 1.0, label=atom))
    return handles


def plot_partition(result, ax=None, *, title: str | None = None):
    """The grid partition of X with the labelled regions filled and named."""
    res = _result(result)
    ax = _ax(ax)
    ax.add_collection(PolyCollection(_rects(res), facecolors="none", edgecolors="#bdbdbd",
                                     linewidths=0.3))
    handles = _draw_regions(ax, res, fill=True)
    _frame(ax, res, title or f"Partition: {res.n_cells} cells, regions {', '.join(h.get_label() for h in handles)}")
    if handles:
        ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.13),
                  ncol=min(4, len(handles)), fontsize=8, frameon=False)
    return ax


def plot_classes(result, ax=None, *, title: str | None = None, legend: bool = True):
    """Cells coloured by class: Q_yes, Q_no, Q_? (with region outlines)."""
    res = _result(result)
    ax = _ax(ax)
    colours = np.array([CLASS_COLOURS[c] for c in res.classes], dtype=object)
    ax.add_collection(PolyCollection(_rects(res), facecolors=colours, edgecolors="white",
                                     linewidths=0.2))
    _draw_regions(ax, res, fill=False, label_text=True, lw=1.8, only=res.dfa_atoms)
    counts = {c: int(np.sum(res.classes == c)) for c in CLASS_COLOURS}
    _frame(ax, res, title or f"Classification for {res.formula!r}, threshold {res.threshold:g}")
    if legend:
        handles = [Patch(facecolor=CLASS_COLOURS[c], label=f"{CLASS_TEXT[c]}: {counts[c]}")
                   for c in ("yes", "maybe", "no")]
        ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=1,
                  fontsize=8, frameon=False)
    return ax


def threshold_segments(result, which: str = "p_low") -> list:
    """Boundary segments of the cells where ``which >= threshold`` (2-D; for p_low: the edge of Q_yes)."""
    res = _result(result)
    bx, by, ind = _raster(res, np.asarray(getattr(res, which), dtype=float) >= res.threshold)
    return _outline_segments(bx, by, ind)


def plot_values(result, which: str = "p_low", ax=None, *, title: str | None = None,
                colorbar: bool = True, cmap: str = "viridis", legend: bool = True):
    """Heat map of a per-cell quantity: ``"p_low"``, ``"p_up"``, ``"p_up_star"`` or ``"error"``.

    With the formula's regions outlined and named and, for the probabilities, the threshold
    contour (dashed): the boundary of the cells with ``which >= threshold``.
    """
    res = _result(result)
    values = np.asarray(getattr(res, which), dtype=float)
    ax = _ax(ax)
    coll = PolyCollection(_rects(res), array=values, cmap=cmap, norm=Normalize(0.0, 1.0),
                          edgecolors="face", linewidths=0.2)
    ax.add_collection(coll)
    _draw_regions(ax, res, fill=False, label_text=True, lw=1.2, only=res.dfa_atoms)
    names = {"p_low": "lower bound p_low", "p_up": "upper bound p_up",
             "p_up_star": "optimal upper bound p_up*", "error": "error p_up* - p_low"}
    if which in _PROBABILITIES:
        segs = threshold_segments(res, which)
        ax.add_collection(LineCollection(segs, colors=THRESHOLD_COLOUR, linewidths=1.6, linestyles="--",
                                         zorder=4, path_effects=[withStroke(linewidth=3.0, foreground="white")]))
        if legend:
            ax.legend(handles=[Line2D([], [], color=THRESHOLD_COLOUR, ls="--", lw=1.6,
                                      label=f"{which} = threshold {res.threshold:g} (contour)")],
                      loc="upper center", bbox_to_anchor=(0.5, -0.13), fontsize=8, frameon=False)
    _frame(ax, res, title or f"{names.get(which, which)} of P(sat) for {res.formula!r}")
    if colorbar:
        ax.figure.colorbar(coll, ax=ax, shrink=0.85, label=names.get(which, which))
    return ax


#: The colours of the Q_yes cells' assumption margins, one per factor of B (light: kept only at B, dark: at 4 B).
MARGIN_COLOURS = ("#ffffcc", "#d9f0a3", "#addd8e", "#78c679", "#31a354", "#006837")
_MARGIN_NO, _MARGIN_MAYBE = "#fcbba1", "#f0f0f0"  # Q_no cells (any margin), Q_? cells (none)


def _margin_scales(res: ResultFile) -> tuple:
    scales = (res.diagnostics.get("margins") or {}).get("scales")
    return tuple(float(v) for v in scales) if scales else (1.0, 1.25, 1.5, 2.0, 3.0, 4.0)


def _margin_handles(res: ResultFile) -> list:
    """Legend patches of the margin map: per factor the Q_yes cells kept at least there, then Q_no and Q_?."""
    scales = _margin_scales(res)
    yes = res.classes == "yes"
    b = np.asarray(res.b_margin, float)
    handles = [Patch(facecolor=MARGIN_COLOURS[min(j, len(MARGIN_COLOURS) - 1)], edgecolor="#bdbdbd",
                     label=f"Q_yes up to {s:g} B: {int(np.sum(yes & (b == s)))}") for j, s in enumerate(scales)]
    handles.append(Patch(facecolor=_MARGIN_NO, label=f"Q_no: {int(np.sum(res.classes == 'no'))}"))
    handles.append(Patch(facecolor=_MARGIN_MAYBE, edgecolor="#bdbdbd",
                         label=f"Q_? (no margin): {int(np.sum(res.classes == 'maybe'))}"))
    return handles


def plot_margins(result, ax=None, *, title: str | None = None, legend: bool = True):
    """Map of the assumption margins ``b_margin`` (docs/margins.md): each Q_yes cell coloured by the largest
    factor beta of B at which the run's controller keeps it in Q_yes (light: only at B; dark: up to 4 B);
    Q_no cells pale red, Q_? cells grey; with the formula's regions outlined.

    Raises
    ------
    InvalidInputError
        The result has no margins (run with margins off, known dynamics, the GP route).
    """
    res = _result(result)
    if res.b_margin is None:
        raise InvalidInputError("the result has no assumption margins (b_margin): run with margins on "
                                "(the default; not computed for known dynamics and error_bound 'chowdhury')")
    scales = _margin_scales(res)
    b = np.asarray(res.b_margin, float)
    idx = np.searchsorted(np.asarray(scales), np.nan_to_num(b, nan=scales[0]))
    colours = np.array([MARGIN_COLOURS[min(int(j), len(MARGIN_COLOURS) - 1)] for j in idx], dtype=object)
    colours[res.classes == "no"] = _MARGIN_NO
    colours[res.classes == "maybe"] = _MARGIN_MAYBE
    ax = _ax(ax)
    ax.add_collection(PolyCollection(_rects(res), facecolors=colours, edgecolors="white", linewidths=0.2))
    _draw_regions(ax, res, fill=False, label_text=True, lw=1.8, only=res.dfa_atoms)
    _frame(ax, res, title or "Assumption margin: largest beta with the cell Q_yes at beta B")
    if legend:
        ax.legend(handles=_margin_handles(res), loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2,
                  fontsize=7, frameon=False)
    return ax


_END_STYLES = {  # outcome code of validate.simulate -> marker style (legend order)
    SATISFIED: dict(marker="*", s=110, c="white", edgecolors="black", linewidths=0.9),
    VIOLATED: dict(marker="X", s=70, c="black", edgecolors="white", linewidths=0.9),
    RUNNING: dict(marker="o", s=30, c="#969696", edgecolors="black", linewidths=0.6),
}


def seam_segments(path, result) -> list:
    """``path`` ((k, d) states) cut into pieces that do not jump across a periodic seam.

    A periodic coordinate wraps (docs/periodic.md), so a step from just below ``upper`` to just
    above ``lower`` is a short move, not a line across the whole plot. The path is cut between
    two consecutive states whose periodic coordinate changes by more than half the period (a
    true step of the system moves less than that: the residual convention of docs/periodic.md
    assumes |g + v| < T/2 per step). Without periodic dimensions: ``[path]``.
    """
    res = _result(result, dims=None)
    p = np.asarray(path, dtype=float)
    if res.periodic is None or not any(res.periodic) or len(p) < 2:
        return [p]
    per = np.flatnonzero(np.asarray(res.periodic, dtype=bool)[: p.shape[1]])
    half = 0.5 * (np.asarray(res.space_upper, dtype=float)[per] - np.asarray(res.space_lower, dtype=float)[per])
    jump = np.any(np.abs(np.diff(p[:, per], axis=0)) > half, axis=1)
    cuts = np.flatnonzero(jump) + 1
    return np.split(p, cuts)


def plot_trajectories(result, trajectories, ax=None, *, title: str | None = None,
                      max_paths: int = 40):
    """Simulated paths over the classification, with start (o) and end (*) markers."""
    res = _result(result)
    ax = plot_classes(res, ax, legend=False, title=title or "Simulated runs of the true system")
    paths = trajectories.paths[:max_paths]
    outcome = np.asarray(trajectories.outcome)[:max_paths]
    segments = [seg for p in paths for seg in seam_segments(p, res)]
    ax.add_collection(LineCollection([s for s in segments if len(s) > 1], colors="black",
                                     linewidths=0.8, alpha=0.8))
    starts = np.array([p[0] for p in paths])
    ends = np.array([p[-1] for p in paths])
    ax.plot(starts[:, 0], starts[:, 1], "o", ms=4, mfc="white", mec="black", ls="none", zorder=3)
    # End markers differ by shape and use no class colour (red stars vanished on red Q_no cells):
    # satisfied = white star, violated = black cross, undecided at the cap = grey dot.
    for code, style in _END_STYLES.items():
        sel = outcome == code
        if np.any(sel):
            ax.scatter(ends[sel, 0], ends[sel, 1], zorder=4, **style)
    handles = [
        Line2D([], [], color="black", lw=0.8, label="path"),
        Line2D([], [], marker="o", mfc="white", mec="black", ls="none", label="start"),
    ] + [Line2D([], [], marker=st["marker"], mfc=st["c"], mec=st["edgecolors"], ms=9, ls="none", label=lab)
         for lab, st in zip(("end: satisfied", "end: violated", "end: undecided (step cap)"), _END_STYLES.values())
         ] + [Patch(facecolor=CLASS_COLOURS[c], label=CLASS_TEXT[c]) for c in ("yes", "maybe", "no")]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2,
              fontsize=7.5, frameon=False)
    return ax


def _end_markers(ax, starts, ends, outcome) -> list:
    """Start (o) and end markers (:data:`_END_STYLES`) of paths already projected to 2-D; the legend's handles."""
    ax.plot(starts[:, 0], starts[:, 1], "o", ms=4, mfc="white", mec="black", ls="none", zorder=3)
    for code, style in _END_STYLES.items():
        sel = outcome == code
        if np.any(sel):
            ax.scatter(ends[sel, 0], ends[sel, 1], zorder=4, **style)
    return [Line2D([], [], color="black", lw=0.8, label="path"),
            Line2D([], [], marker="o", mfc="white", mec="black", ls="none", label="start")] + [
        Line2D([], [], marker=st["marker"], mfc=st["c"], mec=st["edgecolors"], ms=9, ls="none", label=lab)
        for lab, st in zip(("end: satisfied", "end: violated", "end: undecided (step cap)"), _END_STYLES.values())]


def plot_trajectory_panels(result, trajectories, *, pairs=None, max_paths: int = 40, fig=None,
                           suptitle: str | None = None):
    """Simulated paths of a result of any dimension, as panels (``simulate``'s ``trajectories.png``
    outside 2-D, where :func:`plot_trajectories` draws them over the classification).

    1-D: one panel, the state ``x_1`` against the step, over the formula's regions (shaded bands).
    d >= 2: one panel per pair of coordinates, the paths projected on it, over the projections of
    the formula's regions (the cells labelled with them, shaded); a projection mixes cells, so no
    classes are drawn. Paths are cut where they cross a periodic seam (:func:`seam_segments`).

    Parameters
    ----------
    result : a result (any dimension)
    trajectories : validate.Trajectories with recorded paths (``simulate(..., record=True)``)
    pairs : sequence of (i, j), optional
        Coordinates (0-based) of the panels; default every pair of the first four coordinates (at
        most 6 panels).
    max_paths : int

    Returns
    -------
    Figure
    """
    res = _result(result, dims=None)
    d = res.cells_lower.shape[1]
    paths = [np.asarray(p, dtype=float) for p in trajectories.paths[:max_paths]]
    if not paths or any(p.ndim != 2 or p.shape[0] == 0 or p.shape[1] != d for p in paths):
        raise DimensionError(f"trajectories must hold recorded paths of shape (T + 1, {d}) (simulate(..., "
                             "record=True))")
    outcome = np.asarray(trajectories.outcome)[: len(paths)]
    atoms = [a for a in res.dfa_atoms if any(a in lab for lab in res.labels)]
    colours = {a: _REGION_COLOURS[k % len(_REGION_COLOURS)] for k, a in enumerate(atoms)}
    region_handles = [Patch(facecolor=colours[a], alpha=0.35, label=a) for a in atoms]
    if d == 1:
        fig = fig or plt.figure(figsize=(6.4, 4.6), constrained_layout=True)
        ax = fig.subplots()
        for a in atoms:
            has = np.array([a in lab for lab in res.labels])
            for lo, up in zip(res.cells_lower[has, 0], res.cells_upper[has, 0]):
                ax.axhspan(lo, up, color=colours[a], alpha=0.25, lw=0)
        segments = [np.c_[np.arange(len(p)), p[:, 0]] for p in paths]
        ax.add_collection(LineCollection([s for s in segments if len(s) > 1], colors="black", linewidths=0.8,
                                         alpha=0.8))
        starts = np.array([s[0] for s in segments])
        ends = np.array([s[-1] for s in segments])
        handles = _end_markers(ax, starts, ends, outcome)
        ax.set_xlim(0, max(1, max(len(p) for p in paths) - 1))
        ax.set_ylim(res.space_lower[0], res.space_upper[0])
        ax.set_xlabel("step")
        ax.set_ylabel(_axis_text(res, 0, tex=True))
        fig.legend(handles=handles + region_handles, loc="outside lower center", ncol=3, fontsize=7.5, frameon=False)
        fig.suptitle(suptitle or f"Simulated runs of the true system for {res.formula!r}", fontsize=11)
        return fig
    if pairs is None:
        first = list(range(min(d, 4)))
        pairs = [(i, j) for k, i in enumerate(first) for j in first[k + 1:]]
    pairs = [tuple(int(v) for v in pr) for pr in pairs]
    if not pairs or any(len(pr) != 2 or pr[0] == pr[1] or not all(0 <= v < d for v in pr) for pr in pairs):
        raise DimensionError(f"pairs must be pairs (i, j) of different coordinates in [0, {d}); got {pairs!r}")
    ncol = min(3, len(pairs))
    nrow = -(-len(pairs) // ncol)
    fig = fig or plt.figure(figsize=(3.8 * ncol + 0.6, 3.8 * nrow + 0.9), constrained_layout=True)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    cut = [seg for p in paths for seg in seam_segments(p, res)]
    handles = []
    for ax, (i, j) in zip(axes, pairs):
        for a in atoms:  # the region's cells projected on (i, j): each distinct rectangle once
            has = np.array([a in lab for lab in res.labels])
            r = np.unique(np.c_[res.cells_lower[has][:, [i, j]], res.cells_upper[has][:, [i, j]]], axis=0)
            rects = np.stack([r[:, [0, 1]], r[:, [2, 1]], r[:, [2, 3]], r[:, [0, 3]]], axis=1)
            ax.add_collection(PolyCollection(rects, facecolors=colours[a], alpha=0.2, edgecolors="none"))
        ax.add_collection(LineCollection([s[:, [i, j]] for s in cut if len(s) > 1], colors="black",
                                         linewidths=0.8, alpha=0.8))
        handles = _end_markers(ax, np.array([p[0, [i, j]] for p in paths]), np.array([p[-1, [i, j]] for p in paths]),
                               outcome)
        ax.set_xlim(res.space_lower[i], res.space_upper[i])
        ax.set_ylim(res.space_lower[j], res.space_upper[j])
        ax.set_xlabel(_axis_text(res, i, tex=True))
        ax.set_ylabel(_axis_text(res, j, tex=True))
    for ax in axes[len(pairs):]:
        ax.set_visible(False)
    fig.legend(handles=handles + region_handles, loc="outside lower center", ncol=4, fontsize=7.5, frameon=False)
    fig.suptitle(suptitle or f"Simulated runs of the true system for {res.formula!r} (projections; regions: "
                 "their cells projected)", fontsize=10)
    return fig


def plot_eta_sweep(results, etas, *, which: str = "p_low", fig=None, suptitle: str | None = None):
    """One ``which`` map per eta value, side by side, with one shared colour bar.

    Parameters
    ----------
    results : sequence of results (same partition)
    etas : sequence of str or float, the panel captions (e.g. ``"0.96 sigma"``)
    """
    results = [_result(r) for r in results]
    if len(results) != len(etas):
        raise DimensionError(f"etas must have one entry per result ({len(results)}); got {len(etas)}")
    ncol = min(5, len(results))
    nrow = -(-len(results) // ncol)
    fig = fig or plt.figure(figsize=(3.3 * ncol + 0.8, 3.4 * nrow), constrained_layout=True)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    for ax, res, eta in zip(axes, results, etas):
        plot_values(res, which, ax, colorbar=False, legend=False,
                    title=f"eta = {eta}: mean {which} {np.mean(getattr(res, which)):.3f}")
    for ax in axes[len(results):]:
        ax.set_visible(False)
    sm = plt.cm.ScalarMappable(norm=Normalize(0.0, 1.0), cmap="viridis")
    fig.colorbar(sm, ax=axes[: len(results)].tolist(), shrink=0.8, label=which)
    fig.suptitle(suptitle or f"Effect of eta on {which} for {results[0].formula!r}", fontsize=11)
    return fig


# --------------------------------------------------------------------------- 1-D
def plot_bounds_1d(result, ax=None, *, title: str | None = None, legend: bool = True):
    """1-D results: p_low and p_up against x over the cells' classes, the threshold and the regions.

    Each cell is a band coloured by its class (Q_yes / Q_? / Q_no); the bracket [p_low, p_up]
    is shaded between the two step lines; the regions are bars with their names below 0.
    """
    res = _result(result, dims=1)
    ax = _ax(ax)
    order = np.argsort(res.cells_lower[:, 0])
    lo, up = res.cells_lower[order, 0], res.cells_upper[order, 0]
    edges = np.r_[lo, up[-1]]
    colours = [CLASS_COLOURS[c] for c in res.classes[order]]
    bands = np.stack([np.c_[lo, np.zeros_like(lo)], np.c_[up, np.zeros_like(lo)],
                      np.c_[up, np.ones_like(lo)], np.c_[lo, np.ones_like(lo)]], axis=1)
    ax.add_collection(PolyCollection(bands, facecolors=colours, alpha=0.28, edgecolors="white", linewidths=0.3))
    p_low, p_up = res.p_low[order], res.p_up[order]
    ax.stairs(p_up, edges, baseline=p_low, fill=True, color="#bdbdbd", alpha=0.6, label="[p_low, p_up]")
    ax.stairs(p_low, edges, color="black", lw=1.6, label="p_low", baseline=None)
    ax.stairs(p_up, edges, color="#3182bd", lw=1.2, ls="--", label="p_up", baseline=None)
    ax.axhline(res.threshold, color=THRESHOLD_COLOUR, lw=1.2, ls=":", label=f"threshold {res.threshold:g}")
    atoms = sorted({a for lab in res.labels for a in lab})
    for k, atom in enumerate(atoms):  # each region: bars where its cells are, named once per piece
        colour = _REGION_COLOURS[k % len(_REGION_COLOURS)]
        has = np.array([atom in res.labels[q] for q in order])
        y = -0.05 - 0.07 * k
        starts = np.flatnonzero(has & ~np.r_[False, has[:-1]])
        ends = np.flatnonzero(has & ~np.r_[has[1:], False])
        for i, j in zip(starts, ends):
            ax.plot([lo[i], up[j]], [y, y], color=colour, lw=5, solid_capstyle="butt")
            ax.text(0.5 * (lo[i] + up[j]), y, atom, ha="center", va="center", fontsize=8, weight="bold",
                    color="black", zorder=6, bbox=dict(boxstyle="round,pad=0.1", fc="white", ec=colour, alpha=0.95))
    ax.set_xlim(res.space_lower[0], res.space_upper[0])
    ax.set_ylim(-0.05 - 0.07 * max(len(atoms), 1) - 0.02, 1.04)
    ax.set_yticks(np.linspace(0.0, 1.0, 6))  # the region bars below 0 are not probabilities
    ax.set_xlabel(_axis_text(res, 0, tex=True))
    ax.set_ylabel("P(formula)")
    ax.set_title(title or f"Bounds and classes for {res.formula!r}", fontsize=10)
    if legend:
        counts = {c: int(np.sum(res.classes == c)) for c in CLASS_COLOURS}
        handles, _ = ax.get_legend_handles_labels()
        handles += [Patch(facecolor=CLASS_COLOURS[c], alpha=0.5, label=f"{CLASS_TEXT[c]}: {counts[c]}")
                    for c in ("yes", "maybe", "no")]
        ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=8,
                  frameon=False)
    return ax


# --------------------------------------------------------------------------- 3-D and more: slices
def _axis_text(res: ResultFile, j: int, tex: bool = False) -> str:
    """The name of coordinate ``j`` (0-based): its ``[space].names`` entry, else ``x_{j+1}``."""
    if res.dim_names is not None:
        return res.dim_names[j]
    k = j + 1
    return (f"$x_{k}$" if k < 10 else f"$x_{{{k}}}$") if tex else f"x_{k}"


def resolve_slice(slice, lower, upper, names=None) -> dict:
    """Check a slice specification and return ``{coordinate (0-based): value}``.

    Parameters
    ----------
    slice : dict or None
        Coordinates to fix, ``{key: value}``. A key is a dimension name (``[space].names``),
        ``"x3"`` / ``"x_3"`` (dimensions numbered from 1, as in the data file's columns), or an
        int: the 0-based coordinate index, like ``axis``.
    lower, upper : (d,) float arrays
        The set X; every value must lie in it.
    names : sequence of d str, optional

    Raises
    ------
    InvalidInputError
        An unknown key, a value outside X, more than ``d - 2`` fixed coordinates (two are
        drawn), or a state space of dimension < 3.
    """
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    d = lower.size
    if not slice:
        return {}
    if not isinstance(slice, Mapping):
        raise InvalidInputError(f"slice must be a dict {{dimension: value}}, e.g. {{'x3': 0.5}}; got {slice!r}")
    if d < 3:
        raise InvalidInputError(f"slice applies to state spaces of dimension >= 3; got dimension {d} "
                                f"(the figures draw both coordinates)")
    names = None if names is None else tuple(names)
    valid = f"x1 .. x{d}" + (f" or {', '.join(names)}" if names else "")
    out = {}
    for key, value in slice.items():
        j = None
        if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
            j = int(key) if 0 <= int(key) < d else None
        elif isinstance(key, str):
            if names is not None and key in names:
                j = names.index(key)
            else:
                m = re.fullmatch(r"x_?(\d+)", key.strip())
                j = int(m.group(1)) - 1 if m and 1 <= int(m.group(1)) <= d else None
        if j is None:
            raise InvalidInputError(f"slice: {key!r} is not a dimension; use {valid}"
                                    + (" (or an int: the 0-based coordinate index)" if not isinstance(key, str) else ""))
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise InvalidInputError(f"slice: {key} must be a number; got {value!r}") from None
        where = f"dimension {j + 1}" + (f" ({names[j]})" if names else "")
        if not (lower[j] <= v <= upper[j]):
            raise InvalidInputError(f"slice: {key} = {v:g} lies outside X, [{lower[j]:g}, {upper[j]:g}] in {where}")
        if j in out:
            raise InvalidInputError(f"slice: {where} is given twice")
        out[j] = v
    if len(out) > d - 2:
        raise InvalidInputError(f"slice fixes {len(out)} of {d} dimensions; at most {d - 2} (two are drawn)")
    return out


def _interval_counts(res: ResultFile, j: int, has: np.ndarray):
    """Midpoints of coordinate ``j``'s grid intervals and, per interval, how many cells ``has`` meet it."""
    bps = np.unique(np.r_[res.cells_lower[:, j], res.cells_upper[:, j]])
    i0 = np.searchsorted(bps, res.cells_lower[has, j])  # cell faces are breakpoints: exact
    i1 = np.searchsorted(bps, res.cells_upper[has, j])
    diff = np.zeros(bps.size, dtype=np.int64)
    np.add.at(diff, i0, 1)
    np.add.at(diff, i1, -1)  # a cell meets the intervals i0 .. i1 - 1
    return 0.5 * (bps[:-1] + bps[1:]), np.cumsum(diff)[:-1]


def best_slice_value(res, j: int) -> float:
    """The default value of coordinate ``j`` in figures of dimension >= 3 (the rule of :func:`plot_slices`).

    The midpoint of the grid interval of coordinate ``j`` met by the most Q_yes cells; ties (or no
    Q_yes cell) go to the most Q_? cells, then the most cells inside the formula's regions, then
    the interval nearest the centre of X (the lower one first).
    """
    res = _result(res, dims=None)
    mids, yes = _interval_counts(res, j, res.classes == "yes")
    _, maybe = _interval_counts(res, j, res.classes == "maybe")
    _, inside = _interval_counts(res, j, res.label_letters != 0)
    dist = np.abs(mids - 0.5 * (res.space_lower[j] + res.space_upper[j]))
    order = np.lexsort((np.arange(mids.size), dist, -inside, -maybe, -yes))  # last key sorts first
    return float(mids[order[0]])


def _slice_view(res: ResultFile, point: np.ndarray, drawn: list) -> ResultFile:
    """The 2-D result on the plane through ``point`` spanned by the coordinates ``drawn``."""
    d = res.cells_lower.shape[1]
    fixed = [j for j in range(d) if j not in drawn]
    lo, up = res.cells_lower, res.cells_upper
    top = np.isclose(point, res.space_upper)
    meets = np.all((lo[:, fixed] <= point[fixed]) & ((point[fixed] < up[:, fixed]) | top[fixed]), axis=1)
    q = np.flatnonzero(meets)
    fixed_text = ", ".join(f"{_axis_text(res, j)} = {point[j]:.3g}" for j in fixed)
    return dataclasses.replace(
        res, space_lower=res.space_lower[drawn], space_upper=res.space_upper[drawn],
        cells_lower=lo[q][:, drawn], cells_upper=up[q][:, drawn], label_letters=res.label_letters[q],
        labels=tuple(res.labels[i] for i in q), strategy=res.strategy[q], p_low=res.p_low[q], p_up=res.p_up[q],
        p_up_star=res.p_up_star[q], error=res.error[q], classes=res.classes[q],
        strategy_by_time=None if res.strategy_by_time is None else res.strategy_by_time[:, q],
        dim_names=None if res.dim_names is None else tuple(res.dim_names[j] for j in drawn),
        b_margin=None if getattr(res, "b_margin", None) is None else res.b_margin[q],
        parameters={**res.parameters, "_axis_names": tuple(_axis_text(res, j, tex=True) for j in drawn),
                    "_slice": fixed_text, "_cells": q})


def slice_result(result, at: float, *, axis: int = 2, rest=None) -> ResultFile:
    """The 2-D result on the plane ``x_{axis+1} = at``: the cells it meets, drawn in the other two axes.

    Parameters
    ----------
    result : a result of dimension d >= 3
    at : float, the value of coordinate ``axis`` (a cell meets the plane if lower <= at < upper,
        or at == upper at the upper end of X)
    axis : int, the sliced coordinate (0-based)
    rest : (d,) float array, optional
        For d > 3, the values of the coordinates other than the two drawn and ``axis``
        (default: the centre of X; :func:`plot_slices` chooses them by :func:`best_slice_value`).

    Returns
    -------
    ResultFile
        Cells restricted to the slice, with 2-D boxes.
    """
    res = _result(result, dims=None)
    d = res.cells_lower.shape[1]
    if d < 3:
        raise DimensionError(f"slice_result needs a state space of dimension >= 3; got {d}")
    if not 0 <= axis < d:
        raise DimensionError(f"axis must be in [0, {d}); got {axis}")
    centre = 0.5 * (res.space_lower + res.space_upper) if rest is None else np.asarray(rest, float)
    if centre.shape != (d,):
        raise DimensionError(f"rest must have shape ({d},); got {centre.shape}")
    point = centre.copy()
    point[axis] = at
    return _slice_view(res, point, [j for j in range(d) if j != axis][:2])


def _slice_values(res: ResultFile, axis: int, n_slices: int, best: float | None = None) -> np.ndarray:
    """Midpoints of ``n_slices`` intervals of the grid along ``axis``, evenly spread; ``best`` (a
    midpoint) replaces the nearest of them when it is not among them."""
    bps = np.unique(np.r_[res.cells_lower[:, axis], res.cells_upper[:, axis]])
    mids = 0.5 * (bps[:-1] + bps[1:])
    pick = np.unique(np.round(np.linspace(0, len(mids) - 1, min(n_slices, len(mids)))).astype(int))
    values = mids[pick]
    if best is not None and not np.any(values == best):
        values[int(np.argmin(np.abs(values - best)))] = best
    return np.sort(values)


def plot_slices(result, kind: str = "classes", *, n_slices: int = 4, axis: int = 2, slice=None, fig=None,
                suptitle: str | None = None):
    """Panels of 2-D slices of a result of dimension >= 3, one per value of coordinate ``axis``.

    Which slices (the default rule): the panels draw the first two coordinates other than
    ``axis``; ``axis`` takes ``n_slices`` values at the midpoints of evenly spread grid intervals,
    and the one nearest to :func:`best_slice_value` is moved onto it; every further coordinate
    (d > 3) is fixed at its :func:`best_slice_value`: through the grid interval met by the most
    Q_yes cells (ties: most Q_? cells, most cells inside the formula's regions, nearest the centre
    of X). So the Q_yes cells appear in the figure whenever there are any.

    Parameters
    ----------
    kind : "classes", "partition", "b_margin" (:func:`plot_margins`), or a per-cell value ("p_low", "p_up",
        "p_up_star", "error")
    n_slices : int, number of panels
    axis : int, the sliced coordinate (0-based; default the third)
    slice : dict, optional
        Coordinates to fix instead, ``{"x4": 0.0}`` or by ``[space].names`` (see
        :func:`resolve_slice`). With ``d - 2`` of them fixed, one panel shows the other two; with
        fewer, the panels run over ``axis`` (or, if ``axis`` is fixed, over the first coordinate
        after the two drawn) and the rest follow the default rule.

    Returns
    -------
    Figure
    """
    res = _result(result, dims=None)
    d = res.cells_lower.shape[1]
    if d < 3:
        raise DimensionError(f"plot_slices needs a state space of dimension >= 3; got {d} (use plot_classes)")
    if not 0 <= axis < d:
        raise DimensionError(f"axis must be in [0, {d}); got {axis}")
    fixed = resolve_slice(slice, res.space_lower, res.space_upper, res.dim_names)
    free = [j for j in range(d) if j not in fixed]
    if axis in fixed or len(free) == 2:
        drawn = free[:2]
        axis = free[2] if len(free) > 2 else None
    else:
        drawn = [j for j in free if j != axis][:2]
    point = 0.5 * (res.space_lower + res.space_upper)
    for j in free:
        if j not in drawn and j != axis:
            point[j] = best_slice_value(res, j)
    for j, v in fixed.items():
        point[j] = v
    values = [None] if axis is None else _slice_values(res, axis, n_slices, best_slice_value(res, axis))
    ncol = min(4, len(values))
    nrow = -(-len(values) // ncol)
    fig = fig or plt.figure(figsize=(3.4 * ncol + 0.8, 3.6 * nrow + 0.6), constrained_layout=True)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    for ax, at in zip(axes, values):
        p = point.copy()
        if at is not None:
            p[axis] = at
        view = _slice_view(res, p, drawn)
        title = view.parameters["_slice"]
        if kind == "classes":
            plot_classes(view, ax, title=title, legend=False)
        elif kind == "b_margin":
            plot_margins(view, ax, title=title, legend=False)
        elif kind == "partition":
            plot_partition(view, ax, title=title)
            if ax.get_legend() is not None:
                ax.get_legend().remove()
        else:
            plot_values(view, kind, ax, title=title, colorbar=False, legend=False,
                        cmap="magma" if kind == "error" else "viridis")
    for ax in axes[len(values):]:
        ax.set_visible(False)
    shown = axes[: len(values)].tolist()
    if kind == "classes":
        counts = {c: int(np.sum(res.classes == c)) for c in CLASS_COLOURS}
        fig.legend(handles=[Patch(facecolor=CLASS_COLOURS[c], label=f"{CLASS_TEXT[c]}: {counts[c]} of {res.n_cells}")
                            for c in ("yes", "maybe", "no")], loc="outside lower center", ncol=3, fontsize=8,
                   frameon=False)
    elif kind == "b_margin":
        fig.legend(handles=_margin_handles(res), loc="outside lower center", ncol=4, fontsize=8, frameon=False)
    elif kind != "partition":
        sm = plt.cm.ScalarMappable(norm=Normalize(0.0, 1.0), cmap="magma" if kind == "error" else "viridis")
        fig.colorbar(sm, ax=shown, shrink=0.8, label=kind)
        if kind in _PROBABILITIES:
            fig.legend(handles=[Line2D([], [], color=THRESHOLD_COLOUR, ls="--", lw=1.6,
                                       label=f"{kind} = threshold {res.threshold:g} (contour)")],
                       loc="outside lower center", fontsize=8, frameon=False)
    what = {"classes": "Classification", "partition": "Partition", "b_margin": "Assumption margin"}.get(kind, kind)
    how = "slice" if axis is None else f"slices {_axis_text(res, axis)} = const"
    rest = [j for j in range(d) if j not in drawn and j != axis and j not in fixed]
    fig.suptitle(suptitle or f"{what} for {res.formula!r}: {how}"
                 + (" (further coordinates through the most Q_yes cells)" if rest else ""), fontsize=11)
    return fig


def figure_names(result, *, trajectories: bool = False) -> list:
    """The names (file stems) of the PNGs :func:`save_figures` writes for ``result``, in its order: 1-D
    ``bounds``; else ``partition``, ``classes``, ``p_low``, ``error``, ``b_margin`` (where the result has
    assumption margins) and, with ``trajectories`` in 2-D, ``trajectories``."""
    res = _result(result, dims=None)
    d = res.cells_lower.shape[1]
    if d == 1:
        return ["bounds"]
    margins = getattr(res, "b_margin", None) is not None  # b_margin.png where the run computed margins
    return (["partition", "classes", "p_low", "error"] + (["b_margin"] if margins else [])
            + (["trajectories"] if trajectories and d == 2 else []))


def save_figures(result, out_dir, *, trajectories=None, prefix: str = "", dpi: int = 130, slice=None,
                 only=None) -> list:
    """Write the standard PNGs for a result of any dimension (see the module docstring).

    1-D: ``bounds.png``. 2-D: ``partition``, ``classes``, ``p_low``, ``error``, ``b_margin`` (where the
    result has assumption margins; :func:`plot_margins`) and ``trajectories`` (if given). 3-D and more:
    the same but trajectories as panels of slices, where ``slice`` fixes coordinates (:func:`plot_slices`).
    ``only``: the names (:func:`figure_names`) to write, e.g. one per process to draw them in parallel (each
    figure's bytes do not depend on the others); None: all.

    Returns
    -------
    list of Path
        The files written.
    """
    res = _result(result, dims=None)
    resolve_slice(slice, res.space_lower, res.space_upper, res.dim_names)  # a bad slice fails before any file
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    d = res.cells_lower.shape[1]
    written = []
    wanted = set(figure_names(res, trajectories=trajectories is not None) if only is None else only)
    if d == 1:
        if "bounds" in wanted:
            fig, ax = plt.subplots(figsize=(6.4, 4.6), constrained_layout=True)
            plot_bounds_1d(res, ax)
            written.append(_save(fig, out / f"{prefix}bounds.png", dpi))
        return written
    margins = getattr(res, "b_margin", None) is not None  # b_margin.png where the run computed margins
    if d >= 3:
        for kind in ("partition", "classes", "p_low", "error") + (("b_margin",) if margins else ()):
            if kind in wanted:
                written.append(_save(plot_slices(res, kind, slice=slice), out / f"{prefix}{kind}.png", dpi))
        return written
    jobs = [("partition", lambda ax: plot_partition(res, ax)),
            ("classes", lambda ax: plot_classes(res, ax)),
            ("p_low", lambda ax: plot_values(res, "p_low", ax)),
            ("error", lambda ax: plot_values(res, "error", ax, cmap="magma"))]
    if margins:
        jobs.append(("b_margin", lambda ax: plot_margins(res, ax)))
    if trajectories is not None:
        jobs.append(("trajectories", lambda ax: plot_trajectories(res, trajectories, ax)))
    for name, draw in jobs:
        if name not in wanted:
            continue
        fig, ax = plt.subplots(figsize=(5.6, 5.2), constrained_layout=True)
        draw(ax)
        written.append(_save(fig, out / f"{prefix}{name}.png", dpi))
    return written


def _save(fig, path: Path, dpi: int) -> Path:
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


# --------------------------------------------------------------------------- calibration
#: Most components drawn by :func:`plot_calibration` (one row each).
CALIBRATION_ROWS = 24


def _calibration_doc(calibration) -> dict:
    """The ``calibration.json`` document of a ``bounds.calibrate.Calibration``, a dict of it, or its path."""
    if isinstance(calibration, (str, Path)):
        import json

        return json.loads(Path(calibration).read_text())
    if isinstance(calibration, Mapping):
        return dict(calibration)
    if hasattr(calibration, "to_dict"):
        return calibration.to_dict()
    raise InvalidInputError(f"calibration must be a Calibration, its dict or the path of calibration.json; got "
                            f"{type(calibration).__name__}")


def plot_calibration(calibration, *, fig=None):
    """The evidence of ``robust-imdp calibrate``, one row per learned component (at most :data:`CALIBRATION_ROWS`).

    Left: the GP log marginal likelihood (per point) and the K-fold cross-validation RMSE against the
    lengthscale, their optima and the suggested lengthscale. Middle: the certified minimum norm against the
    lengthscale (the lower bound on B; refuted below it), the suggested lengthscale marked. Right: held-out
    violations of the certified bound against B, the minimum norm and the suggested B marked. The footer
    says what the numbers do not prove.

    Parameters
    ----------
    calibration : bounds.calibrate.Calibration, its ``to_dict()``, or the path of ``calibration.json``
    fig : matplotlib Figure, optional

    Returns
    -------
    matplotlib Figure
    """
    from matplotlib.ticker import NullFormatter

    doc = _calibration_doc(calibration)
    comps = doc.get("components", [])[:CALIBRATION_ROWS]
    if not comps:
        raise InvalidInputError("the calibration has no learned component to draw")
    rows = len(comps)
    if fig is None:
        fig = plt.figure(figsize=(13.0, 2.6 * rows + 0.6), constrained_layout=True)
    axes = fig.subplots(rows, 3, squeeze=False)
    for r, c in enumerate(comps):
        curves, held = c["lengthscale_curves"], c["held_out"]
        grid = np.asarray(curves["grid"], float)
        l_sugg = np.atleast_1d(np.asarray(c["suggested"]["lengthscale"], float))
        name = f"mode {c['mode']}, component {c['component']}"
        ax = axes[r, 0]
        ax.semilogx(grid, curves["cv_rmse"], "o-", color="#3182bd", ms=3, label="CV RMSE (left)")
        ax.set_ylabel("CV RMSE", color="#3182bd")
        tw = ax.twinx()
        tw.semilogx(grid, curves["log_likelihood_per_point"], "s-", color="#e6550d", ms=3,
                    label="log likelihood / point (right)")
        tw.set_ylabel("log lik. / point", color="#e6550d")
        ax.axvline(curves["cv_optimum"], color="#3182bd", ls="--", lw=1)
        ax.axvline(curves["likelihood_optimum"], color="#e6550d", ls="--", lw=1)
        ax.axvline(float(np.min(l_sugg)), color="black", lw=1.4, label="suggested")
        ax.set_xlabel("lengthscale")
        ax.set_title(f"{name}: lengthscale", fontsize=9)
        if r == 0:
            h1, l1 = ax.get_legend_handles_labels()
            h2, l2 = tw.get_legend_handles_labels()
            ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="best")
        ax = axes[r, 1]
        ax.loglog(grid, np.maximum(np.asarray(curves["min_norm"], float), 1e-12), "o-", color="#636363", ms=3,
                  label="certified minimum norm")
        ax.axvline(float(np.min(l_sugg)), color="black", lw=1.4)
        ax.plot([float(np.min(l_sugg))], [max(c["min_norm"]["value"], 1e-12)], "D", color="black", ms=5,
                label=f"at the suggestion: {c['min_norm']['value']:.3g}")
        ax.set_xlabel("lengthscale")
        ax.set_ylabel("minimum norm")
        ax.set_title(f"{name}: B below the curve is refuted", fontsize=9)
        ax.legend(fontsize=7, loc="upper center")
        ax = axes[r, 2]
        k = int(held["evaluated"])
        B = np.asarray(held["rkhs_bounds"], float)
        v = np.asarray(held["violations"], float)
        ax.semilogx(B[:k], v[:k], "o-", color="#de2d26", ms=3,
                    label=f"held-out violations (of {held['n_held_out']})")
        if k < B.size:
            ax.semilogx(B[k - 1:], np.zeros(B.size - k + 1), ":", color="#de2d26", lw=1,
                        label="0 beyond (the bound widens with B)")
        ax.axvline(c["min_norm"]["value"], color="#636363", ls="--", lw=1, label="minimum norm")
        ax.axvline(c["suggested"]["rkhs_bound"], color="black", lw=1.4,
                   label=f"suggested B = {c['suggested']['rkhs_bound']:g}")
        if held.get("clopper_pearson_upper") is not None:
            ax.plot([], [], " ", label=f"P[new sample outside] <= {held['clopper_pearson_upper']:.3g} "
                                       f"({held['confidence']:g})")
        ax.xaxis.set_minor_formatter(NullFormatter())  # the grid spans a factor 16: minor labels collide
        ax.set_xlabel("B (rkhs_bound)")
        ax.set_ylabel("violations")
        ax.set_title(f"{name}: held-out evidence", fontsize=9)
        ax.legend(fontsize=7, loc="best")
    total = len(doc.get("components", []))
    foot = doc.get("statement", "")
    if total > rows:
        foot = f"(first {rows} of {total} components) " + foot
    fig.suptitle("robust-imdp calibrate: " + foot, fontsize=8, wrap=True)
    return fig


def save_calibration_figure(calibration, path, *, dpi: int = 110) -> Path:
    """Write :func:`plot_calibration` to ``path`` (PNG); returns the path."""
    return _save(plot_calibration(calibration), Path(path), dpi)
