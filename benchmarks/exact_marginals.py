"""Exact per-axis transition bounds (``[abstraction].transitions = "exact"``) against Thm 1 (``"thm1"``).

    python benchmarks/exact_marginals.py [--suite car problems family eta ...] [--full] [--merge]

Suites (each row: Q_yes / Q_no / Q_? and mean p_low of both, the cells in Q_yes under Thm 1 that the
exact bounds lose (``lost``) or gain, entries per IMDP row, abstraction and synthesis seconds):

* ``car``: car parking (docs/abstraction.md; Mathiesen, Haesaert, Laurenti, HSCC 2025):
  ``x' = 0.9 x + 0.7 u + w``, ``w ~ N(0, I)``, X = [-10, 10]^2 on 40 x 40, the 9 inputs
  ``u in {-1, 0, 1}^2`` as 9 known affine modes (``rkhs_bound = 0``, 9 exact dummy samples per mode),
  ``G !bad & F goal`` within 10 steps, threshold 0.5, through ``Problem.from_arrays`` and
  ``synthesize_from_data``; Monte Carlo of the true system under each controller
  (``validate.validate``, 100 runs per cell). Target: Q_yes >= 315 with the exact joint IMDP.
* ``problems``: every problem of ``benchmarks/identical.py`` (the case studies' files, eleven variants
  of the three-mode study on a coarse grid: ridge, local, GP route, iid, known f, per-component,
  refinement, horizon, uniform noise, the paper's eps rule; a 1-D problem; the newcomer 2-D robots;
  ``robust-imdp example``'s case studies; and two on the GP route with ``guarantee = "paper"``), with
  ``--full`` also the newcomer 3-D unicycle, the 4-D double integrators and the 3-D case study at 16^3.
  Same learned boxes for both (one cache).
* ``family``: the tightness family (``benchmarks/family.py``, its default 19 configurations, or
  ``--quick``'s 4): our certified boxes (no sub-boxes) and the known-dynamics reference boxes,
  abstracted both ways, unbounded horizon.
* ``eta``: the eta sweep's cliff (``examples/eta_sweep.py``): the three-mode study with eta fixed to
  0.96 ... 1.0 sigma under Thm 1 against the exact bounds (no eta), both with the noise scaled by
  1, 4, 16 and 32 (bound 0.01 ... 0.32 against cells of 0.125), and at noise x16 on cells of 0.25 and
  0.0625.

Writes ``benchmarks/results/exact_marginals.json`` and ``.md`` after every suite (``--merge`` keeps the
other suites' rows of the last run).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from reference import merged_rows, results_record  # noqa: E402

NAME = "exact_marginals"
KINDS = ("thm1", "exact")


# --------------------------------------------------------------------------- shared
def _summary(p_low, p_up, threshold) -> dict:
    p_low, p_up = np.asarray(p_low, float), np.asarray(p_up, float)
    yes, no = p_low >= threshold, p_up < threshold
    return {"yes": int(yes.sum()), "no": int(no.sum()), "maybe": int((~yes & ~no).sum()),
            "mean_p_low": float(p_low.mean()), "mean_gap": float((p_up - p_low).mean())}


def _compare(row: dict, a: dict, b: dict) -> None:
    """Cells in Q_yes under Thm 1 and not under exact (lost), the other way round (gained), and the largest
    drop of a cell's p_low from Thm 1 to exact."""
    if a["yes_cells"] is None or b["yes_cells"] is None or len(a["yes_cells"]) != len(b["yes_cells"]):
        row["lost"] = row["gained"] = row["p_low_drop"] = None  # different partitions (refinement): counts only
        return
    ya, yb = np.asarray(a["yes_cells"]), np.asarray(b["yes_cells"])
    row["lost"] = int(np.sum(ya & ~yb))
    row["gained"] = int(np.sum(~ya & yb))
    row["p_low_drop"] = float(np.max(np.asarray(a["p_low"]) - np.asarray(b["p_low"])))


def _as(problem, kind: str):
    """``problem`` with ``transitions = kind`` and, where the pipeline has a factored form, the joint IMDP (this
    benchmark measures the joint rows; the factored form has its own, benchmarks/factored_pipeline.py)."""
    from dataclasses import fields

    extra = {"form": "joint"} if "form" in {f.name for f in fields(problem)} else {}
    return problem.replace(transitions=kind, **extra)


def _pipeline_run(problem, cache, **kw) -> dict:
    from robust_imdp.pipeline.run import synthesize_from_data

    t0 = time.perf_counter()
    res = synthesize_from_data(problem, progress=False, abstraction_cache=cache, advice=False, **kw)
    out = _summary(res.synthesis.p_low, res.synthesis.p_up, problem.threshold)
    out["yes_cells"] = (np.asarray(res.synthesis.p_low) >= problem.threshold).tolist()
    out["p_low"] = np.asarray(res.synthesis.p_low, float)
    out["cells"] = int(res.partition.n_cells)
    vol = np.prod(res.partition.cells_upper - res.partition.cells_lower, axis=1)
    out["yes_volume"] = float(vol[np.asarray(res.synthesis.p_low) >= problem.threshold].sum())
    out["entries_per_row"] = float(np.mean(res.abstraction.nnz_per_row))
    out["abstract_s"] = float(res.timings.get("abstract", 0.0))
    out["synthesize_s"] = float(res.timings.get("synthesize", 0.0))
    out["total_s"] = float(time.perf_counter() - t0)
    out["result"] = res
    return out


def _row(name: str, runs: dict, **extra) -> dict:
    row = {"suite": extra.pop("suite"), "name": name, **extra}
    for k in KINDS:
        r = dict(runs[k])
        r.pop("result", None)
        row[k] = {key: v for key, v in r.items() if key not in ("yes_cells", "p_low")}
    _compare(row, runs["thm1"], runs["exact"])
    return row


# --------------------------------------------------------------------------- car parking
class CarParking:
    """The true system: ``x' = 0.9 x + 0.7 u + w``, ``w ~ N(0, I_2)`` (``validate``'s duck type)."""

    def __init__(self, names, inputs):
        self.mode_names = tuple(names)
        self.inputs = np.asarray(inputs, float)

    def step(self, x, modes, rng):
        return 0.9 * x + 0.7 * self.inputs[modes] + rng.standard_normal(x.shape)


def car_problem():
    from robust_imdp import GaussianNoise, Problem

    inputs = [(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)]
    names = [f"u{a:+d}{b:+d}" for a, b in inputs]
    modes = {n: (0.9 * np.eye(2), 0.7 * np.array(u, float)) for n, u in zip(names, inputs)}
    rng = np.random.default_rng(0)
    x = rng.uniform(-10, 10, (9 * len(names), 2))  # dummy samples: exact successors of the known parts
    u = np.repeat(names, 9)
    un = np.repeat(np.array(inputs, float), 9, axis=0)
    x_next = 0.9 * x + 0.7 * un
    problem = Problem.from_arrays(
        x, u, x_next, lower=[-10, -10], upper=[10, 10], cell_size=0.5,
        regions={"goal": ([4, -4], [10, 0]), "bad": ([4, 0], [10, 4])}, formula="G !bad & F goal", threshold=0.5,
        horizon=10, modes=modes, noise=GaussianNoise([1.0, 1.0]), rkhs_bound=0.0, lengthscale=1.0)
    return problem, CarParking(names, inputs)


def suite_car(args, work: Path) -> list:
    from robust_imdp.pipeline.preflight import exact_successors
    from robust_imdp.validate import validate

    problem, true_system = car_problem()
    estimate = exact_successors(_as(problem, "exact"))
    runs = {}
    for k in KINDS:
        r = _pipeline_run(_as(problem, k), work / "car-cache")
        rep = validate(r["result"], true_system, n_per_cell=args.mc, rng=1)
        r["mc_outside"] = int(len(rep.outside))
        r["mc_allowed_outside"] = int(rep.allowed_outside)
        r["mc_passed"] = bool(rep.passed)
        runs[k] = r
        print(f"car {k}: Q_yes {r['yes']} Q_no {r['no']} mean p_low {r['mean_p_low']:.3f} gap {r['mean_gap']:.3f} "
              f"entries/row {r['entries_per_row']:.0f} MC outside {r['mc_outside']} (allowed {r['mc_allowed_outside']})",
              flush=True)
    return [_row("car_parking_40x40", runs, suite="car", target_yes=315, mc_runs_per_cell=args.mc,
                 preflight_successors=estimate)]


# --------------------------------------------------------------------------- problems
def suite_problems(args, work: Path) -> list:
    import identical

    from robust_imdp.io.files import load_problem

    rows = []
    env = {**os.environ}
    for name, file in _with_paper_route(identical._problems(work / "problems", args.full, env)):
        if args.only and name not in args.only:
            continue
        problem = load_problem(file)
        runs = {k: _pipeline_run(_as(problem, k), work / f"cache-{name}") for k in KINDS}
        row = _row(name, runs, suite="problems", threshold=float(problem.threshold), horizon=problem.horizon)
        print(f"{name}: Q_yes thm1 {row['thm1']['yes']} exact {row['exact']['yes']} (lost {row['lost']}, gained "
              f"{row['gained']}) of {row['exact']['cells']}; entries/row {row['thm1']['entries_per_row']:.1f} -> "
              f"{row['exact']['entries_per_row']:.1f}", flush=True)
        rows.append(row)
    return rows


def _with_paper_route(probs: list) -> list:
    """``identical.py``'s problems and two on the GP route with ``guarantee = "paper"`` (the learned error's
    probability mixed into the transitions, where exact and Thm 1 are not ordered in theory): its coarse
    ``v_gp`` variant and the three-mode study with the GP route."""
    import identical

    files = dict(probs)
    out = list(probs)
    for name, src, edit in (("v_gp_paper", "v_gp", ""),
                            ("three_mode_linear_gp_paper", "three_mode_linear",
                             '[learning]\nerror_bound = "chowdhury"\nmisspecification = 0.0\n')):
        if src not in files:
            continue
        text = files[src].read_text()
        if edit:
            text = identical._edit_toml(text, edit)
        f = files[src].with_name(f"{name}.toml")
        f.write_text(identical._edit_toml(text, '[abstraction]\nguarantee = "paper"\n'))
        out.append((name, f))
    return out


# --------------------------------------------------------------------------- the tightness family
def suite_family(args, work: Path) -> list:
    import family

    from robust_imdp.abstraction.rows import CellBounds, abstract
    from robust_imdp.synthesis.core import synthesize

    rows = []
    configs = family.configurations("quick" if args.quick else "default")
    for c in configs:
        key = family.key_of(c)
        if args.only and key not in args.only:
            continue
        sy = family.system_with_dfa(c, 20)
        part = sy["partition"]
        ref = family.true_boxes(sy)  # the sound outer boxes of the true images
        boxes = {"ours": family.our_boxes(sy, None), "reference": {"lower": ref["outer_lo"], "upper": ref["outer_up"]}}
        for which, bx in boxes.items():
            runs = {}
            for k in KINDS:
                t0 = time.perf_counter()
                ab = abstract(part, CellBounds(bx["lower"], bx["upper"], None), sy["noise"], None, transitions=k)
                t1 = time.perf_counter()
                syn = synthesize(ab.imdp, part.labels, part.atoms, sy["dfa"], threshold=family.THRESHOLD, horizon=None,
                                 outside_state=part.outside_state)
                r = _summary(syn.p_low, syn.p_up, family.THRESHOLD)
                r.update(yes_cells=(np.asarray(syn.p_low) >= family.THRESHOLD).tolist(), cells=int(part.n_cells),
                         p_low=np.asarray(syn.p_low, float),
                         entries_per_row=float(np.mean(ab.nnz_per_row)), abstract_s=t1 - t0,
                         synthesize_s=time.perf_counter() - t1)
                runs[k] = r
            row = _row(f"{key}/{which}", runs, suite="family")
            print(f"family {key} {which}: Q_yes thm1 {row['thm1']['yes']} exact {row['exact']['yes']} "
                  f"(lost {row['lost']}, gained {row['gained']})", flush=True)
            rows.append(row)
    return rows


# --------------------------------------------------------------------------- the eta sweep
def suite_eta(args, work: Path) -> list:
    from robust_imdp.casestudies.systems import write_problem_files
    from robust_imdp.io.files import load_problem
    from robust_imdp.models.noise import TruncatedGaussianNoise

    base = load_problem(write_problem_files("three_mode_linear", work / "eta" / "problem", seed=0))
    sigma = np.asarray(base.noise.sigma, float)
    bound = np.asarray(base.noise.bound, float)
    rows = []
    cache = work / "eta" / "cache"
    exact = _pipeline_run(_as(base, "exact"), cache)
    for frac in (0.96, 0.97, 0.985, 0.995, 1.0):
        runs = {"thm1": _pipeline_run(_as(base.replace(eta=frac * sigma, eps_rule="optimized"), "thm1"), cache),
                "exact": exact}
        row = _row(f"eta {frac} sigma", runs, suite="eta", noise_scale=1.0, eta_fraction=frac)
        print(f"eta {frac}: Q_yes thm1 {row['thm1']['yes']} exact {row['exact']['yes']}", flush=True)
        rows.append(row)
    for scale in (4.0, 16.0, 32.0):
        p = base.replace(noise=TruncatedGaussianNoise(sigma * scale, bound * scale))
        runs = {k: _pipeline_run(_as(p, k), work / "eta" / f"cache-{scale:g}") for k in KINDS}
        row = _row(f"noise x{scale:g} (bound {bound[0] * scale:g}, cells 0.125)", runs, suite="eta",
                   noise_scale=scale, eta_fraction=None)
        print(f"noise x{scale:g}: Q_yes thm1 {row['thm1']['yes']} exact {row['exact']['yes']}; mean p_low "
              f"{row['thm1']['mean_p_low']:.4f} -> {row['exact']['mean_p_low']:.4f}", flush=True)
        rows.append(row)
    # the grid at noise x16 (bound 0.16): cells wider and narrower than the noise
    for cell in (0.25, 0.0625):
        p = base.replace(noise=TruncatedGaussianNoise(sigma * 16, bound * 16), cell_size=np.full(2, cell))
        runs = {k: _pipeline_run(_as(p, k), work / "eta" / f"cache-grid-{cell:g}") for k in KINDS}
        row = _row(f"noise x16 (bound {bound[0] * 16:g}, cells {cell:g})", runs, suite="eta", noise_scale=16.0,
                   eta_fraction=None, cell=cell)
        print(f"grid {cell:g}: Q_yes thm1 {row['thm1']['yes']} exact {row['exact']['yes']}; mean p_low "
              f"{row['thm1']['mean_p_low']:.4f} -> {row['exact']['mean_p_low']:.4f}", flush=True)
        rows.append(row)
    return rows


SUITES = {"car": suite_car, "problems": suite_problems, "family": suite_family, "eta": suite_eta}


# --------------------------------------------------------------------------- report
def _md(data: dict) -> list:
    lines = [f"# Exact per-axis transition bounds against Thm 1 (`benchmarks/{NAME}.py`)", "",
             f"Commit {data.get('commit')}, {data.get('date')}, load average at the end "
             f"{', '.join(f'{x:.1f}' for x in data.get('load', []))}; commands: {'; '.join(data.get('commands', []))}.",
             "",
             "Per problem: Q_yes / Q_no / Q_? and mean p_low with Thm 1 (`thm1`) and with the exact bounds "
             "(`exact`); *lost*: cells in Q_yes under Thm 1 but not under exact; *gained*: the other way; "
             "entries per IMDP row; abstraction and synthesis seconds (2 shared cores).", ""]
    rows = data["rows"]
    lost = [r for r in rows if r.get("lost")]
    drops = [r["p_low_drop"] for r in rows if r.get("p_low_drop") is not None]
    lines += [f"**Q_yes cells lost by exact against thm1 over all rows: {sum(r['lost'] or 0 for r in rows)}** "
              f"({len(lost)} rows with a loss{': ' + ', '.join(r['name'] for r in lost) if lost else ''}); largest "
              f"drop of a cell's p_low from thm1 to exact: "
              f"{max(drops):.3g} (over {len(drops)} rows that record it).", ""] if drops else \
        [f"**Q_yes cells lost by exact against thm1 over all rows: {sum(r['lost'] or 0 for r in rows)}**.", ""]
    for suite in SUITES:
        part = [r for r in rows if r["suite"] == suite]
        if not part:
            continue
        lines += [f"## {suite}", "",
                  "| problem | cells | Q_yes thm1 / exact | lost / gained | Q_no thm1 / exact | mean p_low thm1 / exact "
                  "| entries/row thm1 / exact | abstract s thm1 / exact | synthesize s thm1 / exact |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for r in part:
            t, e = r["thm1"], r["exact"]
            lg = (f"- (Q_yes volume {t.get('yes_volume', float('nan')):g} / {e.get('yes_volume', float('nan')):g})"
                  if r["lost"] is None else f"{r['lost']} / {r['gained']}")
            lines.append(f"| {r['name']} | {e['cells']} | {t['yes']} / {e['yes']} | {lg} | {t['no']} / {e['no']} | "
                         f"{t['mean_p_low']:.4f} / {e['mean_p_low']:.4f} | {t['entries_per_row']:.1f} / "
                         f"{e['entries_per_row']:.1f} | {t['abstract_s']:.1f} / {e['abstract_s']:.1f} | "
                         f"{t['synthesize_s']:.1f} / {e['synthesize_s']:.1f} |")
            if suite == "car":
                lines.append("")
                lines.append(f"Car parking target: Q_yes >= {r['target_yes']} with exact: **{e['yes']}** "
                             f"({'met' if e['yes'] >= r['target_yes'] else 'not met'}); mean gap p_up - p_low "
                             f"{t['mean_gap']:.3f} -> {e['mean_gap']:.3f}. Monte Carlo ({r['mc_runs_per_cell']} runs "
                             f"per cell): cells outside their Wilson interval thm1 {t['mc_outside']} (allowed "
                             f"{t['mc_allowed_outside']}), exact {e['mc_outside']} (allowed {e['mc_allowed_outside']}). "
                             + (f"Pre-flight estimate of the exact rows' entries: {r['preflight_successors']} + the "
                                f"outside state against {e['entries_per_row']:.0f} measured."
                                if "preflight_successors" in r else ""))
        lines.append("")
    return lines


def _write_atomic(data: dict) -> None:
    """``benchmarks/results/NAME.json`` and ``.md``, each written beside the old one and renamed into place
    (the json first: a failure of the table leaves the measurements)."""
    out = ROOT / "benchmarks" / "results"
    for suffix, text in ((".json", lambda: json.dumps(data, indent=1)), (".md", lambda: "\n".join(_md(data)) + "\n")):
        text = text()
        final = out / f"{NAME}{suffix}"
        tmp = out / f".{NAME}{suffix}.part"
        tmp.write_text(text)
        os.replace(tmp, final)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", nargs="+", choices=sorted(SUITES), default=list(SUITES))
    ap.add_argument("--full", action="store_true", help="problems: also the 3-D and 4-D newcomer problems")
    ap.add_argument("--quick", action="store_true", help="family: 4 configurations")
    ap.add_argument("--only", nargs="*", default=None, help="problem names / family keys to run")
    ap.add_argument("--mc", type=int, default=100, help="car: Monte-Carlo runs per cell")
    ap.add_argument("--merge", action="store_true", help="keep the rows of suites not run")
    args = ap.parse_args(argv)
    path = ROOT / "benchmarks" / "results" / f"{NAME}.json"
    old = json.loads(path.read_text()) if args.merge and path.exists() else {"rows": [], "commands": []}
    command = "python benchmarks/exact_marginals.py " + " ".join(sys.argv[1:] if argv is None else argv)
    rows = list(old["rows"])
    work = Path(tempfile.mkdtemp(prefix="exact-marginals-"))
    try:
        for s in args.suite:
            new = SUITES[s](args, work)
            for r in new:
                r["key"] = f"{r['suite']}/{r['name']}"
            rows = merged_rows([r for r in rows if "key" in r], new, "key")
            data = results_record(rows, commands=old.get("commands", [])[-5:] + [command])
            _write_atomic(data)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
