"""Writing a run's result: ``save_result`` (``result.json`` + ``result.npz``) on a real 64^3 result.

    python benchmarks/write_result.py [--result DIR] [--repeat 3] [--old-ref COMMIT] [--name write_result]

``DIR`` holds a ``result.json`` and ``result.npz`` written by ``robust-imdp run`` (default: the 3-D unicycle at
64^3 = 262,144 cells, 3 DFA states, 3 modes, of a ``benchmarks/serial_parts.py`` run). A stand-in for the live
``Result`` is built from them (the attributes ``result_to_dict`` reads: the partition's cells and label letters,
the DFA, the synthesis arrays, the class names, the margins, the parameters and the diagnostics), then

* **new**: this checkout's ``save_result``;
* **old**: ``save_result`` and ``jsonable`` as they were at ``--old-ref`` (read with ``git show``, so both are
  timed in the same process on the same machine state),

each ``--repeat`` times, alternating; the median wall time is reported, with the load average before and after.
Checks (the benchmark fails when one does not hold): ``json.loads`` of the new ``result.json`` equals that of the
old one and of the file in ``DIR`` (the stand-in is faithful), every array of the new ``result.npz`` equals the old
one's (dtype, shape and values, NaN where NaN), and ``load_result`` of the new file gives the same arrays as the old
``load_result`` of the old file (both timed once). Also times ``IMDP.has_floor`` (kept after its first read)
against recomputing it on every read: 2,194 reads (a 64^3 run's count) on a model of 3 * 64^3 rows.
Writes ``benchmarks/results/<name>.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path
from types import SimpleNamespace

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = HERE / "results"
DEFAULT_RESULT = Path("/tmp/sp64work/runs/unicycle_3d-all-0/out")
#: The commit before the writing was made fast (the "old" implementation).
OLD_REF = "3e7af30"
TARGET_S = 2.0

sys.path.insert(0, str(ROOT / "src"))
from robust_imdp.io import result_file as new_module  # noqa: E402
from robust_imdp.io.result_file import ResultFile, load_result  # noqa: E402


def old_module(ref: str):
    """``io/result_file.py`` at ``ref`` as a module whose ``_jsonable`` is ``jsonable.py`` at ``ref``."""
    def source(path):
        return subprocess.run(["git", "-C", str(ROOT), "show", f"{ref}:{path}"], check=True,
                              capture_output=True, text=True).stdout

    jmod = types.ModuleType("old_jsonable")
    exec(compile(source("src/robust_imdp/jsonable.py"), "old_jsonable.py", "exec"), jmod.__dict__)
    rmod = types.ModuleType("old_result_file")
    sys.modules[rmod.__name__] = rmod  # dataclasses look their module up
    exec(compile(source("src/robust_imdp/io/result_file.py"), "old_result_file.py", "exec"), rmod.__dict__)
    rmod._jsonable = jmod.jsonable
    return rmod


def stand_in(folder: Path):
    """A duck-typed ``Result`` with what ``result_to_dict`` / ``save_result`` read, from a written result."""
    doc = json.loads((folder / "result.json").read_text())
    with np.load(folder / "result.npz") as z:
        arrays = {k: z[k] for k in z.files}
    diagnostics = dict(doc["diagnostics"])
    advice, margins = diagnostics.pop("advice", None), diagnostics.pop("margins", None)
    atoms = tuple(doc["dfa"]["atoms"])
    space = doc["space"]
    n_states = len(doc["dfa"]["delta"])
    accepting = np.zeros(n_states, bool)
    accepting[doc["dfa"]["accepting"]] = True
    return SimpleNamespace(
        partition=SimpleNamespace(atoms=atoms, labels=arrays["label_letters"], cells_lower=arrays["cells_lower"],
                                  cells_upper=arrays["cells_upper"],
                                  periodic=tuple(space["periodic"]) if "periodic" in space else None),
        dfa=SimpleNamespace(atoms=atoms, initial=doc["dfa"]["initial"], accepting=accepting,
                            delta=np.asarray(doc["dfa"]["delta"])),
        synthesis=SimpleNamespace(**{k: arrays[k] for k in ("strategy", "p_low", "p_up", "p_up_star", "error")}),
        mode_names=tuple(doc["modes"]), space_lower=np.asarray(space["lower"]), space_upper=np.asarray(space["upper"]),
        dim_names=tuple(space["names"]) if "names" in space else None, class_names=arrays["classes"],
        threshold=doc["threshold"], formula=doc["formula"], horizon=doc["horizon"],
        semantics=doc.get("semantics", "reach"), problem=SimpleNamespace(inputs=None),
        b_margin=arrays.get("b_margin"), parameters=doc["parameters"], diagnostics=diagnostics, advice=advice,
        margins=margins, timings=doc["timings"])


def same_arrays(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(
        a[k].dtype == b[k].dtype and a[k].shape == b[k].shape and np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f")
        for k in a)


def file_arrays(rf: ResultFile) -> dict:
    return {k: v for k, v in vars(rf).items() if isinstance(v, np.ndarray)}


def has_floor_timing(n_rows: int = 3 * 64 ** 3, calls: int = 2194) -> dict:
    """``IMDP.has_floor`` read ``calls`` times (the count of a 64^3 run) on a model of ``n_rows`` rows (one state
    per row, listing its successor with probability 1, floor 0: every row scanned), against the expression it
    evaluated on every call before it was kept."""
    from robust_imdp.models.imdp import IMDP

    idx = np.arange(n_rows)
    m = IMDP.from_csr(np.arange(n_rows + 1), np.arange(n_rows + 1), (idx + 1) % n_rows, np.ones(n_rows),
                      np.ones(n_rows))
    t0 = time.perf_counter()
    for _ in range(calls):
        m.has_floor
    kept = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(calls):
        bool(np.any(m.floor[m.n_unlisted > 0] > 0))
    each = time.perf_counter() - t0
    return {"rows": n_rows, "calls": calls, "kept_s": kept, "recomputed_s": each}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--result", type=Path, default=DEFAULT_RESULT)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--old-ref", default=OLD_REF)
    ap.add_argument("--name", default="write_result")
    args = ap.parse_args(argv)

    result = stand_in(args.result)
    reference = json.loads((args.result / "result.json").read_text())
    old = old_module(args.old_ref)
    times = {"old": [], "new": []}
    cpu = {"old": [], "new": []}  # this process's CPU seconds: less dependent on what else runs on the machine
    load = {"before": os.getloadavg()}
    with tempfile.TemporaryDirectory(prefix="write-result-") as tmp:
        dirs = {k: Path(tmp) / k for k in times}
        for _ in range(args.repeat):
            for key, mod in (("old", old), ("new", new_module)):
                t0, c0 = time.perf_counter(), time.process_time()
                mod.save_result(result, dirs[key])
                times[key].append(time.perf_counter() - t0)
                cpu[key].append(time.process_time() - c0)
                print(f"{key}: {times[key][-1]:.2f} s, {cpu[key][-1]:.2f} CPU s (load {os.getloadavg()[0]:.2f})",
                      flush=True)
        load["after"] = os.getloadavg()
        docs = {k: json.loads((dirs[k] / "result.json").read_text()) for k in dirs}
        npz = {}
        for k in dirs:
            with np.load(dirs[k] / "result.npz") as z:
                npz[k] = {n: z[n] for n in z.files}
        t0 = time.perf_counter()
        back_new = load_result(dirs["new"])
        t_load = time.perf_counter() - t0
        t0 = time.perf_counter()
        back_old = old.load_result(dirs["old"])
        t_load_old = time.perf_counter() - t0
        sizes = {k: (dirs[k] / "result.json").stat().st_size for k in dirs}
        checks = {
            "json_new_equals_old": docs["new"] == docs["old"],
            "json_old_equals_input_file": docs["old"] == reference,
            "npz_new_equals_old": same_arrays(npz["new"], npz["old"]),
            "load_result_arrays_equal": same_arrays(file_arrays(back_new), file_arrays(back_old)),
        }
    floor = has_floor_timing()
    med = {k: statistics.median(v) for k, v in times.items()}
    med_cpu = {k: statistics.median(v) for k, v in cpu.items()}
    doc = {
        "result": str(args.result), "n_cells": int(back_new.n_cells), "old_ref": args.old_ref,
        "repeat": args.repeat, "seconds": times, "median_s": med, "cpu_seconds": cpu, "median_cpu_s": med_cpu, "speedup": med["old"] / med["new"],
        "target_s": TARGET_S, "meets_target": med["new"] <= TARGET_S,
        "load_result_new_s": t_load, "load_result_old_s": t_load_old,
        "result_json_bytes": sizes, "checks": checks, "has_floor": floor, "loadavg": load,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__},
    }
    OUT.mkdir(exist_ok=True)
    (OUT / f"{args.name}.json").write_text(json.dumps(doc, indent=1))
    md = [f"# save_result at {doc['n_cells']:,} cells (`python benchmarks/write_result.py`)", "",
          f"Result: `{args.result}`; old = `{args.old_ref}`; median of {args.repeat}, alternating; "
          f"load average before {load['before'][0]:.2f}, after {load['after'][0]:.2f} on {os.cpu_count()} CPUs.", "",
          "| implementation | median s | runs s | median CPU s | result.json MB |", "| --- | ---: | --- | ---: | ---: |"]
    for k in ("old", "new"):
        md.append(f"| {k} | {med[k]:.2f} | {', '.join(f'{t:.2f}' for t in times[k])} | {med_cpu[k]:.2f} "
                  f"| {sizes[k] / 1e6:.1f} |")
    md += ["", f"Speed-up {doc['speedup']:.1f} x; target <= {TARGET_S} s: {'met' if doc['meets_target'] else 'NOT met'}. "
           f"load_result: new file and reader {t_load:.2f} s, old file and reader {t_load_old:.2f} s.", "",
           f"IMDP.has_floor, {floor['calls']:,} reads on {floor['rows']:,} rows: {floor['kept_s']:.4f} s kept, "
           f"{floor['recomputed_s']:.2f} s recomputed on every read (before).", "",
           "Checks: " + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in checks.items()), ""]
    (OUT / f"{args.name}.md").write_text("\n".join(md))
    print("\n".join(md))
    return 0 if all(checks.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
