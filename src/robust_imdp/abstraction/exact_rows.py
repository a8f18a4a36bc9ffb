r"""The joint interval MDP from the exact per-axis bounds (``[abstraction].transitions = "exact"``).

Valid on any box partition (a grid, a refined :class:`~robust_imdp.models.geometry.BoxPartition`) and
for both ``combine`` rules; docs/abstraction.md has the proofs. For a cell ``q``, a mode ``u`` and an
``x in q`` the next state is ``y + v`` with ``y`` in the image box ``Y = prod_i Y_i`` and ``v`` the
noise; a target cell is a box ``z = prod_i z_i``.

* ``combine = "product"`` (independent noise components, as every ``NoiseModel`` here):
  ``P[y + v in z] = prod_i P[y_i + v_i in z_i]``, each factor in ``[lower_i(z_i), upper_i(z_i)]``
  (``abstraction.marginals``), so ``prod_i lower_i <= T(z | x) <= prod_i upper_i`` (equality of the
  bounds' extremes over the box ``Y``, since every factor depends on its own ``y_i`` only). The
  outside state: ``T(out | x) = 1 - prod_i P[in_i]`` with ``P[in_i] = 1 - P[out_i]``, increasing in
  every ``P[out_i]``; written ``sum_i o_i prod_{j < i} (1 - o_j)`` (no cancellation) and evaluated
  at the per-axis outside bounds (tightened by the listed mass: ``P[out_i] <= 1 - sum lower_i``,
  ``P[out_i] >= 1 - sum upper_i - rest_i`` on a grid).
* ``combine = "union"`` (no independence between components assumed): only the marginals are
  known, and Frechet's bounds hold: ``max(0, sum_i lower_i - (d - 1)) <= T(z | x) <= min_i upper_i``
  and ``max_i P[out_i] <= T(out | x) <= min(1, sum_i P[out_i])``.
* **Unlisted targets and the floor.** A row lists the cells whose every side meets the listed run
  of its axis (grid) or which meet the listing box ``Y ⊕ R`` (``BoxPartition``). An unlisted cell
  has some side ``z_i`` among the unlisted intervals of axis i, whose total mass is at most
  ``rest_i``, so ``T(z | x) <= rest_i prod_{j != i} m_j`` (``m_j`` bounds every interval of axis j:
  the largest listed upper bound or ``rest_j``; on a ``BoxPartition`` ``m_j = 1``); the row's
  ``floor`` is the largest of these, raised to ``floor_level`` where it is positive (any larger
  floor is an upper bound too; a zero floor, e.g. of bounded noise, stays 0). Listed entries whose upper bound is at most the floor are dropped (they are covered by it;
  only their lower bound, at most the floor, is lost). ``abstract`` passes ``floor_tol / 20``
  (docs/abstraction.md: on car parking about 330 instead of 530 entries per row, the same Q_yes).
* **A learned error that holds with probability** ``P_g`` (the GP route with
  ``guarantee = "paper"``): on the error event ``E_g`` the image box grows by ``eps`` and the bounds
  above hold for the grown box; off it nothing is known. Thm 1 combines them the same way
  (``abstraction.rows``): ``T >= P_g lower_eps`` and ``T <= P_g upper_eps + (1 - P_g)``; each of a
  few probability levels gives a valid pair and the best of them is kept per entry (the floor and
  the outside state alike). Such models are not factored: the mixture over ``E_g`` is no product.

Rounding: products and sums of non-negative bounds are rounded by ``gamma(n)`` and one ulp
(``robust_imdp._fp``), subnormal products get an absolute allowance, and zeros stay exact (a
factor that is exactly 0 makes the product exactly 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robust_imdp._fp import U, down, gamma, up
from robust_imdp.abstraction.cell_bounds import CellBounds, CellErrors
from robust_imdp.abstraction.marginals import AXIS_TOL, axis_data, axis_runs, interval_bounds, outside_bounds, \
    rest_bounds
from robust_imdp.abstraction.periodic import arc_pieces
from robust_imdp.abstraction.targets import targets_of
from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.models.geometry import BoxPartition, Partition
from robust_imdp.models.noise import NoiseModel

__all__ = ["ExactRows", "exact_rows", "GP_LEVELS"]

#: Probability levels of the learned-error radius eps tried per row on the GP route (``P_g`` mixture).
GP_LEVELS = (0.9, 0.99, 1.0 - 1e-4, 1.0 - 1e-8)
#: Entries (rows x listed products) expanded at once (memory only).
BLOCK_ENTRIES = 1 << 21
_TINY = 2.0 ** -1000  # below this, products may be subnormal: an absolute allowance joins the bound


@dataclass(frozen=True, eq=False)
class ExactRows:
    """The rows of a chunk of cells (all modes), row ``q * M + u``; each row's last entry is the outside state.

    ``row_len`` (R,), ``col``/``lower``/``upper`` (nnz,) with global cell indices (``n_cells`` = outside),
    ``floor`` (R,): the bound of every unlisted cell.
    """

    row_len: np.ndarray
    col: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    floor: np.ndarray
    n_modes: int
    tol: float


# --------------------------------------------------------------------------- rounding of products and sums
def _prod_up(P, n):
    """Upper bound of a product of ``n + 1`` factors in [0, 1] computed as ``P`` (``gamma(n)``, subnormal allowance).

    Exact where ``P`` is 0 (a factor is 0) or 1 (every factor is 1: a float product of factors <= 1 rounds
    to 1 only then)."""
    r = up(P, gamma(max(n, 1)) * P)
    return np.where((P == 0.0) | (P == 1.0), P, np.where(r < _TINY, up(r + (n + 2) * 2.0 ** -1074), r))


def _prod_down(P, n):
    """Lower bound of such a product (0 where it may be subnormal: 0 is always a lower bound; exact at 0 and 1)."""
    r = np.maximum(down(P, gamma(max(n, 1)) * P), 0.0)
    return np.where(P == 1.0, 1.0, np.where(r < _TINY, 0.0, r))


def _fold_out(o, upward):
    """``1 - prod_i (1 - o_i)`` as ``sum_i o_i prod_{j<i} (1 - o_j)``: a non-negative expression of ``3d`` roundings."""
    d = o.shape[-1]
    acc = np.zeros(o.shape[:-1])
    keep = np.ones(o.shape[:-1])
    for i in range(d):
        acc = acc + o[..., i] * keep
        keep = keep * (1.0 - o[..., i])
    n = 3 * d
    exact = np.any(o == 1.0, axis=-1)  # some axis surely outside: exactly 1
    if upward:
        val = np.minimum(np.where(acc == 0, 0.0, up(acc, gamma(n) * acc + 2.0 ** -1074 * n)), 1.0)
    else:
        val = np.maximum(down(acc, gamma(n) * acc + 2.0 ** -1074 * n), 0.0)
    return np.where(exact, 1.0, val)


# --------------------------------------------------------------------------- candidates (P_g mixture)
@dataclass(frozen=True)
class _Candidate:
    lower: np.ndarray  # (M, N, d) image box grown by eps
    upper: np.ndarray
    pg: np.ndarray | None  # (M, N) lower bound of P(E_g); None: 1 (known dynamics or folded error)


def _candidates(cell_bounds: CellBounds, errors: CellErrors | None, combine: str):
    """The image boxes to bound: the given ones, or one grown box per level of :data:`GP_LEVELS` with its ``P_g``."""
    if errors is None:
        return [_Candidate(cell_bounds.image_lower, cell_bounds.image_upper, None)]
    M, N, d = cell_bounds.image_lower.shape
    out = []
    for level in GP_LEVELS:
        lo = np.empty((M, N, d))
        hi = np.empty((M, N, d))
        p = np.empty((M, N, d))
        for u in range(M):
            me = errors.mode(u)
            for i in range(d):
                e = np.asarray(me.eps_for_prob(i, level), dtype=float) * np.ones(N)
                ok = np.isfinite(e) & (e >= 0)
                e = np.where(ok, e, 0.0)
                pr = me.prob_within(i, e, np.arange(N))
                p[u, :, i] = np.where(ok, pr, 0.0)
                lo[u, :, i] = down(cell_bounds.image_lower[u, :, i] - e)  # Y ⊕ eps, outward
                hi[u, :, i] = up(cell_bounds.image_upper[u, :, i] + e)
        if combine == "product":
            g = np.prod(p, axis=-1)
            pg = np.maximum(down(g, gamma(d) * g), 0.0)  # product of d factors in [0, 1]
        else:
            g = 1.0 - np.sum(1.0 - p, axis=-1)
            pg = np.maximum(down(g, (2 * d + 2) * U), 0.0)  # union bound; clamp: P(E_g) >= 0
        out.append(_Candidate(lo, hi, pg))
    return out


def _mix_lower(low, pg):
    """``P_g lower`` rounded down (the lower bound on the error event)."""
    if pg is None:
        return low
    return np.maximum(down(low * pg), 0.0) * (low > 0)


def _mix_upper(upp, pg):
    """``P_g upper + (1 - P_g)`` rounded up (decreasing in P_g: a lower bound of P(E_g) is safe)."""
    if pg is None:
        return upp
    return np.minimum(up(up(upp * pg) + up(1.0 - pg)), 1.0)


# --------------------------------------------------------------------------- the entry point
def exact_rows(partition, cell_bounds: CellBounds, noise: NoiseModel, error_models=None, *, combine: str = "product",
               tol: float = AXIS_TOL, floor_level: float = 0.0) -> ExactRows:
    """The exact-transition rows of the cells whose image boxes ``cell_bounds`` holds (a chunk, or all cells).

    Parameters
    ----------
    partition : Partition or BoxPartition
    cell_bounds : CellBounds
        ``(n_modes, n_cells_chunk, d)`` image boxes (and ``std_upper`` on the GP route).
    noise : NoiseModel
    error_models : as in :func:`robust_imdp.abstraction.rows.abstract`, or None
    combine : {"product", "union"}
        Independent noise components (products) or none assumed (Frechet bounds); on the GP route
        also how the per-component error probabilities combine into ``P_g``.
    tol : float in (0, 1)
        Per-axis listing tolerance (:data:`~robust_imdp.abstraction.marginals.AXIS_TOL`).
    floor_level : float in [0, 1)
        Every row's floor is at least this; entries whose upper bound is at most the floor are not listed.

    Returns
    -------
    ExactRows
    """
    if not isinstance(partition, (Partition, BoxPartition)):
        raise InvalidInputError(f"partition must be a Partition or a BoxPartition; got {type(partition).__name__}")
    if not isinstance(cell_bounds, CellBounds):
        raise InvalidInputError(f"cell_bounds must be a CellBounds; got {type(cell_bounds).__name__}")
    if not isinstance(noise, NoiseModel):
        raise InvalidInputError(f"noise must be a NoiseModel; got {type(noise).__name__}")
    if combine not in ("product", "union"):
        raise InvalidInputError(f"combine must be 'product' or 'union'; got {combine!r}")
    if not 0.0 < float(tol) < 1.0:
        raise InvalidInputError(f"tol must lie in (0, 1); got {tol!r}")
    if not 0.0 <= float(floor_level) < 1.0:
        raise InvalidInputError(f"floor_level must lie in [0, 1); got {floor_level!r}")
    if cell_bounds.dim != partition.dim or noise.dim != partition.dim:
        raise DimensionError(f"cell_bounds and noise must have dimension {partition.dim} like the partition; got "
                             f"{cell_bounds.dim} and {noise.dim}")
    if (error_models is None) != (cell_bounds.std_upper is None):
        raise InvalidInputError("error_models must be given exactly when cell_bounds.std_upper is given")
    errors = CellErrors.from_gp(cell_bounds, error_models)
    cands = _candidates(cell_bounds, errors, combine)
    # the listing covers every candidate's box (the widest one grown by the listing radius)
    wide_lo = np.min(np.stack([c.lower for c in cands]), axis=0)
    wide_hi = np.max(np.stack([c.upper for c in cands]), axis=0)
    R = noise.listing_radius(tol)
    wlo, whi = down(wide_lo - R), up(wide_hi + R)
    if isinstance(partition, BoxPartition):
        return _box_rows(partition, cands, noise, combine, wlo, whi, float(tol), float(floor_level))
    return _grid_rows(partition, cands, noise, combine, wlo, whi, float(tol), float(floor_level))


# --------------------------------------------------------------------------- grids: per-axis runs, then products
def _grid_rows(partition, cands, noise, combine, wlo, whi, tol, floor_level):
    """Rows on a grid: per axis each row's own run (so a row does not depend on the chunk), then products."""
    M, N, d = wlo.shape
    shape = partition.shape
    starts, counts, ks = [], [], []
    for j in range(d):
        first, count = axis_runs(partition, j, wlo[:, :, j], whi[:, :, j])
        starts.append(first)
        counts.append(count)
        ks.append(int(max(1, count.max(initial=1))))  # array width only: entries past a row's count are not listed
    # per candidate and axis: the marginal bounds of this chunk's rows
    data = [[axis_data(partition, j, c.lower[:, :, j], c.upper[:, :, j], noise, starts[j], counts[j], ks[j])
             for j in range(d)] for c in cands]
    K = int(np.prod(ks))
    strides = np.cumprod((1,) + tuple(shape[::-1]))[:-1][::-1]
    periodic = [partition.periodic is not None and partition.periodic[j] for j in range(d)]
    rows_per_block = max(1, BLOCK_ENTRIES // max(K, 1))
    R_all = N * M
    out = {"row_len": [], "col": [], "lower": [], "upper": [], "floor": []}
    for r0 in range(0, R_all, rows_per_block):
        r = np.arange(r0, min(R_all, r0 + rows_per_block))
        q, u = r // M, r % M
        B = r.size
        # joint columns of the listed box (B, K)
        col = np.zeros((B,) + (1,) * d, dtype=np.int64)
        for j in range(d):
            view = [B] + [1] * d
            view[j + 1] = ks[j]
            pos = starts[j][u, q][:, None] + np.arange(ks[j])
            pos = pos % shape[j] if periodic[j] else np.minimum(pos, shape[j] - 1)  # past the count: not listed
            col = col + pos.reshape(view) * int(strides[j])
        col = np.broadcast_to(col, (B,) + tuple(ks)).reshape(B, K)
        low = upp = fl = olo = ohi = None
        for c, cand in enumerate(cands):
            per = [tuple(x[u, q] for x in data[c][j]) for j in range(d)]
            lo_c, up_c, fl_c, olo_c, ohi_c = _joint(per, ks, combine, grid=shape)
            pg = None if cand.pg is None else cand.pg[u, q]
            lo_c, olo_c = _mix_lower(lo_c, None if pg is None else pg[:, None]), _mix_lower(olo_c, pg)
            up_c, ohi_c, fl_c = (_mix_upper(up_c, None if pg is None else pg[:, None]), _mix_upper(ohi_c, pg),
                                 _mix_upper(fl_c, pg))
            if low is None:
                low, upp, fl, olo, ohi = lo_c, up_c, fl_c, olo_c, ohi_c
            else:  # every candidate's pair is valid: keep the best (the GP route's levels)
                low, upp, fl = np.maximum(low, lo_c), np.minimum(upp, up_c), np.minimum(fl, fl_c)
                olo, ohi = np.maximum(olo, olo_c), np.minimum(ohi, ohi_c)
        listed = np.ones((B,) + (1,) * d, dtype=bool)
        for j in range(d):
            view = [B] + [1] * d
            view[j + 1] = ks[j]
            listed = listed & (np.arange(ks[j])[None, :] < counts[j][u, q][:, None]).reshape(view)
        listed = np.broadcast_to(listed, (B,) + tuple(ks)).reshape(B, K)
        _emit(out, col, low, upp, _raise_floor(fl, floor_level), olo, ohi, partition.n_cells, listed)
    return _finish(out, M, tol)


def _joint(per, ks, combine, grid):
    """Joint bounds of the listed box from per-axis data ``per[j] = (lower (B, k_j), upper, ol (B,), ou, rest)``.

    ``grid``: the grid's shape (the listed mass tightens the outside bounds), or None (a ``BoxPartition``).
    Returns ``(lower (B, K), upper (B, K), floor (B,), out_lower (B,), out_upper (B,))``. Nothing here
    depends on the padding ``k_j`` (sums run left to right, their error bound counts the grid's intervals):
    a row's bounds are the same in every chunk.
    """
    d = len(per)
    B = per[0][0].shape[0]
    K = int(np.prod(ks))
    shape_full = (B,) + tuple(ks)
    if combine == "product":
        plo = np.ones((B,) + (1,) * d)
        phi = np.ones((B,) + (1,) * d)
        for j, (lo, hi, _, _, _) in enumerate(per):
            view = [B] + [1] * d
            view[j + 1] = ks[j]
            plo = plo * lo.reshape(view)
            phi = phi * hi.reshape(view)
        low = _prod_down(np.broadcast_to(plo, shape_full).reshape(B, K), d - 1)
        upp = np.minimum(_prod_up(np.broadcast_to(phi, shape_full).reshape(B, K), d - 1), 1.0)  # safe: <= 1
    else:  # Frechet: max(0, sum lower - (d - 1)) and min upper
        slo = np.zeros((B,) + (1,) * d)
        phi = np.ones((B,) + (1,) * d)
        for j, (lo, hi, _, _, _) in enumerate(per):
            view = [B] + [1] * d
            view[j + 1] = ks[j]
            slo = slo + lo.reshape(view)
            phi = np.minimum(phi, hi.reshape(view))
        s = np.broadcast_to(slo, shape_full).reshape(B, K) - (d - 1)
        # d - 1 additions of partial sums <= d and one subtraction: absolute error <= (d^2 + 1) u <= 4 d^2 u
        low = np.where(s > 4 * d * d * U, np.maximum(down(s, 4 * d * d * U), 0.0), 0.0)
        upp = np.broadcast_to(phi, shape_full).reshape(B, K).copy()
    # outside: per-axis outside bounds tightened by the listed mass (grid only), then combined
    o_lo = np.empty((B, d))
    o_hi = np.empty((B, d))
    for j, (lo, hi, ol, ou, rest) in enumerate(per):
        if grid is not None:
            s_lo = np.cumsum(lo, axis=1)[:, -1]  # left to right: padding zeros change nothing
            s_hi = np.cumsum(hi, axis=1)[:, -1] + rest
            n = int(grid[j]) + 1  # at most n_j listed terms and the rest
            # P[out_j] <= 1 - P[listed] <= 1 - sum lower; P[out_j] >= 1 - sum upper - rest
            cap = np.where(s_lo == 0, 1.0, up(1.0 - down(s_lo, gamma(n) * s_lo)))
            flo = np.where(s_hi >= 1.0, 0.0, down(1.0 - up(s_hi, gamma(n) * s_hi)))
            o_hi[:, j] = np.minimum(ou, cap)
            o_lo[:, j] = np.maximum(ol, flo)
            o_lo[:, j] = np.minimum(o_lo[:, j], o_hi[:, j])
        else:
            o_lo[:, j], o_hi[:, j] = ol, ou
    periodic_only = np.all(o_hi == 0, axis=1)
    if combine == "product":
        out_lo = _fold_out(o_lo, False)
        out_hi = _fold_out(o_hi, True)
    else:
        out_lo = np.max(o_lo, axis=1)
        out_hi = np.minimum(np.where(periodic_only, 0.0, up(np.sum(o_hi, axis=1), gamma(d) * np.sum(o_hi, axis=1))),
                            1.0)
    out_lo = np.where(periodic_only, 0.0, np.minimum(out_lo, out_hi))
    # floor: an unlisted cell has a side among axis i's unlisted intervals (mass <= rest_i)
    floor = np.zeros(B)
    for i, (_, hi_i, _, _, rest_i) in enumerate(per):
        bound = rest_i.copy()
        if combine == "product" and grid is not None:
            for j, (_, hi_j, _, _, rest_j) in enumerate(per):
                if j != i:
                    m_j = np.maximum(hi_j.max(axis=1, initial=0.0), rest_j)
                    bound = bound * m_j
            bound = _prod_up(bound, d - 1)
        floor = np.maximum(floor, bound)
    return low, upp, np.minimum(floor, 1.0), out_lo, out_hi


def _raise_floor(floor, level):
    """The floor raised to ``level`` where it is positive (a zero floor, e.g. of bounded noise, stays exact)."""
    return np.where(floor > 0, np.maximum(floor, level), 0.0)


def _emit(out, col, low, upp, floor, out_lo, out_hi, n_cells, listed):
    """Append a block's rows: listed entries above the floor, then the outside state."""
    B, K = col.shape
    keep = np.empty((B, K + 1), dtype=bool)
    keep[:, :K] = listed & (upp > floor[:, None])  # at most the floor: covered by it as an unlisted cell
    keep[:, K] = True
    C = np.empty((B, K + 1), dtype=np.int64)
    C[:, :K], C[:, K] = col, n_cells
    Lo = np.empty((B, K + 1))
    Lo[:, :K], Lo[:, K] = np.minimum(low, upp), out_lo
    Up = np.empty((B, K + 1))
    Up[:, :K], Up[:, K] = upp, out_hi
    out["row_len"].append(keep.sum(axis=1))
    out["col"].append(C[keep])
    out["lower"].append(Lo[keep])
    out["upper"].append(Up[keep])
    out["floor"].append(floor)


def _finish(out, M, tol):
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}
    return ExactRows(row_len=cat["row_len"].astype(np.int64), col=cat["col"].astype(np.int64), lower=cat["lower"],
                     upper=cat["upper"], floor=cat["floor"], n_modes=M, tol=tol)


# --------------------------------------------------------------------------- box partitions: per-entry sides
def _window_rest(noise, j, a, b, wlo, whi, L, H, circle):
    """Upper bound of the mass of X outside the listing window on axis j (every unlisted cell's side lies there)."""
    if circle is None:
        pieces = [(np.full(a.shape, L), np.minimum(wlo, H), wlo > L), (np.maximum(whi, L), np.full(a.shape, H), whi < H)]
        return rest_bounds(noise, j, a, b, pieces, None)
    (p1lo, p1hi, _), (_, p2hi, two) = arc_pieces(wlo, whi, L, H)
    pieces = [(p2hi, p1lo, two), (np.full(a.shape, L), p1lo, ~two), (p1hi, np.full(a.shape, H), ~two)]
    return rest_bounds(noise, j, a, b, pieces, circle)


def _box_rows(partition, cands, noise, combine, wlo, whi, tol, floor_level):
    M, N, d = wlo.shape
    targets = targets_of(partition)
    cl, ch = partition.cells_lower, partition.cells_upper
    ids = []
    for j in range(d):  # the distinct sides of the cells per axis
        _, inv = np.unique(np.stack([cl[:, j], ch[:, j]], axis=1), axis=0, return_inverse=True)
        ids.append(inv.reshape(-1))
    per_mode = []
    for u in range(M):
        n_listed, (off, cc) = targets.list(wlo[u], whi[u])
        E = int(n_listed.sum())
        er = np.repeat(np.arange(N), n_listed)
        cells = cc[:E]
        low = upp = fl = olo = ohi = None
        for cand in cands:
            per_lo, per_hi, per = [], [], []
            for j in range(d):
                L, H = float(partition.space.lower[j]), float(partition.space.upper[j])
                circle = (L, H) if partition.periodic is not None and partition.periodic[j] else None
                a, b = cand.lower[u, :, j], cand.upper[u, :, j]
                # one evaluation per (row, distinct side)
                key = er * (int(ids[j].max(initial=0)) + 1) + ids[j][cells]
                uk, first, inv = np.unique(key, return_index=True, return_inverse=True)
                rr, c0 = er[first], cells[first]
                lo_k, hi_k = interval_bounds(noise, j, a[rr], b[rr], cl[c0, j], ch[c0, j], circle)
                per_lo.append(lo_k[inv.reshape(-1)])
                per_hi.append(hi_k[inv.reshape(-1)])
                rest = _window_rest(noise, j, a, b, wlo[u, :, j], whi[u, :, j], L, H, circle)
                if circle is None:
                    ol, ou = outside_bounds(noise, j, a, b, L, H)
                else:
                    ol, ou = np.zeros(N), np.zeros(N)
                per.append((ol, ou, rest))
            lo_c, up_c = _entry_products(per_lo, per_hi, combine)
            _, _, fl_c, olo_c, ohi_c = _joint([(np.zeros((N, 1)), np.zeros((N, 1)), ol, ou, rest)
                                               for ol, ou, rest in per], [1] * d, combine, grid=None)
            pg = None if cand.pg is None else cand.pg[u]
            lo_c, olo_c = _mix_lower(lo_c, None if pg is None else pg[er]), _mix_lower(olo_c, pg)
            up_c, ohi_c, fl_c = (_mix_upper(up_c, None if pg is None else pg[er]), _mix_upper(ohi_c, pg),
                                 _mix_upper(fl_c, pg))
            if low is None:
                low, upp, fl, olo, ohi = lo_c, up_c, fl_c, olo_c, ohi_c
            else:
                low, upp, fl = np.maximum(low, lo_c), np.minimum(upp, up_c), np.minimum(fl, fl_c)
                olo, ohi = np.maximum(olo, olo_c), np.minimum(ohi, ohi_c)
        fl = _raise_floor(fl, floor_level)
        keep = upp > fl[er]
        per_mode.append((er[keep], cells[keep], np.minimum(low, upp)[keep], upp[keep], fl, olo, ohi))
    # rows in cell-major order (q * M + u), each row's listed cells then the outside state
    rows, cols, lows, upps = [], [], [], []
    for u, (er, cells, lo, hi, fl, olo, ohi) in enumerate(per_mode):
        rows += [er * M + u, np.arange(N) * M + u]
        cols += [cells, np.full(N, partition.n_cells, dtype=np.int64)]
        lows += [lo, olo]
        upps += [hi, ohi]
        # the outside entry must come last in its row: sort key (row, is_outside, position)
    row = np.concatenate(rows)
    col = np.concatenate(cols)
    is_out = col == partition.n_cells
    order = np.lexsort((np.arange(row.size), is_out, row))
    floor = np.empty(N * M)
    for u, pm in enumerate(per_mode):
        floor[np.arange(N) * M + u] = pm[4]
    return ExactRows(row_len=np.bincount(row, minlength=N * M).astype(np.int64), col=col[order],
                     lower=np.concatenate(lows)[order], upper=np.concatenate(upps)[order], floor=floor, n_modes=M,
                     tol=tol)


def _entry_products(per_lo, per_hi, combine):
    """Joint bounds of listed entries from their per-axis bounds ``(E,)`` each."""
    d = len(per_lo)
    if combine == "product":
        return (_prod_down(np.prod(np.stack(per_lo), axis=0), d - 1),
                np.minimum(_prod_up(np.prod(np.stack(per_hi), axis=0), d - 1), 1.0))
    s = np.sum(np.stack(per_lo), axis=0) - (d - 1)
    low = np.where(s > 4 * d * d * U, np.maximum(down(s, 4 * d * d * U), 0.0), 0.0)
    return low, np.min(np.stack(per_hi), axis=0)
