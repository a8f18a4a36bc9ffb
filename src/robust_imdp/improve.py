"""The sampling loop: suggest samples, simulate them, re-bound only the cells the new data can tighten, re-solve.

:func:`improve` starts from a problem's data (or from an interrupted loop's state) and repeats, round by round
(default :func:`auto_rounds`: up to 8 rounds, a closed loop):

1. **suggest** ``budget / rounds`` sample requests (``synthesis.suggest.suggest_samples``) for the look-ahead's
   targets (:func:`_targets`): every undecided cell's box is shrunk by a share of its predicted RKHS term and
   the model re-solved; the cells that turn Q_yes are the targets, each for the mode the look-ahead uses
   there, weighted up when it is near today's Q_yes (its own smaller box meets the threshold on today's
   values, or few expected steps to Q_yes). Requests maximise the capped share of each target's needed
   drop; the rest of the round (targets met, or none) goes to the undecided cells' summed radius change;
2. **simulate** one step of the user's true system from each request (``step(x, modes, rng)``, the
   interface of ``validate.simulate``); a simulator that raises, returns another shape, NaN / inf
   or states outside X is refused with a message naming the round and the request;
3. **append** the samples to the loop's data file with their ``round`` (written under a temporary
   name and renamed: the file is never half-written);
4. **check** the assumption with *all* the data (new data may refute the RKHS bound B), incrementally
   (:class:`IncrementalCheck`): per mode and component, a *witness* -- a function of certified RKHS norm
   <= B that fits every sample within the check's noise allowance -- proves that the full check would
   pass; last round's witness is kept when it fits the new samples, else a new one is fitted to all the
   data (kernel ridge, certified), else the component gets the full check (the SOCP minimum norm), whose
   refusal is the full check's, message included;
5. **re-bound** only the cells whose certificates the new points can change: with local weights
   the cells whose pool of nearest points now holds a new point, otherwise the cells whose error
   radius the new points shrink by more than :data:`REBOUND_TOL` of the cell's half-width (the power
   function of ``synthesis.suggest``, with and without them); each new box is intersected with the
   cell's previous box;
6. **re-abstract** the rows of the re-bounded cells (a row depends only on its own cell's image
   box and the partition: ``abstraction.rows.abstract_rows``) and **re-solve**.

Soundness. The route is the deterministic bound under bounded noise (``error_bound`` ``"optimal"``
or ``"ridge"``, ``iid_noise = false``): a cell's certificate holds for *any* subset of the data and
for inputs chosen in any way, adaptively from earlier data included. So a box kept from an earlier
round (certified from fewer data) stays valid, a new box is valid, and so is their intersection.
The iid route assumes inputs chosen independently of the noise, which adaptive requests are not:
it is refused (``io.data_file.ADAPTIVE_IID_MESSAGE``); unbounded noise too (its data-noise event
depends on the number of samples, so the events of boxes of different rounds do not combine into
the stated confidence). ``diagnostics.statement`` says so.

Interrupting and resuming. After each round the cell boxes are saved (``improve-state.npz``) and
``result.json`` is rewritten, both atomically, after the data file: the last complete round's
result stays valid. Run again with the same output directory: samples already in the data file
but not yet bounded (interrupted after the append) are bounded first, then the remaining rounds run.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError

__all__ = ["ImproveRound", "ImproveResult", "IncrementalCheck", "improve", "auto_rounds", "REBOUND_TOL", "STATE_FILE",
           "DATA_FILE"]

#: Without local weights, a cell is re-bounded when the new points lower the RKHS term of its error
#: radius at its centre by more than this fraction of its smallest half-width (the power-function
#: estimate of ``synthesis.suggest``, eq. S2); the others keep their box: sound for any subset of the
#: data, and the new points barely move them.
REBOUND_TOL = 0.01
#: Most points of a mode used for that estimate (an evenly spaced subset beyond it, as in suggest).
MAX_POWER_POINTS = 2000
#: The look-ahead (docs/sampling.md, "Look-ahead targets"): the fractions of the undecided cells' RKHS terms kept in
#: its solves, largest first; a Q_? cell's target is the largest at which the solve makes it Q_yes.
LOOKAHEAD_LEVELS = (0.75, 0.5, 0.25, 0.0)
#: Most undecided cells for the look-ahead (each level rebuilds their rows and solves); beyond it the round's
#: requests come from the undecided cells' summed radius change (suggest's own frontier rule).
LOOKAHEAD_MAX_CELLS = 4096
#: Steps of the look-ahead solves of a factored model without a horizon (a k-step value is a lower bound of the
#: unbounded one: a ranking that errs towards fewer targets).
LOOKAHEAD_FACTORED_HORIZON = 64
#: Precision of the look-ahead solves (their values only rank requests).
LOOKAHEAD_PRECISION = 1e-6
#: A target's predicted shrink must exceed this fraction of its cell's smallest half-width (else its box is at
#: the noise floor: more data barely move it, and the cell turned Q_yes through its neighbours' boxes).
TARGET_TOL = 0.01
#: Extra weight of a frontier target: a cell whose own shrunk row, one step on today's lower values, meets the
#: threshold (it turns Q_yes by itself: the next cell of the path to Q_yes).
FRONTIER_WEIGHT = 10.0
#: Cap of a target's expected steps to Q_yes (``_hops``); its extra weight halves with every step beyond the first.
MAX_HOPS = 12
#: A target's weight is divided by ``1 + (the loop's samples in its cell and mode so far) / SPENT_SCALE``: under
#: bounded noise the worst-case bound does not average repeated samples, so a target that stays undecided after
#: several of them is at its noise floor more likely than the look-ahead says.
SPENT_SCALE = 3.0
HOPS_SWEEPS = 500
#: Default rounds (:func:`auto_rounds`): at most this many, of at least MIN_ROUND samples each.
AUTO_ROUNDS = 8
MIN_ROUND = 10
#: The loop's saved state (cell boxes, last complete round) and its data file, in the output directory.
STATE_FILE = "improve-state.npz"
DATA_FILE = "data.csv"
#: Cells per bound task of a round (the new cells of one mode).
ROUND_CHUNK = 256
#: What the statement adds about the adaptively chosen inputs.
ADAPTIVE_NOTE = ("; inputs of rounds > 0 were chosen from earlier data (robust-imdp improve): the deterministic "
                 "bound holds for any inputs, and a cell's box kept from an earlier round was certified from a "
                 "subset of the data")

#: What the diagnostics say about the incremental check's numbers.
INCREMENTAL_NOTE = ("min_norm.minimum is a certified lower bound of the data-implied minimum RKHS norm (the last full "
                    "check's, or the single points' on all data); witness_norm_upper is the certified norm of a "
                    "function of norm <= rkhs_bound that fits all data within the check's allowance: an upper bound "
                    "of that minimum, which shows that the data do not refute rkhs_bound")


@dataclass(frozen=True)
class ImproveRound:
    """One round of :func:`improve` (round 0: the starting data).

    Attributes
    ----------
    round, added, n_data : int
        Round number, samples added in the round, samples in the data after it.
    counts : dict ``{"yes", "no", "maybe"} -> int`` (cells)
    rebound : int
        Cell bounds (cells x modes) recomputed in the round.
    seconds : dict
        ``suggest``, ``simulate``, ``write``, ``check``, ``bound``, ``abstract``, ``solve``, ``total``.
    """

    round: int
    added: int
    n_data: int
    counts: dict
    rebound: int
    seconds: dict

    def line(self) -> str:
        c, s = self.counts, self.seconds
        return (f"round {self.round}: +{self.added} samples ({self.n_data} in all), {self.rebound} cell bounds "
                f"re-bounded; Q_yes {c['yes']}  Q_no {c['no']}  Q_? {c['maybe']}; {s['total']:.1f} s (bound "
                f"{s['bound']:.1f}, solve {s['solve']:.1f})")

    def to_dict(self) -> dict:
        return {"round": self.round, "added": self.added, "n_data": self.n_data, "counts": dict(self.counts),
                "rebound": self.rebound, "seconds": dict(self.seconds)}


@dataclass(frozen=True, eq=False)
class ImproveResult:
    """Output of :func:`improve`: the last round's result, its cell boxes, the rounds and why the loop stopped."""

    result: object
    cell_bounds: object
    rounds: tuple
    stopped: str
    data_file: Path | None = None
    history: list = field(default_factory=list, repr=False)  # per round: (image_lower, image_upper) if kept


# ---------------------------------------------------------------------------------------------- checks
def _refuse_unsupported(problem) -> None:
    """The loop needs the deterministic bound under bounded noise on the grid (see the module docstring)."""
    from robust_imdp.io.data_file import ADAPTIVE_IID_MESSAGE

    if problem.iid_noise:
        raise InvalidInputError("improve: " + ADAPTIVE_IID_MESSAGE)
    if problem.error_bound not in ("optimal", "ridge"):
        raise InvalidInputError(f"improve needs error_bound 'optimal' or 'ridge' (the deterministic bound, valid for "
                                f"adaptively chosen inputs); got {problem.error_bound!r}")
    if not getattr(problem.noise, "bounded", False):
        raise InvalidInputError(
            "improve needs bounded noise: with unbounded noise the data-noise event depends on the number of samples, "
            "so boxes certified in different rounds do not share one event")
    if problem.refine is not None:
        raise InvalidInputError("improve works on the grid: remove [refine] (refine the improved result afterwards)")


def _request_text(k: int, x, mode: str) -> str:
    return f"request {k + 1} (x = {np.asarray(x).tolist()}, mode {mode!r})"


def _simulate(true_system, xs, modes, names, rng, rnd: int, lower, upper, allow_outside: bool) -> np.ndarray:
    """One step of ``true_system`` from every request, checked; errors name the round and the request."""
    sys_names = list(true_system.mode_names)
    missing = [m for m in names if m not in sys_names]
    if missing:
        raise InvalidInputError(f"improve: the true system has no modes {missing}; it has {sys_names}")
    to_sys = np.array([sys_names.index(m) for m in names], dtype=np.int64)
    k, n = xs.shape
    try:
        raw = true_system.step(xs.copy(), to_sys[modes], rng)
    except KeyboardInterrupt:
        raise
    except Exception as exc:
        raise InvalidInputError(f"improve round {rnd}: the true system's step raised {type(exc).__name__}: {exc} "
                                f"(on the round's {k} requests; the first is {_request_text(0, xs[0], names[modes[0]])}"
                                "); the previous round's result is kept") from exc
    try:
        xn = np.asarray(raw, dtype=float)
    except (TypeError, ValueError):
        xn = np.asarray(None)
    if xn.shape != (k, n):
        raise DimensionError(f"improve round {rnd}: the true system's step must return the next states as a ({k}, "
                             f"{n}) float array, one row per request; got {type(raw).__name__} of shape "
                             f"{getattr(xn, 'shape', None)}; the previous round's result is kept")
    bad = np.flatnonzero(~np.all(np.isfinite(xn), axis=1))
    if bad.size:
        r = int(bad[0])
        raise InvalidInputError(f"improve round {rnd}: the true system returned NaN or inf for {bad.size} of {k} "
                                f"requests (first: {_request_text(r, xs[r], names[modes[r]])} -> {xn[r].tolist()}); "
                                "the previous round's result is kept")
    out = np.flatnonzero(np.any((xn < lower) | (xn > upper), axis=1))
    if out.size and not allow_outside:
        r = int(out[0])
        raise InvalidInputError(f"improve round {rnd}: the true system returned states outside X = [{lower.tolist()}, "
                                f"{upper.tolist()}] for {out.size} of {k} requests (first: "
                                f"{_request_text(r, xs[r], names[modes[r]])} -> {xn[r].tolist()}); pass "
                                "allow_outside=True (--allow-outside) if the system can leave X; the previous "
                                "round's result is kept")
    return xn


# ---------------------------------------------------------------------------------------------- files
def _write_data(path: Path, data, rounds, names) -> None:
    """The loop's data file with its ``round`` column, written under a temporary name and renamed."""
    from robust_imdp.io.data_file import write_data_file

    tmp = path.with_name(path.name + ".tmp")
    write_data_file(tmp, data.x, data.u, data.x_next, modes=names, rounds=rounds)
    os.replace(tmp, path)


def _save_state(out: Path, cell_bounds, rnd: int, n_data: int, rounds: list, diagnostics: dict) -> None:
    import json

    from robust_imdp.jsonable import jsonable
    from robust_imdp.pipeline.cache import _savez, write_cache_entry

    doc = json.dumps([r.to_dict() for r in rounds])
    write_cache_entry(out / STATE_FILE, lambda tmp: _savez(tmp, {
        "image_lower": cell_bounds.image_lower, "image_upper": cell_bounds.image_upper,
        "round": np.array(rnd), "n_data": np.array(n_data), "rounds": np.array(doc),
        "diagnostics": np.array(json.dumps(jsonable(diagnostics)))}))


def _load_state(out: Path, n_modes: int, n_cells: int, dim: int):
    """(CellBounds, last round, samples bounded, rounds, diagnostics) of an interrupted loop, or None."""
    import json

    from robust_imdp.abstraction.rows import CellBounds

    f = out / STATE_FILE
    if not (f.exists() and (out / DATA_FILE).exists()):
        return None
    with np.load(f, allow_pickle=False) as z:
        lo, hi = np.array(z["image_lower"]), np.array(z["image_upper"])
        rnd, n_data, doc = int(z["round"]), int(z["n_data"]), json.loads(str(z["rounds"]))
        diagnostics = json.loads(str(z["diagnostics"]))
    if lo.shape != (n_modes, n_cells, dim):
        raise InvalidInputError(f"improve: {f} holds boxes of shape {lo.shape}, not ({n_modes}, {n_cells}, {dim}) "
                                "of this problem's grid; use another output directory")
    rounds = [ImproveRound(d["round"], d["added"], d["n_data"], d["counts"], d["rebound"], d["seconds"]) for d in doc]
    return CellBounds(lo, hi, None), rnd, n_data, rounds, diagnostics


def _read_loop_data(out: Path, problem):
    from robust_imdp.io.data_file import read_data_file, read_rounds
    from robust_imdp.models.system import Dataset

    names = list(problem.mode_names)
    x, u, xn, _ = read_data_file(out / DATA_FILE, names, len(problem.space_lower))
    return Dataset(x, u, xn, modes=tuple(names)), read_rounds(out / DATA_FILE)


# ---------------------------------------------------------------------------------------------- the check
def _check_jobs(problem, res, nb) -> list:
    """Per mode and component: ``(u, i, norm_task arguments, B)``, the very jobs of the full check
    (``pipeline.bound_stage._check_assumption``: ``rkhs_check.check_assumption`` with one setting,
    ``assumptions.check_modes`` per mode and component)."""
    from robust_imdp.pipeline.bound_stage import _noise_allowance, _one_setting, _shared_allowance
    from robust_imdp.pipeline.problem import _settings

    jobs = []
    one = _one_setting(problem)
    if one:
        shared = _shared_allowance(problem, nb)
        ls, tau, B = problem.gp_options.get("lengthscale", 1.0), problem.misspecification, float(problem.rkhs_bound)
    else:
        st, allow = _settings(problem), _noise_allowance(problem, nb)
    for u, (X, Y, _) in enumerate(res):
        Y = np.asarray(Y, float).reshape(np.shape(X)[0], -1)
        for i in range(Y.shape[1]):
            if one:  # check_assumption's job: max_points 300, the SOCP always
                jobs.append((u, i, (X, Y[:, i], ls, float(shared[i]), tau, 300, True), B))
            else:  # check_modes's job: the SOCP only for B > 0
                Bu = float(st.rkhs_bound[u, i])
                jobs.append((u, i, (X, Y[:, i], st.lengthscale[u, i], float(allow[u, i]),
                                    float(st.misspecification[u, i]), 300, Bu > 0), Bu))
    return jobs


@dataclass
class _Component:
    """What the incremental check keeps of one mode and component between rounds."""

    dbar: float          # the allowance it was checked with (rkhs_check.data_allowance)
    x: np.ndarray        # the points it was checked at (a later round's first rows must be these)
    y: np.ndarray
    witness: object      # rkhs_check.Witness fitting (x, y), or None (the full check passed without one)
    minimum: float       # a certified lower bound of the minimum norm of (x, y) at dbar
    n_points: int        # the points behind ``minimum``


class IncrementalCheck:
    """The assumption check of a growing data set, with the full check's decision (module step 4).

    Call it with the problem (its data: last round's samples first, in the same order, then the new
    ones) and the residual data ``pipeline.bound_stage._residual_data(problem)``; it returns
    ``(checks, noise_bound, report)`` like ``_check_assumption`` plus one report row per component.

    Per mode and component, with the full check's allowance ``dbar'`` (``rkhs_check.data_allowance``)
    and bound B:

    1. **kept**: last round's witness h (``rkhs_check.Witness``, ``||h|| <= norm_upper <= B``) fitted
       last round's points within ``dbar'``; when the earlier points and ``dbar'`` are unchanged and h
       fits the new points within ``dbar'`` (``rkhs_check.witness_residuals``, rounded outward), h fits
       all the data;
    2. **refitted**: otherwise a new witness fitted to all the data (``rkhs_check.fit_witness``: kernel
       ridge fits, then, with ``socp_witness``, the minimum-norm function within 0.99 dbar');
    3. **full check**: otherwise the component's own job of the full check (``rkhs_check.norm_task``).

    Why the decision is the full check's: the full check refuses B when a certified lower bound of
    ``min { ||f|| : |f(x_i) - y_i| <= dbar' }`` (over a subset of the points) exceeds B. With a witness
    h that fits all the points, that minimum is ``<= ||h|| <= B``, so the full check passes too. A
    component of step 3 gets the full check's own result. When one of them exceeds B, the full check
    runs on all the data and raises its own ``AssumptionError`` (the same message).

    Honest numbers: a component's ``NormCheck.minimum`` stays a certified *lower* bound of the minimum
    norm -- the largest of the last full check's (more data only raise the minimum; kept while
    ``dbar'`` is unchanged) and the single points' bound on all the data (``min_rkhs_norm(solver=False)``).
    A witness's norm is reported apart, as ``witness_norm_upper``, an *upper* bound of the minimum norm.
    """

    def __init__(self, socp_witness: bool = True):
        self.state: dict = {}
        self.socp_witness = bool(socp_witness)  # step 2 may solve one SOCP for a witness (rkhs_check.fit_witness)

    def seed(self, problem, res, checks=None, min_norm_rows=None) -> None:
        """Start from a full check of ``problem``'s data (its NormChecks, or the diagnostics' ``min_norm``
        rows) without a witness: the next call fits one."""
        from robust_imdp.bounds.rkhs import noise_bound_at_confidence
        from robust_imdp.bounds.rkhs_check import data_allowance
        from robust_imdp.pipeline.problem import CHECK_DELTA

        nb, _ = noise_bound_at_confidence(problem.noise, sum(x.shape[0] for x, _, _ in res), CHECK_DELTA)
        mins = {}
        if checks is not None:
            mins = {(c.mode, c.output): (float(c.minimum), int(c.n_points)) for c in checks}
        elif min_norm_rows is not None:
            names = list(problem.mode_names)
            mins = {(names.index(r["mode"]), int(r["component"]) - 1): (float(r["minimum"]), int(r["n_points"]))
                    for r in min_norm_rows}
        for u, i, (X, y, _, noise, tau, _, _), _ in _check_jobs(problem, res, nb):
            lo, k = mins.get((u, i), (0.0, 0))
            self.state[(u, i)] = _Component(data_allowance(noise, tau), X.copy(), np.array(y), None, lo, k)

    def __call__(self, problem, res, log):
        from robust_imdp.bounds.rkhs import noise_bound_at_confidence
        from robust_imdp.bounds.rkhs_check import (NormCheck, data_allowance, fit_witness, min_rkhs_norm,
                                                   serial_norms, witness_residuals)
        from robust_imdp.pipeline.bound_stage import _check_assumption
        from robust_imdp.pipeline.problem import CHECK_DELTA

        nb, _ = noise_bound_at_confidence(problem.noise, sum(x.shape[0] for x, _, _ in res), CHECK_DELTA)
        jobs = _check_jobs(problem, res, nb)
        how, wit, full, same = {}, {}, [], {}
        for u, i, args, B in jobs:
            X, y, ls, noise, tau = args[:5]
            dbar = data_allowance(noise, tau)
            prev = self.state.get((u, i))
            n0 = 0 if prev is None else prev.x.shape[0]
            same[(u, i)] = (prev is not None and prev.dbar == dbar and n0 <= X.shape[0]
                            and np.array_equal(prev.x, X[:n0]) and np.array_equal(prev.y, y[:n0]))
            if same[(u, i)] and prev.witness is not None and B >= prev.witness.norm_upper:
                try:  # step 1: h fitted the first n0 points within dbar'; does it fit the new ones?
                    if np.all(witness_residuals(prev.witness, X[n0:], y[n0:]) <= dbar):
                        how[(u, i)], wit[(u, i)] = "witness kept", prev.witness
                        continue
                except InvalidInputError:  # a new point too far from the centres for the certified kernel
                    pass
            w = fit_witness(X, y, ls, noise, tau, B, socp=self.socp_witness)  # step 2
            if w is not None:
                how[(u, i)], wit[(u, i)] = "witness refitted", w
            else:
                how[(u, i)] = "full check"
                full.append((u, i, args, B))
        results = dict(zip([(u, i) for u, i, _, _ in full], serial_norms([a for _, _, a, _ in full])))
        if any(results[(u, i)]["minimum"] > B for u, i, _, B in full):
            log.info("assumption check: a component fails; the full check on all the data decides")
            return (*_check_assumption(problem, res, log, None), None)  # raises its AssumptionError
        checks, report = [], []
        for u, i, args, B in jobs:
            X, y, ls, noise, tau = args[:5]
            dbar, prev, idx = data_allowance(noise, tau), self.state.get((u, i)), res[u][2]
            if (u, i) in results:
                r = results[(u, i)]
                lo, k = r["minimum"], r["n_points"]
            else:  # the single points on all data, and the last full check's bound if still at this allowance
                r = min_rkhs_norm(X, y, ls, noise, tau, solver=False)
                lo, k = r["minimum"], 1
                if same[(u, i)] and prev.minimum > lo:  # a bound for a subset of the points, same allowance
                    lo, k = prev.minimum, prev.n_points
            s = r["sample"]
            checks.append(NormCheck(u, i, lo, k, int(idx[s]), r["single_minimum"], float(y[s])))
            w = wit.get((u, i))
            self.state[(u, i)] = _Component(dbar, X.copy(), np.array(y), w, lo, k)
            report.append({"mode": problem.mode_names[u], "component": i + 1, "how": how[(u, i)],
                           "witness_norm_upper": None if w is None else w.norm_upper, "rkhs_bound": B})
        worst = max(checks, key=lambda c: c.minimum)
        log.info(f"assumption check (incremental): {sum(h != 'full check' for h in how.values())} of {len(jobs)} "
                 f"components by a witness; the data need RKHS norm >= {worst.minimum:.4g}")
        return tuple(checks), nb, report


# ---------------------------------------------------------------------------------------------- re-bounding
def _power(points, data, inv_l2, lam: float) -> np.ndarray:
    """The power function at ``points`` (:func:`robust_imdp.synthesis.suggest.power_function`)."""
    from robust_imdp.synthesis.suggest import power_function

    return power_function(points, data, inv_l2, lam, MAX_POWER_POINTS)


def _affected(problem, partition, data, n_old: int) -> list:
    """Per mode: the cells whose certificate the samples ``n_old..`` of ``data`` can change (module step 5)."""
    from robust_imdp.bounds.rkhs_local import local_pools
    from robust_imdp.pipeline.bound_rkhs import _base_settings, _data_noise_bound, _local_settings
    from robust_imdp.pipeline.bound_stage import _failure_budget, _residual_data
    from robust_imdp.synthesis.suggest import _assumption

    res = _residual_data(problem)
    local = _local_settings(problem, res, partition, _data_noise_bound(problem, res, _failure_budget(problem)[0]))
    B, inv_l2, floor = _assumption(problem)
    lo, up = partition.cells_lower, partition.cells_upper
    centre, tol = 0.5 * (lo + up), REBOUND_TOL * 0.5 * np.min(up - lo, axis=1)
    new = np.arange(data.u.shape[0]) >= n_old
    out = []
    for u in range(len(problem.mode_names)):
        x = res[u][0]
        fresh = np.flatnonzero(new[data.u == u])
        if fresh.size == 0 or B[u] <= 0:
            out.append(np.zeros(0, np.int64))
        elif local[u] is not None:  # the cells whose pool gained a point
            pools = local_pools(x, lo, up, _base_settings(problem)["lengthscale"], local[u][0])
            out.append(np.flatnonzero(np.any(pools >= fresh.min(), axis=1)))
        else:
            lam = max((floor[u] / B[u]) ** 2, 1e-10)
            before = np.sqrt(_power(centre, x[:fresh.min()], inv_l2[u], lam))
            after = np.sqrt(_power(centre, x, inv_l2[u], lam))
            out.append(np.flatnonzero(B[u] * (before - after) > tol))
    return out


def _rebound(problem, partition, cell_bounds, cells: list, log, run):
    """New boxes of ``cells[u]`` under mode u (all data), intersected with the previous ones: (CellBounds, count)."""
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.bounds.rkhs import check_ranges
    from robust_imdp.pipeline.bound_rkhs import (_bound_task, _chunk_settings, _data_noise_bound, _mode_settings,
                                                 _share_data, _task_args)
    from robust_imdp.pipeline.bound_stage import _add_known_range, _failure_budget, _known_ranges, _residual_data

    data = _residual_data(problem)
    noise_bound = _data_noise_bound(problem, data, _failure_budget(problem)[0])
    settings = _chunk_settings(problem, noise_bound)
    local, extras = _mode_settings(problem, data, partition, noise_bound)
    sched = run.scheduler(log)
    shared = _share_data(sched, data)
    ilo, ihi = cell_bounds.image_lower.copy(), cell_bounds.image_upper.copy()
    for u, q in enumerate(cells):
        if q.size == 0:
            continue
        lower, upper = partition.cells_lower[q], partition.cells_upper[q]
        starts = list(range(0, q.size, ROUND_CHUNK))
        args = _task_args(problem, shared, lower, upper, local, extras, [(u, s0) for s0 in starts], ROUND_CHUNK)
        lo, hi = np.empty((q.size, ilo.shape[2])), np.empty((q.size, ilo.shape[2]))
        for i, res in sched.run(_bound_task, args, settings):
            sl = slice(starts[i], starts[i] + ROUND_CHUNK)
            lo[sl], hi[sl] = res["lower"], res["upper"]
        check_ranges(lo, hi, u)
        known = _known_ranges(problem, lower, upper)[u]
        if known is not None:
            _add_known_range(lo, hi, known)
        # both boxes contain the image of f_u + g_u over the cell: so does their intersection (max/min are exact)
        ilo[u, q], ihi[u, q] = np.maximum(lo, ilo[u, q]), np.minimum(hi, ihi[u, q])
    return CellBounds(ilo, ihi, None), int(sum(q.size for q in cells))


def _rows(partition, cell_bounds, problem):
    """The abstraction's rows of every cell: joint rows (``abstract_rows``), or in the factored form
    (``Problem.form_choice``; docs/factored.md) the per-axis marginals (``abstraction.factored.factored_rows``)."""
    from robust_imdp.abstraction.rows import abstract_rows

    if problem.form_choice()[0] == "factored":
        from robust_imdp.abstraction.factored import axis_lengths, factored_rows

        return factored_rows(partition, cell_bounds, problem.noise, axis_lengths(partition, cell_bounds, problem.noise))
    return abstract_rows(partition, cell_bounds, problem.noise, None, **_abstraction_options(problem))


def _assemble(partition, rows):
    """The abstraction of :func:`_rows`' rows (joint or factored)."""
    from robust_imdp.abstraction.factored import FactoredRows, assemble_factored
    from robust_imdp.abstraction.rows import assemble_abstraction

    return (assemble_factored if isinstance(rows, FactoredRows) else assemble_abstraction)(partition, [rows])


def _rebuild(partition, rows, cell_bounds, cells, problem):
    """The abstraction's rows with those of ``cells`` recomputed from their new boxes (every other row kept)."""
    from robust_imdp.abstraction.factored import FactoredRows
    from robust_imdp.abstraction.rows import CellBounds, abstract_rows, join_rows, select_rows

    N = partition.n_cells
    redo = np.unique(np.concatenate(cells)) if cells else np.zeros(0, np.int64)
    if redo.size == 0:
        return rows
    if isinstance(rows, FactoredRows):  # the boxes only shrink (intersections), so their runs fit the listed k
        from robust_imdp.abstraction.factored import axis_lengths, factored_rows, replace_cells

        if any(a > b for a, b in zip(axis_lengths(partition, cell_bounds, problem.noise), rows.k)):
            return _rows(partition, cell_bounds, problem)
        new = factored_rows(partition, CellBounds(cell_bounds.image_lower[:, redo], cell_bounds.image_upper[:, redo],
                                                  None), problem.noise, rows.k)
        return replace_cells(rows, redo, new)
    keep = np.setdiff1d(np.arange(N), redo)
    new_rows = abstract_rows(partition, CellBounds(cell_bounds.image_lower[:, redo], cell_bounds.image_upper[:, redo],
                                                   None), problem.noise, None, **_abstraction_options(problem))
    joined = join_rows([select_rows(rows, keep), new_rows]) if keep.size else new_rows
    order = np.empty(N, dtype=np.int64)
    order[np.concatenate([keep, redo])] = np.arange(N)
    return select_rows(joined, order)


def _abstraction_options(problem) -> dict:
    return problem.abstraction_options()


# ---------------------------------------------------------------------------------------------- the loop
@dataclass
class _Loop:
    """The loop's fixed parts and its current state."""

    problem: object
    partition: object
    dfa: object
    log: object
    run: object
    out: Path | None
    cell_bounds: object = None
    check: IncrementalCheck = field(default_factory=IncrementalCheck)
    rows: object = None
    rounds: list = field(default_factory=list)
    diagnostics: dict = field(default_factory=dict)
    result: object = None
    data_rounds: np.ndarray = None

    def solve(self, timer: dict):
        """Assemble the rows, solve, and the Result with the rounds in its diagnostics."""
        from robust_imdp.pipeline.result import Result
        from robust_imdp.pipeline.run import _parameters, _synthesize

        t0 = time.perf_counter()
        abstraction = _assemble(self.partition, self.rows)
        timer["abstract"] = timer.get("abstract", 0.0) + time.perf_counter() - t0
        t0 = time.perf_counter()
        syn, classes = _synthesize(self.problem, self.partition, abstraction, self.dfa, self.log)
        timer["solve"] = time.perf_counter() - t0
        self.result = Result(problem=self.problem, partition=self.partition, abstraction=abstraction, dfa=self.dfa,
                             synthesis=syn, class_names=classes, timings=dict(self.log.timings),
                             parameters=_parameters(self.problem, abstraction), diagnostics=self.diagnostics)
        return self.result

    def record(self, rnd: int, added: int, rebound: int, timer: dict) -> ImproveRound:
        from robust_imdp.io.files import save_result

        c = np.asarray(self.result.class_names)
        timer["total"] = sum(v for k, v in timer.items() if k != "total")
        r = ImproveRound(rnd, added, int(self.problem.data.u.shape[0]),
                         {k: int(np.sum(c == k)) for k in ("yes", "no", "maybe")}, rebound, dict(timer))
        self.rounds.append(r)
        self.diagnostics["improve"] = {"rounds": [x.to_dict() for x in self.rounds],
                                       "data_file": None if self.out is None else str(self.out / DATA_FILE)}
        if self.out is not None:  # the boxes first, then result.json: a result on disk always has its state
            _save_state(self.out, self.cell_bounds, rnd, r.n_data, self.rounds, self.diagnostics)
            save_result(self.result, self.out)
        self.log.info(r.line())
        return r


def _start(loop: _Loop, resume) -> int:
    """Round 0 (bound the grid, abstract, solve) or the interrupted loop's state; returns the last round."""
    from robust_imdp.pipeline.bound_stage import _learn_and_bound, _residual_data

    problem = loop.problem
    timer: dict = {}
    if resume is None:
        t0 = time.perf_counter()
        cache = None if loop.out is None else loop.out / "cache"
        loop.cell_bounds, _, diag = _learn_and_bound(problem, loop.partition, loop.log, loop.run, cache)
        timer["bound"] = time.perf_counter() - t0
        loop.diagnostics = dict(diag)
        loop.check.seed(problem, _residual_data(problem), min_norm_rows=diag.get("assumption", {}).get("min_norm"))
        last, added = 0, 0
    else:
        loop.cell_bounds, last, _, loop.rounds, loop.diagnostics = resume
        added = None
    t0 = time.perf_counter()
    loop.rows = _rows(loop.partition, loop.cell_bounds, problem)
    timer["abstract"] = time.perf_counter() - t0
    loop.solve(timer)
    if added is not None:
        loop.record(0, 0, loop.partition.n_cells * len(problem.mode_names), timer)
    return last


def _update(loop: _Loop, data, n_old: int, rnd: int, timer: dict) -> int:
    """Steps 4-6 for the samples ``n_old..`` of ``data``: check, re-bound, re-abstract, re-solve."""
    from robust_imdp.pipeline.bound_stage import _diagnostics, _residual_data, _failure_budget
    from robust_imdp.pipeline.bound_rkhs import _data_noise_bound, _statement

    problem = loop.problem = loop.problem.replace(data=data)
    t0 = time.perf_counter()
    res = _residual_data(problem)
    checks, check_noise, report = loop.check(problem, res, loop.log)  # all data: new ones may refute B
    timer["check"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    cells = _affected(problem, loop.partition, data, n_old)
    loop.cell_bounds, rebound = _rebound(problem, loop.partition, loop.cell_bounds, cells, loop.log, loop.run)
    timer["bound"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    loop.rows = _rebuild(loop.partition, loop.rows, loop.cell_bounds, cells, problem)
    timer["abstract"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    data_fail = _failure_budget(problem)[0]
    statement = _statement(1.0 - data_fail, _data_noise_bound(problem, res, data_fail), data_fail, 0.0)
    loop.diagnostics = _diagnostics(problem, loop.partition, loop.cell_bounds, res, checks, check_noise,
                                    1.0 - data_fail, statement + ADAPTIVE_NOTE)
    loop.diagnostics["assumption"]["incremental_check"] = {"note": INCREMENTAL_NOTE, "components": report}
    timer["diagnostics"] = time.perf_counter() - t0
    loop.solve(timer)
    return rebound


def _targets(loop):
    """The look-ahead's value-of-information targets (``synthesis.suggest.Targets``), or None when no undecided
    cell turns Q_yes even without RKHS terms (or more than :data:`LOOKAHEAD_MAX_CELLS` are undecided).

    Every undecided cell's box is shrunk on each side by ``(1 - a)`` times its predicted shrink
    (:func:`_predicted_shrink`: the RKHS term, down to the noise floor), for ``a`` in :data:`LOOKAHEAD_LEVELS`;
    the rows of those cells are rebuilt and the model solved. A cell that turns Q_yes at ``a`` (the largest
    such) is a target for the mode its look-ahead strategy uses there, keeping the share ``a`` of its term
    (dropped when that is less than :data:`TARGET_TOL` of its half-width: its own box hardly matters).
    Weights: ``1 + FRONTIER_WEIGHT`` for the *frontier* (a target whose own shrunk row, one step on today's
    lower values, meets the threshold, at the largest level where it does, in its best mode there), else
    ``1 + FRONTIER_WEIGHT / 2^(h - 1)`` with ``h`` the expected steps to today's Q_yes along the look-ahead's
    rows (:func:`_hops`). This is a ranking: the look-ahead's boxes are predictions, never used for a guarantee.
    """
    from robust_imdp.abstraction.factored import abstraction_model
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.pipeline.run import _class_names
    from robust_imdp.synthesis.core import synthesize
    from robust_imdp.synthesis.suggest import Targets

    problem, part = loop.problem, loop.partition
    maybe = np.flatnonzero(np.asarray(loop.result.class_names) == "maybe")
    if maybe.size == 0 or maybe.size > LOOKAHEAD_MAX_CELLS:
        return None
    M = len(problem.mode_names)
    lo_c, up_c = np.asarray(part.cells_lower)[maybe], np.asarray(part.cells_upper)[maybe]
    ilo, ihi = np.asarray(loop.cell_bounds.image_lower), np.asarray(loop.cell_bounds.image_upper)
    shrink = _predicted_shrink(problem, part, loop.cell_bounds, maybe)
    if not np.any(shrink > 0):
        return None
    keep = np.full(maybe.size, -1.0)
    mode = np.zeros(maybe.size, dtype=np.int64)
    models = []
    # factored models: a bounded look-ahead (the factored solver's unbounded iteration has no deflation and can run
    # to its sweep cap on the shrunk model: 46 s per solve on benchmarks/starved.py against 0.7 s for the loop's own)
    horizon = problem.horizon
    if horizon is None and problem.form_choice()[0] == "factored":
        horizon = LOOKAHEAD_FACTORED_HORIZON
    values = np.append(np.clip(np.asarray(loop.result.p_low, float), 0.0, 1.0), 0.0)  # cells, then outside
    for a in LOOKAHEAD_LEVELS:
        todo = keep < 0  # every level is solved: the frontier below may need a deeper one
        lo2, hi2 = ilo.copy(), ihi.copy()
        lo2[:, maybe] += (1.0 - a) * shrink
        hi2[:, maybe] = np.maximum(hi2[:, maybe] - (1.0 - a) * shrink, lo2[:, maybe])
        abstraction = _assemble(part, _rebuild(part, loop.rows, CellBounds(lo2, hi2, None), [maybe] * M, problem))
        syn = synthesize(abstraction_model(abstraction), part.labels, part.atoms, loop.dfa,
                         threshold=problem.threshold, horizon=horizon, outside_state=part.outside_state,
                         semantics=problem.semantics, precision=LOOKAHEAD_PRECISION)
        cls = np.asarray(_class_names(syn.classes, syn, problem.threshold))
        strategy = np.asarray(syn.strategy)
        if strategy.ndim == 3:  # k-step: the first step's choice
            strategy = strategy[0]
        chosen = strategy[np.arange(part.n_cells), np.asarray(syn.initial_dfa_state)]
        hit = np.flatnonzero(todo & (cls[maybe] == "yes"))
        keep[hit], mode[hit] = a, chosen[maybe[hit]]
        models.append(abstraction)
    tol = TARGET_TOL * 0.5 * np.min(up_c - lo_c, axis=1)
    k = np.flatnonzero((keep >= 0) & ((1.0 - np.maximum(keep, 0.0)) * shrink[mode, np.arange(maybe.size)].max(axis=1)
                                      > tol))
    if k.size == 0:
        return None
    # the frontier: a target whose own shrunk row, one step on today's lower values, meets the threshold (the
    # largest share of the term at which it does, and the best mode there): it turns Q_yes by itself
    front = np.zeros(k.size, dtype=bool)
    for a, abstraction in zip(LOOKAHEAD_LEVELS, models):
        cand = np.flatnonzero(~front)
        if cand.size == 0:
            break
        cells = np.repeat(maybe[k[cand]], M)
        best = _one_step(abstraction, values, np.tile(np.arange(M), cand.size), cells).reshape(cand.size, M)
        ok = best.max(axis=1) >= float(problem.threshold)
        front[cand[ok]] = True
        keep[k[cand[ok]]] = np.minimum(keep[k[cand[ok]]], a)
        mode[k[cand[ok]]] = best[ok].argmax(axis=1)
    # how close to today's Q_yes each target is along the look-ahead's rows: the expected number of steps to
    # reach Q_yes, successors drawn in proportion to their upper bounds (a cluster of targets that turns Q_yes
    # only together, next to Q_yes, comes before the far ones)
    level_of = {a: i for i, a in enumerate(LOOKAHEAD_LEVELS[:len(models)])}
    hops = _hops(part.n_cells, np.asarray(loop.result.class_names) == "yes", maybe[k], mode[k],
                 [models[level_of[float(a)]] for a in keep[k]])
    near = np.where(front, 1.0, 0.5 ** np.maximum(hops - 1.0, 0.0))
    spent = _requested(loop, M, part)[mode[k], maybe[k]]
    weights, keeps = np.zeros((M, part.n_cells)), np.zeros((M, part.n_cells))
    weights[mode[k], maybe[k]] = (1.0 + FRONTIER_WEIGHT * near) / (1.0 + spent / SPENT_SCALE)
    keeps[mode[k], maybe[k]] = keep[k]
    reason = {int(maybe[i]): f"undecided (Q_?), Q_yes in the look-ahead keeping {keep[i]:.2f} of its RKHS term, "
              f"{h:.1f} steps from Q_yes" + ("; frontier: its own smaller box turns it Q_yes on today's values"
                                             if f else "")
              for i, f, h in zip(k, front, hops)}
    return Targets(weights, keeps, reason)


def _requested(loop, M: int, part) -> np.ndarray:
    """``(M, n_cells)``: the loop's samples so far (rounds >= 1) per mode and cell."""
    data = loop.problem.data
    out = np.zeros((M, part.n_cells))
    if loop.data_rounds is None:
        return out
    mine = np.flatnonzero(np.asarray(loop.data_rounds)[:data.u.shape[0]] >= 1)
    q = np.asarray(part.locate(data.x[mine])) if mine.size else np.zeros(0, np.int64)
    inside = q >= 0
    np.add.at(out, (np.asarray(data.u)[mine][inside], q[inside]), 1.0)
    return out


def _hops(n_cells: int, yes: np.ndarray, cells: np.ndarray, modes: np.ndarray, models: list) -> np.ndarray:
    """Expected steps from each ``cells[k]`` (row ``modes[k]`` of ``models[k]``) to the ``yes`` cells, successors
    drawn in proportion to their upper bounds; other cells and the outside state count :data:`MAX_HOPS`."""
    from scipy.sparse import csr_matrix

    from robust_imdp.synthesis.suggest import _row_reader

    ptr, cols_all, w_all, cache = [0], [], [], {}
    for q, u, m in zip(cells, modes, models):
        reader = cache.setdefault(id(m), _row_reader(m))
        cols, upper = reader(int(q), int(u))
        upper = np.asarray(upper, float)
        cols_all.append(np.minimum(np.asarray(cols, np.int64), n_cells))
        w_all.append(upper / max(upper.sum(), 1e-300))
        ptr.append(ptr[-1] + upper.size)
    P = csr_matrix((np.concatenate(w_all), np.concatenate(cols_all), np.asarray(ptr)),
                   shape=(cells.size, n_cells + 1))
    val = np.append(np.where(yes, 0.0, float(MAX_HOPS)), float(MAX_HOPS))  # the outside state last
    h = np.full(cells.size, float(MAX_HOPS))
    for _ in range(HOPS_SWEEPS):  # from above: monotone, each sweep one sparse product
        val[cells] = h
        new = np.minimum(1.0 + P @ val, float(MAX_HOPS))
        done = np.max(np.abs(new - h), initial=0.0) < 1e-9
        h = new
        if done:
            break
    return h


def _predicted_shrink(problem, part, cell_bounds, maybe: np.ndarray) -> np.ndarray:
    """``(n_modes, maybe.size, d)``: how much each side of the boxes of the cells ``maybe`` would shrink without
    their RKHS term: ``kappa B_ui sqrt(P_u(centre))`` (:func:`_term_line`'s slope; the power function of
    ``synthesis.suggest``), at most the box's excess beyond the known affine part's range less the noise floor
    ``e0``; 0 for known components (B = 0). A prediction for ranking, never a bound."""
    from robust_imdp.bounds.assumptions import resolve
    from robust_imdp.pipeline.bound_rkhs import _affine_part
    from robust_imdp.synthesis.suggest import _assumption

    M, n = len(problem.mode_names), int(np.size(problem.space_lower))
    st = resolve(problem.rkhs_bound, problem.gp_options.get("lengthscale"), problem.misspecification,
                 problem.mode_names, n)
    Bmax, inv_l2, floor = _assumption(problem)
    lo_all, up_all = np.asarray(part.cells_lower), np.asarray(part.cells_upper)
    centre = 0.5 * (lo_all + up_all)
    ilo, ihi = np.asarray(cell_bounds.image_lower), np.asarray(cell_bounds.image_upper)
    B_ui = np.asarray(st.rkhs_bound, float)
    shrink = np.zeros((M, maybe.size, n))
    for u in range(M):
        x = np.asarray(problem.data.by_mode(u)[0], float)
        if Bmax[u] <= 0 or x.shape[0] == 0:
            continue
        root = np.sqrt(_power(centre, x, inv_l2[u], max((floor[u] / Bmax[u]) ** 2, 1e-10)))
        A = np.asarray(_affine_part(problem, u)[0], float)
        excess = np.maximum(0.5 * (ihi[u] - ilo[u] - (up_all - lo_all) @ np.abs(A).T), 0.0)  # (N, n)
        for i in range(n):
            if B_ui[u, i] > 0:
                term = B_ui[u, i] * root
                e0, kappa = _term_line(term, excess[:, i])
                shrink[u, :, i] = np.minimum(kappa * term[maybe], np.maximum(excess[maybe, i] - e0, 0.0))
    return shrink


def _one_step(abstraction, values: np.ndarray, modes: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """The pessimistic value of one step from each ``(modes[k], cells[k])`` row with successor ``values``
    ``(n_cells + 1,)`` (the outside state last): ``min sum_j p_j V_j`` over the row's intervals (the mass
    beyond the lower bounds to the lowest values first; a row's floor on unlisted states goes to value 0)."""
    from robust_imdp.abstraction.factored import is_factored

    if is_factored(abstraction):
        from robust_imdp.solvers.factored import factored_bellman

        return factored_bellman(abstraction.model, values, rounding="nearest")[modes, cells]
    imdp = abstraction.imdp
    out = np.empty(cells.size)
    for k, (q, u) in enumerate(zip(cells, modes)):
        row = int(imdp.state_ptr[q]) + int(u)  # one choice per mode, in mode order
        j0, j1 = int(imdp.row_ptr[row]), int(imdp.row_ptr[row + 1])
        v = np.append(values[imdp.col[j0:j1]], 0.0)
        lo = np.append(imdp.lower[j0:j1], 0.0)
        hi = np.append(imdp.upper[j0:j1], float(imdp.floor[row]) * int(imdp.n_unlisted[row]))
        order = np.argsort(v, kind="stable")
        room = np.minimum(np.cumsum((hi - lo)[order]), max(1.0 - lo.sum(), 0.0))
        extra = np.diff(np.concatenate([[0.0], room]))
        out[k] = lo @ v + extra @ v[order]
    return out


def _term_line(term: np.ndarray, excess: np.ndarray) -> tuple:
    """``(e0, kappa)``: the least-squares line ``excess ~ e0 + kappa term`` over the cells, ``e0 >= 0``, ``kappa >= 1``.

    ``term`` is the predicted RKHS term ``B sqrt(P)`` at each cell's centre, ``excess`` the half-width of the
    cell's box beyond the known part's range. The certificate's radius is larger than the term at the centre
    (its supremum over the cell, and the noise terms its weights trade against it): ``kappa`` turns a drop of
    the term into a drop of the box. ``e0`` is the noise floor: what no amount of data removes (bounded noise,
    a worst-case bound: repeated samples do not average it away).
    """
    t, e = np.asarray(term, float), np.asarray(excess, float)
    if t.size < 2 or np.ptp(t) <= 0:
        return 0.0, 1.0
    kappa = max(float(np.cov(t, e)[0, 1] / np.var(t, ddof=1)), 1.0)
    e0 = float(e.mean() - kappa * t.mean())
    if e0 < 0:  # the floor cannot be negative: the line through the origin
        e0, kappa = 0.0, max(float(t @ e / (t @ t)), 1.0)
    return e0, kappa


def _requests(loop, n: int, targeted: bool) -> list:
    """The round's ``n`` requests: the look-ahead's targets first (:func:`_targets`), the rest (targets met,
    or none) by the undecided cells' radius change, seeing the targeted requests as data."""
    from robust_imdp.synthesis.suggest import suggest_samples

    targets = _targets(loop) if targeted else None
    reqs = [] if targets is None else suggest_samples(loop.result, n, targets=targets)
    if len(reqs) < n:
        names = list(loop.problem.mode_names)
        pts = [np.vstack([loop.problem.data.by_mode(u)[0]] + [r.x[None] for r in reqs if r.mode == m])
               for u, m in enumerate(names)]
        reqs += suggest_samples(loop.result, n - len(reqs), data_points=pts)
    return reqs


def _append(data, xs, us, xn):
    from robust_imdp.models.system import Dataset

    return Dataset(np.vstack([data.x, xs]), np.concatenate([data.u, us]), np.vstack([data.x_next, xn]),
                   modes=data.mode_names)


def auto_rounds(budget: int) -> int:
    """The default number of rounds: ``budget // MIN_ROUND`` capped at :data:`AUTO_ROUNDS` (at least 1).

    One round is not a closed loop: the look-ahead's targets are predictions, and a path to Q_yes turns
    Q_yes a stretch at a time (docs/sampling.md, "How many rounds")."""
    return max(1, min(AUTO_ROUNDS, int(budget) // MIN_ROUND))


def _per_round(budget: int, rounds: int, rnd: int) -> int:
    """Samples of round ``rnd`` (1-based): ``budget // rounds``, the remainder spread over the first rounds."""
    return budget // rounds + (1 if rnd <= budget % rounds else 0)


def improve(problem, true_system, budget: int, *, rounds: int | None = None, out=None, seed: int = 0, progress: bool = True,
            allow_outside: bool = False, keep_history: bool = False, workers: int | None = None,
            on_round=None, targeted: bool = True) -> ImproveResult:
    """Collect ``budget`` samples in ``rounds`` rounds where they help most, re-bounding incrementally.

    Parameters
    ----------
    problem : Problem
        Its data are the starting data (ignored when ``out`` holds an interrupted loop).
    true_system : object
        ``mode_names`` (sequence of str) and ``step(x (k, n), modes (k,) int, rng) -> (k, n)``
        (``modes`` index ``true_system.mode_names``), as for ``validate.simulate``.
    budget : int
        Samples to add in all.
    rounds : int, optional
        In how many rounds (``budget // rounds`` each, the remainder to the first rounds); default
        :func:`auto_rounds` (``budget // 10``, at most 8).
    out : str or Path, optional
        Directory of the loop's data file (``data.csv``, with a ``round`` column), its state and
        ``result.json`` (rewritten after every round); an interrupted loop resumes from it.
    seed : int
        Round r simulates with ``np.random.default_rng([seed, r])`` (the same after a resume).
    allow_outside : bool
        Accept next states outside X (otherwise refused as a simulator error).
    keep_history : bool
        Keep every round's image boxes in ``ImproveResult.history`` (for tests and benchmarks).
    on_round : callable ``(ImproveRound, Result) -> None``, optional
        Called after every completed round (round 0 included), after its files are written.
    targeted : bool
        Choose requests by the look-ahead's value-of-information targets (:func:`_targets`; default), else
        (or when there are none) by the undecided cells' summed radius change alone.

    Returns
    -------
    ImproveResult
    """
    from robust_imdp.models.geometry import Box, Partition
    from robust_imdp.pipeline.preflight import _check_atoms, _region_objects
    from robust_imdp.pipeline.runtime import _Log, _Run
    from robust_imdp.spec.api import to_dfa
    if rounds is None and not (isinstance(budget, bool) or not isinstance(budget, (int, np.integer))):
        rounds = auto_rounds(budget)
    for name, v, least in (("budget", budget, 1), ("rounds", rounds, 1)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < least:
            raise InvalidInputError(f"improve: {name} must be an integer >= {least}; got {v!r}")
    _refuse_unsupported(problem)
    out = None if out is None else Path(out)
    log = _Log(progress)
    dfa = to_dfa(problem.formula)
    _check_atoms(dfa, problem)
    partition = Partition(Box(problem.space_lower, problem.space_upper), problem.cell_size, _region_objects(problem),
                          names=problem.dim_names, periodic=problem.periodic)
    M, n = len(problem.mode_names), len(problem.space_lower)
    resume = None if out is None else _load_state(out, M, partition.n_cells, n)
    if resume is not None:
        data, data_rounds = _read_loop_data(out, problem)
        problem = problem.replace(data=data)
        log.info(f"improve: resuming after round {resume[1]} from {out}")
    else:
        data_rounds = np.zeros(problem.data.u.shape[0], dtype=np.int64)
        if out is not None:
            out.mkdir(parents=True, exist_ok=True)
            _write_data(out / DATA_FILE, problem.data, data_rounds, problem.mode_names)
    run = _Run(workers=workers)
    loop = _Loop(problem, partition, dfa, log, run, out, data_rounds=data_rounds)
    history = []
    try:
        if resume is not None:  # bound what the data file has beyond the state (at most one round's samples)
            loop.problem = problem.replace(data=_first(data, resume[2]))
        last = _start(loop, resume)
        if resume is not None and data.u.shape[0] > resume[2]:
            timer: dict = {}
            rebound = _update(loop, data, resume[2], last + 1, timer)
            last += 1
            loop.record(last, data.u.shape[0] - resume[2], rebound, timer)
        elif resume is not None:
            loop.problem = problem
        if keep_history:
            history.append((loop.cell_bounds.image_lower.copy(), loop.cell_bounds.image_upper.copy()))
        if on_round is not None:
            on_round(loop.rounds[-1], loop.result)
        stopped = "budget spent"
        names = list(problem.mode_names)
        for rnd in range(last + 1, rounds + 1):
            timer = {}
            t0 = time.perf_counter()
            reqs = _requests(loop, _per_round(budget, rounds, rnd), targeted)
            timer["suggest"] = time.perf_counter() - t0
            if not reqs:
                stopped = "no undecided cells"
                break
            xs = np.array([r.x for r in reqs], dtype=float)
            us = np.array([names.index(r.mode) for r in reqs], dtype=np.int64)
            t0 = time.perf_counter()
            xn = _simulate(true_system, xs, us, names, np.random.default_rng([int(seed), rnd]), rnd,
                           np.asarray(problem.space_lower, float), np.asarray(problem.space_upper, float),
                           allow_outside)
            timer["simulate"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            n_old = loop.problem.data.u.shape[0]
            data = _append(loop.problem.data, xs, us, xn)
            loop.data_rounds = np.concatenate([loop.data_rounds, np.full(len(us), rnd, dtype=np.int64)])
            if out is not None:
                _write_data(out / DATA_FILE, data, loop.data_rounds, names)
            timer["write"] = time.perf_counter() - t0
            rebound = _update(loop, data, n_old, rnd, timer)
            loop.record(rnd, len(us), rebound, timer)
            if keep_history:
                history.append((loop.cell_bounds.image_lower.copy(), loop.cell_bounds.image_upper.copy()))
            if on_round is not None:
                on_round(loop.rounds[-1], loop.result)
    finally:
        run.close()
    return ImproveResult(result=loop.result, cell_bounds=loop.cell_bounds, rounds=tuple(loop.rounds), stopped=stopped,
                         data_file=None if out is None else out / DATA_FILE, history=history)


def _first(data, m: int):
    """The first ``m`` samples of ``data``."""
    from robust_imdp.models.system import Dataset

    return Dataset(data.x[:m], data.u[:m], data.x_next[:m], modes=data.mode_names)


def command(args, true_system) -> int:
    """``robust-imdp improve``: the loop with the command's options; one line per round on stdout."""
    from robust_imdp.io.files import load_problem

    problem = load_problem(args.problem)
    if getattr(args, "tight", False):  # the run's --tight: Problem.tightened() on the starting data
        import sys

        from robust_imdp.pipeline.problem import tight_line

        problem = problem.tightened()
        if not args.quiet:
            print(tight_line(problem), file=sys.stderr)
    args.interrupt_note = (f"interrupted; the completed rounds are saved in {args.out}: run the same command "
                           "again to resume")
    out = improve(problem, true_system, args.budget, rounds=args.rounds, out=args.out, seed=args.seed,
                  progress=not args.quiet, allow_outside=args.allow_outside,
                  on_round=lambda r, _: print(r.line(), flush=True))
    print(f"improve stopped ({out.stopped}) after round {out.rounds[-1].round}; wrote {args.out / 'result.json'} "
          f"and {out.data_file}")
    return 0
