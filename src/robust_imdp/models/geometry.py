"""Boxes, named regions and the rectilinear partition of the compact set X.

The partition is the paper's set of cells ``Q_safe`` (Sec. "IMDP Abstraction",
"States and Actions"): a grid over X that **respects the regions of interest** --
every cell lies either wholly inside a region or has no interior point in common
with it. Instead of failing when a region boundary does not fall on the uniform
grid, the grid is refined: per dimension the breakpoints are the uniform ticks
plus every region boundary that is not already a tick (cells are split, never
rejected).

Conventions
-----------
* Cells are closed boxes ``[lower, upper]``; neighbouring cells share faces.
  Cell indices are ``np.ravel_multi_index`` of the per-dimension interval
  indices in C order.
* Regions are closed sets (finite unions of closed boxes). A cell is **labelled**
  with a region when the cell lies inside the region (``cell ⊆ region``). Because
  the breakpoints contain every box boundary, each cell is either inside a
  region or meets it at most on its boundary, so the label of a cell is the
  label of every point of the cell's *interior*. Points on a shared face (a set
  of measure zero) belong to the cell given by :meth:`Partition.locate`, which
  uses half-open intervals ``[b_k, b_{k+1})`` except that the last interval of
  each dimension is closed at the upper end of X.
* The absorbing outside-X state is ``outside_state == n_cells``.
* Periodic dimensions (``periodic[j]``, the problem file's ``[space].periodic``): X is a circle
  along ``j``, of period ``upper_j - lower_j``. Points are wrapped into ``[lower_j, upper_j)``
  before they are located (:func:`wrap_points`), a point never leaves X along ``j``, and a region
  box may cross the seam (``lower_j < X.lower_j`` or ``upper_j > X.upper_j``, width at most the
  period): it is cut into the pieces inside X (:func:`wrap_region_boxes`). See docs/periodic.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Mapping

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError, OutsideDomainError

__all__ = ["Box", "Region", "Partition", "BoxPartition", "partition_from_dict", "dimension_text",
           "region_overlaps", "check_periodic", "wrap_points", "wrap_region_boxes", "wrap_residuals"]

# Relative tolerance (w.r.t. the cell size) under which a region boundary is
# considered to coincide with a uniform tick; the region's exact value is then
# used as the breakpoint (the tick moves by < 1e-9 cell sizes, the region is kept exact).
_SNAP_RTOL = 1e-9


def dimension_text(j: int, names=None) -> str:
    """How user-facing messages name dimension ``j`` (0-based index): ``"dimension 3 (theta)"``.

    Dimensions are numbered from 1 in every message, like the data file's columns
    ``x_1 .. x_n``; the name (``[space].names``) follows in parentheses when there is one.
    """
    text = f"dimension {int(j) + 1}"
    if names is not None and 0 <= j < len(names):
        text += f" ({names[j]})"
    return text


def _as_vector(value, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1 or arr.size == 0:
        raise DimensionError(f"{name} must be a non-empty 1-D array of floats; got shape {np.shape(value)}")
    return arr


@dataclass(frozen=True, eq=False)
class Box:
    """Closed axis-aligned box ``[lower, upper]`` in R^d.

    Parameters
    ----------
    lower, upper : (d,) float arrays
        Finite corners with ``lower < upper`` in every dimension.
    """

    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self):
        lo = _as_vector(self.lower, "Box lower")
        hi = _as_vector(self.upper, "Box upper")
        if lo.shape != hi.shape:
            raise DimensionError(
                f"Box lower and upper must have the same length; got {lo.size} and {hi.size}"
            )
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise InvalidInputError(f"Box corners must be finite; got lower={lo}, upper={hi}")
        if np.any(lo >= hi):
            bad = int(np.flatnonzero(lo >= hi)[0])
            raise InvalidInputError(
                f"Box must have lower < upper in every dimension; got lower = {lo[bad]} >= upper = "
                f"{hi[bad]} in {dimension_text(bad)} (an empty or inverted box)"
            )
        lo.setflags(write=False)
        hi.setflags(write=False)
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    @property
    def dim(self) -> int:
        return int(self.lower.size)

    def contains(self, x) -> np.ndarray:
        """``(k,)`` bool: points ``x`` (``(k, d)`` or ``(d,)``) in the closed box."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.shape[1] != self.dim:
            raise DimensionError(f"x must have shape (k, {self.dim}); got {x.shape}")
        return np.all((x >= self.lower) & (x <= self.upper), axis=1)

    def contains_box(self, other: "Box") -> bool:
        """True when ``other`` ⊆ ``self`` (closed boxes)."""
        return bool(np.all(other.lower >= self.lower) and np.all(other.upper <= self.upper))

    def intersects(self, other: "Box") -> bool:
        """True when the closed boxes share a point (overlap on EVERY axis)."""
        return bool(np.all(other.lower <= self.upper) and np.all(other.upper >= self.lower))

    def to_dict(self) -> dict:
        return {"lower": self.lower.tolist(), "upper": self.upper.tolist()}

    @classmethod
    def from_dict(cls, d: Mapping) -> "Box":
        return cls(d["lower"], d["upper"])

    def __eq__(self, other) -> bool:
        return isinstance(other, Box) and np.array_equal(self.lower, other.lower) and np.array_equal(
            self.upper, other.upper
        )

    def __hash__(self):
        return hash((tuple(self.lower), tuple(self.upper)))

    def __repr__(self) -> str:
        return f"Box(lower={self.lower.tolist()}, upper={self.upper.tolist()})"


@dataclass(frozen=True)
class Region:
    """A named region of interest: the union of closed boxes (a closed set).

    Parameters
    ----------
    name : str
        Atomic proposition name (non-empty).
    boxes : Box or sequence of Box
        At least one box, all of the same dimension.
    """

    name: str
    boxes: tuple = field(default=())

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise InvalidInputError(f"Region name must be a non-empty string; got {self.name!r}")
        boxes = (self.boxes,) if isinstance(self.boxes, Box) else tuple(self.boxes)
        if not boxes:
            raise InvalidInputError(f"Region {self.name!r} needs at least one Box; got none")
        for b in boxes:
            if not isinstance(b, Box):
                raise InvalidInputError(f"Region {self.name!r} boxes must be Box objects; got {type(b).__name__}")
        if len({b.dim for b in boxes}) != 1:
            raise DimensionError(
                f"Region {self.name!r} boxes must share one dimension; got {[b.dim for b in boxes]}"
            )
        object.__setattr__(self, "boxes", boxes)

    @property
    def dim(self) -> int:
        return self.boxes[0].dim

    def contains(self, x) -> np.ndarray:
        """``(k,)`` bool: points in the closed region."""
        return np.any([b.contains(x) for b in self.boxes], axis=0)

    def to_dict(self) -> dict:
        return {"name": self.name, "boxes": [b.to_dict() for b in self.boxes]}

    @classmethod
    def from_dict(cls, d: Mapping) -> "Region":
        return cls(d["name"], tuple(Box.from_dict(b) for b in d["boxes"]))


def _normalise_regions(regions) -> tuple:
    if regions is None:
        return ()
    if isinstance(regions, Mapping):
        out = []
        for key, value in regions.items():
            if isinstance(value, Region):
                if value.name != key:
                    raise InvalidInputError(
                        f"regions[{key!r}] is a Region named {value.name!r}; the key must equal the name"
                    )
                out.append(value)
            elif isinstance(value, Box):
                out.append(Region(key, (value,)))
            elif isinstance(value, Iterable):
                out.append(Region(key, tuple(value)))
            else:
                raise InvalidInputError(
                    f"regions[{key!r}] must be a Region, a Box or a list of Box; got {type(value).__name__}"
                )
        regions = out
    regions = tuple(regions)
    for r in regions:
        if not isinstance(r, Region):
            raise InvalidInputError(f"regions must be Region objects (or a dict name -> Region); got {type(r).__name__}")
    names = [r.name for r in regions]
    if len(set(names)) != len(names):
        raise InvalidInputError(f"region names must be unique; got {names}")
    return regions


# ============================================================================ periodic dimensions
def check_periodic(periodic, d: int, where: str = "periodic"):
    """``periodic`` as a tuple of d bools, or None when no dimension is periodic (the default).

    ``where`` names the argument (or file and key) in the message of a list of the wrong length.
    """
    if periodic is None:
        return None
    if isinstance(periodic, (str, bytes)) or not isinstance(periodic, Iterable):
        raise InvalidInputError(f"{where} must be a list of {d} booleans, one per dimension; got {periodic!r}")
    flags = list(periodic)
    if len(flags) != d or not all(isinstance(v, (bool, np.bool_)) for v in flags):
        raise DimensionError(f"{where} must be a list of {d} booleans, one per dimension; got {flags!r}"
                             + (f" ({len(flags)} values)" if len(flags) != d else ""))
    flags = tuple(bool(v) for v in flags)
    return flags if any(flags) else None


def wrap_points(x, lower, upper, periodic) -> np.ndarray:
    """``x`` (``(k, d)`` or ``(d,)``) with every periodic coordinate moved into ``[lower_j, upper_j)``.

    The representative is ``lower_j + ((x_j - lower_j) mod period)``; a float result equal to
    ``upper_j`` (rounding) becomes ``lower_j``, the same point of the circle. Non-periodic
    coordinates (and ``periodic=None``) are returned unchanged, as a copy.
    """
    x = np.array(x, dtype=float)
    if periodic is None:
        return x
    flat = np.atleast_2d(x)
    for j in np.flatnonzero(periodic):
        lo, hi = float(lower[j]), float(upper[j])
        w = lo + np.mod(flat[:, j] - lo, hi - lo)
        flat[:, j] = np.where((w >= hi) | (w < lo), lo, w)
    return flat.reshape(x.shape)


def wrap_residuals(y, bound, lower, upper, periodic):
    """Residuals ``y`` (``(k, d)``) on the periodic dimensions taken modulo the period: ``(y_w, bound_w)``.

    The representative nearest 0, ``y_j - k T`` with ``k = round(y_j / T)``. It is the true
    ``g_j + v_j`` only if ``|g_j + v_j| < T / 2`` (an assumption on the dynamics, docs/periodic.md).
    ``bound`` (broadcast to ``y``) bounds ``|y - y_exact|``; ``bound_w`` adds the wrap's float error
    (``T = fl(upper - lower)``, ``k T`` and the difference: three roundings, ``gamma(4)`` with a
    margin), rounded up. Where ``k = 0`` both are returned unchanged.
    """
    from robust_imdp._fp import gamma, up

    y = np.array(y, dtype=float)
    bound = np.array(np.broadcast_to(np.asarray(bound, dtype=float), y.shape))
    if periodic is None or y.size == 0:
        return y, bound
    for j in np.flatnonzero(periodic):
        period = float(upper[j]) - float(lower[j])
        k = np.round(y[:, j] / period)
        s = k * period
        yw = y[:, j] - s
        err = gamma(4) * (np.abs(s) + np.abs(y[:, j]) + np.abs(yw))
        bound[:, j] = np.where(k == 0, bound[:, j], up(bound[:, j] + err))
        y[:, j] = np.where(k == 0, y[:, j], yw)
    return y, bound


def wrap_region_boxes(regions, space: Box, periodic, names=None) -> tuple:
    """Regions with every box that crosses the seam of a periodic dimension cut into boxes inside X.

    A box with ``lower_j < X.lower_j`` or ``upper_j > X.upper_j`` on a periodic ``j`` is moved by a
    whole number of periods so that its lower end lies in ``[X.lower_j, X.upper_j)``, then cut at
    ``X.upper_j`` into ``[lower_j, X.upper_j]`` and ``[X.lower_j, upper_j - period]`` (up to two
    boxes per periodic dimension). A box wider than the period there is refused. Boxes inside X
    are kept exactly (no arithmetic), so a problem without seam-crossing regions is unchanged.
    """
    regions = _normalise_regions(regions)
    if periodic is None:
        return regions
    out = []
    for r in regions:
        boxes = list(r.boxes)
        for j in np.flatnonzero(periodic):
            lo_x, hi_x = float(space.lower[j]), float(space.upper[j])
            period = hi_x - lo_x
            cut = []
            for b in boxes:
                lo, hi = float(b.lower[j]), float(b.upper[j])
                if lo >= lo_x and hi <= hi_x:
                    cut.append(b)
                    continue
                if hi - lo > period:
                    raise InvalidInputError(
                        f"region {r.name!r} box {b} is {hi - lo:g} wide in {dimension_text(j, names)}, which is "
                        f"periodic with period {period:g}; a region box may be at most one period wide")
                k = np.floor((lo - lo_x) / period)
                lo, hi = lo - k * period, hi - k * period
                pieces = [(max(lo, lo_x), min(hi, hi_x))]
                if hi > hi_x:
                    pieces.append((lo_x, min(hi - period, hi_x)))
                for a, c in pieces:
                    if c > a:
                        bl, bu = b.lower.copy(), b.upper.copy()
                        bl[j], bu[j] = a, c
                        cut.append(Box(bl, bu))
            boxes = cut
        out.append(r if boxes == list(r.boxes) else Region(r.name, tuple(boxes)))
    return tuple(out)


def region_overlaps(regions) -> list:
    """Where two different regions overlap: every pair of their boxes sharing interior points.

    Closed boxes that only share a face, an edge or a corner (a set of volume zero) do not
    overlap: no cell gets both labels there.

    Parameters
    ----------
    regions : dict[str, Region] or sequence of Region

    Returns
    -------
    list of (str, str, Box)
        ``(name_a, name_b, box)`` with ``name_a`` before ``name_b`` in the given order and ``box``
        the intersection ``[max(lower), min(upper)]`` of one box of each, which has positive volume.
    """
    regions = _normalise_regions(regions)
    out = []
    for i, a in enumerate(regions):
        for b in regions[i + 1:]:
            for ba in a.boxes:
                for bb in b.boxes:
                    lo, hi = np.maximum(ba.lower, bb.lower), np.minimum(ba.upper, bb.upper)
                    if lo.shape == hi.shape and np.all(lo < hi):
                        out.append((a.name, b.name, Box(lo, hi)))
    return out


class Partition:
    """Rectilinear grid over the box X that respects the regions of interest.

    Parameters
    ----------
    space : Box
        The compact set X.
    cell_size : float or (d,) float array
        Uniform cell size per dimension; must divide the width of X (up to a
        relative 1e-9), otherwise :class:`InvalidInputError` says which sizes do.
    regions : dict[str, Region] or sequence of Region, optional
        Regions of interest (closed unions of boxes), each inside X.
    names : sequence of d str, optional
        Names of the dimensions (``[space].names``), used in messages only.
    periodic : sequence of d bool, optional
        Periodic dimensions (``[space].periodic``; default none): see the module's conventions.

    Attributes
    ----------
    dim : int
    names : tuple of str or None
    shape : tuple of int, the number of intervals per dimension
    n_cells : int
    breakpoints : list of (n_j + 1,) float arrays
    cells_lower, cells_upper : (n_cells, d) float arrays
    atoms : tuple of str, region names in the given order
    labels : (n_cells,) int64, bit ``i`` set iff the cell lies inside ``atoms[i]``
    outside_state : int, ``n_cells`` (the absorbing outside-X state)
    periodic : tuple of d bool, or None when no dimension is periodic
    """

    def __init__(self, space: Box, cell_size, regions=None, *, names=None, periodic=None):
        if not isinstance(space, Box):
            raise InvalidInputError(f"space must be a Box; got {type(space).__name__}")
        d = space.dim
        if names is not None:
            names = tuple(names)
            if len(names) != d or not all(isinstance(n, str) and n for n in names):
                raise DimensionError(f"names must be {d} non-empty strings, one per dimension; got {names!r}")
        self.names = names
        h = np.asarray(cell_size, dtype=float)
        if h.ndim == 0:
            h = np.full(d, float(h))
        if h.shape != (d,):
            raise DimensionError(f"cell_size must be a float or one value per dimension ({d}); got shape {h.shape}")
        if not np.all(np.isfinite(h)) or np.any(h <= 0):
            raise InvalidInputError(f"cell_size must be finite and > 0; got {h.tolist()}")
        self.space = space
        self.cell_size = h
        self.periodic = check_periodic(periodic, d)
        self.regions = wrap_region_boxes(regions, space, self.periodic, names)
        for r in self.regions:
            if r.dim != d:
                raise DimensionError(f"region {r.name!r} has dimension {r.dim}; X has dimension {d}")
            for b in r.boxes:
                if not space.contains_box(b):
                    raise OutsideDomainError(
                        f"region {r.name!r} box {b} must lie inside X = {space}; regions outside X are not allowed"
                    )
        self.breakpoints = [self._axis_breakpoints(j) for j in range(d)]
        for bp in self.breakpoints:
            bp.setflags(write=False)
        self.dim = d
        self.shape = tuple(len(bp) - 1 for bp in self.breakpoints)
        self.n_cells = int(np.prod(self.shape))
        self.outside_state = self.n_cells
        self.atoms = tuple(r.name for r in self.regions)
        grids = np.meshgrid(*[np.arange(n) for n in self.shape], indexing="ij")
        idx = np.stack([g.ravel() for g in grids], axis=1)  # C order == ravel_multi_index
        self.cells_lower = np.stack([self.breakpoints[j][idx[:, j]] for j in range(d)], axis=1)
        self.cells_upper = np.stack([self.breakpoints[j][idx[:, j] + 1] for j in range(d)], axis=1)
        labels = np.zeros(self.n_cells, dtype=np.int64)
        for i, r in enumerate(self.regions):
            inside = np.zeros(self.n_cells, dtype=bool)
            for b in r.boxes:
                inside |= np.all((self.cells_lower >= b.lower) & (self.cells_upper <= b.upper), axis=1)
            labels[inside] |= 1 << i
        self.labels = labels
        for a in (self.cells_lower, self.cells_upper, self.labels):
            a.setflags(write=False)
        self._frozen = True

    def __setattr__(self, name, value):  # invalid objects cannot exist: no mutation after __init__
        if getattr(self, "_frozen", False):
            raise AttributeError(f"Partition is immutable; cannot set {name!r}")
        object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ construction
    def _axis_breakpoints(self, j: int) -> np.ndarray:
        lo, hi, h = self.space.lower[j], self.space.upper[j], self.cell_size[j]
        width = hi - lo
        ratio = width / h
        n = int(round(ratio))
        if n < 1 or abs(ratio - n) > 1e-9 * max(ratio, 1.0):
            n_lo, n_hi = max(int(np.floor(ratio)), 1), int(np.ceil(ratio))
            raise InvalidInputError(
                f"cell_size in {dimension_text(j, self.names)} is {h:g}, which does not divide the width "
                f"{width:g} of X there (width/cell_size = {ratio:.6g}); use width/k, e.g. {width / n_lo:.6g} "
                f"({n_lo} cells) or {width / n_hi:.6g} ({n_hi} cells)"
            )
        ticks = lo + np.arange(n + 1) * (width / n)
        ticks[-1] = hi  # the last tick is the upper end of X exactly
        bounds = {float(v) for r in self.regions for b in r.boxes for v in (b.lower[j], b.upper[j])}
        for v in sorted(bounds):
            k = int(np.argmin(np.abs(ticks - v)))
            if ticks[k] == v:
                continue
            if 0 < k < len(ticks) - 1 and abs(ticks[k] - v) <= _SNAP_RTOL * h:
                ticks[k] = v  # region boundary on the grid: keep the region's exact value
            else:
                ticks = np.sort(np.append(ticks, v))  # off-grid boundary: split the cells
        if np.any(np.diff(ticks) <= 0):
            raise InvalidInputError(
                f"region boundaries in {dimension_text(j, self.names)} produced a degenerate breakpoint list "
                f"{ticks.tolist()}"
            )
        return ticks

    # ------------------------------------------------------------------ queries
    def label_sets(self) -> list:
        """List of ``frozenset`` of atom names, one per cell."""
        return [frozenset(a for i, a in enumerate(self.atoms) if (lab >> i) & 1) for lab in self.labels.tolist()]

    def contains(self, x) -> np.ndarray:
        """``(k,)`` bool: points in X (closed; every coordinate of a periodic dimension is in X)."""
        if self.periodic is None:
            return self.space.contains(x)
        return self.space.contains(self.wrap(x))

    def wrap(self, x) -> np.ndarray:
        """``x`` with its periodic coordinates moved into X (:func:`wrap_points`; a copy)."""
        return wrap_points(x, self.space.lower, self.space.upper, self.periodic)

    def locate(self, x) -> np.ndarray:
        """Cell index of each point (periodic coordinates wrapped first).

        Parameters
        ----------
        x : (k, d) or (d,) float array

        Returns
        -------
        (k,) int64 array: the cell index, or ``-1`` for points outside X.
        Intervals are half-open ``[b_k, b_{k+1})`` except the last, which also
        contains the upper end of X.
        """
        x = np.atleast_2d(np.asarray(x, dtype=float))
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise DimensionError(f"x must have shape (k, {self.dim}); got {np.shape(x)}")
        if np.any(np.isnan(x)):
            raise InvalidInputError("x must not contain NaN")
        if self.periodic is not None:
            x = self.wrap(x)
        multi = np.empty(x.shape, dtype=np.int64)
        for j, bp in enumerate(self.breakpoints):
            k = np.searchsorted(bp, x[:, j], side="right") - 1
            multi[:, j] = np.minimum(k, len(bp) - 2)  # x == upper end of X -> last cell
        inside = self.contains(x)
        out = np.full(x.shape[0], -1, dtype=np.int64)
        if np.any(inside):
            out[inside] = np.ravel_multi_index(tuple(multi[inside].T), self.shape)
        return out

    def cell_box(self, index: int) -> Box:
        """The closed box of cell ``index``."""
        return Box(self.cells_lower[index], self.cells_upper[index])

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        """JSON-able description; :meth:`from_dict` rebuilds an identical partition."""
        out = {
            "space": self.space.to_dict(),
            "cell_size": self.cell_size.tolist(),
            "regions": [r.to_dict() for r in self.regions],
        }
        if self.periodic is not None:  # only then: descriptions without periodic dimensions are unchanged
            out["periodic"] = list(self.periodic)
        return out

    @classmethod
    def from_dict(cls, d: Mapping) -> "Partition":
        return cls(Box.from_dict(d["space"]), d["cell_size"], [Region.from_dict(r) for r in d["regions"]],
                   periodic=d.get("periodic"))

    def __repr__(self) -> str:
        return f"Partition(shape={self.shape}, n_cells={self.n_cells}, atoms={self.atoms})"


# ============================================================================ non-uniform cells
def intervals_meeting(breakpoints, lo, hi):
    """Per axis j, the grid intervals ``[b_l, b_{l+1}]`` of ``breakpoints[j]`` meeting each closed ``[lo, hi]``.

    ``lo, hi`` are (k, d) arrays. Returns ``(first, count)``, (k, d) int64 arrays: the intervals
    ``first, ..., first + count - 1`` (``count = 0``: none; closed intervals meet iff they share a point).
    """
    k, d = lo.shape
    first = np.empty((k, d), dtype=np.int64)
    count = np.empty((k, d), dtype=np.int64)
    for j in range(d):
        first[:, j] = np.searchsorted(breakpoints[j][1:], lo[:, j], side="left")  # first l: b_{l+1} >= lo
        last = np.searchsorted(breakpoints[j][:-1], hi[:, j], side="right") - 1  # last l: b_l <= hi
        count[:, j] = np.maximum(last - first[:, j] + 1, 0)
    return first, count


class BoxPartition:
    """Boxes of different sizes tiling X: a rectilinear :class:`Partition` refined by bisection.

    Every cell of ``base`` is the root of a binary tree (a k-d tree); :meth:`split` bisects
    cells at the midpoint of an axis and returns a new partition. The cells are the leaves.

    Labels are exact: a base cell lies inside a region or has no interior point in common
    with it (its breakpoints contain every region boundary), and a child is a subset of its
    parent, so a child has its parent's label, which is the label of every point of its
    interior. The same attribute names as :class:`Partition` mean the same things, so
    synthesis, the result file, validation and the figures take either.

    Cell indices are stable under :meth:`split`: a split cell's index goes to its first child
    (the one at the lower end of the split axes); the other children are appended, in the
    order of the split cells. An unsplit ``BoxPartition(base)`` has ``base``'s cells in
    ``base``'s order.

    Spatial index. :meth:`locate` finds the base cell by per-axis ``searchsorted`` and
    descends the tree (half-open halves ``[lo, m)``, ``[m, hi]``, as :meth:`Partition.locate`);
    :meth:`intersecting` lists every cell meeting a closed query box the same way, descending
    only into the halves the box meets (cost ~ depth + matches per query, vectorised over
    queries).

    Parameters
    ----------
    base : Partition
        The grid that is refined (it respects the regions).

    Attributes
    ----------
    base : Partition
    space, regions, atoms, dim : as in :class:`Partition`
    n_cells : int
    cells_lower, cells_upper : (n_cells, d) float arrays
    labels : (n_cells,) int64, bit ``i`` set iff the cell lies inside ``atoms[i]``
    base_cell : (n_cells,) int64, the base cell containing each cell
    depth : (n_cells,) int64, number of bisections from the base cell
    outside_state : int, ``n_cells``
    """

    def __init__(self, base: Partition, _tree=None):
        if not isinstance(base, Partition):
            raise InvalidInputError(f"base must be a Partition; got {type(base).__name__}")
        self.base = base
        self.space, self.regions, self.atoms, self.dim = base.space, base.regions, base.atoms, base.dim
        self.periodic = base.periodic
        nb = base.n_cells
        if _tree is None:  # one leaf per base cell
            _tree = (np.full(nb, -1, dtype=np.int64), np.full(nb, np.nan), np.full(nb, -1, dtype=np.int64),
                     np.arange(nb, dtype=np.int64))
        axis, split, child, cell = (np.array(a) for a in _tree)
        self._axis, self._split, self._child, self._cell = axis, split, child, cell
        leaves = np.flatnonzero(axis < 0)
        n = leaves.size
        node_of_cell = np.full(n, -1, dtype=np.int64)
        if np.any(cell[leaves] < 0) or np.any(cell[leaves] >= n):
            raise InvalidInputError("BoxPartition tree: leaf cell indices must lie in [0, n_cells)")
        node_of_cell[cell[leaves]] = leaves
        if np.any(node_of_cell < 0):
            raise InvalidInputError("BoxPartition tree: every cell index must belong to exactly one leaf")
        # node boxes, parents before children (children always have larger node indices)
        nlo = np.empty((axis.size, self.dim))
        nhi = np.empty((axis.size, self.dim))
        nlo[:nb], nhi[:nb] = base.cells_lower, base.cells_upper
        rootof = np.empty(axis.size, dtype=np.int64)
        rootof[:nb] = np.arange(nb)
        depth = np.zeros(axis.size, dtype=np.int64)
        seen = np.zeros(axis.size, dtype=bool)
        seen[:nb] = True
        frontier = np.flatnonzero(axis[:nb] >= 0)
        while frontier.size:  # level by level; the children of k are child[k] and child[k] + 1
            a, m, c = axis[frontier], split[frontier], child[frontier]
            ok = (a < self.dim) & (c > frontier) & (c + 1 < axis.size)
            ok[ok] &= (nlo[frontier[ok], a[ok]] < m[ok]) & (m[ok] < nhi[frontier[ok], a[ok]])
            ok[ok] &= ~seen[c[ok]] & ~seen[c[ok] + 1]
            if not np.all(ok):
                k = int(frontier[np.flatnonzero(~ok)[0]])
                raise InvalidInputError(f"BoxPartition tree: node {k} has an invalid split "
                                        f"(axis {axis[k]}, value {split[k]!r}, child {child[k]})")
            for cc in (c, c + 1):
                seen[cc] = True
                nlo[cc], nhi[cc] = nlo[frontier], nhi[frontier]
                rootof[cc], depth[cc] = rootof[frontier], depth[frontier] + 1
            nhi[c, a] = m
            nlo[c + 1, a] = m
            nxt = np.concatenate([c, c + 1])
            frontier = nxt[axis[nxt] >= 0]
        if not np.all(seen):
            raise InvalidInputError(f"BoxPartition tree: node {int(np.flatnonzero(~seen)[0])} is not reachable")
        self.n_cells = n
        self.outside_state = n
        self._node_of_cell = node_of_cell
        self.cells_lower = nlo[node_of_cell]
        self.cells_upper = nhi[node_of_cell]
        self.base_cell = rootof[node_of_cell]
        self.depth = depth[node_of_cell]
        self.labels = np.asarray(base.labels)[self.base_cell]  # a child has its parent's label
        for a in (self.cells_lower, self.cells_upper, self.labels, self.base_cell, self.depth,
                  self._axis, self._split, self._child, self._cell, self._node_of_cell):
            a.setflags(write=False)
        self._frozen = True

    def __setattr__(self, name, value):  # invalid objects cannot exist: no mutation after __init__
        if getattr(self, "_frozen", False):
            raise AttributeError(f"BoxPartition is immutable; cannot set {name!r}")
        object.__setattr__(self, name, value)

    # ------------------------------------------------------------------ refinement
    def split(self, cells, axes=None) -> "BoxPartition":
        """A new partition with ``cells`` bisected at their midpoints.

        Parameters
        ----------
        cells : (k,) int array
            Distinct cell indices.
        axes : (k,) int array, optional
            The axis along which each cell is bisected (two children). Default: every axis
            (``2**d`` children, a quad/oct-tree step).

        Returns
        -------
        BoxPartition
            Cell ``cells[i]`` keeps its index for the child at the lower end of the split axes;
            the other children get ``n_cells, n_cells + 1, ...`` in the order of ``cells``.
        """
        cells = np.asarray(cells, dtype=np.int64).reshape(-1)
        if np.any((cells < 0) | (cells >= self.n_cells)) or np.unique(cells).size != cells.size:
            raise InvalidInputError(f"cells must be distinct indices in [0, {self.n_cells}); got {cells.tolist()[:10]}")
        if axes is None:
            k, N = cells.size, self.n_cells
            out, pieces = self, cells[:, None]
            for a in range(self.dim):  # bisect every piece of every cell along axis a
                flat = pieces.ravel()
                k0 = out.n_cells
                out = out._bisect(flat, np.full(flat.size, a))
                pieces = np.stack([pieces, (k0 + np.arange(flat.size)).reshape(pieces.shape)], axis=2).reshape(k, -1)
            # renumber the appended children cell by cell: cells[i]'s j-th child (j >= 1) gets
            # N + i (2^d - 1) + j - 1 (the bisections above appended them axis by axis)
            perm = np.arange(out.n_cells)
            perm[pieces[:, 1:].ravel()] = N + np.arange(k * (pieces.shape[1] - 1))
            cell = out._cell.copy()
            leaves = cell >= 0
            cell[leaves] = perm[cell[leaves]]
            return BoxPartition(self.base, (out._axis, out._split, out._child, cell))
        axes = np.asarray(axes, dtype=np.int64).reshape(-1)
        if axes.shape != cells.shape or np.any((axes < 0) | (axes >= self.dim)):
            raise InvalidInputError(f"axes must hold one axis in [0, {self.dim}) per cell; got {axes.tolist()[:10]}")
        return self._bisect(cells, axes)

    def _bisect(self, cells, axes) -> "BoxPartition":
        nodes = self._node_of_cell[cells]
        lo = self.cells_lower[cells, axes]
        hi = self.cells_upper[cells, axes]
        mid = lo + 0.5 * (hi - lo)
        bad = np.flatnonzero(~((lo < mid) & (mid < hi)))
        if bad.size:
            i = int(bad[0])
            raise InvalidInputError(f"cell {int(cells[i])} is too small to bisect in {dimension_text(int(axes[i]))} "
                                    f"([{lo[i]!r}, {hi[i]!r}])")
        k, N, n_nodes = cells.size, self.n_cells, self._axis.size
        axis = np.concatenate([self._axis, np.full(2 * k, -1, dtype=np.int64)])
        split = np.concatenate([self._split, np.full(2 * k, np.nan)])
        child = np.concatenate([self._child, np.full(2 * k, -1, dtype=np.int64)])
        cell = np.concatenate([self._cell, np.full(2 * k, -1, dtype=np.int64)])
        first = n_nodes + 2 * np.arange(k)
        axis[nodes], split[nodes], child[nodes], cell[nodes] = axes, mid, first, -1
        cell[first] = cells  # the lower child keeps the index
        cell[first + 1] = N + np.arange(k)
        return BoxPartition(self.base, (axis, split, child, cell))


    # ------------------------------------------------------------------ queries
    def label_sets(self) -> list:
        """List of ``frozenset`` of atom names, one per cell."""
        return [frozenset(a for i, a in enumerate(self.atoms) if (lab >> i) & 1) for lab in self.labels.tolist()]

    def contains(self, x) -> np.ndarray:
        """``(k,)`` bool: points in X (closed; periodic coordinates are always in X)."""
        return self.base.contains(x)

    def wrap(self, x) -> np.ndarray:
        """``x`` with its periodic coordinates moved into X (:meth:`Partition.wrap`)."""
        return self.base.wrap(x)

    def cell_box(self, index: int) -> Box:
        """The closed box of cell ``index``."""
        return Box(self.cells_lower[index], self.cells_upper[index])

    def volumes(self) -> np.ndarray:
        """``(n_cells,)`` float: the volume (area in 2-D) of every cell."""
        return np.prod(self.cells_upper - self.cells_lower, axis=1)

    def locate(self, x) -> np.ndarray:
        """Cell index of each point (``-1`` outside X), with :meth:`Partition.locate`'s convention.

        The base cell is found per axis (half-open intervals, the last one closed at the upper
        end of X); inside it, a point with ``x_a < m`` goes to the lower half of a node split at
        ``m`` along axis ``a``, else to the upper half, so every point of X has exactly one cell.

        Parameters
        ----------
        x : (k, d) or (d,) float array

        Returns
        -------
        (k,) int64 array
        """
        x = np.atleast_2d(np.asarray(x, dtype=float))
        out = self.base.locate(x)  # checks the shape and NaN
        if self.periodic is not None:
            x = self.wrap(x)
        inside = np.flatnonzero(out >= 0)
        node = out[inside]
        while True:  # one level of the trees per pass, vectorised over points
            a = self._axis[node]
            go = np.flatnonzero(a >= 0)
            if go.size == 0:
                break
            n_go = node[go]
            node[go] = self._child[n_go] + (x[inside[go], a[go]] >= self._split[n_go])
        out[inside] = self._cell[node]
        return out

    def intersecting(self, lower, upper):
        """Every cell meeting each closed query box ``[lower[i], upper[i]]`` (the spatial index).

        Parameters
        ----------
        lower, upper : (k, d) float arrays

        Returns
        -------
        query, cell : (E,) int64 arrays
            The pairs (query box, cell) whose closed boxes share a point, sorted by query, then
            cell index. Closed boxes meet iff they overlap on every axis, as in
            :mod:`robust_imdp.abstraction.rows`.
        """
        lo = np.atleast_2d(np.asarray(lower, dtype=float))
        hi = np.atleast_2d(np.asarray(upper, dtype=float))
        if lo.shape != hi.shape or lo.shape[1] != self.dim:
            raise DimensionError(f"lower and upper must both have shape (k, {self.dim}); got {lo.shape}, {hi.shape}")
        k = lo.shape[0]
        # base cells: per axis, the intervals [b_l, b_{l+1}] meeting [lo, hi] (closed)
        klo, cnt = intervals_meeting(self.base.breakpoints, lo, hi)
        tot = np.prod(cnt, axis=1)
        q = np.repeat(np.arange(k), tot)
        off = np.zeros(k + 1, dtype=np.int64)
        np.cumsum(tot, out=off[1:])
        t = np.arange(q.size) - off[q]
        multi = np.empty((q.size, self.dim), dtype=np.int64)
        for j in range(self.dim - 1, -1, -1):  # C-order unravel of the local index
            cj = np.maximum(cnt[q, j], 1)
            multi[:, j] = klo[q, j] + t % cj
            t = t // cj
        node = np.ravel_multi_index(tuple(multi.T), self.base.shape) if q.size else np.zeros(0, dtype=np.int64)
        out_q, out_c = [], []
        while q.size:  # descend into the halves the query box meets
            a = self._axis[node]
            leaf = a < 0
            out_q.append(q[leaf])
            out_c.append(self._cell[node[leaf]])
            q, node, a = q[~leaf], node[~leaf], a[~leaf]
            m = self._split[node]
            left = lo[q, a] <= m  # [cell lo, m] meets [lo, hi] (the parent meets it)
            right = hi[q, a] >= m  # [m, cell hi] meets [lo, hi]
            c = self._child[node]
            q = np.concatenate([q[left], q[right]])
            node = np.concatenate([c[left], c[right] + 1])
        qq = np.concatenate(out_q) if out_q else np.zeros(0, dtype=np.int64)
        cc = np.concatenate(out_c) if out_c else np.zeros(0, dtype=np.int64)
        order = np.lexsort((cc, qq))
        return qq[order], cc[order]

    def grid_index(self):
        """The cells on the grid of all their faces: ``(breakpoints, table)``.

        ``breakpoints`` lists per axis every face coordinate of every cell, and ``table`` (one
        entry per elementary box of that grid, C order) the cell holding it. Locating a point
        there (per-axis ``searchsorted``, as :meth:`Partition.locate`) and reading the table
        gives :meth:`locate`'s cell; a deployed controller needs nothing else.
        """
        bps = [np.unique(np.concatenate([self.cells_lower[:, j], self.cells_upper[:, j]])) for j in range(self.dim)]
        table = np.full(tuple(len(b) - 1 for b in bps), -1, dtype=np.int64)
        i0 = [np.searchsorted(bps[j], self.cells_lower[:, j]) for j in range(self.dim)]
        i1 = [np.searchsorted(bps[j], self.cells_upper[:, j]) for j in range(self.dim)]
        for c in range(self.n_cells):  # set-up only
            table[tuple(slice(i0[j][c], i1[j][c]) for j in range(self.dim))] = c
        return bps, table

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict:
        """JSON-able description; :meth:`from_dict` (or :func:`partition_from_dict`) rebuilds it exactly."""
        return {
            "kind": "boxes",
            "base": self.base.to_dict(),
            "axis": self._axis.tolist(),
            "split": [None if np.isnan(v) else float(v) for v in self._split.tolist()],
            "child": self._child.tolist(),
            "cell": self._cell.tolist(),
        }

    @classmethod
    def from_dict(cls, d: Mapping) -> "BoxPartition":
        try:
            tree = (np.asarray(d["axis"], dtype=np.int64), np.array([np.nan if v is None else v for v in d["split"]],
                                                                     dtype=float),
                    np.asarray(d["child"], dtype=np.int64), np.asarray(d["cell"], dtype=np.int64))
        except (KeyError, TypeError, ValueError) as exc:
            raise InvalidInputError(f"BoxPartition description is incomplete or malformed ({exc})") from None
        if len({t.shape for t in tree}) != 1 or tree[0].ndim != 1:
            raise InvalidInputError("BoxPartition description: axis, split, child and cell must have one length")
        return cls(Partition.from_dict(d["base"]), tree)

    def __repr__(self) -> str:
        return (f"BoxPartition(n_cells={self.n_cells}, base={self.base.shape}, max depth="
                f"{int(self.depth.max(initial=0))}, atoms={self.atoms})")


def partition_from_dict(d: Mapping):
    """A :class:`Partition` or a :class:`BoxPartition` from its ``to_dict()`` description."""
    if d.get("kind") == "boxes":
        return BoxPartition.from_dict(d)
    return Partition.from_dict(d)
