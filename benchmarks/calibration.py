"""Calibration on the tightness family: is the suggested (lengthscale, B) honest? (docs/calibration.md)

The family (``benchmarks/family.py``) draws every unknown component as ``g = sum_j a_j k_l(., c_j)``, a
finite sum of SE bumps of a known lengthscale ``l``, scaled to RKHS norm 0.2. Its norm at any other
lengthscale ``l'`` is known in closed form (:func:`norm_at`): for ``l' < sqrt(2) l``

    ||g||_{l'}^2 = (l^2 / (l' s))^d  sum_jk a_j a_k exp(-|c_j - c_k|^2 / (2 s^2)),   s^2 = 2 l^2 - l'^2

(the Fourier form of the SE RKHS norm, ``||f||^2 = (2 pi)^-d int |f^(w)|^2 / k^(w) dw``), and infinite for
``l' >= sqrt(2) l`` (the bumps are then not in the RKHS at all). So for every configuration, mode and
component the benchmark runs ``bounds.calibrate.calibrate_data`` on the family's data, exactly as
``robust-imdp calibrate`` would on its problem file, and compares the suggestion with the truth:

* **B >= true norm**: the suggested B against ``||g||`` at the *suggested* lengthscale (what the
  guarantee needs: the assumption is ``||g||_{l'} <= B`` at the lengthscale used), and against the
  generating norm 0.2 (``||g||_l``);
* **B <= 3 x true norm**: against both;
* **lengthscale within a factor 2** of the generating one;
* the **trend** flag (the family has no affine trend: every flag is a false alarm), and on a few extra
  components with an added trend ``0.3 + 0.2 x_1`` (every one should be flagged);
* time per component.

Counted per component (the unit calibrate suggests values for), per configuration (every component of
it passes), and per configuration with one problem-wide B (the largest suggested B against the largest
true norm, the family's own notion of B).

The rule table (``--rules``, on by default) decides the constants: for each lengthscale shrink factor
kappa and margin beta, the certified minimum norm (300 points, the assumption check's) at
``kappa * min(l_ML, l_CV)`` (capped at the data's extent) and the true norm there give the same three
rates for the rule ``l' = kappa min(l_ML, l_CV)``, ``B = beta x minimum norm``.

Writes ``benchmarks/results/calibration.json`` and ``calibration.md``. Usage:
``python benchmarks/calibration.py [--quick | --full] [--seed N] [--only KEY ...] [--no-rules] [--render]``
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # the machine's 2 cores are shared
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import family  # noqa: E402
from reference import merged_rows, results_record, write_results  # noqa: E402

from robust_imdp.bounds import calibrate as cal  # noqa: E402
from robust_imdp.jsonable import jsonable  # noqa: E402
from robust_imdp.bounds.rkhs_check import min_rkhs_norm  # noqa: E402

KAPPAS = (0.5, 0.6, 0.75, 1.0)
BETAS = (1.5, 2.0, 2.5, 3.0)
TREND = (0.3, 0.2)  # offset and x_1 slope added to the trend components
TARGETS = {"b_lower": 0.90, "b_upper": 0.90, "lengthscale": 0.80}


def norm_at(g, lp: float) -> float:
    """``||g||_{l'}`` of the family's ``g = sum_j a_j k_l(., c_j)`` (module docstring), 40-digit mpmath, rounded up."""
    import mpmath

    l = g.lengthscale
    if lp >= np.sqrt(2.0) * l:
        return float("inf")
    d = g.centres.shape[1]
    with mpmath.workdps(40):
        L, P = mpmath.mpf(float(l)), mpmath.mpf(float(lp))
        s2 = 2 * L * L - P * P
        coef = (L * L / (P * mpmath.sqrt(s2))) ** d
        c = [[mpmath.mpf(float(v)) for v in row] for row in g.centres]
        a = [mpmath.mpf(float(v)) for v in g.coef]
        total = mpmath.mpf(0)
        for j in range(len(a)):
            for k in range(len(a)):
                d2 = mpmath.fsum((c[j][i] - c[k][i]) ** 2 for i in range(d))
                total += a[j] * a[k] * mpmath.exp(-d2 / (2 * s2))
        val = float(mpmath.sqrt(coef * total))
    return float(np.nextafter(val, np.inf))


def run_config(c: dict, seed: int, rules: bool, trend: bool = False) -> dict:
    sy = family.system(c, seed)
    data = [(X, Y) for X, Y, _ in sy["data"]]
    if trend:  # an affine trend the SE kernel cannot represent, in every component
        data = [(X, Y + TREND[0] + TREND[1] * X[:, :1]) for X, Y in data]
    nv = cal.noise_variance(sy["noise"])
    t0 = time.perf_counter()
    res = cal.calibrate_data(data, noise_bound=sy["noise_bound"], noise_variance=nv, lower=sy["lower"],
                             upper=sy["upper"], mode_names=[str(u) for u in range(len(data))], rng=seed)
    seconds = time.perf_counter() - t0
    comps = []
    for r in res.components:
        g = sy["g"][r.mode][r.component]
        lp = float(r.lengthscale)
        row = {"mode": r.mode, "component": r.component + 1, "l_true": g.lengthscale, "l_ml": r.curves.ml,
               "l_cv": r.curves.cv, "l_suggested": lp, "min_norm": r.min_norm, "held_out_smallest": r.held_out.smallest,
               "held_out_evaluated": r.held_out.evaluated, "cp_upper": r.held_out.cp_upper, "B": r.rkhs_bound,
               "norm_true_l": g.norm, "norm_at_suggested": norm_at(g, lp), "trend": r.trend.detected,
               "trend_share": 1 - r.trend.min_norm_detrended / r.min_norm if r.min_norm > 0 else 0.0,
               "seconds": r.seconds}
        row["ok_lower"] = bool(row["B"] >= row["norm_at_suggested"])
        row["ok_lower_true_l"] = bool(row["B"] >= row["norm_true_l"])
        row["ok_upper"] = bool(row["B"] <= 3 * min(row["norm_at_suggested"], 1e300))
        row["ok_upper_true_l"] = bool(row["B"] <= 3 * row["norm_true_l"])
        row["ok_lengthscale"] = bool(0.5 <= lp / g.lengthscale <= 2.0)
        if rules and not trend:
            X, Y = data[r.mode]
            base = min(r.curves.ml, r.curves.cv)
            extent = cal._extent(X)
            row["rules"] = {}
            for kap in KAPPAS:
                lk = min(kap * base, extent)
                mn = min_rkhs_norm(X, Y[:, r.component], lk, sy["noise_bound"], max_points=cal.MIN_NORM_POINTS)
                row["rules"][str(kap)] = {"l": lk, "min_norm": mn["minimum"], "norm": norm_at(g, lk)}
        comps.append(row)
    return {"key": family.key_of(c) + ("-trend" if trend else ""), "config": c, "trend_added": trend,
            "seconds": seconds, "components": comps,
            "problem_wide_ok_lower": bool(max(x["B"] for x in comps) >= max(_inf(x["norm_at_suggested"]) for x in comps)),
            "problem_wide_ok_upper": bool(max(x["B"] for x in comps) <= 3 * max(x["norm_true_l"] for x in comps))}


def _inf(v) -> float:
    """A norm from the record (null: infinite)."""
    return float("inf") if v is None else float(v)


def _rate(flags) -> str:
    flags = list(flags)
    return f"{sum(flags)}/{len(flags)} = {sum(flags) / max(len(flags), 1):.0%}"


def render(data: dict) -> list:
    rows = [r for r in data["rows"] if not r["trend_added"]]
    comps = [c for r in rows for c in r["components"]]
    lines = ["# Calibration on the tightness family (`benchmarks/calibration.py`)", "",
             f"Commit {data.get('commit')}, {data.get('date')}, load {data.get('load')}. Seed {data.get('seed')}; "
             f"subset `{data.get('subset')}`. Rule: lengthscale = {cal.LENGTHSCALE_SHRINK:g} x min(likelihood, CV "
             f"optimum), capped at the data's extent; B = {cal.B_MARGIN:g} x max(certified minimum norm, held-out "
             "smallest B), rounded up. True norm at the suggested lengthscale: closed form (module docstring); "
             "inf where the suggested lengthscale is >= sqrt(2) x the generating one.", "",
             "## Targets", "",
             "| measure | per component | per configuration (all components) | target |",
             "|---|---|---|---|"]
    by_cfg = lambda key: [all(c[key] for c in r["components"]) for r in rows]  # noqa: E731
    for key, what, target in (("ok_lower", "B >= true norm at the suggested lengthscale", TARGETS["b_lower"]),
                              ("ok_lower_true_l", "B >= true norm at the generating lengthscale (0.2)", None),
                              ("ok_upper_true_l", "B <= 3 x true norm at the generating lengthscale", TARGETS["b_upper"]),
                              ("ok_upper", "B <= 3 x true norm at the suggested lengthscale", None),
                              ("ok_lengthscale", "lengthscale within a factor 2 of the generating one",
                               TARGETS["lengthscale"])):
        lines.append(f"| {what} | {_rate(c[key] for c in comps)} | {_rate(by_cfg(key))} | "
                     f"{'' if target is None else f'>= {target:.0%}'} |")
    lines += ["", f"One problem-wide B (the largest suggested against the largest true norm at the suggested "
              f"lengthscales): B >= truth on {_rate(r['problem_wide_ok_lower'] for r in rows)} configurations, "
              f"B <= 3 x 0.2 on {_rate(r['problem_wide_ok_upper'] for r in rows)}.",
              f"Trend flags on the family (no trend: false alarms): {_rate(c['trend'] for c in comps)} components.",
              ]
    trows = [r for r in data["rows"] if r["trend_added"]]
    if trows:
        tc = [c for r in trows for c in r["components"]]
        lines.append(f"Trend flags with `{TREND[0]} + {TREND[1]} x_1` added to every component: {_rate(c['trend'] for c in tc)}.")
    secs = [c["seconds"] for c in comps]
    lines += [f"Time per component: median {np.median(secs):.1f} s, max {max(secs):.1f} s (in this process, "
              "one core for BLAS).", "",
              "## Per configuration", "",
              "| configuration | l_true | l_ML / l | l_CV / l | l_sugg / l | min norm | B | true norm at l_sugg | "
              "B >= truth | B <= 3 x 0.2 | l ok | trend | s |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in data["rows"]:
        cs = r["components"]

        def span(f):
            v = [f(c) for c in cs]
            return f"{min(v):.2f}-{max(v):.2f}" if len(v) > 1 else f"{v[0]:.2f}"
        def norms():
            v = [_inf(c["norm_at_suggested"]) for c in cs]
            return f"{min(v):.2f}-" + ("inf" if max(v) == float("inf") else f"{max(v):.2f}")

        def count(key):  # the truth is g alone: not the data's g + trend
            return "-" if r["trend_added"] else f"{sum(c[key] for c in cs)}/{len(cs)}"
        lines.append(
            f"| {r['key']} | {cs[0]['l_true']:.3g} | {span(lambda c: c['l_ml'] / c['l_true'])} | "
            f"{span(lambda c: c['l_cv'] / c['l_true'])} | {span(lambda c: c['l_suggested'] / c['l_true'])} | "
            f"{span(lambda c: c['min_norm'])} | {span(lambda c: c['B'])} | "
            f"{'-' if r['trend_added'] else norms()} | {count('ok_lower')} | {count('ok_upper_true_l')} | "
            f"{count('ok_lengthscale')} | {sum(c['trend'] for c in cs)}/{len(cs)} | {r['seconds']:.0f} |")
    ruled = [c for c in comps if "rules" in c]
    if ruled:
        lines += ["", "## Rule table (the constants' decision)", "",
                  "Per component, for the rule `l' = kappa min(l_ML, l_CV)` (capped at the extent) and "
                  "`B = beta x certified minimum norm at l'` (300 points, no held-out term, no rounding): "
                  "B >= true norm at l' / B <= 3 x 0.2 / l' within a factor 2 of l.", "",
                  "| kappa | " + " | ".join(f"beta {b:g}" for b in BETAS) + " | l within 2 |",
                  "|---|" + "---|" * (len(BETAS) + 1)]
        for kap in KAPPAS:
            cells = []
            for beta in BETAS:
                lo = [beta * c["rules"][str(kap)]["min_norm"] >= _inf(c["rules"][str(kap)]["norm"]) for c in ruled]
                hi = [beta * c["rules"][str(kap)]["min_norm"] <= 3 * c["norm_true_l"] for c in ruled]
                cells.append(f"{np.mean(lo):.0%} / {np.mean(hi):.0%}")
            lw = [0.5 <= c["rules"][str(kap)]["l"] / c["l_true"] <= 2 for c in ruled]
            lines.append(f"| {kap:g} | " + " | ".join(cells) + f" | {np.mean(lw):.0%} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--quick", action="store_true")
    g.add_argument("--full", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", nargs="*", default=None, help="configuration keys to (re-)run, merged into the record")
    ap.add_argument("--no-rules", action="store_true", help="skip the rule table")
    ap.add_argument("--no-trend", action="store_true", help="skip the added-trend components")
    ap.add_argument("--render", action="store_true", help="rewrite the markdown from the JSON record")
    args = ap.parse_args(argv)
    path = family.OUT / "calibration.json"
    if args.render:
        data = json.loads(path.read_text())
        write_results("calibration", data, render(data))
        return 0
    subset = "quick" if args.quick else "full" if args.full else "default"
    configs = family.configurations(subset)
    jobs = [(c, False) for c in configs]
    if not args.no_trend:
        jobs += [(family.configurations("quick")[0], True), (dict(family.configurations("quick")[0], dim=1), True)]
    if args.only:
        jobs = [(c, t) for c, t in jobs if family.key_of(c) + ("-trend" if t else "") in args.only]
    rows = []
    for c, t in jobs:
        r = run_config(c, args.seed, rules=not args.no_rules, trend=t)
        rows.append(r)
        cs = r["components"]
        print(f"{r['key']}: {r['seconds']:.0f} s; B >= truth {sum(x['ok_lower'] for x in cs)}/{len(cs)}, "
              f"l ok {sum(x['ok_lengthscale'] for x in cs)}/{len(cs)}, trend {sum(x['trend'] for x in cs)}/{len(cs)}",
              flush=True)
    if args.only and path.exists():
        rows = merged_rows(json.loads(path.read_text())["rows"], rows, "key")
    data = results_record(rows, seed=args.seed, subset=subset,
                          constants={"lengthscale_shrink": cal.LENGTHSCALE_SHRINK, "b_margin": cal.B_MARGIN,
                                     "folds": cal.FOLDS, "max_points": cal.MAX_POINTS,
                                     "min_norm_points": cal.MIN_NORM_POINTS, "trend_factor": cal.TREND_FACTOR})
    data = jsonable(data)  # infinite norms (a lengthscale >= sqrt(2) l) become null
    write_results("calibration", data, render(data))
    print("\n".join(render(data)[:14]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
