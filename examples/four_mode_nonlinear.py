"""The paper's nonlinear case study: two formulas on one abstraction (Jackson et al., HSCC 2021, Sec. 6.3).

    python examples/four_mode_nonlinear.py --out results/four_mode_nonlinear

x+ = x + g_u(x) + v with four modes (known part: identity; g_u unknown: sines and cosines),
truncated Gaussian noise (sigma = 0.01), 300 samples per mode (fixed seed). First "F des", then
"G !o & F d1 & F d2" re-solved on the same abstraction (no re-learning). For each formula:
result files and figures in OUT/<formula tag>/, and a Monte-Carlo validation summary.
"""

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402

from robust_imdp.casestudies.systems import get_case_study, true_system, write_problem_files  # noqa: E402
from robust_imdp.io.files import load_problem, save_result  # noqa: E402
from robust_imdp.pipeline.run import resynthesize, synthesize_from_data  # noqa: E402
from robust_imdp.plotting import save_figures  # noqa: E402
from robust_imdp.validate import simulate, validate  # noqa: E402

NAME = "four_mode_nonlinear"


def report(result, out: Path, seed: int, n_per_cell: int) -> None:
    system = true_system(NAME)
    rep = validate(result, system, n_per_cell=n_per_cell, max_steps=100, rng=seed)
    rng = np.random.default_rng(seed + 1)
    runs = simulate(result, system, rng.uniform(-2.0, 2.0, size=(25, 2)), max_steps=100, rng=rng,
                    record=True)
    save_figures(result, out, trajectories=runs)
    (out / "validation.txt").write_text(rep.summary() + "\n")
    save_result(result, out)
    print(result.summary())
    print(rep.summary())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("results") / NAME)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-per-cell", type=int, default=50)
    args = ap.parse_args(argv)
    first, second = get_case_study(NAME).formulas
    problem = load_problem(write_problem_files(NAME, args.out / "problem", seed=args.seed, formula=first))
    result = synthesize_from_data(problem, abstraction_cache=args.out / "cache")
    report(result, args.out / "F_des", args.seed, args.n_per_cell)
    t = time.perf_counter()
    again = resynthesize(result, formula=second)
    print(f"re-solved {second!r} on the same abstraction in {time.perf_counter() - t:.2f} s")
    report(again, args.out / "G_not_o_F_d1_F_d2", args.seed, args.n_per_cell)


if __name__ == "__main__":
    main()
