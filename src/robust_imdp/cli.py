"""The ``robust-imdp`` command.

    robust-imdp run PROBLEM.toml --out DIR        synthesize; write DIR/result.json, result.npz, figures
    robust-imdp simulate DIR --true-system NAME   Monte-Carlo validation of DIR's result on a true system
                                                  (a case study, or FILE.py:NAME for your own system)
    robust-imdp export DIR --format drn --out F   the abstraction (or --product: with the DFA) for Storm / PRISM
    robust-imdp example NAME --out DIR            write a case study's problem file and data
    robust-imdp suggest DIR --problem P --budget N  where to sample next: N (x, mode) requests as CSV
    robust-imdp improve P --true-system S --budget N  the sampling loop: suggest, simulate, re-bound, re-solve
    robust-imdp calibrate PROBLEM.toml --out DIR  suggest lengthscale and rkhs_bound from the data (evidence,
                                                  not proof); write DIR/calibration.json and .png
    robust-imdp --version

``simulate`` exits with status 1 when more cells are flagged than chance allows (the result's
bounds are contradicted by the simulated system), 0 otherwise.

Errors (bad files, unknown regions, ...) print one message and exit with status 1; usage errors
(including option values out of range, checked before any work) exit with status 2 (argparse);
unexpected internal errors exit with status 3; Ctrl-C exits with status 130. No traceback is
shown unless ``--debug`` is given (before or after the command). Warnings print as
``robust-imdp: warning: ...``, without the library's source line.
"""

from __future__ import annotations

import argparse
import enum
import json
import sys
import warnings
from pathlib import Path

from robust_imdp import __version__
from robust_imdp.errors import InvalidInputError, RobustImdpError, interrupt_in

__all__ = ["main"]


class Exit(enum.IntEnum):
    """The exit statuses of ``robust-imdp`` (see the module docstring)."""

    OK = 0
    ERROR = 1  #: bad input, or a validation the result fails
    USAGE = 2  #: argparse's status for usage errors
    INTERNAL = 3  #: a bug, not bad input
    INTERRUPTED = 130  #: Ctrl-C (128 + SIGINT), the shell's convention


# --------------------------------------------------------------------------- option values
# Checked by argparse while parsing, so a bad value stops the command before any work (exit 2).
def _number(kind, text: str, what: str):
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {what}; got {text!r}") from None


def _probability(text: str) -> float:
    v = _number(float, text, "a probability in [0, 1]")
    if not 0.0 <= v <= 1.0:  # also refuses nan
        raise argparse.ArgumentTypeError(f"must be a probability in [0, 1]; got {text}")
    return v


def _open_unit(text: str) -> float:
    v = _number(float, text, "a number in (0, 1)")
    if not 0.0 < v < 1.0:
        raise argparse.ArgumentTypeError(f"must lie in (0, 1); got {text}")
    return v


def _at_least(low: int):
    def check(text: str) -> int:
        v = _number(int, text, f"an integer >= {low}")
        if v < low:
            raise argparse.ArgumentTypeError(f"must be an integer >= {low}; got {text}")
        return v

    check.__name__ = f"integer >= {low}"
    return check


def _slice_spec(text: str) -> dict:
    """``x3=0.5,x4=0`` (or dimension names) -> ``{"x3": 0.5, "x4": 0.0}``; the names are checked
    against the problem once it is read (``plotting.resolve_slice``)."""
    import math

    out = {}
    for part in text.split(","):
        key, sep, value = part.partition("=")
        try:
            v = float(value) if sep and key.strip() else None
        except ValueError:
            v = None
        if v is None or not math.isfinite(v):
            raise argparse.ArgumentTypeError(
                f"must be NAME=VALUE[,NAME=VALUE...] with NAME x1 .. xn or a [space].names entry and VALUE a "
                f"number, e.g. x3=0.5,x4=0; got {text!r}")
        out[key.strip()] = v
    return out


#: The case studies ``example`` writes and ``--true-system`` simulates (``casestudies.systems.CASE_STUDIES``, named
#: here so that ``--help`` does not import them; a test keeps the two equal).
CASE_STUDY_NAMES = ("three_mode_linear", "four_mode_nonlinear", "unicycle_3d", "unicycle_3d_known", "vehicle_4d")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="robust-imdp",
        description="Formally guaranteed switching controllers from data (certified bounds of the "
                    "unknown dynamics, interval-MDP abstraction, LTLf synthesis).",
    )
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    # --debug is also accepted after the command; SUPPRESS keeps a --debug given before it.
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    run = sub.add_parser("run", parents=[common], help="synthesize a controller from a TOML problem file",
                         description="Learn, bound, abstract and synthesize; write result.json, "
                                     "result.npz and PNG figures into --out.")
    run.add_argument("problem", type=Path, help="TOML problem file")
    run.add_argument("--out", type=Path, required=True, help="output directory")
    run.add_argument("--cache", type=Path, default=None,
                     help="abstraction cache directory (default: OUT/cache); reused when only "
                          "the formula, threshold or horizon changes")
    run.add_argument("--formula", default=None, help="override [spec].formula")
    run.add_argument("--threshold", type=_probability, default=None, help="override [spec].threshold")
    run.add_argument("--no-figures", action="store_true", help="do not write PNG figures")
    run.add_argument("--advice", choices=("auto", "on", "off"), default="auto",
                     help="estimate which lever (2x finer grid, more data, sub-boxes, larger local pools) would "
                          "move most of X into Q_yes, by re-solving with modified image boxes; auto: cheapest "
                          "first within 25 %% of the run's time before it (re-solves of at most 65,536 cells); "
                          "on: every lever, no budget")
    run.add_argument("--margins", choices=("on", "off"), default="on",
                     help="assumption margins (default on): per cell the largest factor beta of 1, 1.25, 1.5, 2, 3, "
                          "4 at which the controller keeps the cell's class with every rkhs_bound B replaced by "
                          "beta B (result.json's b_margin, b_margin.png, the summary); the same certificate "
                          "weights, one abstraction and evaluation per factor (docs/margins.md)")
    _add_tight(run)
    run.add_argument("--quiet", action="store_true", help="no progress lines")
    run.add_argument("--workers", type=_at_least(1), default=None,
                     help="local cores: 1 = in this process on one core, N > 1 = a local Dask cluster "
                          "of N processes (default: this process, numba threads on all cores)")
    run.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="run the bound and abstraction stages on a running Dask cluster "
                          "(e.g. tcp://host:8786)")
    run.add_argument("--slice", type=_slice_spec, default=None, metavar="NAME=VALUE[,...]",
                     help="figures of 3 or more dimensions: fix these coordinates (x3=0.5,x4=0, or by "
                          "[space].names); default: slices through the cells with the most Q_yes")
    run.add_argument("--yes", action="store_true",
                     help="run even when the pre-flight estimate says the run does not fit the machine")

    sim = sub.add_parser("simulate", parents=[common], help="validate a result by simulating a true system",
                         description="Simulate the true system under the result's controller "
                                     "from random states in every cell and compare the "
                                     "empirical satisfaction with [p_low, p_up] (Wilson "
                                     "intervals). Writes validation.json and trajectories.png. "
                                     "Exit status 0 when no more cells are flagged than chance allows "
                                     "(a binomial tail over the cells at --confidence), 1 when more are: "
                                     "the bounds are contradicted by the system.")
    sim.add_argument("result", type=Path, help="directory holding result.json")
    sim.add_argument("--true-system", required=True, metavar="NAME | FILE.py:NAME",
                     help="the true dynamics to simulate: a case study (" + ", ".join(CASE_STUDY_NAMES) + "), "
                          "or NAME in your Python file: a class built with no "
                          "arguments, or an object, with mode_names (the result's mode names) and "
                          "step(x (k, n), modes (k,) int indices into mode_names, rng) -> (k, n)")
    sim.add_argument("--n-per-cell", type=_at_least(1), default=50, help="runs per cell (default 50)")
    sim.add_argument("--max-steps", type=_at_least(1), default=None,
                     help="step cap per run (default: robust_imdp.validate.MAX_STEPS, 200)")
    sim.add_argument("--confidence", type=_open_unit, default=0.999, help="Wilson confidence (0.999)")
    sim.add_argument("--seed", type=_at_least(0), default=0, help="random seed (default 0)")
    sim.add_argument("--paths", type=_at_least(0), default=20, help="trajectories to draw (default 20)")
    sim.add_argument("--no-figures", action="store_true", help="do not write trajectories.png")

    exp = sub.add_parser("export", parents=[common],
                         help="write the abstraction (or its product with the DFA) for Storm or PRISM",
                         description="Write the interval MDP behind DIR's result (from the run's cache) in "
                                     "Storm's DRN format or as PRISM explicit files. States: cells 0..n-1, "
                                     "then the outside-X state n; action a = mode index (see FILE.states.json). "
                                     "With --product: the product with the DFA (state s * (n + 1) + q for DFA "
                                     "state s and cell q), labels init (every cell's initial product state), "
                                     "target (accepting) and avoid (outside X or acceptance unreachable).")
    exp.add_argument("result", type=Path, help="directory holding result.json")
    exp.add_argument("--format", required=True, choices=("drn", "prism"),
                     help="drn: one .drn file; prism: OUT.tra, .lab, .sta (and .props with --product)")
    exp.add_argument("--out", type=Path, required=True,
                     help="output file (drn) or file prefix (prism; a .tra suffix is dropped)")
    exp.add_argument("--product", action="store_true",
                     help="the product with the result's DFA, whose values are p_low / p_up_star")
    exp.add_argument("--cache", type=Path, default=None,
                     help="the run's cache directory (default: DIR/cache)")

    sg = sub.add_parser("suggest", parents=[common], help="where to collect data next: (x, mode) sample requests",
                        description="Rank sample requests (state, mode) by how much one more sample there "
                                    "shrinks the RKHS term of the error radii of the undecided cells and of the "
                                    "cells their strategy reaches (robust_imdp.synthesis.suggest). Writes a CSV "
                                    "(x_1..x_d, mode, cell, radius_change, gain, reason). The run's cache "
                                    "(DIR/cache) makes this a re-read, not a re-run.")
    sg.add_argument("result", type=Path, help="the run's output directory (holding result.json and cache/)")
    sg.add_argument("--problem", type=Path, required=True, help="the run's TOML problem file")
    sg.add_argument("--budget", type=_at_least(1), required=True, help="number of sample requests")
    sg.add_argument("--out", type=Path, default=None, help="CSV file (default: DIR/suggestions.csv)")
    sg.add_argument("--cache", type=Path, default=None, help="the run's cache directory (default: DIR/cache)")
    _add_tight(sg, "as the run was")

    im = sub.add_parser("improve", parents=[common], help="the sampling loop: suggest, simulate, re-bound, re-solve",
                        description="Collect --budget samples in --rounds rounds from the true system where they "
                                    "help most (robust_imdp.improve): each round suggests requests, simulates one "
                                    "step from each, appends them to OUT/data.csv (column round), re-bounds only "
                                    "the cells near the new data and re-solves; prints Q_yes / Q_no / Q_? per round "
                                    "and keeps the rounds in OUT/result.json. Interrupted, the same command resumes.")
    im.add_argument("problem", type=Path, help="TOML problem file (its data are the starting data)")
    im.add_argument("--true-system", required=True, help="a case study name, or FILE.py:NAME (a class or object with "
                                                         "mode_names and step(x, modes, rng))")
    im.add_argument("--budget", type=_at_least(1), required=True, help="samples to add in all")
    im.add_argument("--rounds", type=_at_least(1), default=None,
                    help="rounds (default: budget // 10, at most 8; robust_imdp.improve.auto_rounds)")
    im.add_argument("--out", type=Path, default=Path("improve"), help="output directory (default ./improve)")
    im.add_argument("--seed", type=int, default=0, help="random seed of the simulations (default 0)")
    im.add_argument("--allow-outside", action="store_true", help="accept next states outside X")
    im.add_argument("--quiet", action="store_true", help="no progress lines (the per-round lines stay)")
    _add_tight(im, "its local_points from the starting data")

    ca = sub.add_parser("calibrate", parents=[common], help="suggest lengthscale and rkhs_bound from the data",
                        description="Per mode and component: GP likelihood and cross-validation curves of the "
                                    "lengthscale, the certified minimum RKHS norm, held-out violations of the "
                                    "certified bound per B with a Clopper-Pearson bound, affine trends "
                                    "(robust_imdp.bounds.calibrate, docs/calibration.md). Writes calibration.json "
                                    "and calibration.png into --out and prints the suggested [learning] table; "
                                    "never edits the problem file. Evidence, not proof.")
    ca.add_argument("problem", type=Path, help="TOML problem file")
    ca.add_argument("--out", type=Path, default=Path("calibration"), help="output directory (default ./calibration)")
    ca.add_argument("--folds", type=_at_least(2), default=5, help="cross-validation folds (default 5)")
    ca.add_argument("--seed", type=_at_least(0), default=0, help="random seed of the subsets and folds (default 0)")
    ca.add_argument("--keep-lengthscale", action="store_true",
                    help="keep the problem's lengthscale (e.g. one per input dimension) and calibrate B only")
    ca.add_argument("--workers", type=_at_least(1), default=None,
                    help="local cores: 1 = this process on one core, N > 1 = a local Dask cluster of N processes "
                         "(default: this process, numba threads on all cores)")
    ca.add_argument("--no-figures", action="store_true", help="do not write calibration.png")
    ca.add_argument("--quiet", action="store_true", help="no progress lines")

    ex = sub.add_parser("example", parents=[common], help="write a case study's problem file and data",
                        description="Generate the data of a paper case study with a fixed seed "
                                    "and write NAME.toml + NAME_data.csv into --out.")
    ex.add_argument("name", help="the case study: " + ", ".join(CASE_STUDY_NAMES))
    ex.add_argument("--out", type=Path, required=True, help="output directory")
    ex.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ex.add_argument("--formula", default=None, help="formula (default: the case study's first)")
    return p


def _writable_dir(directory: Path, option: str) -> list:
    """Check, before any long work, that ``directory`` can be created or written to; create nothing.

    Returns the directories that do not exist yet, deepest first (made when the first file is
    written; :func:`_remove_if_empty` takes them away again when the run fails).
    """
    import tempfile

    missing, existing = [], directory
    while not existing.exists() and existing != existing.parent:
        missing.append(existing)
        existing = existing.parent
    try:
        if not existing.is_dir():
            raise NotADirectoryError(20, "not a directory", str(existing))
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as exc:
        raise InvalidInputError(f"{option} must be a directory you can write to; {directory}: "
                                f"{exc.strerror or exc}" + (f" ({existing})" if existing != directory else "")) from None
    return missing


def _remove_if_empty(directories) -> None:
    """Remove those of ``directories`` (deepest first) that are empty: a failed run leaves no empty folders."""
    for d in sorted(set(directories), key=lambda p: len(p.parts), reverse=True):
        try:
            d.rmdir()
        except OSError:  # not empty, or never made
            pass


#: The files of a result directory: ``run`` writes the result and figures, ``simulate`` the
#: validation. A ``run`` writes its outputs beside the old ones and swaps them in only when all are
#: complete (``io.result_file.staged_outputs``): then nothing of the previous result is left beside the
#: new one, and a run that fails or is interrupted leaves the previous result exactly as it was.
RESULT_OUTPUTS = ("result.json", "result.npz", "validation.json", "trajectories.png", "partition.png",
                  "classes.png", "p_low.png", "error.png", "bounds.png", "b_margin.png")
#: The files ``simulate`` writes into the result directory, replaced as one the same way.
VALIDATION_OUTPUTS = ("validation.json", "trajectories.png")


def _cmd_run(args) -> int:
    out: Path = args.out
    cache = args.cache if args.cache is not None else out / "cache"
    # Everything the command line can get wrong is checked before the data are read:
    # option ranges by argparse, the output directories and the formula's syntax here, the
    # formula's regions by the pipeline's first stage.
    created = _writable_dir(out, "--out") + _writable_dir(cache, "--cache")
    if args.formula is not None:
        from robust_imdp.spec.ltlf import parse

        parse(args.formula)
    try:
        return _run_into(args, out, cache)
    except BaseException:
        _remove_if_empty(created)
        raise


def _add_tight(parser, what: str = "") -> None:
    """The ``--tight`` flag (``run``, ``suggest``, ``improve``): :meth:`Problem.tightened`."""
    parser.add_argument("--tight", action="store_true",
                        help="the tight preset (Problem.tightened" + (f"; {what}" if what else "") + "): "
                             "certification sub-boxes down to a Taylor term of 4e-4 (1-D, 2-D) or 1.5e-3 (3-D "
                             "and up) and, where local pools would be used, all points up to 2,048 per mode "
                             "(else pools of 400); [learning] split_tol / local_points the file sets are kept. "
                             "Tighter where cells are large against the lengthscale, at several times the "
                             "bound time (README, 'Tightness in one switch')")


def _tightened(problem, args):
    """``problem.tightened()`` with ``--tight`` (its settings on stderr unless ``--quiet``), else ``problem``."""
    if not getattr(args, "tight", False):
        return problem
    from robust_imdp.pipeline.problem import tight_line

    problem = problem.tightened()
    if not getattr(args, "quiet", False):
        print(tight_line(problem), file=sys.stderr)
    return problem


class _Figures:
    """The figures of ``run`` (``plotting.save_figures``, the same bytes whichever way they are drawn).

    With a side lane (``pipeline.parallel.side_lane``) its helper processes draw them into a temporary folder:
    those of the result after the solve while the advice and the margins run (:meth:`start`, the run's
    ``on_solved``), the assumption margins' after the run (:meth:`finish`), each helper a share of the figures;
    :meth:`collect` moves them into the staged outputs. This process then never imports matplotlib. Without a
    lane, or when the lane cannot take them (``SideLaneError``), this process draws them all in :meth:`collect`.
    """

    #: Figures the result has when it is solved (those of 1-D and of 2-D and more; ``save_figures`` draws the
    #: ones of the result's dimension), and those that wait for the end of the run.
    EARLY = ("bounds", "partition", "classes", "p_low", "error")
    LATE = ("b_margin",)

    def __init__(self, lane, args):
        self.enabled = not args.no_figures
        self.lane = lane if self.enabled else None
        self.options = {"slice": args.slice} if args.slice else {}
        self.tmp, self.futures, self.result = None, [], None

    def __enter__(self) -> "_Figures":
        return self

    def __exit__(self, *exc) -> bool:
        if self.tmp is not None:
            import shutil

            shutil.rmtree(self.tmp, ignore_errors=True)
        return False

    def _submit(self, result, names) -> None:
        import dataclasses
        import tempfile

        if self.tmp is None:
            self.tmp = Path(tempfile.mkdtemp(prefix="robust-imdp-figures-"))
        light = dataclasses.replace(result, abstraction=None)  # what the figures read, without the IMDP
        k = min(len(self.lane.helpers), len(names))
        for group in (names[i::k] for i in range(k)):  # each helper converts the result once
            self.futures.append(self.lane.submit("robust_imdp.plotting:save_figures", light, self.tmp,
                                                 only=tuple(group), **self.options))

    def start(self, result) -> None:
        """``on_solved``: draw the figures the solved result already has."""
        if self.lane is not None:
            self._submit(result, self.EARLY)

    def finish(self, result) -> None:
        """After the run: draw the rest (all of them when :meth:`start` was not called)."""
        self.result = result
        if self.lane is not None:
            names = self.LATE if self.futures else self.EARLY + self.LATE
            if getattr(result, "b_margin", None) is not None or not self.futures:
                self._submit(result, names)

    def collect(self, out: Path) -> list:
        """The figures' files in ``out`` (moved there, or drawn there in this process)."""
        if not self.enabled:
            return []
        if self.lane is not None:
            import shutil

            from robust_imdp.pipeline.parallel import SideLaneError

            try:
                drawn = [Path(p) for f in self.futures for p in f.result()]
            except SideLaneError:
                drawn = None  # drawn below, in this process
            if drawn is not None:
                return [Path(shutil.move(str(p), str(out / p.name))) for p in drawn]
        from robust_imdp.plotting import save_figures

        return save_figures(self.result, out, **self.options)


def _run_into(args, out: Path, cache: Path) -> int:
    from robust_imdp.io.files import load_problem, save_result
    from robust_imdp.pipeline.parallel import SIDE_MIN_CELL_MODES, side_lane
    from robust_imdp.pipeline.run import synthesize_from_data

    problem = load_problem(args.problem)
    changes = {}
    if args.formula is not None:
        changes["formula"] = args.formula
    if args.threshold is not None:
        changes["threshold"] = args.threshold
    if changes:
        problem = problem.replace(**changes)
    problem = _tightened(problem, args)
    if args.slice:  # checked against the problem's dimensions before the long stages
        from robust_imdp.plotting import resolve_slice

        resolve_slice(args.slice, problem.space_lower, problem.space_upper, getattr(problem, "dim_names", None))
    args.interrupt_note = (f"interrupted; the finished chunks are saved in {cache}: run the same command again "
                           "to resume" + (f" ({out}'s previous result is unchanged)" if (out / "result.json").exists()
                                          else ""))
    # Side work (the assumption check, the figures) goes to helper processes beside the long stages on several
    # cores, for problems large enough to hide their start-up (pipeline.parallel, "Side work"); they import
    # what their tasks need while this process reads the data and starts the stages.
    beside = args.workers != 1 and problem.n_grid_cells * len(problem.mode_names) >= SIDE_MIN_CELL_MODES
    preload = ("robust_imdp.bounds.rkhs_check", "cvxpy") + (() if args.no_figures else ("robust_imdp.plotting",))
    with side_lane(enabled=beside, preload=preload) as lane, _Figures(lane, args) as drawing:
        return _run_and_write(args, out, cache, problem, drawing, synthesize_from_data, save_result)


def _run_and_write(args, out: Path, cache: Path, problem, drawing: _Figures, synthesize_from_data, save_result) -> int:
    """The run and its outputs (:func:`_run_into` inside its side lane)."""
    result = synthesize_from_data(problem, progress=not args.quiet, abstraction_cache=cache,
                                  workers=args.workers, scheduler=args.scheduler, check_resources=not args.yes,
                                  advice={"auto": "auto", "on": True, "off": False}[args.advice],
                                  margins=getattr(args, "margins", "on") == "on",
                                  on_solved=drawing.start if drawing.lane is not None else None)
    from robust_imdp.io.result_file import staged_outputs

    # the new result and figures are written beside the old ones and replace them only when all are complete
    stage = None
    try:
        with staged_outputs(out, RESULT_OUTPUTS) as stage:
            drawing.finish(result)  # helper processes draw while this one writes the result
            save_result(result, stage.path)
            figures = drawing.collect(stage.path)
    except KeyboardInterrupt:
        if stage is not None and stage.committed:  # Ctrl-C during the swap: held back until it was over
            args.interrupt_note = f"interrupted after the new result was complete: it is in {out}"
        raise
    print(result.summary())
    print(f"wrote {out / 'result.json'}" + (f" and {len(figures)} figures in {out}" if figures else " (no figures)"))
    return Exit.OK


# --------------------------------------------------------------------------- true systems
class _UserSystem:
    """A user's true system, checked once and wrapped so that its errors name it.

    The interface (the one :func:`robust_imdp.validate.simulate` uses): ``mode_names``, a
    sequence of str, and ``step(x (k, n) float array, modes (k,) int array of indices into
    mode_names, rng numpy Generator) -> (k, n) float array``, the next states.
    """

    def __init__(self, obj, where: str):
        names = getattr(obj, "mode_names", None)
        if isinstance(names, str) or names is None or not all(isinstance(m, str) for m in names):
            raise InvalidInputError(
                f"--true-system {where} must have mode_names, a sequence of mode-name strings; got "
                f"{names!r}")
        if not callable(getattr(obj, "step", None)):
            raise InvalidInputError(
                f"--true-system {where} must have a method step(x (k, n), modes (k,) int, rng) -> (k, n); "
                f"{type(obj).__name__} has none")
        self.mode_names = tuple(names)
        self._obj, self._where = obj, where

    def step(self, x, modes, rng):
        try:
            return self._obj.step(x, modes, rng)
        except Exception as exc:  # the user's code, not ours: say whose it is
            raise InvalidInputError(
                f"--true-system {self._where}: step(x, modes, rng) raised {type(exc).__name__}: {exc} "
                "(--debug shows the traceback)") from exc


def _load_true_system(spec: str):
    """A case study's true system, or the class / object NAME of the Python file in ``FILE.py:NAME``."""
    import importlib.util

    file, sep, name = spec.rpartition(":")
    if not (sep and file.endswith(".py")):
        if spec.endswith(".py") or ".py:" in spec:
            raise InvalidInputError(
                f"--true-system must be a case study name or FILE.py:NAME (NAME: a class or object in "
                f"FILE.py); got {spec!r}")
        from robust_imdp.casestudies.systems import true_system

        return true_system(spec)
    path = Path(file)
    where = f"{path}:{name}"
    if not name.isidentifier():
        raise InvalidInputError(f"--true-system {spec!r}: NAME must be a Python name; got {name!r}")
    if not path.is_file():
        raise InvalidInputError(f"--true-system {spec!r}: file {path} not found")
    module_name = f"_robust_imdp_true_system_{abs(hash(str(path.resolve())))}"
    loader_spec = importlib.util.spec_from_file_location(module_name, path)
    module = importlib.util.module_from_spec(loader_spec)
    sys.path.insert(0, str(path.resolve().parent))  # the file may import its neighbours
    try:
        loader_spec.loader.exec_module(module)
    except Exception as exc:
        raise InvalidInputError(
            f"--true-system {where}: {path} cannot be run ({type(exc).__name__}: {exc}; --debug shows the "
            "traceback)") from exc
    finally:
        sys.path.remove(str(path.resolve().parent))
    if not hasattr(module, name):
        public = sorted(k for k in vars(module) if not k.startswith("_"))
        raise InvalidInputError(f"--true-system {where}: {path} defines no {name!r} (it defines {public})")
    obj = getattr(module, name)
    if isinstance(obj, type):
        try:
            obj = obj()
        except TypeError as exc:
            raise InvalidInputError(
                f"--true-system {where}: the class must be constructible with no arguments ({exc}); or give "
                "an object built in the file") from exc
    return _UserSystem(obj, where)


def _cmd_simulate(args) -> int:
    import numpy as np

    from robust_imdp.io.files import load_result
    from robust_imdp.jsonable import jsonable
    from robust_imdp.validate import simulate, validate

    system = _load_true_system(args.true_system)  # before the result: a bad NAME fails first
    res = load_result(args.result)
    if args.max_steps is None:  # one default step cap for the library and the command
        from robust_imdp.validate import MAX_STEPS

        args.max_steps = MAX_STEPS
    report = validate(res, system, n_per_cell=args.n_per_cell, max_steps=args.max_steps,
                      rng=args.seed, confidence=args.confidence)
    print(report.summary())
    out = Path(args.result)
    doc = {k: getattr(report, k) for k in (
        "cells", "n_per_cell", "max_steps", "confidence", "satisfied", "capped", "empirical",
        "wilson_low", "wilson_up", "p_low", "p_up", "outside", "containment_rate",
        "expected_outside", "allowed_outside", "passed")}
    from robust_imdp.io.result_file import staged_outputs

    # validation.json and trajectories.png replace the previous validation together, once both are written
    with staged_outputs(out, VALIDATION_OUTPUTS) as stage:
        (stage.path / "validation.json").write_text(json.dumps(jsonable(doc), indent=1))
        if not args.no_figures and args.paths > 0:
            import matplotlib.pyplot as plt

            from robust_imdp.plotting import plot_trajectories, plot_trajectory_panels

            d = len(res.space_lower)
            rng = np.random.default_rng(args.seed + 1)
            x0 = res.space_lower + rng.random((args.paths, d)) * (res.space_upper - res.space_lower)
            tr = simulate(res, system, x0, max_steps=args.max_steps, rng=rng, record=True)
            if d == 2:
                fig, ax = plt.subplots(figsize=(5.6, 5.6), constrained_layout=True)
                plot_trajectories(res, tr, ax)
            else:  # 1-D: the state against the step; 3-D and more: projections on pairs of coordinates
                fig = plot_trajectory_panels(res, tr)
            fig.savefig(stage.path / "trajectories.png", dpi=130)
            plt.close(fig)
    if not report.passed:
        print(f"robust-imdp: validation failed: {len(report.outside)} of {len(report.cells)} cells are flagged, more "
              f"than the {report.allowed_outside} that chance allows at confidence {report.confidence:g}; the "
              "result's bounds are contradicted by this system (see validation.json)", file=sys.stderr)
        return Exit.ERROR
    return Exit.OK


# --------------------------------------------------------------------------- export
def _cmd_export(args) -> int:
    import numpy as np

    from robust_imdp.io.formats import MAX_ENTRIES, write_drn, write_prism_explicit
    from robust_imdp.io.files import load_result

    res = load_result(args.result)
    key = res.parameters.get("abstraction_key")
    cache = args.cache if args.cache is not None else Path(args.result) / "cache"
    file = cache / f"abstraction-{key}.npz"
    if key is None or not file.exists():
        raise InvalidInputError(
            f"export needs the abstraction of this result, abstraction-{key}.npz in the run's cache {cache}; "
            f"it is not there: pass the run's --cache, or run `robust-imdp run PROBLEM --out {args.result}` again")
    from robust_imdp.abstraction.factored import is_factored
    from robust_imdp.pipeline.cache import cache_entry_problem, load_abstraction_file

    why = cache_entry_problem(file)
    if why is None:
        try:
            abstraction = load_abstraction_file(file)
        except Exception as exc:  # a damaged file that still matches its checksum, or a foreign one
            if interrupt_in(exc) is not None:
                raise
            why = f"cannot be read ({type(exc).__name__}: {exc})"
    if why is not None:
        raise InvalidInputError(
            f"export needs the abstraction of this result; the cache entry {file} {why}: run `robust-imdp run "
            f"PROBLEM --out {args.result}` again to rebuild it")
    form = None
    if is_factored(abstraction):  # DRN and PRISM hold joint models: the joint expansion (docs/factored.md)
        from robust_imdp.models.factored import MAX_JOINT_ENTRIES

        entries = abstraction.joint_entries()
        if entries > MAX_JOINT_ENTRIES:
            raise InvalidInputError(
                f"this result's abstraction is factored (per-axis interval vectors, docs/factored.md); DRN and PRISM "
                f"hold joint models, and its joint expansion has {entries:,} entries, more than the "
                f"{MAX_JOINT_ENTRIES:,} export limit: export a coarser grid, or run with [abstraction].form = 'joint'")
        imdp = abstraction.to_joint()
        form = ("factored: the joint expansion of the per-axis marginals (FactoredIMDP.to_joint: its rows contain "
                "every product law; p_low / p_up of result.json come from the factored solver, at least as tight)")
    else:
        imdp = abstraction.imdp
    n = res.n_cells
    if imdp.n_states != n + 1:
        raise InvalidInputError(f"{file}: the abstraction has {imdp.n_states} states; result.json has {n} cells "
                                "(+ 1 outside state)")
    states = {"format": "robust_imdp.export/1", "kind": "product" if args.product else "abstraction",
              "n_cells": n, "outside_state": n, "actions": list(res.modes),
              "action_meaning": "action a applies mode actions[a]", **({"form": form} if form else {})}
    if args.product:
        from types import SimpleNamespace

        from robust_imdp.solvers.product import materialize_product

        S = res.dfa_delta.shape[0]
        # Materialising lists every floor mass explicitly: refuse before building what cannot be written.
        per_row = np.where(imdp.floor > 0, imdp.n_states, np.diff(imdp.row_ptr))
        entries = int(per_row.sum()) * S
        if entries > MAX_ENTRIES:
            raise InvalidInputError(
                f"the product has {S} DFA states x {imdp.n_states} states, about {entries:,} listed transitions "
                f"with the floors written out, more than the {MAX_ENTRIES:,} export limit; export the abstraction "
                "alone (without --product)")
        letters = np.concatenate([res.label_letters, [0]])  # the outside state's letter is never read
        dfa = SimpleNamespace(n_states=S, initial=res.dfa_initial, accepting=res.dfa_accepting, delta=res.dfa_delta)
        safety = getattr(res, "semantics", "reach") == "safety"  # target: the bad states; value 1 - P(reach)
        prod = materialize_product(imdp, letters, dfa, avoid=[n], semantics="safety" if safety else "reach")
        initial = prod.initial[:n]  # the cells' initial product states (the outside state has one too)
        model, target, labels = prod.imdp, prod.target, {"avoid": prod.avoid}
        states.update({"dfa_states": S, "state": "s * (n_cells + 1) + q for DFA state s and state q",
                       "initial": initial, "horizon": res.horizon,
                       "values": ("from initial[q]: 1 - (min-max of reaching target) = p_low[q], 1 - (min-min) = "
                                  "p_up_star[q] of result.json (safety reading)" if safety else
                                  "from initial[q]: max-min = p_low[q], max-max = p_up_star[q] of result.json")})
    else:
        regions = sorted({a for lab in res.labels for a in lab})
        model, target, initial = imdp, None, np.arange(n)
        labels = {a: np.array([a in lab for lab in res.labels] + [False]) for a in regions}
        labels["outside"] = np.arange(n + 1) == n
    out: Path = args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.format == "drn":
        write_drn(model, out, target=target, labels=labels, initial=initial)
        written = [str(out)]
        meta = out.with_name(out.name + ".states.json") if out.suffix != ".drn" else out.with_suffix(".states.json")
    else:
        prefix = out.with_suffix("") if out.suffix == ".tra" else out
        written = write_prism_explicit(model, prefix, target=target, labels=labels, initial=initial)
        if args.product and res.horizon is not None:  # the k-step values: bounded until
            props = Path(str(prefix) + ".props")
            opt = "min" if getattr(res, "semantics", "reach") == "safety" else "max"  # safety: 1 - these
            props.write_text(f'P{opt}{"max" if opt == "min" else "min"}=? [ F<={int(res.horizon)} "target" ]\n'
                             f'P{opt}{opt}=? [ F<={int(res.horizon)} "target" ]\n')
        meta = Path(str(prefix) + ".states.json")
    from robust_imdp.jsonable import jsonable

    meta.write_text(json.dumps(jsonable(states), indent=1))
    written.append(str(meta))
    print(f"wrote {', '.join(written)}: {model.n_states} states, {model.n_choices} choices"
          + (f" (product of {n} cells + outside with {states['dfa_states']} DFA states)" if args.product else
             f" ({n} cells + the outside state {n})")
          + ("; the factored abstraction's joint expansion" if form else ""))
    return Exit.OK


def _cmd_example(args) -> int:
    from robust_imdp.casestudies.systems import write_problem_files

    path = write_problem_files(args.name, args.out, seed=args.seed, formula=args.formula)
    print(f"wrote {path} and its data file")
    return Exit.OK


def _cmd_suggest(args) -> int:
    from robust_imdp.io.files import load_problem
    from robust_imdp.pipeline.run import synthesize_from_data
    from robust_imdp.synthesis.suggest import suggest_samples

    if not (args.result / "result.json").exists():
        raise InvalidInputError(f"{args.result}: no result.json; run `robust-imdp run PROBLEM --out {args.result}` "
                                "first")
    problem = _tightened(load_problem(args.problem), args)
    cache = args.cache or args.result / "cache"
    result = synthesize_from_data(problem, progress=False, abstraction_cache=cache)
    if not result.from_cache:
        print(f"robust-imdp: note: {cache} did not hold this problem's abstraction; it was computed again",
              file=sys.stderr)
    requests = suggest_samples(result, args.budget)
    out = Path(args.out or args.result / "suggestions.csv")
    names = list(problem.dim_names) if getattr(problem, "dim_names", None) else \
        [f"x_{i + 1}" for i in range(len(problem.space_lower))]
    from robust_imdp.io.result_file import staged_outputs
    from robust_imdp.synthesis import suggest as _suggest

    with staged_outputs(out.parent, (out.name,)) as stage:  # the previous CSV stays until the new one is complete
        _suggest.write_requests(requests, stage.path / out.name, names)
    undecided = int((result.class_names == "maybe").sum())
    print(f"wrote {out}: {len(requests)} sample requests for {undecided} undecided cells")
    for r in requests[:5]:  # radius_change as the CSV writes it (the decrease of the error radius, > 0)
        print(f"  x = {', '.join(f'{v:.4g}' for v in r.x)}  mode {r.mode}: cell {r.cell}, {r.reason}; "
              f"radius_change {r.radius_change:.6g}")
    return Exit.OK


def _cmd_improve(args) -> int:
    from robust_imdp.improve import command

    return command(args, _load_true_system(args.true_system))


#: The files ``calibrate`` writes (replaced as one set, ``io.result_file.staged_outputs``).
CALIBRATION_OUTPUTS = ("calibration.json", "calibration.png")


def _cmd_calibrate(args) -> int:
    from robust_imdp.io.files import load_problem
    from robust_imdp.io.result_file import staged_outputs
    from robust_imdp.jsonable import jsonable

    created = _writable_dir(args.out, "--out")
    try:
        problem = load_problem(args.problem)
        progress = None if args.quiet else (lambda line: print(line, file=sys.stderr, flush=True))
        cal = problem.calibrate(folds=args.folds, rng=args.seed, keep_lengthscale=args.keep_lengthscale,
                                workers=args.workers, progress=progress)
        with staged_outputs(args.out, CALIBRATION_OUTPUTS) as stage:  # the previous files stay until all are new
            (stage.path / "calibration.json").write_text(json.dumps(jsonable(cal.to_dict()), indent=1))
            if not args.no_figures:
                from robust_imdp.plotting import save_calibration_figure

                save_calibration_figure(cal, stage.path / "calibration.png")
    except BaseException:
        _remove_if_empty(created)
        raise
    print(cal.summary())
    print(f"wrote {args.out / 'calibration.json'}" + ("" if args.no_figures else " and calibration.png")
          + f"; {args.problem} is unchanged")
    return Exit.OK


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings read like the errors: ``robust-imdp: warning: <message>``, no source line."""
    print(f"robust-imdp: warning: {message}", file=sys.stderr if file is None else file, flush=True)


def main(argv=None) -> int:
    """Entry point of ``robust-imdp``; returns the exit status."""
    from robust_imdp._blas import quiet_openmp_waits

    quiet_openmp_waits()  # before any parallel kernel loads the OpenMP runtime (robust_imdp._blas.OMP_SPIN)
    args = _parser().parse_args(argv)
    commands = {"run": _cmd_run, "simulate": _cmd_simulate, "export": _cmd_export, "example": _cmd_example,
                "suggest": _cmd_suggest, "improve": _cmd_improve, "calibrate": _cmd_calibrate}
    try:
        with warnings.catch_warnings():
            if not args.debug:  # --debug keeps Python's format, with the source line
                warnings.showwarning = _show_warning
            # the library's own deprecations (e.g. a problem file's former table names) are for the user
            warnings.filterwarnings("default", category=DeprecationWarning, module=r"robust_imdp\.")
            return commands[args.command](args)
    except KeyboardInterrupt:
        if args.debug:
            raise
        print(f"robust-imdp: {getattr(args, 'interrupt_note', 'interrupted')}", file=sys.stderr)
        return Exit.INTERRUPTED
    except Exception as exc:
        return _failure(exc, args)


def _failure(exc: Exception, args) -> int:
    """Print one line for ``exc`` and return the exit status (or re-raise it with ``--debug``)."""
    if interrupt_in(exc) is not None:
        # Ctrl-C inside compiled code arrives as a SystemError (or a wrapper) caused by the
        # KeyboardInterrupt: it is the interrupt, whatever stage it stopped
        if args.debug:
            raise exc
        print(f"robust-imdp: {getattr(args, 'interrupt_note', 'interrupted')}", file=sys.stderr)
        return Exit.INTERRUPTED
    if type(exc).__name__ == "KilledWorker":  # distributed: a worker was lost for good
        print(f"robust-imdp: a Dask worker was lost ({exc}); "
              f"{getattr(args, 'interrupt_note', 'interrupted')}", file=sys.stderr)
        return Exit.INTERRUPTED
    if isinstance(exc, (RobustImdpError, ValueError, OSError, KeyError)):
        if args.debug:
            raise exc
        msg = str(exc) if not isinstance(exc, KeyError) else f"missing entry {exc}"
        if isinstance(exc, OSError) and getattr(exc, "filename", None):
            msg = f"{exc.strerror}: {exc.filename}"
        print(f"robust-imdp: error: {msg}", file=sys.stderr)
        return Exit.ERROR
    # a bug, not bad input: still no traceback unless --debug
    if args.debug:
        raise exc
    print(f"robust-imdp: internal error ({type(exc).__name__}: {exc}); please report it, "
          "and rerun with --debug for the traceback", file=sys.stderr)
    return Exit.INTERNAL


def console_main() -> None:
    """The ``robust-imdp`` command (the console script): :func:`main`, then :func:`end_process` with its status."""
    end_process(main())


def end_process(status: int) -> None:
    """End this process with ``status`` the way the interpreter's exit would, without its teardown.

    In order, as ``Py_FinalizeEx``: wait for the threads that are not daemons (``threading._shutdown``, which also
    shuts the thread pools down), run the ``atexit`` functions (temporary folders' finalizers, the pools' and
    the logging's clean-ups), flush stdout and stderr; then ``os._exit``. What is skipped is the teardown of every
    module and object, which frees nothing the operating system does not free at the exit: 0.15-0.2 s of one core
    after a 2-D run of 16,384 cells (0.03 s with this), a serial part of every run. A flush that fails (the reader
    of a pipe has gone) exits 120, as Python does. Every file the command writes is closed and renamed before
    :func:`main` returns (``io.result_file.staged_outputs``; the cache entries' writes are complete)."""
    import atexit
    import os
    import threading

    shutdown = getattr(threading, "_shutdown", None)
    if shutdown is None or not hasattr(atexit, "_run_exitfuncs"):  # another interpreter: its own exit
        sys.exit(status)
    shutdown()
    atexit._run_exitfuncs()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):
        os._exit(120)
    os._exit(int(status))


if __name__ == "__main__":  # pragma: no cover
    console_main()
