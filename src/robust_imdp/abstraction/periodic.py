r"""Periodic dimensions in Thm 1: gaps, margins and listed intervals on a circle (see docs/periodic.md).

Along a periodic dimension ``j`` of ``X = [L, H]`` (period ``T = H - L``) the state lives on a
circle: a target cell ``[lo, hi]`` is the set of its translates ``[lo + kT, hi + kT]``, k integer,
and an image box ``[a, b]`` (not wrapped: ``f_u(x) + mu_u(x)`` may leave ``[L, H]``) meets the cell
iff it meets one translate. Thm 1's two per-axis quantities become

* the **gap** ``min_k gap_k``, ``gap_k = max(lo + kT - b, a - hi - kT)``: ``Im ⊕ e`` misses every
  translate iff ``e < min_k gap_k`` (the upper bound of the cell, summed over its wrapped copies:
  each copy the expanded image can reach is listed, and one gap covers them all);
* the **margin** ``max_k margin_k``, ``margin_k = min(a - lo - kT, hi + kT - b)``: ``Im ⊕ e`` lies
  inside one translate iff ``e < max_k margin_k`` (the lower bound).

``gap_k`` is convex and ``margin_k`` concave piecewise linear in k, both optimal at the real
``k* = ((a + b) - (lo + hi)) / (2T)``; the optimum over the integers is at ``floor(k*)`` or
``ceil(k*)``, and the four integers ``floor(k̃) - 1 .. floor(k̃) + 2`` of a computed ``k̃`` contain
both even when ``k̃`` carries a rounding error. Evaluating only those four copies is exact (no copy
is dropped: ``benchmarks/mutations.py`` has the mutation that drops one).

Rounding (outward, :mod:`robust_imdp._fp`): ``kT`` is enclosed by ``[S_lo, S_hi]`` (``T`` and
``k T`` each rounded once: error ``<= gamma(3) |S|``); every gap or margin term is a sum of three
floats, rounded down by ``gamma(2)`` times the sum of their magnitudes and one ulp. With k = 0
the terms are computed exactly like the non-periodic ones (``S = 0``).

Listing: :func:`intervals_on_circle` returns, per query box, a cyclic run of intervals (the arc
the box covers, or every interval when it is at least a period wide), enlarged by a slop that
covers the float error of moving the box by whole periods. Listing too many targets is harmless
(each listed target gets its own sound bound); too few would not be.
"""

from __future__ import annotations

import numpy as np

from robust_imdp._fp import down, gamma, up

__all__: list = []

#: The copies ``floor(k̃) + OFFSETS`` evaluated per (image, target) pair (module doc).
_COPY_OFFSETS = (-1, 0, 1, 2)
#: Relative slop (w.r.t. the period) of the listed arc: a superset of the cells that can be met.
_LIST_SLOP = 1e-9


def _shift_bounds(k, period):
    """``[S_lo, S_hi]`` enclosing ``k (H - L)`` for integer floats ``k`` (``period = fl(H - L)``)."""
    s = k * period
    err = gamma(3) * np.abs(s)
    return np.where(k == 0, 0.0, down(s, err)), np.where(k == 0, 0.0, up(s, err))


def _sum3_down(x, y, z):
    """Lower bound of the real ``x + y + z`` (floats; two roundings)."""
    return down((x + y) + z, gamma(2) * (np.abs(x) + np.abs(y) + np.abs(z)))


def _copies(lo_t, hi_t, a, b, period):
    """The integers ``floor(k̃) + _COPY_OFFSETS``, (Q, 4), around the optimal copy of each pair."""
    with np.errstate(invalid="ignore", over="ignore"):
        k = np.floor(((a + b) - (lo_t + hi_t)) / (2.0 * period))
    return k[:, None] + np.asarray(_COPY_OFFSETS, dtype=float)[None, :]


def circle_gap(lo_t, hi_t, a, b, lower, upper):
    """Lower bound of ``min_k max(lo_t + kT - b, a - hi_t - kT)`` (the gap on the circle), (Q,)."""
    lo_t, hi_t, a, b = (np.asarray(v, dtype=float) for v in (lo_t, hi_t, a, b))
    period = upper - lower
    k = _copies(lo_t, hi_t, a, b, period)
    s_lo, s_hi = _shift_bounds(k, period)
    g = np.maximum(_sum3_down(lo_t[:, None], s_lo, -b[:, None]), _sum3_down(a[:, None], -s_hi, -hi_t[:, None]))
    return np.min(g, axis=1)


def circle_margin(lo_t, hi_t, a, b, lower, upper):
    """Lower bound of ``max_k min(a - lo_t - kT, hi_t + kT - b)`` (the margin on the circle), (Q,)."""
    lo_t, hi_t, a, b = (np.asarray(v, dtype=float) for v in (lo_t, hi_t, a, b))
    period = upper - lower
    k = _copies(lo_t, hi_t, a, b, period)
    s_lo, s_hi = _shift_bounds(k, period)
    m = np.minimum(_sum3_down(a[:, None], -lo_t[:, None], -s_hi), _sum3_down(hi_t[:, None], s_lo, -b[:, None]))
    return np.max(m, axis=1)


def _arc(lo, hi, lower, upper):
    """The query boxes ``[lo, hi]`` moved by whole periods: ``(lo2, hi2, full)``, lo2 in [L, H] (+ slop).

    ``full``: the box is (about) a period wide or more, so it meets every interval.
    """
    period = upper - lower
    slop = _LIST_SLOP * period + 64 * 2.0 ** -53 * (np.abs(lo) + np.abs(hi) + abs(lower) + abs(upper))
    full = (hi - lo) >= period - 2 * slop
    k = np.floor((lo - lower) / period)
    lo2, hi2 = lo - k * period - slop, hi - k * period + slop
    back = lo2 < lower  # starts just before the seam: the previous copy (its upper end)
    lo2, hi2 = np.where(back, lo2 + period, lo2), np.where(back, hi2 + period, hi2)
    return lo2, hi2, full


def intervals_on_circle(bp, lo, hi, lower, upper):
    """Cyclic runs of the intervals of ``bp`` (one periodic axis) meeting the boxes ``[lo, hi]`` (Q,).

    Returns ``(first, count)``, (Q,) int64: intervals ``(first + t) mod n``, ``t < count <= n``.
    """
    n = bp.size - 1
    lo2, hi2, full = _arc(lo, hi, lower, upper)
    period = upper - lower
    first = np.minimum(np.searchsorted(bp[1:], lo2, side="left"), n - 1)
    last = np.where(hi2 <= upper, np.searchsorted(bp[:-1], hi2, side="right") - 1,
                    n + np.searchsorted(bp[:-1], hi2 - period, side="right") - 1)
    count = np.clip(last - first + 1, 0, n)
    return np.where(full, 0, first).astype(np.int64), np.where(full, n, count).astype(np.int64)


def arc_pieces(lo, hi, lower, upper):
    """The query boxes as at most two intervals inside ``[L, H]`` each: ``[(plo, phi, valid)]`` (Q,) arrays."""
    lo2, hi2, full = _arc(lo, hi, lower, upper)
    period = upper - lower
    first = (np.where(full, lower, np.maximum(lo2, lower)), np.where(full, upper, np.minimum(hi2, upper)),
             np.ones(lo.shape, dtype=bool))
    second = (np.full(lo.shape, lower), np.minimum(hi2 - period, upper), ~full & (hi2 > upper))
    return [first, second]
