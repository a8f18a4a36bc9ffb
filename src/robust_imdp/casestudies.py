"""The paper's case studies: true systems, regions and formulas (Jackson et al., HSCC 2021, Sec. 6).

Used by the examples, by ``robust-imdp simulate --true-system NAME`` and by the tests. The true
dynamics here are what the *data* come from; the synthesis only sees the data, the known affine
part of each mode and the noise model.

* ``three_mode_linear``: x+ = A_u x + v with A_1 = [[0.4, 0.1], [0, 0.5]],
  A_2 = [[0.4, 0.5], [0, 0.5]], A_3 = [[0.4, 0], [0.5, 0.5]], all dynamics unknown (f_u = 0);
  v ~ N(0, 0.01^2 I) truncated to [-0.01, 0.01] per dimension; 200 samples per mode.
* ``four_mode_nonlinear``: x+ = x + g_u(x) + v (f_u = identity) with g_1 = [0.5 + 0.2 sin x2,
  0.4 cos x1], g_2 = [-0.5 + 0.2 sin x2, 0.4 cos x1], g_3 = [0.4 cos x2, 0.5 + 0.2 sin x1],
  g_4 = [0.4 cos x2, -0.5 + 0.2 sin x1]; same noise; 300 samples per mode.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from robust_imdp.errors import InvalidInputError

__all__ = ["TrueSystem", "CaseStudy", "CASE_STUDIES", "get_case_study", "true_system"]

_A_LINEAR = np.array([
    [[0.4, 0.1], [0.0, 0.5]],
    [[0.4, 0.5], [0.0, 0.5]],
    [[0.4, 0.0], [0.5, 0.5]],
])


def _g_linear(x: np.ndarray, modes: np.ndarray) -> np.ndarray:
    return np.einsum("kij,kj->ki", _A_LINEAR[modes], x)


def _g_nonlinear(x: np.ndarray, modes: np.ndarray) -> np.ndarray:
    s1, s2 = np.sin(x[:, 0]), np.sin(x[:, 1])
    c1, c2 = np.cos(x[:, 0]), np.cos(x[:, 1])
    g = np.empty_like(x)
    # modes 0, 1: [+-0.5 + 0.2 sin x2, 0.4 cos x1]; modes 2, 3: [0.4 cos x2, +-0.5 + 0.2 sin x1]
    offset = np.where((modes == 0) | (modes == 2), 0.5, -0.5)
    horiz = modes < 2
    g[:, 0] = np.where(horiz, offset + 0.2 * s2, 0.4 * c2)
    g[:, 1] = np.where(horiz, 0.4 * c1, offset + 0.2 * s1)
    return g


@dataclass(frozen=True, eq=False)
class TrueSystem:
    """x+ = A_u x + b_u + g_u(x) + v, vectorised over rows with per-row modes.

    Attributes
    ----------
    mode_names : tuple of str
    known_A : (n_modes, n, n) float array, known_b : (n_modes, n) float array
    g : callable ``(x (k, n), modes (k,) int) -> (k, n)``, the unknown part
    sigma, bound : (n,) float arrays of the truncated Gaussian noise
    """

    mode_names: tuple
    known_A: np.ndarray
    known_b: np.ndarray
    g: Callable
    sigma: np.ndarray
    bound: np.ndarray

    def noise_model(self):
        """The noise as a :class:`robust_imdp.noise.TruncatedGaussianNoise`."""
        from robust_imdp.noise import TruncatedGaussianNoise

        return TruncatedGaussianNoise(self.sigma, self.bound)

    def sample_noise(self, k: int, rng) -> np.ndarray:
        """(k, n) independent N(0, sigma_i^2) components truncated to [-bound_i, bound_i]."""
        from scipy.stats import truncnorm

        rng = np.random.default_rng(rng)
        a = self.bound / self.sigma
        return truncnorm.rvs(-a, a, size=(k, len(self.sigma)), random_state=rng) * self.sigma

    def step(self, x, modes, rng) -> np.ndarray:
        """One step for every row of ``x`` (k, n) under ``modes`` (k,) int indices."""
        x = np.asarray(x, dtype=float)
        modes = np.broadcast_to(np.asarray(modes, dtype=np.int64), (x.shape[0],))
        known = np.einsum("kij,kj->ki", self.known_A[modes], x) + self.known_b[modes]
        return known + self.g(x, modes) + self.sample_noise(x.shape[0], rng)

    def sample_dataset(self, n_per_mode: int, lower, upper, rng):
        """Uniform i.i.d. states in the box, propagated once through each mode.

        Returns
        -------
        x : (n_modes * n_per_mode, n), u : (n_modes * n_per_mode,) int, x_next : like x
        """
        rng = np.random.default_rng(rng)
        lower, upper = np.asarray(lower, float), np.asarray(upper, float)
        u = np.repeat(np.arange(len(self.mode_names)), n_per_mode)
        x = lower + rng.random((u.size, lower.size)) * (upper - lower)
        return x, u, self.step(x, u, rng)


@dataclass(frozen=True)
class CaseStudy:
    """A named case study: true system, data size, regions, formulas, threshold."""

    name: str
    system: TrueSystem
    n_per_mode: int
    regions: dict  # name -> list of (lower, upper) pairs
    formulas: tuple
    threshold: float = 0.95
    lower: tuple = (-2.0, -2.0)
    upper: tuple = (2.0, 2.0)
    cell_size: tuple = (0.125, 0.125)
    # GP settings of the examples: fixed before seeing the data (C&G's theorem needs a fixed
    # kernel); B0 is the assumption on the RKHS norm (unit-amplitude SE kernel), chosen above the
    # posterior-mean norm diagnostic (three-mode: < 10; four-mode: ~11.4 for the cos components).
    gp: tuple = (("lengthscale", 8.0), ("signal_variance", 100.0))
    rkhs_bound: float = 10.0


_SIGMA = np.array([0.01, 0.01])
_ZERO = np.zeros((2, 2))
_EYE = np.eye(2)

_THREE = CaseStudy(
    name="three_mode_linear",
    system=TrueSystem(("1", "2", "3"), np.stack([_ZERO] * 3), np.zeros((3, 2)), _g_linear,
                      _SIGMA, _SIGMA.copy()),
    n_per_mode=200,
    regions={
        "des": [((-1.0, -1.0), (0.0, 0.0)), ((0.0, 0.0), (1.0, 1.0))],
        "obs": [((-2.0, -2.0), (-1.0, -1.0)), ((-1.0, 0.0), (0.0, 1.0)),
                ((0.0, -1.0), (1.0, 0.0)), ((1.0, 1.0), (2.0, 2.0))],
    },
    formulas=("G !obs & F des",),
)

_FOUR = CaseStudy(
    name="four_mode_nonlinear",
    system=TrueSystem(("1", "2", "3", "4"), np.stack([_EYE] * 4), np.zeros((4, 2)), _g_nonlinear,
                      _SIGMA, _SIGMA.copy()),
    n_per_mode=300,
    regions={
        "des": [((-0.75, -0.75), (0.75, 0.75))],
        "d1": [((-1.25, 1.0), (0.0, 2.0)), ((-1.75, -2.0), (0.0, -1.5)),
               ((1.25, -1.75), (2.0, 0.0))],
        "d2": [((-0.75, -0.75), (0.75, 0.75))],
        "o": [((-1.75, -0.75), (-1.25, 1.0)), ((-1.0, -1.25), (-0.5, -0.75)),
              ((0.5, -1.75), (1.25, -1.25)), ((0.75, -0.5), (1.0, 0.5)),
              ((0.75, 0.75), (1.75, 1.75))],
    },
    formulas=("F des", "G !o & F d1 & F d2"),
    rkhs_bound=20.0,
)

CASE_STUDIES = {c.name: c for c in (_THREE, _FOUR)}


def get_case_study(name: str) -> CaseStudy:
    """The case study called ``name`` (one of ``CASE_STUDIES``)."""
    try:
        return CASE_STUDIES[name]
    except KeyError:
        raise InvalidInputError(
            f"case study must be one of {sorted(CASE_STUDIES)}; got {name!r}"
        ) from None


def true_system(name: str) -> TrueSystem:
    """The true system of case study ``name`` (for ``validate`` and ``simulate``)."""
    return get_case_study(name).system


def _toml_list(v) -> str:
    return "[" + ", ".join(_toml_list(e) if np.ndim(e) else repr(float(e)) for e in v) + "]"


def problem_toml(case: CaseStudy, formula: str, data_path: str, *, rkhs_bound: float | None = None,
                 eta=None) -> str:
    """The TOML problem file text for ``case`` with ``formula`` (see :mod:`robust_imdp.io`)."""
    rkhs_bound = case.rkhs_bound if rkhs_bound is None else rkhs_bound
    lines = [
        f"# {case.name}: generated by robust_imdp.casestudies (Jackson et al., HSCC 2021, Sec. 6)",
        "[space]",
        f"lower = {_toml_list(case.lower)}",
        f"upper = {_toml_list(case.upper)}",
        f"cell_size = {_toml_list(case.cell_size)}",
        "",
    ]
    for name, boxes in case.regions.items():
        for lo, up in boxes:
            lines += [f"[[regions.{name}]]", f"lower = {_toml_list(lo)}", f"upper = {_toml_list(up)}"]
    lines += ["", "[spec]", f"formula = {formula!r}".replace("'", '"'),
              f"threshold = {case.threshold!r}", "", "[data]", f'path = "{data_path}"', ""]
    sysm = case.system
    for i, m in enumerate(sysm.mode_names):
        lines += [f'[modes."{m}"]', f"A = {_toml_list(sysm.known_A[i])}",
                  f"b = {_toml_list(sysm.known_b[i])}"]
    lines += ["", "[noise]", 'kind = "truncated_gaussian"', f"sigma = {_toml_list(sysm.sigma)}",
              f"bound = {_toml_list(sysm.bound)}", "", "[gp]", f"rkhs_bound = {float(rkhs_bound)!r}"]
    for key, value in case.gp:
        lines.append(f"{key} = {value!r}" if not isinstance(value, str) else f'{key} = "{value}"')
    if eta is not None:
        lines += ["", "[abstraction]", f"eta = {_toml_list(np.broadcast_to(eta, sysm.sigma.shape))}"]
    return "\n".join(lines) + "\n"


def write_problem_files(name: str, directory, *, seed: int = 0, formula: str | None = None,
                        rkhs_bound: float | None = None, eta=None):
    """Generate the case study's data (fixed seed) and problem file into ``directory``.

    Returns
    -------
    Path
        The problem file ``<directory>/<name>.toml`` (data in ``<name>_data.csv``).
    """
    from pathlib import Path

    from robust_imdp.io import write_data_file

    case = get_case_study(name)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    x, u, x_next = case.system.sample_dataset(case.n_per_mode, case.lower, case.upper, seed)
    write_data_file(directory / f"{name}_data.csv", x, u, x_next, modes=case.system.mode_names)
    path = directory / f"{name}.toml"
    path.write_text(problem_toml(case, formula or case.formulas[0], f"{name}_data.csv",
                                 rkhs_bound=rkhs_bound, eta=eta))
    return path
