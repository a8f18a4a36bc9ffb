"""A data-starved 2-D reach-avoid problem for the sampling loop (``robust-imdp improve``), reproducible.

    python benchmarks/starved.py DIR [--per-mode 40] [--seed 0]   # writes DIR/starved.toml + its data file

and then, for example::

    robust-imdp improve DIR/starved.toml --true-system benchmarks/starved.py:System --budget 240 --out DIR/imp

The system: X = [-2, 2]^2 in cells of 0.25 (16 x 16), three modes whose known part is a step of 0.55
(2.2 cells) at 0, 120 and 240 degrees (east, north-west, south-west), ``f_u(x) = x + s_u``, plus an unknown smooth drift per mode
and output, ``g(x) = sum_j a_j k(x, c_j)`` (the unit-amplitude SE kernel of lengthscale 1, 16 centres
uniform on [-2.5, 2.5]^2, Gaussian coefficients scaled to RKHS norm ``TRUE_NORM``; the norm is then
recomputed from the float coefficients in 40-digit arithmetic by ``family.exact_norm``), and bounded
noise (truncated Gaussian, sigma 0.01, bound 0.02). The assumption: lengthscale 1 and
``B = B_FACTOR`` x the largest exact norm (so it holds). Specification ``G !obs & F goal`` with
threshold 0.9: the goal ``[0.5, 1.5] x [1, 2]`` (a 4 x 4 block of cells near the north edge), the obstacle
``[-0.75, 1.75] x [0, 0.5]`` a wall south of it, so paths from the south half go round it.

The unknown drift is drawn once (``SYSTEM_SEED``); the data depend on ``(per_mode, seed)``: ``per_mode``
inputs per mode uniform on X, one step of the true system from each. :func:`build` gives the true system,
the start data and a ``problem(x, u, x_next)`` builder for other data (the sampling benchmark's interface).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "src"))

LOWER, UPPER = np.array([-2.0, -2.0]), np.array([2.0, 2.0])
CELL = 0.25
LENGTHSCALE = 1.0
STEP = 0.55
ANGLES = (0.0, 120.0, 240.0)  # degrees: east, north-west, south-west
MODE_NAMES = ("e", "nw", "sw")
N_CENTRES = 16
TRUE_NORM = 0.15  # RKHS norm every unknown component is scaled to (before the exact recomputation)
B_FACTOR = 1.5  # B / the largest exact norm
NOISE_SIGMA, NOISE_BOUND = 0.01, 0.02
GOAL = ([0.5, 1.0], [1.5, 2.0])
OBSTACLE = ([-0.75, 0.0], [1.75, 0.5])
FORMULA = "G !obs & F goal"
THRESHOLD = 0.9
SYSTEM_SEED = 0


def _drift(seed: int = SYSTEM_SEED):
    """Per mode and output an ``family.Expansion`` (exact norm), and the largest exact norm."""
    import family

    rng = np.random.default_rng([seed, 20261204])
    gs = []
    for _ in MODE_NAMES:
        row = []
        for _i in range(2):
            cen = rng.uniform(LOWER - 0.5, UPPER + 0.5, (N_CENTRES, 2))
            a = rng.standard_normal(N_CENTRES)
            d2 = ((cen[:, None] - cen[None]) ** 2).sum(-1)
            a = a * (TRUE_NORM / np.sqrt(a @ np.exp(-0.5 * d2 / LENGTHSCALE ** 2) @ a))
            row.append(family.Expansion(a, cen, LENGTHSCALE))
        gs.append(row)
    return gs, max(g.norm for row in gs for g in row)


def steps() -> np.ndarray:
    """(3, 2): the known step of every mode."""
    t = np.deg2rad(np.asarray(ANGLES))
    return STEP * np.stack([np.cos(t), np.sin(t)], axis=1)


class System:
    """The true system ``x+ = x + s_u + g_u(x) + v`` (the ``step(x, modes, rng)`` interface of ``simulate``)."""

    mode_names = MODE_NAMES

    def __init__(self, seed: int = SYSTEM_SEED):
        from robust_imdp import TruncatedGaussianNoise

        self.g, self.true_norm = _drift(seed)
        self.steps = steps()
        # within (1 - 1e-9) of the bound: the residuals' rounding stays inside it (as family.py)
        self.noise = TruncatedGaussianNoise(np.full(2, NOISE_SIGMA), np.full(2, NOISE_BOUND * (1 - 1e-9)))

    def drift(self, x, modes) -> np.ndarray:
        x = np.asarray(x, float)
        out = np.empty_like(x)
        for u in range(len(MODE_NAMES)):
            k = np.flatnonzero(np.asarray(modes) == u)
            if k.size:
                out[k] = np.stack([g(x[k]) for g in self.g[u]], axis=1)
        return out

    def step(self, x, modes, rng):
        x = np.asarray(x, float)
        modes = np.asarray(modes, dtype=np.int64)
        return x + self.steps[modes] + self.drift(x, modes) + self.noise.sample(x.shape[0], rng)


def start_data(system: System, per_mode: int, seed: int):
    """``per_mode`` uniform inputs per mode and one step from each: ``(x, u, x_next)``."""
    rng = np.random.default_rng([seed, per_mode])
    u = np.repeat(np.arange(len(MODE_NAMES)), per_mode)
    x = LOWER + rng.random((u.size, 2)) * (UPPER - LOWER)
    return x, u, system.step(x, u, rng)


def problem(x, u, x_next, system: System | None = None):
    """The Problem of data ``(x, u (mode indices), x_next)``."""
    from robust_imdp import Problem, TruncatedGaussianNoise

    system = system or System()
    return Problem.from_arrays(
        x, np.asarray(MODE_NAMES)[np.asarray(u)], x_next, lower=LOWER, upper=UPPER, cell_size=CELL,
        regions={"goal": GOAL, "obs": OBSTACLE}, formula=FORMULA, threshold=THRESHOLD,
        modes={n: (np.eye(2), s) for n, s in zip(MODE_NAMES, system.steps)},
        noise=TruncatedGaussianNoise(np.full(2, NOISE_SIGMA), np.full(2, NOISE_BOUND)),
        rkhs_bound=B_FACTOR * system.true_norm, lengthscale=LENGTHSCALE, misspecification=0.0)


def build(per_mode: int = 40, seed: int = 0) -> dict:
    """``{"system", "lower", "upper", "start": (x, u, x_next), "problem": (x, u, x_next) -> Problem, "B",
    "true_norm"}``."""
    system = System()
    return {"system": system, "lower": LOWER.copy(), "upper": UPPER.copy(), "start": start_data(system, per_mode, seed),
            "problem": lambda x, u, xn: problem(x, u, xn, system), "B": B_FACTOR * system.true_norm,
            "true_norm": system.true_norm, "lengthscale": LENGTHSCALE}


def main(argv=None) -> int:
    from robust_imdp import save_problem

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--per-mode", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    b = build(args.per_mode, args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    path = save_problem(b["problem"](*b["start"]), args.out / "starved.toml")
    print(f"wrote {path} ({args.per_mode} samples per mode, seed {args.seed}; B = {b['B']:.4g}, exact norm "
          f"{b['true_norm']:.4g})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
