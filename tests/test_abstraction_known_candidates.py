"""Known dynamics take a short path through Thm 1's candidate pairs, with the same bits.

With ``std_upper=None`` every (eps, p) candidate of every cell is (0, 1), so the abstraction keeps
one candidate per cell instead of ``len(EPS_LEVELS)``. The general path, given error models whose
error is exactly 0 with probability 1 (``eps_for_prob = 0``, ``prob_within = 1``), lists the same
pairs K times; the argmax of equal scores keeps the first, so both must give the same IMDP to the
last bit (grid and periodic grid, both rules, both combinations, three noise kinds).
"""

from __future__ import annotations

import numpy as np
import pytest

from robust_imdp.abstraction.rows import CellBounds, abstract
from robust_imdp.models.geometry import Box, Partition, Region
from robust_imdp.models.noise import GaussianNoise, TruncatedGaussianNoise, UniformNoise


class _Exact:
    """An error model whose error is 0 with probability 1."""

    def eps_for_prob(self, p, std_upper):
        return np.zeros_like(np.asarray(std_upper, dtype=float))

    def prob_within(self, eps, std_upper):
        return np.ones(np.broadcast(np.asarray(eps), np.asarray(std_upper)).shape)


def _same_imdp(a, b):
    for name in ("state_ptr", "row_ptr", "col", "lower", "upper", "floor"):
        x, y = np.asarray(getattr(a.imdp, name)), np.asarray(getattr(b.imdp, name))
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name
    for name in ("floor_eps", "floor_eta", "lower_eps", "lower_eta", "containing_cell"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(b, name))
        assert x.shape == y.shape and np.array_equal(x, y, equal_nan=True), name


@pytest.mark.parametrize("periodic", [None, (False, True)])
@pytest.mark.parametrize("rule,combine", [("optimized", "product"), ("optimized", "union"), ("paper", "product")])
@pytest.mark.parametrize("noise", [TruncatedGaussianNoise([0.05, 0.04], [0.1, 0.08]), GaussianNoise([0.05, 0.04]),
                                   UniformNoise([0.1, 0.08])], ids=["truncated", "gaussian", "uniform"])
def test_known_dynamics_short_path_gives_the_general_paths_bits(periodic, rule, combine, noise):
    rng = np.random.default_rng(7)
    part = Partition(Box([-1.0, -np.pi], [1.0, np.pi]), [0.25, np.pi / 6], [Region("g", (Box([0.2, -0.5], [0.7, 0.5]),))],
                     periodic=periodic)
    n = part.n_cells
    centre = rng.uniform([-1.2, -4.0], [1.2, 4.0], size=(2, n, 2))  # some images leave X or cross the seam
    half = rng.uniform(0.0, [0.2, 0.4], size=(2, n, 2))
    lo, hi = centre - half, centre + half
    known = abstract(part, CellBounds(lo, hi), noise, eps_rule=rule, combine=combine)
    general = abstract(part, CellBounds(lo, hi, np.ones_like(lo)), noise, [[_Exact(), _Exact()]] * 2,
                       eps_rule=rule, combine=combine)
    _same_imdp(known, general)
    assert known.imdp.col.size > 4 * n  # rows list several targets: the comparison has content
