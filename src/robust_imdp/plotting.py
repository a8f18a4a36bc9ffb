"""Figures (the only matplotlib importer; nothing else in the library imports this module).

Every function takes a result (a :class:`~robust_imdp.io.ResultFile`, a pipeline
``Result``, a result dict or a path to ``result.json``) and an optional ``ax``; it draws and
returns the Axes. :func:`save_figures` writes the standard set of PNGs. Only 2-D state spaces
are drawn.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.colors import Normalize
from matplotlib.lines import Line2D
from matplotlib.patches import Patch
from matplotlib.patheffects import withStroke
from scipy import ndimage

from robust_imdp.errors import DimensionError
from robust_imdp.io import ResultFile, as_result_file as _as_result_file

__all__ = [
    "plot_partition",
    "plot_classes",
    "plot_values",
    "plot_trajectories",
    "plot_eta_sweep",
    "save_figures",
]

CLASS_COLOURS = {"yes": "#2ca25f", "maybe": "#fec44f", "no": "#de2d26"}
CLASS_TEXT = {"yes": "Q_yes (p_low >= threshold)", "maybe": "Q_? (undecided)",
              "no": "Q_no (p_up < threshold)"}
_REGION_COLOURS = ["#3182bd", "#636363", "#e6550d", "#756bb1", "#31a354", "#d6616b"]


def _result(result) -> ResultFile:
    res = _as_result_file(result)
    if res.cells_lower.shape[1] != 2:
        raise DimensionError(
            f"plots need a 2-D state space; got cells of dimension {res.cells_lower.shape[1]}"
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
    ax.set_xlabel("$x_1$")
    ax.set_ylabel("$x_2$")
    ax.set_title(title, fontsize=10)


def _region_raster(res: ResultFile, atom: str):
    """Indicator of ``atom`` on the breakpoint grid; returns (bps_x, bps_y, ind (nx, ny))."""
    bx = np.unique(np.r_[res.cells_lower[:, 0], res.cells_upper[:, 0]])
    by = np.unique(np.r_[res.cells_lower[:, 1], res.cells_upper[:, 1]])
    ind = np.zeros((len(bx) - 1, len(by) - 1), dtype=bool)
    has = np.array([atom in lab for lab in res.labels])
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
    return segs


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
                ax.text(cx, cy, atom, ha="center", va="center", fontsize=9, weight="bold",
                        color=colour, bbox=dict(boxstyle="round,pad=0.15", fc="white",
                                                ec="none", alpha=0.7))
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


def plot_values(result, which: str = "p_low", ax=None, *, title: str | None = None,
                colorbar: bool = True, cmap: str = "viridis"):
    """Heat map of a per-cell quantity: ``"p_low"``, ``"p_up"``, ``"p_up_star"`` or ``"error"``."""
    res = _result(result)
    values = np.asarray(getattr(res, which), dtype=float)
    ax = _ax(ax)
    coll = PolyCollection(_rects(res), array=values, cmap=cmap, norm=Normalize(0.0, 1.0),
                          edgecolors="face", linewidths=0.2)
    ax.add_collection(coll)
    _draw_regions(ax, res, fill=False, label_text=False, lw=1.2, only=res.dfa_atoms)
    names = {"p_low": "lower bound p_low", "p_up": "upper bound p_up",
             "p_up_star": "optimal upper bound p_up*", "error": "error p_up* - p_low"}
    _frame(ax, res, title or f"{names.get(which, which)} of P(sat) for {res.formula!r}")
    if colorbar:
        ax.figure.colorbar(coll, ax=ax, shrink=0.85, label=names.get(which, which))
    return ax


def plot_trajectories(result, trajectories, ax=None, *, title: str | None = None,
                      max_paths: int = 40):
    """Simulated paths over the classification, with start (o) and end (*) markers."""
    res = _result(result)
    ax = plot_classes(res, ax, legend=False, title=title or "Simulated runs of the true system")
    paths = trajectories.paths[:max_paths]
    outcome = np.asarray(trajectories.outcome)[:max_paths]
    ax.add_collection(LineCollection([p for p in paths if len(p) > 1], colors="black",
                                     linewidths=0.8, alpha=0.8))
    starts = np.array([p[0] for p in paths])
    ends = np.array([p[-1] for p in paths])
    ax.plot(starts[:, 0], starts[:, 1], "o", ms=4, mfc="white", mec="black", ls="none")
    end_colour = np.where(outcome == 1, "#08519c", np.where(outcome == 2, "#a50f15", "#525252"))
    ax.scatter(ends[:, 0], ends[:, 1], marker="*", s=70, c=end_colour, edgecolors="black",
               linewidths=0.4, zorder=3)
    handles = [
        Line2D([], [], color="black", lw=0.8, label="path"),
        Line2D([], [], marker="o", mfc="white", mec="black", ls="none", label="start"),
        Line2D([], [], marker="*", color="#08519c", ms=9, ls="none", label="end: satisfied"),
        Line2D([], [], marker="*", color="#a50f15", ms=9, ls="none", label="end: violated"),
    ] + [Patch(facecolor=CLASS_COLOURS[c], label=CLASS_TEXT[c]) for c in ("yes", "maybe", "no")]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2,
              fontsize=7.5, frameon=False)
    return ax


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
        plot_values(res, which, ax, colorbar=False,
                    title=f"eta = {eta}: mean {which} {np.mean(getattr(res, which)):.3f}")
    for ax in axes[len(results):]:
        ax.set_visible(False)
    sm = plt.cm.ScalarMappable(norm=Normalize(0.0, 1.0), cmap="viridis")
    fig.colorbar(sm, ax=axes[: len(results)].tolist(), shrink=0.8, label=which)
    fig.suptitle(suptitle or f"Effect of eta on {which} for {results[0].formula!r}", fontsize=11)
    return fig


def save_figures(result, out_dir, *, trajectories=None, prefix: str = "", dpi: int = 130) -> list:
    """Write partition, classes, p_low and error PNGs (and trajectories if given).

    Returns
    -------
    list of Path
        The files written.
    """
    res = _result(result)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [("partition", lambda ax: plot_partition(res, ax)),
            ("classes", lambda ax: plot_classes(res, ax)),
            ("p_low", lambda ax: plot_values(res, "p_low", ax)),
            ("error", lambda ax: plot_values(res, "error", ax, cmap="magma"))]
    if trajectories is not None:
        jobs.append(("trajectories", lambda ax: plot_trajectories(res, trajectories, ax)))
    written = []
    for name, draw in jobs:
        fig, ax = plt.subplots(figsize=(5.6, 5.2), constrained_layout=True)
        draw(ax)
        path = out / f"{prefix}{name}.png"
        fig.savefig(path, dpi=dpi)
        plt.close(fig)
        written.append(path)
    return written
