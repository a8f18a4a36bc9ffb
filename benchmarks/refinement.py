"""Adaptive refinement of undecided cells (issue 13): area shares against cell counts, round by round.

Targets (each refined run end to end -- check, bound, abstract, solve, refine -- in at most 2 min on
2 cores, at most 2,048 cells):

* **four_mode_nonlinear_two_goals** (``G !o & F d1 & F d2``), from the 0.125 grid (1,024 cells):
  the Q_yes AREA share must reach at least that of the uniform 0.0625 grid (4,096 cells) under the
  same bounds (our pipeline at ``cell_size = 0.0625``); aim 0.70; the known-dynamics share of the
  uniform 0.0625 grid is the yardstick (issue: 0.746).
* **three_mode_linear** (``G !obs & F des``): the Q_? area share must be at most half of the
  unrefined grid's.

Also measured: the known-dynamics shares (exact image boxes of the true system,
``casestudies.known_dynamics_cell_bounds``, through our own abstraction and solver) on the uniform
grids and on the refined partition, and the Monte-Carlo containment of every refined result
(``validate``: the true system under the refined controller from random states of every cell).

Writes ``benchmarks/results/refinement.json`` and ``.md``, ``refinement.png`` (area shares against
cells, round by round, with the uniform grids) and ``refinement_classes_<problem>.png`` (the refined
cells coloured by class). The uniform 0.0625 run is cached under ``--cache`` (default
``$TMPDIR/robust_imdp_bench_refinement``); the refined runs are never cached (they are what is timed).

Usage: ``python benchmarks/refinement.py [--only STEM ...] [--no-validate] [--save-abstractions DIR]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from robust_imdp.synthesis import refine as _refine_module
from robust_imdp.abstraction.rows import abstract
from robust_imdp.casestudies.systems import known_dynamics_cell_bounds, true_system
from robust_imdp.spec.dfa import ltlf_to_dfa
from robust_imdp.models.geometry import Box, Partition, Region
from robust_imdp.io.files import load_problem, save_result
from robust_imdp.pipeline.run import synthesize_from_data
from robust_imdp.synthesis.refine import class_shares
from robust_imdp.synthesis.core import synthesize
from robust_imdp.validate import validate

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
PROBLEMS = ROOT / "examples" / "problems"
OUT = HERE / "results"

#: problem stem -> (case study, [refine] table, fine uniform cell size, target)
CASES = {
    "four_mode_nonlinear_two_goals": ("four_mode_nonlinear", {"max_cells": 2048, "max_rounds": 6}, 0.0625, "yes"),
    "three_mode_linear": ("three_mode_linear", {"max_cells": 2048, "max_rounds": 6}, 0.0625, "maybe"),
}
TIME_LIMIT = 120.0


def _partition(problem, cell_size=None) -> Partition:
    regions = [Region(k, [Box(lo, up) for lo, up in v]) for k, v in problem.regions.items()]
    return Partition(Box(problem.space_lower, problem.space_upper),
                     problem.cell_size if cell_size is None else cell_size, regions)


def known_shares(problem, case: str, partition) -> dict:
    """Area shares with the exact image boxes of the true system on ``partition`` (any cells)."""
    cb = known_dynamics_cell_bounds(case, partition)
    ab = abstract(partition, cb, problem.noise, None, eta=problem.eta, eps_rule=problem.eps_rule,
                  combine=problem.combine)
    syn = synthesize(ab.imdp, partition.labels, partition.atoms, ltlf_to_dfa(problem.formula),
                     threshold=problem.threshold, horizon=problem.horizon, outside_state=partition.outside_state)
    vol = np.prod(partition.cells_upper - partition.cells_lower, axis=1)
    counts, shares = class_shares(syn.classes, vol)
    return {"n_cells": int(partition.n_cells), "counts": counts, "shares": shares}


def _shares_of(result) -> dict:
    P = result.partition
    vol = np.prod(P.cells_upper - P.cells_lower, axis=1)
    counts, shares = class_shares(result.class_names, vol)
    return {"n_cells": int(P.n_cells), "counts": counts, "shares": shares}


def _solver_warnings(result) -> list:
    return [{"name": r.name, "iterations": r.iterations, "max_gap": r.max_gap}
            for r in result.synthesis.runs if not r.converged]


def run_one(stem: str, cache: Path, do_validate: bool, save_dir: Path | None) -> tuple[dict, object]:
    case, table, fine, target = CASES[stem]
    problem = load_problem(PROBLEMS / f"{stem}.toml")
    row = {"problem": f"examples/problems/{stem}.toml", "formula": problem.formula,
           "threshold": float(problem.threshold), "refine": table, "target": target}
    # -- known dynamics on the uniform grids (the yardstick)
    coarse, finer = _partition(problem), _partition(problem, [fine] * len(problem.cell_size))
    row["known_uniform"] = {"coarse": known_shares(problem, case, coarse), "fine": known_shares(problem, case, finer)}
    # -- our bounds on the uniform fine grid (cached)
    t0 = time.perf_counter()
    uni = synthesize_from_data(problem.replace(cell_size=np.full(len(problem.cell_size), fine)), progress=False,
                               abstraction_cache=cache / stem)
    row["uniform_fine"] = {**_shares_of(uni), "seconds": time.perf_counter() - t0, "from_cache": uni.from_cache,
                           "cell_size": fine}
    # -- the refined run, end to end, timed (no cache)
    saved = []
    if save_dir is not None:  # keep every round's abstraction (e.g. for solver reproducers)
        original = _refine_module.assemble_abstraction

        def keeping(partition, chunks):
            ab = original(partition, chunks)
            save_dir.mkdir(parents=True, exist_ok=True)
            ab.save(save_dir / f"{stem}-{len(saved)}.npz")
            saved.append(partition.n_cells)
            return ab

        _refine_module.assemble_abstraction = keeping
    try:
        t0 = time.perf_counter()
        res = synthesize_from_data(problem.replace(refine=table), progress=True)
        wall = time.perf_counter() - t0
    finally:
        if save_dir is not None:
            _refine_module.assemble_abstraction = original
    info = res.diagnostics["refinement"]
    row["refined"] = {**_shares_of(res), "wall_seconds": wall, "stage_seconds": dict(res.timings),
                      "stopped": info["stopped"], "rounds": info["rounds"], "solver_not_converged":
                      _solver_warnings(res), "max_depth": int(res.partition.depth.max())}
    row["unrefined"] = {"n_cells": info["rounds"][0]["n_cells"], "counts": info["rounds"][0]["counts"],
                        "shares": info["rounds"][0]["shares"]}
    row["known_refined"] = known_shares(problem, case, res.partition)
    # -- the targets
    un, ref, uf = row["unrefined"]["shares"], row["refined"]["shares"], row["uniform_fine"]["shares"]
    if target == "yes":
        met = ref["yes"] >= uf["yes"] and res.partition.n_cells <= table["max_cells"]
        row["target_text"] = (f"Q_yes area {ref['yes']:.4f} with {res.partition.n_cells} cells >= uniform "
                              f"{fine} grid's {uf['yes']:.4f} with {row['uniform_fine']['n_cells']} cells")
    else:
        met = ref["maybe"] <= 0.5 * un["maybe"] and res.partition.n_cells <= table["max_cells"]
        row["target_text"] = (f"Q_? area {ref['maybe']:.4f} with {res.partition.n_cells} cells <= half of the "
                              f"unrefined {un['maybe']:.4f}")
    row["target_met"] = bool(met)
    row["time_met"] = bool(wall <= TIME_LIMIT)
    # -- Monte-Carlo containment on the refined cells
    if do_validate:
        t0 = time.perf_counter()
        rep = validate(res, true_system(case), n_per_cell=40, max_steps=120, rng=0, confidence=0.999)
        row["validation"] = {"cells": int(len(rep.cells)), "n_per_cell": rep.n_per_cell, "outside": int(len(rep.outside)),
                             "expected_outside_by_chance": rep.expected_outside,
                             "containment_rate": rep.containment_rate, "seconds": time.perf_counter() - t0}
    if saved:
        row["saved_abstractions"] = {"dir": str(save_dir), "n_cells": saved}
    return row, res


# --------------------------------------------------------------------------- outputs
def plot(rows: dict, results: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from robust_imdp.plotting import CLASS_COLOURS, plot_classes

    fig, axes = plt.subplots(2, len(rows), figsize=(5.6 * len(rows), 7.4), constrained_layout=True, squeeze=False,
                             gridspec_kw={"height_ratios": [3, 2]})
    floor = 1e-5  # a zero share is drawn here on the log axis
    for ax, (stem, row) in zip(axes[1], rows.items()):  # the undecided share on a log scale
        rounds = row["refined"]["rounds"]
        ax.plot([r["n_cells"] for r in rounds], [max(r["shares"]["maybe"], floor) for r in rounds], "-o",
                color=CLASS_COLOURS["maybe"], ms=4, label="Q_?, refined (round by round)")
        ax.plot([row["unrefined"]["n_cells"], row["uniform_fine"]["n_cells"]],
                [max(row["unrefined"]["shares"]["maybe"], floor), max(row["uniform_fine"]["shares"]["maybe"], floor)],
                ls=":", marker="s", mfc="white", color=CLASS_COLOURS["maybe"], label="Q_?, uniform grid, our bounds")
        ax.axhline(0.5 * row["unrefined"]["shares"]["maybe"], color="grey", lw=0.8, ls="--",
                   label="half of the unrefined Q_?")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_ylim(floor / 2, 1)
        ax.set_xlabel("cells")
        ax.set_ylabel(f"Q_? share of the area (0 drawn at {floor:g})")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6.5, loc="upper right")
    for ax, (stem, row) in zip(axes[0], rows.items()):
        rounds = row["refined"]["rounds"]
        cells = [r["n_cells"] for r in rounds]
        for c, name in (("yes", "Q_yes"), ("maybe", "Q_?"), ("no", "Q_no")):
            ax.plot(cells, [r["shares"][c] for r in rounds], "-o", color=CLASS_COLOURS[c], ms=4,
                    label=f"{name}, refined (round by round)")
            for key, marker, lab in (("uniform_fine", "s", "uniform grid, our bounds"),):
                pts = [(row["unrefined"]["n_cells"], row["unrefined"]["shares"][c]),
                       (row[key]["n_cells"], row[key]["shares"][c])]
                ax.plot(*zip(*pts), ls=":", marker=marker, color=CLASS_COLOURS[c], mfc="white", ms=6,
                        label=f"{name}, {lab}" if c == "yes" else None)
            k = row["known_uniform"]
            ax.plot([k["coarse"]["n_cells"], k["fine"]["n_cells"]], [k["coarse"]["shares"][c], k["fine"]["shares"][c]],
                    ls="none", marker="^", color=CLASS_COLOURS[c], mfc="none", ms=7,
                    label="uniform grid, known dynamics" if c == "yes" else None)
        ax.set_xscale("log", base=2)
        ax.set_ylabel("share of the area of X")
        ax.set_ylim(0, 1)
        ax.set_title(f"{stem}\n{row['formula']!r}", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6.5, loc="center right")
    fig.savefig(OUT / "refinement.png", dpi=130)
    plt.close(fig)
    for stem, res in results.items():
        fig, ax = plt.subplots(figsize=(5.4, 5.2), constrained_layout=True)
        plot_classes(res, ax, title=f"{stem}: {res.partition.n_cells} refined cells")
        fig.savefig(OUT / f"refinement_classes_{stem}.png", dpi=130)
        plt.close(fig)


def markdown(doc: dict) -> str:
    m = doc["machine"]
    lines = ["# Adaptive refinement (`benchmarks/refinement.py`, issue 13)", "",
             f"{m['note']}; commit {m['commit']}; {m['date']}; python {m['python']}, {m['platform']}.", "",
             "Refined runs: `synthesize_from_data` on the shipped problem file plus the `[refine]` table shown, "
             "end to end with no cache (check, bound, abstract, solve, refinement rounds), timed on the wall clock. "
             "*Uniform*: our pipeline on the uniform finer grid (same data, same bounds). *Known*: exact image boxes "
             "of the true system through our abstraction and solver. Shares are fractions of the AREA of X.", "",
             "| problem | target | met | refined cells | Q_yes / Q_no / Q_? area | unrefined (cells, area) | uniform fine "
             "(cells, area) | known, uniform fine | known, refined cells | wall s (limit 120) | stopped | containment |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    fmt = lambda s: f"{s['yes']:.4f} / {s['no']:.4f} / {s['maybe']:.4f}"  # noqa: E731
    for stem, r in doc["problems"].items():
        v = r.get("validation")
        cont = f"{v['outside']} of {v['cells']} cells outside (chance <= {v['expected_outside_by_chance']:.1f})" \
            if v else "not run"
        lines.append(
            f"| {stem} | {r['target_text']} | {'yes' if r['target_met'] else 'NO'} | {r['refined']['n_cells']} | "
            f"{fmt(r['refined']['shares'])} | {r['unrefined']['n_cells']}: {fmt(r['unrefined']['shares'])} | "
            f"{r['uniform_fine']['n_cells']}: {fmt(r['uniform_fine']['shares'])} | "
            f"{fmt(r['known_uniform']['fine']['shares'])} | {fmt(r['known_refined']['shares'])} | "
            f"{r['refined']['wall_seconds']:.1f} ({'ok' if r['time_met'] else 'OVER'}) | {r['refined']['stopped']} | "
            f"{cont} |")
    lines += ["", "## Round by round", "",
              "| problem | round | cells | split | rows rebuilt | Q_yes | Q_no | Q_? | bound s | abstract s | solve s | "
              "elapsed s |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for stem, r in doc["problems"].items():
        for rd in r["refined"]["rounds"]:
            s, t = rd["shares"], rd["seconds"]
            lines.append(f"| {stem} | {rd['round']} | {rd['n_cells']} | {rd['n_split']} | {rd['rows_rebuilt']} | "
                         f"{s['yes']:.4f} | {s['no']:.4f} | {s['maybe']:.4f} | {t['bound']:.1f} | {t['abstract']:.2f} | "
                         f"{t['solve']:.1f} | {rd['elapsed']:.1f} |")
    lines += ["", "Stage times of the refined runs (s): " + "; ".join(
        f"{stem}: " + ", ".join(f"{k} {v:.1f}" for k, v in r["refined"]["stage_seconds"].items())
        for stem, r in doc["problems"].items())]
    bad = {stem: r["refined"]["solver_not_converged"] for stem, r in doc["problems"].items()
           if r["refined"]["solver_not_converged"]}
    if bad:
        lines += ["", "Solver runs of the final solve that did not converge (sound but loose brackets): "
                  + json.dumps(bad)]
    lines += ["", "![area shares against cells](refinement.png)", ""]
    return "\n".join(lines)


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="*", choices=sorted(CASES))
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "robust_imdp_bench_refinement")
    ap.add_argument("--no-validate", action="store_true")
    ap.add_argument("--save-abstractions", type=Path, default=None)
    ap.add_argument("--replot", action="store_true", help="redraw refinement.png from refinement.json only")
    args = ap.parse_args(argv)
    if args.replot:
        plot(json.loads((OUT / "refinement.json").read_text())["problems"], {})
        return 0
    stems = args.only or list(CASES)
    rows, results = {}, {}
    for stem in stems:
        print(f"== {stem}", file=sys.stderr, flush=True)
        rows[stem], results[stem] = run_one(stem, args.cache, not args.no_validate, args.save_abstractions)
        print(f"   {rows[stem]['target_text']}: {'met' if rows[stem]['target_met'] else 'NOT met'}; "
              f"{rows[stem]['refined']['wall_seconds']:.1f} s", file=sys.stderr, flush=True)
    doc = {"machine": {"python": platform.python_version(), "platform": platform.platform(), "cores": os.cpu_count(),
                       "commit": _commit(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                       "note": os.environ.get("BENCH_NOTE", "2-core machine shared with other jobs")},
           "problems": rows}
    OUT.mkdir(parents=True, exist_ok=True)
    name = "refinement" if args.only is None else "refinement_" + "_".join(stems)
    (OUT / f"{name}.json").write_text(json.dumps(doc, indent=1))
    (OUT / f"{name}.md").write_text(markdown(doc))
    plot(rows, results)
    for stem, res in results.items():
        if os.environ.get("BENCH_SAVE_RESULTS"):
            save_result(res, Path(os.environ["BENCH_SAVE_RESULTS"]) / stem)
    return 0 if all(r["target_met"] and r["time_met"] for r in rows.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
