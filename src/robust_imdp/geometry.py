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
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable, Mapping

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError, OutsideDomainError

__all__ = ["Box", "Region", "Partition"]

# Relative tolerance (w.r.t. the cell size) under which a region boundary is
# considered to coincide with a uniform tick; the region's exact value is then
# used as the breakpoint (the tick moves by < 1e-9 cell sizes, the region is kept exact).
_SNAP_RTOL = 1e-9


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
                f"Box must have lower < upper in every dimension (empty or inverted box); "
                f"got lower[{bad}]={lo[bad]} >= upper[{bad}]={hi[bad]}"
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

    Attributes
    ----------
    dim : int
    shape : tuple of int, the number of intervals per dimension
    n_cells : int
    breakpoints : list of (n_j + 1,) float arrays
    cells_lower, cells_upper : (n_cells, d) float arrays
    atoms : tuple of str, region names in the given order
    labels : (n_cells,) int64, bit ``i`` set iff the cell lies inside ``atoms[i]``
    outside_state : int, ``n_cells`` (the absorbing outside-X state)
    """

    def __init__(self, space: Box, cell_size, regions=None):
        if not isinstance(space, Box):
            raise InvalidInputError(f"space must be a Box; got {type(space).__name__}")
        d = space.dim
        h = np.asarray(cell_size, dtype=float)
        if h.ndim == 0:
            h = np.full(d, float(h))
        if h.shape != (d,):
            raise DimensionError(f"cell_size must be a float or an array of shape ({d},); got shape {h.shape}")
        if not np.all(np.isfinite(h)) or np.any(h <= 0):
            raise InvalidInputError(f"cell_size must be finite and > 0; got {h.tolist()}")
        self.space = space
        self.cell_size = h
        self.regions = _normalise_regions(regions)
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
                f"cell_size[{j}]={h} does not divide the width {width} of X in dimension {j} "
                f"(width/cell_size = {ratio:.6g}); use width/k, e.g. {width / n_lo:.6g} ({n_lo} cells) "
                f"or {width / n_hi:.6g} ({n_hi} cells)"
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
                f"region boundaries in dimension {j} produced a degenerate breakpoint list {ticks.tolist()}"
            )
        return ticks

    # ------------------------------------------------------------------ queries
    def label_sets(self) -> list:
        """List of ``frozenset`` of atom names, one per cell."""
        return [frozenset(a for i, a in enumerate(self.atoms) if (lab >> i) & 1) for lab in self.labels.tolist()]

    def contains(self, x) -> np.ndarray:
        """``(k,)`` bool: points in X (closed)."""
        return self.space.contains(x)

    def locate(self, x) -> np.ndarray:
        """Cell index of each point.

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
        return {
            "space": self.space.to_dict(),
            "cell_size": self.cell_size.tolist(),
            "regions": [r.to_dict() for r in self.regions],
        }

    @classmethod
    def from_dict(cls, d: Mapping) -> "Partition":
        return cls(Box.from_dict(d["space"]), d["cell_size"], [Region.from_dict(r) for r in d["regions"]])

    def __repr__(self) -> str:
        return f"Partition(shape={self.shape}, n_cells={self.n_cells}, atoms={self.atoms})"
