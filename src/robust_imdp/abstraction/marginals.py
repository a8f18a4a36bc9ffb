r"""Exact per-axis transition bounds: min and max over the image interval of the noise's mass in a target interval.

For a cell q, a mode u and an axis i, the next state's i-th coordinate is ``x'_i = y_i + v_i`` with
``y = f_u(x) + g_u(x)`` for some ``x in q``, so ``y_i`` lies in the certified image interval
``Y_i = [a, b]`` (``CellBounds``), and ``v_i`` is the axis's noise (independent of ``y``). For a
target interval ``z = [l, h]`` on the axis (a grid interval, or a refined cell's side)::

    lower_i(z) = min_{y in Y_i} g(y),   upper_i(z) = max_{y in Y_i} g(y),   g(y) = P[y + v_i in [l, h]],

and the same for "outside X on this axis" (``1 - g`` of ``X``'s own interval). docs/abstraction.md
has the proofs; in short:

* **Unimodality** (non-periodic axes). Every noise model here has a symmetric density ``phi``,
  non-increasing in ``|t|``. ``g'(y) = phi(l - y) - phi(h - y)``, and ``|l - y| <= |h - y|`` iff
  ``y <= m = (l + h)/2``: ``g`` rises up to ``m`` and falls after it. So the minimum over
  ``[a, b]`` is at an end and the maximum at ``clip(m, a, b)``; the outside probability ``1 - g_X``
  is smallest at ``clip((L + H)/2, a, b)`` and largest at an end.
* **Periodic axes** (period ``T = H - L``): ``G(y) = sum_k g(y - kT)`` is the mass of the interval
  under the wrapped law. When that law is symmetric unimodal on the circle
  (``NoiseModel.wrapped_unimodal``: always for Gaussian noise, for bounded noise when
  ``bound <= T/2``), ``G`` is largest at the arc centre ``m`` and smallest at its antipode
  ``m + T/2``, monotone in between: the maximum over the arc ``[a, b] mod T`` is ``G(m)`` if the
  arc holds ``m``, else at an end; the minimum is ``G(m + T/2)`` if the arc holds the antipode,
  else at an end. Otherwise the bound is the sum over copies of each copy's own (non-periodic)
  bounds, which is sound for any law (a sum of minima is below the minimum of the sum).
  The infinite sum is truncated soundly: the copies ``k < k_lo`` all lie in
  ``v <= h + (k_lo - 1) T - y`` (the intervals are disjoint), so their total is at most that tail
  probability, which joins the upper bound (and is dropped from the lower bound).

**Rounding** (outward). The ends ``l - y`` (and ``l + kT - y``) are enclosed with ``robust_imdp._fp``
(one correctly rounded subtraction: one ulp; three terms: ``gamma(2)``); ``kT`` is enclosed as in
``abstraction.periodic``. Where the extremum's location ``y*`` is known only within a float
enclosure ``[y_lo, y_hi]``, the bound is taken over the whole enclosure (an upper bound with the
interval ``[l - y_hi, h - y_lo]``, a lower bound with ``[l - y_lo, h - y_hi]``: a wider/narrower
interval has more/less mass). The probabilities themselves are the noise model's certified
``interval_prob_lower`` / ``interval_prob_upper`` (``models.noise``: ``ndtr`` with an allowance
measured against mpmath). Where the location test (does the arc hold ``m``?) cannot be decided in
floats, the global extremum ``G(m)`` / ``G(m + T/2)`` is used, which bounds every value.

**Sparse listing.** Per (mode, cell, axis) the listed intervals are the contiguous (cyclic on a
periodic axis) run meeting ``[a - R, b + R]``, ``R = noise.listing_radius(tol)`` (so that the mass
beyond is about ``tol``), widened to one length ``k`` per axis (the longest run) for the
:class:`~robust_imdp.models.factored.AxisMarginals` arrays. ``rest_upper`` bounds the total mass of
the unlisted in-grid intervals: they form at most two intervals of X (``[L, l_first]`` and
``[h_last, H]``; on a circle one arc, cut at the seam into at most two), and the maximum over
``Y_i`` of each one's mass is computed like any target's (the sum of the two maxima bounds the
maximum of the sum). The listing only decides which bounds are stored: every bound is sound for
any listing.
"""

from __future__ import annotations

import numpy as np

from robust_imdp._fp import U, down, gamma, up
from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.models.factored import AxisMarginals
from robust_imdp.models.geometry import Partition
from robust_imdp.models.noise import NoiseModel

__all__ = ["AXIS_TOL", "MAX_COPIES", "interval_bounds", "outside_bounds", "axis_marginals", "axis_runs", "axis_data",
           "rest_bounds"]

#: Listing tolerance per axis: intervals are listed out to the radius ``R`` with ``P[|v_i| > R] = tol``,
#: so ``rest_upper`` is about ``tol / 2`` (the one-sided tail beyond the listed run). 1e-9 keeps the
#: joint floor (docs/abstraction.md) a thousand times below Thm 1's default ``floor_tol`` (1e-6).
AXIS_TOL = 1e-9
#: Copies of a target per side summed on a periodic axis (beyond them the tail bound takes over).
MAX_COPIES = 32
#: Mass of the noise beyond the copies summed on a periodic axis (a choice of accuracy, not of soundness).
_COPY_TAIL = 1e-16


# --------------------------------------------------------------------------- enclosures
def _sub(x, y, upward: bool):
    """``x - y`` rounded to the safe side (one correctly rounded subtraction; +-inf pass through)."""
    d = np.asarray(x, dtype=float) - y
    return up(d) if upward else down(d)


def _sum3(x, y, z, upward: bool):
    """The real ``x + y + z`` bounded from above / below (two roundings: ``gamma(2)`` of the magnitudes)."""
    s = (x + y) + z
    err = gamma(2) * (np.abs(x) + np.abs(y) + np.abs(z))
    return up(s, err) if upward else down(s, err)


def _half_sum(x, y):
    """``[lo, hi]`` enclosing the real ``(x + y) / 2`` (the halving is exact)."""
    return down(x + y) * 0.5, up(x + y) * 0.5


def _shift_bounds(k, period_lo, period_hi):
    """``[S_lo, S_hi]`` enclosing ``k T`` for integer floats ``k`` and the real period ``T in [period_lo, period_hi]``."""
    s_lo = np.where(k >= 0, k * period_lo, k * period_hi)
    s_hi = np.where(k >= 0, k * period_hi, k * period_lo)
    # one rounding of the product: one ulp outward; k = 0 exact
    return np.where(k == 0, 0.0, down(s_lo)), np.where(k == 0, 0.0, up(s_hi))


# --------------------------------------------------------------------------- one copy, non-periodic
def _p_lower(noise, i, l, h, y_lo, y_hi, s_lo=None, s_hi=None):
    """Lower bound of ``min_{y in [y_lo, y_hi]} P[y + v_i in [l + S, h + S]]`` (``S = kT`` enclosed, or 0).

    The interval ``[l + S - y_lo, h + S - y_hi]`` lies inside every ``[l + S - y, h + S - y]``, and its
    ends are rounded inward."""
    if s_lo is None:
        alpha, beta = _sub(l, y_lo, True), _sub(h, y_hi, False)
    else:
        alpha, beta = _sum3(l, s_hi, -y_lo, True), _sum3(h, s_lo, -y_hi, False)
    return noise.interval_prob_lower(alpha, beta, i)


def _p_upper(noise, i, l, h, y_lo, y_hi, s_lo=None, s_hi=None):
    """Upper bound of ``max_{y in [y_lo, y_hi]} P[y + v_i in [l + S, h + S]]`` (the union interval, ends outward)."""
    if s_lo is None:
        alpha, beta = _sub(l, y_hi, False), _sub(h, y_lo, True)
    else:
        alpha, beta = _sum3(l, s_lo, -y_hi, False), _sum3(h, s_hi, -y_lo, True)
    return noise.interval_prob_upper(alpha, beta, i)


def _sum_down(terms, axis=-1):
    """Lower bound of the real sum of non-negative floats (``gamma(n)`` relative, one ulp; clamped at 0: safe)."""
    n = terms.shape[axis]
    s = np.sum(terms, axis=axis)
    return np.maximum(down(s, gamma(max(n - 1, 1)) * s), 0.0)


def _sum_up(terms, axis=-1):
    """Upper bound of the real sum of non-negative floats (``gamma(n)`` relative, one ulp; exact when 0)."""
    n = terms.shape[axis]
    s = np.sum(terms, axis=axis)
    return np.where(s == 0.0, 0.0, up(s, gamma(max(n - 1, 1)) * s))


def _line_bounds(noise, i, a, b, l, h):
    """``(lower, upper)`` of ``g(y) = P[y + v_i in [l, h]]`` over ``y in [a, b]`` (unimodal ``g``, module doc)."""
    lower = np.minimum(_p_lower(noise, i, l, h, a, a), _p_lower(noise, i, l, h, b, b))
    m_lo, m_hi = _half_sum(l, h)
    upper = _p_upper(noise, i, l, h, np.clip(m_lo, a, b), np.clip(m_hi, a, b))  # y* = clip(m, a, b) in there
    return lower, upper


# --------------------------------------------------------------------------- periodic axes
class _Circle:
    """One periodic axis ``[L, H]`` of a noise component: period enclosure and the copies to sum."""

    def __init__(self, noise: NoiseModel, i: int, L: float, H: float):
        self.noise, self.i, self.L, self.H = noise, i, float(L), float(H)
        self.T = self.H - self.L
        self.T_lo, self.T_hi = float(down(self.T)), float(up(self.T))
        self.unimodal = noise.wrapped_unimodal(self.T, i)
        reach = float(noise.listing_radius(_COPY_TAIL)[i])  # copies farther than this hold < 1e-16 together
        self.K = int(min(MAX_COPIES, np.ceil(reach / self.T) + 1))

    def _copies(self, centre, extra=0):
        """(..., C) integer floats ``k``: the copies around ``centre`` (a float estimate of the nearest one)."""
        K = self.K + extra
        return np.round(centre)[..., None] + np.arange(-K, K + 1, dtype=float)

    def mass(self, l, h, y_lo, y_hi, upward: bool, k=None):
        """Bound of ``min`` (``upward=False``) / ``max`` over ``y in [y_lo, y_hi]`` of ``G(y) = sum_k P[y + v in [l, h] + kT]``.

        The copies ``k`` (default: ``self.K`` each side of the nearest one) are summed; the copies
        beyond them add their tail probabilities to the upper bound and nothing to the lower bound.
        """
        l, h, y_lo, y_hi = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (l, h, y_lo, y_hi)))
        if k is None:
            k = self._copies((0.5 * (y_lo + y_hi) - 0.5 * (l + h)) / self.T)
        s_lo, s_hi = _shift_bounds(k, self.T_lo, self.T_hi)
        ex = (..., None)
        if not upward:
            terms = _p_lower(self.noise, self.i, l[ex], h[ex], y_lo[ex], y_hi[ex], s_lo, s_hi)
            return _sum_down(terms)
        terms = _p_upper(self.noise, self.i, l[ex], h[ex], y_lo[ex], y_hi[ex], s_lo, s_hi)
        # tails: copies below k[..., 0] lie in v <= h + (k0 - 1) T - y; copies above k[..., -1] in v >= l + (k1 + 1) T - y
        b_lo, b_hi = _shift_bounds(k[..., :1] - 1.0, self.T_lo, self.T_hi)
        t_lo, t_hi = _shift_bounds(k[..., -1:] + 1.0, self.T_lo, self.T_hi)
        below = self.noise.interval_prob_upper(-np.inf, _sum3(h[ex], b_hi, -y_lo[ex], True), self.i)
        above = self.noise.interval_prob_upper(_sum3(l[ex], t_lo, -y_hi[ex], False), np.inf, self.i)
        return np.minimum(_sum_up(np.concatenate([terms, below, above], axis=-1)), 1.0)  # safe: a probability

    def contains(self, a, b, p_lo, p_hi):
        """Whether the arc ``[a, b] mod T`` may hold a point of ``[p_lo, p_hi] mod T`` (False only when it surely does not).

        ``r = (p - a) mod T`` (``np.mod``: an exact remainder, then at most one rounding) against
        ``b - a``, with a slop that exceeds every rounding error on the way (``p - a``, the period's
        rounding times the number of periods), and the width of ``[p_lo, p_hi]``.
        """
        T = self.T
        p = 0.5 * (p_lo + p_hi)
        mag = np.abs(p) + np.abs(a) + np.abs(b) + abs(self.L) + abs(self.H)
        slop = (p_hi - p_lo) + 1e-12 * T + 64.0 * U * mag
        r = np.mod(p - a, T)
        return ((b - a) >= T - slop) | (r <= (b - a) + slop) | (r >= T - slop)

    def bounds(self, a, b, l, h):
        """``(lower, upper)`` of ``G`` over ``y in [a, b]`` (module doc: unimodal on the circle, else per copy)."""
        a, b, l, h = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (a, b, l, h)))
        if not self.unimodal:
            return self._per_copy(a, b, l, h)
        m_lo, m_hi = _half_sum(l, h)
        an_lo, an_hi = down(m_lo + 0.5 * self.T_lo), up(m_hi + 0.5 * self.T_hi)  # the antipode m + T/2
        upper = np.where(self.contains(a, b, m_lo, m_hi), self.mass(l, h, m_lo, m_hi, True),
                         np.maximum(self.mass(l, h, a, a, True), self.mass(l, h, b, b, True)))
        lower = np.where(self.contains(a, b, an_lo, an_hi), self.mass(l, h, an_lo, an_hi, False),
                         np.minimum(self.mass(l, h, a, a, False), self.mass(l, h, b, b, False)))
        return lower, upper

    def _per_copy(self, a, b, l, h):
        """Bounds as sums over the copies of each copy's own bounds (any symmetric unimodal law; looser)."""
        centre = (0.5 * (a + b) - 0.5 * (l + h)) / self.T
        extra = int(min(MAX_COPIES, np.ceil(np.max(0.5 * (b - a), initial=0.0) / self.T) + 1))
        k = self._copies(centre, extra)
        s_lo, s_hi = _shift_bounds(k, self.T_lo, self.T_hi)
        ex = (..., None)
        lo = np.minimum(_p_lower(self.noise, self.i, l[ex], h[ex], a[ex], a[ex], s_lo, s_hi),
                        _p_lower(self.noise, self.i, l[ex], h[ex], b[ex], b[ex], s_lo, s_hi))
        m_lo, m_hi = _half_sum(l, h)
        ys_lo = np.clip(down(m_lo[ex] + s_lo), a[ex], b[ex])  # copy k's centre m + kT, enclosed, clipped to [a, b]
        ys_hi = np.clip(up(m_hi[ex] + s_hi), a[ex], b[ex])
        hi = _p_upper(self.noise, self.i, l[ex], h[ex], ys_lo, ys_hi, s_lo, s_hi)
        b_lo, b_hi = _shift_bounds(k[..., :1] - 1.0, self.T_lo, self.T_hi)
        t_lo, t_hi = _shift_bounds(k[..., -1:] + 1.0, self.T_lo, self.T_hi)
        below = self.noise.interval_prob_upper(-np.inf, _sum3(h[ex], b_hi, -a[ex], True), self.i)
        above = self.noise.interval_prob_upper(_sum3(l[ex], t_lo, -b[ex], False), np.inf, self.i)
        upper = np.minimum(_sum_up(np.concatenate([hi, below, above], axis=-1)), 1.0)  # safe: a probability
        return np.minimum(_sum_down(lo), upper), upper


# --------------------------------------------------------------------------- public per-axis bounds
def _check_axis(noise, i):
    if not isinstance(noise, NoiseModel):
        raise InvalidInputError(f"noise must be a NoiseModel; got {type(noise).__name__}")
    if not 0 <= int(i) < noise.dim:
        raise DimensionError(f"axis i must lie in [0, {noise.dim}) for this noise; got {i}")


def interval_bounds(noise: NoiseModel, i: int, a, b, l, h, circle=None):
    """Certified ``min`` and ``max`` over ``y in [a, b]`` of ``P[y + v_i in [l, h]]`` (wrapped on a circle).

    Parameters
    ----------
    noise : NoiseModel
    i : int
        The axis (noise component).
    a, b : float arrays (broadcast), ``a <= b``
        The image interval ``Y_i``.
    l, h : float arrays (broadcast), ``l <= h``
        The target interval (``h - l <= H - L`` on a circle).
    circle : (L, H) or None
        The axis is periodic with period ``H - L``: the target is the union of its translates.

    Returns
    -------
    lower, upper : float arrays (the broadcast shape), ``0 <= lower <= upper <= 1``
    """
    _check_axis(noise, i)
    a, b, l, h = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (a, b, l, h)))
    if circle is not None:
        return _Circle(noise, i, *circle).bounds(a, b, l, h)
    return _line_bounds(noise, i, a, b, l, h)


def outside_bounds(noise: NoiseModel, i: int, a, b, L: float, H: float):
    """Certified ``min`` and ``max`` over ``y in [a, b]`` of ``P[y + v_i not in [L, H]]`` (a non-periodic axis).

    ``P[y + v < L] + P[y + v > H] = 1 - g_X(y)``: largest at an end of ``[a, b]`` (each end's two tails
    rounded up, summed up), smallest at ``y* = clip((L + H)/2, a, b)``, where each tail is bounded
    from below over ``y*``'s enclosure (the left tail falls with y, the right one rises).

    Returns
    -------
    out_lower, out_upper : float arrays
    """
    _check_axis(noise, i)
    a, b = np.broadcast_arrays(np.asarray(a, dtype=float), np.asarray(b, dtype=float))
    L, H = float(L), float(H)

    def tails_up(y):
        left = noise.interval_prob_upper(-np.inf, _sub(L, y, True), i)
        right = noise.interval_prob_upper(_sub(H, y, False), np.inf, i)
        return np.where((left == 0) | (right == 0), left + right, up(left + right))  # x + 0 is exact

    out_upper = np.minimum(np.maximum(tails_up(a), tails_up(b)), 1.0)  # safe: a probability
    m_lo, m_hi = _half_sum(L, H)
    y_lo, y_hi = np.clip(m_lo, a, b), np.clip(m_hi, a, b)
    left = noise.interval_prob_lower(-np.inf, _sub(L, y_hi, False), i)
    right = noise.interval_prob_lower(_sub(H, y_lo, True), np.inf, i)
    out_lower = np.where((left == 0) | (right == 0), left + right, np.maximum(down(left + right), 0.0))
    return np.minimum(out_lower, out_upper), out_upper


def rest_bounds(noise: NoiseModel, i: int, a, b, pieces, circle=None):
    """Upper bound of ``max_{y in [a, b]}`` of the total mass of ``pieces`` (intervals of X, disjoint interiors).

    ``pieces`` : list of ``(l, h, valid)`` arrays; an invalid or empty piece adds nothing. The sum
    of the pieces' maxima bounds the maximum of their sum.
    """
    total = np.zeros(np.broadcast(np.asarray(a), np.asarray(b)).shape)
    for l, h, valid in pieces:
        _, upper = interval_bounds(noise, i, a, b, l, h, circle)
        upper = np.where(valid & (h > l), upper, 0.0)
        total = np.where((total == 0) | (upper == 0), total + upper, up(total + upper))  # x + 0 is exact
    return np.minimum(total, 1.0)  # safe: a probability


# --------------------------------------------------------------------------- the factored arrays of a grid
def _runs(bp, lo, hi, circle):
    """``(first, count)`` of the grid intervals of ``bp`` meeting ``[lo, hi]`` (a cyclic run on a circle)."""
    n = bp.size - 1
    if circle is not None:
        from robust_imdp.abstraction.periodic import intervals_on_circle

        return intervals_on_circle(bp, lo, hi, circle[0], circle[1])
    first = np.searchsorted(bp[1:], lo, side="left")
    last = np.searchsorted(bp[:-1], hi, side="right") - 1
    first = np.minimum(first, n - 1)
    return first.astype(np.int64), np.maximum(last - first + 1, 0).astype(np.int64)


def axis_marginals(partition: Partition, image_lower, image_upper, noise: NoiseModel, *, tol: float = AXIS_TOL,
                   block_size: int = 65536) -> tuple:
    """The per-axis bounds of every (mode, cell) of a grid, as :class:`~robust_imdp.models.factored.AxisMarginals`.

    Parameters
    ----------
    partition : Partition
        The grid (``breakpoints``, ``space``, ``periodic``); may be non-uniform (regions refine it).
    image_lower, image_upper : (n_modes, n_cells, d) float arrays
        The certified image boxes (``CellBounds.image_lower`` / ``image_upper``) of the cells whose
        marginals are wanted (all the partition's cells, or a chunk of them).
    noise : NoiseModel
        Independent components (the product law the factored model assumes).
    tol : float in (0, 1)
        Listing tolerance (:data:`AXIS_TOL`).
    block_size : int
        Cells per vectorised block (memory only).

    Returns
    -------
    tuple of d AxisMarginals
        Axis j: ``start`` (M, N), ``lower``/``upper`` (M, N, k_j) with ``k_j`` the longest listed run
        (every row lists ``k_j`` intervals: its own run, widened where the grid allows), ``out_lower``
        / ``out_upper`` (0 on periodic axes), ``rest_upper``.
    """
    if not isinstance(partition, Partition):
        raise InvalidInputError(f"partition must be a Partition (a grid); got {type(partition).__name__}")
    lo_all = np.asarray(image_lower, dtype=float)
    hi_all = np.asarray(image_upper, dtype=float)
    if lo_all.ndim != 3 or lo_all.shape != hi_all.shape or lo_all.shape[2] != partition.dim:
        raise DimensionError(f"image_lower and image_upper must have shape (n_modes, n_cells, {partition.dim}); "
                             f"got {lo_all.shape} and {hi_all.shape}")
    if noise.dim != partition.dim:
        raise DimensionError(f"noise must have dimension {partition.dim}; got {noise.dim}")
    if not 0.0 < float(tol) < 1.0:
        raise InvalidInputError(f"tol must lie in (0, 1); got {tol!r}")
    M, N, d = lo_all.shape
    R = noise.listing_radius(tol)
    axes = []
    for j in range(d):
        n = partition.shape[j]
        a, b = lo_all[:, :, j], hi_all[:, :, j]
        first, count = axis_runs(partition, j, down(a - R[j]), up(b + R[j]))
        k = int(max(1, count.max(initial=1)))
        # one run length k per axis: a run is widened (to the left where it would pass the grid's end)
        start = first if _circle(partition, j) is not None else np.where(
            count > 0, np.minimum(first, n - k), np.clip(first, 0, n - k))
        parts = [np.empty((M, N, k)), np.empty((M, N, k)), np.empty((M, N)), np.empty((M, N)), np.empty((M, N))]
        for c0 in range(0, N, block_size):
            sl = slice(c0, min(N, c0 + block_size))
            for arr, val in zip(parts, axis_data(partition, j, a[:, sl], b[:, sl], noise, start[:, sl],
                                                 np.full(start[:, sl].shape, k), k)):
                arr[:, sl] = val
        lower, upper, ol, ou, rest = parts
        axes.append(AxisMarginals(n=n, periodic=_circle(partition, j) is not None, start=start, lower=lower,
                                  upper=upper, out_lower=ol, out_upper=ou, rest_upper=rest, axis=j))
    return tuple(axes)


def _circle(partition, j):
    """``(L, H)`` of axis j when it is periodic, else None."""
    if partition.periodic is not None and partition.periodic[j]:
        return float(partition.space.lower[j]), float(partition.space.upper[j])
    return None


def axis_runs(partition: Partition, j: int, lo, hi):
    """``(first, count)`` (shape of ``lo``): the grid intervals of axis ``j`` meeting ``[lo, hi]`` (cyclic on a circle)."""
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    first, count = _runs(partition.breakpoints[j], lo.ravel(), hi.ravel(), _circle(partition, j))
    return first.reshape(lo.shape), count.reshape(lo.shape)


def axis_data(partition: Partition, j: int, a, b, noise: NoiseModel, start, count, k: int):
    """Bounds of axis ``j`` for image intervals ``[a, b]`` and listed runs ``[start, start + count)`` (any shape S).

    Returns ``(lower (S + (k,)), upper, out_lower (S), out_upper, rest_upper)``; entries ``t >= count``
    are not listed (0, 0) and their mass is part of ``rest_upper`` (the mass of every in-grid interval
    outside the run). ``count <= k``; non-periodic runs end at the grid's end at the latest.
    """
    bp = partition.breakpoints[j]
    n = bp.size - 1
    circle = _circle(partition, j)
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    t = np.arange(k)
    listed = t < count[..., None]
    idx = start[..., None] + t
    idx = idx % n if circle is not None else np.minimum(idx, n - 1)
    lower, upper = interval_bounds(noise, j, a[..., None], b[..., None], bp[idx], bp[idx + 1], circle)
    lower, upper = np.where(listed, lower, 0.0), np.where(listed, upper, 0.0)
    rest = rest_bounds(noise, j, a, b, _unlisted_pieces(bp, start, count, circle), circle)
    if circle is None:
        L, H = float(partition.space.lower[j]), float(partition.space.upper[j])
        ol, ou = outside_bounds(noise, j, a, b, L, H)
    else:
        ol, ou = np.zeros(a.shape), np.zeros(a.shape)
    return lower, upper, ol, ou, rest


def _unlisted_pieces(bp, start, count, circle):
    """The unlisted in-grid intervals of the runs ``[start, start + count)`` as at most two pieces of X each."""
    n = bp.size - 1
    end = start + count
    if circle is None:  # [L, bp[start]] and [bp[start + count], H]
        return [(np.full(start.shape, bp[0]), bp[np.minimum(start, n)], start > 0),
                (bp[np.minimum(end, n)], np.full(start.shape, bp[n]), end < n)]
    # the complement arc from the run's end forward to bp[start]: one piece [bp[end - n], bp[start]] when
    # the run wraps past the seam, else [bp[end], H] and [L, bp[start]]
    wraps = end > n
    full = count >= n  # the whole circle is listed: nothing is left
    return [(np.where(wraps, bp[np.clip(end - n, 0, n)], bp[np.minimum(end, n)]), np.where(wraps, bp[start], bp[n]),
             ~full),
            (np.full(start.shape, bp[0]), bp[start], ~full & ~wraps & (start > 0))]
