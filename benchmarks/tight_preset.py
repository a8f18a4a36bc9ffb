"""The ``tight`` preset (``Problem.tightened``, ``run --tight``) on the benchmark family (issue 20).

    python benchmarks/tight_preset.py [--only KEY ...] [--merge]

For every configuration of the family's default subset (``family.configurations("default")``, seed 20):
our cell bounds with the preset's settings (``pipeline.problem.tight_settings``: ``split_tol =
TIGHT_SPLIT_TOL`` (``TIGHT_SPLIT_TOL_3D`` in 3-D) and, above ``LOCAL_AUTO`` points per mode, all points up to ``POOL_ALL_MAX``) and with the
default settings, one after the other in this run, against

* the optimal range of the family's sampled cells (``family.slack_cells``, first mode and output: the
  pointwise optimal bound on a grid in the cell), for the slack per side;
* the per-cell optimal boxes' Q_yes (``family.optimal_boxes``, what the data allow cell by cell) and the
  widened reference's Q_yes, both read from ``benchmarks/results/family.json`` (same seed: the sampled cells
  are checked to be the same);
* the sampled true images (containment violations must be 0).

Writes ``benchmarks/results/tight_preset.json`` and ``.md`` after every configuration.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import family  # noqa: E402
from reference import merged_rows, results_record, write_results  # noqa: E402

from robust_imdp.pipeline.problem import (TIGHT_SPLIT_TOL, TIGHT_SPLIT_TOL_3D, cell_taylor_term, pool_size,  # noqa: E402
                                          tight_settings)

SEED = 20
NAME = "tight_preset"


def measure(key: str, c: dict, old: dict) -> dict:
    t0 = time.perf_counter()
    sy = family.system_with_dfa(c, SEED)
    tb = family.true_boxes(sy)
    cells = family.slack_cells(sy)
    if cells.tolist() != old["optimal"]["cells"]:
        raise SystemExit(f"{key}: the sampled cells differ from family.json's: not the same system")
    opt = family.optimal_ranges(sy, cells)
    part = sy["partition"]
    term = cell_taylor_term(part.cells_upper[0] - part.cells_lower[0], sy["lengthscale"], sy["B"])
    settings = tight_settings([sy["m"]] * len(sy["maps"]), c["dim"], n_cells=part.n_cells, taylor_term=term)
    row = {"key": key, "dim": c["dim"], "ratio": c["ratio"], "points_per_mode": sy["m"], "settings": settings,
           "optimal_boxes_q_yes": old["optimal_boxes"]["yes"], "widened_q_yes": old["widened"]["yes"],
           "reference_q_yes": old["reference"]["yes"]}
    for name, tol, local in (("default", None, "auto"),
                             ("tight", settings["split_tol"], pool_size(settings["local_points"], sy["m"]))):
        ob = family.our_boxes(sy, tol, local)
        q = family.q_yes(sy, ob["lower"], ob["upper"])
        su = ob["upper"][0, cells, 0] - opt["opt_up"]
        sl = opt["opt_lo"] - ob["lower"][0, cells, 0]
        row[name] = {"q_yes": int(q["yes"]), "bound_seconds": ob["seconds"], "local_points": ob["local_points"],
                     "slack_upper": float(np.median(su)), "slack_lower": float(np.median(sl)),
                     "containment_violations": int(np.sum(ob["lower"] > tb["inner_lo"])
                                                   + np.sum(ob["upper"] < tb["inner_up"])),
                     "n_unconverged": int(ob["n_unconverged"])}
    row["seconds"] = time.perf_counter() - t0
    return row


def _ratio(a, b) -> str:
    return f"{a / b:.3f}" if b else "n/a"


def lines_of(data: dict) -> list[str]:
    rows = data["rows"]
    out = ["# The `tight` preset on the benchmark family (`benchmarks/tight_preset.py`)", "",
           f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}; seed {SEED}, the family's "
           f"default subset. *tight* = `Problem.tightened()` (`split_tol = {TIGHT_SPLIT_TOL:g}` in 1-D / 2-D, "
           f"`{TIGHT_SPLIT_TOL_3D:g}` in 3-D; above 1,000 points per mode all points up to 2,048)"
           "; *default* = no sub-boxes, pools of 100 above 1,000 points per mode; both "
           "bounded one after the other in this run. Slack: our range over the optimal range of the sampled cells, "
           "median per side (target <= 0.002 up to r/l 0.25, <= 0.005 at 0.5). Q_yes ratios against the per-cell "
           "optimal boxes and the widened reference of `family.json` (target >= 0.95). Violations: our boxes "
           "against the sampled true images, all cells.", "",
           "| config | points/mode | tight settings | slack default up/lo | slack tight up/lo | Q_yes default / tight "
           "| opt boxes / widened | tight vs opt boxes | tight vs widened | bound s default / tight (ratio) "
           "| violations |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        d, t = r["default"], r["tight"]
        lp = t["local_points"]
        st = f"split_tol {r['settings']['split_tol']:g}, " + ("all points" if lp is None else f"pools of {lp}")
        out.append(f"| {r['key']} | {r['points_per_mode']} | {st} | {d['slack_upper']:.4f} / {d['slack_lower']:.4f} "
                   f"| {t['slack_upper']:.4f} / {t['slack_lower']:.4f} | {d['q_yes']} / {t['q_yes']} | "
                   f"{r['optimal_boxes_q_yes']} / {r['widened_q_yes']} | "
                   f"{_ratio(t['q_yes'], r['optimal_boxes_q_yes'])} | {_ratio(t['q_yes'], r['widened_q_yes'])} | "
                   f"{d['bound_seconds']:.1f} / {t['bound_seconds']:.1f} ({t['bound_seconds'] / d['bound_seconds']:.1f}x) "
                   f"| {d['containment_violations'] + t['containment_violations']} |")
    target = {0.5: 0.005}
    slack_bad = [r["key"] for r in rows
                 if max(r["tight"]["slack_upper"], r["tight"]["slack_lower"]) > target.get(r["ratio"], 0.002)]
    opt_bad = [r["key"] for r in rows if r["optimal_boxes_q_yes"]
               and r["tight"]["q_yes"] < 0.95 * r["optimal_boxes_q_yes"]]
    wide_bad = [r["key"] for r in rows if r["widened_q_yes"] and r["tight"]["q_yes"] < 0.95 * r["widened_q_yes"]]
    out += ["", f"Configurations: {len(rows)}. Over the slack target with the preset: {slack_bad or 'none'}. "
            f"Below 0.95 of the optimal boxes: {opt_bad or 'none'}. Below 0.95 of the widened reference: "
            f"{wide_bad or 'none'}. Containment violations: "
            f"{sum(r['default']['containment_violations'] + r['tight']['containment_violations'] for r in rows)}."]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", metavar="KEY", help="configuration keys (default: all 19)")
    ap.add_argument("--merge", action="store_true", help="replace these rows of the existing tight_preset.json")
    args = ap.parse_args(argv)
    fam = {r["key"]: r for r in json.loads((ROOT / "benchmarks" / "results" / "family.json").read_text())["rows"]}
    configs = {family.key_of(c): c for c in family.configurations("default")}
    todo = sorted(family.chosen(configs, args.only), key=lambda kc: (kc[1]["dim"], kc[1]["ratio"]))
    family.warm_up(SEED)
    old_rows = []
    path = ROOT / "benchmarks" / "results" / f"{NAME}.json"
    if args.merge and path.exists():
        old_rows = json.loads(path.read_text())["rows"]
    rows = []
    for key, c in todo:
        rows.append(measure(key, c, fam[key]))
        r = rows[-1]
        print(f"{key}: default {r['default']['q_yes']} ({r['default']['bound_seconds']:.1f} s) tight "
              f"{r['tight']['q_yes']} ({r['tight']['bound_seconds']:.1f} s) opt boxes {r['optimal_boxes_q_yes']}; "
              f"slack tight {r['tight']['slack_upper']:.4f}/{r['tight']['slack_lower']:.4f}", flush=True)
        data = results_record(merged_rows(old_rows, rows, "key"))
        write_results(NAME, data, lines_of(data))
    bad = sum(r["default"]["containment_violations"] + r["tight"]["containment_violations"] for r in rows)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
