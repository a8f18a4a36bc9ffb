"""The 4-D planar vehicle (p_x, p_y, theta, v): known kinematics, periodic heading, learned drag.

Case study ``vehicle_4d`` (``robust_imdp.casestudies.vehicle``): modes accelerate / brake / left /
right; the kinematics, heading update and the known part of the speed update are ``[modes.NAME] f``
expressions, the heading is periodic, ``p_x, p_y, theta`` are known components (B = 0) and only the
drag ``-c_d v |v|`` on ``v`` is learned. Spec: ``G !obs & F goal``, threshold 0.9.

Rows, per grid of ``k^4`` cells (``--cells``):

* **reference** -- the exact image boxes of the true system (``VehicleSystem.image_bounds``) through our
  own abstraction on the same periodic grid, then the same synthesis: the best a learned bound can reach.
* **learned** -- ``synthesize_from_data`` on the problem file and data ``write_problem_files`` writes;
  stage times (check, bound, abstraction, synthesis), IMDP size (stored transitions ``nnz`` and the bytes
  of its arrays, ``IMDP.memory_bytes``), and a Monte-Carlo check (``validate``) on ``--mc-cells`` random
  cells x ``--n-per-cell`` runs.
* **learned_iid** -- the same with ``iid_noise = true`` (``--rows``; not in the default rows).

Every row runs in its own process, so its peak RSS (``resource.getrusage``) is its own. The load
average (``os.getloadavg``) is recorded before and after each row. Writes
``benchmarks/results/vehicle_4d.json`` and ``.md``.

Usage: ``python benchmarks/vehicle_4d.py [--cells 8 16] [--rows reference learned] [--mc-cells 1000]``
(``--render`` re-writes the markdown from the JSON, ``--merge`` adds rows to the existing JSON.)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# one BLAS thread: the machine has 2 cores shared by other jobs (oversubscription is slower)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
OUT = HERE / "results"
ROWS = ("reference", "learned", "learned_iid")
#: the stages whose per-cell cost is projected (Result.timings keys)
STAGES = ("check", "bound", "abstract", "synthesize")


def _counts(p_low, p_up, threshold) -> dict:
    """Classes by definition (paper, Sec. 5): yes iff p_low >= t, no iff p_up < t."""
    p_low, p_up = np.asarray(p_low), np.asarray(p_up)
    yes = p_low >= threshold
    no = (p_up < threshold) & ~yes
    return {"yes": int(yes.sum()), "no": int(no.sum()), "maybe": int((~yes & ~no).sum())}


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _imdp_size(imdp) -> dict:
    nnz, nbytes = int(imdp.nnz), int(imdp.memory_bytes)
    return {"n_states": int(imdp.n_states), "n_choices": int(imdp.n_choices), "stored_transitions": nnz,
            "imdp_bytes": nbytes, "bytes_per_transition": nbytes / max(nnz, 1)}


def _goal_cells(partition) -> int:
    bit = 1 << list(partition.atoms).index("goal")
    return int(np.count_nonzero(np.asarray(partition.labels) & bit))


def _reference(problem) -> dict:
    """Exact image boxes of the true vehicle through our abstraction, on the problem's periodic grid."""
    from robust_imdp.abstraction import rows as abstraction
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.casestudies.vehicle import VEHICLE
    from robust_imdp.models.geometry import Box, Partition, Region
    from robust_imdp.spec.dfa import ltlf_to_dfa
    from robust_imdp.synthesis.core import synthesize

    times = {}
    t = time.perf_counter()
    regions = [Region(k, [Box(lo, up) for lo, up in v]) for k, v in problem.regions.items()]
    part = Partition(Box(problem.space_lower, problem.space_upper), problem.cell_size, regions,
                     periodic=problem.periodic)
    lo, hi = VEHICLE.image_bounds(part.cells_lower, part.cells_upper)
    times["bound"] = time.perf_counter() - t
    t = time.perf_counter()
    abstr = abstraction.abstract(part, CellBounds(lo, hi, None), problem.noise, None, eta=problem.eta,
                                 eps_rule=problem.eps_rule, combine=problem.combine)
    times["abstract"] = time.perf_counter() - t
    t = time.perf_counter()
    syn = synthesize(abstr.imdp, part.labels, part.atoms, ltlf_to_dfa(problem.formula), threshold=problem.threshold,
                     horizon=problem.horizon, outside_state=part.outside_state)
    times["synthesize"] = time.perf_counter() - t
    return {"counts": _counts(syn.p_low, syn.p_up, problem.threshold), "stage_times_s": times,
            "imdp": _imdp_size(abstr.imdp), "goal_cells": _goal_cells(part)}


def _learned(problem, mc_cells: int, n_per_cell: int, seed: int) -> dict:
    from robust_imdp.casestudies.vehicle import VEHICLE
    from robust_imdp.pipeline.run import synthesize_from_data
    from robust_imdp.validate import validate

    result = synthesize_from_data(problem, progress=False)
    row = {"counts": _counts(result.synthesis.p_low, result.synthesis.p_up, problem.threshold),
           "stage_times_s": {k: float(v) for k, v in result.timings.items()},
           "imdp": _imdp_size(result.abstraction.imdp), "goal_cells": _goal_cells(result.partition)}
    eps = result.diagnostics.get("eps") if isinstance(result.diagnostics, dict) else None
    if eps is not None:
        row["eps"] = eps
    if mc_cells > 0 and n_per_cell > 0:
        n = result.partition.n_cells
        cells = np.sort(np.random.default_rng(seed).choice(n, size=min(mc_cells, n), replace=False))
        t = time.perf_counter()
        rep = validate(result, VEHICLE, n_per_cell=n_per_cell, max_steps=200, rng=seed, cells=cells)
        row["monte_carlo"] = {"cells": int(len(cells)), "n_per_cell": n_per_cell, "flagged": int(len(rep.outside)),
                              "allowed": int(rep.allowed_outside), "passed": bool(rep.passed),
                              "containment_rate": float(rep.containment_rate),
                              "time_s": time.perf_counter() - t}
    return row


def load_vehicle_problem(directory, seed: int = 0):
    """The case study's problem (problem file + data written into ``directory``) as a ``Problem``."""
    from robust_imdp.casestudies.systems import CaseStudy, problem_toml
    from robust_imdp.casestudies.vehicle import VEHICLE, VEHICLE_CASE
    from robust_imdp.io.files import load_problem, write_data_file
    from robust_imdp.models.geometry import wrap_points

    case = CaseStudy(system=VEHICLE, **VEHICLE_CASE)
    directory = Path(directory)
    x, u, x_next = VEHICLE.sample_dataset(case.n_per_mode, case.lower, case.upper, seed)
    x_next = wrap_points(x_next, np.asarray(case.lower, float), np.asarray(case.upper, float), case.periodic)
    data_name = f"{case.name}_data.{case.data_format}"
    write_data_file(directory / data_name, x, u, x_next, modes=VEHICLE.mode_names)
    path = directory / f"{case.name}.toml"
    path.write_text(problem_toml(case, case.formulas[0], data_name))
    return load_problem(path)


def run_row(name: str, k: int, mc_cells: int, n_per_cell: int, seed: int, warm: bool = True) -> dict:
    """One row in this process: the case study's problem at k^4 cells, run and timed (after a 4^4 warm-up:
    a kernel file edited since the numba cache was written would otherwise put its compile time into a stage)."""
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as d:  # load_problem reads the data into memory
        problem = load_vehicle_problem(d, seed)
    if name == "learned_iid":  # the noise i.i.d. across samples: averaging shrinks the noise term (confidence bound)
        problem = problem.replace(iid_noise=True)
    span = problem.space_upper - problem.space_lower
    t = time.perf_counter()
    if warm:  # the same stages on 4^4 cells first: numba kernels compiled / loaded before the timed run
        small = problem.replace(cell_size=span / 4)
        _reference(small) if name == "reference" else _learned(small, 0, 0, seed)
    warm_s = time.perf_counter() - t
    problem = problem.replace(cell_size=span / k)
    t = time.perf_counter()
    row = _reference(problem) if name == "reference" else _learned(problem, mc_cells, n_per_cell, seed)
    row["warm_up_s"] = warm_s
    row["iid_noise"] = bool(problem.iid_noise)
    row.update(name=name, cells_per_axis=k, n_cells=k ** 4, time_s=time.perf_counter() - t,
               peak_rss_mb=_peak_rss_mb(), load_before=list(load0), load_after=list(os.getloadavg()))
    return row


def _subprocess_row(name: str, k: int, args) -> dict:
    cmd = [sys.executable, __file__, "--one", name, "--cells", str(k), "--mc-cells", str(args.mc_cells),
           "--n-per-cell", str(args.n_per_cell), "--seed", str(args.seed)] + (["--no-warm"] if args.no_warm else [])
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"name": name, "cells_per_axis": k, "error": proc.stderr.strip().splitlines()[-5:]}
    row = json.loads(proc.stdout.strip().splitlines()[-1])
    row["end_to_end_s"] = time.perf_counter() - t  # process start, imports, data, warm-up, run, validation
    return row


def _ratios(rows: list) -> None:
    by = {(r["name"], r["cells_per_axis"]): r for r in rows}
    for r in rows:
        ref = by.get(("reference", r["cells_per_axis"]))
        if r["name"] != "reference" and ref and "counts" in r and "counts" in ref and ref["counts"]["yes"]:
            r["fraction_of_reference_yes"] = r["counts"]["yes"] / ref["counts"]["yes"]
            extra_ref = ref["counts"]["yes"] - ref["goal_cells"]
            if extra_ref > 0:  # the part of Q_yes that needs control: cells outside the goal
                r["fraction_of_reference_yes_outside_goal"] = (r["counts"]["yes"] - r["goal_cells"]) / extra_ref


def projection(rows: list, targets=(20, 30), workers=(1, 2, 16, 64)) -> list:
    """Per-cell cost of each stage of the largest learned row, scaled to ``targets`` cells per axis.

    The per-cell costs are those of this machine (2 cores, numba threads on both), so one "worker"
    below is one such 2-core machine. Linear in the number of cells for the bound and abstraction
    stages (independent per cell, so they split over Dask workers); the check (per mode and component,
    on the data) does not grow with the grid; the solve is taken as linear in the stored transitions
    times the grid's diameter (value-iteration sweeps x iterations) and is not split (one process).
    Transitions per cell are taken from the measured row: a lower estimate, since an image spans more
    cells of a finer grid (the cell shrinks, the image's spread from heading and speed does not).
    """
    learned = [r for r in rows if r.get("name") == "learned" and "stage_times_s" in r and "error" not in r]
    if not learned:
        return []
    r = max(learned, key=lambda r: r["n_cells"])
    n = r["n_cells"]
    per_cell = {s: r["stage_times_s"].get(s, 0.0) / n for s in STAGES}
    tr_per_cell = r["imdp"]["stored_transitions"] / n
    out = []
    for k in targets:
        m = k ** 4
        # the finer grid: fewer successors per row (images span fewer cells) is not assumed
        base = {s: per_cell[s] * m for s in STAGES}
        base["check"] = r["stage_times_s"].get("check", 0.0)  # on the data, not on the cells
        scale = k / r["cells_per_axis"]  # value iteration: iterations ~ grid diameter
        base["synthesize"] *= scale
        entry = {"cells_per_axis": k, "n_cells": m, "from_cells_per_axis": r["cells_per_axis"],
                 "per_cell_s": per_cell, "stored_transitions": tr_per_cell * m,
                 "imdp_gb": tr_per_cell * m * r["imdp"]["bytes_per_transition"] / 1e9, "by_workers": {}}
        for w in workers:
            entry["by_workers"][str(w)] = {
                "check_s": base["check"], "bound_s": base["bound"] / w, "abstraction_s": base["abstract"] / w,
                "synthesis_s": base["synthesize"],
                "total_s": base["check"] + (base["bound"] + base["abstract"]) / w + base["synthesize"]}
        out.append(entry)
    return out


def write_md(path: Path, data: dict) -> None:
    lines = ["# The 4-D vehicle: known kinematics, periodic heading, only the drag learned", "",
             "`benchmarks/vehicle_4d.py`, case study `vehicle_4d` (`robust_imdp.casestudies.vehicle`): modes "
             "accelerate / brake / left / right; `f` = kinematics, heading and known speed update as expressions, "
             "heading periodic, `rkhs_bound = [0, 0, 0, B]` (only the drag `-c_d v|v|` learned, lengthscale "
             "`[100, 100, 100, 0.5]`); `G !obs & F goal`, threshold 0.9. **reference**: the exact image boxes of the "
             "true system through our abstraction on the same periodic grid. Every row in its own process (peak RSS "
             "its own); load = `os.getloadavg()` 1-min before / after the row. Each row first runs the same stages on "
             "4^4 cells (warm-up: numba kernels loaded or compiled; its seconds are in the JSON as `warm_up_s` and in "
             "'end to end', not in 'run').", "",
             f"Machine: {data['machine']}. Commit: {data.get('commit')}.", "",
             "| grid | row | Q_yes | (goal cells) | Q_no | Q_? | / reference | outside goal / ref | run s | end to end s "
             "| check / bound / abstraction / synthesis s | transitions | B / transition | peak RSS MB | load | "
             "Monte Carlo |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in data["rows"]:
        if "error" in r:
            lines.append(f"| {r['cells_per_axis']}^4 | {r['name']} | error: {' '.join(r['error'])[:300]} |"
                         + " |" * 13)
            continue
        c, st, im = r["counts"], r["stage_times_s"], r["imdp"]
        frac = r.get("fraction_of_reference_yes")
        frac_out = r.get("fraction_of_reference_yes_outside_goal")
        mc = r.get("monte_carlo")
        mc_text = (f"{mc['flagged']} of {mc['cells']} cells x {mc['n_per_cell']} flagged (allowed {mc['allowed']}): "
                   f"{'passed' if mc['passed'] else 'FAILED'}") if mc else ""
        stages = " / ".join(f"{st[s]:.1f}" if s in st else "-" for s in STAGES)
        lines.append(
            f"| {r['cells_per_axis']}^4 | {r['name']} | {c['yes']:,} | {r['goal_cells']:,} | {c['no']:,} | "
            f"{c['maybe']:,} | {'' if frac is None else f'{frac:.3f}'} | "
            f"{'' if frac_out is None else f'{frac_out:.3f}'} | {r['time_s']:.1f} | "
            f"{r.get('end_to_end_s', 0):.1f} | {stages} | {im['stored_transitions']:,} | "
            f"{im['bytes_per_transition']:.1f} | {r['peak_rss_mb']:.0f} | "
            f"{r['load_before'][0]:.1f} / {r['load_after'][0]:.1f} | {mc_text} |")
    proj = data.get("projection") or []
    if proj:
        lines += ["", f"## Projection (from the measured per-cell costs of the {proj[0]['from_cells_per_axis']}^4 "
                  "learned row)", "",
                  "A worker is one 2-core machine like this one (the per-cell costs were measured with numba threads on "
                  "both cores). Bound and abstraction split over Dask workers (independent per cell); the check (on the "
                  "data) and the solve (one process; scaled by transitions x grid diameter) do not. Transitions per "
                  "cell as measured: a lower estimate, since an image spans more cells of a finer grid.", "",
                  "| grid | cells | transitions | IMDP GB | workers | check s | bound s | abstraction s | solve s | total s |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for e in proj:
            for w, v in e["by_workers"].items():
                lines.append(f"| {e['cells_per_axis']}^4 | {e['n_cells']:,} | {e['stored_transitions']:.3g} | "
                             f"{e['imdp_gb']:.2f} | {w} | {v['check_s']:.0f} | {v['bound_s']:.0f} | "
                             f"{v['abstraction_s']:.0f} | {v['synthesis_s']:.0f} | {v['total_s']:.0f} |")
    lines += ["", "Targets (issue 21, item 5): 16^4 cells (aim 20^4), end to end <= 15 min and <= 12 GB peak RSS on "
              "2 cores; Q_yes >= 0.7 x its reference; Monte-Carlo containment; <= 40 B per stored transition.", ""]
    lines += [f"* {note}" for note in data.get("notes", [])] + ([""] if data.get("notes") else [])
    path.write_text("\n".join(lines))


def _git_commit():
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=HERE.parent).stdout.strip() or None
    except OSError:
        return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", type=int, nargs="+", default=[16, 20], help="cells per axis (grids k^4)")
    ap.add_argument("--rows", nargs="+", default=["reference", "learned"], choices=ROWS)
    ap.add_argument("--mc-cells", type=int, default=1000, help="cells of the Monte-Carlo check (0: none)")
    ap.add_argument("--n-per-cell", type=int, default=4, help="Monte-Carlo runs per cell")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-warm", action="store_true", help="no 4^4 warm-up before each row (compile time counts)")
    ap.add_argument("--one", choices=ROWS, help=argparse.SUPPRESS)  # a single row, JSON on stdout
    ap.add_argument("--out", type=Path, default=OUT / "vehicle_4d")
    ap.add_argument("--merge", action="store_true", help="add the rows to the existing JSON (same grid + row replaced)")
    ap.add_argument("--render", action="store_true", help="only re-write the markdown from the JSON")
    ap.add_argument("--note", action="append", default=[], help="a note for the markdown (repeatable)")
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(run_row(args.one, args.cells[0], args.mc_cells, args.n_per_cell, args.seed,
                                 warm=not args.no_warm)))
        return 0
    json_path = args.out.with_suffix(".json")
    if args.render:
        data = json.loads(json_path.read_text())
        data["notes"] = data.get("notes", []) + args.note
    else:
        rows = []
        for k in args.cells:
            for name in args.rows:
                row = _subprocess_row(name, k, args)
                rows.append(row)
                print(json.dumps({key: row.get(key) for key in ("name", "cells_per_axis", "counts", "time_s",
                                                                "end_to_end_s", "peak_rss_mb", "monte_carlo", "error",
                                                                "stage_times_s", "imdp")}), flush=True)
        old = json.loads(json_path.read_text()) if args.merge and json_path.exists() else {"rows": [], "notes": []}
        keys = {(r["name"], r["cells_per_axis"]) for r in rows}
        merged = [r for r in old["rows"] if (r["name"], r["cells_per_axis"]) not in keys] + rows
        merged.sort(key=lambda r: (r["cells_per_axis"], ROWS.index(r["name"])))
        data = {"machine": f"{platform.platform()}, {os.cpu_count()} cores, Python {platform.python_version()}",
                "commit": _git_commit(), "rows": merged, "notes": old.get("notes", []) + args.note}
    _ratios(data["rows"])
    data["projection"] = projection(data["rows"])
    json_path.write_text(json.dumps(data, indent=1) + "\n")
    write_md(args.out.with_suffix(".md"), data)
    print(args.out.with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
