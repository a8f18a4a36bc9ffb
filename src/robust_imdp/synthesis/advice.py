"""Why cells are undecided, measured: the excess radius and the advice on which lever to pull.

A learned image box must contain ``{f_u(x) + g_u(x) : x in cell}``. Two things make it wide:

* the **spread** of the function itself over the cell (it shrinks with the cell), estimated by the
  range of a data-fitted function ``f_u + g_hat_u`` (:class:`FittedModes`; ``g_hat`` is the
  kernel-ridge fit of the residuals with the problem's SE kernel);
* the **excess**: what the box adds on top of that spread because ``g`` is only known through
  noisy data and ``||g|| <= B`` (it shrinks with more data down to the noise floor, and with B).

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
* **smaller B** (``max(B/2, the data-implied minimum norm)``): the excess scaled by the ratio
  measured on pilot cells bounded with that B;
* **sub-boxes** (only where the run did not split): ``split_tol`` set so the cells with the largest
  Taylor term are halved once per axis; the excess scaled by the ratio measured on pilot cells
  certified on those sub-boxes; the setting names the grid's mean number of sub-boxes per cell (the
  bound stage's cost grows about with it);
* **larger local pools** (only where a mode's cells are certified with weights on their ``k`` nearest
  data points, ``local_points``): all of a mode's points where it has at most :data:`POOL_ALL_MAX`,
  else ``POOL_FACTOR k``; the excess scaled by the ratio measured on the pilot cells bounded with those
  pools.

Each estimate re-abstracts (Thm 1, ``abstraction.abstract``) and re-solves
(``synthesis.synthesize``) with the modified boxes; the bound stage, the expensive one, runs only
on the pilot cells. The estimates are estimates: they say which lever to try, not what a run
will certify (the printed bounds of a run come only from its own bound stage).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from robust_imdp.bounds.fit import FIT_POINTS, FittedModes, _excess_sides, excess_radius, fit_modes  # noqa: F401
from robust_imdp.errors import DimensionError

__all__ = ["FittedModes", "fit_modes", "excess_radius", "Lever", "Advice", "advise", "advice_line", "LEVERS",
           "MAX_CELLS", "MAX_AUTO_TRANSITIONS", "FIT_POINTS", "PILOT_CELLS", "MIN_GAIN"]

#: Undecided cells (at most) bounded for real to calibrate the finer-grid and smaller-B estimates:
#: each once with the smaller B and one of its sub-cells.
PILOT_CELLS = 16
#: The pilot takes at most 1/_PILOT_FRACTION of the grid's cells (so it costs at most about
#: 2/_PILOT_FRACTION of the bound stage), but at least _PILOT_MIN of them.
_PILOT_FRACTION = 16
_PILOT_MIN = 4
#: Largest number of cells an estimate abstracts and solves (the finer grid has 2^d times the cells).
MAX_CELLS = 65536
#: ``advice="auto"`` runs when the finer grid's IMDP has at most about this many listed transitions
#: (cells x modes x 3^d): a few seconds of abstraction and solving at the case studies' speed.
MAX_AUTO_TRANSITIONS = 3_000_000
LEVERS = ("finer grid", "more data", "smaller B", "sub-boxes", "larger local pools")
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
    """The measured advice: baseline Q_yes share, one :class:`Lever` per lever, the winner."""

    baseline_share: float
    levers: tuple = field(default_factory=tuple)
    winner: str | None = None
    seconds: float = 0.0
    note: str = ""

    def to_dict(self) -> dict:
        """JSON-able, without ``seconds`` (the run's ``timings["advice"]`` has the time)."""
        return {"baseline_share": self.baseline_share, "levers": [lv.to_dict() for lv in self.levers],
                "winner": self.winner, "note": self.note}


def advice_line(adv: dict) -> str:
    """One line naming the lever that decides most (from :meth:`Advice.to_dict`)."""
    if not adv:
        return ""
    if adv.get("winner") is None and not adv.get("levers"):
        return f"advice: {adv.get('note', '')}".rstrip()

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
    return text + " (estimated by re-solving with modified image boxes)"


def _share(partition, yes) -> float:
    vol = np.prod(np.asarray(partition.cells_upper) - np.asarray(partition.cells_lower), axis=1)
    return float(np.sum(vol[yes]) / np.sum(vol))


def _q_yes(partition, lower, upper, noise, dfa, threshold, horizon, options) -> float:
    """Q_yes share (volume) of the abstraction of these boxes (Thm 1) after the robust solve."""
    from robust_imdp.abstraction.rows import CellBounds, abstract
    from robust_imdp.synthesis.core import synthesize

    ab = abstract(partition, CellBounds(lower, upper, None), noise, None, **options)
    syn = synthesize(ab.imdp, partition.labels, partition.atoms, dfa, threshold=threshold, horizon=horizon,
                     outside_state=partition.outside_state)
    return _share(partition, np.asarray(syn.p_low) >= threshold)  # Q_yes: p_low >= threshold (Sec. 5)


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


def advise(partition, cell_bounds, fits: FittedModes, noise, dfa, *, threshold: float, horizon=None,
           classes, noise_floor, rkhs_bound: float, min_norm: float = 0.0, abstraction_options=None,
           bound_cells=None, max_cells: int = MAX_CELLS, pilot_cells: int = PILOT_CELLS,
           progress=None, sub_box_t=None, local_pools=None) -> Advice:
    """Estimate the Q_yes share of X that a finer grid, more data, a smaller B, sub-boxes or larger local
    pools would give.

    Parameters
    ----------
    partition : geometry.Partition
        The grid that was solved.
    cell_bounds : abstraction.CellBounds
        Its image boxes ``(n_modes, n_cells, n)`` (as abstracted).
    fits : FittedModes
    noise : noise model of the abstraction
    dfa : dfa.DFA
    threshold, horizon
        As solved.
    classes : (n_cells,) str array
        The solved classes (``"yes"`` / ``"no"`` / ``"maybe"``); the pilot cells are undecided ones.
    noise_floor : (n,) float array
        Excess per side left with dense data: the data-noise bound plus tau.
    rkhs_bound : float
        B; the smaller-B lever uses ``max(B / 2, min_norm)``.
    min_norm : float
        The data-implied minimum RKHS norm (largest over modes and components).
    abstraction_options : dict
        ``eta``, ``eps_rule``, ``combine`` of the run.
    bound_cells : callable ``(lower (k, d), upper (k, d), rkhs_bound[, split_tol[, local_points]]) -> (lower,
        upper)`` of shape ``(n_modes, k, n)``, optional
        The run's bound stage for a few pilot cells; without it the excess ratios are 1 (finer
        grid) and ``B' / B`` (smaller B), and sub-boxes are not estimated.
    sub_box_t : callable ``(lower (k, d), upper (k, d)) -> (k,)``, optional
        Every cell's ``t_max = sum r^2 / l^2`` (``rkhs_model.t_max_up``), from which ``rkhs.split_counts``
        picks the sub-boxes; None: the run cannot split or already does (no sub-box estimate).
    local_pools : (int, int), optional
        ``(k, m)``: the run certifies some mode's cells with weights on ``k`` nearest points, and the
        largest mode has ``m`` points; None: every mode uses all its points (no pool estimate).
    max_cells : int
        An estimate that would abstract more cells than this is skipped (its note says so).
    pilot_cells : int
        Parent cells bounded for real per estimate.
    progress : callable str -> None, optional

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
    open_cells = np.flatnonzero(classes == "maybe")
    if open_cells.size == 0:
        open_cells = np.flatnonzero(classes != "yes")
    if open_cells.size == 0:
        return Advice(base, (), None, time.perf_counter() - t_all, "every cell is in Q_yes")
    flo, fhi = fits.grid_ranges(partition.breakpoints)
    e_lo, e_hi = _excess_sides(lo, hi, flo, fhi)
    # a few undecided cells (a small share of the grid, so the pilot costs a small share of the bound stage)
    pilot = _pilot(open_cells, min(int(pilot_cells), max(_PILOT_MIN, partition.n_cells // _PILOT_FRACTION)))
    ctx = _Context(partition, lo, hi, flo, fhi, e_lo, e_hi, pilot, base, noise, dfa, threshold, horizon,
                   dict(abstraction_options or {}), bound_cells, max_cells)

    def say(text):
        if progress is not None:
            progress(text)

    floor = np.broadcast_to(np.asarray(noise_floor, float), (lo.shape[2],))
    levers = [_finer_grid(ctx, fits, rkhs_bound, say), _more_data(ctx, floor, say),
              _smaller_b(ctx, rkhs_bound, min_norm, say)]
    if sub_box_t is not None:
        levers.append(_sub_boxes(ctx, rkhs_bound, sub_box_t, say))
    if local_pools is not None:
        levers.append(_larger_pools(ctx, rkhs_bound, *local_pools, say))
    est = [lv for lv in levers if lv.gain is not None and lv.gain >= MIN_GAIN]
    winner = max(est, key=lambda lv: lv.gain).name if est else None
    return Advice(base, tuple(levers), winner, time.perf_counter() - t_all)


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
    dfa: object
    threshold: float
    horizon: object
    opts: dict
    bound_cells: object
    max_cells: int

    def q_yes(self, partition, lower, upper) -> float:
        return _q_yes(partition, lower, upper, self.noise, self.dfa, self.threshold, self.horizon, self.opts)

    def pilot_ratio(self, plo, phi) -> np.ndarray:
        """Per (mode, component): the excess ratio of the pilot cells' boxes ``[plo, phi]`` (bounded with a
        lever's setting) over their boxes as solved (:func:`_ratio`)."""
        s_lo, s_hi = _excess_sides(plo, phi, self.flo[:, self.pilot], self.fhi[:, self.pilot])
        return _ratio(np.concatenate([s_lo, s_hi], axis=1),
                      np.concatenate([self.e_lo[:, self.pilot], self.e_hi[:, self.pilot]], axis=1))

    def no_pilot(self) -> str:
        """Why the pilot cells cannot be bounded (no bound stage, or too many cells to re-solve), or ``""``."""
        if self.bound_cells is None:
            return "no pilot bound stage"
        n = self.partition.n_cells
        return f"{n:,} cells > {self.max_cells:,}" if n > self.max_cells else ""


def _finer_grid(ctx: _Context, fits: FittedModes, rkhs_bound: float, say) -> Lever:
    """Lever (a), a finer grid: every cell split in 2^d; the excess scaled by the pilot sub-cells' ratio."""
    from robust_imdp.models.geometry import Partition

    partition, lo, hi, e_lo, e_hi = ctx.partition, ctx.lo, ctx.hi, ctx.e_lo, ctx.e_hi
    t0 = time.perf_counter()
    h2 = np.asarray(partition.cell_size, float) / 2
    n_fine = partition.n_cells * 2 ** partition.dim
    setting = f"cell_size {np.round(h2, 6).tolist()}"
    if n_fine > ctx.max_cells:
        return Lever("finer grid", setting, None, None, n_fine,
                     note=f"{n_fine:,} cells > {ctx.max_cells:,}: run it on a sub-box of X")
    fine = Partition(partition.space, h2, partition.regions, periodic=getattr(partition, "periodic", None))
    parent = np.asarray(partition.locate(0.5 * (fine.cells_lower + fine.cells_upper)))
    glo, ghi = fits.grid_ranges(fine.breakpoints)
    ratio = None
    if ctx.bound_cells is not None:
        # one sub-cell per pilot cell, its position cycling through the children (2^d, or fewer
        # where a region's boundary already split the cell)
        kids = [np.flatnonzero(parent == q) for q in ctx.pilot]
        sub = np.array([c[k % c.size] for k, c in enumerate(kids)])
        blo, bhi = ctx.bound_cells(fine.cells_lower[sub], fine.cells_upper[sub], rkhs_bound)
        s_lo, s_hi = _excess_sides(blo, bhi, glo[:, sub], ghi[:, sub])
        ratio = _ratio(np.concatenate([s_lo, s_hi], axis=1),
                       np.concatenate([e_lo[:, parent[sub]], e_hi[:, parent[sub]]], axis=1))
    r = np.ones((lo.shape[0], lo.shape[2])) if ratio is None else ratio
    flo_, fhi_ = _shrunk(lo[:, parent], hi[:, parent], glo, ghi, r[:, None] * e_lo[:, parent],
                         r[:, None] * e_hi[:, parent])
    share = ctx.q_yes(fine, flo_, fhi_)
    say(f"advice: finer grid ({fine.n_cells} cells) -> Q_yes {100 * share:.0f} % of X")
    return Lever("finer grid", setting, share, share - ctx.base, fine.n_cells,
                 None if ratio is None else float(np.median(ratio)), time.perf_counter() - t0,
                 "" if ratio is not None else "excess ratio 1 (no pilot)")


def _more_data(ctx: _Context, floor, say) -> Lever:
    """Lever (b), more data: the excess down to its noise floor."""
    partition = ctx.partition
    t0 = time.perf_counter()
    if partition.n_cells > ctx.max_cells:
        return Lever("more data", "excess at the noise floor", None, None, partition.n_cells,
                     note=f"{partition.n_cells:,} cells > {ctx.max_cells:,}")
    f = floor[None, None, :]
    blo, bhi = _shrunk(ctx.lo, ctx.hi, ctx.flo, ctx.fhi, np.minimum(ctx.e_lo, f), np.minimum(ctx.e_hi, f))
    share = ctx.q_yes(partition, blo, bhi)
    say(f"advice: more data -> Q_yes {100 * share:.0f} % of X")
    return Lever("more data", f"excess at the noise floor {np.round(floor, 6).tolist()}", share,
                 share - ctx.base, partition.n_cells, None, time.perf_counter() - t0)


def _smaller_b(ctx: _Context, rkhs_bound: float, min_norm: float, say) -> Lever:
    """Lever (c), a smaller B, as small as the data allow: ``max(B / 2, min_norm)``."""
    partition, lo, pilot = ctx.partition, ctx.lo, ctx.pilot
    t0 = time.perf_counter()
    B = float(rkhs_bound)
    Bs = max(0.5 * B, float(min_norm))
    if Bs >= B * (1 - 1e-9):
        return Lever("smaller B", f"B = {B:g}", None, None, partition.n_cells,
                     note=f"the data need ||g|| >= {min_norm:.3g}, so B = {B:g} cannot be smaller")
    if partition.n_cells > ctx.max_cells:
        return Lever("smaller B", f"B = {Bs:.3g}", None, None, partition.n_cells,
                     note=f"{partition.n_cells:,} cells > {ctx.max_cells:,}")
    if ctx.bound_cells is not None:
        r = ctx.pilot_ratio(*ctx.bound_cells(partition.cells_lower[pilot], partition.cells_upper[pilot], Bs))
        note = ""
    else:
        r = np.full((lo.shape[0], lo.shape[2]), Bs / B)
        note = "excess ratio B'/B (no pilot)"
    blo, bhi = _shrunk(lo, ctx.hi, ctx.flo, ctx.fhi, r[:, None] * ctx.e_lo, r[:, None] * ctx.e_hi)
    share = ctx.q_yes(partition, blo, bhi)
    say(f"advice: B = {Bs:.3g} -> Q_yes {100 * share:.0f} % of X")
    return Lever("smaller B", f"B = {Bs:.3g}", share, share - ctx.base, partition.n_cells,
                 float(np.median(r)), time.perf_counter() - t0, note)


def _sub_boxes(ctx: _Context, rkhs_bound: float, cell_t, say) -> Lever:
    """Lever (d), sub-box certification: one halving per axis where the Taylor term of eq. C is largest
    (``split_tol`` = the grid's largest term / 2.25, so ``s = ceil(sqrt(term / split_tol)) = 2`` there,
    but at least ``rkhs.SPLIT_TOL``); the excess scaled by the ratio measured on the pilot cells certified
    on those sub-boxes. The grid, and so the abstraction's size, stay as they are.

    Why one halving: it divides the term by about 4, and that took most of the gain where measured (the
    issue-20 newcomer system, B = 6, r/l 0.125: Q_yes 141 unsplit, 171 with s = 2 at about 3x the bound time,
    174 with the s = 10 of ``SPLIT_TOL`` at about 30x; ``benchmarks/results/advice_sub_boxes.md``)."""
    from robust_imdp.bounds.rkhs_model import SPLIT_TOL, split_counts, split_term

    partition, pilot = ctx.partition, ctx.pilot
    t0 = time.perf_counter()
    t = cell_t(partition.cells_lower, partition.cells_upper)
    tol = max(SPLIT_TOL, float(np.max(split_term(t, rkhs_bound))) / 2.25 * (1 + 1e-9))
    n_sub = split_counts(t, rkhs_bound, partition.dim, tol) ** partition.dim
    setting = f"split_tol = {tol:.3g}, {float(np.mean(n_sub)):.3g} sub-boxes per cell"
    if np.all(n_sub[pilot] <= 1):
        return Lever("sub-boxes", setting, None, None, partition.n_cells,
                     note="the Taylor term is below split_tol in the undecided cells: sub-boxes change nothing")
    if ctx.no_pilot():
        return Lever("sub-boxes", setting, None, None, partition.n_cells, note=ctx.no_pilot())
    r = ctx.pilot_ratio(*ctx.bound_cells(partition.cells_lower[pilot], partition.cells_upper[pilot], rkhs_bound, tol))
    # cells the rule leaves whole keep their boxes
    split = (n_sub > 1)[None, :, None]
    blo, bhi = _shrunk(ctx.lo, ctx.hi, ctx.flo, ctx.fhi, np.where(split, r[:, None] * ctx.e_lo, ctx.e_lo),
                       np.where(split, r[:, None] * ctx.e_hi, ctx.e_hi))
    share = ctx.q_yes(partition, blo, bhi)
    say(f"advice: sub-boxes -> Q_yes {100 * share:.0f} % of X")
    return Lever("sub-boxes", setting, share, share - ctx.base, partition.n_cells, float(np.median(r)),
                 time.perf_counter() - t0)


def pool_proposal(k: int, m: int) -> int:
    """The local-pools lever's ``local_points``: all ``m`` points up to :data:`POOL_ALL_MAX`, else
    ``POOL_FACTOR k`` (at most ``m``)."""
    return int(m) if int(m) <= POOL_ALL_MAX else int(min(int(m), POOL_FACTOR * int(k)))


def _larger_pools(ctx: _Context, rkhs_bound: float, k: int, m: int, say) -> Lever:
    """Lever (e), larger local pools (``local_points`` = :func:`pool_proposal`): the excess scaled by the ratio
    measured on the pilot cells bounded with those pools. In 3-D the pools, not the certificate, are most of
    the slack over the optimal range (``benchmarks/results/local_auto.md``: 0.0047 with pools of 100 against
    0.0006 with all 1,024 points at r/l 0.03)."""
    partition, pilot = ctx.partition, ctx.pilot
    t0 = time.perf_counter()
    K = pool_proposal(k, m)
    setting = (f"local_points = {K} (all points)" if K >= m else f"local_points = {K}") + f", now {int(k)}"
    if K <= k:
        return Lever("larger local pools", setting, None, None, partition.n_cells,
                     note="the pools already hold the proposed number of points")
    if ctx.no_pilot():
        return Lever("larger local pools", setting, None, None, partition.n_cells, note=ctx.no_pilot())
    r = ctx.pilot_ratio(*ctx.bound_cells(partition.cells_lower[pilot], partition.cells_upper[pilot], rkhs_bound,
                                         None, K))
    blo, bhi = _shrunk(ctx.lo, ctx.hi, ctx.flo, ctx.fhi, r[:, None] * ctx.e_lo, r[:, None] * ctx.e_hi)
    share = ctx.q_yes(partition, blo, bhi)
    say(f"advice: local_points = {K} -> Q_yes {100 * share:.0f} % of X")
    return Lever("larger local pools", setting, share, share - ctx.base, partition.n_cells, float(np.median(r)),
                 time.perf_counter() - t0)
