"""Compile and cache every numba kernel of the pipeline once, on tiny inputs.

    python -m robust_imdp.warmup [--only CASE ...] [--quiet]

The kernels of ``solve.py``, ``rkhs.py`` and ``bounds.py`` are ``@njit(cache=True)``: numba
compiles a kernel on its first call with a new combination of argument types and writes the
machine code next to the source (``src/robust_imdp/__pycache__/*.nbi, *.nbc``; git-ignored), or
into ``NUMBA_CACHE_DIR`` / the user's cache when that folder is not writable. Compiling them all
takes one to three minutes on 2 cores; without this step that time lands in the first run of
the pipeline (bound and synthesize stages). ``make venv`` (and so ``make demo`` / ``make test``)
runs this module after installing, so the first real run only loads the cached code.

What is compiled is decided by running the real pipeline on tiny problems (the three-mode case
study on a 16 x 16 grid, data from a fixed seed), one per code path that selects different kernels
or argument types (:data:`CASES`), and the solver on small random IMDPs: the same calls with the
same argument types (dtype, layout, read-only flag) as a real run, so the cached specialisations
are the ones a real run asks for.

Invalidation: numba keys each cache file by its source file's modification time and size, so
editing ``solve.py`` recompiles solve's kernels on their next call (the next ``make venv`` reruns
this module when a source is newer than its stamp). Some kernels call jitted functions of another module
(``bounds/rkhs_local.py`` those of ``rkhs_model``/``rkhs_weights``, the bound kernels ``_atomic.fetch_add``), whose
change numba does not see in the caller's cache: ``make venv`` therefore empties the whole cache whenever any
source changed (the Makefile's ``.warm`` rule).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: The tiny problems, in order: name -> (what it covers, changes to the base problem or a
#: re-synthesis of the first case's abstraction).
CASES = {
    "optimal": "assumption check, optimal weights on all points, abstraction, product solve by components",
    "floor": "a coarser grid: abstraction rows with a floor (Jacobi optimistic value iteration)",
    "horizon": "k-step horizon on the same abstraction (Jacobi sweeps)",
    "threaded": "the threaded Jacobi sweep (bellman_layer_parallel), forced on a small product",
    "local": "optimal weights on the nearest points of each cell (data sets > 1000 points per mode)",
    "ridge": "kernel-ridge weights, all points and local",
    "refine": "adaptive refinement of the undecided cells (box-tree partition)",
    "solver": "random IMDPs: end components, floors, interval iteration, both adversaries and objectives, "
              "a fixed strategy, rows of more than 256 successors",
    "factored": "a small factored IMDP (solvers.factored): the operator's kernels, k-step and unbounded, DFA product",
}

#: Cell width of the tiny grid over X = [-2, 2]^2 (16 x 16 cells: like the demo's grid, no row
#: needs a floor, so the product is solved by components), of the coarse one (8 x 8: rows with a
#: floor), and local points per cell.
CELL = 0.25
COARSE_CELL = 0.5
LOCAL_POINTS = 50


def _base_problem(directory: Path):
    from robust_imdp.casestudies.systems import write_problem_files
    from robust_imdp.io.files import load_problem

    problem = load_problem(write_problem_files("three_mode_linear", directory, seed=0))
    return problem.replace(cell_size=[CELL] * len(problem.space_lower))


def _run_case(name: str, base, first):
    """Run case ``name``; returns the pipeline Result of the "optimal" case (reused), else None."""
    from robust_imdp.solvers import sweep as solve  # PAR_MIN_STATES: the threshold of the threaded sweep
    from robust_imdp.pipeline.run import resynthesize, synthesize_from_data

    if name == "optimal":
        return synthesize_from_data(base, progress=False)
    if first is None:
        first = synthesize_from_data(base, progress=False)
    if name == "horizon":
        resynthesize(first, horizon=3, progress=False)
    elif name == "threaded":
        keep = solve.PAR_MIN_STATES
        solve.PAR_MIN_STATES = 1  # every Jacobi layer takes the threaded kernel (results are identical)
        try:
            resynthesize(first, horizon=3, progress=False)
            resynthesize(first, progress=False)
        finally:
            solve.PAR_MIN_STATES = keep
    elif name == "floor":
        synthesize_from_data(base.replace(cell_size=[COARSE_CELL] * len(base.space_lower)), progress=False)
    elif name == "solver":
        _solver_models()
    elif name == "factored":
        _factored_models()
    elif name == "local":
        synthesize_from_data(base.replace(local_points=LOCAL_POINTS), progress=False)
        from robust_imdp.bounds.rkhs_local import _blocks_done

        _blocks_done(np.zeros(1, dtype=np.int64), 0)  # the pieces' count read: chunks of more blocks than here
    elif name == "ridge":
        synthesize_from_data(base.replace(error_bound="ridge"), progress=False)
        synthesize_from_data(base.replace(error_bound="ridge", local_points=LOCAL_POINTS), progress=False)
    elif name == "refine":
        synthesize_from_data(base.replace(refine={"max_cells": 96, "max_rounds": 2}), progress=False)
    return first


def _random_imdp(n, rng, *, floor=0.0, wide_row=False):
    """n states, 2 actions, 2-6 successors per row, intervals [0.8 p, 1.2 p] (+ ``floor`` per row);
    action 0 of states 4 and 5 swaps them for sure (an end component away from the targets 0, 1);
    with ``wide_row`` one row of state 0 lists every state (more than 256 successors when n > 256)."""
    from robust_imdp.models.imdp import IMDP

    R = 2 * n
    k = rng.integers(2, 7, size=R)
    k[[8, 10]] = 1
    if wide_row:
        k[0] = n
    row_ptr = np.r_[0, np.cumsum(k)].astype(np.int64)
    col = np.concatenate([np.sort(rng.choice(n, size=kk, replace=False)) for kk in k]).astype(np.int64)
    col[row_ptr[8]], col[row_ptr[10]] = 5, 4
    p = rng.random(row_ptr[-1]) + 0.05
    p /= np.repeat(np.add.reduceat(p, row_ptr[:-1]), k)
    lower, upper = 0.8 * p, np.minimum(1.2 * p, 1.0)
    lower[row_ptr[[8, 10]]] = upper[row_ptr[[8, 10]]] = 1.0
    return IMDP.from_csr(np.arange(0, R + 1, 2), row_ptr, col, lower, upper,
                         floor=np.full(R, floor) if floor else None)


def _solver_models():
    """Solve small random IMDPs through every solver path the pipeline can take."""
    from robust_imdp.solvers.api import evaluate_strategy, solve_reachability

    rng = np.random.default_rng(0)
    for model in (_random_imdp(40, rng), _random_imdp(40, rng, floor=0.05), _random_imdp(300, rng, wide_row=True)):
        n = model.n_states
        target = np.zeros(n, dtype=bool)
        target[:2] = True
        avoid = np.zeros(n, dtype=bool)
        avoid[2:4] = True
        for method in ("vi", "interval"):
            for adversary in ("pessimistic", "optimistic"):
                for objective in ("maximize", "minimize"):
                    res = solve_reachability(model, target, avoid=avoid, adversary=adversary, objective=objective,
                                             method=method)
        solve_reachability(model, target, avoid=avoid, horizon=3)
        evaluate_strategy(model, target, res.strategy, avoid=avoid)
        # action 0 everywhere: keeps the end component of states 4, 5 (and the wide row) in the evaluated chain,
        # whatever the synthesised strategies choose, so the per-component kernels are typed for every row width
        evaluate_strategy(model, target, np.zeros(n, dtype=np.int64), avoid=avoid)


def _factored_models():
    """Solve a small factored IMDP through the factored solver's kernels (operator, fibre orders, support)."""
    import warnings

    from robust_imdp.errors import ConvergenceWarning
    from robust_imdp.models.factored import AxisMarginals, FactoredIMDP
    from robust_imdp.solvers.factored import solve_factored_product, solve_factored_reachability
    from robust_imdp.spec.api import to_dfa

    n, N = 4, 16
    start = np.tile(np.array([0, 0, 1, 1] * 4), (2, 1))
    axes = tuple(AxisMarginals(n=n, periodic=i == 1, start=start, lower=np.full((2, N, 3), 0.2),
                               upper=np.full((2, N, 3), 0.4), out_lower=np.zeros((2, N)),
                               out_upper=np.full((2, N), 0.1 if i == 0 else 0.0), rest_upper=np.full((2, N), 0.1),
                               axis=i) for i in range(2))
    model = FactoredIMDP(shape=(n, n), axes=axes)
    target = np.zeros(N + 1, dtype=bool)
    target[5] = True
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # 5 iterations: not converged, on purpose
        _factored_solves(model, target, N, solve_factored_product, solve_factored_reachability, to_dfa)


def _factored_solves(model, target, N, solve_factored_product, solve_factored_reachability, to_dfa):
    for adversary in ("pessimistic", "optimistic"):
        for objective in ("maximize", "minimize"):
            # a few iterations compile every path (the rest mass keeps the upper side from converging)
            solve_factored_reachability(model, target, avoid=[N], adversary=adversary, objective=objective,
                                        max_iterations=5)
        solve_factored_reachability(model, target, avoid=[N], adversary=adversary, horizon=3)
    dfa = to_dfa("F a", ["a"])
    letters = target.astype(np.int64)
    opt = solve_factored_product(model, letters, dfa, avoid=[N], adversary="optimistic", max_iterations=5)
    solve_factored_product(model, letters, dfa, avoid=[N], tie_break=opt, max_iterations=5)


def kernels():
    """``{"subpackage.name": dispatcher}`` of every numba kernel of the package (keys name the subpackage,
    e.g. ``solvers.solve_components``, so they survive moves between the modules of a subpackage)."""
    import importlib
    import pkgutil

    import numba

    import robust_imdp

    out = {}
    root = Path(robust_imdp.__file__).parent
    for info in pkgutil.walk_packages(robust_imdp.__path__, "robust_imdp."):
        rel = info.name.split(".")[1:]
        path = root.joinpath(*rel).with_suffix(".py")
        if info.ispkg or not path.exists() or "numba" not in path.read_text(encoding="utf-8"):
            continue  # only modules that use numba are imported here
        mod = importlib.import_module(info.name)
        for key, obj in vars(mod).items():
            if isinstance(obj, numba.core.registry.CPUDispatcher) and obj.py_func.__module__ == mod.__name__:
                out[f"{rel[0]}.{key}"] = obj
    return out


def warm(cases=None, *, progress: bool = True, strict: bool = True) -> dict:
    """Run the tiny problems of ``cases`` (default: all of :data:`CASES`) and return seconds per case.

    With ``strict=False`` a case that raises is reported (one line on stderr, seconds None) and
    the others still run: a kernel left uncompiled is compiled on its first real use, so a failed
    warm-up costs time, never a result.

    Raises
    ------
    InvalidInputError
        For a case name not in :data:`CASES`.
    """
    from robust_imdp.errors import InvalidInputError

    cases = list(CASES) if cases is None else list(cases)
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise InvalidInputError(f"warm-up cases must be among {', '.join(CASES)}; got {', '.join(map(repr, unknown))}")
    seconds = {}
    with tempfile.TemporaryDirectory(prefix="robust-imdp-warmup-") as tmp:
        base = _base_problem(Path(tmp))
        first = None
        for name in cases:
            t0 = time.perf_counter()
            try:
                first = _run_case(name, base, first)
            except Exception as exc:
                if strict:
                    raise
                seconds[name] = None
                print(f"[robust-imdp] warm-up {name} failed ({type(exc).__name__}: {exc}); its kernels will be "
                      "compiled on first use", file=sys.stderr, flush=True)
                continue
            seconds[name] = time.perf_counter() - t0
            if progress:
                print(f"[robust-imdp] warm-up {name}: {seconds[name]:.1f} s ({CASES[name]})", file=sys.stderr,
                      flush=True)
    return seconds


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m robust_imdp.warmup", description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="+", choices=list(CASES), help="run only these cases")
    ap.add_argument("--quiet", action="store_true", help="print nothing but errors")
    ap.add_argument("--strict", action="store_true", help="exit 1 when a case fails (default: report it, exit 0)")
    args = ap.parse_args(argv)
    import warnings

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tiny problems: coarse-grid and few-sample warnings are expected
        seconds = warm(args.only, progress=not args.quiet, strict=False)
    failed = [k for k, v in seconds.items() if v is None]
    if not args.quiet:
        ks = kernels()
        done = sum(1 for d in ks.values() if d.signatures)
        where = Path(sys.modules["robust_imdp"].__file__).parent / "*" / "__pycache__"
        print(f"[robust-imdp] warm-up: {done} of {len(ks)} numba kernels compiled or loaded from the cache "
              f"({where}) in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    return 1 if failed and args.strict else 0


if __name__ == "__main__":
    sys.exit(main())
