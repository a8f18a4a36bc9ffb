"""End to end on a cylinder: a learned part, a periodic heading, and Monte-Carlo containment.

x1 in [0, 2] (not periodic) drifts by an unknown 0.05 sin(x2); x2 in [-pi, pi) is periodic and
known (rkhs_bound 0 there): mode ``plus`` turns by +0.6, ``minus`` by -0.6. An obstacle band
|x2| <= 0.6 separates the cells above it from the goal x2 <= -2.4, so a cell above the band can
only be certified by turning ``plus`` through the seam at +-pi (docs/periodic.md).
"""

import numpy as np
import pytest

from robust_imdp import Problem, TruncatedGaussianNoise, synthesize_from_data
from robust_imdp.validate import validate

PI = float(np.pi)


class Cylinder:
    mode_names = ("plus", "minus")

    def step(self, x, modes, rng):
        x = np.asarray(x, dtype=float)
        v = np.clip(rng.normal(0.0, 0.01, x.shape), -0.02, 0.02)  # truncated N(0, 0.01^2) to +-0.02
        turn = np.where(np.asarray(modes) == 0, 0.6, -0.6)
        return np.column_stack([x[:, 0] + 0.05 * np.sin(x[:, 1]), x[:, 1] + turn]) + v


@pytest.fixture(scope="module")
def run():
    system = Cylinder()
    rng = np.random.default_rng(0)
    n = 150
    x = np.column_stack([rng.uniform(0, 2, 2 * n), rng.uniform(-PI, PI, 2 * n)])
    modes = np.repeat([0, 1], n)
    x_next = system.step(x, modes, rng)
    x_next[:, 1] = (x_next[:, 1] + PI) % (2 * PI) - PI  # the data wrap like the states
    problem = Problem.from_arrays(
        x, np.array(system.mode_names)[modes], x_next, lower=[0, -PI], upper=[2, PI],
        cell_size=[0.25, 2 * PI / 16],
        regions={"goal": ([0, -PI], [2, -2.4]), "obs": ([0, -0.6], [2, 0.6])},
        formula="G !obs & F goal", threshold=0.5,
        modes={"plus": (np.eye(2), [0, 0.6]), "minus": (np.eye(2), [0, -0.6])},
        noise=TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02]), rkhs_bound=[0.3, 0.0],
        lengthscale=1.5, periodic=(False, True))
    return system, synthesize_from_data(problem, progress=False)


def test_cells_above_the_band_are_certified_through_the_seam(run):
    _, result = run
    centre = 0.5 * (result.cells_lower + result.cells_upper)
    yes = result.class_names == "yes"
    above = yes & (centre[:, 1] > 0.6)
    # The only route from above the band to the goal crosses +-pi: without the wrap these cells
    # would leave X (an absorbing failure) and none of them could be Q_yes.
    assert np.count_nonzero(above) >= 5
    plus = result.mode_names.index("plus")
    # DFA state 0 (not yet reached the goal, not violated): where these cells' runs start
    assert np.all(np.asarray(result.strategy)[above, 0] == plus)


def test_monte_carlo_containment_on_the_cylinder(run):
    system, result = run
    # 152 cells x 200 runs at 99.99 % Wilson confidence: a sound result is flagged in a cell
    # with probability <= 1e-4, so the allowance (binomial tail at 0.9999) is 0 or 1 cells.
    rep = validate(result, system, n_per_cell=200, max_steps=80, rng=1, confidence=0.9999)
    assert rep.outside.size <= rep.allowed_outside, rep.summary()
    assert rep.capped.sum() == 0  # every run decided, so the check is not vacuous on p_up
