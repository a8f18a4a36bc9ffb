"""Where to sample next: Q_yes against added samples, for the incremental ``improve`` loop and for the same
number of samples drawn uniformly at random.

    python benchmarks/sampling.py [--cases three_mode_linear four_mode_nonlinear starved:20 starved:40 starved:80
                                   unicycle_3d_known family:d2-rl0.125-nz0.15-dn2 ...] [--start 30] [--budget 90]
                                  [--round-size 10] [--uniform-steps 3] [--seeds 3] [--validate 20]
                                  [--out benchmarks/results/sampling] [--render]

Case studies: ``three_mode_linear`` and ``four_mode_nonlinear`` (the paper's grids); ``unicycle_3d_known``
(the 3-D robot with known kinematics, only the cross current learned) on a ``--unicycle-cells``^3 grid
(default 32: at 16^3 and 24^3 the Q_yes of 30 samples per mode is already the known-dynamics reference's
or within 2 cells of it, so no sampling can show), with global weights (``local_points`` off: a
data-starved start has fewer points than the 50 local ones) and Monte-Carlo validation on
``--validate-cells`` seeded cells per round; and configurations of the tightness family
(``family:KEY``, ``benchmarks/family.py``'s random systems of exactly known RKHS norm, its builders
imported, the start data drawn afresh).

Each case starts from ``--start`` samples per mode (data-starved). ``improve``
(:func:`robust_imdp.improve.improve`) adds ``--budget`` samples in rounds of ``--round-size``: each round
suggests requests, simulates one step of the true system from each, checks the assumption incrementally,
re-bounds only the cells near the new points, rebuilds their rows and re-solves; its per-round wall time
is recorded with the time of its bound + solve parts (the target: a round costs <= 3 x that). Uniform
random: ``--uniform-steps`` points (``budget / steps`` apart) of whole pipeline runs on the start data plus
that many uniformly drawn (state, mode) pairs, for ``--seeds`` seeds. ``--validate K``: Monte-Carlo
containment (``validate.validate``, K runs per cell, fixed seed) of every improve round's result.

``starved:PER`` (e.g. ``starved:20 starved:40 starved:80``): the data-starved 2-D problem of
``benchmarks/starved.py`` with PER samples per mode, over ``--seeds`` start-data seeds: improve with
``--starved-budget`` N samples in its default rounds, with and without the look-ahead targets, against whole
runs with N and 3 N uniform samples (:func:`run_starved`; target: improve with N >= uniform with 3 N, medians).

Target: the Q_yes uniform random sampling reaches with N added samples (median over the seeds, at the
largest N) is reached by improve with <= N / 3 samples. Writes ``case_<name>.json`` per case, and
``sampling.json`` / ``sampling.md`` / ``sampling.png`` from every case file in ``--out`` (``--render``:
only that).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from robust_imdp.casestudies.systems import get_case_study, true_system  # noqa: E402
from robust_imdp.models.system import Dataset  # noqa: E402

#: Seed of the starting data of every curve (the same data for improve and uniform).
START_SEED = 0


#: Cells per axis of the 3-D unicycle (see the module docstring).
UNICYCLE_CELLS = 32
_TEMPLATES: dict = {}


def _template(case_name: str):
    """The case study's problem (its own data file, replaced below); cached per case."""
    import tempfile

    from robust_imdp.casestudies.systems import write_problem_files
    from robust_imdp.io.files import load_problem

    if case_name not in _TEMPLATES:
        with tempfile.TemporaryDirectory() as tmp:
            p = load_problem(write_problem_files(case_name, tmp, seed=0))
        if case_name.startswith("unicycle"):
            p = p.replace(cell_size=(np.asarray(p.space_upper) - np.asarray(p.space_lower)) / UNICYCLE_CELLS,
                          local_points=None)
        _TEMPLATES[case_name] = p
    return _TEMPLATES[case_name]


def _problem(case_name: str, x, u, xn):
    if case_name.startswith("family:"):
        return _family(case_name)["problem"](x, u, xn)
    p = _template(case_name)
    return p.replace(data=Dataset(x, u, xn, modes=p.mode_names))


class FamilySystem:
    """A configuration of ``benchmarks/family.py`` as a true system: ``x+ = A x + s_u + g_u(x) + v``."""

    def __init__(self, sy: dict):
        import family

        self.sy = sy
        self.mode_names = tuple(f"m{i}" for i in range(len(sy["maps"])))
        d = sy["dim"]
        # family's data noise: within (1 - 1e-9) of the bound (the residuals' rounding stays inside it)
        self.noise = family.TruncatedGaussianNoise(np.full(d, sy["noise_bound"] / 2),
                                                   np.full(d, sy["noise_bound"] * (1 - 1e-9)))

    def step(self, x, modes, rng):
        x = np.asarray(x, float)
        modes = np.asarray(modes)
        out = np.empty_like(x)
        for u, (A, s) in enumerate(self.sy["maps"]):
            k = np.flatnonzero(modes == u)
            if k.size:
                xu = x[k]
                g = np.stack([gi(xu) for gi in self.sy["g"][u]], axis=1)
                out[k] = xu @ A.T + s + g + self.noise.sample(k.size, rng)
        return out


_FAMILY: dict = {}


def _family(case_name: str) -> dict:
    """``{"system", "lower", "upper", "problem": (x, u, xn) -> Problem}`` of ``family:KEY`` (seed 0)."""
    if case_name not in _FAMILY:
        import family

        key = case_name.split(":", 1)[1]
        conf = [c for c in family.configurations("full") if family.key_of(c) == key]
        if not conf:
            raise SystemExit(f"unknown family configuration {key!r}")
        sy = family.system(conf[0], 0)
        system = FamilySystem(sy)

        def problem(x, u, xn):
            from robust_imdp.pipeline.problem import Problem

            names = list(system.mode_names)
            return Problem.from_arrays(
                x, np.asarray(names)[np.asarray(u)], xn, lower=sy["lower"], upper=sy["upper"],
                cell_size=2 * sy["r"], regions=sy["regions"], formula=family.FORMULA, threshold=family.THRESHOLD,
                modes={n: m for n, m in zip(names, sy["maps"])}, noise=sy["noise"], rkhs_bound=sy["B"],
                lengthscale=sy["lengthscale"])

        _FAMILY[case_name] = {"system": system, "lower": sy["lower"], "upper": sy["upper"], "problem": problem,
                              "B": sy["B"], "true_norm": sy["true_norm"], "lengthscale": sy["lengthscale"]}
    return _FAMILY[case_name]


def _case(case_name: str):
    """(system, lower, upper) of a case."""
    if case_name.startswith("family:"):
        f = _family(case_name)
        return f["system"], np.asarray(f["lower"], float), np.asarray(f["upper"], float)
    case = get_case_study(case_name)
    return true_system(case_name), np.asarray(case.lower, float), np.asarray(case.upper, float)


def _start_data(system, lower, upper, start: int):
    rng = np.random.default_rng(START_SEED)
    u = np.repeat(np.arange(len(system.mode_names)), start)
    x = lower + rng.random((u.size, lower.size)) * (upper - lower)
    return x, u, system.step(x, u, rng)


def _classes(result) -> dict:
    c = np.asarray(result.class_names)
    return {"yes": int((c == "yes").sum()), "no": int((c == "no").sum()), "maybe": int((c == "maybe").sum())}


def _improve_curve(case_name, system, x0, u0, xn0, budget, round_size, n_validate, validate_cells) -> list:
    """The improve loop's rounds; with ``n_validate``, Monte-Carlo containment of every round's result."""
    from robust_imdp.improve import improve
    from robust_imdp.validate import validate

    rows = []

    def each(r, result):
        s = r.seconds
        rows.append({"added": (rows[-1]["added"] if rows else 0) + r.added, **r.counts, "seconds": s["total"],
                     "bound_plus_solve": s.get("bound", 0.0) + s.get("solve", 0.0), "rebound": r.rebound, "parts": s})
        if n_validate:
            n_cells = result.partition.n_cells
            cells = None if n_cells <= validate_cells else np.sort(
                np.random.default_rng(11).choice(n_cells, validate_cells, replace=False))
            rep = validate(result, system, n_per_cell=n_validate, rng=7, cells=cells)
            rows[-1]["validation"] = {"passed": bool(rep.passed), "flagged": len(rep.outside),
                                      "allowed": int(rep.allowed_outside), "cells": int(len(rep.cells)),
                                      "n_per_cell": int(n_validate)}
        inc = result.diagnostics.get("assumption", {}).get("incremental_check")
        if inc and inc.get("components"):
            rows[-1]["check_paths"] = [c["how"] for c in inc["components"]]
        print(f"  improve round {r.round}: +{rows[-1]['added']}: Q_yes {r.counts['yes']} ({s['total']:.2f} s, bound + "
              f"solve {rows[-1]['bound_plus_solve']:.2f} s)"
              + (f", validation {'passed' if rows[-1]['validation']['passed'] else 'FAILED'}" if n_validate else ""),
              flush=True)

    improve(_problem(case_name, x0, u0, xn0), system, budget, rounds=max(1, budget // round_size), progress=False,
            allow_outside=True, on_round=each)
    return rows


def _uniform_curve(lower, upper, case_name, system, x0, u0, xn0, budget, steps, seed, start_row=None) -> list:
    from robust_imdp.pipeline.run import synthesize_from_data

    rng = np.random.default_rng(1000 + seed)
    M = len(system.mode_names)
    xs = rng.uniform(lower, upper, (budget, len(lower)))
    us = rng.integers(0, M, budget)
    xn = system.step(xs, us, rng)
    rows = []
    for k in range(steps + 1):
        m = budget * k // steps
        if m == 0 and start_row is not None:  # the start data: the same run for every seed
            rows.append(dict(start_row))
            continue
        t0 = time.perf_counter()
        res = synthesize_from_data(_problem(case_name, np.vstack([x0, xs[:m]]), np.concatenate([u0, us[:m]]),
                                            np.vstack([xn0, xn[:m]])), progress=False, advice=False)
        rows.append({"added": m, **_classes(res), "seconds": time.perf_counter() - t0})
        print(f"  uniform seed {seed}: +{m}: Q_yes {rows[-1]['yes']} ({rows[-1]['seconds']:.1f} s)", flush=True)
    return rows


def run(case_name: str, start: int, budget: int, round_size: int, steps: int, seeds: int, n_validate: int,
        validate_cells: int = 10 ** 9) -> dict:
    system, lower, upper = _case(case_name)
    if not case_name.startswith("family:"):  # a case study: its own sampler (the earlier measurements' data)
        x0, u0, xn0 = system.sample_dataset(start, lower, upper, np.random.default_rng(START_SEED))
    else:
        x0, u0, xn0 = _start_data(system, lower, upper, start)
    print(case_name, flush=True)
    p = _problem(case_name, x0, u0, xn0)
    out = {"case": case_name, "start_per_mode": start, "budget": budget, "round_size": round_size,
           "cells": int(np.prod(np.round((np.asarray(p.space_upper) - np.asarray(p.space_lower))
                                         / np.asarray(p.cell_size)))), "curves": {}}
    if case_name.startswith("family:"):
        f = _family(case_name)
        out["family"] = {"B": f["B"], "true_norm": f["true_norm"], "lengthscale": f["lengthscale"]}
    if case_name.startswith("unicycle"):
        out["grid"] = f"{UNICYCLE_CELLS}^3, local_points off"
    t0 = time.time()
    out["load_before"] = os.getloadavg()
    out["curves"]["improve"] = _improve_curve(case_name, system, x0, u0, xn0, budget, round_size, n_validate,
                                              validate_cells)
    start_row = None
    for s in range(seeds):
        c = _uniform_curve(lower, upper, case_name, system, x0, u0, xn0, budget, steps, s, start_row)
        start_row = c[0]
        out["curves"][f"uniform_seed{s}"] = c
    out["load_after"] = os.getloadavg()
    out["wall_s"] = time.time() - t0
    out["target"] = _target(out)
    return out


def _target(out: dict) -> dict:
    """The fewest improve samples reaching the uniform median Q_yes at the largest N, against N / 3; the
    round-time ratio (round wall time / its bound + solve) per round, its worst round and median."""
    uni = [v for k, v in out["curves"].items() if k.startswith("uniform")]
    N = uni[0][-1]["added"]
    goal = float(np.median([c[-1]["yes"] for c in uni]))
    reach = [r["added"] for r in out["curves"]["improve"] if r["yes"] >= goal]
    need = min(reach) if reach else None
    imp = out["curves"]["improve"][1:]
    ratios = [r["seconds"] / max(r["bound_plus_solve"], 1e-9) for r in imp]
    worst = int(np.argmax(ratios)) + 1 if ratios else None
    val = [r["validation"]["passed"] for r in out["curves"]["improve"] if "validation" in r]
    return {"N": N, "uniform_median_yes": goal, "improve_samples_needed": need, "met": need is not None
            and need <= N / 3, "ratios": ratios, "max_round_over_bound_plus_solve": max(ratios, default=None),
            "worst_round": worst, "median_round_over_bound_plus_solve": float(np.median(ratios)) if ratios else None,
            "round_time_met": bool(ratios) and max(ratios) <= 3.0,
            "median_round_s": float(np.median([r["seconds"] for r in imp])) if imp else None,
            "max_check_s": max((r["parts"].get("check", 0.0) for r in imp), default=None),
            "validation_all_passed": bool(val) and all(val), "validated_rounds": len(val)}


def run_starved(case_name: str, budget: int, seeds: int, factor: int = 3) -> dict:
    """``starved:PER``: ``benchmarks/starved.py`` with PER samples per mode, over ``seeds`` start-data seeds.

    Per seed s (start data ``starved.build(PER, s)``, the same for every curve): ``improve`` with ``budget``
    samples in its default rounds (the look-ahead targets), the same without targets (``targeted=False``:
    the undecided cells' summed radius change, the rule before the look-ahead), and whole runs on the start
    data plus ``budget`` and ``factor x budget`` uniform (state, mode) samples (``np.random.default_rng(1000 + s)``).
    The target: improve's median Q_yes >= the uniform median at ``factor x budget``."""
    import starved
    from robust_imdp.improve import auto_rounds, improve
    from robust_imdp.pipeline.run import synthesize_from_data

    per = int(case_name.split(":", 1)[1])
    print(case_name, flush=True)
    out = {"case": case_name, "start_per_mode": per, "budget": budget, "factor": factor, "seeds": seeds,
           "rounds": auto_rounds(budget), "cells": 256, "load_before": os.getloadavg(), "per_seed": []}
    t0 = time.time()
    for seed in range(seeds):
        b = starved.build(per, seed)
        x0, u0, xn0 = b["start"]
        row = {"seed": seed}
        for key, targeted in (("improve", True), ("improve_untargeted", False)):
            t1 = time.perf_counter()
            res = improve(b["problem"](x0, u0, xn0), b["system"], budget, progress=False, allow_outside=True,
                          seed=seed, targeted=targeted)
            row[key] = [r.counts["yes"] for r in res.rounds]
            row[key + "_s"] = time.perf_counter() - t1
            row[key + "_suggest_s"] = sum(r.seconds.get("suggest", 0.0) for r in res.rounds)
        rng = np.random.default_rng(1000 + seed)
        M = len(b["system"].mode_names)
        xs = rng.uniform(b["lower"], b["upper"], (factor * budget, 2))
        us = rng.integers(0, M, factor * budget)
        xn = b["system"].step(xs, us, rng)
        for m in (0, budget, factor * budget):
            res = synthesize_from_data(b["problem"](np.vstack([x0, xs[:m]]), np.concatenate([u0, us[:m]]),
                                                    np.vstack([xn0, xn[:m]])), progress=False, advice=False)
            row[f"uniform_{m}"] = _classes(res)["yes"]
        print(f"  seed {seed}: start {row['uniform_0']}; improve {row['improve']} ({row['improve_s']:.0f} s); "
              f"untargeted {row['improve_untargeted']}; uniform +{budget}: {row[f'uniform_{budget}']}, "
              f"+{factor * budget}: {row[f'uniform_{factor * budget}']}", flush=True)
        out["per_seed"].append(row)
    out["load_after"] = os.getloadavg()
    out["wall_s"] = time.time() - t0
    med = {k: float(np.median([r[k][-1] if isinstance(r[k], list) else r[k] for r in out["per_seed"]]))
           for k in ("improve", "improve_untargeted", "uniform_0", f"uniform_{budget}", f"uniform_{factor * budget}")}
    out["median"] = med
    out["target_met"] = med["improve"] >= med[f"uniform_{factor * budget}"]
    return out


def _write_starved(outs: list) -> list:
    """The markdown section of the ``starved:PER`` cases."""
    if not outs:
        return []
    b, f = outs[0]["budget"], outs[0]["factor"]
    lines = ["## The data-starved 2-D problem (`benchmarks/starved.py`)", "",
             f"X = [-2, 2]^2, cells 0.25 (256), 3 modes, lengthscale 1, bounded noise 0.02, `G !obs & F goal` at 0.9. "
             f"Per start density and seed (start data `starved.build(PER, seed)`): `improve` with N = {b} samples in "
             f"its default rounds ({outs[0]['rounds']}), the same loop without the look-ahead targets (the rule "
             f"before them), and whole runs with N and {f} N uniform (state, mode) samples. Median over "
             f"{outs[0]['seeds']} seeds; per seed in brackets. Target: improve with N >= uniform with {f} N.", "",
             f"| start per mode | start Q_yes | improve N = {b} | untargeted N = {b} | uniform N = {b} | "
             f"uniform {f} N = {f * b} | target | improve s per run (median) |", "|---|---|---|---|---|---|---|---|"]
    for o in outs:
        rs, m = o["per_seed"], o["median"]

        def cell(key, last=False):
            v = [r[key][-1] if last else r[key] for r in rs]
            return f"{m[key]:g} ({', '.join(str(x) for x in v)})"

        lines.append(f"| {o['start_per_mode']} | {cell('uniform_0')} | {cell('improve', True)} | "
                     f"{cell('improve_untargeted', True)} | {cell(f'uniform_{b}')} | {cell(f'uniform_{f * b}')} | "
                     f"{'met' if o['target_met'] else 'NOT met'} | "
                     f"{np.median([r['improve_s'] for r in rs]):.0f} |")
    lines += ["", "Q_yes after each round of improve (round 0 = start):", ""]
    for o in outs:
        for r in o["per_seed"]:
            lines.append(f"* {o['start_per_mode']} per mode, seed {r['seed']}: improve {r['improve']}; untargeted "
                         f"{r['improve_untargeted']}")
    return lines + [""]


def write(outs: list, where: Path) -> None:
    where.mkdir(parents=True, exist_ok=True)
    _write_atomic(where / "sampling.json", json.dumps(outs, indent=1))
    starved_outs = [o for o in outs if o["case"].startswith("starved:")]
    outs = [o for o in outs if not o["case"].startswith("starved:")]
    lines = ["# improve (incremental) vs uniform random samples", "",
             "`benchmarks/sampling.py`; targets (issue 22): improve reaches the uniform median Q_yes at the largest N "
             "with <= N/3 samples; a round costs <= 3 x (bound + solve) of the round; Monte-Carlo containment "
             "after every round. Machine: 2 cores, shared; load averages (1, 5, 15 min) before / after each case.",
             ""]
    summary = [] if not outs else [
        "| case | cells | N | uniform median Q_yes at N | improve samples to reach it (<= N/3) | worst round "
        "ratio (round) | median ratio | median s per round | max check s | MC every round |",
        "|---|---|---|---|---|---|---|---|---|---|"]
    for out in outs:
        t = out["target"]
        summary.append(
            f"| {out['case']} | {out.get('cells', '')} | {t['N']} | {t['uniform_median_yes']:g} | "
            f"{t['improve_samples_needed']} ({'met' if t['met'] else 'NOT met'}) | "
            f"{t['max_round_over_bound_plus_solve']:.2f} ({t['worst_round']}; "
            f"{'met' if t['round_time_met'] else 'NOT met'}) | {t['median_round_over_bound_plus_solve']:.2f} | "
            f"{t['median_round_s']:.2f} | {t['max_check_s']:.3f} | "
            f"{'passed' if t['validation_all_passed'] else 'NOT all passed'} ({t['validated_rounds']} rounds) |")
    lines += summary + [""] if summary else []
    lines += _write_starved(sorted(starved_outs, key=lambda o: o["start_per_mode"]))
    for out in outs:
        imp = out["curves"]["improve"]
        uni = [v for k, v in out["curves"].items() if k.startswith("uniform")]
        t = out["target"]
        extra = ""
        if "family" in out:
            f = out["family"]
            extra = (f" Family system: B = {f['B']:.4g} ({f['B'] / f['true_norm']:.2f} x the exact norm "
                     f"{f['true_norm']:.4g}), lengthscale {f['lengthscale']:g}.")
        if "grid" in out:
            extra = f" Grid {out['grid']}."
        load = (f" Load {', '.join(f'{v:.1f}' for v in out['load_before'])} before, "
                f"{', '.join(f'{v:.1f}' for v in out['load_after'])} after; {out['wall_s']:.0f} s in all."
                if "load_before" in out else "")
        lines += [f"## {out['case']}", "",
                  f"Start: {out['start_per_mode']} samples per mode; improve adds {out['budget']} in rounds of "
                  f"{out['round_size']} (incremental); uniform: whole runs, {len(uni)} seeds.{extra}{load}", "",
                  "| added | Q_yes improve | s per round | bound + solve | ratio | check s | cell bounds re-bounded | "
                  "check (witness kept / refitted / full) | MC (flagged / allowed, cells) |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for i, r in enumerate(imp):
            paths = r.get("check_paths")
            pc = "" if not paths else (f"{paths.count('witness kept')} / {paths.count('witness refitted')} / "
                                       f"{paths.count('full check')}")
            v = r.get("validation")
            vc = "" if v is None else (f"{'pass' if v['passed'] else 'FAIL'} ({v['flagged']}/{v['allowed']}, "
                                       f"{v.get('cells', '')})")
            ratio = "" if i == 0 else f"{r['seconds'] / max(r['bound_plus_solve'], 1e-9):.2f}"
            lines.append(f"| {r['added']} | {r['yes']} | {r['seconds']:.2f} | {r['bound_plus_solve']:.2f} | {ratio} | "
                         f"{r['parts'].get('check', 0.0):.3f} | {r['rebound']} | {pc} | {vc} |")
        lines += ["", "| added | Q_yes uniform (median, min-max) | s per whole run (median) |", "|---|---|---|"]
        for i, row in enumerate(uni[0]):
            u = [c[i]["yes"] for c in uni]
            lines.append(f"| {row['added']} | {int(np.median(u))} ({min(u)}-{max(u)}) | "
                         f"{np.median([c[i]['seconds'] for c in uni]):.1f} |")
        lines += ["", f"Target: uniform median Q_yes at N = {t['N']}: {t['uniform_median_yes']:g}; improve reaches "
                      f"it with {t['improve_samples_needed']} samples (<= N/3 = {t['N'] / 3:g}: "
                      f"{'met' if t['met'] else 'NOT met'}). Round time / (bound + solve): worst "
                      f"{t['max_round_over_bound_plus_solve']:.2f} (round {t['worst_round']}; <= 3: "
                      f"{'met' if t['round_time_met'] else 'NOT met'}), median "
                      f"{t['median_round_over_bound_plus_solve']:.2f}.", ""]
    notes = where / "notes.md"  # measurement notes kept beside the case files (appended as they are)
    if notes.exists():
        lines += ["## Notes", "", notes.read_text().strip(), ""]
    _write_atomic(where / "sampling.md", "\n".join(lines) + "\n")
    if outs:
        _plot(outs, where / "sampling.png")


def _plot(outs: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = min(3, len(outs))
    rows = -(-len(outs) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 3.5 * rows), squeeze=False)
    for ax in axes.flat[len(outs):]:
        ax.set_visible(False)
    for ax, out in zip(axes.flat, outs):
        imp = out["curves"]["improve"]
        ax.plot([r["added"] for r in imp], [r["yes"] for r in imp], "o-", label="improve (suggested)")
        for k, c in enumerate(v for key, v in out["curves"].items() if key.startswith("uniform")):
            ax.plot([r["added"] for r in c], [r["yes"] for r in c], "x--", color="grey", alpha=0.7,
                    label="uniform random" if k == 0 else None)
        ax.set_xlabel("added samples")
        ax.set_ylabel("Q_yes cells")
        ax.set_title(out["case"], fontsize=9)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def main(argv=None) -> int:
    global UNICYCLE_CELLS
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+",
                    default=["three_mode_linear", "four_mode_nonlinear", "starved:20", "starved:40", "starved:80"])
    ap.add_argument("--start", type=int, default=30)
    ap.add_argument("--budget", type=int, default=90)
    ap.add_argument("--round-size", type=int, default=10)
    ap.add_argument("--uniform-steps", type=int, default=3)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--validate", type=int, default=20, help="runs per cell of each round's validation (0: none)")
    ap.add_argument("--validate-cells", type=int, default=2000, help="most cells validated per round (seeded subset)")
    ap.add_argument("--unicycle-cells", type=int, default=UNICYCLE_CELLS)
    ap.add_argument("--starved-budget", type=int, default=240, help="N of the starved:PER cases (default 240)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "sampling")
    ap.add_argument("--render", action="store_true", help="only re-render from the case files in --out")
    args = ap.parse_args(argv)
    UNICYCLE_CELLS = args.unicycle_cells
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.render:
        for c in args.cases:
            if c.startswith("starved:"):
                out = run_starved(c, args.starved_budget, args.seeds)
            else:
                out = run(c, args.start, args.budget, args.round_size, args.uniform_steps, args.seeds, args.validate,
                          args.validate_cells)
            _write_atomic(args.out / f"case_{c.replace(':', '_')}.json", json.dumps(out, indent=1))
    order = ["three_mode_linear", "four_mode_nonlinear", "unicycle_3d_known"]
    outs = [json.loads(f.read_text()) for f in sorted(args.out.glob("case_*.json"))]
    outs.sort(key=lambda o: (order.index(o["case"]) if o["case"] in order else len(order), o["case"]))
    write(outs, args.out)
    print((args.out / "sampling.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
