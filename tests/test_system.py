"""Tests of system.py: Dataset validation, AffineMap, residuals, SwitchedSystem."""

from __future__ import annotations

import numpy as np
import pytest

from robust_imdp.models import noise
from robust_imdp.errors import DimensionError, InvalidInputError, InvalidModelError
from robust_imdp.models.system import AffineMap, Dataset, ModeResiduals, SwitchedSystem, residuals


class _UniformNoise:
    """Tiny stand-in for noise.py: independent uniform components on [-b, b]."""

    def __init__(self, bound, dim):
        self.bound, self.dim = bound, dim

    def sample(self, k, rng=None):
        return np.random.default_rng(rng).uniform(-self.bound, self.bound, (k, self.dim))


def _xs(m=6, n=2, seed=0):
    r = np.random.default_rng(seed)
    return r.normal(size=(m, n)), r.normal(size=(m, n))


# --------------------------------------------------------------------------- Dataset
def test_dataset_with_indices_and_names():
    x, xn = _xs()
    d = Dataset(x, [0, 1, 0, 1, 2, 2], xn)
    assert d.mode_names == ("0", "1", "2") and d.n_modes == 3 and d.dim == 2 and d.n_samples == 6
    bx, bxn = d.by_mode(1)
    np.testing.assert_array_equal(bx, x[[1, 3]])
    np.testing.assert_array_equal(bxn, xn[[1, 3]])
    np.testing.assert_array_equal(d.by_mode("2")[0], x[[4, 5]])
    named = Dataset(x, ["up", "down", "up", "up", "down", "down"], xn)
    assert named.mode_names == ("down", "up")  # sorted distinct names
    np.testing.assert_array_equal(named.u, [1, 0, 1, 1, 0, 0])
    ordered = Dataset(x, ["up", "down", "up", "up", "down", "down"], xn, modes=("up", "down"))
    np.testing.assert_array_equal(ordered.by_mode("up")[0], x[[0, 2, 3]])
    with pytest.raises(ValueError):  # arrays are read-only: the validated object cannot change
        ordered.x[0, 0] = 1.0


def test_dataset_validation_messages():
    x, xn = _xs()
    u = [0, 1, 0, 1, 0, 1]
    with pytest.raises(DimensionError, match=r"x_next must have shape \(m, 2\) like x.*got \(6, 3\)"):
        Dataset(x, u, np.zeros((6, 3)))
    with pytest.raises(DimensionError, match="x must be a 2-D"):
        Dataset(x[:, 0], u, xn)
    with pytest.raises(DimensionError, match=r"u must have shape \(6,\)"):
        Dataset(x, u[:5], xn)
    bad = x.copy()
    bad[2, 1] = np.inf
    with pytest.raises(InvalidInputError, match=r"x must be finite; got inf at index \(2, 1\)"):
        Dataset(bad, u, xn)
    bad = xn.copy()
    bad[4, 0] = np.nan
    with pytest.raises(InvalidInputError, match="x_next must be finite"):
        Dataset(x, u, bad)
    with pytest.raises(InvalidInputError, match=r"modes without data: \['1'\]"):
        Dataset(x, [0, 2, 0, 2, 0, 2], xn)
    with pytest.raises(InvalidInputError, match=r"u must hold mode indices in \[0, 2\); got u\[1\] = 5"):
        Dataset(x, [0, 5, 0, 1, 0, 1], xn, modes=("a", "b"))
    with pytest.raises(InvalidInputError, match="unknown mode 'left'"):
        Dataset(x, ["a", "left", "a", "b", "a", "b"], xn, modes=("a", "b"))
    with pytest.raises(InvalidInputError, match="modes must be distinct"):
        Dataset(x, u, xn, modes=("a", "a"))
    with pytest.raises(InvalidInputError, match="u must hold integer mode indices or mode names"):
        Dataset(x, np.array(u, dtype=float), xn)
    d = Dataset(x, u, xn)
    with pytest.raises(InvalidInputError, match="mode must be an index"):
        d.by_mode(7)


# --------------------------------------------------------------------------- AffineMap
def test_affine_map():
    A = np.array([[1.0, 2.0], [0.0, -1.0]])
    f = AffineMap(A, [0.5, -0.5])
    x = np.array([[1.0, 1.0], [0.0, 2.0]])
    np.testing.assert_allclose(f(x), [[3.5, -1.5], [4.5, -2.5]])  # row i: A x_i + b, by hand
    np.testing.assert_array_equal(AffineMap.zero(2)(x), np.zeros((2, 2)))
    np.testing.assert_array_equal(AffineMap.identity(2)(x), x)
    with pytest.raises(DimensionError, match="A must be square"):
        AffineMap(np.zeros((2, 3)), [0, 0])
    with pytest.raises(DimensionError, match=r"b must have shape \(2,\)"):
        AffineMap(A, [0, 0, 0])
    with pytest.raises(InvalidInputError, match="A must be finite"):
        AffineMap([[np.nan, 0], [0, 1]], [0, 0])
    with pytest.raises(DimensionError, match=r"x must have shape \(k, 2\)"):
        f(np.zeros((3, 3)))


def test_residuals_recover_the_unknown_part_exactly_without_noise():
    x, _ = _xs(m=8)
    u = np.array([0, 1] * 4)
    maps = [AffineMap.identity(2), AffineMap(0.5 * np.eye(2), [1.0, 0.0])]
    g = [lambda z: np.sin(z), lambda z: z**2]
    xn = np.where((u == 0)[:, None], maps[0](x) + g[0](x), maps[1](x) + g[1](x))
    res = residuals(Dataset(x, u, xn), maps)
    assert len(res) == 2 and isinstance(res[0], ModeResiduals)
    for i in range(2):
        np.testing.assert_allclose(res[i].y, g[i](res[i].x), atol=1e-15)
    with pytest.raises(DimensionError, match="known_maps must have one map per mode"):
        residuals(Dataset(x, u, xn), maps[:1])
    with pytest.raises(DimensionError, match="known_maps"):
        residuals(Dataset(x, u, xn), [AffineMap.identity(3), AffineMap.identity(2)])


# --------------------------------------------------------------------------- SwitchedSystem
def _system(bound=0.1):
    maps = [AffineMap.identity(2), AffineMap(0.9 * np.eye(2), [0.2, 0.0])]
    fns = [lambda z: 0.1 * np.sin(z), lambda z: 0.05 * np.cos(z)]
    return SwitchedSystem(maps, fns, _UniformNoise(bound, 2), mode_names=("go", "stay"))


def test_step_is_known_plus_unknown_plus_bounded_noise():
    s = _system()
    x = np.random.default_rng(1).uniform(-1, 1, (500, 2))
    nxt = s.step(x, "stay", rng=3)
    mean = 0.9 * x + [0.2, 0.0] + 0.05 * np.cos(x)
    v = nxt - mean
    assert np.all(np.abs(v) <= 0.1)  # noise is in [-0.1, 0.1]
    # zero-mean noise: |mean(v)| <= 4 sd, sd = 0.1/sqrt(3)/sqrt(500) = 2.6e-3 per component
    assert np.all(np.abs(v.mean(axis=0)) <= 4 * 0.1 / np.sqrt(3) / np.sqrt(500))
    np.testing.assert_array_equal(s.step(x, 1, rng=3), nxt)  # seeded and index == name
    with pytest.raises(InvalidInputError, match="mode must be an index"):
        s.step(x, "jump")
    with pytest.raises(DimensionError, match=r"x must have shape \(k, 2\)"):
        s.step(x[:, :1], 0)


def test_sample_dataset():
    s = _system(bound=0.0)
    d = s.sample_dataset(40, [-2, -1], [2, 1], rng=0)
    assert d.mode_names == ("go", "stay") and d.n_samples == 80
    assert np.all((d.x >= [-2, -1]) & (d.x <= [2, 1]))
    for i, name in enumerate(d.mode_names):
        res = residuals(d, s.known_maps)[i]
        np.testing.assert_allclose(res.y, s.unknown_fns[i](res.x), atol=1e-15)  # zero noise
    again = s.sample_dataset(40, [-2, -1], [2, 1], rng=0)
    np.testing.assert_array_equal(again.x_next, d.x_next)
    with pytest.raises(InvalidInputError, match="box_lower <= box_upper"):
        s.sample_dataset(5, [1, 1], [0, 2])
    with pytest.raises(InvalidInputError, match="n_per_mode"):
        s.sample_dataset(0, [0, 0], [1, 1])


def test_switched_system_validation():
    maps = [AffineMap.identity(2)]
    with pytest.raises(DimensionError, match="unknown_fns must have one function per mode"):
        SwitchedSystem(maps, [], _UniformNoise(0.1, 2))
    with pytest.raises(DimensionError, match="noise.dim must equal the state dimension 2"):
        SwitchedSystem(maps, [np.sin], _UniformNoise(0.1, 3))
    with pytest.raises(InvalidModelError, match="mode_names"):
        SwitchedSystem(maps, [np.sin], _UniformNoise(0.1, 2), mode_names=("a", "b"))
    with pytest.raises(InvalidModelError, match="at least one mode"):
        SwitchedSystem([], [], _UniformNoise(0.1, 2))


def test_works_with_the_noise_module():
    s = SwitchedSystem([AffineMap.zero(2)], [lambda z: 0 * z], noise.TruncatedGaussianNoise([0.01, 0.02], [0.01, 0.02]))
    d = s.sample_dataset(300, [0, 0], [1, 1], rng=4)
    assert np.all(np.abs(d.x_next) <= [0.01, 0.02])  # x_next = v exactly, truncated at the bound
