"""Scale: chunked stages on 1 and 2 workers, the 3-D case study at 64^3, and a projection (issue 10).

    python benchmarks/scale.py [--cells-per-axis 64] [--skip-speedup] [--skip-3d]

1. **Speed-up.** The bound and abstraction stages of one problem (four-mode nonlinear on a
   0.0625 grid: 4,096 cells) with ``workers=1`` (in process, one core) and ``workers=2`` (a
   local Dask cluster of two single-threaded processes), in the same run; the cluster's start-up
   is reported separately. The results must be identical (the chunked stages are pure).
2. **3-D case study** (``unicycle_3d``) at ``--cells-per-axis``^3 cells: end-to-end time on all
   local cores, stage times, peak resident memory of the process (``ru_maxrss``), and the
   measured cost per cell of the bound stage.
3. **Projection** of 10^6 and 10^7 cells on 32 and 128 workers from the measured per-cell costs
   (bound stage parallel over workers; abstraction chunks parallel too; the product solve on one
   machine).

Writes ``benchmarks/results/scale.json`` and ``.md``. Runs under ``if __name__ == "__main__"``
(a local Dask cluster re-imports the main module in its workers).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "results"


def _machine() -> dict:
    return {"python": platform.python_version(), "platform": platform.platform(), "cores": os.cpu_count(),
            "load_average": os.getloadavg(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "note": os.environ.get("BENCH_NOTE", "")}


def _stage_seconds(res) -> dict:
    return {k: round(float(v), 3) for k, v in res.timings.items()}


def speedup(repeat: int = 3) -> dict:
    import dask
    from distributed import Client, LocalCluster

    from robust_imdp.io.files import load_problem, result_to_dict
    from robust_imdp.pipeline.parallel import LOCAL_PROFILER_KEY
    from robust_imdp.pipeline.run import synthesize_from_data

    problem = load_problem(HERE.parent / "examples" / "problems" / "four_mode_nonlinear.toml").replace(
        cell_size=np.array([0.0625, 0.0625]))
    warm = problem.replace(cell_size=np.array([0.25, 0.25]))
    out = {"problem": "four_mode_nonlinear at cell 0.0625 (4,096 cells x 4 modes x 2 outputs); both configurations "
                      "warmed up by the same problem on a 64-cell grid first (imports, numba's cached kernels); "
                      f"{repeat} alternating runs each, medians"}
    docs = set()
    runs = {1: [], 2: []}
    t0 = time.perf_counter()
    # the cluster that `--workers 2` starts (robust_imdp.pipeline.parallel.open_scheduler)
    with dask.config.set({LOCAL_PROFILER_KEY: False}), \
            LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                         silence_logs=40) as cluster, Client(cluster) as client:
        startup = time.perf_counter() - t0
        synthesize_from_data(warm, progress=False, workers=1)
        synthesize_from_data(warm, progress=False, client=client)
        for _ in range(repeat):
            for workers in (1, 2):
                kw = {"workers": 1} if workers == 1 else {"client": client}
                res = synthesize_from_data(problem, progress=False, **kw)
                t = res.timings
                runs[workers].append({"bound_s": t.get("bound"), "abstract_s": t.get("abstract"),
                                      "bound_plus_abstract_s": t.get("bound", 0) + t.get("abstract", 0),
                                      "stages": _stage_seconds(res)})
                doc = result_to_dict(res)
                doc.pop("timings")
                docs.add(json.dumps(doc, sort_keys=True))
                print(workers, runs[workers][-1]["bound_plus_abstract_s"], flush=True)
    for workers in (1, 2):
        rs = runs[workers]
        out[f"workers_{workers}"] = {k: float(np.median([r[k] for r in rs]))
                                     for k in ("bound_s", "abstract_s", "bound_plus_abstract_s")}
        out[f"workers_{workers}"]["cluster_startup_s"] = startup if workers == 2 else 0.0
        out[f"workers_{workers}"]["runs"] = rs
    out["identical_results"] = len(docs) == 1
    out["speedup_bound_plus_abstract"] = (out["workers_1"]["bound_plus_abstract_s"]
                                          / out["workers_2"]["bound_plus_abstract_s"])
    out["speedup_per_run"] = [a["bound_plus_abstract_s"] / b["bound_plus_abstract_s"] for a, b in zip(runs[1], runs[2])]
    return out


def three_d(cells_per_axis: int) -> dict:
    from robust_imdp.casestudies.systems import write_problem_files
    from robust_imdp.io.files import load_problem
    from robust_imdp.pipeline.preflight import estimate_resources
    from robust_imdp.pipeline.run import synthesize_from_data

    with tempfile.TemporaryDirectory() as d:
        problem = load_problem(write_problem_files("unicycle_3d", d))
        problem = problem.replace(cell_size=(problem.space_upper - problem.space_lower) / cells_per_axis)
        est = estimate_resources(problem, 3)
        t0 = time.perf_counter()
        res = synthesize_from_data(problem, progress=True)
        total = time.perf_counter() - t0
    n = res.partition.n_cells
    M = len(res.mode_names)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    out = {"cells": n, "modes": M, "outputs": 3, "total_s": total, "stages": _stage_seconds(res),
           "peak_rss_bytes": rss, "estimated_bytes": est["bytes"], "counts": res.counts(),
           "successors_per_row": res.diagnostics.get("successors_per_row"),
           "eps": res.diagnostics.get("eps"), "imdp_entries": int(res.abstraction.imdp.col.size),
           "bound_s_per_cell_mode": res.timings.get("bound", float("nan")) / (n * M),
           "abstract_s_per_cell_mode": res.timings.get("abstract", float("nan")) / (n * M),
           "synthesize_s_per_cell": res.timings.get("synthesize", float("nan")) / n,
           "threads": os.cpu_count()}
    print(out, flush=True)
    return out


def projection(cost: dict) -> list:
    """Wall time of the bound + abstraction stages (parallel) and the solve (one machine)."""
    rows = []
    cores = cost.get("threads") or 2
    for cells in (10 ** 6, 10 ** 7):
        for workers in (32, 128):
            par = (cost["bound_s_per_cell_mode"] + cost["abstract_s_per_cell_mode"]) * cost["modes"] * cells * cores
            solve = cost["synthesize_s_per_cell"] * cells
            mem = cost["peak_rss_bytes"] / cost["cells"] * cells
            rows.append({"cells": cells, "workers": workers, "parallel_stages_s": par / workers,
                         "solve_s_one_machine": solve, "total_s": par / workers + solve,
                         "client_memory_gb": mem / 1e9})
    return rows


def _kept(data: dict, part: str) -> list:
    """A line naming the earlier run a section was kept from (``--skip-speedup`` / ``--skip-3d``)."""
    kept = data.get("kept_from_earlier_run", {}).get(part)
    if not kept:
        return []
    flag = "--skip-speedup" if part == "speedup" else "--skip-3d"
    return [f"(From the earlier run of {kept.get('date')}, load average "
            f"{tuple(round(v, 1) for v in kept.get('load_average', ()))}: {kept.get('note', '')}; "
            f"not re-run with `{flag}`.)", ""]


def write_md(data: dict) -> None:
    m = data["machine"]
    lines = ["# Scale (`benchmarks/scale.py`)", "",
             f"{m['cores']} cores, load average {tuple(round(v, 1) for v in m['load_average'])} at the start; {m['date']}; "
             f"python {m['python']}. {m['note']}", ""]
    sp = data.get("speedup")
    if sp:
        w1, w2 = sp["workers_1"], sp["workers_2"]
        lines += ["## Bound + abstraction stages, 1 worker against 2 (same run)", "", *_kept(data, "speedup"),
                  sp["problem"], "",
                  "| workers | bound s | abstract s | bound + abstract s | cluster start-up s |", "|---|---|---|---|---|",
                  f"| 1 (in process) | {w1['bound_s']:.2f} | {w1['abstract_s']:.2f} | {w1['bound_plus_abstract_s']:.2f} | - |",
                  f"| 2 (LocalCluster) | {w2['bound_s']:.2f} | {w2['abstract_s']:.2f} | {w2['bound_plus_abstract_s']:.2f} | "
                  f"{w2['cluster_startup_s']:.1f} |", "",
                  f"Speed-up {sp['speedup_bound_plus_abstract']:.2f}x (ratio of the medians; per run: "
                  f"{', '.join(f'{x:.2f}' for x in sp.get('speedup_per_run', []))}); identical results: "
                  f"{sp['identical_results']}.", ""]
    td = data.get("three_d")
    if td:
        lines += ["## 3-D case study (`unicycle_3d`)", "", *_kept(data, "three_d"),
                  f"{td['cells']:,} cells x {td['modes']} modes x 3 outputs, all local cores in process: "
                  f"**{td['total_s']:.0f} s** end to end, peak memory **{td['peak_rss_bytes'] / 1e9:.2f} GB** "
                  f"(pre-flight estimate {td['estimated_bytes'] / 1e9:.2f} GB); {td['imdp_entries']:,} IMDP entries, "
                  f"{td['successors_per_row']:.1f} successors per row; classes {td['counts']}.", "",
                  "| stage | seconds |", "|---|---|"]
        lines += [f"| {k} | {v:.1f} |" for k, v in td["stages"].items()]
        lines += ["", f"Per cell and mode: bound {td['bound_s_per_cell_mode'] * 1e3:.3f} ms, abstraction "
                  f"{td['abstract_s_per_cell_mode'] * 1e3:.3f} ms; solve {td['synthesize_s_per_cell'] * 1e3:.3f} ms per cell "
                  "(wall time on this machine's cores).", ""]
    pj = data.get("projection")
    if pj:
        lines += ["## Projection (from the measured per-cell costs)", "",
                  "| cells | workers | bound + abstraction s | solve s (one machine) | total | client memory GB |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {r['cells']:.0e} | {r['workers']} | {r['parallel_stages_s']:.0f} | {r['solve_s_one_machine']:.0f} | "
                  f"{r['total_s'] / 60:.1f} min | {r['client_memory_gb']:.1f} |" for r in pj]
    (OUT / "scale.md").write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells-per-axis", type=int, default=64)
    ap.add_argument("--skip-speedup", action="store_true")
    ap.add_argument("--skip-3d", action="store_true")
    args = ap.parse_args(argv)
    data = {"machine": _machine()}
    old = OUT / "scale.json"
    if (args.skip_speedup or args.skip_3d) and old.exists():
        # keep the part that is not re-run (its own machine record goes with it)
        prev = json.loads(old.read_text())
        for k in (["speedup"] if args.skip_speedup else []) + (["three_d", "projection"] if args.skip_3d else []):
            if k in prev:
                data[k] = prev[k]
                data.setdefault("kept_from_earlier_run", {})[k] = (prev.get("kept_from_earlier_run", {}).get(k)
                                                                   or prev.get("machine", {}))
    if not args.skip_speedup:
        data["speedup"] = speedup()
    if not args.skip_3d:
        data["three_d"] = three_d(args.cells_per_axis)
        data["projection"] = projection(data["three_d"])
    OUT.mkdir(exist_ok=True)
    (OUT / "scale.json").write_text(json.dumps(data, indent=1, default=float))
    write_md(data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
