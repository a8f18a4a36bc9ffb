"""What closes the 3-D local pools' slack? Pointwise bounds of three pool variants against the optimum (issue 20).

    python benchmarks/archive/pool_variants.py [--ratios 0.03 0.125 0.25]

On the family's 3-D middle configuration (1,024 points per mode, first mode and output), at the grid points
of the sampled cells (``family.slack_cells``, ``OPT_GRID`` per axis; degenerate cells, so no Taylor term),
the slack of the local certificate over the pointwise optimum with all points (Scharnhorst et al.'s bound,
``family.optimal_ranges``), median per side, for:

* **pool size**: the ``k`` nearest points, k = 100 (the default), 200;
* **mixed pools**: ``near`` nearest points plus ``far`` points of one seeded global subset;
* **minimum-norm shift** (not in the library): ``h~ = sum_j alpha_j k(., z_j)``, the minimum-norm function of
  a subset of the data (the assumption check's SOCP, 300 points, or all 1,024). For every g with
  ``||g|| <= B`` that fits the data, ``||g - h~||^2 <= B^2 - 2 (alpha.y - dbar ||alpha||_1) + alpha.K alpha =: B'^2``,
  so the pool certificate of ``e = g - h~`` (data ``y - h~(x_i)``, norm ``B'``) plus ``h~(x)`` is sound. The
  float evaluation here is plain (this is a measurement of the gain, not a certificate).

Writes ``benchmarks/results/pool_variants.json`` and ``.md``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
import family  # noqa: E402
from reference import results_record, write_results  # noqa: E402

SEED = 20
VARIANTS = (("nearest 100", 100, 0), ("nearest 200", 200, 0), ("60 nearest + 40 global", 60, 40),
            ("100 nearest + 100 global", 100, 100))


def _mixed_pools(orig, X, near: int, far: int):
    glob = np.random.default_rng(1).choice(X.shape[0], far, replace=False)

    def pools(Xa, lo, up, ls, k):
        P = orig(Xa, lo, up, ls, near + far)
        out = np.empty((P.shape[0], near + far), np.int64)
        for q in range(P.shape[0]):
            chosen = list(P[q, :near])
            seen = set(chosen)
            extra = [int(i) for i in glob if i not in seen] + [int(i) for i in P[q, near:] if i not in seen]
            out[q] = np.array(chosen + list(dict.fromkeys(extra))[:far])
        return out
    return pools


def run(ratio: float) -> dict:
    from robust_imdp.bounds import rkhs, rkhs_local
    from robust_imdp.solvers.lp import rkhs_min_norm_socp

    sy = family.system(family.middle_3d(ratio), SEED)
    opt = family.optimal_ranges(sy, family.slack_cells(sy))
    pts = opt["points"]
    X, Y, _ = sy["data"][0]
    A, b = sy["maps"][0]
    y, ell, B, nb = Y[:, 0], sy["lengthscale"], sy["B"], sy["noise_bound"]
    ou, ol = opt["point_upper"], opt["point_lower"]

    def pooled(yy, bound, k):
        res = rkhs.bound_chunk(X, yy[:, None], A[:1], b[:1], pts, pts, lengthscale=ell, rkhs_bound=bound,
                               noise_bound=np.array([nb]), local_points=k)
        return res["lower"][:, 0], res["upper"][:, 0]

    def slack(lo, up):
        return {"upper": float(np.median(up - ou)), "lower": float(np.median(ol - lo))}

    out = {"ratio": ratio, "points": int(pts.shape[0]), "variants": {}}
    orig = rkhs_local.local_pools
    try:
        for name, near, far in VARIANTS:
            rkhs_local.local_pools = _mixed_pools(orig, X, near, far) if far else orig
            t0 = time.perf_counter()
            lo, up = pooled(y, B, near + far)
            out["variants"][name] = dict(slack(lo, up), seconds=time.perf_counter() - t0)
    finally:
        rkhs_local.local_pools = orig
    base_lo, base_up = pooled(y, B, 100)
    for n_sub in (300, X.shape[0]):
        idx = np.sort(np.random.default_rng(0).choice(X.shape[0], min(n_sub, X.shape[0]), replace=False))
        Kz = rkhs.unit_kernel(X[idx], X[idx], ell)
        w, val = rkhs_min_norm_socp(Kz, y[idx], nb)
        alpha = float(val) * np.asarray(w)
        b_shift = float(np.sqrt(max(B * B - 2 * (alpha @ y[idx] - nb * np.abs(alpha).sum()) + alpha @ Kz @ alpha, 0)))
        lo, up = pooled(y - rkhs.unit_kernel(X, X[idx], ell) @ alpha, b_shift, 100)
        h_p = rkhs.unit_kernel(pts, X[idx], ell) @ alpha
        lo, up = lo + h_p, up + h_p
        out["variants"][f"nearest 100, shift by h~ of {n_sub} points"] = dict(
            slack(lo, up), B_shift_over_B=b_shift / B, h_norm=float(np.sqrt(alpha @ Kz @ alpha)),
            min_with_plain=slack(np.maximum(lo, base_lo), np.minimum(up, base_up)))
    out["B"], out["true_norm"] = float(B), float(sy["true_norm"])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ratios", nargs="+", type=float, default=[0.03, 0.125, 0.25])
    args = ap.parse_args(argv)
    family.warm_up(SEED)
    rows = [run(r) for r in args.ratios]
    data = results_record(rows)
    lines = ["# What closes the 3-D local pools' slack? (`benchmarks/pool_variants.py`)", "",
             f"{data['date']}, commit {data['commit']}, load at the end {data['load'][0]:.1f}. Family 3-D middle "
             "configuration, 1,024 points per mode, first mode and output; pointwise slack over the optimum with "
             "all points at the grid points of the sampled cells, median upper / lower. The shifted rows are a "
             "measurement, not in the library (see the module docstring).", "",
             "| r/l | variant | slack upper / lower | note |", "|---|---|---|---|"]
    for r in rows:
        for name, v in r["variants"].items():
            note = (f"B' = {v['B_shift_over_B']:.3f} B, ||h~|| {v['h_norm']:.3f} (B {r['B']:.3f}, true norm "
                    f"{r['true_norm']:.3f}); min with the plain pool: {v['min_with_plain']['upper']:.5f} / "
                    f"{v['min_with_plain']['lower']:.5f}") if "B_shift_over_B" in v else f"{v['seconds']:.2f} s"
            lines.append(f"| {r['ratio']:g} | {name} | {v['upper']:.5f} / {v['lower']:.5f} | {note} |")
    write_results("pool_variants", data, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
