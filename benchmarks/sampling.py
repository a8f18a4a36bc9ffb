"""Where to sample next: Q_yes against added samples, for the incremental ``improve`` loop and for the same
number of samples drawn uniformly at random.

    python benchmarks/sampling.py [--cases three_mode_linear four_mode_nonlinear] [--start 30] [--budget 90]
                                  [--round-size 10] [--uniform-steps 3] [--seeds 3] [--validate 20]
                                  [--out benchmarks/results/sampling]

Each case study starts from ``--start`` samples per mode (data-starved). ``improve``
(:func:`robust_imdp.improve.improve`) adds ``--budget`` samples in rounds of ``--round-size``: each round
suggests requests, simulates one step of the true system from each, re-bounds only the cells near the new
points, rebuilds their rows and re-solves; its per-round wall time is recorded with the time of its
bound + solve parts (the target: a round costs <= 3 x that). Uniform random: ``--uniform-steps`` points
(``budget / steps`` apart) of whole pipeline runs on the start data plus that many uniformly drawn
(state, mode) pairs, for ``--seeds`` seeds. ``--validate K``: Monte-Carlo containment
(``validate.validate``, K runs per cell, fixed seed) of every improve round's result.

Target: the Q_yes uniform random sampling reaches with N added samples (median over the seeds, at the
largest N) is reached by improve with <= N / 3 samples. Writes ``sampling.json``, ``sampling.md`` and
``sampling.png`` into ``--out``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from robust_imdp.casestudies.systems import get_case_study, true_system  # noqa: E402
from robust_imdp.models.system import Dataset  # noqa: E402

#: Seed of the starting data of every curve (the same data for improve and uniform).
START_SEED = 0


def _problem(case_name: str, x, u, xn):
    import tempfile

    from robust_imdp.casestudies.systems import write_problem_files
    from robust_imdp.io.files import load_problem

    with tempfile.TemporaryDirectory() as tmp:
        p = load_problem(write_problem_files(case_name, tmp, seed=0))
    return p.replace(data=Dataset(x, u, xn, modes=p.mode_names))


def _classes(result) -> dict:
    c = np.asarray(result.class_names)
    return {"yes": int((c == "yes").sum()), "no": int((c == "no").sum()), "maybe": int((c == "maybe").sum())}


def _improve_curve(case_name, system, x0, u0, xn0, budget, round_size, n_validate) -> list:
    """The improve loop's rounds; with ``n_validate``, Monte-Carlo containment of every round's result."""
    from robust_imdp.improve import improve
    from robust_imdp.validate import validate

    rows = []

    def each(r, result):
        s = r.seconds
        rows.append({"added": (rows[-1]["added"] if rows else 0) + r.added, **r.counts, "seconds": s["total"],
                     "bound_plus_solve": s.get("bound", 0.0) + s.get("solve", 0.0), "rebound": r.rebound, "parts": s})
        if n_validate:
            rep = validate(result, system, n_per_cell=n_validate, rng=7)
            rows[-1]["validation"] = {"passed": bool(rep.passed), "flagged": len(rep.outside),
                                      "allowed": int(rep.allowed_outside)}
        print(f"  improve round {r.round}: +{rows[-1]['added']}: Q_yes {r.counts['yes']} ({s['total']:.2f} s, bound + "
              f"solve {rows[-1]['bound_plus_solve']:.2f} s)"
              + (f", validation {'passed' if rows[-1]['validation']['passed'] else 'FAILED'}" if n_validate else ""),
              flush=True)

    improve(_problem(case_name, x0, u0, xn0), system, budget, rounds=max(1, budget // round_size), progress=False,
            allow_outside=True, on_round=each)
    return rows


def _uniform_curve(case, case_name, system, x0, u0, xn0, budget, steps, seed) -> list:
    from robust_imdp.pipeline.run import synthesize_from_data

    rng = np.random.default_rng(1000 + seed)
    M = len(system.mode_names)
    xs = rng.uniform(case.lower, case.upper, (budget, len(case.lower)))
    us = rng.integers(0, M, budget)
    xn = system.step(xs, us, rng)
    rows = []
    for k in range(steps + 1):
        m = budget * k // steps
        t0 = time.perf_counter()
        res = synthesize_from_data(_problem(case_name, np.vstack([x0, xs[:m]]), np.concatenate([u0, us[:m]]),
                                            np.vstack([xn0, xn[:m]])), progress=False, advice=False)
        rows.append({"added": m, **_classes(res), "seconds": time.perf_counter() - t0})
        print(f"  uniform seed {seed}: +{m}: Q_yes {rows[-1]['yes']} ({rows[-1]['seconds']:.1f} s)", flush=True)
    return rows


def run(case_name: str, start: int, budget: int, round_size: int, steps: int, seeds: int, n_validate: int) -> dict:
    case = get_case_study(case_name)
    system = true_system(case_name)
    x0, u0, xn0 = system.sample_dataset(start, case.lower, case.upper, np.random.default_rng(START_SEED))
    print(case_name, flush=True)
    out = {"case": case_name, "start_per_mode": start, "budget": budget, "round_size": round_size, "curves": {}}
    out["curves"]["improve"] = _improve_curve(case_name, system, x0, u0, xn0, budget, round_size, n_validate)
    for s in range(seeds):
        out["curves"][f"uniform_seed{s}"] = _uniform_curve(case, case_name, system, x0, u0, xn0, budget, steps, s)
    out["target"] = _target(out)
    return out


def _target(out: dict) -> dict:
    """The fewest improve samples reaching the uniform median Q_yes at the largest N, against N / 3."""
    uni = [v for k, v in out["curves"].items() if k.startswith("uniform")]
    N = uni[0][-1]["added"]
    goal = float(np.median([c[-1]["yes"] for c in uni]))
    reach = [r["added"] for r in out["curves"]["improve"] if r["yes"] >= goal]
    need = min(reach) if reach else None
    imp = out["curves"]["improve"][1:]
    ratio = max((r["seconds"] / max(r["bound_plus_solve"], 1e-9) for r in imp), default=None)
    # the assumption check on all data is required every round (new data may refute B): shown apart
    no_check = max(((r["seconds"] - r["parts"].get("check", 0.0)) / max(r["bound_plus_solve"], 1e-9) for r in imp),
                   default=None)
    return {"N": N, "uniform_median_yes": goal, "improve_samples_needed": need, "met": need is not None
            and need <= N / 3, "max_round_over_bound_plus_solve": ratio,
            "round_time_met": ratio is not None and ratio <= 3.0, "max_round_without_check_over_bound_plus_solve":
            no_check}


def write(outs: list, where: Path) -> None:
    where.mkdir(parents=True, exist_ok=True)
    (where / "sampling.json").write_text(json.dumps(outs, indent=1))
    lines = ["# improve (incremental) vs uniform random samples", ""]
    for out in outs:
        imp = out["curves"]["improve"]
        uni = [v for k, v in out["curves"].items() if k.startswith("uniform")]
        t = out["target"]
        lines += [f"## {out['case']}", "",
                  f"Start: {out['start_per_mode']} samples per mode; improve adds {out['budget']} in rounds of "
                  f"{out['round_size']} (incremental); uniform: whole runs, {len(uni)} seeds.", "",
                  "| added | Q_yes improve | s per round (bound + solve) | cell bounds re-bounded |", "|---|---|---|---|"]
        for r in imp:
            lines.append(f"| {r['added']} | {r['yes']} | {r['seconds']:.2f} ({r['bound_plus_solve']:.2f}) | "
                         f"{r['rebound']} |")
        lines += ["", "| added | Q_yes uniform (median, min-max) | s per whole run (median) |", "|---|---|---|"]
        for i, row in enumerate(uni[0]):
            u = [c[i]["yes"] for c in uni]
            lines.append(f"| {row['added']} | {int(np.median(u))} ({min(u)}-{max(u)}) | "
                         f"{np.median([c[i]['seconds'] for c in uni]):.1f} |")
        val = [(i, r["validation"]) for i, r in enumerate(imp) if "validation" in r]
        if val:
            lines += ["", "Monte-Carlo containment per improve round (round: flagged cells / allowed): " + ", ".join(
                f"{i}: {'pass' if v['passed'] else 'FAIL'} ({v['flagged']}/{v['allowed']})" for i, v in val)]
        lines += ["", f"Target: uniform median Q_yes at N = {t['N']}: {t['uniform_median_yes']:g}; improve reaches "
                      f"it with {t['improve_samples_needed']} samples (<= N/3 = {t['N'] / 3:g}: "
                      f"{'met' if t['met'] else 'NOT met'}). Largest round time / (bound + solve): "
                      f"{t['max_round_over_bound_plus_solve']:.2f} (<= 3: "
                      f"{'met' if t['round_time_met'] else 'NOT met'}); without the assumption check on all "
                      f"data (required each round): {t['max_round_without_check_over_bound_plus_solve']:.2f}.", ""]
    (where / "sampling.md").write_text("\n".join(lines) + "\n")
    _plot(outs, where / "sampling.png")


def _plot(outs: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(outs), figsize=(5 * len(outs), 3.5), squeeze=False)
    for ax, out in zip(axes[0], outs):
        imp = out["curves"]["improve"]
        ax.plot([r["added"] for r in imp], [r["yes"] for r in imp], "o-", label="improve (suggested)")
        for k, c in enumerate(v for key, v in out["curves"].items() if key.startswith("uniform")):
            ax.plot([r["added"] for r in c], [r["yes"] for r in c], "x--", color="grey", alpha=0.7,
                    label="uniform random" if k == 0 else None)
        ax.set_xlabel("added samples")
        ax.set_ylabel("Q_yes cells")
        ax.set_title(out["case"])
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", default=["three_mode_linear", "four_mode_nonlinear"])
    ap.add_argument("--start", type=int, default=30)
    ap.add_argument("--budget", type=int, default=90)
    ap.add_argument("--round-size", type=int, default=10)
    ap.add_argument("--uniform-steps", type=int, default=3)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--validate", type=int, default=20, help="runs per cell of each round's validation (0: none)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "sampling")
    args = ap.parse_args(argv)
    outs = [run(c, args.start, args.budget, args.round_size, args.uniform_steps, args.seeds, args.validate)
            for c in args.cases]
    write(outs, args.out)
    print((args.out / "sampling.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
