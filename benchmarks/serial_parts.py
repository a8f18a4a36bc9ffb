"""Serial parts of a run: per-stage times on one core and on all cores, end to end through ``robust-imdp run``.

    python benchmarks/serial_parts.py [--problems reach_avoid_2d unicycle_3d] [--repeat 3]
                                      [--unicycle-cells 64] [--src SRC] [--name serial_parts]

Problems (each run in a fresh output and cache folder, figures and advice at their defaults):

* ``reach_avoid_2d``: the three-mode linear case study's problem file (``examples/problems/three_mode_linear.toml``,
  600 points, ``G !obs & F des`` at 0.95) on cells of 1/32: 128 x 128 = 16,384 cells, 3 modes;
* ``unicycle_3d``: ``robust-imdp example unicycle_3d`` (64^3 = 262,144 cells, 3 modes, 10,000 points per mode,
  local weights; ``--unicycle-cells`` another count per axis).

Two configurations, alternating, each run in its own process:

* **one core**: ``taskset -c 0``, ``NUMBA_NUM_THREADS=1``, ``--workers 1`` (everything in one process, one core);
* **all cores**: every core of this process's affinity mask, the default ``robust-imdp run`` (in process, numba
  threads on all cores, helper processes for the side work).

Per run (the child process wraps the command's functions; nothing in the library is changed): the start-up
(interpreter, imports and reading the problem, from the process start until the pipeline is entered), each stage
of ``Result.timings`` (wall and the process's CPU seconds), the pipeline's time outside its stages, the figures
(rendering or waiting for them), the writing of ``result.json`` / ``result.npz`` and the end-to-end wall time
(process start to exit), the CPU seconds of this process and of its helper processes, and the load average before
and after. The results of every run must be identical (``benchmarks/identical.py``'s digest of ``result.json``
without run-dependent fields and of every ``result.npz`` array).

The serial part of a stage is what one core adds over the ideal of the parallel stages on ``p`` cores
(Amdahl): a stage with one-core time ``T1`` and ``p``-core time ``Tp`` has ``s = (p Tp - T1) / (p - 1)`` seconds
that did not run in parallel; the run's serial part is their sum, as a share of the one-core time. Ratios are
taken per pair of consecutive runs (one core, then all cores: the same machine state), then the median.

The library's source is compiled to bytecode first (``compileall`` of the tree's ``src``, or of ``--src``), as pip
does when it installs the package: where the environment sets ``PYTHONDONTWRITEBYTECODE`` (this sandbox does), every
run would otherwise compile the library's modules from source at start-up, in this process and in every helper
(0.1 s of the 2-D run's start-up, measured).

Writes ``benchmarks/results/<name>.json`` and ``.md`` after every pair (an interrupted benchmark keeps what it
measured). The machine is shared: the load average of every run is recorded, and the CPU seconds show how much
of a core each stage got.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = HERE / "results"
#: The end-to-end speed-up on 2 cores and the serial share the issue asks for.
TARGET_SPEEDUP = 1.85
TARGET_SERIAL = 0.05
#: Rows of the table: (key, label). Stage keys are Result.timings' names; the others are measured by the child.
ROWS = [("startup", "start-up (interpreter, imports, reading the problem)"), ("specify", "specify"),
        ("partition", "partition"), ("check", "check"), ("bound", "bound"), ("abstract", "abstract"),
        ("nominal", "nominal model (beside the bound stage on several cores: the wait)"), ("synthesize", "synthesize"),
        ("advice", "advice (on several cores the margins' factors and the figures run beside it)"),
        ("margins", "margins (on several cores: the factors left when the advice ends)"),
        ("refine", "refine"),
        ("outside_stages", "pipeline outside its stages (pre-flight, diagnostics, ...)"),
        ("figures", "figures"), ("writing", "writing (result.json, result.npz, renames)")]


# ---------------------------------------------------------------------------------------------- problems
#: ``build_problem``'s assumption (not refuted by its data at lengthscale 1, with a margin) and samples per mode.
RKHS_BOUND = 6.0
N_PER_MODE = 300


def build_problem(cell: float):
    """The three-mode linear system on [-2, 2]^2 with cells of ``cell``, 300 seeded samples per mode, truncated
    Gaussian noise (sigma 0.01, bound 0.02), lengthscale 1, B = 6 (this benchmark's problem before the
    ``robust-imdp run`` problems above; ``advice_sub_boxes.py`` and ``tight_problems.py`` use it)."""
    import numpy as np

    from robust_imdp.casestudies.systems import get_case_study
    from robust_imdp.models.noise import TruncatedGaussianNoise
    from robust_imdp.models.system import AffineMap, Dataset
    from robust_imdp.pipeline.problem import Problem

    case = get_case_study("three_mode_linear")
    sysm = case.system
    sigma, bound = np.array([0.01, 0.01]), np.array([0.02, 0.02])
    rng = np.random.default_rng(7)
    u = np.repeat(np.arange(3), N_PER_MODE)
    lo, hi = np.array(case.lower), np.array(case.upper)
    x = lo + rng.random((u.size, 2)) * (hi - lo)
    from scipy.stats import truncnorm

    noise = truncnorm.rvs(-2.0, 2.0, size=(u.size, 2), random_state=rng) * sigma
    xn = np.einsum("kij,kj->ki", sysm.known_A[u], x) + sysm.known_b[u] + sysm.g(x, u) + noise
    return Problem(
        space_lower=lo, space_upper=hi, cell_size=np.array([cell, cell]), regions=case.regions,
        formula="G !obs & F des", threshold=0.95, horizon=None,
        data=Dataset(x, u, xn, modes=sysm.mode_names), mode_names=sysm.mode_names,
        maps=tuple(AffineMap.zero(2) for _ in range(3)), noise=TruncatedGaussianNoise(sigma, bound),
        rkhs_bound=RKHS_BOUND, gp_options={"lengthscale": 1.0}, misspecification=0.001)


def _write_problems(work: Path, names, reach_cells: int, unicycle_cells: int, env: dict) -> dict:
    """``{name: problem file}`` under ``work``."""
    out = {}
    if "reach_avoid_2d" in names:
        d = work / "reach_avoid_2d"
        d.mkdir(parents=True, exist_ok=True)
        src = ROOT / "examples" / "problems"
        shutil.copy(src / "three_mode_linear_data.csv", d)
        text = (src / "three_mode_linear.toml").read_text()
        size = repr(4.0 / reach_cells)
        text, n = re.subn(r"^cell_size = \[.*\]$", f"cell_size = [{size}, {size}]", text, flags=re.M)
        assert n == 1, "three_mode_linear.toml has no cell_size line"
        (d / "reach_avoid_2d.toml").write_text(text)
        out["reach_avoid_2d"] = d / "reach_avoid_2d.toml"
    if "unicycle_3d" in names:
        d = work / "unicycle_3d"
        cli = str(Path(sys.executable).parent / "robust-imdp")
        subprocess.run([cli, "example", "unicycle_3d", "--out", str(d)], check=True, env=env, stdout=subprocess.DEVNULL)
        p = d / "unicycle_3d.toml"
        if unicycle_cells != 64:
            import math

            size = [4.0 / unicycle_cells, 4.0 / unicycle_cells, 2 * math.pi / unicycle_cells]
            text = re.sub(r"^cell_size = \[.*\]$", f"cell_size = [{', '.join(repr(s) for s in size)}]",
                          p.read_text(), flags=re.M)
            p.write_text(text)
        out["unicycle_3d"] = p
    return out


# ---------------------------------------------------------------------------------------------- the child
class _CPU:
    """CPU seconds of every thread of this process and of the side lane's helper processes, attributed to the
    part of the run in progress (``bucket``): per part the total and the estimate of its wall time on ``p``
    idle cores, ``max(the busiest thread's CPU, total CPU / p)`` summed over the intervals between samples (a
    thread's work cannot be shared, and ``p`` cores do at most ``p`` seconds of work per second). Read from
    ``/proc`` (clock ticks, 10 ms); the helpers' last seconds are sampled just before their lane closes."""

    def __init__(self, p: int):
        self.p, self.bucket, self.last, self.parts = p, "startup", {}, {}
        self.tick = os.sysconf("SC_CLK_TCK")

    def _read(self) -> dict:
        out = {}
        with open("/proc/self/stat") as fh:  # the process: its live threads and those that ended
            f = fh.read().rsplit(")", 1)[1].split()
        process = (int(f[11]) + int(f[12])) / self.tick
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/stat") as fh:
                    f = fh.read().rsplit(")", 1)[1].split()
                out[("t", tid)] = (int(f[11]) + int(f[12])) / self.tick
            except OSError:  # the thread ended
                pass
        out[("p", "process")] = process
        from robust_imdp.pipeline import parallel

        for lane in list(getattr(parallel, "_LANES", [])):
            for h in lane.helpers:
                try:
                    with open(f"/proc/{h.proc.pid}/stat") as fh:
                        f = fh.read().rsplit(")", 1)[1].split()
                    out[("h", h.proc.pid)] = (int(f[11]) + int(f[12])) / self.tick
                except OSError:
                    pass
        return out

    def switch(self, bucket: str) -> None:
        now = self._read()
        keys = [k for k in now if k[0] != "p"]
        deltas = [max(0.0, now[k] - self.last.get(k, 0.0)) for k in keys]
        # threads that ended since the last sample (a pool's threads, their numba threads): the process's CPU not
        # in its live threads' deltas, as one more thread
        ended = max(0.0, now[("p", "process")] - self.last.get(("p", "process"), 0.0)
                    - sum(d for k, d in zip(keys, deltas) if k[0] == "t"))
        keys.append(("t", "ended"))
        deltas.append(ended)
        self.last.update(now)
        part = self.parts.setdefault(self.bucket, {"cpu": 0.0, "cpu_main_process": 0.0, "wall_estimate": 0.0})
        total = sum(deltas)
        part["cpu"] += total
        part["cpu_main_process"] += sum(d for k, d in zip(keys, deltas) if k[0] == "t")
        part["wall_estimate"] += max(max(deltas, default=0.0), total / self.p)
        self.bucket = bucket


def child(args) -> int:
    """One ``robust-imdp run`` in this process, timed; writes the timings under ``args.child``."""
    t_enter = time.time()
    c_enter = time.process_time()
    marks: dict = {}
    cpu = _CPU(len(os.sched_getaffinity(0)))
    import robust_imdp.cli as cli
    from robust_imdp.pipeline import parallel, runtime

    stage_cpu: dict = {}
    original_stage = runtime._Log.stage
    depth = [0]

    def stage(self, name):
        inner = original_stage(self, name)

        class _Timed:
            def __enter__(self_):
                self_.c = time.process_time()
                depth[0] += 1
                if depth[0] == 1:  # a stage inside a stage (the advice's solves) belongs to the outer one
                    cpu.switch(name)
                return inner.__enter__()

            def __exit__(self_, *exc):
                stage_cpu[name] = stage_cpu.get(name, 0.0) + time.process_time() - self_.c
                depth[0] -= 1
                if depth[0] == 0:
                    cpu.switch("outside_stages")
                return inner.__exit__(*exc)

        return _Timed()

    runtime._Log.stage = stage
    if hasattr(parallel, "SideLane"):
        original_close = parallel.SideLane.close

        def close(self, *a, **kw):
            cpu.switch(cpu.bucket)  # the helpers' last CPU seconds, before they exit
            return original_close(self, *a, **kw)

        parallel.SideLane.close = close
    import robust_imdp.io.files as files
    import robust_imdp.pipeline.run as run_module

    def timed(module, attr, key, bucket, after):
        fn = getattr(module, attr)

        def wrapper(*a, **kw):
            t0, c0 = time.time(), time.process_time()
            cpu.switch(bucket)
            try:
                return fn(*a, **kw)
            finally:
                cpu.switch(after)
                marks.setdefault(key, []).append((t0, time.time(), time.process_time() - c0))

        setattr(module, attr, wrapper)

    timed(run_module, "synthesize_from_data", "run", "outside_stages", "figures")
    timed(files, "save_result", "save_result", "writing", "figures")
    results = {}

    def keep(fn):
        def wrapper(*a, **kw):
            res = fn(*a, **kw)
            results["timings"] = dict(res.timings)
            return res

        return wrapper

    run_module.synthesize_from_data = keep(run_module.synthesize_from_data)
    argv = ["run", str(args.problem), "--out", str(args.out), "--quiet"] + (["--workers", "1"] if args.config == "one" else [])
    rc = cli.main(argv)
    t_exit = time.time()
    cpu.switch("end")
    import resource

    (r0, r1, c_run), = marks["run"]
    (w0, w1, c_write), = marks["save_result"]
    timings = results["timings"]
    stages = {k: float(v) for k, v in timings.items() if k != "total"}
    doc = {"rc": rc, "config": args.config, "t_enter": t_enter, "t_exit": t_exit,
           "startup_in_process_s": r0 - t_enter, "run_s": r1 - r0, "after_run_s": t_exit - r1,
           "writing_s": w1 - w0, "figures_and_rest_s": (t_exit - r1) - (w1 - w0),
           "stages": stages, "stage_cpu": stage_cpu, "cpu_s": time.process_time() - c_enter, "cpu_run_s": c_run,
           "cpu_writing_s": c_write, "cpu_parts": cpu.parts, "cores": cpu.p,
           "children_cpu_s": sum(getattr(resource.getrusage(resource.RUSAGE_CHILDREN), f) for f in ("ru_utime", "ru_stime"))}
    Path(args.child).write_text(json.dumps(doc, indent=1))
    # the process ends as the console script does (cli.console_main; a tree before it: the interpreter's exit)
    getattr(cli, "end_process", sys.exit)(int(rc))
    return int(rc)


def _run_one(config: str, problem: Path, run_dir: Path, env: dict, cores: list) -> dict:
    """One child run; the parent adds the wall time from the process start and the loads."""
    env = dict(env)
    if config == "one":
        env["NUMBA_NUM_THREADS"] = "1"
        prefix = ["taskset", "-c", str(cores[0])]
    else:
        env.pop("NUMBA_NUM_THREADS", None)
        prefix = ["taskset", "-c", ",".join(str(c) for c in cores)]
    shutil.rmtree(run_dir, ignore_errors=True)
    run_dir.mkdir(parents=True)
    rec = run_dir / "timings.json"
    cmd = prefix + [sys.executable, str(Path(__file__).resolve()), "--child", str(rec), "--config", config,
                    "--problem", str(problem), "--out", str(run_dir / "out")]
    load0 = os.getloadavg()
    t0 = time.time()
    p = subprocess.run(cmd, env=env, cwd=problem.parent, capture_output=True, text=True)
    t1 = time.time()
    load1 = os.getloadavg()
    if p.returncode != 0 or not rec.exists():
        raise RuntimeError(f"{config} run of {problem.name} failed ({p.returncode}):\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}")
    doc = json.loads(rec.read_text())
    doc["wall_s"] = t1 - t0
    doc["startup_s"] = doc["t_enter"] - t0 + doc["startup_in_process_s"]  # interpreter + imports + reading
    doc["load_before"], doc["load_after"] = load0, load1
    sys.path.insert(0, str(HERE))
    from identical import _drop, _strip, digest

    doc["digest"] = digest(run_dir / "out")
    # the advice runs within a share of the run's time, so which levers it estimates depends on the machine's
    # speed (a lever beyond the budget is "not estimated"): the results compared also without it
    kept = _strip(json.loads((run_dir / "out" / "result.json").read_text()), "", [])
    _drop(kept, "diagnostics.advice")
    import hashlib

    doc["digest_without_advice"] = hashlib.sha256(json.dumps(kept, sort_keys=True).encode()).hexdigest()
    doc["result_json"] = str(run_dir / "out" / "result.json")
    return doc


def _first_difference(docs: list) -> str | None:
    """The first result.json key (without run fields and the advice) where a run differs from the first one."""
    sys.path.insert(0, str(HERE))
    from identical import _drop, _first_difference as first, _strip

    def load(d):
        j = _strip(json.loads(Path(d["result_json"]).read_text()), "", [])
        _drop(j, "diagnostics.advice")
        return j

    try:
        ref = load(docs[0])
        for d in docs[1:]:
            if d["digest_without_advice"] != docs[0]["digest_without_advice"]:
                return first(ref, load(d))
    except (OSError, KeyError):  # a run's output is gone (another work folder)
        return "unknown (outputs removed)"
    return None


# ---------------------------------------------------------------------------------------------- summary
def _median(v):
    v = sorted(v)
    k = len(v)
    return float("nan") if k == 0 else (v[k // 2] if k % 2 else 0.5 * (v[k // 2 - 1] + v[k // 2]))


def _parts(doc: dict) -> dict:
    """The table's rows of one run (seconds of wall time)."""
    st = doc["stages"]
    known = {k for k, _ in ROWS}
    out = {"startup": doc["startup_s"], "figures": doc["figures_and_rest_s"], "writing": doc["writing_s"]}
    for k, v in st.items():
        out[k if k in known else "outside_stages"] = out.get(k if k in known else "outside_stages", 0.0) + v
    out["outside_stages"] = out.get("outside_stages", 0.0) + doc["run_s"] - sum(st.values())
    out["total"] = doc["wall_s"]
    return out


def _estimate(pairs, p: int) -> dict:
    """From the CPU seconds (``_CPU``): per part the one-core run's CPU (its wall time on an idle core) and the
    all-cores run's wall estimate on ``p`` idle cores; medians over the pairs, and the per-pair speed-up and
    serial share (``(p T_p - T_1) / (p - 1)`` per part, summed, over the one-core total)."""
    pairs = [(a, b) for a, b in pairs if "cpu_parts" in a and "cpu_parts" in b]
    if not pairs:
        return {}
    known = {k for k, _ in ROWS}

    def folded(parts: dict, field: str) -> dict:  # a stage without a row of its own (e.g. load_abstraction) counts
        out: dict = {}                            # as the pipeline outside its stages, as in _parts
        for k, v in parts.items():
            key = k if k in known else "outside_stages"
            out[key] = out.get(key, 0.0) + v.get(field, 0.0)
        return out

    ones_ = [folded(a["cpu_parts"], "cpu") for a, _ in pairs]
    alls_ = [folded(b["cpu_parts"], "wall_estimate") for _, b in pairs]
    keys = [k for k, _ in ROWS if any(k in x or k in y for x, y in zip(ones_, alls_))]
    one = [{k: x.get(k, 0.0) for k in keys} for x in ones_]
    all_ = [{k: y.get(k, 0.0) for k in keys} for y in alls_]
    ratio = [sum(x.values()) / sum(y.values()) for x, y in zip(one, all_)]
    by_rows = [sum(max(0.0, (p * y[k] - x[k]) / (p - 1)) for k in keys) / sum(x.values()) for x, y in zip(one, all_)]
    # Amdahl's serial share of the whole run, from its totals: (p T_p / T_1 - 1) / (p - 1). The sum over rows
    # above clips each row's negative part to zero, so work run beside another stage (the check and the nominal
    # model beside the bound stage, the margins beside the advice) is charged to that stage: it overstates.
    serial = [(p * sum(y.values()) / sum(x.values()) - 1) / (p - 1) for x, y in zip(one, all_)]
    return {"rows": {k: {"one": _median([x[k] for x in one]), "all": _median([y[k] for y in all_])} for k in keys},
            "total": {"one": _median([sum(x.values()) for x in one]), "all": _median([sum(y.values()) for y in all_])},
            "ratio_per_pair": ratio, "ratio": _median(ratio), "serial_share_per_pair": serial,
            "serial_share": _median(serial), "serial_share_by_rows": _median(by_rows), "n_pairs": len(pairs)}


def summarise(runs: dict, p: int) -> dict:
    """Per problem: median wall per row and configuration, per-pair ratios, serial parts, identity."""
    out = {}
    for name, pairs in runs.items():
        ones = [_parts(a) for a, _ in pairs]
        alls = [_parts(b) for _, b in pairs]
        keys = [k for k, _ in ROWS if any(k in d for d in ones + alls)] + ["total"]
        med = {k: {"one": _median([d.get(k, 0.0) for d in ones]), "all": _median([d.get(k, 0.0) for d in alls])}
               for k in keys}
        ratio = [a["total"] / b["total"] for a, b in zip(ones, alls)]
        serial = [sum(max(0.0, (p * b.get(k, 0.0) - a.get(k, 0.0)) / (p - 1)) for k in keys if k != "total") / a["total"]
                  for a, b in zip(ones, alls)] if p > 1 else []
        amdahl = [(p * b["total"] / a["total"] - 1) / (p - 1) for a, b in zip(ones, alls)] if p > 1 else []
        digests = [json.dumps(d["digest"]["json"]) + json.dumps(d["digest"]["npz"], sort_keys=True)
                   for pair in pairs for d in pair]
        without = [d["digest_without_advice"] + json.dumps(d["digest"]["npz"], sort_keys=True)
                   for pair in pairs for d in pair]
        est = _estimate(pairs, p)
        out[name] = {"estimate": est, "rows": med, "ratio_per_pair": ratio, "ratio": _median(ratio),
                     "serial_share_per_pair": serial, "serial_share": _median(serial),
                     "amdahl_share_per_pair": amdahl, "amdahl_share": _median(amdahl),
                     "identical": len(set(digests)) == 1, "identical_without_advice": len(set(without)) == 1,
                     "first_difference_without_advice": _first_difference([d for pair in pairs for d in pair]),
                     "n_pairs": len(pairs),
                     "cpu": {"one": _median([a["cpu_s"] + a["children_cpu_s"] for a, _ in pairs]),
                             "all": _median([b["cpu_s"] + b["children_cpu_s"] for _, b in pairs]),
                             "all_helpers": _median([b["children_cpu_s"] for _, b in pairs])},
                     "stage_cpu": {c: {k: _median([d[i]["stage_cpu"].get(k, 0.0) for d in pairs])
                                       for k in pairs[0][i]["stage_cpu"]} for i, c in enumerate(("one", "all"))},
                     "loads": [[pair[0]["load_before"][0], pair[1]["load_after"][0]] for pair in pairs]}
    return out


def _table(rows: dict, total: dict, p: int) -> list:
    lines = ["| part | one core s | all cores s | speed-up | serial part s |", "|---|---|---|---|---|"]
    for k, label in ROWS:
        if k in rows:
            a, b = rows[k]["one"], rows[k]["all"]
            ser = max(0.0, (p * b - a) / (p - 1)) if p > 1 else float("nan")
            lines.append(f"| {label} | {a:.2f} | {b:.2f} | {a / b if b > 0 else float('nan'):.2f} | {ser:.2f} |")
    a, b = total["one"], total["all"]
    return lines + [f"| **end to end** | {a:.2f} | {b:.2f} | {a / b if b > 0 else float('nan'):.2f} | |"]


def write_md(doc: dict, path: Path) -> None:
    p = doc["machine"]["cores_used"]
    lines = [f"# Serial parts of a run (`benchmarks/serial_parts.py`)", "",
             f"{doc['machine']['date']}; {doc['machine']['cores']} cores, {p} used; python {doc['machine']['python']}; "
             f"source `{doc['src']}`. {doc['note']}", "",
             f"One core: `taskset -c 0`, `NUMBA_NUM_THREADS=1`, `--workers 1`; all cores: the default `robust-imdp "
             f"run` on {p} cores; each a fresh process, output and cache, alternating (one core, then all cores). A "
             f"part's serial part is `(p T_p - T_1) / (p - 1)`, what did not run in parallel; their sum over the "
             f"one-core time is the run's serial share.", "",
             f"Two tables per problem. **Estimated for {p} idle cores** (load-independent): every thread's and "
             f"helper's CPU seconds are sampled at each stage boundary; one core = the one-core run's CPU seconds; "
             f"all cores = per interval between samples max(the busiest thread or helper, CPU / {p}), summed (a "
             f"lower bound of the wall time on idle cores, reached when nothing waits). **Measured** wall seconds on "
             f"the shared machine, with its 1-minute load average: above {p}, and with the kernel's per-session "
             f"fair share (autogroup), a run's threads do not get the cores, so its wall times say little about "
             f"cores."]
    for name, s in doc["summary"].items():
        lines += ["", f"## {name}: {doc['problems'][name]}", ""]
        est = s.get("estimate") or {}
        if est:
            lines += [f"**Estimated for {p} idle cores** (medians of {est['n_pairs']} pairs):", ""]
            lines += _table(est["rows"], est["total"], p)
            lines += ["", f"Estimated speed-up **{est['ratio']:.2f}x** (per pair "
                          f"{', '.join(f'{r:.2f}' for r in est['ratio_per_pair'])}; target >= {TARGET_SPEEDUP}x on 2 "
                          f"cores); serial part **{100 * est['serial_share']:.1f} %** of the one-core time, Amdahl's "
                          f"`(p T_p / T_1 - 1) / (p - 1)` of the totals (per pair "
                          f"{', '.join(f'{100 * v:.1f}' for v in est['serial_share_per_pair'])} %; target <= "
                          f"{100 * TARGET_SERIAL:.0f} %)"
                          + (f"; the rows' serial parts add up to {100 * est['serial_share_by_rows']:.1f} % (a row's "
                             "negative part counts as 0, so work run beside another stage is charged to that stage)"
                             if "serial_share_by_rows" in est else "") + ".", ""]
        lines += [f"**Measured** wall seconds (medians of {s['n_pairs']} pairs):", ""]
        lines += _table({k: v for k, v in s["rows"].items() if k != "total"}, s["rows"]["total"], p)
        lines += ["",
                  f"Measured speed-up {s['ratio']:.2f}x (per pair {', '.join(f'{r:.2f}' for r in s['ratio_per_pair'])}); "
                  + (f"serial part {100 * s['amdahl_share']:.1f} % of the one-core time, Amdahl's on the totals (per "
                     f"pair {', '.join(f'{100 * v:.1f}' for v in s['amdahl_share_per_pair'])} %); the rows' serial "
                     f"parts add up to {100 * s['serial_share']:.1f} % (per pair "
                     f"{', '.join(f'{100 * v:.1f}' for v in s['serial_share_per_pair'])} %; a row's negative part "
                     "counts as 0). " if "amdahl_share" in s else
                     f"serial part {100 * s['serial_share']:.1f} % (per pair "
                     f"{', '.join(f'{100 * v:.1f}' for v in s['serial_share_per_pair'])} %). ")
                  + f"Load average before / after "
                  f"each pair: {'; '.join(f'{a:.1f} / {b:.1f}' for a, b in s['loads'])}.", "",
                  f"Identical results (result.json without run fields, every result.npz array) in all "
                  f"{2 * s['n_pairs']} runs: **{s['identical']}**; without `diagnostics.advice` (which levers the "
                  f"advice estimates within its time budget depends on the machine's speed): "
                  f"**{s['identical_without_advice']}**"
                  + (f" (first difference: `{s['first_difference_without_advice']}`)"
                     if s.get("first_difference_without_advice") else "") + ". CPU seconds (this process + helpers): one core "
                  f"{s['cpu']['one']:.1f}, all cores {s['cpu']['all']:.1f} (helpers {s['cpu']['all_helpers']:.1f})."]
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--problems", nargs="+", default=["reach_avoid_2d", "unicycle_3d"],
                    choices=["reach_avoid_2d", "unicycle_3d"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--reach-cells", type=int, default=128, help="cells per axis of reach_avoid_2d")
    ap.add_argument("--unicycle-cells", type=int, default=64, help="cells per axis of unicycle_3d")
    ap.add_argument("--src", help="another tree's src, first on PYTHONPATH (e.g. the tree before a change)")
    ap.add_argument("--name", default="serial_parts", help="results file name (benchmarks/results/NAME.json, .md)")
    ap.add_argument("--note", default="", help="a line for the table (what the tree is)")
    ap.add_argument("--work", default=None, help="where the runs' outputs go (default: a temporary folder)")
    ap.add_argument("--append", action="store_true", help="add the pairs to those of benchmarks/results/NAME.json")
    ap.add_argument("--render", nargs=2, metavar=("JSON", "MD"), help="write the md of a saved json only")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--config", help=argparse.SUPPRESS)
    ap.add_argument("--problem", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.render:
        write_md(json.loads(Path(args.render[0]).read_text()), Path(args.render[1]))
        return 0
    if args.child:
        return child(args)
    import tempfile

    env = dict(os.environ)
    if args.src:
        env["PYTHONPATH"] = str(Path(args.src).resolve()) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    # bytecode as an installed package has it (the module docstring): Python reads .pyc files also where the
    # environment keeps it from writing them
    import compileall

    compileall.compile_dir(str(Path(args.src).resolve() if args.src else ROOT / "src"), quiet=1)
    cores = sorted(os.sched_getaffinity(0))
    work = Path(args.work or tempfile.mkdtemp(prefix="serial_parts-"))
    probs = _write_problems(work / "problems", args.problems, args.reach_cells, args.unicycle_cells, env)
    desc = {"reach_avoid_2d": f"three_mode_linear.toml (600 points, lengthscale 2, B = 6) on cells of 4/{args.reach_cells}: "
                              f"{args.reach_cells ** 2:,} cells x 3 modes, `G !obs & F des` at 0.95",
            "unicycle_3d": f"`robust-imdp example unicycle_3d` at {args.unicycle_cells}^3 = {args.unicycle_cells ** 3:,} "
                           "cells x 3 modes, 10,000 points per mode, local weights (50 points)"}
    runs: dict = {name: [] for name in probs}
    if args.append and (OUT / f"{args.name}.json").exists():  # more pairs for an earlier record (same tree)
        for name, pairs in json.loads((OUT / f"{args.name}.json").read_text())["runs"].items():
            runs.setdefault(name, [])[:0] = pairs
    doc = {}
    for r in range(args.repeat):
        for name, prob in probs.items():
            pair = []
            for config in ("one", "all"):
                d = _run_one(config, prob, work / "runs" / f"{name}-{config}-{len(runs[name])}", env, cores)
                pair.append(d)
                print(f"{name} {config} #{len(runs[name])}: {d['wall_s']:.1f} s (load {d['load_before'][0]:.1f} -> "
                      f"{d['load_after'][0]:.1f}) stages {json.dumps({k: round(v, 1) for k, v in d['stages'].items()})}",
                      flush=True)
            runs[name].append(pair)
            doc = {"src": args.src or str(ROOT / "src"), "note": args.note,
                   "problems": {n: desc[n] for n in runs if runs[n]},
                   "machine": {"python": platform.python_version(), "cores": os.cpu_count(), "cores_used": len(cores),
                               "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())},
                   "summary": summarise({n: v for n, v in runs.items() if v}, len(cores)), "runs": runs}
            OUT.mkdir(exist_ok=True)
            (OUT / f"{args.name}.json").write_text(json.dumps(doc, indent=1, default=float))
            write_md(doc, OUT / f"{args.name}.md")
    for name, s in doc["summary"].items():
        print(f"{name}: speed-up {s['ratio']:.2f}x, serial part (Amdahl) {100 * s.get('amdahl_share', float('nan')):.1f} %, "
              f"rows {100 * s['serial_share']:.1f} %, identical {s['identical']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
