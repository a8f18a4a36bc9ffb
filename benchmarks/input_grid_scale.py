"""Input grids at scale: the 2-D robot reach-avoid (441 inputs x 1,600 cells) and BAS-4D (4 inputs x 1,225 cells).

    python benchmarks/input_grid_scale.py [--repeat 3]

Measures, per problem of ``benchmarks/arch/problems``: loading the problem file (parsing, the grid, the load-time
domain check of ``f(x, u)`` over every (mode, cell) box), the known-dynamics bound stage
(``pipeline.bound_stage.known_cell_bounds``), and its images (``known_images``: one vectorised pass over every
(mode, cell) box) against the same images computed mode by mode (``InputMode.image_bounds`` in a Python loop:
what a per-mode stage would do). The two give the same arrays (checked). Best of ``--repeat`` runs; results in benchmarks/results/input_grid_scale.json
and .md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PROBLEMS = ROOT / "benchmarks" / "arch" / "problems"
OUT = ROOT / "benchmarks" / "results"


def _best(fn, repeat):
    best, value = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        value = fn()
        best = min(best, time.perf_counter() - t0)
    return best, value


def measure(name: str, repeat: int) -> dict:
    from robust_imdp.io.problem_file import load_problem
    from robust_imdp.models.geometry import Box, Partition
    from robust_imdp.pipeline.bound_stage import known_cell_bounds, known_images
    from robust_imdp.pipeline.preflight import _region_objects

    load_s, p = _best(lambda: load_problem(PROBLEMS / name), repeat)
    part = Partition(Box(p.space_lower, p.space_upper), p.cell_size, _region_objects(p))
    lo, hi = part.cells_lower, part.cells_upper
    stage_s, _ = _best(lambda: known_cell_bounds(p, lo, hi), repeat)
    vec_s, together = _best(lambda: known_images(p.maps, lo, hi), repeat)

    def per_mode():
        return [m.image_bounds(lo, hi) for m in p.maps]

    loop_s, rows = _best(per_mode, repeat)
    same = all(np.array_equal(r.lower, t.lower) and np.array_equal(r.upper, t.upper) for r, t in zip(rows, together))
    return {"problem": name, "modes": len(p.mode_names), "cells": int(part.n_cells),
            "boxes": int(len(p.mode_names) * part.n_cells), "load_s": round(load_s, 3),
            "bound_stage_s": round(stage_s, 3), "images_vectorised_s": round(vec_s, 3),
            "images_per_mode_loop_s": round(loop_s, 3), "same_bounds": bool(same)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    rows = [measure(name, args.repeat) for name in ("robot2d_reach_avoid.toml", "bas4d.toml")]
    meta = {"command": "python benchmarks/input_grid_scale.py --repeat %d" % args.repeat,
            "machine": f"{platform.machine()}, {os.cpu_count()} cores", "python": sys.version.split()[0],
            "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "input_grid_scale.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = ["# Input grids at scale (`benchmarks/input_grid_scale.py`)", "",
             f"`{meta['command']}` on {meta['machine']} (load average {meta['load_average']:.1f} at the end); "
             "best of the repeats, seconds.", "",
             "| problem | modes | cells | (mode, cell) boxes | load | known bound stage | images, vectorised | "
             "images, mode by mode | same |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['problem']} | {r['modes']} | {r['cells']:,} | {r['boxes']:,} | {r['load_s']} | "
                     f"{r['bound_stage_s']} | {r['images_vectorised_s']} | {r['images_per_mode_loop_s']} | "
                     f"{r['same_bounds']} |")
    (OUT / "input_grid_scale.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0 if all(r["same_bounds"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
