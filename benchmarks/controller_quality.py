"""What the controller achieves from every cell: mean empirical satisfaction against the true system, before and
after the nominal model ranks modes of equal robust value, against the best strategy for the known dynamics.

    python benchmarks/controller_quality.py [--only NAME ...] [--runs N] [--seed S]
    python benchmarks/controller_quality.py --render      # the markdown table again from the JSON record

Problems: the newcomer problems of ``examples/newcomer`` (data from their generators, as their README says:
``robot2d_16``, ``robot2d_32``, ``unicycle3d_16``, ``di4d_8``) and ``robot2d_ens``, a 2-D robot through the
Python API on X = [0, 5]^2 with modes east / north / stay, an obstacle in the middle and the goal in a corner
(``advice_cost.dense_robot`` at cell 0.25: 400 cells, Gaussian noise sigma 0.08); and ``robot2d_16_safety``, the
16 x 16 robot's abstraction under the safety reading (``G !obstacle`` within 25 steps: the controller minimises the
probability of touching the obstacle or leaving X, and the nominal model ranks its ties the mirrored way).

Per problem, in this process:

1. the learned run, ``synthesize_from_data`` (no advice, no margins; abstraction cached in the work folder), and
   its strategy re-chosen on the same abstraction three ways (``synthesis.core.synthesize``): *before* (no
   nominal model: lower value, then optimistic value), *centre* (a nominal model of the cells' centres only) and
   *after* (the run's: the nominal model of ``pipeline.nominal_stage``, several points per cell);
2. the known-dynamics reference: the same grid, regions, noise and formula with the true dynamics as the known
   part (``rkhs_bound = 0``: ``f = [...]`` expressions), its strategy chosen both ways; the reference is the
   better of the two (the best strategy for the known dynamics this library computes);
3. ``validate`` (``--runs`` runs from uniform states in every cell, seeded, step cap 200) of each strategy
   against the true system: the mean over all cells of the empirical satisfaction, and whether the runs are
   inside ``[p_low, p_up]`` (cells flagged against what chance allows).

Checked and recorded: no cell leaves Q_yes (``yes_lost``), ``p_low`` of the Q_yes cells unchanged or higher
(``min_plow_change_yes``; the bounds of every other cell are the chosen strategy's own, and may move either way),
how many (cell, DFA state) entries of the strategy changed, and ``after / reference`` (target >= 0.8).

Writes ``benchmarks/results/controller_quality.json`` and ``.md`` after every problem (``--only`` replaces those
rows, keeps the others), beside the old files and renamed into place.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from advice_cost import dense_robot, problems  # noqa: E402
from reference import merged_rows, results_record  # noqa: E402

NAME = "controller_quality"
NAMES = ("robot2d_16", "robot2d_32", "unicycle3d_16", "di4d_8", "robot2d_ens", "robot2d_16_safety")
#: The issue's target: mean empirical satisfaction at least this share of the known-dynamics reference's.
TARGET = 0.8
#: Runs per cell by problem (the 3-D and 4-D problems have 4,096 cells).
RUNS = {"unicycle3d_16": 20, "di4d_8": 20}


# --------------------------------------------------------------------------- the true systems
def _truncated(rng, shape, sigma=0.01, bound=0.02):
    out = rng.normal(0, sigma, shape)
    bad = np.abs(out) > bound
    while bad.any():
        out[bad] = rng.normal(0, sigma, int(bad.sum()))
        bad = np.abs(out) > bound
    return out


class Robot2D:
    """``examples/newcomer/robot2d_system.py``: steps of 0.3, drift (0.05 sin y, -0.04 cos x)."""

    mode_names = ("east", "west", "north", "south")
    steps = np.array([[0.3, 0.0], [-0.3, 0.0], [0.0, 0.3], [0.0, -0.3]])
    known = {m: [f"x1 + {float(s[0])!r} + 0.05*sin(x2)", f"x2 + {float(s[1])!r} - 0.04*cos(x1)"] for m, s in zip(mode_names, steps)}

    def step(self, x, modes, rng):
        drift = np.stack([0.05 * np.sin(x[:, 1]), -0.04 * np.cos(x[:, 0])], axis=1)
        return x + self.steps[modes] + drift + _truncated(rng, x.shape)


class Unicycle3D:
    """``examples/newcomer/unicycle3d_data.py`` (plain headings): speed 0.2, turn rates 0.3 / 0 / -0.3."""

    mode_names = ("left", "straight", "right")
    omega = np.array([0.3, 0.0, -0.3])
    known = {m: ["x1 + 0.2*cos(x3)", "x2 + 0.2*sin(x3)", f"x3 + {float(w)!r}"] for m, w in zip(mode_names, omega)}

    def step(self, x, modes, rng):
        d = np.column_stack([0.2 * np.cos(x[:, 2]), 0.2 * np.sin(x[:, 2]), self.omega[modes]])
        return x + d + _truncated(rng, x.shape)


class DoubleIntegrators4D:
    """``examples/newcomer/di4d_data.py``: two double integrators, dt 0.25, accelerations +-1, drag 0.1 sin v."""

    mode_names = ("pp", "pm", "mp", "mm")
    acc = np.array([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])
    known = {m: ["x1 + 0.25*x2", f"x2 + {float(0.25 * a[0])!r} - 0.1*sin(x2)", "x3 + 0.25*x4",
                 f"x4 + {float(0.25 * a[1])!r} - 0.1*sin(x4)"] for m, a in zip(mode_names, acc)}

    def step(self, x, modes, rng):
        a = self.acc[modes]
        p1, v1, p2, v2 = x.T
        nxt = np.column_stack([p1 + 0.25 * v1, v1 + 0.25 * a[:, 0] - 0.1 * np.sin(v1),
                               p2 + 0.25 * v2, v2 + 0.25 * a[:, 1] - 0.1 * np.sin(v2)])
        return nxt + _truncated(rng, x.shape)


class RobotENS:
    """``advice_cost.dense_robot``: steps east 0.3 / north 0.3 / stay, drift (0.1 sin y, -0.08 cos x), Gaussian
    noise sigma 0.08."""

    mode_names = ("east", "north", "stay")
    steps = np.array([[0.3, 0.0], [0.0, 0.3], [0.0, 0.0]])
    known = {m: [f"x1 + {float(s[0])!r} + 0.1*sin(x2)", f"x2 + {float(s[1])!r} - 0.08*cos(x1)"] for m, s in zip(mode_names, steps)}

    def step(self, x, modes, rng):
        drift = np.stack([0.1 * np.sin(x[:, 1]), -0.08 * np.cos(x[:, 0])], axis=1)
        return x + self.steps[modes] + drift + rng.normal(0, 0.08, x.shape)


SYSTEMS = {"robot2d_16": Robot2D, "robot2d_32": Robot2D, "unicycle3d_16": Unicycle3D, "di4d_8": DoubleIntegrators4D,
           "robot2d_ens": RobotENS, "robot2d_16_safety": Robot2D}
#: The safety variant: formula and horizon (the cache reuses the 16 x 16 robot's abstraction).
SAFETY = {"formula": "G !obstacle", "horizon": 25, "semantics": "safety"}


# --------------------------------------------------------------------------- one problem
def _known(problem, system):
    """The problem with the true dynamics as the known part (no data, rkhs_bound 0)."""
    from robust_imdp.models.known import KnownDynamics

    maps = tuple(KnownDynamics(system.known[m], name=f"mode {m!r}") for m in problem.mode_names)
    return problem.replace(data=None, rkhs_bound=0.0, maps=maps, misspecification=0.0)


def _resolve(res, nominal):
    """``res``'s strategy re-chosen on its abstraction (``nominal``: None or a model): a Result of the same run."""
    from robust_imdp.abstraction.factored import abstraction_model
    from robust_imdp.synthesis.core import synthesize

    P, pr = res.partition, res.problem
    syn = synthesize(abstraction_model(res.abstraction), P.labels, P.atoms, res.dfa, threshold=pr.threshold,
                     horizon=pr.horizon, outside_state=P.outside_state, semantics=pr.semantics, nominal=nominal)
    return dataclasses.replace(res, synthesis=syn, class_names=np.asarray(syn.classes).astype(str))


def _quality(res, system, runs, seed) -> dict:
    from robust_imdp.validate import validate

    rep = validate(res, system, n_per_cell=runs, rng=seed)
    syn = res.synthesis
    return {"mean_empirical": float(rep.empirical.mean()), "flagged": int(len(rep.outside)),
            "allowed": int(rep.allowed_outside), "contained": bool(rep.passed),
            "classes": {k: int(v) for k, v in syn.class_counts().items()}, "tie_keys": list(syn.tie_keys),
            "mean_p_low": float(np.mean(syn.p_low)), "mean_p_up": float(np.mean(syn.p_up))}


def _changes(before, after) -> dict:
    b, a = before.synthesis, after.synthesis
    yes_b, yes_a = np.asarray(b.classes) == "yes", np.asarray(a.classes) == "yes"
    dp = np.asarray(a.p_low) - np.asarray(b.p_low)
    return {"yes_lost": int(np.count_nonzero(yes_b & ~yes_a)), "yes_gained": int(np.count_nonzero(~yes_b & yes_a)),
            "min_plow_change_yes": float(dp[yes_b].min()) if yes_b.any() else 0.0,
            "strategy_entries_changed": int(np.count_nonzero(np.asarray(a.strategy) != np.asarray(b.strategy))),
            "initial_modes_changed": int(np.count_nonzero(_first(a)[np.arange(b.n_cells), b.initial_dfa_state]
                                                          != _first(b)[np.arange(b.n_cells), b.initial_dfa_state]))}


def _first(syn):
    """The strategy's first decision per (cell, DFA state): a k-step strategy's time 0 layer."""
    st = np.asarray(syn.strategy)
    return st[0] if st.ndim == 3 else st


def measure(name: str, make, work: Path, runs: int, seed: int) -> dict:
    from robust_imdp.pipeline.nominal_stage import nominal_dynamics, nominal_model
    from robust_imdp.pipeline.run import synthesize_from_data

    system = SYSTEMS[name]()
    problem = make()
    row = {"problem": name, "runs_per_cell": runs, "seed": seed}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        cache = work / "cache" / name.replace("_safety", "")
        res = synthesize_from_data(problem, progress=False, abstraction_cache=cache, advice=False, margins=False)
        row["run_s"] = time.perf_counter() - t0
        row["nominal_s"] = float(res.timings.get("nominal", 0.0))
        row["cells"] = int(res.partition.n_cells)
        dyn = nominal_dynamics(problem)
        variants = {"before": _resolve(res, None),
                    "centre": _resolve(res, nominal_model(problem, res.partition, dyn, per_axis=1)),
                    "after": res}
        for k, r in variants.items():
            row[k] = _quality(r, system, runs, seed)
        row["changes"] = _changes(variants["before"], variants["after"])
        known = _known(problem, system)
        t0 = time.perf_counter()
        kres = synthesize_from_data(known, progress=False, abstraction_cache=cache.with_name(f"{cache.name}_known"),
                                    advice=False, margins=False)
        row["known_s"] = time.perf_counter() - t0
        row["known_before"] = _quality(_resolve(kres, None), system, runs, seed)
        row["known_after"] = _quality(kres, system, runs, seed)
    ref = max(row["known_before"]["mean_empirical"], row["known_after"]["mean_empirical"])
    row["reference"] = ref
    row["ratio_before"] = row["before"]["mean_empirical"] / ref if ref > 0 else None
    row["ratio_after"] = row["after"]["mean_empirical"] / ref if ref > 0 else None
    if name == "robot2d_ens":  # the state just left of the obstacle
        x = np.array([1.0, 2.0])
        for k in ("before", "after"):
            c = variants[k].controller()
            c.reset(x)
            row[f"act_1_2_{k}"] = c.act(x)
    row["load"] = os.getloadavg()[0]
    return row


# --------------------------------------------------------------------------- output
def _md(data: dict) -> list[str]:
    lines = [
        "# Controller quality (`benchmarks/controller_quality.py`)", "",
        "Mean empirical satisfaction from all cells (runs from uniform states in every cell, true system, step cap "
        "200) under the run's controller: *before* = modes of equal robust lower value ranked by their optimistic "
        "value; *centre* = ranked by a nominal model of the cells' centres, then the optimistic value; *after* = "
        "ranked by the run's nominal model (the fitted dynamics at several points per cell and the noise), then the "
        "optimistic value (README, \"What the controller does\"). *reference* = the best of the two strategies of "
        "the known-dynamics abstraction (true f as the known part, rkhs_bound 0). Target: after / reference >= "
        f"{TARGET}, no Q_yes cell lost, p_low of Q_yes cells not lower, runs contained in [p_low, p_up].", "",
        f"{data.get('date', '')}; commit {data.get('commit', '')}; load at the end {data.get('load', '')}.", "",
        "| problem | cells | before | centre | after | reference (known: before / after) | after / ref | "
        "Q_yes before -> after (lost) | min p_low change on Q_yes | strategy entries changed | flagged / allowed "
        "(after) | nominal s / run s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in data["rows"]:
        c = r["changes"]
        lines.append(
            f"| {r['problem']} | {r['cells']} | {r['before']['mean_empirical']:.3f} | "
            f"{r['centre']['mean_empirical']:.3f} | **{r['after']['mean_empirical']:.3f}** | {r['reference']:.3f} "
            f"({r['known_before']['mean_empirical']:.3f} / {r['known_after']['mean_empirical']:.3f}) | "
            f"{r['ratio_after']:.2f} (before {r['ratio_before']:.2f}) | {r['before']['classes']['yes']} -> "
            f"{r['after']['classes']['yes']} ({c['yes_lost']}) | {c['min_plow_change_yes']:+.2g} | "
            f"{c['strategy_entries_changed']} ({c['initial_modes_changed']} initial) | "
            f"{r['after']['flagged']} / {r['after']['allowed']} | {r['nominal_s']:.1f} / {r['run_s']:.0f} |")
    ens = [r for r in data["rows"] if "act_1_2_after" in r]
    for r in ens:
        lines += ["", f"`{r['problem']}`: at (1.0, 2.0), just left of the obstacle, the controller says "
                      f"`{r['act_1_2_before']}` before and `{r['act_1_2_after']}` after."]
    per_cell = ", ".join(f"{r['problem']} {r['runs_per_cell']}" for r in data["rows"])
    lines += ["", f"Runs per cell: {per_cell}; seeded (`--seed`)."]
    return lines


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def write(data: dict) -> None:
    out = HERE / "results"
    out.mkdir(exist_ok=True)
    _write_atomic(out / f"{NAME}.json", json.dumps(data, indent=1) + "\n")
    _write_atomic(out / f"{NAME}.md", "\n".join(_md(data)) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="+", choices=NAMES)
    ap.add_argument("--runs", type=int, default=None, help="runs per cell (default 50; 20 for the 3-D and 4-D)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--render", action="store_true")
    args = ap.parse_args(argv)
    path = HERE / "results" / f"{NAME}.json"
    old = json.loads(path.read_text()) if path.exists() else {"rows": []}
    if args.render:
        write(old)
        return 0
    names = args.only or NAMES
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="controller_quality-"))
    made = problems(work, sorted({"robot2d_16" if n == "robot2d_16_safety" else n for n in names} - {"robot2d_ens"}))
    made["robot2d_ens"] = lambda: dense_robot(cell=0.25)
    made["robot2d_16_safety"] = lambda: made["robot2d_16"]().replace(**SAFETY)
    rows = []
    for n in names:
        runs = args.runs if args.runs is not None else RUNS.get(n, 50)
        print(f"[controller_quality] {n} ...", file=sys.stderr, flush=True)
        rows.append(measure(n, made[n], work, runs, args.seed))
        r = rows[-1]
        print(f"[controller_quality] {n}: before {r['before']['mean_empirical']:.3f}, after "
              f"{r['after']['mean_empirical']:.3f}, reference {r['reference']:.3f}", file=sys.stderr, flush=True)
        write(results_record(merged_rows(old.get("rows", []), rows, "problem")))
    bad = [r["problem"] for r in rows if r["changes"]["yes_lost"] or r["changes"]["min_plow_change_yes"] < 0
           or not r["after"]["contained"]]
    if bad:
        print(f"[controller_quality] FAILED checks (Q_yes lost, p_low lower or runs outside): {bad}", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
