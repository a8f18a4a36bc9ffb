"""benchmarks/arch/problems: the field's benchmark problem files load as stated in shared/notes/field-benchmarks.md,
and tiny coarse variants of them run end to end (the full ones are the benchmark runner's)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).parents[1]
PROBLEMS = ROOT / "benchmarks" / "arch" / "problems"

# BAS-4D as the notes state it: x' = A x + B u + Q + w
BAS_A = np.array([[0.6682, 0, 0.02632, 0], [0, 0.6830, 0, 0.02096], [1.0005, 0, -0.000499, 0],
                  [0, 0.8004, 0, 0.1996]])
BAS_B = np.array([0.1320, 0.1402, 0, 0])
BAS_Q = np.array([3.4378, 2.9272, 13.0207, 10.4166])
BAS_VAR = 1 / np.array([12.9199, 12.9199, 2.5826, 3.2276])


def _load(name, **edits):
    from robust_imdp.io.problem_file import load_problem

    text = (PROBLEMS / name).read_text()
    for old, new in edits.items():
        assert old in text, old
        text = text.replace(old, new)
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        (Path(d) / name).write_text(text)
        return load_problem(Path(d) / name)


def test_bas4d_is_the_benchmark():
    p = _load("bas4d.toml")
    assert p.n_grid_cells == 1225 and p.known and p.data is None
    assert p.mode_names == ("u=(17)", "u=(18)", "u=(19)", "u=(20)") and p.horizon == 10
    assert p.formula == "G safe" and p.semantics == "auto"
    np.testing.assert_allclose(p.noise.sigma ** 2, BAS_VAR, rtol=1e-15)
    rng = np.random.default_rng(0)
    x = rng.uniform([18.75, 18.75, 29.5, 29.5], [21.25, 21.25, 36.5, 36.5], (50, 4))
    for u, m in zip((17, 18, 19, 20), p.maps):  # the expressions are A x + B u + Q
        np.testing.assert_allclose(m(x), x @ BAS_A.T + BAS_B * u + BAS_Q, rtol=1e-14)


def test_car_parking_is_the_benchmark():
    p = _load("car_parking.toml")
    assert p.n_grid_cells == 1600 and p.known and len(p.mode_names) == 9 and p.horizon == 10
    assert p.inputs.points.tolist()[:2] == [[-1.0, -1.0], [-1.0, 0.0]]
    x = np.array([[1.0, -2.0]])
    for pt, m in zip(p.inputs.points, p.maps):
        np.testing.assert_allclose(m(x), 0.9 * x + 0.7 * pt[None], rtol=1e-15)


def test_robot_reach_avoid_has_441_inputs():
    p = _load("robot2d_reach_avoid.toml")
    assert len(p.mode_names) == 441 and p.n_grid_cells == 1600 and p.inputs.shape == (21, 21)
    m = p.maps[p.mode_names.index("u=(0.5, -0.3)")]
    np.testing.assert_allclose(m([[1.0, 2.0]]), [[1 + 5 * np.cos(-0.3), 2 + 5 * np.sin(-0.3)]], rtol=1e-15)


class BAS:
    """The true BAS-4D system (Gaussian noise, the notes' variances)."""

    mode_names = ("u=(17)", "u=(18)", "u=(19)", "u=(20)")

    def step(self, x, modes, rng):
        u = np.array([17.0, 18.0, 19.0, 20.0])[np.asarray(modes)]
        return x @ BAS_A.T + BAS_B * u[:, None] + BAS_Q + rng.normal(0.0, np.sqrt(BAS_VAR), x.shape)


def test_bas4d_tiny_variant_runs_and_monte_carlo_agrees():
    """2 x 2 x 2 x 2 cells, 2 steps: the safety reading, sound against 16 cells x 300 runs of the true system."""
    from robust_imdp.pipeline.run import synthesize_from_data
    from robust_imdp.validate import validate

    p = _load("bas4d.toml", **{"cell_size = [0.5, 0.5, 1.0, 1.0]": "cell_size = [1.25, 1.25, 3.5, 3.5]",
                               "horizon = 10": "horizon = 2"})
    r = synthesize_from_data(p, progress=False)
    assert r.semantics == "safety" and r.n_cells == 16 and r.diagnostics["dynamics"] == "known"
    assert np.all(r.p_low <= r.p_up) and np.all(r.p_up <= r.p_up_star) and np.all(r.p_low > 0)
    rep = validate(r, BAS(), n_per_cell=300, rng=1, confidence=0.9999)
    assert rep.passed, rep.summary()


def test_car_parking_tiny_variant_runs():
    from robust_imdp.pipeline.run import synthesize_from_data

    p = _load("car_parking.toml", **{"cell_size = [0.5, 0.5]": "cell_size = [2.0, 2.0]", "horizon = 10": "horizon = 3"})
    r = synthesize_from_data(p, progress=False)
    assert r.semantics == "reach" and r.n_cells == 100
    target = (r.partition.labels & (1 << r.partition.atoms.index("target"))) > 0
    assert np.all(r.p_low[target] == 1.0) and np.all(r.p_low <= r.p_up)
    u = r.controller().reset(np.array([2.0, -1.0])).act_input(np.array([2.0, -1.0]))
    assert u.shape == (2,) and set(u.tolist()) <= {-1.0, 0.0, 1.0}
