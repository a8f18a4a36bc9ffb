r"""Per-cell image and error bounds -> IMDP: the paper's Thm 1 with corrected complements.

Setting (paper, Process (1)): ``x' = f_u(x) + g_u(x) + v`` with ``g_u`` learned as
``mu_u`` by one GP per output dimension and ``v`` additive noise with independent
components. For a cell ``q``, mode ``u`` and target ``q'``:

* ``Im(q)`` is a box containing ``{f_u(x) + mu_u(x) : x in q}`` (``CellBounds.image_*``);
* ``E_g = {sup_{x in q} |g_i(x) - mu_i(x)| <= eps_i  for all i}``, with
  ``P(E_g) >= P_g``: ``P_g = prod_i p_i`` (``p_i = error_models[u][i].prob_within(eps_i,
  std_upper[u, q, i])``, independent components as in the paper) or the union bound
  ``P_g = max(0, 1 - sum_i (1 - p_i))`` (``combine="union"``, no independence needed);
* ``E_v = {|v_i| <= eta_i for all i}``, ``P(E_v) >= P_v = prod_i P[|v_i| <= eta_i]`` (or the
  union bound); ``v`` is independent of ``E_g`` (fresh noise).

Derivation (law of total probability over ``E_g`` and ``E_v``). On ``E_g ∩ E_v`` every
successor of every ``x in q`` lies in the closed box ``Im(q) ⊕ [-(eps+eta), eps+eta]``.
Hence for every ``x in q``::

    T(q'|x) <= P(E_g) [ P(E_v) 1[Im ⊕ (eps+eta) ∩ q' != ∅] + (1 - P(E_v)) ] + (1 - P(E_g))
            = 1 - P(E_g) P(E_v) (1 - 1[...])                              (Thm 1, eq. upper-bound)
    T(q'|x) >= P(E_g) P(E_v) 1[Im ⊕ (eps+eta) ⊆ q']                        (Thm 1, eq. lower-bound)

Both right-hand sides are monotone in ``P(E_g)`` and ``P(E_v)`` in the safe direction, so
the lower bounds ``P_g``, ``P_v`` may replace them. **Deviation from the printed paper**
(issue 5): the paper weights the "bad" branches with ``prod_i P[|v_i| > eta_i]`` and
``prod_i (1 - p_i)``, the probability that *all* components fail; the complement of
``E_v`` (resp. ``E_g``) is that *some* component fails, ``1 - prod_i P[|v_i| <= eta_i]``.
For ``d >= 2`` the printed upper bound is too small whenever ``P_v < 1`` (e.g. Gaussian
noise); ``tests/test_abstraction.py`` shows a Monte-Carlo counterexample.

The authors' code also (a) drops the noise factor from the upper bound (sound only if
``P_v = 1``) and (b) measures image-to-target separation with a max over all axes,
overlapping ones included. Neither is done here: two closed boxes intersect iff they
overlap on EVERY axis, i.e. they are disjoint iff some axis ``j`` has a strictly positive
gap ``gap_j > eps_j + eta_j``.

Outside state (corollary): ``lower(q,u,out) = 1 - [upper bound of T(X|x)] =
P_g P_v 1[Im ⊕ (eps+eta) ∩ X = ∅]`` and ``upper(q,u,out) = 1 - P_g P_v 1[Im ⊕ (eps+eta) ⊆ X]``.

Cells and boundaries: cells are closed boxes sharing faces; since ``v`` has a density and
is independent of ``x``, ``P[x' ∈ ∂q'] = 0``, so closed/half-open cell conventions give the
same probabilities and the closed tests above are exact for :meth:`Partition.locate`'s cells.

Choosing eps and eta. The theorem holds for every ``eps, eta > 0`` and each bound may use
its own values:

* ``eps_rule="paper"``: eta = the given ``eta`` (default: noise bound, else 0.99 quantile);
  for the target containing ``Im(q)``, the largest eps with ``Im ⊕ (eps+eta) ⊆ q'``
  (``eps_i = m_i - eta_i``, margins ``m``); otherwise ``eps = eps_for_prob(0.99)``.
* ``eps_rule="optimized"`` (default): per (cell, mode, target) and per dimension, the best
  split of the available margin/gap ``t_i`` into ``eps_i + eta_i < t_i``: eps over a
  geometric grid of probability levels (``EPS_LEVELS``, via ``eps_for_prob``, probabilities
  recomputed with ``prob_within``) and the paper's candidate, eta = the whole rest of the
  margin (or the fixed ``eta`` when given). For the product combination this maximises
  ``P_g P_v`` dimension by dimension (the constraint and the objective separate); an axis
  that is not constrained uses the largest candidates. The paper's choices are among the
  candidates, so the optimised bounds are never looser (for ``combine="product"``).

Sparse output: each row lists the targets whose closed box meets ``Im ⊕ e_f`` for a per-row
"floor" pair ``(eps_f, eta_f)`` plus the outside state; every other target is separated
from ``Im ⊕ e_f`` along some axis, so ``1 - P_g(eps_f) P_v(eta_f)`` is a valid upper bound for
all of them: the row's ``floor``. The floor pair takes, per dimension, the smallest level
``>= 0.99`` with ``p_i P[|v_i| <= eta_i] >= 1 - floor_tol/d`` (else the best level).

Rounding: all computed bounds go through :func:`_outward` (error bound + ``np.nextafter``):
probabilities of good events down, upper bounds up; margins/gaps down, expansions up.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError, SoundnessError
from robust_imdp.models.geometry import BoxPartition, Partition, partition_from_dict
from robust_imdp.models.imdp import IMDP
from robust_imdp.models.noise import NoiseModel

__all__ = ["CellBounds", "Abstraction", "AbstractionRows", "abstract", "abstract_rows", "assemble_abstraction",
           "select_rows", "join_rows",
           "confidence_cell_bounds", "EPS_LEVELS"]

#: Probability levels at which candidate eps are proposed (``eps_for_prob(level, std)``).
EPS_LEVELS = 1.0 - np.array(
    [0.5, 0.3, 0.2, 0.1, 0.05, 0.02, 0.01, 5e-3, 2e-3, 1e-3, 5e-4, 2e-4, 1e-4, 3e-5, 1e-5,
     3e-6, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-12]
)
_PAPER_LEVEL = 0.99
_U = 2.0 ** -53  # unit round-off of float64
_SHRINK = 1.0 - 2.0 ** -40  # makes eta = (t - eps) * _SHRINK strictly below t - eps in reals


# ============================================================================ rounding
def _outward(x, err, up: bool):
    """The one rounding helper: move ``x`` by the error bound ``err`` (>= 0) and one ulp outward.

    Where ``err == 0`` the value was computed exactly and is returned unchanged.
    """
    x = np.asarray(x, dtype=float)
    err = np.broadcast_to(np.asarray(err, dtype=float), x.shape)
    if up:
        moved = np.nextafter(x + err, np.inf)
    else:
        moved = np.nextafter(x - err, -np.inf)
    return np.where(err > 0, moved, x)


def _down1(x):
    """Lower bound of a real computed by one correctly rounded operation."""
    return np.nextafter(x, -np.inf)


def _up1(x):
    """Upper bound of a real computed by one correctly rounded operation."""
    return np.nextafter(x, np.inf)


def _combine_down(p, pv, combine: str):
    """Lower bound of ``P(E_g) P(E_v)`` from per-dimension lower bounds ``p, pv`` (..., d)."""
    d = p.shape[-1]
    if combine == "product":
        g = np.prod(p, axis=-1) * np.prod(pv, axis=-1)
        # product of 2d factors in [0,1]: relative error <= (2d - 1) u; g == 1 only if exact
        err = np.where(g == 1.0, 0.0, (2 * d) * 2 * _U * g)
    else:
        g = np.maximum(1.0 - np.sum(1.0 - p, axis=-1), 0.0) * np.maximum(1.0 - np.sum(1.0 - pv, axis=-1), 0.0)
        # each sum of d complements and the final difference: absolute error <= (2d + 2) u per
        # factor; the clamp at 0 is safe (the union bound of a probability is >= 0 anyway)
        err = np.where(g == 1.0, 0.0, (4 * d + 6) * _U)
    return np.maximum(_outward(g, err, up=False), 0.0)  # clamp: a probability is >= 0


def _complement_up(g):
    """Upper bound of ``1 - g`` for a float ``g`` in [0, 1] (Sterbenz: exact when g >= 0.5)."""
    val = 1.0 - g
    # clamp at 1 is safe: every transition probability is <= 1
    return np.minimum(_outward(val, np.where(g >= 0.5, 0.0, _U), up=True), 1.0)


# ============================================================================ data types
@dataclass(frozen=True, eq=False)
class CellBounds:
    """Certified per-cell bounds, the input of :func:`abstract`.

    Parameters
    ----------
    image_lower, image_upper : (n_modes, n_cells, d) float arrays
        A box containing ``{f_u(x) + mu_u(x) : x in cell}`` for each mode and cell.
    std_upper : (n_modes, n_cells, d) float array or None
        Upper bound of the posterior std over each cell; ``None`` means known dynamics
        (``g = 0``: eps = 0 and error probability 1).
    """

    image_lower: np.ndarray
    image_upper: np.ndarray
    std_upper: np.ndarray | None = None

    def __post_init__(self):
        lo = np.array(self.image_lower, dtype=float)
        hi = np.array(self.image_upper, dtype=float)
        if lo.ndim != 3:
            raise DimensionError(f"image_lower must have shape (n_modes, n_cells, d); got {lo.shape}")
        if hi.shape != lo.shape:
            raise DimensionError(f"image_upper must have shape {lo.shape} like image_lower; got {hi.shape}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise InvalidInputError("image_lower and image_upper must be finite")
        bad = np.argwhere(lo > hi)
        if bad.size:
            u, q, i = (int(v) for v in bad[0])
            raise InvalidInputError(
                f"image_lower must be <= image_upper; got [{lo[u, q, i]}, {hi[u, q, i]}] at mode {u}, cell {q}, dim {i}"
            )
        std = None
        if self.std_upper is not None:
            std = np.array(self.std_upper, dtype=float)
            if std.shape != lo.shape:
                raise DimensionError(f"std_upper must have shape {lo.shape} like image_lower; got {std.shape}")
            if not np.all(np.isfinite(std)) or np.any(std < 0):
                raise InvalidInputError("std_upper must be finite and >= 0")
            std.setflags(write=False)
        lo.setflags(write=False)
        hi.setflags(write=False)
        object.__setattr__(self, "image_lower", lo)
        object.__setattr__(self, "image_upper", hi)
        object.__setattr__(self, "std_upper", std)

    @property
    def n_modes(self) -> int:
        return self.image_lower.shape[0]

    @property
    def n_cells(self) -> int:
        return self.image_lower.shape[1]

    @property
    def dim(self) -> int:
        return self.image_lower.shape[2]


@dataclass(frozen=True, eq=False)
class Abstraction:
    """Result of :func:`abstract`.

    Attributes
    ----------
    imdp : IMDP
        States: cells ``0..n_cells-1`` then the outside state ``n_cells``; choice = mode.
    partition : Partition
    eps_rule, combine : str
    eta : (d,) float array or None
        The fixed eta (given, or the paper rule's default); None when optimised freely.
    floor_tol : float
    floor_eps, floor_eta : (n_modes, n_cells, d) float arrays
        The per-row pair defining the listed targets and the floor.
    lower_eps, lower_eta : (n_modes, n_cells, d) float arrays
        The pair behind the lower bound to the cell containing the image (NaN if none).
    containing_cell : (n_modes, n_cells) int array
        The cell containing ``Im(q)`` with positive margins (-1 if none).
    nnz_per_row : (n_choices,) int array
        Listed entries per IMDP row (including the outside state).
    """

    imdp: IMDP
    partition: Partition
    eps_rule: str
    combine: str
    eta: np.ndarray | None
    floor_tol: float
    floor_eps: np.ndarray
    floor_eta: np.ndarray
    lower_eps: np.ndarray
    lower_eta: np.ndarray
    containing_cell: np.ndarray
    nnz_per_row: np.ndarray = field(repr=False)

    @property
    def n_modes(self) -> int:
        return self.floor_eps.shape[0]

    def save(self, path) -> None:
        """Write an ``.npz`` file (no pickle): IMDP arrays, partition JSON and parameters."""
        m = self.imdp
        meta = {"partition": self.partition.to_dict(), "eps_rule": self.eps_rule, "combine": self.combine,
                "floor_tol": self.floor_tol}
        arrays = dict(state_ptr=m.state_ptr, row_ptr=m.row_ptr, col=m.col, lower=m.lower, upper=m.upper,
                      floor=m.floor, actions=m.actions, floor_eps=self.floor_eps, floor_eta=self.floor_eta,
                      lower_eps=self.lower_eps, lower_eta=self.lower_eta, containing_cell=self.containing_cell,
                      nnz_per_row=self.nnz_per_row, meta=np.array(json.dumps(meta)))
        if self.eta is not None:
            arrays["eta"] = self.eta
        np.savez_compressed(Path(path), **arrays)

    @classmethod
    def load(cls, path) -> "Abstraction":
        """Read a file written by :meth:`save` (the IMDP is validated again)."""
        with np.load(Path(path), allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            imdp = IMDP.from_csr(z["state_ptr"], z["row_ptr"], z["col"], z["lower"], z["upper"],
                                 floor=z["floor"], actions=z["actions"])
            return cls(imdp=imdp, partition=partition_from_dict(meta["partition"]), eps_rule=meta["eps_rule"],
                       combine=meta["combine"], eta=np.array(z["eta"]) if "eta" in z else None,
                       floor_tol=float(meta["floor_tol"]), floor_eps=np.array(z["floor_eps"]),
                       floor_eta=np.array(z["floor_eta"]), lower_eps=np.array(z["lower_eps"]),
                       lower_eta=np.array(z["lower_eta"]), containing_cell=np.array(z["containing_cell"]),
                       nnz_per_row=np.array(z["nnz_per_row"]))


# ============================================================================ candidates
class _Mode:
    """Per-mode candidate (eps, p) arrays and the noise context (internal)."""

    def __init__(self, u, bounds, models, noise, eta_fixed, rule, floor_tol, combine):
        n, d = bounds.n_cells, bounds.dim
        self.noise, self.combine, self.rule = noise, combine, rule
        self.std = None if bounds.std_upper is None else bounds.std_upper[u]
        self.models = None if models is None else models[u]
        levels = np.array([_PAPER_LEVEL]) if rule == "paper" else EPS_LEVELS
        k99 = int(np.flatnonzero(levels == _PAPER_LEVEL)[0])
        K = levels.size
        if self.std is None:  # known dynamics: eps = 0 with probability 1
            self.eps = np.zeros((n, d, K))
            self.p = np.ones((n, d, K))
        else:
            self.eps = np.empty((n, d, K))
            self.p = np.empty((n, d, K))
            for i in range(d):
                e = np.stack([np.asarray(self.models[i].eps_for_prob(lv, self.std[:, i]), dtype=float)
                              * np.ones(n) for lv in levels], axis=1)
                bad = ~np.isfinite(e) | (e < 0)
                e = np.where(bad, 0.0, e)
                pr = self._prob(i, e, np.arange(n)[:, None])
                self.eps[:, i, :] = np.where(bad, np.inf, e)  # unusable candidate
                self.p[:, i, :] = np.where(bad, 0.0, pr)
        # --- noise context: fixed eta (paper rule or given) or free eta (optimised)
        self.fixed = eta_fixed is not None
        self.eta_def = np.array(eta_fixed if self.fixed else noise.default_eta(), dtype=float)
        self.pv_def = noise.prob_abs_le(self.eta_def)
        if self.fixed:
            eta_top = self.eta_def
        elif noise.bounded:
            eta_top = np.array(noise.bound, dtype=float)
        else:
            eta_top = noise.abs_quantile(1.0 - 1e-15)
        self.eta_top = eta_top
        self.pv_top = noise.prob_abs_le(eta_top)
        # --- top candidate (unconstrained axes): the best p (eps) with the top eta
        if rule == "paper":
            self.p_top, self.eps_top = self.p[:, :, k99], self.eps[:, :, k99]
        else:
            kt = np.argmax(self.p, axis=2)
            self.p_top = np.take_along_axis(self.p, kt[..., None], 2)[..., 0]
            self.eps_top = np.take_along_axis(self.eps, kt[..., None], 2)[..., 0]
        # --- floor pair per (cell, dim)
        if rule == "paper":
            self.floor_p, self.floor_eps = self.p[:, :, k99], self.eps[:, :, k99]
            self.floor_pv = np.broadcast_to(self.pv_def, (n, d)).copy()
            self.floor_eta = np.broadcast_to(self.eta_def, (n, d)).copy()
        else:
            lv = levels[k99:]
            if self.fixed:
                eta_l = np.broadcast_to(self.eta_def, (lv.size, d))
            else:
                q = np.minimum(lv, 1.0 - 1e-15)
                eta_l = np.maximum(noise.abs_quantile(q), self.eta_def)  # (L, d), >= paper's eta
            pv_l = noise.prob_abs_le(eta_l)  # (L, d)
            pk = self.p[:, :, k99:]  # (n, d, L)
            score = pk * pv_l.T[None]
            good = score >= 1.0 - floor_tol / d
            kf = np.where(good.any(axis=2), np.argmax(good, axis=2), np.argmax(score, axis=2))
            self.floor_p = np.take_along_axis(pk, kf[..., None], 2)[..., 0]
            self.floor_eps = np.take_along_axis(self.eps[:, :, k99:], kf[..., None], 2)[..., 0]
            self.floor_pv = pv_l[kf, np.arange(d)[None, :]]
            self.floor_eta = eta_l[kf, np.arange(d)[None, :]]

    def _prob(self, i, eps, rows):
        """Lower bound ``p_i(eps)`` of the GP-error event for cells ``rows`` (broadcast with eps)."""
        if self.std is None:
            return np.ones(np.shape(eps))
        s = self.std[rows, i]
        pr = np.asarray(self.models[i].prob_within(eps, s), dtype=float)
        if pr.shape != np.broadcast(eps, s).shape or not np.all((pr >= 0) & (pr <= 1)):
            raise InvalidInputError(
                f"error_models[.][{i}].prob_within must return probabilities in [0, 1] of shape "
                f"{np.broadcast(eps, s).shape}; got shape {pr.shape}"
            )
        return pr

    def _score(self, p, pv):
        return p * pv if self.combine == "product" else p + pv - 1.0

    def split(self, t, rows, i, paper_candidate: bool):
        """Best per-dimension pair with ``eps + eta < t`` (strict) for queries ``t`` (Q,).

        Returns ``(p, pv, eps, eta)`` arrays of shape (Q,); ``p = pv = 0`` (and NaN eps/eta)
        where no pair fits.
        """
        t = np.asarray(t, dtype=float)
        cols = []
        if self.rule != "paper" or not paper_candidate:
            E = self.eps[rows, i, :]
            P = self.p[rows, i, :]
            tt = t[:, None]
            if self.fixed:
                ETA = np.broadcast_to(self.eta_def[i], E.shape)
                ok = _up1(E + self.eta_def[i]) < tt
                PV = np.where(ok, self.pv_def[i], 0.0)
            else:
                with np.errstate(invalid="ignore"):
                    eta1 = (tt - E) * _SHRINK  # eps + eta1 < t in exact arithmetic (module doc)
                eta1 = np.where(np.isfinite(eta1), eta1, -1.0)
                pv1 = self.noise.marginal_prob_abs_le(eta1, i)
                okd = _up1(E + self.eta_def[i]) < tt
                use_def = okd & (self.pv_def[i] > pv1)
                PV = np.where(use_def, self.pv_def[i], pv1)
                ETA = np.where(use_def, self.eta_def[i], eta1)
                ok = (eta1 > 0) | use_def
            cols.append((P, PV, E, ETA, ok))
        if paper_candidate:
            # paper's rule for containment: eta fixed, eps_i = (t_i - eta_i) shrunk (largest eps)
            with np.errstate(invalid="ignore"):
                e = (t - self.eta_def[i]) * _SHRINK
            okp = e > 0
            e = np.where(okp, e, 0.0)
            P = self._prob(i, e, rows)
            cols.append((P[:, None], np.full((t.size, 1), self.pv_def[i]), e[:, None],
                         np.full((t.size, 1), self.eta_def[i]), okp[:, None]))
        P, PV, E, ETA, OK = (np.concatenate([c[k] for c in cols], axis=1) for k in range(5))
        score = np.where(OK, self._score(P, PV), -np.inf)
        k = np.argmax(score, axis=1)[:, None]
        ok = np.take_along_axis(OK, k, 1)[:, 0]
        pick = lambda A: np.take_along_axis(np.broadcast_to(A, OK.shape), k, 1)[:, 0]  # noqa: E731
        return (np.where(ok, pick(P), 0.0), np.where(ok, pick(PV), 0.0),
                np.where(ok, pick(E), np.nan), np.where(ok, pick(ETA), np.nan))

    def top(self, rows):
        """(p, pv) of the largest candidates for cells ``rows``: (Q, d) each."""
        return self.p_top[rows], np.broadcast_to(self.pv_top, (len(rows), self.pv_top.size)).copy()


def _separated_best(mode, gap_p, gap_pv, rows, j):
    """``combine`` lower bound with axis ``j`` from a split and every other axis at the top."""
    P, PV = mode.top(rows)
    P[:, j] = gap_p
    PV[:, j] = gap_pv
    return _combine_down(P, PV, mode.combine)


# ============================================================================ confidence mode
def confidence_cell_bounds(cell_bounds: CellBounds, error_models, confidence: float = 0.99) -> CellBounds:
    """Fold the GP error into the image boxes at one data-confidence level (the sound default).

    Why. Thm 1 mixes two different probabilities: ``P[sup_q |g - mu| <= eps]`` is a probability
    over the *training data* (g is a fixed unknown function), while ``T(q'|x)`` is a probability
    over the process noise. For a fixed system and a fixed data set the printed product
    ``P_g * P_v * 1[...]`` is therefore not a bound of ``T(q'|x)``: when the realised error is
    large, the true ``T`` can be below the printed lower bound (``tests/test_soundness_audit.py``
    shows 0.575 printed against 0.436 true). The statement that does hold is a confidence
    statement: by Lemma 1 (Chowdhury & Gopalan 2017, Thm 2) applied with ``delta_ui`` to the GP of
    mode u and output i, and a union bound over all ``n_modes * d`` GPs, with probability at least
    ``confidence = 1 - sum delta_ui`` over the data,

        for every mode u, output i and x in X:  |g_ui(x) - mu_ui(x)| <= beta_ui(delta_ui) sigma_ui(x).

    On that event the true successor mean ``f_u(x) + g_u(x)`` of every x in cell q lies in the
    image box expanded by ``eps_uqi = beta_ui(delta_ui) * std_upper[u, q, i]``, so the
    known-dynamics abstraction of the expanded boxes (eps = 0, error probability 1) contains
    the true transition probabilities of *every* row simultaneously, and every p_low/p_up
    computed from it holds with that confidence. No independence between GPs is needed.

    Parameters
    ----------
    cell_bounds : CellBounds
        Image boxes of ``f_u + mu_u`` and std bounds (``std_upper`` must not be None).
    error_models : sequence (n_modes) of sequences (d) of error models
        Each with ``eps_for_prob(p, std_upper)`` returning ``beta(1 - p) * std_upper`` rounded up.
    confidence : float in (0, 1)
        Probability over the data with which the resulting abstraction is sound.

    Returns
    -------
    CellBounds
        Expanded image boxes (rounded outward) with ``std_upper=None``.
    """
    confidence = float(confidence)
    if not 0.0 < confidence < 1.0:
        raise InvalidInputError(f"confidence must lie in (0, 1); got {confidence}")
    if cell_bounds.std_upper is None:
        raise InvalidInputError("cell_bounds.std_upper is None (known dynamics): there is no GP error to fold in")
    M, _, d = cell_bounds.image_lower.shape
    models = _check_models(error_models, M, d)
    # Union bound over the M*d GPs: each gets an equal share of 1 - confidence. 1 - confidence
    # is rounded down (smaller delta -> larger beta -> larger eps: the safe side).
    delta_each = _down1(_down1(1.0 - confidence) / (M * d))
    # p one ulp above fl(1 - delta_each): then 1 - p (exact by Sterbenz) <= delta_each, so the
    # per-GP failure probability used by eps_for_prob never exceeds its union-bound share.
    p_each = _up1(1.0 - delta_each)
    eps = np.empty_like(cell_bounds.std_upper)
    for u in range(M):
        for i in range(d):
            eps[u, :, i] = models[u][i].eps_for_prob(p_each, cell_bounds.std_upper[u, :, i])
    # Expansion by eps, rounded outward (one correctly rounded subtraction/addition each).
    lo = _down1(cell_bounds.image_lower - eps)
    hi = _up1(cell_bounds.image_upper + eps)
    return CellBounds(lo, hi, None)


# ============================================================================ main entry
def _check_models(error_models, n_modes, d):
    if error_models is None:
        return None
    try:
        models = [list(m) for m in error_models]
    except TypeError:
        raise InvalidInputError(
            f"error_models must be a sequence of {n_modes} sequences of {d} error models; got {type(error_models).__name__}"
        ) from None
    if len(models) != n_modes or any(len(m) != d for m in models):
        raise DimensionError(
            f"error_models must have shape ({n_modes} modes, {d} dims); got {[len(m) for m in models]}"
        )
    for u, row in enumerate(models):
        for i, m in enumerate(row):
            if not (callable(getattr(m, "prob_within", None)) and callable(getattr(m, "eps_for_prob", None))):
                raise InvalidInputError(
                    f"error_models[{u}][{i}] must have prob_within(eps, std_upper) and eps_for_prob(p, std_upper); "
                    f"got {type(m).__name__}"
                )
    return models


def abstract(partition: Partition, cell_bounds: CellBounds, noise: NoiseModel, error_models=None, *,
             eta=None, eps_rule: str = "optimized", combine: str = "product", floor_tol: float = 1e-6,
             block_size: int = 4096) -> Abstraction:
    """Build the IMDP abstraction (Thm 1 with corrected complements, corollary for outside X).

    Parameters
    ----------
    partition : Partition
        The cells (``n_cells``, dimension d).
    cell_bounds : CellBounds
        ``(n_modes, n_cells, d)`` image boxes and std bounds.
    noise : NoiseModel
        Additive noise with independent components, dimension d.
    error_models : sequence (n_modes) of sequences (d) of error models, or None
        Duck-typed: ``prob_within(eps, std_upper)`` (a lower bound of
        ``P[sup_cell |g_i - mu_i| <= eps]``, vectorised, non-decreasing in eps) and
        ``eps_for_prob(p, std_upper)``. Must be None iff ``cell_bounds.std_upper`` is None.
    eta : float or (d,) float array, optional
        Fixed noise radius (> 0). Default: the paper rule uses ``noise.default_eta()``,
        the optimised rule chooses eta freely per pair.
    eps_rule : {"optimized", "paper"}
    combine : {"product", "union"}
        How per-dimension probabilities are combined (independence vs union bound).
    floor_tol : float in (0, 1)
        Per-row floor target: the floor pair is the smallest level >= 0.99 whose per-dimension
        good-event probability is >= 1 - floor_tol/d, so the floor is about floor_tol (plus the
        GP part). Smaller values list more targets (nnz grows slowly, ~log) and tighten the
        unbounded-horizon results (benchmarks/results/abstraction.md: 1e-4 -> 1e-6 turned 44 of
        762 "maybe" cells of the 32x32 example into "yes" for +5 % non-zeros).
    block_size : int
        Cells processed at once (memory/speed trade-off only).

    Returns
    -------
    Abstraction

    Raises
    ------
    DimensionError, InvalidInputError
        Bad shapes or parameters.
    SoundnessError
        A row violates ``sum(lower) <= 1 <= sum(upper) + floor * n_unlisted`` after rounding.
    """
    return assemble_abstraction(partition, [abstract_rows(
        partition, cell_bounds, noise, error_models, eta=eta, eps_rule=eps_rule, combine=combine,
        floor_tol=floor_tol, block_size=block_size, _chunk=False)])


@dataclass(frozen=True, eq=False)
class AbstractionRows:
    """The IMDP rows of a chunk of cells (all modes), in cell order: the unit of :func:`assemble_abstraction`.

    Rows are ``q * M + u`` for the chunk's local cell index q; columns are global cell indices
    (``n_cells`` is the outside state).
    """

    row_len: np.ndarray
    col: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    floor: np.ndarray
    lower_eps: np.ndarray
    lower_eta: np.ndarray
    containing: np.ndarray
    floor_eps: np.ndarray
    floor_eta: np.ndarray
    n_modes: int
    eps_rule: str
    combine: str
    eta: np.ndarray | None
    floor_tol: float


def abstract_rows(partition: Partition, cell_bounds: CellBounds, noise: NoiseModel, error_models=None, *,
                  eta=None, eps_rule: str = "optimized", combine: str = "product", floor_tol: float = 1e-6,
                  block_size: int = 4096, _chunk: bool = True) -> AbstractionRows:
    """The rows of :func:`abstract` for the cells whose image boxes ``cell_bounds`` holds (a chunk).

    A pure function of its arguments: each row depends only on its own cell's image box (and the
    partition), so computing the rows chunk by chunk and concatenating them in cell order
    (:func:`assemble_abstraction`) gives exactly :func:`abstract`'s IMDP. Parameters as in
    :func:`abstract`, except that ``cell_bounds`` may hold any number of cells.
    """
    if not isinstance(partition, (Partition, BoxPartition)):
        raise InvalidInputError(f"partition must be a Partition or a BoxPartition; got {type(partition).__name__}")
    if not isinstance(cell_bounds, CellBounds):
        raise InvalidInputError(f"cell_bounds must be a CellBounds; got {type(cell_bounds).__name__}")
    if not isinstance(noise, NoiseModel):
        raise InvalidInputError(f"noise must be a NoiseModel; got {type(noise).__name__}")
    if eps_rule not in ("optimized", "paper"):
        raise InvalidInputError(f"eps_rule must be 'optimized' or 'paper'; got {eps_rule!r}")
    if combine not in ("product", "union"):
        raise InvalidInputError(f"combine must be 'product' or 'union'; got {combine!r}")
    if not (0 < floor_tol < 1):
        raise InvalidInputError(f"floor_tol must lie in (0, 1); got {floor_tol!r}")
    M, N, d = cell_bounds.n_modes, cell_bounds.n_cells, cell_bounds.dim
    if (N != partition.n_cells and not _chunk) or d != partition.dim:
        raise DimensionError(
            f"cell_bounds must have shape (n_modes, {partition.n_cells}, {partition.dim}) for this partition; "
            f"got {cell_bounds.image_lower.shape}"
        )
    if noise.dim != d:
        raise DimensionError(f"noise must have dimension {d}; got {noise.dim}")
    if (error_models is None) != (cell_bounds.std_upper is None):
        raise InvalidInputError(
            "error_models must be given exactly when cell_bounds.std_upper is given "
            f"(std_upper is {'None' if cell_bounds.std_upper is None else 'an array'}, "
            f"error_models is {'None' if error_models is None else 'given'})"
        )
    models = _check_models(error_models, M, d)
    eta_fixed = None
    if eta is not None:
        eta_fixed = np.asarray(eta, dtype=float)
        if eta_fixed.ndim == 0:
            eta_fixed = np.full(d, float(eta_fixed))
        if eta_fixed.shape != (d,):
            raise DimensionError(f"eta must be a float or have shape ({d},); got shape {eta_fixed.shape}")
        if not np.all(np.isfinite(eta_fixed)) or np.any(eta_fixed <= 0):
            raise InvalidInputError(f"eta must be finite and > 0 in every dimension; got {eta_fixed.tolist()}")
    elif eps_rule == "paper":
        eta_fixed = noise.default_eta()

    modes = [_Mode(u, cell_bounds, models, noise, eta_fixed, eps_rule, floor_tol, combine) for u in range(M)]
    if isinstance(partition, BoxPartition):
        return _box_rows(partition, cell_bounds, modes, combine, block_size, eps_rule, eta_fixed, floor_tol)
    bp = partition.breakpoints
    shape = np.array(partition.shape)
    Xlo, Xhi = partition.space.lower, partition.space.upper

    # ---------------------------------------------------------------- pass 1: listed targets per row
    klo = np.empty((M, N, d), dtype=np.int64)
    cnt = np.empty((M, N, d), dtype=np.int64)
    floors = np.empty((M, N))
    for u, md in enumerate(modes):
        a, b = cell_bounds.image_lower[u], cell_bounds.image_upper[u]
        ef = _up1(md.floor_eps + md.floor_eta)
        lo, hi = _down1(a - ef), _up1(b + ef)  # closed box ⊇ Im ⊕ e_f
        for j in range(d):
            klo[u, :, j] = np.searchsorted(bp[j][1:], lo[:, j], side="left")  # first k: b_{k+1} >= lo
            khi = np.searchsorted(bp[j][:-1], hi[:, j], side="right") - 1  # last k: b_k <= hi
            cnt[u, :, j] = np.maximum(khi - klo[u, :, j] + 1, 0)
        floors[u] = _complement_up(_combine_down(md.floor_p, md.floor_pv, combine))
    n_listed = np.prod(cnt, axis=2)  # (M, N); 0 when Im ⊕ e_f misses X
    cnt[n_listed == 0] = 0
    row_len = (n_listed + 1).T.ravel()  # rows q*M + u (the outside state's rows: assemble_abstraction)
    row_ptr = np.zeros(row_len.size + 1, dtype=np.int64)
    np.cumsum(row_len, out=row_ptr[1:])
    nnz = int(row_ptr[-1])
    col = np.empty(nnz, dtype=np.int64)
    lower = np.zeros(nnz)
    upper = np.empty(nnz)

    lower_eps = np.full((M, N, d), np.nan)
    lower_eta = np.full((M, N, d), np.nan)
    containing = np.full((M, N), -1, dtype=np.int64)

    # ---------------------------------------------------------------- pass 2: bounds, block by block
    for u, md in enumerate(modes):
        for start in range(0, N, block_size):
            rows = np.arange(start, min(start + block_size, N))
            B = rows.size
            a = cell_bounds.image_lower[u, rows]
            b = cell_bounds.image_upper[u, rows]
            # -- cell containing Im(q) with positive margins (Thm 1, eq. lower-bound)
            j0 = np.empty((B, d), dtype=np.int64)
            m = np.empty((B, d))
            inside = np.ones(B, dtype=bool)
            for j in range(d):
                k = np.searchsorted(bp[j], a[:, j], side="right") - 1
                kk = np.clip(k, 0, shape[j] - 1)
                ok = (k >= 0) & (k < shape[j]) & (b[:, j] <= bp[j][kk + 1])
                j0[:, j] = kk
                m[:, j] = np.where(ok, _down1(np.minimum(a[:, j] - bp[j][kk], bp[j][kk + 1] - b[:, j])), 0.0)
                inside &= ok & (m[:, j] > 0)
            Pc, PVc = np.zeros((B, d)), np.zeros((B, d))
            for j in range(d):
                p_, pv_, e_, h_ = md.split(m[:, j], rows, j, paper_candidate=True)
                Pc[:, j], PVc[:, j] = p_, pv_
                lower_eps[u, rows, j], lower_eta[u, rows, j] = e_, h_
            low_c = np.where(inside, _combine_down(Pc, PVc, combine), 0.0)
            cont = np.where(inside & (low_c > 0), np.ravel_multi_index(tuple(j0.T), partition.shape), -1)
            containing[u, rows] = cont
            lower_eps[u, rows[cont < 0]] = np.nan
            lower_eta[u, rows[cont < 0]] = np.nan
            # -- outside state (corollary)
            PX, PVX = np.zeros((B, d)), np.zeros((B, d))
            g_out = np.zeros(B)
            for j in range(d):
                mX = _down1(np.minimum(a[:, j] - Xlo[j], Xhi[j] - b[:, j]))
                PX[:, j], PVX[:, j], _, _ = md.split(mX, rows, j, paper_candidate=True)
                gX = _down1(np.maximum(Xlo[j] - b[:, j], a[:, j] - Xhi[j]))
                sp, spv, _, _ = md.split(gX, rows, j, paper_candidate=False)
                g_out = np.maximum(g_out, _separated_best(md, sp, spv, rows, j))
            up_out = _complement_up(_combine_down(PX, PVX, combine))  # 1 - P_g P_v 1[Im ⊕ e ⊆ X]
            low_out = g_out  # 1 - (1 - P_g P_v 1[Im ⊕ e ∩ X = ∅])
            # -- listed cells: per-axis gaps of every listed interval, then entries
            c = cnt[u, rows]  # (B, d)
            nl = n_listed[u, rows]
            per_axis = []
            for j in range(d):
                rr = np.repeat(np.arange(B), c[:, j])
                off = np.zeros(B + 1, dtype=np.int64)
                np.cumsum(c[:, j], out=off[1:])
                ell = klo[u, rows, j][rr] + (np.arange(rr.size) - off[rr])
                gap = _down1(np.maximum(bp[j][ell] - b[rr, j], a[rr, j] - bp[j][ell + 1]))
                sp, spv, _, _ = md.split(gap, rows[rr], j, paper_candidate=False)
                per_axis.append((off, ell, sp, spv))
            E = int(nl.sum())
            er = np.repeat(np.arange(B), nl)  # block-local row of each entry
            eoff = np.zeros(B + 1, dtype=np.int64)
            np.cumsum(nl, out=eoff[1:])
            t = np.arange(E) - eoff[er]
            loc = np.empty((E, d), dtype=np.int64)
            for j in range(d - 1, -1, -1):  # C-order unravel of the local index
                cj = c[er, j]
                loc[:, j] = t % np.maximum(cj, 1)
                t = t // np.maximum(cj, 1)
            G = np.zeros(E)
            P0, PV0 = md.top(rows)
            multi = []
            for j in range(d):
                off, ell, sp, spv = per_axis[j]
                idx = off[er] + loc[:, j]
                multi.append(ell[idx])
                P, PV = P0[er], PV0[er]
                P[:, j], PV[:, j] = sp[idx], spv[idx]
                G = np.maximum(G, _combine_down(P, PV, combine))
            cols = np.ravel_multi_index(tuple(multi), partition.shape) if E else np.zeros(0, dtype=np.int64)
            low = np.where(cols == cont[er], low_c[er], 0.0)
            # -- scatter into the state-major CSR (row = q * M + u), outside state last
            grow = rows * M + u
            dest = row_ptr[grow][er] + np.arange(E) - eoff[er]
            col[dest] = cols
            upper[dest] = _complement_up(G)
            lower[dest] = low
            dout = row_ptr[grow + 1] - 1
            col[dout] = partition.n_cells  # the outside state (global index)
            upper[dout] = up_out
            lower[dout] = low_out
    return AbstractionRows(
        row_len=(n_listed + 1).T.ravel(), col=col, lower=lower, upper=upper, floor=floors.T.ravel(),
        lower_eps=lower_eps, lower_eta=lower_eta, containing=containing,
        floor_eps=np.stack([md.floor_eps for md in modes]), floor_eta=np.stack([md.floor_eta for md in modes]),
        n_modes=M, eps_rule=eps_rule, combine=combine, eta=None if eta_fixed is None else np.array(eta_fixed),
        floor_tol=float(floor_tol))


def _box_rows(partition: BoxPartition, cell_bounds: CellBounds, modes, combine, block_size, eps_rule, eta_fixed,
              floor_tol) -> AbstractionRows:
    """:func:`abstract_rows` on a :class:`~robust_imdp.models.geometry.BoxPartition` (cells of different sizes).

    The same Thm 1 bounds as the rectilinear path, entry by entry: the targets of a row are the
    cells whose closed box meets ``Im ⊕ e_f`` (found through the partition's spatial index,
    :meth:`BoxPartition.intersecting`), the gap to a target along axis j is
    ``max(lo_j(q') - b_j, a_j - hi_j(q'))`` rounded down (the rectilinear path's per-interval gap),
    the containing cell is the listed cell with positive margins ``min(a_j - lo_j(q'), hi_j(q') - b_j)``
    on every axis (at most one: cells have disjoint interiors), and every other cell is
    separated from ``Im ⊕ e_f`` along some axis, so the floor bounds it. Each entry is computed
    by the same operations in the same order as there, so a ``BoxPartition`` whose cells are
    a grid gives the same numbers as the ``Partition`` of that grid.
    """
    M, N, d = cell_bounds.n_modes, cell_bounds.n_cells, cell_bounds.dim
    Xlo, Xhi = partition.space.lower, partition.space.upper
    tlo, thi = partition.cells_lower, partition.cells_upper
    # ---------------------------------------------------------------- pass 1: listed targets per row
    listed = []
    n_listed = np.empty((M, N), dtype=np.int64)
    floors = np.empty((M, N))
    for u, md in enumerate(modes):
        a, b = cell_bounds.image_lower[u], cell_bounds.image_upper[u]
        ef = _up1(md.floor_eps + md.floor_eta)
        qq, cc = partition.intersecting(_down1(a - ef), _up1(b + ef))  # closed box ⊇ Im ⊕ e_f
        n_listed[u] = np.bincount(qq, minlength=N)
        off = np.zeros(N + 1, dtype=np.int64)
        np.cumsum(n_listed[u], out=off[1:])
        listed.append((off, cc))
        floors[u] = _complement_up(_combine_down(md.floor_p, md.floor_pv, combine))
    row_len = (n_listed + 1).T.ravel()  # rows q*M + u (the outside state's rows: assemble_abstraction)
    row_ptr = np.zeros(row_len.size + 1, dtype=np.int64)
    np.cumsum(row_len, out=row_ptr[1:])
    nnz = int(row_ptr[-1])
    col = np.empty(nnz, dtype=np.int64)
    lower = np.zeros(nnz)
    upper = np.empty(nnz)
    lower_eps = np.full((M, N, d), np.nan)
    lower_eta = np.full((M, N, d), np.nan)
    containing = np.full((M, N), -1, dtype=np.int64)

    # ---------------------------------------------------------------- pass 2: bounds, block by block
    for u, md in enumerate(modes):
        off_all, cc_all = listed[u]
        for start in range(0, N, block_size):
            rows = np.arange(start, min(start + block_size, N))
            B = rows.size
            a = cell_bounds.image_lower[u, rows]
            b = cell_bounds.image_upper[u, rows]
            nl = n_listed[u, rows]
            E = int(nl.sum())
            er = np.repeat(np.arange(B), nl)  # block-local row of each entry
            cols = cc_all[off_all[start]:off_all[start] + E]
            # -- cell containing Im(q) with positive margins (Thm 1, eq. lower-bound)
            m = np.empty((E, d))
            for j in range(d):
                m[:, j] = _down1(np.minimum(a[er, j] - tlo[cols, j], thi[cols, j] - b[er, j]))
            hit = np.flatnonzero(np.all(m > 0, axis=1))  # at most one entry per row
            rin = er[hit]
            Pc, PVc = np.zeros((hit.size, d)), np.zeros((hit.size, d))
            for j in range(d):
                p_, pv_, e_, h_ = md.split(m[hit, j], rows[rin], j, paper_candidate=True)
                Pc[:, j], PVc[:, j] = p_, pv_
                lower_eps[u, rows[rin], j], lower_eta[u, rows[rin], j] = e_, h_
            low_in = _combine_down(Pc, PVc, combine) if hit.size else np.zeros(0)
            low_c = np.zeros(B)
            cont = np.full(B, -1, dtype=np.int64)
            low_c[rin] = low_in
            cont[rin] = np.where(low_in > 0, cols[hit], -1)
            containing[u, rows] = cont
            lower_eps[u, rows[cont < 0]] = np.nan
            lower_eta[u, rows[cont < 0]] = np.nan
            # -- outside state (corollary)
            PX, PVX = np.zeros((B, d)), np.zeros((B, d))
            g_out = np.zeros(B)
            for j in range(d):
                mX = _down1(np.minimum(a[:, j] - Xlo[j], Xhi[j] - b[:, j]))
                PX[:, j], PVX[:, j], _, _ = md.split(mX, rows, j, paper_candidate=True)
                gX = _down1(np.maximum(Xlo[j] - b[:, j], a[:, j] - Xhi[j]))
                sp, spv, _, _ = md.split(gX, rows, j, paper_candidate=False)
                g_out = np.maximum(g_out, _separated_best(md, sp, spv, rows, j))
            up_out = _complement_up(_combine_down(PX, PVX, combine))  # 1 - P_g P_v 1[Im ⊕ e ⊆ X]
            low_out = g_out  # 1 - (1 - P_g P_v 1[Im ⊕ e ∩ X = ∅])
            # -- listed cells: per-axis gaps of every entry, then the separation bound
            G = np.zeros(E)
            P0, PV0 = md.top(rows)
            for j in range(d):
                gap = _down1(np.maximum(tlo[cols, j] - b[er, j], a[er, j] - thi[cols, j]))
                sp, spv, _, _ = md.split(gap, rows[er], j, paper_candidate=False)
                P, PV = P0[er], PV0[er]
                P[:, j], PV[:, j] = sp, spv
                G = np.maximum(G, _combine_down(P, PV, combine))
            low = np.where(cols == cont[er], low_c[er], 0.0)
            # -- scatter into the state-major CSR (row = q * M + u), outside state last
            eoff = np.zeros(B + 1, dtype=np.int64)
            np.cumsum(nl, out=eoff[1:])
            grow = rows * M + u
            dest = row_ptr[grow][er] + np.arange(E) - eoff[er]
            col[dest] = cols
            upper[dest] = _complement_up(G)
            lower[dest] = low
            dout = row_ptr[grow + 1] - 1
            col[dout] = partition.n_cells  # the outside state (global index)
            upper[dout] = up_out
            lower[dout] = low_out
    return AbstractionRows(
        row_len=row_len, col=col, lower=lower, upper=upper, floor=floors.T.ravel(),
        lower_eps=lower_eps, lower_eta=lower_eta, containing=containing,
        floor_eps=np.stack([md.floor_eps for md in modes]), floor_eta=np.stack([md.floor_eta for md in modes]),
        n_modes=M, eps_rule=eps_rule, combine=combine, eta=None if eta_fixed is None else np.array(eta_fixed),
        floor_tol=float(floor_tol))


def select_rows(rows: AbstractionRows, cells) -> AbstractionRows:
    """The rows of ``cells`` (local indices into ``rows``' cells), in that order: a chunk of its own.

    With :func:`join_rows` this lets a refinement keep the rows of the cells it did not touch
    (a row depends only on its cell's image box and on the target cells it lists).
    """
    cells = np.asarray(cells, dtype=np.int64)
    M = rows.n_modes
    ptr = np.zeros(rows.row_len.size + 1, dtype=np.int64)
    np.cumsum(rows.row_len, out=ptr[1:])
    r = (cells[:, None] * M + np.arange(M)[None, :]).ravel()
    lens = rows.row_len[r]
    starts = np.repeat(ptr[r], lens)
    o = np.zeros(r.size + 1, dtype=np.int64)
    np.cumsum(lens, out=o[1:])
    idx = starts + np.arange(int(o[-1])) - np.repeat(o[:-1], lens)
    return AbstractionRows(
        row_len=lens, col=rows.col[idx], lower=rows.lower[idx], upper=rows.upper[idx], floor=rows.floor[r],
        lower_eps=rows.lower_eps[:, cells], lower_eta=rows.lower_eta[:, cells], containing=rows.containing[:, cells],
        floor_eps=rows.floor_eps[:, cells], floor_eta=rows.floor_eta[:, cells], n_modes=M, eps_rule=rows.eps_rule,
        combine=rows.combine, eta=rows.eta, floor_tol=rows.floor_tol)


def join_rows(chunks) -> AbstractionRows:
    """Concatenate chunks of rows (in the order given) into one :class:`AbstractionRows`."""
    chunks = list(chunks)
    f = chunks[0]

    def cat(name, axis=0):
        return np.concatenate([getattr(c, name) for c in chunks], axis=axis)

    return AbstractionRows(
        row_len=cat("row_len"), col=cat("col"), lower=cat("lower"), upper=cat("upper"), floor=cat("floor"),
        lower_eps=cat("lower_eps", 1), lower_eta=cat("lower_eta", 1), containing=cat("containing", 1),
        floor_eps=cat("floor_eps", 1), floor_eta=cat("floor_eta", 1), n_modes=f.n_modes, eps_rule=f.eps_rule,
        combine=f.combine, eta=f.eta, floor_tol=f.floor_tol)


def assemble_abstraction(partition: Partition, chunks) -> Abstraction:
    """Concatenate :func:`abstract_rows` results (in cell order, covering every cell once) into the IMDP.

    Adds the absorbing outside state and checks every row (``sum(lower) <= 1 <= sum(upper) +
    floor x unlisted``).
    """
    chunks = list(chunks)
    if not chunks:
        raise InvalidInputError("chunks must hold at least one AbstractionRows; got none")
    M = chunks[0].n_modes
    N = partition.n_cells
    n_rows = sum(c.row_len.size for c in chunks)
    if n_rows != N * M or any(c.n_modes != M for c in chunks):
        raise DimensionError(f"chunks must cover the {N} cells x {M} modes of the partition once; got {n_rows} rows")
    row_len = np.concatenate([c.row_len for c in chunks] + [np.ones(M, dtype=np.int64)])
    row_ptr = np.zeros(row_len.size + 1, dtype=np.int64)
    np.cumsum(row_len, out=row_ptr[1:])
    col = np.concatenate([c.col for c in chunks] + [np.full(M, N, dtype=np.int64)])
    lower = np.concatenate([c.lower for c in chunks] + [np.ones(M)])
    upper = np.concatenate([c.upper for c in chunks] + [np.ones(M)])
    # outside-state rows: absorbing self-loops [1, 1], floor 0
    floor = np.concatenate([c.floor for c in chunks] + [np.zeros(M)])
    _check_rows(row_ptr, lower, upper, floor, N + 1, M)
    state_ptr = np.arange(0, (N + 1) * M + 1, M, dtype=np.int64)
    actions = np.tile(np.arange(M, dtype=np.int64), N + 1)
    imdp = IMDP.from_csr(state_ptr, row_ptr, col, lower, upper, floor=floor, actions=actions)
    first = chunks[0]

    def cat(name, axis=1):
        return np.concatenate([getattr(c, name) for c in chunks], axis=axis)

    return Abstraction(
        imdp=imdp, partition=partition, eps_rule=first.eps_rule, combine=first.combine, eta=first.eta,
        floor_tol=first.floor_tol, floor_eps=cat("floor_eps"), floor_eta=cat("floor_eta"),
        lower_eps=cat("lower_eps"), lower_eta=cat("lower_eta"), containing_cell=cat("containing"),
        nnz_per_row=row_len,
    )


def _check_rows(row_ptr, lower, upper, floor, n_states, M):
    """Raise SoundnessError naming the first row with sum(lower) > 1 or sum(upper)+floor*unlisted < 1.

    Exact float sums are not available, so the comparison allows the summation error
    ``len(row) * u`` (entries are in [0, 1]); anything beyond is a bug.
    """
    n = np.diff(row_ptr)
    s_low = np.add.reduceat(lower, row_ptr[:-1]) if lower.size else np.zeros(n.size)
    s_up = np.add.reduceat(upper, row_ptr[:-1]) + floor * (n_states - n)
    tol = (n + 2) * 4 * _U
    bad = np.flatnonzero((s_low > 1 + tol) | (s_up < 1 - tol))
    if bad.size:
        r = int(bad[0])
        raise SoundnessError(
            f"row {r} (state {r // M}, mode {r % M}): sum(lower) = {s_low[r]!r}, "
            f"sum(upper) + floor x unlisted = {s_up[r]!r}; expected sum(lower) <= 1 <= sum(upper) + floor x unlisted"
        )
