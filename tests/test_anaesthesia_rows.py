"""The rows of one cell of the ARCH anaesthesia benchmark (benchmarks/arch/problems/anaesthesia3d.toml) against
mpmath: the robust exact row of the cell's image box and the nominal mixture row of its 8 point images.

The nominal row of cell 118 under u = 7 (row 356) once failed the IMDP constructor in
``benchmarks/arch/run.py --only anaesthesia3d``: its outside entry came out as
``[6.17790013215588e-12, 6.1779001321526835e-12]`` (lower above upper by 3e-27). Here every entry of both
rows must be a valid interval that brackets the probability computed with 50 digits; the outside probability
of that row is ~6e-12 and its bracket is ~1e-13 wide relative to it, so a 0.1 % shrink of an upper bound (or
raise of a lower one) of any entry fails, where an absolute tolerance like 1e-12 could not see it.
"""

from __future__ import annotations

import mpmath
import numpy as np
import pytest

from robust_imdp.abstraction.cell_bounds import CellBounds
from robust_imdp.abstraction.exact_rows import exact_rows
from robust_imdp.abstraction.nominal import cell_points, nominal_abstraction
from robust_imdp.models.geometry import Box, Partition
from robust_imdp.models.noise import GaussianNoise

mpmath.mp.dps = 60

A = np.array([[0.8192, 0.03412, 0.01265], [0.01646, 0.9822, 0.0001], [0.0009, 0.00002, 0.9989]])
B = np.array([0.01883, 0.0002, 0.00001])
LOWER, UPPER, WIDTH = np.array([1.0, 0.0, 0.0]), np.array([6.0, 10.0, 10.0]), np.array([0.25, 0.5, 0.5])
SIGMA = 0.03162277660168379  # variance 1e-3 per axis
CELL, U = 118, 7.0  # cell (0, 5, 18) of the 20 x 20 x 20 grid, the input of mode 2


@pytest.fixture(scope="module")
def grid():
    return Partition(Box(LOWER, UPPER), WIDTH, {})


def _phi(t):
    """Standard normal cdf of ``t / SIGMA`` (``t`` an mpf: differences of floats taken exactly)."""
    return mpmath.ncdf(t / mpmath.mpf(SIGMA))


def _mass(lo, hi):
    """``P[lo <= v <= hi]``, written on the side of 0 where no cancellation occurs (tails of 1e-100 and below)."""
    return _phi(hi) - _phi(lo) if lo < 0 else _phi(-lo) - _phi(-hi)


def _axis_masses(y, bp):
    """Per axis and point: the masses of the grid's intervals and of leaving [L, H] (mpmath), as lists."""
    b = [mpmath.mpf(float(v)) for v in bp]
    ys = [mpmath.mpf(float(v)) for v in y]
    inside = [[_mass(b[k] - y, b[k + 1] - y) for k in range(len(b) - 1)] for y in ys]
    out = [_phi(b[0] - y) + _phi(y - b[-1]) for y in ys]
    return inside, out


def _joint_truth(points, grid):
    """Per axis ``(interval masses [point][interval], outside mass [point])`` of the exact law at ``points``."""
    return [_axis_masses(points[:, j], np.asarray(grid.breakpoints[j], float)) for j in range(3)]


def _cell_mass(per_axis, s, idx):
    m = mpmath.mpf(1)
    for j in range(3):
        m *= per_axis[j][0][s][idx[j]]
    return m


def _out_mass(per_axis, s):
    stay = mpmath.mpf(1)
    for j in range(3):
        stay *= 1 - per_axis[j][1][s]
    return 1 - stay


def _check_row(col, lo, up, truth):
    """Every listed entry is a valid interval that brackets ``truth(col)`` (50 digits)."""
    assert np.all((0.0 <= lo) & (lo <= up) & (up <= 1.0)), "an entry violates 0 <= lower <= upper <= 1"
    for c, a, b in zip(col, lo, up):
        t = truth(int(c))
        assert mpmath.mpf(float(a)) <= t <= mpmath.mpf(float(b)), (int(c), float(a), float(t), float(b))


def _image_box(cell_lo, cell_hi):
    """Image of the cell under x -> A x + B u by interval arithmetic, widened by 1e-12 (a sound box)."""
    pos, neg = np.maximum(A, 0.0), np.minimum(A, 0.0)
    lo = pos @ cell_lo + neg @ cell_hi + B * U
    hi = pos @ cell_hi + neg @ cell_lo + B * U
    return lo - 1e-12, hi + 1e-12


def test_nominal_mixture_row_of_the_failing_cell_brackets_the_mpmath_mixture(grid):
    """Row 356 of the nominal model (cell 118, u = 7): 8 point images (2 per axis), every entry, the outside
    one included (~6.18e-12), brackets the mean over the points of the exact probability (50 digits), and the
    outside bracket is tight (relative width < 1e-9: so a 0.1 % shrink is caught)."""
    pts = cell_points(grid, 2)  # (N, 8, 3)
    images = (pts @ A.T + B * U)[None]  # one mode: (1, N, 8, 3)
    ab = nominal_abstraction(grid, images, GaussianNoise([SIGMA] * 3))
    m = ab.imdp
    r = m.state_ptr[CELL]
    sl = slice(m.row_ptr[r], m.row_ptr[r + 1])
    col, lo, up = m.col[sl], m.lower[sl], m.upper[sl]
    y = images[0, CELL]
    per_axis = _joint_truth(y, grid)
    S = y.shape[0]

    def truth(c):
        if c == grid.n_cells:
            return sum(_out_mass(per_axis, s) for s in range(S)) / S
        idx = np.unravel_index(c, grid.shape)
        return sum(_cell_mass(per_axis, s, idx) for s in range(S)) / S

    _check_row(col, lo, up, truth)
    assert col[-1] == grid.n_cells
    t_out = truth(grid.n_cells)
    assert 1e-12 < float(t_out) < 1e-10  # the failing entry's magnitude (6.18e-12)
    assert (up[-1] - lo[-1]) <= 1e-9 * float(t_out)  # tight: a 0.1 % shrink of either side leaves the truth out


def test_robust_exact_row_of_the_failing_cell_brackets_mpmath_at_image_points(grid):
    """The robust exact row of the same cell (image box by interval arithmetic): each listed entry's interval
    holds the exact probability at the box's 8 corners and 16 seeded interior points (50 digits); the outside
    entry's lower bound is the minimum over the box (at its far side) and is matched within 1e-6 relative by
    the best sampled corner (so a 0.1 % raise of it is caught)."""
    idx = np.array(np.unravel_index(CELL, grid.shape))
    cell_lo, cell_hi = LOWER + idx * WIDTH, LOWER + (idx + 1) * WIDTH
    ylo, yhi = _image_box(cell_lo, cell_hi)
    full_lo = np.tile(ylo, (1, grid.n_cells, 1))
    full_hi = np.tile(yhi, (1, grid.n_cells, 1))
    ex = exact_rows(grid, CellBounds(full_lo, full_hi), GaussianNoise([SIGMA] * 3), floor_level=1e-6 / 20)
    start = int(np.sum(ex.row_len[:CELL]))
    sl = slice(start, start + int(ex.row_len[CELL]))
    col, lo, up = ex.col[sl], ex.lower[sl], ex.upper[sl]
    corners = np.array([[(yhi if (k >> j) & 1 else ylo)[j] for j in range(3)] for k in range(8)])
    rng = np.random.default_rng(118)
    pts = np.vstack([corners, ylo + rng.uniform(size=(16, 3)) * (yhi - ylo)])
    per_axis = _joint_truth(pts, grid)
    for s in range(pts.shape[0]):
        def truth(c, s=s):
            if c == grid.n_cells:
                return _out_mass(per_axis, s)
            return _cell_mass(per_axis, s, np.unravel_index(c, grid.shape))

        _check_row(col, lo, up, truth)
    # the outside lower bound is attained at the corner farthest from X's faces: within 1e-6 of the smallest
    # corner value (the per-axis minimum sits at an end of each image interval, here a corner)
    best = min(_out_mass(per_axis, s) for s in range(8))
    assert mpmath.mpf(float(lo[-1])) >= best * (1 - 1e-6)
