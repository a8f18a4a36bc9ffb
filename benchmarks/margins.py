"""Assumption margins (docs/margins.md): what they cost, how tight they are, and whether they warn where it matters.

Three measurements, written to ``benchmarks/results/margins.json`` and ``margins.md``:

(a) **Cost** on the three case studies (``examples/problems/*.toml``): a plain run (``margins=False``) and a
    run with margins (the default), each with a fresh cache, in this process, alternating which goes first
    (``--reps``); the ratio of the wall times (target <= 2: margins cost at most one extra run) and the
    margins stage's own seconds (its abstractions and evaluations). Every run uses the defaults of
    ``robust-imdp run`` (advice "auto").
(b) **Tightness** of the re-evaluated boxes (the weights of B at beta B) against a fresh bound stage at
    beta B, on ``three_mode_linear`` at beta = 2: the median / max ratio of box widths, and the Q_yes cells
    the run's controller keeps at 2 B with either set of boxes (the margin's conservatism).
(c) **Warning where it matters** (the benchmark family of ``benchmarks/family.py``: unknown parts of exactly
    known RKHS norm N): run with ``rkhs_bound = N / 2`` (the assumption is false; it must still be above the
    data's certified minimum norm, else the configuration is reported and skipped), simulate the true
    system under the run's controller (``validate``, Wilson confidence 0.999) and check that every cell the
    Monte Carlo finds outside its bounds ``[p_low, p_up]`` (and every cell whose class the simulation
    contradicts) has a margin < 2 there: a margin >= 2 claims the class at 2 B = N, the true norm. Cells
    flagged by chance alone are allowed (``expected_outside``). The same with ``rkhs_bound = N`` for
    contrast (every cell's bounds hold).

Usage: ``python benchmarks/margins.py [--reps N] [--only cost tightness family] [--seeds 0 1]``
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = HERE / "results"
sys.path.insert(0, str(HERE))

CASES = ("three_mode_linear", "four_mode_nonlinear", "four_mode_nonlinear_two_goals")
COST_TARGET = 2.0
#: Data-starved configurations of the family (2-D, 256 cells): the data must leave the norm open below N / 2,
#: so few points (0.1 or 0.25 per cell and mode: 26 or 64) and large noise (0.4 or 1 cell half-width). With
#: the family's default densities (2 per cell) the certified minimum norm is 0.8-0.98 N and B = N / 2 is
#: refuted by the data (measured: every configuration of an earlier version of this list).
FAMILY_CONFIGS = tuple({"dim": 2, "ratio": r, "noise": nz, "density": dn}
                       for r, nz, dn in ((0.25, 0.4, 0.1), (0.125, 1.0, 0.1), (0.25, 1.0, 0.1), (0.25, 0.4, 0.25),
                                         (0.25, 1.0, 0.25)))
N_PER_CELL = 400
MAX_STEPS = 60
CONFIDENCE = 0.999


def _git_commit() -> str:
    import subprocess

    if os.environ.get("MARGINS_COMMIT"):  # run from a snapshot of a commit (no .git there)
        return os.environ["MARGINS_COMMIT"] + " (snapshot)"
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except Exception:  # noqa: BLE001 - a report without the commit is still a report
        return "unknown"


def _load() -> str:
    try:
        return f"{os.getloadavg()[0]:.1f}"
    except OSError:
        return "n/a"


# --------------------------------------------------------------------------- (a) cost
def _run(problem, margins: bool, cache) -> tuple:
    from robust_imdp.pipeline.run import synthesize_from_data

    t0, c0 = time.perf_counter(), time.process_time()
    res = synthesize_from_data(problem, progress=False, abstraction_cache=cache, margins=margins)
    return res, time.perf_counter() - t0, time.process_time() - c0


def cost(reps: int) -> list:
    from robust_imdp.io.files import load_problem

    rows = []
    for name in CASES:
        problem = load_problem(ROOT / "examples" / "problems" / f"{name}.toml")
        walls = {False: [], True: []}
        cpus = {False: [], True: []}
        last = {}
        for rep in range(reps):
            for margins in ((False, True) if rep % 2 == 0 else (True, False)):
                with tempfile.TemporaryDirectory(prefix="margins-cost-") as tmp:
                    res, wall, cpu = _run(problem, margins, Path(tmp) / "cache")
                walls[margins].append(wall)
                cpus[margins].append(cpu)
                last[margins] = res
        on, off = last[True], last[False]
        doc = on.margins
        row = {"problem": name, "cells": on.n_cells, "q_yes": on.counts["yes"], "q_no": on.counts["no"],
               "wall_off_s": walls[False], "wall_on_s": walls[True],
               "ratio": float(np.median(walls[True]) / np.median(walls[False])),
               "cpu_off_s": cpus[False], "cpu_on_s": cpus[True],
               "cpu_ratio": float(np.median(cpus[True]) / np.median(cpus[False])),
               "bound_off_s": float(off.timings.get("bound", 0.0)), "bound_on_s": float(on.timings.get("bound", 0.0)),
               "margins_stage_s": float(on.timings.get("margins", 0.0)), "solved": doc["solved"],
               "scales": doc["scales"], "kept_yes": doc["kept_yes"], "kept_no": doc["kept_no"],
               "same_classes": bool(np.array_equal(on.class_names, off.class_names)), "load": _load()}
        print(f"cost {name}: off {row['wall_off_s']} s, on {row['wall_on_s']} s, ratio {row['ratio']:.3f}, "
              f"CPU ratio {row['cpu_ratio']:.3f}, "
              f"margins stage {row['margins_stage_s']:.2f} s; kept_yes {doc['kept_yes']}", flush=True)
        rows.append(row)
    return rows


# --------------------------------------------------------------------------- (b) tightness
def tightness(scale: float = 2.0) -> dict:
    """Re-evaluated boxes at ``scale`` B against a fresh bound stage at ``scale`` B (three_mode_linear)."""
    from robust_imdp.abstraction.cell_bounds import CellBounds
    from robust_imdp.io.files import load_problem
    from robust_imdp.pipeline.cache import _load_bounds, _load_npz, bounds_key
    from robust_imdp.pipeline.run import _chunked_abstract, synthesize_from_data
    from robust_imdp.pipeline.runtime import _Log, _Run
    from robust_imdp.synthesis.margins import strategy_bounds

    problem = load_problem(ROOT / "examples" / "problems" / f"{CASES[0]}.toml")
    with tempfile.TemporaryDirectory(prefix="margins-tight-") as tmp:
        cache = Path(tmp) / "cache"
        res = synthesize_from_data(problem, progress=False, abstraction_cache=cache, advice=False)
        z = _load_npz(cache / f"scaled-{bounds_key(problem)}.npz")
        j = int(np.flatnonzero(z["scales"] == scale)[0])
        re_lo, re_hi = z["lower"][j], z["upper"][j]
        big = problem.replace(rkhs_bound=scale * float(problem.rkhs_bound))
        t0 = time.perf_counter()
        synthesize_from_data(big, progress=False, abstraction_cache=cache, advice=False, margins=False)
        fresh_s = time.perf_counter() - t0
        fresh = _load_bounds(cache / f"bounds-{bounds_key(big)}.npz")[0]
    f_lo, f_hi = np.asarray(fresh.image_lower), np.asarray(fresh.image_upper)
    ratio = (re_hi - re_lo) / (f_hi - f_lo)
    P = res.partition
    kept = {}
    for name, lo, hi in (("re-evaluated", re_lo, re_hi), ("fresh", f_lo, f_hi)):
        ab = _chunked_abstract(problem, P, CellBounds(lo, hi, None), _Log(False), _Run(), P.n_cells)
        p_low, _ = strategy_bounds(ab.imdp, P.labels, P.atoms, res.dfa, res.synthesis,
                                   outside_state=P.outside_state)
        kept[name] = int(np.sum((res.class_names == "yes") & (p_low >= problem.threshold)))
    # the fresh bound stage prunes vertices too (a pruned vertex keeps a neighbour's certified value), so its
    # boxes are not the optimal ones: where they stick out of the re-evaluated ones, by how much
    over = np.maximum(f_hi - re_hi, re_lo - f_lo)
    contained = bool(np.all(over <= 1e-9))
    out = {"problem": CASES[0], "scale": scale, "width_ratio_median": float(np.median(ratio)),
           "width_ratio_max": float(np.max(ratio)), "q_yes": res.counts["yes"], "kept_yes_re_evaluated":
           kept["re-evaluated"], "kept_yes_fresh": kept["fresh"], "fresh_contained": contained,
           "fresh_outside_boxes": int(np.sum(over > 1e-9)), "boxes": int(over.size),
           "fresh_outside_max": float(over.max()), "fresh_outside_max_over_width": float(np.max(over / (f_hi - f_lo))),
           "fresh_run_s": fresh_s, "margins_stage_s": float(res.timings.get("margins", 0.0))}
    print(f"tightness: {out}", flush=True)
    return out


# --------------------------------------------------------------------------- (c) the family at half the true norm
class FamilySystem:
    """The true system of a family configuration (``family.system``): ``x' = A x + s_u + g_u(x) + v``."""

    def __init__(self, sy: dict):
        self.sy = sy
        self.mode_names = tuple(f"m{i}" for i in range(len(sy["maps"])))

    def step(self, x, modes, rng):
        out = np.empty_like(x)
        for u, (A, s) in enumerate(self.sy["maps"]):
            idx = np.flatnonzero(modes == u)
            if idx.size:
                xu = x[idx]
                g = np.stack([gi(xu) for gi in self.sy["g"][u]], axis=1)
                out[idx] = xu @ A.T + s + g + self.sy["noise"].sample(idx.size, rng)
        return out


class _Adversarial:
    """``h*(x) = N' (phi(x) - sum_i w_i k(x, x_i)) / r``: the admissible function (norm N', within the noise bound of
    every residual) that maximises the mean of h over the grid points ``Z`` (``phi = mean_j k(., z_j)``)."""

    def __init__(self, X, y, Z, ell, N, dbar):
        from robust_imdp.bounds import rkhs
        from robust_imdp.solvers.lp import rkhs_vertex_socp

        self.X, self.Z, self.ell = X, Z, ell
        K = rkhs.unit_kernel(X, X, ell)
        b = rkhs.unit_kernel(X, Z, ell).mean(axis=1)
        s0 = float(rkhs.unit_kernel(Z, Z, ell).mean())
        # a little inside the assumption (norm and noise), so that the solver's accuracy cannot leave it
        self.norm, noise = N * (1 - 1e-6), dbar * (1 - 1e-3)
        _, w = rkhs_vertex_socp(K, y, b, s0, noise, self.norm, 1)
        self.w = np.asarray(w, float)
        self.r = float(np.sqrt(max(s0 - 2 * self.w @ b + self.w @ K @ self.w, 1e-300)))
        self.data_gap = float(np.max(np.abs(self(X) - y)) / dbar)  # <= 1: the data are consistent with h*

    def __call__(self, x):
        from robust_imdp.bounds import rkhs

        x = np.asarray(x, float)
        return self.norm / self.r * (rkhs.unit_kernel(x, self.Z, self.ell).mean(axis=1)
                                     - rkhs.unit_kernel(x, self.X, self.ell) @ self.w)


def adversarial(sy: dict) -> dict:
    """The family system with every mode's first component replaced by :class:`_Adversarial` (a drift east, towards
    the obstacle, as large as norm N and the data allow): an admissible truth under the assumption at N."""
    part = sy["partition"]
    Z = 0.5 * (part.cells_lower + part.cells_upper)
    g = [list(row) for row in sy["g"]]
    gaps = []
    for u, (X, Y, _) in enumerate(sy["data"]):
        g[u][0] = _Adversarial(X, Y[:, 0], Z, sy["lengthscale"], float(sy["true_norm"]), sy["noise_bound"])
        gaps.append(g[u][0].data_gap)
    return dict(sy, g=g, adversary_data_gap=max(gaps))


def family_case(c: dict, seed: int, factor: float) -> list:
    """One family configuration with ``rkhs_bound = factor * N`` (N the true norm): margins vs Monte Carlo, once with
    the data-generating functions as the truth, once with the adversarial drift (:func:`adversarial`)."""
    import family
    from robust_imdp.errors import AssumptionError
    from robust_imdp.pipeline.run import synthesize_from_data

    sy = family.system(c, seed)
    N = float(sy["true_norm"])
    problem = family.pipeline_problem(c, seed).replace(rkhs_bound=factor * N)
    row = {"key": family.key_of(c), "seed": seed, "factor": factor, "true_norm": N, "rkhs_bound": factor * N}
    try:
        res = synthesize_from_data(problem, progress=False, advice=False)
    except AssumptionError as exc:
        return [dict(row, truth=t, skipped=f"refused: {str(exc)[:160]}") for t in ("data", "adversarial")]
    adv = adversarial(sy)
    return [_monte_carlo(dict(row, truth="data"), res, sy, seed),
            _monte_carlo(dict(row, truth="adversarial", adversary_data_gap=adv["adversary_data_gap"]), res, adv, seed)]


def _monte_carlo(row: dict, res, sy: dict, seed: int) -> dict:
    from robust_imdp.validate import validate

    mins = [m["minimum"] for m in res.diagnostics["assumption"]["min_norm"]]
    rep = validate(res, FamilySystem(sy), n_per_cell=N_PER_CELL, max_steps=MAX_STEPS, rng=seed,
                   confidence=CONFIDENCE)
    b = np.asarray(res.b_margin, float)
    cls = np.asarray(res.class_names)
    thr = res.threshold
    contradicted = rep.cells[((cls[rep.cells] == "yes") & (rep.wilson_up < thr))
                             | ((cls[rep.cells] == "no") & (rep.wilson_low >= thr))]
    outside = np.asarray(rep.outside, dtype=np.int64)

    def split(cells):
        m = b[cells]
        return {"n": int(cells.size), "margin_below_2": int(np.sum(m < 2)), "margin_at_least_2": int(np.sum(m >= 2)),
                "undecided": int(np.sum(np.isnan(m)))}

    row.update({"min_norm": float(max(mins)), "cells": res.n_cells, "q_yes": int(np.sum(cls == "yes")),
                "q_no": int(np.sum(cls == "no")), "margin_below_2_decided": int(np.sum(b < 2)),
                "outside": split(outside), "contradicted": split(contradicted),
                "expected_outside": float(rep.expected_outside), "allowed_outside": int(rep.allowed_outside),
                "outside_cells_margin_ge_2": [int(q) for q in outside[b[outside] >= 2]],
                "yes_cells": np.flatnonzero(cls == "yes").tolist(),
                "yes_cells_margin_ge_2": np.flatnonzero((cls == "yes") & (b >= 2)).tolist(),
                "kept_yes": res.margins["kept_yes"]})
    print(f"family {row['key']} seed {seed} B = {row['factor']:g} N, truth {row['truth']}: outside {row['outside']}, contradicted "
          f"{row['contradicted']}, expected by chance {row['expected_outside']:.2f}", flush=True)
    return row


def family_rows(seeds) -> list:
    rows = []
    for c in FAMILY_CONFIGS:
        for seed in seeds:
            for factor in (0.5, 1.0):
                rows.extend(family_case(c, seed, factor))
    return rows


# --------------------------------------------------------------------------- report
def write_md(path: Path, data: dict) -> None:
    lines = ["# Assumption margins (benchmarks/margins.py)", ""]
    metas = {p: data.get(f"{p}_meta") for p in ("cost", "tightness", "family") if data.get(p) is not None}
    if all(metas.values()):
        for p, m in metas.items():
            lines.append(f"* ({p}) `{m['command']}`; commit {m['commit']}, {m['date']}, {m['machine']}.")
        lines.append("")
    else:
        lines += [f"Command: `{data['command']}`; commit {data['commit']}, {data['date']}, {data['machine']}.", ""]
    if data.get("cost"):
        lines += ["## (a) Cost on the case studies (target: with margins <= 2 x a plain run)", "",
                  "Wall times of each run (fresh cache, alternating order) and the ratio of their medians; CPU "
                  "seconds of this process (all its threads: less sensitive to the other jobs on the machine) "
                  "and their ratio.", "",
                  "| problem | cells | Q_yes | plain run (s) | with margins (s) | wall ratio | CPU plain / margins (s) | CPU ratio | bound off / on (s) | margins stage (s) | factors solved | Q_yes kept at 1.25, 1.5, 2, 3, 4 B | load |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in data["cost"]:
            lines.append(f"| {r['problem']} | {r['cells']} | {r['q_yes']} | {', '.join(f'{v:.1f}' for v in r['wall_off_s'])} "
                         f"| {', '.join(f'{v:.1f}' for v in r['wall_on_s'])} | {r['ratio']:.3f} | "
                         f"{', '.join(f'{v:.0f}' for v in r.get('cpu_off_s', []))} / "
                         f"{', '.join(f'{v:.0f}' for v in r.get('cpu_on_s', []))} | {r.get('cpu_ratio', float('nan')):.3f} | "
                         f"{r['bound_off_s']:.1f} / {r['bound_on_s']:.1f} | {r['margins_stage_s']:.2f} | "
                         f"{len(r['solved'])} | {', '.join(str(k) for k in r['kept_yes'][1:])} | {r['load']} |")
        worst = max(max(r["ratio"], r.get("cpu_ratio", 0.0)) for r in data["cost"])
        lines += ["", f"Largest ratio (wall or CPU) {worst:.3f} (target {COST_TARGET:g}): "
                  + ("met." if worst <= COST_TARGET else "NOT met."),
                  "The classes with and without margins are identical on every problem: "
                  + str(all(r["same_classes"] for r in data["cost"])) + ".", ""]
    if data.get("tightness"):
        t = data["tightness"]
        lines += [f"## (b) Re-evaluated boxes at {t['scale']:g} B against a fresh bound stage at {t['scale']:g} B ({t['problem']})", "",
                  f"* box width re-evaluated / fresh: median {t['width_ratio_median']:.4f}, max {t['width_ratio_max']:.4f}; "
                  f"the fresh boxes lie inside the re-evaluated ones: {t['fresh_contained']}"
                  + ("" if t["fresh_contained"] or "fresh_outside_boxes" not in t else
                     f" ({t['fresh_outside_boxes']} of {t['boxes']} boxes stick out, by at most {t['fresh_outside_max']:.3g} = "
                     f"{t['fresh_outside_max_over_width']:.3g} of the width: the fresh stage prunes vertices too, so its boxes are "
                     "not the optimal ones)"),
                  f"* Q_yes cells the run's controller keeps at {t['scale']:g} B: {t['kept_yes_re_evaluated']} (re-evaluated) vs "
                  f"{t['kept_yes_fresh']} (fresh optimisation) of {t['q_yes']}",
                  f"* a fresh bound stage at {t['scale']:g} B took {t['fresh_run_s']:.1f} s; the whole margins stage "
                  f"{t['margins_stage_s']:.2f} s", ""]
    if data.get("family"):
        lines += ["## (c) The family with B = N / 2 (N the true norm): Monte Carlo against the margins", "",
                  "Cells outside their bounds (`validate`, Wilson 0.999) and cells whose class the simulation contradicts, "
                  "split by their margin from the run at B (target: none with margin >= 2 beyond chance).", "",
                  "Truth `data`: the functions that generated the data. Truth `adversarial`: every mode's first "
                  "component replaced by the admissible function (norm N, within the noise bound of every residual) "
                  "that maximises its mean over X, a drift east towards the obstacle (the same data, so the same run).", "",
                  "| configuration | seed | B / N | truth | min norm / N | Q_yes | margin < 2 (decided) | outside: n (margin < 2 / >= 2 / Q_?) | class contradicted: n (< 2 / >= 2) | expected by chance |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in data["family"]:
            if "skipped" in r:
                lines.append(f"| {r['key']} | {r['seed']} | {r['factor']:g} | {r.get('truth', 'data')} | | | | {r['skipped']} | | |")
                continue
            o, k = r["outside"], r["contradicted"]
            lines.append(f"| {r['key']} | {r['seed']} | {r['factor']:g} | {r.get('truth', 'data')} | {r['min_norm'] / r['true_norm']:.2f} | {r['q_yes']} | "
                         f"{r['margin_below_2_decided']} | {o['n']} ({o['margin_below_2']} / {o['margin_at_least_2']} / "
                         f"{o['undecided']}) | {k['n']} ({k['margin_below_2']} / {k['margin_at_least_2']}) | "
                         f"{r['expected_outside']:.2f} |")
        for truth in ("data", "adversarial"):
            for factor in (0.5, 1.0):
                rs = [r for r in data["family"] if r["factor"] == factor and "skipped" not in r
                      and r.get("truth", "data") == truth]
                if not rs:
                    continue
                bad = sum(r["outside"]["margin_at_least_2"] + r["contradicted"]["margin_at_least_2"] for r in rs)
                lines.append(f"* truth {truth}, B = {factor:g} N: {sum(r['outside']['n'] for r in rs)} cells outside their "
                             f"bounds and {sum(r['contradicted']['n'] for r in rs)} contradicted classes over {len(rs)} runs "
                             f"({sum(r['expected_outside'] for r in rs):.1f} expected by chance); {bad} of them with a "
                             f"margin >= 2.")
        # the cells the run at N / 2 says keep Q_yes up to 2 B = N, against the run at the true norm N
        pairs = {}
        for r in data["family"]:
            if "skipped" not in r and r.get("truth", "data") == "data" and "yes_cells" in r:
                pairs.setdefault((r["key"], r["seed"]), {})[r["factor"]] = r
        kept = inside = yes_half = yes_true = 0
        for pr in pairs.values():
            if 0.5 in pr and 1.0 in pr:
                ge2 = set(pr[0.5]["yes_cells_margin_ge_2"])
                kept += len(ge2)
                inside += len(ge2 & set(pr[1.0]["yes_cells"]))
                yes_half += len(pr[0.5]["yes_cells"])
                yes_true += len(pr[1.0]["yes_cells"])
        if kept or yes_half:
            lines.append(f"* over the {sum(1 for pr in pairs.values() if 0.5 in pr and 1.0 in pr)} configurations run at "
                         f"both B: the runs at N / 2 have {yes_half} Q_yes cells, those at N {yes_true}; {kept} of the "
                         f"former have a margin >= 2 (their class claimed up to 2 B = N), and {inside} of these are Q_yes "
                         "in the run at the true norm too.")
        gaps = [r["adversary_data_gap"] for r in data["family"] if "adversary_data_gap" in r]
        if gaps:
            lines.append(f"* the adversarial functions meet the data within {max(gaps):.4f} of the noise bound (<= 1: "
                         "admissible).")
        lines.append("")
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=1, help="runs per case study and setting (default 1)")
    ap.add_argument("--only", nargs="+", choices=("cost", "tightness", "family"), default=None)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    args = ap.parse_args(argv)
    parts = args.only or ["cost", "tightness", "family"]
    import platform

    import robust_imdp

    path = OUT / "margins.json"
    data = json.loads(path.read_text()) if (args.only and path.exists()) else {}
    data.update({"command": "python benchmarks/margins.py" + "".join(f" {a}" for a in (argv or sys.argv[1:])),
                 "commit": _git_commit(), "version": robust_imdp.__version__,
                 "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                 "machine": f"{platform.machine()}, {os.cpu_count()} cores, load {_load()} at the start"})
    meta = {k: data[k] for k in ("command", "commit", "date", "machine")}  # each part says how it was run
    if "cost" in parts:
        data["cost"], data["cost_meta"] = cost(args.reps), meta
    if "tightness" in parts:
        data["tightness"], data["tightness_meta"] = tightness(), meta
    if "family" in parts:
        data["family"], data["family_meta"] = family_rows(args.seeds), meta
    OUT.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.part")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)
    write_md(OUT / "margins.md", data)
    print(f"wrote {path} and {OUT / 'margins.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
