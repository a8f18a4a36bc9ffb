"""The ``robust-imdp`` command.

    robust-imdp run PROBLEM.toml --out DIR        synthesize; write DIR/result.json, result.npz, figures
    robust-imdp simulate DIR --true-system NAME   Monte-Carlo validation of DIR's result on a true system
    robust-imdp example NAME --out DIR            write a case study's problem file and data

Errors (bad files, unknown regions, ...) print one message and exit with status 1; usage errors
exit with status 2 (argparse); unexpected internal errors exit with status 3. No traceback is
shown unless ``--debug`` is given.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from robust_imdp.errors import RobustImdpError

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="robust-imdp",
        description="Formally guaranteed switching controllers from data (GP learning, "
                    "interval-MDP abstraction, LTLf synthesis).",
    )
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    run = sub.add_parser("run", help="synthesize a controller from a TOML problem file",
                         description="Learn, bound, abstract and synthesize; write result.json, "
                                     "result.npz and PNG figures into --out.")
    run.add_argument("problem", type=Path, help="TOML problem file")
    run.add_argument("--out", type=Path, required=True, help="output directory")
    run.add_argument("--cache", type=Path, default=None,
                     help="abstraction cache directory (default: OUT/cache); reused when only "
                          "the formula, threshold or horizon changes")
    run.add_argument("--formula", default=None, help="override [spec].formula")
    run.add_argument("--threshold", type=float, default=None, help="override [spec].threshold")
    run.add_argument("--no-figures", action="store_true", help="do not write PNG figures")
    run.add_argument("--quiet", action="store_true", help="no progress lines")
    run.add_argument("--workers", type=int, default=None,
                     help="local cores: 1 = in this process on one core, N > 1 = a local Dask cluster "
                          "of N processes (default: this process, numba threads on all cores)")
    run.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="run the bound and abstraction stages on a running Dask cluster "
                          "(e.g. tcp://host:8786)")
    run.add_argument("--yes", action="store_true",
                     help="run even when the pre-flight estimate says the run does not fit the machine")

    sim = sub.add_parser("simulate", help="validate a result by simulating a true system",
                         description="Simulate the true system under the result's controller "
                                     "from random states in every cell and compare the "
                                     "empirical satisfaction with [p_low, p_up] (Wilson "
                                     "intervals). Writes validation.json and trajectories.png.")
    sim.add_argument("result", type=Path, help="directory holding result.json")
    sim.add_argument("--true-system", required=True,
                     help="case study whose true dynamics to simulate "
                          "(three_mode_linear, four_mode_nonlinear)")
    sim.add_argument("--n-per-cell", type=int, default=50, help="runs per cell (default 50)")
    sim.add_argument("--max-steps", type=int, default=100, help="step cap per run (default 100)")
    sim.add_argument("--confidence", type=float, default=0.999, help="Wilson confidence (0.999)")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sim.add_argument("--paths", type=int, default=20, help="trajectories to draw (default 20)")
    sim.add_argument("--no-figures", action="store_true", help="do not write trajectories.png")

    ex = sub.add_parser("example", help="write a case study's problem file and data",
                        description="Generate the data of a paper case study with a fixed seed "
                                    "and write NAME.toml + NAME_data.csv into --out.")
    ex.add_argument("name", help="three_mode_linear or four_mode_nonlinear")
    ex.add_argument("--out", type=Path, required=True, help="output directory")
    ex.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ex.add_argument("--formula", default=None, help="formula (default: the case study's first)")
    return p


def _cmd_run(args) -> int:
    from robust_imdp.io import load_problem, save_result
    from robust_imdp.pipeline import synthesize_from_data

    out: Path = args.out
    # A stale complete-looking result must not survive a failed run.
    for name in ("result.json", "result.npz"):
        (out / name).unlink(missing_ok=True)
    problem = load_problem(args.problem)
    changes = {}
    if args.formula is not None:
        changes["formula"] = args.formula
    if args.threshold is not None:
        changes["threshold"] = args.threshold
    if changes:
        problem = problem.replace(**changes)
    cache = args.cache if args.cache is not None else out / "cache"
    args.interrupt_note = (f"interrupted; the finished chunks are saved in {cache}: run the same command again "
                           "to resume")
    result = synthesize_from_data(problem, progress=not args.quiet, abstraction_cache=cache,
                                  workers=args.workers, scheduler=args.scheduler, check_resources=not args.yes)
    figures = not args.no_figures and len(problem.space_lower) == 2  # plots are 2-D only
    if figures:
        from robust_imdp.plotting import save_figures

        save_figures(result, out)
    path = save_result(result, out)
    print(result.summary())
    print(f"wrote {path}" + (f" and figures in {out}" if figures else " (no figures)"))
    return 0


def _cmd_simulate(args) -> int:
    import numpy as np

    from robust_imdp.casestudies import true_system
    from robust_imdp.io import load_result
    from robust_imdp.jsonable import jsonable
    from robust_imdp.validate import simulate, validate

    res = load_result(args.result)
    system = true_system(args.true_system)
    report = validate(res, system, n_per_cell=args.n_per_cell, max_steps=args.max_steps,
                      rng=args.seed, confidence=args.confidence)
    print(report.summary())
    out = Path(args.result)
    doc = {k: getattr(report, k) for k in (
        "cells", "n_per_cell", "max_steps", "confidence", "satisfied", "capped", "empirical",
        "wilson_low", "wilson_up", "p_low", "p_up", "outside", "containment_rate",
        "expected_outside")}
    (out / "validation.json").write_text(json.dumps(jsonable(doc), indent=1))
    if not args.no_figures and args.paths > 0 and len(res.space_lower) == 2:
        from robust_imdp.plotting import plot_trajectories
        import matplotlib.pyplot as plt

        rng = np.random.default_rng(args.seed + 1)
        x0 = res.space_lower + rng.random((args.paths, len(res.space_lower))) * (
            res.space_upper - res.space_lower)
        tr = simulate(res, system, x0, max_steps=args.max_steps, rng=rng, record=True)
        fig, ax = plt.subplots(figsize=(5.6, 5.6), constrained_layout=True)
        plot_trajectories(res, tr, ax)
        fig.savefig(out / "trajectories.png", dpi=130)
        plt.close(fig)
    return 0


def _cmd_example(args) -> int:
    from robust_imdp.casestudies import write_problem_files

    path = write_problem_files(args.name, args.out, seed=args.seed, formula=args.formula)
    print(f"wrote {path} and its data file")
    return 0


def main(argv=None) -> int:
    """Entry point of ``robust-imdp``; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        return {"run": _cmd_run, "simulate": _cmd_simulate, "example": _cmd_example}[
            args.command](args)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print(f"robust-imdp: {getattr(args, 'interrupt_note', 'interrupted')}", file=sys.stderr)
        return 130
    except (RobustImdpError, ValueError, OSError, KeyError) as exc:
        if type(exc).__name__ == "KilledWorker":  # distributed: a worker was lost for good
            print(f"robust-imdp: a Dask worker was lost ({exc}); "
                  f"{getattr(args, 'interrupt_note', 'interrupted')}", file=sys.stderr)
            return 130
        if args.debug:
            raise
        msg = str(exc) if not isinstance(exc, KeyError) else f"missing entry {exc}"
        if isinstance(exc, OSError) and getattr(exc, "filename", None):
            msg = f"{exc.strerror}: {exc.filename}"
        print(f"robust-imdp: error: {msg}", file=sys.stderr)
        return 1
    except Exception as exc:  # a bug, not bad input: still no traceback unless --debug
        if args.debug:
            raise
        print(f"robust-imdp: internal error ({type(exc).__name__}: {exc}); please report it, "
              "and rerun with --debug for the traceback", file=sys.stderr)
        return 3


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
