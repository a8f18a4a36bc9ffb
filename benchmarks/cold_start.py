"""The first run in a fresh clone against the second: numba compile time and the pre-flight estimate.

    python benchmarks/cold_start.py [--repo /work/main] [--shared ../shared] [--runs 1]

Per run, in a new temporary folder: ``git clone`` of ``--repo`` (its committed HEAD) with a copy
of the shared folder beside it (``make demo`` is run as a new user would), then

1. ``make venv`` (timed: the install step, with its numba warm-up where the Makefile has one);
2. the newcomer problem ``robot2d_32.toml`` (data from ``robot2d_data.py`` in a temp folder),
   ``robust-imdp run`` twice: cold (first run after the install) and warm;
3. numba's cache files are deleted and the install's warm-up (``python -m robust_imdp.warmup``,
   if the clone has it) is run again, so the kernels are as ``make venv`` leaves them; then
   ``make demo`` twice: cold and warm (its ``results/`` removed in between: the demo would reuse
   its abstraction cache and skip the stages measured here).

Read from each run's output: the pipeline time and stage times (``stage times: ...``), the bound
stage's pre-flight estimate ("about X s on N cores") and the end-to-end time; and the numba
cache files that the run wrote (kernels compiled during the run, not loaded). Medians over
``--runs``. Writes ``benchmarks/results/cold_start.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "results"
NEWCOMER = "robot2d_32.toml"


def sh(cmd, cwd, env=None):
    """Run ``cmd`` (list) in ``cwd``; returns (seconds, merged stdout+stderr). Raises on failure."""
    t0 = time.perf_counter()
    p = subprocess.run(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    dt = time.perf_counter() - t0
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, cmd))} in {cwd} exited {p.returncode}:\n{p.stdout[-4000:]}")
    return dt, p.stdout


def cache_files(clone: Path) -> dict:
    """{numba cache file: (mtime_ns, size)} of the package's kernels."""
    d = clone / "src" / "robust_imdp" / "__pycache__"
    return {f.name: (f.stat().st_mtime_ns, f.stat().st_size) for f in d.glob("*.nb[ic]")} if d.exists() else {}


def parse(text: str) -> dict:
    """Pipeline and stage times, the bound pre-flight estimate, end-to-end time of one run's output."""
    out = {}
    m = re.search(r"^stage times: (.*)$", text, flags=re.M)
    if m:
        stages = dict((k, float(v)) for k, v in re.findall(r"(\w+) ([\d.]+) s", m.group(1)))
        out["stages"] = stages
        out["pipeline_s"] = stages.get("total")
    m = re.search(r"pre-flight: .* cell bounds; about (\d+) s of work.*about (\d+) s on (\d+) core", text)
    if m:
        out["preflight_bound_s"] = float(m.group(2))
    m = re.search(r"numba compiled the bound kernels in (\d+) s", text)
    if m:
        out["preflight_compile_s"] = float(m.group(1))
    m = re.search(r"\(([\d.]+) s end to end\)", text)
    if m:
        out["end_to_end_s"] = float(m.group(1))
    return out


def timed_run(cmd, cwd, clone, env) -> dict:
    before = cache_files(clone)
    wall, text = sh(cmd, cwd, env)
    after = cache_files(clone)
    res = parse(text)
    res["wall_s"] = round(wall, 2)
    res["cache_files_written"] = sorted(k for k, v in after.items() if before.get(k) != v)
    res["kernels_compiled"] = len([k for k in res["cache_files_written"] if k.endswith(".nbi")])
    if "preflight_bound_s" in res and "stages" in res and res["stages"].get("bound"):
        res["preflight_ratio"] = round(res["preflight_bound_s"] / res["stages"]["bound"], 3)
    return res


def one_run(repo: Path, shared: Path) -> dict:
    with tempfile.TemporaryDirectory(prefix="cold-start-") as tmp:
        tmp = Path(tmp)
        clone = tmp / "p"
        subprocess.run(["git", "clone", "-q", str(repo), str(clone)], check=True)
        shutil.copytree(shared, tmp / "shared")
        env = dict(os.environ, MPLBACKEND="Agg")
        env.pop("PYTHONPATH", None)
        env.pop("NUMBA_CACHE_DIR", None)
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=clone, capture_output=True, text=True,
                                check=True).stdout.strip()
        install_s, install_log = sh(["make", "venv"], clone, env)
        rec = {"commit": commit, "install_s": round(install_s, 1),
               "install_kernels_cached": len([k for k in cache_files(clone) if k.endswith(".nbi")]),
               "loadavg_start": os.getloadavg()[0]}
        py = clone / ".venv" / "bin" / "python"
        # the newcomer problem, first after the install
        work = tmp / "newcomer"
        work.mkdir()
        shutil.copy(tmp / "shared" / "newcomer" / NEWCOMER, work)
        sh([str(py), str(tmp / "shared" / "newcomer" / "robot2d_data.py")], work, env)
        cli = [str(clone / ".venv" / "bin" / "robust-imdp"), "run", NEWCOMER]
        rec["newcomer_cold"] = timed_run(cli + ["--out", "out1"], work, clone, env)
        rec["newcomer_warm"] = timed_run(cli + ["--out", "out2"], work, clone, env)
        # back to the state make venv leaves: no cached kernels, then the install's warm-up (if any)
        for f in (clone / "src" / "robust_imdp" / "__pycache__").glob("*.nb[ic]"):
            f.unlink()
        if (clone / "src" / "robust_imdp" / "warmup.py").exists():
            w, _ = sh([str(py), "-m", "robust_imdp.warmup", "--quiet"], clone, env)
            rec["warmup_s"] = round(w, 1)
        rec["demo_cold"] = timed_run(["make", "demo"], clone, clone, env)
        # the demo reuses its abstraction cache (results/three_mode_linear/cache): without it the
        # second run computes everything again, like the first, with the kernels cached
        shutil.rmtree(clone / "results")
        rec["demo_warm"] = timed_run(["make", "demo"], clone, clone, env)
        rec["loadavg_end"] = os.getloadavg()[0]
        for what in ("demo", "newcomer"):
            c, w = rec[f"{what}_cold"].get("pipeline_s"), rec[f"{what}_warm"].get("pipeline_s")
            rec[f"{what}_cold_over_warm"] = round(c / w, 3) if c and w else None
        return rec


def med(runs, *path):
    vals = []
    for r in runs:
        v = r
        for p in path:
            v = v.get(p) if isinstance(v, dict) else None
        if isinstance(v, (int, float)):
            vals.append(v)
    return round(statistics.median(vals), 3) if vals else None


def table(runs) -> str:
    rows = [("install (make venv)", med(runs, "install_s"), ""),
            ("warm-up (re-run of the install's)", med(runs, "warmup_s"), "")]
    lines = ["| quantity | demo (three_mode_linear) | newcomer (robot2d_32) |", "|---|---|---|"]
    for k, v, _ in rows:
        lines.append(f"| {k} | {v} s | |")
    for label, key in (("pipeline cold (s)", ("_cold", "pipeline_s")), ("pipeline warm (s)", ("_warm", "pipeline_s")),
                       ("bound stage cold (s)", ("_cold", "stages", "bound")),
                       ("bound stage warm (s)", ("_warm", "stages", "bound")),
                       ("synthesize cold (s)", ("_cold", "stages", "synthesize")),
                       ("synthesize warm (s)", ("_warm", "stages", "synthesize")),
                       ("pre-flight bound estimate cold (s)", ("_cold", "preflight_bound_s")),
                       ("pre-flight bound estimate warm (s)", ("_warm", "preflight_bound_s")),
                       ("estimate / actual, cold", ("_cold", "preflight_ratio")),
                       ("estimate / actual, warm", ("_warm", "preflight_ratio")),
                       ("kernels compiled during the cold run", ("_cold", "kernels_compiled")),
                       ("end to end cold (s)", ("_cold", "end_to_end_s"))):
        vals = [med(runs, what + key[0], *key[1:]) for what in ("demo", "newcomer")]
        lines.append(f"| {label} | {vals[0]} | {vals[1]} |")
    lines.append(f"| cold / warm pipeline | {med(runs, 'demo_cold_over_warm')} | {med(runs, 'newcomer_cold_over_warm')} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", type=Path, default=HERE.parent)
    ap.add_argument("--shared", type=Path, default=HERE.parent.parent / "shared")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--label", default="", help="a note stored with the results (e.g. 'before the warm-up')")
    args = ap.parse_args(argv)
    runs = []
    for i in range(args.runs):
        runs.append(one_run(args.repo.resolve(), args.shared.resolve()))
        print(json.dumps(runs[-1], indent=1), flush=True)
    OUT.mkdir(exist_ok=True)
    doc = {"label": args.label, "cores": os.cpu_count(), "runs": runs}
    (OUT / "cold_start.json").write_text(json.dumps(doc, indent=1) + "\n")
    md = (f"# Cold start: fresh clone, first run vs second ({args.label or 'no label'})\n\n"
          f"Commit {runs[0]['commit']}, {os.cpu_count()} cores, load average {runs[0]['loadavg_start']:.1f} at the "
          f"start and {runs[-1]['loadavg_end']:.1f} at the end (shared machine); medians of {len(runs)} run(s).\n\n"
          + table(runs) + "\n")
    (OUT / "cold_start.md").write_text(md)
    print(md)


if __name__ == "__main__":
    sys.exit(main())
