"""Where to sample next: Q_yes against added samples, suggested (``suggest_samples``) or uniform random.

    python benchmarks/sampling.py [--case three_mode_linear] [--start 30] [--budget 90] [--rounds 3]
                                  [--seeds 3] [--out benchmarks/results/sampling]

Starts from ``--start`` samples per mode of a case study (data-starved), then adds ``--budget``
samples in ``--rounds`` rounds: each round either asks :func:`robust_imdp.synthesis.suggest.suggest_samples`
for ``budget / rounds`` requests and simulates one step of the true system from each, or draws the same
number of (state, mode) pairs uniformly at random (``--seeds`` seeds). Every round re-runs the whole
pipeline (no incremental re-bounding yet) and records Q_yes / Q_no / Q_? and the wall time.
Writes ``sampling.json``, ``sampling.md`` and ``sampling.png`` into ``--out``.
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


def run(case_name: str, start: int, budget: int, rounds: int, seeds: int) -> dict:
    from robust_imdp.pipeline.run import synthesize_from_data
    from robust_imdp.synthesis.suggest import suggest_samples

    case = get_case_study(case_name)
    system = true_system(case_name)
    M = len(system.mode_names)
    x0, u0, xn0 = system.sample_dataset(start, case.lower, case.upper, np.random.default_rng(0))
    per_round = budget // rounds
    out = {"case": case_name, "start_per_mode": start, "budget": budget, "rounds": rounds, "curves": {}}

    def loop(label, pick):
        x, u, xn = x0.copy(), u0.copy(), xn0.copy()
        rng = np.random.default_rng(label[1] if isinstance(label, tuple) else 12345)
        t0 = time.perf_counter()
        res = synthesize_from_data(_problem(case_name, x, u, xn), progress=False)
        rows = [{"added": 0, **_classes(res), "seconds": time.perf_counter() - t0}]
        for _ in range(rounds):
            t0 = time.perf_counter()
            xs, us = pick(res, rng)
            xs_next = system.step(xs, us, rng)
            x, u, xn = np.vstack([x, xs]), np.concatenate([u, us]), np.vstack([xn, xs_next])
            res = synthesize_from_data(_problem(case_name, x, u, xn), progress=False)
            rows.append({"added": rows[-1]["added"] + len(us), **_classes(res), "seconds": time.perf_counter() - t0})
            print(f"{label}: +{rows[-1]['added']} samples: Q_yes {rows[-1]['yes']}  ({rows[-1]['seconds']:.1f} s)",
                  flush=True)
        return rows

    def suggested(res, rng):
        reqs = suggest_samples(res, per_round)
        names = list(res.problem.mode_names)
        return np.array([r.x for r in reqs]), np.array([names.index(r.mode) for r in reqs], dtype=np.int64)

    def uniform(res, rng):
        xs = rng.uniform(case.lower, case.upper, (per_round, len(case.lower)))
        return xs, rng.integers(0, M, per_round)

    out["curves"]["suggested"] = loop("suggested", suggested)
    for s in range(seeds):
        out["curves"][f"uniform_seed{s}"] = loop(("uniform", s), uniform)
    return out


def write(out: dict, where: Path) -> None:
    where.mkdir(parents=True, exist_ok=True)
    (where / "sampling.json").write_text(json.dumps(out, indent=1))
    sug = out["curves"]["suggested"]
    uni = [v for k, v in out["curves"].items() if k.startswith("uniform")]
    lines = [f"# Suggested vs uniform random samples: {out['case']}", "",
             f"Start: {out['start_per_mode']} samples per mode; {out['budget']} added in {out['rounds']} rounds "
             f"(whole pipeline re-run each round). Uniform: median over {len(uni)} seeds.", "",
             "| added | Q_yes suggested | Q_yes uniform (median, min-max) | s per round (suggested) |", "|---|---|---|---|"]
    for i, row in enumerate(sug):
        u = [c[i]["yes"] for c in uni]
        lines.append(f"| {row['added']} | {row['yes']} | {int(np.median(u))} ({min(u)}-{max(u)}) | {row['seconds']:.1f} |")
    (where / "sampling.md").write_text("\n".join(lines) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot([r["added"] for r in sug], [r["yes"] for r in sug], "o-", label="suggested")
    for k, c in enumerate(uni):
        ax.plot([r["added"] for r in c], [r["yes"] for r in c], "x--", color="grey", alpha=0.7,
                label="uniform random" if k == 0 else None)
    ax.set_xlabel("added samples")
    ax.set_ylabel("Q_yes cells")
    ax.set_title(out["case"])
    ax.legend()
    fig.tight_layout()
    fig.savefig(where / "sampling.png", dpi=120)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--case", default="three_mode_linear")
    ap.add_argument("--start", type=int, default=30)
    ap.add_argument("--budget", type=int, default=90)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "sampling")
    args = ap.parse_args(argv)
    out = run(args.case, args.start, args.budget, args.rounds, args.seeds)
    write(out, args.out)
    print((args.out / "sampling.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
