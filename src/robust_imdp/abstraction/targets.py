"""The target cells of each abstraction row, and the per-axis gaps to them, for both kinds of partition.

A row of cell q and mode u lists the cells whose closed box meets ``Im(q) ⊕ e_f`` (see
``abstraction.rows``). How they are found depends on the partition; what is computed for each
listed entry does not:

* :class:`_GridTargets` (a rectilinear :class:`~robust_imdp.models.geometry.Partition`): per axis
  the intervals the box meets, and the listed cells are their products (C order). The gap of an
  entry along axis j depends only on its interval there, so the eps/eta split of each gap is
  computed once per (row, axis, interval), not once per entry.
* :class:`_BoxTargets` (a :class:`~robust_imdp.models.geometry.BoxPartition`): the partition's
  spatial index (:meth:`BoxPartition.intersecting`), and the split of every entry's own gap.

Both give, per listed entry, the same floats: the gap along axis j is
``max(lo_j(q') - b_j, a_j - hi_j(q'))`` rounded down, and ``split`` is elementwise, so a
``BoxPartition`` whose cells are a grid gives the same numbers as the ``Partition`` of that grid.

Periodic dimensions (``partition.periodic``): there the listed intervals are a cyclic run and the
gap is the one on the circle (``abstraction.periodic``); the other axes are computed as above.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robust_imdp._fp import down
from robust_imdp.abstraction.periodic import arc_pieces, circle_gap, intervals_on_circle
from robust_imdp.models.geometry import BoxPartition, intervals_meeting

__all__: list = []


@dataclass(frozen=True)
class _Entries:
    """The listed entries of a block of rows, in row order then target order.

    ``row`` (E,): block-local row of each entry; ``cell`` (E,): its target cell (global index);
    ``gap_p``, ``gap_pv``: per axis j, (E,) lower bounds ``p_j``, ``P[|v_j| <= eta_j]`` of the best
    split of the entry's gap along j (``_Mode.split``; 0 where no split fits).
    """

    row: np.ndarray
    cell: np.ndarray
    gap_p: list
    gap_pv: list


def _gap(lo_t, hi_t, a, b):
    """Separation of the image ``[a, b]`` from the target ``[lo_t, hi_t]`` along one axis, rounded down."""
    return down(np.maximum(lo_t - b, a - hi_t))


def _axis_gap(space, periodic, j, lo_t, hi_t, a, b):
    """The gap along axis ``j``: :func:`_gap`, or the gap on the circle on a periodic axis."""
    if periodic is not None and periodic[j]:
        return circle_gap(lo_t, hi_t, a, b, float(space.lower[j]), float(space.upper[j]))
    return _gap(lo_t, hi_t, a, b)


class _GridTargets:
    """Targets in a rectilinear grid: per axis, the intervals a row's box meets."""

    def __init__(self, partition):
        self.breakpoints = partition.breakpoints
        self.shape = partition.shape
        self.space, self.periodic = partition.space, getattr(partition, "periodic", None)

    def list(self, lo, hi):
        """``(n_listed (N,), listing)``: the cells meeting each closed box ``[lo[q], hi[q]]``."""
        first, count = intervals_meeting(self.breakpoints, lo, hi)
        for j in np.flatnonzero(self.periodic or ()):  # a cyclic run of intervals on a periodic axis
            first[:, j], count[:, j] = intervals_on_circle(self.breakpoints[j], lo[:, j], hi[:, j],
                                                           float(self.space.lower[j]), float(self.space.upper[j]))
        n_listed = np.prod(count, axis=1)  # 0 when the box misses X
        count[n_listed == 0] = 0
        return n_listed, (first, count)

    def entries(self, listing, mode, rows, a, b, n_listed) -> _Entries:
        """The entries of the block ``rows`` (image boxes ``[a, b]``, ``n_listed`` entries per row)."""
        first, count = listing
        c = count[rows]  # (B, d)
        B, d = c.shape
        per_axis = []
        for j in range(d):  # the split of every (row, interval) gap along axis j
            bp = self.breakpoints[j]
            rr = np.repeat(np.arange(B), c[:, j])
            off = np.zeros(B + 1, dtype=np.int64)
            np.cumsum(c[:, j], out=off[1:])
            ell = first[rows, j][rr] + (np.arange(rr.size) - off[rr])
            if self.periodic is not None and self.periodic[j]:
                ell = ell % (bp.size - 1)
            gap = _axis_gap(self.space, self.periodic, j, bp[ell], bp[ell + 1], a[rr, j], b[rr, j])
            sp, spv, _, _ = mode.split(gap, rows[rr], j, paper_candidate=False)
            per_axis.append((off, ell, sp, spv))
        E = int(n_listed.sum())
        er = np.repeat(np.arange(B), n_listed)  # block-local row of each entry
        eoff = np.zeros(B + 1, dtype=np.int64)
        np.cumsum(n_listed, out=eoff[1:])
        t = np.arange(E) - eoff[er]
        loc = np.empty((E, d), dtype=np.int64)
        for j in range(d - 1, -1, -1):  # C-order unravel of the local index
            cj = c[er, j]
            loc[:, j] = t % np.maximum(cj, 1)
            t = t // np.maximum(cj, 1)
        multi, gap_p, gap_pv = [], [], []
        for j in range(d):
            off, ell, sp, spv = per_axis[j]
            idx = off[er] + loc[:, j]
            multi.append(ell[idx])
            gap_p.append(sp[idx])
            gap_pv.append(spv[idx])
        cells = np.ravel_multi_index(tuple(multi), self.shape) if E else np.zeros(0, dtype=np.int64)
        return _Entries(er, cells, gap_p, gap_pv)


class _BoxTargets:
    """Targets in a :class:`BoxPartition`: its spatial index, and every entry's own gap."""

    def __init__(self, partition: BoxPartition):
        self.partition = partition
        self.lower, self.upper = partition.cells_lower, partition.cells_upper
        self.space, self.periodic = partition.space, getattr(partition, "periodic", None)

    def list(self, lo, hi):
        """``(n_listed (N,), listing)``: the cells meeting each closed box ``[lo[q], hi[q]]``."""
        if self.periodic is None:
            qq, cc = self.partition.intersecting(lo, hi)
        else:
            qq, cc = self._intersecting_on_circle(lo, hi)
        n_listed = np.bincount(qq, minlength=lo.shape[0])
        off = np.zeros(lo.shape[0] + 1, dtype=np.int64)
        np.cumsum(n_listed, out=off[1:])
        return n_listed, (off, cc)

    def _intersecting_on_circle(self, lo, hi):
        """:meth:`BoxPartition.intersecting` of the boxes cut into pieces inside X on the periodic axes.

        Per periodic axis a box is at most two intervals in X (``arc_pieces``); the pieces' products
        are queried and every (row, cell) pair is kept once, rows ascending, cells ascending.
        """
        queries = [(lo.copy(), hi.copy(), np.ones(lo.shape[0], dtype=bool))]
        for j in np.flatnonzero(self.periodic):
            pieces = arc_pieces(lo[:, j], hi[:, j], float(self.space.lower[j]), float(self.space.upper[j]))
            nxt = []
            for qlo, qhi, ok in queries:
                for plo, phi, pok in pieces:
                    l2, h2 = qlo.copy(), qhi.copy()
                    l2[:, j], h2[:, j] = plo, phi
                    nxt.append((l2, h2, ok & pok))
            queries = nxt
        rows, cells = [], []
        for qlo, qhi, ok in queries:
            idx = np.flatnonzero(ok)
            q, c = self.partition.intersecting(qlo[idx], qhi[idx])
            rows.append(idx[q])
            cells.append(c)
        pairs = np.unique(np.stack([np.concatenate(rows), np.concatenate(cells)], axis=1), axis=0)
        return pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)

    def entries(self, listing, mode, rows, a, b, n_listed) -> _Entries:
        """The entries of the block ``rows`` (image boxes ``[a, b]``, ``n_listed`` entries per row)."""
        off, cc = listing
        E = int(n_listed.sum())
        er = np.repeat(np.arange(rows.size), n_listed)  # block-local row of each entry
        cells = cc[off[rows[0]]:off[rows[0]] + E]
        gap_p, gap_pv = [], []
        for j in range(a.shape[1]):
            gap = _axis_gap(self.space, self.periodic, j, self.lower[cells, j], self.upper[cells, j], a[er, j], b[er, j])
            sp, spv, _, _ = mode.split(gap, rows[er], j, paper_candidate=False)
            gap_p.append(sp)
            gap_pv.append(spv)
        return _Entries(er, cells, gap_p, gap_pv)


def targets_of(partition):
    """The target finder of ``partition`` (a ``BoxPartition`` or a rectilinear ``Partition``)."""
    return _BoxTargets(partition) if isinstance(partition, BoxPartition) else _GridTargets(partition)
