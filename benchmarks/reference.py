"""Known-dynamics reference: how close are our learned guarantees to what the grid allows? (issue 9)

For every shipped case-study problem (``examples/problems/*.toml``):

* **reference** -- the same grid, regions, noise, threshold, formula and abstraction options,
  but the EXACT image boxes of the true dynamics over every cell
  (``casestudies.known_dynamics_cell_bounds``) fed to our own ``abstraction.abstract`` and
  ``synthesis.synthesize``. No learned bound can classify more cells as Q_yes on this grid
  (up to the abstraction's own rules), so it is the yardstick of tightness.
* **ours** -- ``io.load_problem`` + ``pipeline.synthesize_from_data`` on the problem file, as
  shipped (no cache): Q_yes / Q_no / Q_?, Q_yes as a fraction of the reference, pipeline time.
* **image boxes** -- the boxes our pipeline abstracts are recorded by watching every
  ``abstraction.CellBounds`` made during the run (no library change; works however the pipeline
  learns, bounds and chunks, since the abstraction's input is a ``CellBounds``): the last one of
  full shape, with ``std_upper=None`` if any (the boxes with the learning error folded in).
  Per mode and output: median / max excess per
  side over the exact box (``exact_lo - ours_lo`` and ``ours_hi - exact_hi``), and
  **containment**: the number of (mode, cell, output, side) where an exact box sticks out of
  ours. In the confidence mode that number must be 0 (the boxes then contain the true images
  with the stated data confidence; a violation on the shipped data is a soundness red flag).
  In the "paper" mode the boxes hold ``f + mu`` only (the GP error enters the probabilities),
  so containment is not expected and is reported as n/a.

Writes ``benchmarks/results/reference.json`` and ``.md`` (machine info, medians over
``--repeat`` pipeline runs, ``BENCH_NOTE``). One untimed warm-up run of the first problem comes
first (numba compiles on first use; ``--no-warmup`` skips it).

Usage: ``python benchmarks/reference.py [--repeat N] [--only STEM ...] [--render]``
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
from pathlib import Path

# one BLAS thread: the machine has 2 cores shared by other jobs (oversubscription is slower)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np  # noqa: E402

import robust_imdp  # noqa: E402
from robust_imdp.abstraction import rows as _abstraction  # noqa: E402
from robust_imdp.casestudies.systems import CASE_STUDIES, known_dynamics_cell_bounds, true_system  # noqa: E402
from robust_imdp.spec.dfa import ltlf_to_dfa  # noqa: E402
from robust_imdp.models.geometry import Box, Partition, Region  # noqa: E402
from robust_imdp.io.files import load_problem  # noqa: E402
from robust_imdp.pipeline.run import synthesize_from_data  # noqa: E402
from robust_imdp.synthesis.core import synthesize  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
PROBLEMS = ROOT / "examples" / "problems"
OUT = HERE / "results"

#: Problem file stem -> case study whose true dynamics produced its data.
CASES = {
    "three_mode_linear": "three_mode_linear",
    "four_mode_nonlinear": "four_mode_nonlinear",
    "four_mode_nonlinear_two_goals": "four_mode_nonlinear",
    "unicycle_3d": "unicycle_3d",
}
#: Run by default (the shipped problem files); the 3-D case study (64^3 cells, ~6 min, its
#: problem written to a temporary directory by ``casestudies.write_problem_files``) only with
#: ``--only unicycle_3d``, whose row is then merged into the existing results.
DEFAULT = ("three_mode_linear", "four_mode_nonlinear", "four_mode_nonlinear_two_goals")
#: Reference Q_yes measured by the session that filed issue 9 (same grid 0.125, same settings).
EXPECTED_REFERENCE_YES = {"three_mode_linear": 764, "four_mode_nonlinear": 1018,
                          "four_mode_nonlinear_two_goals": 654}


# --------------------------------------------------------------------------- helpers
def _counts(p_low, p_up, threshold) -> dict:
    """Classes by definition (paper, Sec. 5): yes iff p_low >= t, no iff p_up < t."""
    p_low, p_up = np.asarray(p_low), np.asarray(p_up)
    yes = p_low >= threshold
    no = (p_up < threshold) & ~yes
    return {"yes": int(yes.sum()), "no": int(no.sum()), "maybe": int((~yes & ~no).sum())}


def _partition(problem) -> Partition:
    regions = [Region(k, [Box(lo, up) for lo, up in v]) for k, v in problem.regions.items()]
    return Partition(Box(problem.space_lower, problem.space_upper), problem.cell_size, regions)


def _mean_successors(abstr, n_cells: int) -> float:
    """Mean listed successors per cell row, the outside-state entry not counted."""
    nnz = np.asarray(abstr.nnz_per_row)
    return float(np.mean(nnz[: n_cells * abstr.n_modes]) - 1.0)


def reference(problem, case: str) -> dict:
    """Known-dynamics reference of ``problem`` (exact images of case study ``case``)."""
    system = true_system(case)
    if tuple(problem.mode_names) != tuple(system.mode_names):
        raise ValueError(f"problem modes {problem.mode_names} differ from case study {case!r} "
                         f"modes {system.mode_names}")
    t0 = time.perf_counter()
    part = _partition(problem)
    cb = known_dynamics_cell_bounds(case, part)
    abstr = _abstraction.abstract(part, cb, problem.noise, None, eta=getattr(problem, "eta", None),
                                  eps_rule=getattr(problem, "eps_rule", "optimized"),
                                  combine=getattr(problem, "combine", "product"))
    dfa = ltlf_to_dfa(problem.formula)
    syn = synthesize(abstr.imdp, part.labels, part.atoms, dfa, threshold=problem.threshold,
                     horizon=problem.horizon, outside_state=part.outside_state)
    return {"counts": _counts(syn.p_low, syn.p_up, problem.threshold),
            "time_s": time.perf_counter() - t0,
            "mean_successors_per_row": _mean_successors(abstr, part.n_cells),
            "mean_p_low": float(np.mean(syn.p_low)),
            "cell_bounds": cb, "p_low": np.asarray(syn.p_low), "p_up_star": np.asarray(syn.p_up_star)}


class _RecordCellBounds:
    """Records every ``abstraction.CellBounds`` made in this process while active."""

    def __init__(self):
        self.calls = []
        self.cls = _abstraction.CellBounds
        self.original = self.cls.__post_init__

    def __enter__(self):
        original, calls = self.original, self.calls

        def recording(obj):
            original(obj)
            calls.append(obj)

        self.cls.__post_init__ = recording
        return self

    def __exit__(self, *exc):
        self.cls.__post_init__ = self.original
        return False


def image_comparison(ours, exact) -> dict:
    """Per-side excess of our boxes over the exact ones and containment violations."""
    lo_ex = exact.image_lower - ours.image_lower  # >= 0 when ours contains the exact box
    hi_ex = ours.image_upper - exact.image_upper
    both = np.stack([lo_ex, hi_ex])  # (2, M, N, n)
    M, _, n = exact.image_lower.shape
    per = [[{"median": float(np.median(both[:, u, :, i])), "max": float(np.max(both[:, u, :, i])),
             "violations": int(np.sum(both[:, u, :, i] < 0))} for i in range(n)] for u in range(M)]
    return {"excess_median": float(np.median(both)), "excess_max": float(np.max(both)),
            "containment_violations": int(np.sum(both < 0)),
            "worst_violation": float(max(0.0, -np.min(both))),
            "per_mode_output": per}


def _load(stem: str):
    path = PROBLEMS / f"{stem}.toml"
    if path.exists():
        return load_problem(path), f"examples/problems/{stem}.toml"
    from robust_imdp.casestudies.systems import write_problem_files

    with tempfile.TemporaryDirectory() as d:  # the data are read into memory by load_problem
        return load_problem(write_problem_files(CASES[stem], d)), f"casestudies.write_problem_files({CASES[stem]!r})"


def run_one(stem: str, repeat: int) -> dict:
    case = CASES[stem]
    problem, source = _load(stem)
    ref = reference(problem, case)
    exact = ref.pop("cell_bounds")
    ref_p_low, ref_p_up_star = ref.pop("p_low"), ref.pop("p_up_star")
    row = {"problem": source, "stem": stem, "case_study": case, "formula": problem.formula,
           "threshold": float(problem.threshold), "guarantee": getattr(problem, "guarantee", None),
           "reference": ref, "expected_reference_yes": EXPECTED_REFERENCE_YES.get(stem)}
    times, result, recorded = [], None, None
    for _ in range(repeat):
        with _RecordCellBounds() as rec:
            result = synthesize_from_data(problem, progress=False)  # no cache: a full run
        times.append(float(result.timings.get("total", float("nan"))))
        recorded = rec.calls
    c = _counts(result.synthesis.p_low, result.synthesis.p_up, problem.threshold)
    row["ours"] = {
        "counts": c, "class_names_counts": result.counts(),
        "fraction_of_reference_yes": c["yes"] / ref["counts"]["yes"] if ref["counts"]["yes"] else None,
        "pipeline_time_median_s": statistics.median(times), "pipeline_times_s": times,
        "stage_times_s": {k: float(v) for k, v in result.timings.items()},
        "mean_successors_per_row": _mean_successors(result.abstraction, result.partition.n_cells),
        "mean_p_low": float(np.mean(result.synthesis.p_low)),
        "parameters": {k: result.parameters.get(k) for k in ("rkhs_bound", "gp_options", "guarantee",
                                                             "confidence", "eps_rule", "combine")},
    }
    # Consistency: when our boxes contain the exact ones, every interval of our IMDP contains the
    # reference's (the abstraction is monotone in the boxes), so our p_low cannot exceed the
    # reference's and our p_up_star cannot fall below it, up to the solver precision (1e-8).
    d_low = np.asarray(result.synthesis.p_low) - ref_p_low
    d_star = ref_p_up_star - np.asarray(result.synthesis.p_up_star)
    row["ours"]["p_low_above_reference"] = {"cells": int(np.sum(d_low > 1e-7)), "max": float(np.max(d_low))}
    row["ours"]["p_up_star_below_reference"] = {"cells": int(np.sum(d_star > 1e-7)), "max": float(np.max(d_star))}
    boxes = [cb for cb in (recorded or []) if getattr(cb, "image_lower", None) is not None
             and cb.image_lower.shape == exact.image_lower.shape]
    folded = [cb for cb in boxes if cb.std_upper is None]
    if not boxes:
        row["images"] = {"note": "the pipeline made no CellBounds of the full shape in this process "
                                 "(cache? worker processes?): no image comparison"}
    else:
        ours = (folded or boxes)[-1]
        row["images"] = image_comparison(ours, exact)
        if ours.std_upper is not None:  # "paper" mode: boxes of f + mu, GP error not folded in
            row["images"]["note"] = ("boxes hold f + mu only (GP error enters the probabilities): "
                                     "containment not expected")
            row["images"]["containment_violations"] = None
    return row


def _git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--", "src", "examples/problems"],
                               capture_output=True, text=True, check=True).stdout.strip()
        return out.stdout.strip() + (" + uncommitted changes in src/ or examples/problems/" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return None


def results_record(rows: list, **extra) -> dict:
    """A results file's record: the rows, the commit, the load average at the end and the date (UTC)."""
    return {"rows": rows, **extra, "commit": _git_commit(), "load": os.getloadavg(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}


def merged_rows(old_rows: list, rows: list, key: str) -> list:
    """``rows`` in place of the rows of an earlier record with the same ``key`` (in the old order), the other old
    rows kept, new keys at the end (``--only`` / ``--merge`` re-runs)."""
    fresh = {r[key]: r for r in rows}
    return [fresh.pop(r[key], r) for r in old_rows] + list(fresh.values())


def write_results(name: str, data: dict, lines: list[str]) -> None:
    """Write ``benchmarks/results/NAME.json`` (the record) and ``NAME.md`` (the table's lines)."""
    out = ROOT / "benchmarks" / "results"
    out.mkdir(exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(data, indent=1))
    (out / f"{name}.md").write_text("\n".join(lines) + "\n")


# --------------------------------------------------------------------------- report
def _stem(row: dict) -> str:
    """The problem's name in the tables (a generated problem is named by its case study)."""
    if row.get("stem"):
        return row["stem"]
    return row["case_study"] if row["problem"].startswith("casestudies.") else Path(row["problem"]).stem


def write_md(path: Path, data: dict) -> None:
    meta, rows = data["meta"], data["rows"]
    lines = [
        "# Known-dynamics reference (`benchmarks/reference.py`)", "",
        f"{meta['note']}; {meta['date']}; commit {meta['commit']}; python {meta['python']}, "
        f"numpy {meta['numpy']}, {meta['machine']}; pipeline times are medians of {meta['repeat']} run(s)"
        + (f" after an untimed warm-up run ({meta['warmup_s']:.0f} s)" if meta.get("warmup_s") else "")
        + ".", "",
        "*reference*: the same grid, regions, noise, threshold and abstraction options with the EXACT "
        "image boxes of the true dynamics (`casestudies.known_dynamics_cell_bounds`) through our own "
        "`abstract` + `synthesize`. *ours*: `synthesize_from_data` on the shipped problem file. "
        "*excess*: per side, how far our image box (the input of our abstraction) reaches beyond the exact "
        "box. *containment*: (mode, cell, output, side) where the exact box sticks out of ours "
        "(must be 0). *succ/row*: mean listed successor cells per row. *monotone*: cells where our "
        "p_low exceeds the reference's or our p_up_star falls below it by > 1e-7 (must be 0 when "
        "the boxes are contained).", "",
        "| problem | formula | reference Q_yes / Q_no / Q_? | ours Q_yes / Q_no / Q_? | Q_yes fraction |"
        " pipeline s | excess median / max | containment | monotone | succ/row ref / ours |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        rc, oc, im = r["reference"]["counts"], r["ours"]["counts"], r["images"]
        frac = r["ours"]["fraction_of_reference_yes"]
        exc = (f"{im['excess_median']:.4f} / {im['excess_max']:.4f}" if "excess_median" in im else "n/a")
        cont = im.get("containment_violations")
        lines.append(
            f"| {_stem(r)} | `{r['formula']}` | {rc['yes']} / {rc['no']} / {rc['maybe']} | "
            f"{oc['yes']} / {oc['no']} / {oc['maybe']} | {'n/a' if frac is None else f'{frac:.3f}'} | "
            f"{r['ours']['pipeline_time_median_s']:.1f} | {exc} | {'n/a' if cont is None else cont} | "
            f"{r['ours'].get('p_low_above_reference', {}).get('cells', 'n/a')} / "
            f"{r['ours'].get('p_up_star_below_reference', {}).get('cells', 'n/a')} | "
            f"{r['reference']['mean_successors_per_row']:.1f} / {r['ours']['mean_successors_per_row']:.1f} |")
    lines += ["", "## Excess of our image boxes per mode and output (per side: median / max)", "",
              "| problem | mode | output | median | max | containment violations |", "|---|---|---|---|---|---|"]
    for r in rows:
        per = r["images"].get("per_mode_output")
        if per is None:
            continue
        for u, outs in enumerate(per):
            for i, e in enumerate(outs):
                lines.append(f"| {_stem(r)} | {u} | {i} | {e['median']:.4f} | {e['max']:.4f} | "
                             f"{e['violations']} |")
    notes = []
    for r in rows:
        m = r.get("measured_in")
        if m and m.get("date") != meta.get("date"):
            notes.append(f"* {_stem(r)}: measured in an earlier run ({m.get('date')}, commit {m.get('commit')}, "
                         f"{m.get('note')}).")
        exp = r.get("expected_reference_yes")
        if exp is not None and exp != r["reference"]["counts"]["yes"]:
            notes.append(f"* {_stem(r)}: reference Q_yes {r['reference']['counts']['yes']} differs "
                         f"from the {exp} measured when issue 9 was filed (problem settings changed?).")
        if "note" in r["images"]:
            notes.append(f"* {_stem(r)}: {r['images']['note']}.")
        for key, what in (("p_low_above_reference", "p_low above"), ("p_up_star_below_reference", "p_up_star below")):
            v = r["ours"].get(key)
            if v and v["cells"]:
                notes.append(f"* {_stem(r)}: ours {what} the reference in {v['cells']} cells "
                             f"(max {v['max']:.3g}): expected 0 when our boxes contain the exact ones.")
        cont = r["images"].get("containment_violations")
        if cont:
            notes.append(f"* {_stem(r)}: **{cont} containment violations** (worst "
                         f"{r['images']['worst_violation']:.3g}): a learned box misses the exact image.")
    if notes:
        lines += ["", "## Notes", "", *notes]
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=1, help="pipeline runs per problem (median time)")
    ap.add_argument("--only", nargs="+", choices=sorted(CASES), help="problem file stems to run")
    ap.add_argument("--render", action="store_true", help="only rewrite reference.md from reference.json")
    ap.add_argument("--no-warmup", action="store_true", help="skip the untimed warm-up run")
    args = ap.parse_args(argv)
    OUT.mkdir(exist_ok=True)
    if args.render:
        write_md(OUT / "reference.md", json.loads((OUT / "reference.json").read_text()))
        return 0
    assert set(CASES.values()) <= set(CASE_STUDIES)
    t0 = time.perf_counter()
    stems = args.only or list(DEFAULT)
    warmup_s = None
    if not args.no_warmup:  # numba compiles on first use: keep that out of the timings
        synthesize_from_data(load_problem(PROBLEMS / f"{DEFAULT[0]}.toml"), progress=False)
        warmup_s = time.perf_counter() - t0
    rows = []
    for stem in stems:
        row = run_one(stem, max(1, args.repeat))
        rc, oc = row["reference"]["counts"], row["ours"]["counts"]
        print(f"{stem}: reference {rc['yes']}/{rc['no']}/{rc['maybe']}, ours {oc['yes']}/{oc['no']}/{oc['maybe']} "
              f"(Q_yes fraction {row['ours']['fraction_of_reference_yes']}), pipeline "
              f"{row['ours']['pipeline_time_median_s']:.1f} s, containment violations "
              f"{row['images'].get('containment_violations')}", flush=True)
        rows.append(row)
    meta = {"machine": platform.platform(), "python": platform.python_version(), "numpy": np.__version__,
            "robust_imdp": robust_imdp.__version__, "commit": _git_commit(), "repeat": max(1, args.repeat),
            "note": os.environ.get("BENCH_NOTE", "2-core machine shared with other jobs"),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "warmup_s": warmup_s, "total_s": time.perf_counter() - t0}
    data = {"meta": meta, "rows": rows}
    if args.only and (OUT / "reference.json").exists():
        # merge: the other problems keep their rows (and the run that measured them)
        prev = json.loads((OUT / "reference.json").read_text())
        mine = {r["problem"] for r in rows}
        kept = [r for r in prev["rows"] if r["problem"] not in mine]
        for r in kept:
            r.setdefault("measured_in", prev["meta"])
        for r in rows:
            r["measured_in"] = meta
        data = {"meta": meta, "rows": kept + rows}
    (OUT / "reference.json").write_text(json.dumps(data, indent=1))
    write_md(OUT / "reference.md", data)
    bad = [r for r in rows if r["images"].get("containment_violations")]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
