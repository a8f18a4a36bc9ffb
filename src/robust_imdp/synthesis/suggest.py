"""Where to collect data next: sample requests ``(x, mode)`` that shrink the error radii that hold
undecided cells back.

A cell's image box is the known part's range plus the error radius of the learned part. That
radius has a noise term (a floor no amount of data removes) and an RKHS term that more data near
the cell shrinks. For the SE kernel, the RKHS term at a point ``x`` scales with ``B sqrt(P(x))``,
where ``P`` is the *power function* (the posterior variance of a GP with prior ``k`` and noise
variance ``lambda = (floor / B)^2``) of the mode's data: the optimal and ridge certificates of
``bounds.rkhs`` are ``B ||phi_x - Phi* w||`` plus noise terms, and ``min_w ||phi_x - Phi* w||^2 +
lambda ||w||^2 = P(x)``. One more sample at ``c`` lowers the power function everywhere by the
rank-one update

    P+(x) = P(x) - Sigma(x, c)^2 / (P(c) + lambda),       Sigma = posterior covariance      (eq. S1)

so the expected change of the RKHS term at ``x`` is ``B (sqrt(P(x)) - sqrt(P+(x)))`` (eq. S2).

Requests are chosen greedily: each maximises the weighted sum of (S2) over the candidate cells,
then the covariance is updated by (S1), so the next request sees the data the previous ones will
add. Candidates are the undecided cells (Q_?; weight 1 for the mode their strategy uses, 1/2 for the
others) and the cells their strategy reaches in one step (weight = the largest upper transition
probability into them from an undecided cell, halved). This is a ranking, not a bound: nothing
here changes a guarantee. New data change the certificates only after a new run.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robust_imdp._kernels import se_gram
from robust_imdp.bounds.fit import evenly_spaced
from robust_imdp.errors import InvalidInputError

__all__ = ["SampleRequest", "Targets", "suggest_samples", "write_requests", "power_function"]

#: Largest number of data points of a mode used for the power function (an evenly spaced subset
#: beyond it: fewer points only make the power function larger, i.e. the gains look larger).
MAX_POINTS = 2000
#: Largest number of candidate cells (beyond it, only those whose strategy puts upper probability on Q_yes cells,
#: the most first, then those whose lower bound is closest to the threshold -- a reached cell: its undecided
#: source's --, then those with the largest weights).
MAX_CANDIDATES = 3000
#: Largest number of candidate *sites* (cells whose centre may be requested): the candidates with the
#: largest weighted RKHS term ``w B sqrt(P)`` at their centre. The gains are still summed over every
#: candidate cell; the greedy step costs O(candidates x sites) instead of O(candidates^2).
MAX_SITES = 500
#: Weight of a mode other than the strategy's in an undecided cell, and of a reached cell.
OTHER_MODE_WEIGHT = 0.5
REACHED_WEIGHT = 0.5


@dataclass(frozen=True)
class Targets:
    """Which (mode, cell) pairs a smaller box would decide, and how much smaller (the value-of-information
    candidates of ``robust_imdp.improve``'s look-ahead; docs/sampling.md, "Look-ahead targets").

    Attributes
    ----------
    weights : (n_modes, n_cells) float array
        Weight of each (mode, cell); 0 for pairs that are no target.
    keep : (n_modes, n_cells) float array in [0, 1)
        The fraction of the cell's current RKHS term (``B sqrt(P)`` at its centre) it may keep: the
        look-ahead turned the cell Q_yes with every undecided cell's RKHS term scaled by ``keep``.
        A request's gain for the pair is the fraction of the needed drop ``(1 - keep) sqrt(P0)`` it
        achieves, capped at the need (eq. S3).
    reason : dict ``cell -> str``
    """

    weights: np.ndarray
    keep: np.ndarray
    reason: dict


@dataclass(frozen=True)
class SampleRequest:
    """One suggested sample: apply ``mode`` at ``x`` and record the next state.

    Attributes
    ----------
    x : (d,) float array
        The state (the centre of ``cell``).
    mode : str
    cell : int
        The cell the request is for.
    reason : str
        Why: the cell's class and role (undecided / reached from an undecided cell).
    radius_change : float
        Expected decrease of the RKHS term of the error radius at the cell centre (eq. S2), in
        state units, for the component with the largest RKHS bound.
    gain : float
        The weighted sum of (S2) over all candidate cells that the greedy choice maximised.
    """

    x: np.ndarray
    mode: str
    cell: int
    reason: str
    radius_change: float
    gain: float


def _whitened(points: np.ndarray, data: np.ndarray, inv_l2: np.ndarray, lam: float) -> np.ndarray:
    """``V = L^-1 K_xc`` with ``L L^T = K + lam I``: ``k_i^T (K + lam I)^-1 k_j = (V^T V)_ij``."""
    L = np.linalg.cholesky(se_gram(data, data, inv_l2) + lam * np.eye(data.shape[0]))
    return np.linalg.solve(L, se_gram(data, points, inv_l2))


def _posterior_cov(points: np.ndarray, data: np.ndarray, inv_l2: np.ndarray, lam: float) -> np.ndarray:
    """``Sigma(c_i, c_j) = k(c_i, c_j) - k_i^T (K + lam I)^-1 k_j`` over the candidate points."""
    K_cc = se_gram(points, points, inv_l2)
    if data.shape[0] == 0:
        return K_cc
    V = _whitened(points, data, inv_l2, lam)
    return K_cc - V.T @ V


def _posterior_block(points: np.ndarray, data: np.ndarray, inv_l2: np.ndarray, lam: float, sites=None):
    """``(Sigma[:, sites], diag Sigma)``: the columns of :func:`_posterior_cov` at the points ``sites``
    indexes (default all) and its diagonal over all points (``k(x, x) = 1``)."""
    cols = points if sites is None else points[sites]
    K_cs = se_gram(points, cols, inv_l2)
    if data.shape[0] == 0:
        return K_cs, np.ones(points.shape[0])
    V = _whitened(points, data, inv_l2, lam)
    Vs = V if sites is None else V[:, sites]
    return K_cs - V.T @ Vs, 1.0 - np.sum(V * V, axis=0)


def power_function(points: np.ndarray, data: np.ndarray, inv_l2: np.ndarray, lam: float,
                   max_points: int = MAX_POINTS) -> np.ndarray:
    """The power function ``P(x) = k(x,x) - k_x^T (K + lam I)^-1 k_x`` at ``points`` (the diagonal of
    :func:`_posterior_cov`, without the full matrix), on at most ``max_points`` evenly spaced data points."""
    if data.shape[0] > max_points:
        data = data[evenly_spaced(data.shape[0], max_points)]
    V = _whitened(points, data, inv_l2, lam)
    return np.maximum(1.0 - np.sum(V * V, axis=0), 0.0)


def _row_reader(abstraction):
    """``rows(cell, mode) -> (cols, upper)``: a row's listed successors and their upper bounds, from a joint
    abstraction's IMDP or a factored one's per-axis vectors (``FactoredAbstraction.row_upper``)."""
    from robust_imdp.abstraction.factored import is_factored

    if is_factored(abstraction):
        return abstraction.row_upper
    imdp = abstraction.imdp

    def rows(q, u):
        row = int(imdp.state_ptr[q]) + int(u)  # one choice per mode, in mode order
        lo, hi = int(imdp.row_ptr[row]), int(imdp.row_ptr[row + 1])
        return np.asarray(imdp.col[lo:hi]), np.asarray(imdp.upper[lo:hi])

    return rows


def _candidates(result):
    """(cells, weight per (mode, cell), reason per cell) of the undecided cells and those they reach."""
    syn = result.synthesis
    n_cells = result.partition.n_cells
    n_modes = len(result.problem.mode_names)
    classes = np.asarray(result.class_names)
    undecided = np.flatnonzero(classes == "maybe")
    weights = np.zeros((n_modes, n_cells))
    reason = {}
    strategy = np.asarray(syn.strategy)
    if strategy.ndim == 3:  # k-step: the first step's choice
        strategy = strategy[0]
    init = np.asarray(syn.initial_dfa_state)
    chosen = strategy[np.arange(n_cells), init]
    rows = _row_reader(result.abstraction)
    # how far each undecided cell's lower bound is from the threshold (a reached cell: that of the closest
    # undecided cell reaching it); orders the candidates when there are more than MAX_CANDIDATES
    gap_q = np.maximum(float(result.threshold) - np.asarray(result.p_low, float), 0.0)
    gap = np.full(n_cells, np.inf)
    gap[undecided] = gap_q[undecided]
    # and how much upper probability its strategy's row puts on Q_yes cells (the frontier of the decided
    # region, where a tighter box can lift p_low over the threshold); a reached cell: its source's
    yes_mass = np.zeros(n_cells)
    for q in undecided:
        weights[:, q] = OTHER_MODE_WEIGHT
        weights[chosen[q], q] = 1.0
        reason[int(q)] = "undecided (Q_?)"
        cols, upper = rows(int(q), int(chosen[q]))
        inside = cols < n_cells
        yes_mass[q] = float(np.sum(upper[inside][classes[cols[inside]] == "yes"]))
        for t, p in zip(cols, upper):
            t = int(t)
            if t >= n_cells or classes[t] == "maybe" or p <= 0:
                continue
            w = REACHED_WEIGHT * float(p)
            gap[t] = min(gap[t], gap_q[q])
            yes_mass[t] = max(yes_mass[t], yes_mass[q])
            if w > weights[chosen[t], t]:
                weights[chosen[t], t] = w
                reason[t] = f"reached from undecided cell {int(q)} (upper probability {float(p):.2f})"
    cells = np.flatnonzero(weights.max(axis=0) > 0)
    if cells.size > MAX_CANDIDATES:  # the frontier of Q_yes first, then the closest to the threshold, then weight
        if np.any(yes_mass[cells] > 0):  # too many to rank them all: only the frontier
            cells = cells[yes_mass[cells] > 0]
        order = np.lexsort((-weights[:, cells].max(axis=0), gap[cells], -yes_mass[cells]))
        cells = np.sort(cells[order[:MAX_CANDIDATES]])
    return cells, weights[:, cells], reason


def _assumption(problem):
    """(B per mode, inverse squared lengthscale per input dimension, noise floor per mode) of the
    problem's assumption, the most pessimistic over components where they differ."""
    from robust_imdp.bounds.assumptions import resolve

    st = resolve(problem.rkhs_bound, problem.gp_options.get("lengthscale"), problem.misspecification,
                 problem.mode_names, int(np.size(problem.space_lower)))
    B = st.rkhs_bound.max(axis=1)  # (n_modes,): the largest over the components
    # (n_modes, d): the shortest (the most local data influence) over the learned components (B > 0; a known
    # component's lengthscale plays no part), over all of them in a mode without one
    learned = st.rkhs_bound > 0
    ls_all = np.where(learned[:, :, None], st.lengthscale, np.inf).min(axis=1)
    ls = np.where(np.isfinite(ls_all), ls_all, st.lengthscale.min(axis=1))
    noise = np.asarray(problem.noise.bound if getattr(problem.noise, "bound", None) is not None
                       else problem.noise.sigma, float).reshape(-1)
    tau = st.misspecification.max(axis=1)
    floor = float(np.max(noise)) + tau
    return B, 1.0 / (ls * ls), floor


def suggest_samples(result, n: int, *, data_points=None, targets: Targets | None = None) -> list:
    """The ``n`` sample requests that shrink the error radii of undecided cells most (see the module).

    Parameters
    ----------
    result : pipeline.Result
        A run's result (needs its problem's data, partition, abstraction and strategy).
    n : int
        Number of requests (>= 1).
    data_points : sequence (n_modes) of (m_u, d) arrays, optional
        The inputs of each mode's data (default: the problem's data set).
    targets : Targets, optional
        Value-of-information candidates (``improve``'s look-ahead): the (mode, cell) pairs whose smaller
        box turns them Q_yes, each scored by the capped fraction of its needed drop (eq. S3) instead of
        the undecided cells' summed radius change (eq. S2).

    Returns
    -------
    list of SampleRequest
        At most ``n`` requests, best first; empty when no cell is undecided.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InvalidInputError(f"n (the number of sample requests) must be an integer >= 1; got {n!r}")
    problem = result.problem
    if targets is None:
        cells, weights, reason = _candidates(result)
        keep = None
    else:
        cells = np.flatnonzero(np.asarray(targets.weights).max(axis=0) > 0)
        if cells.size > MAX_CANDIDATES:  # the cheapest targets first (the largest share of the term they may keep)
            k = np.asarray(targets.keep)[:, cells].max(axis=0)
            order = np.lexsort((-np.asarray(targets.weights)[:, cells].max(axis=0), -k))
            cells = np.sort(cells[order[:MAX_CANDIDATES]])
        weights, keep, reason = np.asarray(targets.weights, float)[:, cells], np.asarray(targets.keep)[:, cells], \
            targets.reason
    if cells.size == 0:
        return []
    part = result.partition
    centres = 0.5 * (np.asarray(part.cells_lower)[cells] + np.asarray(part.cells_upper)[cells])
    B, inv_l2, floor = _assumption(problem)
    modes = problem.mode_names
    xs, lam = [], []
    for u in range(len(modes)):
        x = np.asarray(problem.data.by_mode(u)[0] if data_points is None else data_points[u], float)
        if x.shape[0] > MAX_POINTS:
            x = x[evenly_spaced(x.shape[0], MAX_POINTS)]
        xs.append(x)
        lam.append(max((floor[u] / B[u]) ** 2, 1e-10) if B[u] > 0 else 1.0)
    sites = None
    if cells.size > MAX_SITES:  # the sites with the largest weighted RKHS term at their centre
        score = np.zeros(cells.size)
        for u in range(len(modes)):
            if B[u] > 0:
                P = power_function(centres, xs[u], inv_l2[u], lam[u])
                score = np.maximum(score, weights[u] * B[u] * np.sqrt(P))
        sites = np.sort(np.argsort(-score, kind="stable")[:MAX_SITES])
    site_index = np.arange(cells.size) if sites is None else sites
    sig, var = [], []
    for u in range(len(modes)):
        S, p = _posterior_block(centres, xs[u], inv_l2[u], lam[u], sites)
        sig.append(S)
        var.append(p)
    if keep is not None:  # eq. S3: per candidate the level its RKHS term must reach, and the drop it needs
        root0 = [np.sqrt(np.maximum(v, 0.0)) for v in var]
        level = [keep[u] * root0[u] for u in range(len(modes))]
        need = [np.maximum(root0[u] - level[u], 1e-300) for u in range(len(modes))]
    out = []
    for _ in range(int(n)):
        best = None
        for u in range(len(modes)):
            if B[u] <= 0 or not np.any(weights[u] > 0):
                continue
            S = sig[u]  # (candidates, sites)
            p = np.maximum(var[u], 0.0)
            ps = p[site_index]
            drop = S * S / (ps[None, :] + lam[u])  # drop[q, c]: decrease of P(q) from a sample at site c (eq. S1)
            after = np.sqrt(np.maximum(p[:, None] - drop, 0.0))
            change = B[u] * (np.sqrt(p)[:, None] - after)  # (eq. S2)
            if keep is None:
                gain = weights[u] @ change
            else:  # eq. S3: the fraction of each target's needed drop, capped at the need
                lv = level[u][:, None]
                gain = weights[u] @ ((np.maximum(np.sqrt(p)[:, None], lv) - np.maximum(after, lv)) / need[u][:, None])
            c = int(np.argmax(gain))
            if best is None or gain[c] > best[0]:
                best = (float(gain[c]), u, c, float(change[site_index[c], c]))
        if best is None or best[0] <= 0:
            break
        g, u, c, own = best
        k = int(site_index[c])  # the site's index among the candidates
        q = int(cells[k])
        out.append(SampleRequest(x=centres[k].copy(), mode=str(modes[u]), cell=q,
                                 reason=reason.get(q, "undecided (Q_?)"), radius_change=own, gain=g))
        S = sig[u]
        col = S[:, c].copy()  # Sigma(., site): the request's sample joins the data (eq. S1)
        denom = col[k] + lam[u]
        sig[u] = S - np.outer(col, col[site_index]) / denom
        var[u] = var[u] - col * col / denom
    return out


def write_requests(requests, path, dim_names) -> None:
    """Write the requests as CSV: ``x_1..x_d`` (or the dimension names), mode, cell, radius change,
    gain, reason; written under a temporary name and renamed, so a file is never half-written."""
    import csv
    import os
    from pathlib import Path

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow([*dim_names, "mode", "cell", "radius_change", "gain", "reason"])
        for r in requests:
            w.writerow([*(repr(float(v)) for v in r.x), r.mode, r.cell, f"{r.radius_change:.6g}", f"{r.gain:.6g}",
                        r.reason])
    os.replace(tmp, path)
