"""The field's benchmarks (ARCH-COMP stochastic models, IMPaCT, the HSCC 2025 harness) beside the published numbers.

    python benchmarks/arch/run.py                       # every benchmark, full size; results/arch.{json,md}
    python benchmarks/arch/run.py --only bas4d car_parking --timeout 900
    python benchmarks/arch/run.py --quick               # coarse variants (CI-sized); results/arch_quick.{json,md}
    python benchmarks/arch/run.py --list                # the benchmarks, their files and what --quick changes

Every benchmark is a problem file of ``benchmarks/arch/problems`` (its header names the source, the variant
conflicts and how our grid corresponds to the published tools' cell counts), run as it is -- or, for the
``*_lattice`` rows, with X widened by half a cell so that our cells are IMPaCT's lattice points -- each in a child
process of its own (``--child``), one after the other. Per benchmark:

* **our numbers**: p_low and p_up (min / mean / max over the cells), Q_yes / Q_no / Q_? at the file's threshold, the
  value at the reference initial state or set where a source reports one, the abstraction form (factored or
  joint) and the stage times (``Result.timings``: bound, abstract, synthesize);
* **time and memory**: the child's wall time (start to exit: interpreter, imports, loading, the pipeline; the
  Monte Carlo not included) and the peak resident memory of the pipeline (``resource.getrusage`` of the child and
  of its helper processes, read before the Monte Carlo), and the load average before and after (the machine is
  shared: 2 cores);
* **Monte-Carlo check from the true system**: the dynamics written again in numpy from the source's definition
  (not from the problem file: the vehicle's uses ``atan`` as IMPaCT does, the file an identity without it), the
  noise drawn with numpy; the run's controller from sampled initial states of ``--mc-cells`` seeded cells (plus
  the reference cells), ``--mc-runs`` runs each (``robust_imdp.validate.validate``): the empirical satisfaction
  must lie in [p_low, p_up] up to Wilson intervals at confidence 0.999, no more cells flagged than chance allows;
* **published numbers** beside ours (IMPaCT, QEST+FORMATS 2024, Tables 1-2; the ARCH-COMP19 report, Tables 8
  and 10), with their hardware, and whether the instance is the same as ours.

A benchmark whose joint abstraction cannot fit (BAS-7D, linear 6-D/7-D) needs the factored form
(``[abstraction].form``): it is reported ``pending`` when the installed pipeline cannot give it. A child that
runs past ``--timeout`` is stopped (its process group) and reported ``timeout``; one refused by the pre-flight
memory estimate ``too large``; any other failure ``error`` with its last line. Nothing crashes the run.

Results: ``benchmarks/results/arch.json`` (one row per benchmark; ``--only`` replaces its rows and keeps the
others) and ``arch.md``, written beside the old ones and renamed into place (``--out`` another folder).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
PROBLEMS = HERE / "problems"
RESULTS = ROOT / "benchmarks" / "results"

# ----------------------------------------------------------------------------------------- published numbers
IMPACT_T1 = "IMPaCT (QEST+FORMATS 2024) Table 1; 2x AMD EPYC 7702 (128 cores), 2 TB"
IMPACT_T2 = "IMPaCT Table 2; Intel i9-12900 (CPU) / NVIDIA RTX A4000 (GPU)"
ARCH19 = "ARCH-COMP19 report; StocHy and FAUST2 on an Intel i7-8550U, 8 GB"


def _pub(source, what, same, note=""):
    return {"source": source, "numbers": what, "same_instance": same, "note": note}


# ----------------------------------------------------------------------------------------- true systems
class TrueSystem:
    """The true system of a benchmark, for ``validate``: ``f(x, u)`` in numpy and the source's noise.

    ``inputs`` is the ``(n_modes, m)`` input of each mode (the problem's grid points; ``(1, 0)`` for an
    autonomous system), ``f(x, u)`` takes ``(k, n)`` states and ``(k, m)`` inputs.
    """

    def __init__(self, f, mode_names, inputs, *, variance=None, uniform=None):
        self.f, self.mode_names, self.inputs = f, tuple(mode_names), np.asarray(inputs, dtype=float)
        self.sd = None if variance is None else np.sqrt(np.asarray(variance, dtype=float))
        self.uniform = None if uniform is None else np.asarray(uniform, dtype=float)

    def step(self, x, modes, rng):
        u = self.inputs[np.asarray(modes, dtype=np.int64)]
        mean = self.f(np.asarray(x, dtype=float), u)
        if self.sd is not None:
            return mean + rng.normal(0.0, self.sd, mean.shape)
        return mean + rng.uniform(-self.uniform, self.uniform, mean.shape)


BAS4_A = np.array([[0.6682, 0, 0.02632, 0], [0, 0.6830, 0, 0.02096], [1.0005, 0, -0.000499, 0],
                   [0, 0.8004, 0, 0.1996]])
BAS4_B = np.array([0.1320, 0.1402, 0, 0])
BAS4_Q = np.array([3.4378, 2.9272, 13.0207, 10.4166])
BAS7_A = np.array([[0.9678, 0, 0.0036, 0, 0.0036, 0, 0.0036], [0, 0.9682, 0, 0.0034, 0, 0.0034, 0.0034],
                   [0.0106, 0, 0.9494, 0, 0, 0, 0], [0, 0.0097, 0, 0.9523, 0, 0, 0], [0.0106, 0, 0, 0, 0.9494, 0, 0],
                   [0, 0.0097, 0, 0, 0, 0.9523, 0], [0.0106, 0.0097, 0, 0, 0, 0, 0.9794]])
AN_A = np.array([[0.8192, 0.03412, 0.01265], [0.01646, 0.9822, 0.0001], [0.0009, 0.00002, 0.9989]])
AN_B = np.array([0.01883, 0.0002, 0.00001])


def _integrator(n, tau=0.1):
    a, b = np.eye(n), np.zeros(n)
    for i in range(n):
        for j in range(i + 1, n):
            a[i, j] = tau ** (j - i) / math.factorial(j - i)
        b[i] = tau ** (n - i) / math.factorial(n - i)
    return a, b


def _cyclic(n):
    a = 0.7 * np.eye(n)
    a[np.arange(n), (np.arange(n) + 1) % n] = -0.1
    return a


def _vdp(peer):
    def f(x, u):
        damp = (1 - x[:, 0]) ** 2 if peer else 1 - x[:, 0] ** 2
        x2 = x[:, 1] + 0.1 * (damp * x[:, 1] - x[:, 0]) + (u[:, 0] if u.shape[1] else 0.0)
        return np.column_stack([x[:, 0] + 0.1 * x[:, 1], x2])
    return f


def _vehicle(x, u):
    a = np.arctan(np.tan(u[:, 1]) / 2.0)  # IMPaCT's vehicle3D.cpp, as written there
    return x + 0.1 * np.column_stack([u[:, 0] * np.cos(a + x[:, 2]) / np.cos(a),
                                      u[:, 0] * np.sin(a + x[:, 2]) / np.cos(a), u[:, 0] * np.tan(u[:, 1])])


def _robot(x, u):
    return x + 10.0 * u[:, :1] * np.column_stack([np.cos(u[:, 1]), np.sin(u[:, 1])])


SYSTEMS = {  # name -> (f(x, u), noise keyword arguments)
    "bas4d": (lambda x, u: x @ BAS4_A.T + BAS4_B * u[:, :1] + BAS4_Q,
              {"variance": 1 / np.array([12.9199, 12.9199, 2.5826, 3.2276])}),
    "robot2d": (_robot, {"variance": [0.75, 0.75]}),
    "car_parking": (lambda x, u: 0.9 * x + 0.7 * u, {"variance": [1.0, 1.0]}),
    "vdp_arch20": (_vdp(False), {"uniform": [0.02, 0.02]}),
    "vdp_gaussian": (_vdp(False), {"variance": [0.2, 0.2]}),
    "vdp_gaussian_peer": (_vdp(True), {"variance": [0.2, 0.2]}),
    "anaesthesia3d": (lambda x, u: x @ AN_A.T + AN_B * u[:, :1], {"variance": [1e-3] * 3}),
    "vehicle3d": (_vehicle, {"variance": [2 / 3] * 3}),
    "bas7d": (lambda x, u: x @ BAS7_A.T,
              {"variance": 1 / np.array([51.2821, 50.0, 21.7865, 23.5294, 25.1889, 26.5252, 91.7431])}),
    **{f"integrator{n}": ((lambda a, b: lambda x, u: x @ a.T + b * u[:, :1])(*_integrator(n)),
                          {"variance": [0.01] * n}) for n in (2, 3, 4)},
    **{f"linear{n}d": ((lambda a: lambda x, u: x @ a.T)(_cyclic(n)), {"variance": [0.01] * n}) for n in (6, 7)},
}


def true_system(system: str, problem) -> TrueSystem:
    """The benchmark's true system with the problem's modes (their inputs from the problem's input grid)."""
    f, noise = SYSTEMS[system]
    inputs = problem.inputs.points if problem.inputs is not None else np.zeros((len(problem.mode_names), 0))
    return TrueSystem(f, problem.mode_names, inputs, **noise)


# ----------------------------------------------------------------------------------------- the benchmarks
@dataclass(frozen=True)
class Bench:
    """One benchmark row.

    ``edits`` are text replacements applied to the problem file (a variant of it: the lattice rows), ``quick``
    the replacements of ``--quick`` (None: not run in quick mode); ``reference`` is a box of initial states
    ``(label, lower, upper, published)`` whose cells' p_low is reported, ``factored`` says the joint abstraction
    cannot fit (the row is pending without the factored form).
    """

    name: str
    file: str
    system: str
    published: tuple = ()
    edits: dict = field(default_factory=dict)
    quick: dict | None = None
    reference: tuple | None = None
    factored: bool = False
    note: str = ""


_ROBOT_PUB = (_pub(IMPACT_T1, "441 x 121: abstraction 0.60 + 1.58 s, 175 MB; synthesis 7.34 s (GLPK) / 8.53 s "
                   "(sorted), infinite horizon", False, "IMPaCT's 441 cells are our lattice variant; unbounded reach"),
              _pub(IMPACT_T2, "synthesis 13.07 s GLPK, 2.26 s sorted CPU, 5.2 s GPU", False))
_RA_PUB = (_pub(IMPACT_T1, "1,681 x 441: abstraction 20.7 + 59.8 s, 8.8 GB; synthesis 1,549 s (GLPK) / 1,047 s "
                "(sorted), infinite horizon", False, "IMPaCT's 1,681 cells are our lattice variant; unbounded"),
           _pub(IMPACT_T2, "synthesis 1,691 s GLPK, 577 s sorted CPU, 216 s GPU", False))

BENCHMARKS = (
    Bench("bas4d", "bas4d.toml", "bas4d",
          (_pub(IMPACT_T1, "1,225 x 4: abstraction 0.89 + 1.33 s, 48 MB; synthesis 6.37 h (GLPK, infinite) / "
                "3,038 s (sorted, run to convergence)", False, "same grid and inputs; infinite horizon"),
           _pub(IMPACT_T2, "10 steps: synthesis 23.2 s GLPK, 0.38 s sorted CPU, 0.53 s GPU", True,
                "same grid, inputs and horizon; no probabilities published"),
           _pub(ARCH19, "CS1BAS (Problem 4.2.1): StocHy IMDP 0.43 s, >= 0.99; FAUST2 2,940 s, >= 0.80", False,
                "another instance: u in [15, 22], safe [19.5, 20.5]^2 x R^2, 6 steps")),
          quick={"cell_size = [0.5, 0.5, 1.0, 1.0]": "cell_size = [1.25, 1.25, 3.5, 3.5]",
                 "horizon = 10": "horizon = 2"}),
    Bench("robot2d_reach", "robot2d_reach.toml", "robot2d", _ROBOT_PUB,
          quick={"cell_size = [1.0, 1.0]": "cell_size = [4.0, 4.0]", "step = [0.2, 0.2]": "step = [1.0, 0.5]",
                 "upper = [7.0, 7.0]": "upper = [10.0, 10.0]", "lower = [5.0, 5.0]": "lower = [6.0, 6.0]",
                 "horizon = 10": "horizon = 3"}),
    Bench("robot2d_reach_lattice", "robot2d_reach.toml", "robot2d", _ROBOT_PUB,
          edits={"lower = [-10.0, -10.0]": "lower = [-10.5, -10.5]", "upper = [10.0, 10.0]": "upper = [10.5, 10.5]",
                 "lower = [5.0, 5.0]": "lower = [4.5, 4.5]", "upper = [7.0, 7.0]": "upper = [7.5, 7.5]"},
          note="IMPaCT's 441 cells: X = [-10.5, 10.5]^2; T = the cells whose centres lie in [5, 7]^2"),
    Bench("robot2d_reach_avoid", "robot2d_reach_avoid.toml", "robot2d", _RA_PUB),
    Bench("robot2d_reach_avoid_lattice", "robot2d_reach_avoid.toml", "robot2d", _RA_PUB,
          edits={"lower = [-10.0, -10.0]": "lower = [-10.25, -10.25]",
                 "upper = [10.0, 10.0]": "upper = [10.25, 10.25]",
                 "lower = [5.0, 5.0]": "lower = [4.75, 4.75]", "upper = [7.0, 7.0]": "upper = [7.25, 7.25]",
                 "lower = [-2.0, -2.0]": "lower = [-2.25, -2.25]", "upper = [2.0, 2.0]": "upper = [2.25, 2.25]"},
          note="IMPaCT's 1,681 cells: X = [-10.25, 10.25]^2; T and the avoid set = the cells whose centres lie "
               "in them"),
    Bench("car_parking", "car_parking.toml", "car_parking",
          quick={"cell_size = [0.5, 0.5]": "cell_size = [2.0, 2.0]", "horizon = 10": "horizon = 3"}),
    Bench("vdp_arch20", "vdp_arch20.toml", "vdp_arch20",
          quick={"cell_size = [0.1, 0.1]": "cell_size = [0.5, 0.5]", "formula = \"F target\"":
                 "formula = \"F target\"\nhorizon = 5", "lower = [-1.2, -2.9]": "lower = [-1.5, -3.0]",
                 "upper = [-0.9, -2.0]": "upper = [-0.5, -2.0]"},
          note="reach B staying in X, not the report's G a & G F b"),
    Bench("vdp_gaussian", "vdp_gaussian.toml", "vdp_gaussian",
          quick={"cell_size = [0.16, 0.16]": "cell_size = [0.8, 0.8]", "step = [0.2]": "step = [1.0]",
                 "horizon = 10": "horizon = 3"}),
    Bench("vdp_gaussian_peer", "vdp_gaussian_peer.toml", "vdp_gaussian_peer",
          note="the peers' (1 - x1)^2 variant, not Van der Pol"),
    Bench("integrator2", "integrator2.toml", "integrator2",
          quick={"cell_size = [0.2, 0.2]": "cell_size = [2.0, 2.0]"}),
    Bench("integrator3", "integrator3.toml", "integrator3"),
    Bench("integrator4", "integrator4.toml", "integrator4", factored=True),
    Bench("anaesthesia3d", "anaesthesia3d.toml", "anaesthesia3d",
          (_pub(ARCH19, "Table 8, x3[0] = 5: StocHy IMDP 27.86 s, >= 0.991 (abstraction error 0.008); StocHy MDP "
                "422.92 s; FAUST2 1,596.93 s; SReachTools 33.93 s, >= 0.99. All of S: StocHy IMDP 85.80 s, "
                ">= 0.994; FAUST2 18,147 s", True,
                "the report prints w ~ N(0, 5); its truncation implies the variance 1e-3 used here"),),
          quick={"cell_size = [0.25, 0.5, 0.5]": "cell_size = [1.25, 2.5, 2.5]", "horizon = 10": "horizon = 3"},
          reference=("x3[0] = 5 (max p_low over the cells at x3 = 5)", [1.0, 0.0, 5.0], [6.0, 10.0, 5.0],
                     ">= 0.991 (StocHy IMDP)")),
    Bench("anaesthesia3d_factored", "anaesthesia3d.toml", "anaesthesia3d",
          edits={'transitions = "exact"': 'transitions = "exact"\nform = "factored"'},
          reference=("x3[0] = 5 (max p_low over the cells at x3 = 5)", [1.0, 0.0, 5.0], [6.0, 10.0, 5.0],
                     ">= 0.991 (StocHy IMDP)"), factored=True,
          note="the same problem with [abstraction].form = 'factored' (auto picks the joint form: short rows)"),
    Bench("vehicle3d", "vehicle3d.toml", "vehicle3d",
          (_pub(IMPACT_T1, "7,938 x 30: abstraction 89.1 + 114 s, 7.42 GB (+ 44.6 + 46.6 s, 2.91 GB target "
                "vectors); synthesis 3.69 h (GLPK) / 286 s (sorted)", True, "same cells, inputs and sets; unbounded"),
           _pub(IMPACT_T2, "synthesis > 3.0 h GLPK, 241 s sorted CPU, 490 s GPU", True)),
          quick={"cell_size = [0.5, 0.5, 0.4]": "cell_size = [1.5, 1.5, 1.2]",
                 "values = [[-1.0, 0.0, 1.0, 2.0, 3.0, 4.0], [-0.4, -0.2, 0.0, 0.2, 0.4]]":
                 "values = [[0.0, 4.0], [-0.4, 0.4]]",
                 "[[regions.target]]\nlower = [-5.25, -0.25, -3.6]\nupper = [0.25, 5.25, 3.6]":
                 "[[regions.target]]\nlower = [-5.25, 0.75, -3.6]\nupper = [0.75, 5.25, 3.6]",
                 "[[regions.avoid]]\nlower = [-5.25, -0.75, -3.6]\nupper = [0.25, -0.25, 3.6]":
                 "[[regions.avoid]]\nlower = [-5.25, -0.75, -3.6]\nupper = [0.75, 0.75, 3.6]",
                 "threshold = 0.9": "threshold = 0.9\nhorizon = 3"}),
    Bench("bas7d", "bas7d.toml", "bas7d",
          (_pub(IMPACT_T1, "107,163 cells: abstraction 1.47 h + 2.03 h, 91.9 GB; synthesis > 24 h", False,
                "same cells; unbounded safety"),),
          factored=True),
    Bench("linear6d", "linear6d.toml", "linear6d", factored=True),
    Bench("linear7d", "linear7d.toml", "linear7d", factored=True),
)
BY_NAME = {b.name: b for b in BENCHMARKS}


# ----------------------------------------------------------------------------------------- the child
def problem_text(bench: Bench, quick: bool) -> str:
    """The problem file's text with the row's edits (and ``--quick``'s) applied; every edit must apply once."""
    text = (PROBLEMS / bench.file).read_text()
    for edits in (bench.edits, bench.quick if quick else {}):
        for old, new in (edits or {}).items():
            if text.count(old) != 1:
                raise ValueError(f"{bench.name}: edit {old!r} must occur once in {bench.file}; found "
                                 f"{text.count(old)}")
            text = text.replace(old, new)
    return text


def factored_available() -> str | None:
    """Why the installed pipeline cannot give the factored form, or None when it can."""
    try:
        from robust_imdp.abstraction import factored  # noqa: F401
        from robust_imdp.pipeline.problem import Problem
    except ImportError as exc:
        return f"the factored form is not installed ({exc})"
    if not hasattr(Problem, "form_choice"):
        return "the pipeline has no [abstraction].form yet"
    from robust_imdp.io import problem_file
    if "form" not in getattr(problem_file, "_SCHEMA", {}).get("abstraction", ((), ()))[1]:
        return "problem files do not take [abstraction].form yet"
    return None


def _peak_mb() -> float:
    """Peak resident memory of this process and of its waited-for helpers, MB (Linux: ru_maxrss in KB)."""
    return max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
               resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) / 1024.0


def _stats(v) -> dict:
    v = np.asarray(v, dtype=float)
    return {"min": float(v.min()), "mean": float(v.mean()), "max": float(v.max())}


def _reference_cells(result, lower, upper) -> np.ndarray:
    """Cells whose closed box meets the closed box [lower, upper]."""
    lo, hi = np.asarray(result.cells_lower), np.asarray(result.cells_upper)
    return np.flatnonzero(np.all((lo <= np.asarray(upper)) & (hi >= np.asarray(lower)), axis=1))


def child(name: str, quick: bool, out: Path, mc_cells: int, mc_runs: int, seed: int) -> None:
    """Run one benchmark in this process and write its row to ``out`` (JSON)."""
    t0 = time.perf_counter()
    bench = BY_NAME[name]
    row = {"name": name, "file": f"benchmarks/arch/problems/{bench.file}", "quick": quick}
    from robust_imdp.io.problem_file import load_problem
    from robust_imdp.pipeline.run import synthesize_from_data
    from robust_imdp.validate import validate

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / bench.file
        path.write_text(problem_text(bench, quick))
        problem = load_problem(path)
    form, why = problem.form_choice() if hasattr(problem, "form_choice") else ("joint", "no factored form")
    row.update(grid_cells=int(problem.n_grid_cells), modes=len(problem.mode_names), formula=problem.formula,
               horizon=problem.horizon, threshold=float(problem.threshold), form=form, form_reason=why)
    result = synthesize_from_data(problem, progress=False, advice=False, margins=False)
    row["seconds"] = time.perf_counter() - t0
    row["peak_mb"] = _peak_mb()
    row["timings"] = {k: float(v) for k, v in result.timings.items()}
    row["form"] = result.parameters.get("form", "joint")  # a factored result's parameters name its form
    row["semantics"] = getattr(result.synthesis, "semantics", None)
    p_low, p_up = np.asarray(result.p_low), np.asarray(result.p_up)
    t = float(problem.threshold)
    row["cells"] = int(result.n_cells)
    row.update(p_low=_stats(p_low), p_up=_stats(p_up), q_yes=int(np.sum(p_low >= t)), q_no=int(np.sum(p_up < t)),
               q_maybe=int(np.sum((p_low < t) & (p_up >= t))), sound_order=bool(np.all(p_low <= p_up)))
    ref = None
    if bench.reference is not None:
        label, lower, upper, published = bench.reference
        ref = _reference_cells(result, lower, upper)
        row["reference"] = {"label": label, "cells": int(ref.size), "published": published,
                            "p_low": _stats(p_low[ref]) if ref.size else None,
                            "p_up": _stats(p_up[ref]) if ref.size else None}
    rng = np.random.default_rng(seed)
    cells = rng.choice(result.n_cells, size=min(mc_cells, result.n_cells), replace=False)
    if ref is not None and ref.size:
        cells = np.union1d(cells, rng.choice(ref, size=min(10, ref.size), replace=False))
    t1 = time.perf_counter()
    rep = validate(result, true_system(bench.system, problem), n_per_cell=mc_runs, rng=seed + 1,
                   confidence=0.999, cells=np.sort(cells))
    row["monte_carlo"] = {"cells": int(len(rep.cells)), "runs_per_cell": int(rep.n_per_cell),
                          "flagged": int(len(rep.outside)), "allowed": int(rep.allowed_outside),
                          "expected": float(rep.expected_outside), "passed": bool(rep.passed),
                          "seconds": time.perf_counter() - t1, "empirical": _stats(rep.empirical),
                          "p_low_of_cells": _stats(rep.p_low), "p_up_of_cells": _stats(rep.p_up),
                          "max_excess_below": float(np.max(np.asarray(rep.p_low) - np.asarray(rep.wilson_up),
                                                           initial=-1.0)),
                          "max_excess_above": float(np.max(np.asarray(rep.wilson_low) - np.asarray(rep.p_up),
                                                           initial=-1.0))}
    row["status"] = "ok" if rep.passed else "monte-carlo failed"
    _write_json(out, row)


# ----------------------------------------------------------------------------------------- the parent
def _write_json(path: Path, data) -> None:
    """Write beside the old file and rename into place (a failure leaves the old file as it was)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def _write_text(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def run_child(bench: Bench, args) -> dict:
    """One benchmark in its own process group: wall time, peak memory (``wait4``), stopped at ``--timeout``."""
    row = {"name": bench.name, "file": f"benchmarks/arch/problems/{bench.file}", "quick": args.quick,
           "load_before": os.getloadavg()[0]}
    if bench.factored and (why := factored_available()) is not None:
        row.update(status="pending", why=f"needs the factored form: {why}")
        return row
    with tempfile.TemporaryDirectory() as tmp:
        out, err = Path(tmp) / "row.json", Path(tmp) / "stderr.txt"
        cmd = [sys.executable, str(Path(__file__).resolve()), "--child", bench.name, "--child-out", str(out),
               "--mc-cells", str(args.mc_cells), "--mc-runs", str(args.mc_runs), "--seed", str(args.seed)]
        cmd += ["--quick"] if args.quick else []
        t0 = time.perf_counter()
        with open(err, "w") as ferr:
            proc = subprocess.Popen(cmd, stdout=ferr, stderr=subprocess.STDOUT, start_new_session=True, cwd=ROOT)
        timed_out, status, usage = False, None, None
        while status is None:
            pid, st, ru = os.wait4(proc.pid, os.WNOHANG)
            if pid == proc.pid:
                status, usage = st, ru
                break
            if time.perf_counter() - t0 > args.timeout:
                timed_out = True
                os.killpg(proc.pid, signal.SIGKILL)
                _, status, usage = os.wait4(proc.pid, 0)
                break
            time.sleep(0.2)
        proc.returncode = os.waitstatus_to_exitcode(status)
        row["wall_seconds"] = time.perf_counter() - t0
        row["child_peak_mb"] = usage.ru_maxrss / 1024.0
        row["load_after"] = os.getloadavg()[0]
        tail = err.read_text().strip().splitlines()[-6:] if err.exists() else []
        if timed_out:
            row.update(status="timeout", why=f"stopped after --timeout {args.timeout:g} s")
        elif out.exists():
            row.update(json.loads(out.read_text()))
            row["load_after"] = os.getloadavg()[0]
        elif any("ResourceError" in line for line in tail):
            row.update(status="too large", why=tail[-1][-300:])
        else:
            row.update(status="error", why=(tail[-1][-300:] if tail else f"exit {proc.returncode}"))
    return row


def _fmt_stats(s, digits=3) -> str:
    return "-" if not s else f"{s['min']:.{digits}f} / {s['mean']:.{digits}f} / {s['max']:.{digits}f}"


def render(data: dict) -> str:
    """The markdown tables of a record."""
    rows = data["rows"]
    cmd = "python benchmarks/run.py arch" + (" --quick" if data.get("quick") else "")
    lines = [f"# The field's benchmarks (`benchmarks/arch/run.py`{' --quick' if data.get('quick') else ''})", "",
             f"{data['date']}, commit {data['commit']}, {data['machine']}; load average {data['load_start']:.1f} at "
             f"the start, {data['load_end']:.1f} at the end (per row below). Reproduce: `{cmd}` "
             f"(`python benchmarks/arch/run.py --only NAME` for one row). Each row runs in its own process: "
             f"*time* is its wall time (start to exit, Monte Carlo excluded) and *stages* the pipeline's bound / "
             f"abstract / synthesize seconds (numba's kernels warmed up before the rows: `python -m robust_imdp.warmup`); "
             f"*peak* the pipeline's peak RSS. Monte Carlo: the true system "
             f"(numpy, from the source's definition) under the run's controller, {data['mc_cells']} seeded cells "
             f"(+ the reference cells) x {data['mc_runs']} runs, Wilson 0.999; *flagged / allowed*.", "",
             "| benchmark | cells x inputs | spec | form | p_low min / mean / max | p_up min / mean / max | "
             "Q_yes / Q_no / Q_? | reference | time (stages) | peak | load | Monte Carlo |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.get("status") not in ("ok", "monte-carlo failed"):
            lines.append(f"| {r['name']} | | | | **{r['status']}**: {r.get('why', '')} | | | | "
                         f"{r.get('wall_seconds', 0):.0f} s | | {r.get('load_before', 0):.1f} | |")
            continue
        spec = f"`{r['formula']}`" + (f", k = {r['horizon']}" if r.get("horizon") else "") + \
            f" ({r.get('semantics') or 'reach'}, t = {r['threshold']:g})"
        tm = r["timings"]
        stages = " / ".join(f"{tm.get(k, 0):.2f}" for k in ("bound", "abstract", "synthesize"))
        ref = "-"
        if r.get("reference") and r["reference"].get("p_low"):
            rr = r["reference"]
            ref = f"{rr['label']}: max p_low {rr['p_low']['max']:.4f} ({rr['cells']} cells); published {rr['published']}"
        mc = r["monte_carlo"]
        mc_txt = f"{'passed' if mc['passed'] else '**FAILED**'} {mc['flagged']} / {mc['allowed']} ({mc['cells']} cells)"
        if "empirical" in mc:  # mean over the tested cells: p_low <= empirical <= p_up
            mc_txt += (f"; mean {mc['p_low_of_cells']['mean']:.3f} <= {mc['empirical']['mean']:.3f} <= "
                       f"{mc['p_up_of_cells']['mean']:.3f}")
        lines.append(f"| {r['name']} | {r['cells']:,} x {r['modes']} | {spec} | {r['form']} | {_fmt_stats(r['p_low'])} | "
                     f"{_fmt_stats(r['p_up'])} | {r['q_yes']} / {r['q_no']} / {r['q_maybe']} | {ref} | "
                     f"{r['wall_seconds']:.1f} s ({stages}) | {r['peak_mb']:.0f} MB | "
                     f"{r['load_before']:.1f}-{r['load_after']:.1f} | {mc_txt} |")
    if data.get("quick"):
        return "\n".join(lines + ["", "Coarse variants (`--quick`): a check that every stage runs, not numbers to set "
                                   "beside the published ones (`arch.md` has those)."]) + "\n"
    lines += ["", "## Published numbers beside ours", "",
              "| benchmark | source and hardware | published | same instance as ours? | ours (time, peak) |", "|---|---|---|---|---|"]
    for r in rows:
        b = BY_NAME.get(r["name"])
        ours = (f"{r['wall_seconds']:.1f} s, {r['peak_mb']:.0f} MB" if r.get("status") in ("ok", "monte-carlo failed")
                else r.get("status", "-"))
        for p in (b.published if b else ()):
            same = "yes" if p["same_instance"] else "no"
            lines.append(f"| {r['name']} | {p['source']} | {p['numbers']} | {same}{': ' + p['note'] if p['note'] else ''} "
                         f"| {ours} |")
    notes = [f"* {r['name']}: {BY_NAME[r['name']].note}" for r in rows if r["name"] in BY_NAME and BY_NAME[r["name"]].note]
    if notes:
        lines += ["", "Notes:", ""] + notes
    return "\n".join(lines) + "\n"


def _machine() -> str:
    import platform
    return f"{platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}"


def _commit() -> str | None:
    try:
        head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--", "src", "benchmarks/arch"],
                               capture_output=True, text=True, check=True).stdout.strip()
        return head + (" + uncommitted changes in src/ or benchmarks/arch/" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="+", metavar="NAME", help="these benchmarks (see --list)")
    ap.add_argument("--quick", action="store_true", help="the coarse variants (results/arch_quick.*)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per benchmark (default 1800)")
    ap.add_argument("--mc-cells", type=int, default=40, help="Monte-Carlo cells per benchmark (default 40)")
    ap.add_argument("--mc-runs", type=int, default=200, help="Monte-Carlo runs per cell (default 200)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=RESULTS, help="results folder (default benchmarks/results)")
    ap.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    ap.add_argument("--no-warm", action="store_true",
                    help="skip the numba warm-up before the timed rows (compile time then lands in the first rows)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--child-out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child, args.quick, args.child_out, args.mc_cells, args.mc_runs, args.seed)
        return 0
    if args.list:
        for b in BENCHMARKS:
            flags = ("factored" if b.factored else "") + (" quick" if b.quick is not None else "")
            print(f"{b.name:28s} {b.file:26s} {flags.strip()}")
        return 0
    unknown = sorted(set(args.only or ()) - set(BY_NAME))
    if unknown:
        ap.error(f"--only: unknown benchmark(s) {', '.join(unknown)}; known: {', '.join(BY_NAME)}")
    chosen = [b for b in BENCHMARKS if (args.only is None or b.name in args.only) and (not args.quick or
                                                                                      b.quick is not None)]
    if not chosen:
        ap.error("no benchmark selected (--quick runs only the rows with a coarse variant: see --list)")
    name = "arch_quick" if args.quick else "arch"
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"{name}.json"
    old = json.loads(path.read_text()) if path.exists() else {"rows": []}
    load_start = os.getloadavg()[0]
    warm = None
    if not args.no_warm:  # numba's kernels compiled (or loaded) once, outside the timed rows
        t0 = time.perf_counter()
        rc = subprocess.run([sys.executable, "-m", "robust_imdp.warmup"], cwd=ROOT, capture_output=True).returncode
        warm = {"seconds": time.perf_counter() - t0, "exit": rc}
        print(f"[arch] warm-up (python -m robust_imdp.warmup): {warm['seconds']:.0f} s, exit {rc}", file=sys.stderr)
    rows = []
    for bench in chosen:
        print(f"[arch] {bench.name} ...", file=sys.stderr, flush=True)
        row = run_child(bench, args)
        rows.append(row)
        extra = (f"p_low mean {row['p_low']['mean']:.4f}, Q_yes {row['q_yes']}, {row['wall_seconds']:.1f} s, "
                 f"{row['peak_mb']:.0f} MB, Monte Carlo {'passed' if row['monte_carlo']['passed'] else 'FAILED'}"
                 if "p_low" in row else row.get("why", ""))
        print(f"[arch] {bench.name}: {row['status']}: {extra}", file=sys.stderr, flush=True)
        fresh = {r["name"]: r for r in rows}
        merged = [fresh.pop(r["name"], r) for r in old["rows"]] + list(fresh.values())
        order = {b.name: i for i, b in enumerate(BENCHMARKS)}
        merged.sort(key=lambda r: order.get(r["name"], len(order)))
        data = {"rows": merged, "quick": args.quick, "commit": _commit(), "machine": _machine(),
                "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load_start": load_start,
                "load_end": os.getloadavg()[0], "mc_cells": args.mc_cells, "mc_runs": args.mc_runs,
                "timeout": args.timeout, "warm_up": warm}
        _write_json(path, data)
        _write_text(args.out / f"{name}.md", render(data))
    bad = [r["name"] for r in rows if r["status"] in ("monte-carlo failed", "error")]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
