"""Per-dimension probabilities of Thm 1's good events and their outward-rounded combinations.

For each mode, :class:`_Mode` holds candidate pairs (eps, p): a GP-error radius eps per cell and
dimension with a lower bound p of ``P[sup_cell |g_i - mu_i| <= eps]`` (``eps = 0, p = 1`` for known
dynamics), plus the noise side (eta and ``P[|v_i| <= eta_i]``). :meth:`_Mode.split` chooses, for
a margin or gap ``t`` along one axis, the best split ``eps + eta < t``; :func:`_combine_down` and
:func:`_complement_up` turn per-dimension lower bounds into ``P_g P_v`` (rounded down) and
``1 - P_g P_v`` (rounded up). The choice of eps and eta is described in ``abstraction.rows``.
"""

from __future__ import annotations

import numpy as np

from robust_imdp._fp import U, outward, up

__all__ = ["EPS_LEVELS"]

#: Probability levels at which candidate eps are proposed (``eps_for_prob(level, std)``).
EPS_LEVELS = 1.0 - np.array(
    [0.5, 0.3, 0.2, 0.1, 0.05, 0.02, 0.01, 5e-3, 2e-3, 1e-3, 5e-4, 2e-4, 1e-4, 3e-5, 1e-5,
     3e-6, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-12]
)
_PAPER_LEVEL = 0.99
_SHRINK = 1.0 - 2.0 ** -40  # makes eta = (t - eps) * _SHRINK strictly below t - eps in reals


def _combine_down(p, pv, combine: str):
    """Lower bound of ``P(E_g) P(E_v)`` from per-dimension lower bounds ``p, pv`` (..., d)."""
    d = p.shape[-1]
    if combine == "product":
        g = np.prod(p, axis=-1) * np.prod(pv, axis=-1)
        # product of 2d factors in [0,1]: relative error <= (2d - 1) u; g == 1 only if exact
        err = np.where(g == 1.0, 0.0, (2 * d) * 2 * U * g)
    else:
        g = np.maximum(1.0 - np.sum(1.0 - p, axis=-1), 0.0) * np.maximum(1.0 - np.sum(1.0 - pv, axis=-1), 0.0)
        # each sum of d complements and the final difference: absolute error <= (2d + 2) u per
        # factor; the clamp at 0 is safe (the union bound of a probability is >= 0 anyway)
        err = np.where(g == 1.0, 0.0, (4 * d + 6) * U)
    return np.maximum(outward(g, err, upward=False), 0.0)  # clamp: a probability is >= 0


def _complement_up(g):
    """Upper bound of ``1 - g`` for a float ``g`` in [0, 1] (Sterbenz: exact when g >= 0.5)."""
    val = 1.0 - g
    # clamp at 1 is safe: every transition probability is <= 1
    return np.minimum(outward(val, np.where(g >= 0.5, 0.0, U), upward=True), 1.0)


class _Mode:
    """Per-mode candidate (eps, p) arrays and the noise context (internal)."""

    def __init__(self, u, bounds, errors, noise, eta_fixed, rule, floor_tol, combine):
        n, d = bounds.n_cells, bounds.dim
        self.noise, self.combine, self.rule = noise, combine, rule
        self.errors = None if errors is None else errors.mode(u)  # None: known dynamics
        levels = np.array([_PAPER_LEVEL]) if rule == "paper" else EPS_LEVELS
        k99 = int(np.flatnonzero(levels == _PAPER_LEVEL)[0])
        K = levels.size
        # Known dynamics (image boxes exact up to their own rounding): every candidate is the pair
        # eps = 0, p = 1, the same for every cell. One candidate per cell is then enough: split's
        # argmax keeps the first of equal scores, so K equal candidates pick what one picks, and
        # the floor and top pairs are the same for every cell (computed once, broadcast).
        self._same = self.errors is None
        if self._same:
            self.eps = np.zeros((1, d, 1))
            self.p = np.ones((1, d, 1))
        else:
            self.eps = np.empty((n, d, K))
            self.p = np.empty((n, d, K))
            for i in range(d):
                e = np.stack([np.asarray(self.errors.eps_for_prob(i, lv), dtype=float) * np.ones(n)
                              for lv in levels], axis=1)
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
        if self._same:  # the one candidate (0, 1) whatever the rule
            self.p_top, self.eps_top = np.ones((n, d)), np.zeros((n, d))
        elif rule == "paper":
            self.p_top, self.eps_top = self.p[:, :, k99], self.eps[:, :, k99]
        else:
            kt = np.argmax(self.p, axis=2)
            self.p_top = np.take_along_axis(self.p, kt[..., None], 2)[..., 0]
            self.eps_top = np.take_along_axis(self.eps, kt[..., None], 2)[..., 0]
        # --- floor pair per (cell, dim)
        if rule == "paper":
            self.floor_p = np.broadcast_to(self.p[:, :, 0] if self._same else self.p[:, :, k99], (n, d)).copy()
            self.floor_eps = np.broadcast_to(self.eps[:, :, 0] if self._same else self.eps[:, :, k99], (n, d)).copy()
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
            # (n, d, L); known dynamics: one row (1, d, L) of p = 1 for every cell
            pk = np.ones((1, d, lv.size)) if self._same else self.p[:, :, k99:]
            ek = np.zeros((1, d, lv.size)) if self._same else self.eps[:, :, k99:]
            score = pk * pv_l.T[None]
            good = score >= 1.0 - floor_tol / d
            kf = np.where(good.any(axis=2), np.argmax(good, axis=2), np.argmax(score, axis=2))
            self.floor_p = np.broadcast_to(np.take_along_axis(pk, kf[..., None], 2)[..., 0], (n, d)).copy()
            self.floor_eps = np.broadcast_to(np.take_along_axis(ek, kf[..., None], 2)[..., 0], (n, d)).copy()
            self.floor_pv = np.broadcast_to(pv_l[kf, np.arange(d)[None, :]], (n, d)).copy()
            self.floor_eta = np.broadcast_to(eta_l[kf, np.arange(d)[None, :]], (n, d)).copy()

    def _prob(self, i, eps, rows):
        """Lower bound ``p_i(eps)`` of the learning-error event for cells ``rows`` (broadcast with eps)."""
        if self.errors is None:
            return np.ones(np.shape(eps))
        return self.errors.prob_within(i, eps, rows)

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
            if self._same:  # the one candidate of every cell
                E = np.broadcast_to(self.eps[0, i, :], (t.size, 1))
                P = np.broadcast_to(self.p[0, i, :], (t.size, 1))
            else:
                E = self.eps[rows, i, :]
                P = self.p[rows, i, :]
            tt = t[:, None]
            if self.fixed:
                ETA = np.broadcast_to(self.eta_def[i], E.shape)
                ok = up(E + self.eta_def[i]) < tt
                PV = np.where(ok, self.pv_def[i], 0.0)
            else:
                with np.errstate(invalid="ignore"):
                    eta1 = (tt - E) * _SHRINK  # eps + eta1 < t in exact arithmetic (module doc)
                eta1 = np.where(np.isfinite(eta1), eta1, -1.0)
                pv1 = self.noise.marginal_prob_abs_le(eta1, i)
                okd = up(E + self.eta_def[i]) < tt
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
