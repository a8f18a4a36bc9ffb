"""The benchmark suites: one entry point that runs named suites and writes their tables.

    python benchmarks/run.py --list                 # the suites, their scripts and what each writes
    python benchmarks/run.py SUITE [SUITE ...]      # run them, script after script
    python benchmarks/run.py SUITE --quick          # the scripts' small variants where they have one
    python benchmarks/run.py SUITE --dry-run        # print the commands only

Every script of a suite writes its own ``benchmarks/results/NAME.{json,md}`` (the md is the table the README
cites); this entry point runs them in order with this interpreter (``nice -n 5`` with ``--nice``), reports each
script's exit status and wall time, and goes on after a failure (exit status 1 at the end if any failed).
``make bench`` runs the ``perf`` suite (the README's Performance table). Finished one-off experiments are in
``benchmarks/archive/`` (``INDEX.md`` says what each decided); ``identical.py`` (behaviour check between two
trees) and ``mutations.py`` (the test suite's teeth) are tools with arguments of their own, not suites.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


@dataclass(frozen=True)
class Step:
    """One script run: ``args`` for the full run, ``quick`` (None: the same as ``args``) for ``--quick``."""

    script: str
    args: tuple = ()
    quick: tuple | None = None
    writes: str = ""

    def command(self, quick: bool) -> list[str]:
        args = self.quick if quick and self.quick is not None else self.args
        return [sys.executable, str(HERE / self.script), *args]


@dataclass(frozen=True)
class Suite:
    name: str
    what: str
    steps: tuple = field(default_factory=tuple)


SUITES = (
    Suite("perf", "the README's Performance table (what `make bench` runs)", (
        Step("solver.py", quick=("--quick",), writes="solver"),
        Step("parallel_sweep.py", writes="parallel_sweep"),
        Step("abstraction.py", quick=("--quick",), writes="abstraction"),
        Step("bounds.py", quick=("--quick",), writes="bounds"),
        Step("reference.py", writes="reference"),
        Step("scale.py", quick=("--cells-per-axis", "16", "--skip-speedup"), writes="scale"),
        Step("refinement.py", writes="refinement"),
    )),
    Suite("solver", "value iteration: proven brackets against Storm, sweeps, threads, the factored solver", (
        Step("solver.py", quick=("--quick",), writes="solver"),
        Step("parallel_sweep.py", writes="parallel_sweep"),
        Step("storm_check.py", quick=("--sizes", "1000", "--repeat", "1"), writes="storm_check"),
        Step("factored_solver.py", quick=("--dims", "4", "--n", "6"), writes="factored_solver"),
        Step("finite_horizon.py", quick=("--repeat", "1"), writes="finite_horizon"),
    )),
    Suite("stages", "the bound and abstraction stages alone; exact transitions against Thm 1", (
        Step("abstraction.py", quick=("--quick",), writes="abstraction"),
        Step("bounds.py", quick=("--quick",), writes="bounds"),
        Step("exact_marginals.py", quick=("--quick",), writes="exact_marginals"),
    )),
    Suite("casestudies", "the case studies against their known-dynamics references; refinement; margins", (
        Step("reference.py", writes="reference"),
        Step("refinement.py", writes="refinement"),
        Step("unicycle_known.py", quick=("--cells", "16"), writes="unicycle_known"),
        Step("vehicle_4d.py", quick=("--cells", "8"), writes="vehicle_4d"),
        Step("margins.py", writes="margins"),
        Step("tight_problems.py", writes="tight_problems"),
    )),
    Suite("newcomer", "the newcomer problems through `robust-imdp run` (the README's newcomer table)", (
        Step("newcomer.py", quick=("--only", "robot2d_16", "robot2d_32"), writes="newcomer"),
        Step("controller_quality.py", quick=("--only", "robot2d_16"), writes="controller_quality"),
    )),
    Suite("advice", "the advice's cost and its levers' estimates against real runs", (
        Step("advice_cost.py", ("--label", "after"), writes="advice_cost"),
        Step("advice_sub_boxes.py", writes="advice_sub_boxes"),
        Step("advice_local_pools.py", writes="advice_local_pools"),
    )),
    Suite("family", "the tightness family: slack over the optimum, Q_yes, the tight preset, calibration", (
        Step("family.py", quick=("--quick",), writes="family"),
        Step("tight_preset.py", writes="tight_preset"),
        Step("calibration.py", quick=("--quick",), writes="calibration"),
    )),
    Suite("sampling", "where to sample next: improve against uniform sampling (the README's sampling table)", (
        Step("sampling.py", writes="sampling/"),
    )),
    Suite("arch", "the field's benchmarks (ARCH-COMP, IMPaCT, HSCC 2025) beside the published numbers", (
        Step("arch/run.py", quick=("--quick",), writes="arch (arch_quick with --quick)"),
        Step("factored_pipeline.py", quick=("--suite", "car", "bas4d"), writes="factored_pipeline"),
        Step("input_grid_scale.py", writes="input_grid_scale"),
    )),
    Suite("scale", "large problems: chunked stages on workers, the 3-D study at 64^3, serial parts", (
        Step("scale.py", quick=("--cells-per-axis", "16", "--skip-speedup"), writes="scale"),
        Step("serial_parts.py", quick=("--unicycle-cells", "16", "--repeat", "1"), writes="serial_parts"),
    )),
    Suite("cold_start", "a fresh clone's first run against the second (numba compile, pre-flight)", (
        Step("cold_start.py", writes="cold_start"),
    )),
)
BY_NAME = {s.name: s for s in SUITES}
ALIASES = {"anchors": "arch", "case_studies": "casestudies", "cold-start": "cold_start", "bench": "perf"}


def describe() -> str:
    lines = []
    for s in SUITES:
        lines.append(f"{s.name}: {s.what}")
        for st in s.steps:
            quick = "" if st.quick is None else f"  [--quick: {' '.join(st.quick)}]"
            args = " ".join(st.args)
            lines.append(f"    benchmarks/{st.script}{' ' + args if args else ''} -> results/{st.writes}{quick}")
    lines.append(f"aliases: {', '.join(f'{k} = {v}' for k, v in ALIASES.items())}")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 epilog="suites: " + ", ".join(BY_NAME), formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("suites", nargs="*", metavar="SUITE")
    ap.add_argument("--list", action="store_true", help="list the suites and their scripts")
    ap.add_argument("--quick", action="store_true", help="the scripts' small variants where they have one")
    ap.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    ap.add_argument("--nice", action="store_true", help="run every script under nice -n 5")
    args = ap.parse_args(argv)
    if args.list or not args.suites:
        print(describe())
        return 0
    names = [ALIASES.get(s, s) for s in args.suites]
    unknown = [s for s, n in zip(args.suites, names) if n not in BY_NAME]
    if unknown:
        ap.error(f"unknown suite(s) {', '.join(unknown)}; known: {', '.join(BY_NAME)} (aliases: "
                 f"{', '.join(ALIASES)})")
    failed, seen = [], set()
    for name in names:
        for step in BY_NAME[name].steps:
            key = (step.script, step.args if not args.quick else step.quick)
            if key in seen:  # a script shared by two suites asked for together runs once
                continue
            seen.add(key)
            cmd = (["nice", "-n", "5"] if args.nice else []) + step.command(args.quick)
            print(f"[bench] {name}: {' '.join(cmd)}", flush=True)
            if args.dry_run:
                continue
            t0 = time.perf_counter()
            rc = subprocess.run(cmd, cwd=ROOT).returncode
            print(f"[bench] {name}: {step.script} exit {rc} after {time.perf_counter() - t0:.0f} s", flush=True)
            if rc != 0:
                failed.append(f"{name}/{step.script} (exit {rc})")
    if failed:
        print(f"[bench] failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
