"""Monte-Carlo validation of synthesis results against the true system.

The guarantee being checked (paper, Thm 2 with the product of Sec. 5): for every initial state
x0 in cell q, the probability that the true system under the refined switching controller
satisfies the formula lies in ``[p_low[q], p_up[q]]``. Sampling x0 uniformly in q gives a
mixture of such probabilities, which therefore lies in the same interval. For each cell we run
``n_per_cell`` independent simulations and compare the empirical frequency with the interval
through Wilson score intervals at the requested confidence.

Step cap. The guarantee is about the unbounded-horizon probability; a run still undecided after
``max_steps`` steps ("capped") may go either way. We count capped runs **as satisfied** when
checking ``p_low`` and **as not satisfied** when checking ``p_up``, so a reported violation is a
real one whatever the capped runs would have done. For k-step formulas (``horizon`` set) the cap
is the horizon and capped runs are exactly the non-satisfying ones.

The controller is driven from the result tables (``result.json`` contract, read by
:class:`robust_imdp.io.ResultFile`), independently of ``controller.py``: locate the cell, look the mode up in ``strategy[q][s]``, step the DFA with
the new cell's label. Leaving X is a violation (the abstraction's absorbing outside state).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import norm

from robust_imdp.errors import DimensionError, InvalidInputError, OutsideDomainError
from robust_imdp.io import ResultFile, as_result_file as _as_result_file  # noqa: F401 (re-exported)

__all__ = [
    "ResultFile",
    "Trajectories",
    "ValidationReport",
    "wilson_interval",
    "simulate",
    "validate",
]

RUNNING, SATISFIED, VIOLATED = 0, 1, 2
#: Default step cap of a simulated run, the same for :func:`validate`, :func:`simulate` and
#: ``robust-imdp simulate --max-steps`` (runs still undecided there count as "capped").
MAX_STEPS = 200


# --------------------------------------------------------------------------- statistics
def wilson_interval(successes, trials, confidence: float = 0.999):
    """Two-sided Wilson score interval for a binomial proportion.

    Parameters
    ----------
    successes, trials : int or int arrays (broadcastable)
    confidence : float in (0, 1)

    Returns
    -------
    lower, upper : float arrays
        ``(k + z^2/2)/(n + z^2) -/+ z/(n + z^2) sqrt(k (n-k)/n + z^2/4)`` with
        ``z = Phi^-1(1 - (1 - confidence)/2)`` (Wilson 1927).
    """
    if not 0.0 < confidence < 1.0:
        raise InvalidInputError(f"confidence must lie in (0, 1); got {confidence!r}")
    k = np.asarray(successes, dtype=float)
    n = np.asarray(trials, dtype=float)
    if np.any(n <= 0) or np.any(k < 0) or np.any(k > n):
        raise InvalidInputError(
            f"successes must lie in [0, trials] and trials must be > 0; got {successes!r}, {trials!r}"
        )
    z = norm.ppf(1.0 - (1.0 - confidence) / 2.0)
    denom = n + z * z
    centre = (k + z * z / 2.0) / denom
    half = z / denom * np.sqrt(k * (n - k) / n + z * z / 4.0)
    # Widen by 1e-12 (the closed form's rounding error is ~1e-15) so that e.g. k = n gives an
    # upper end of exactly 1 and a correct bound is never flagged by rounding. The clamps to
    # [0, 1] are safe: a proportion lies in [0, 1], so clipping cannot exclude it.
    slack = 1e-12
    return np.clip(centre - half - slack, 0.0, 1.0), np.clip(centre + half + slack, 0.0, 1.0)


# --------------------------------------------------------------------------- simulation
@dataclass(frozen=True, eq=False)
class Trajectories:
    """Simulated runs.

    Attributes
    ----------
    paths : list of (T_r + 1, n) float arrays (empty arrays when not recorded)
    outcome : (R,) int array: 1 satisfied, 2 violated, 0 capped (undecided at max_steps)
    steps : (R,) int array, steps taken
    """

    paths: list
    outcome: np.ndarray
    steps: np.ndarray


def simulate(result, true_system, x0, *, max_steps: int = MAX_STEPS, rng=None, record: bool = False):
    """Run the true system under the result's controller from each row of ``x0``.

    Parameters
    ----------
    result : ResultFile, pipeline Result, result dict or path to result.json / its directory
    true_system : object
        ``mode_names`` (tuple of str) and ``step(x (k, n), modes (k,) int, rng) -> (k, n)``
        where ``modes`` index ``true_system.mode_names``.
    x0 : (R, n) float array of initial states in X
    max_steps : int
    rng : anything ``np.random.default_rng`` accepts
    record : bool
        Keep every path (memory O(R * max_steps * n)).

    Returns
    -------
    Trajectories
    """
    res = _as_result_file(result)
    rng = np.random.default_rng(rng)
    x = np.array(x0, dtype=float, ndmin=2)
    if x.shape[1] != res.cells_lower.shape[1]:
        raise DimensionError(f"x0 must have shape (R, {res.cells_lower.shape[1]}); got {x.shape}")
    sys_index = {m: i for i, m in enumerate(true_system.mode_names)}
    missing = [m for m in res.modes if m not in sys_index]
    if missing:
        raise InvalidInputError(
            f"true_system has no modes {missing}; it has {list(true_system.mode_names)}"
        )
    to_sys = np.array([sys_index[m] for m in res.modes], dtype=np.int64)
    locate = res.locator()
    sink = res.dfa_sink()
    q = locate(x)
    if np.any(q < 0):
        raise OutsideDomainError(
            f"x0 must lie in X = [{res.space_lower.tolist()}, {res.space_upper.tolist()}]; "
            f"row {int(np.flatnonzero(q < 0)[0])} does not"
        )
    # Standard product semantics: the first DFA move reads the initial cell's label.
    s = res.dfa_delta[res.dfa_initial, res.label_letters[q]]
    status = np.where(res.dfa_accepting[s], SATISFIED, np.where(sink[s], VIOLATED, RUNNING))
    steps = np.zeros(len(x), dtype=np.int64)
    hist = [x.copy()] if record else None
    for t in range(max_steps):
        run = np.flatnonzero(status == RUNNING)
        if run.size == 0:
            break
        table = res.strategy
        if res.strategy_by_time is not None:  # k-step: time-varying strategy
            table = res.strategy_by_time[min(t, len(res.strategy_by_time) - 1)]
        modes = table[q[run], s[run]]
        if np.any(modes < 0):
            raise InvalidInputError("result strategy is undefined (-1) for a reachable (cell, DFA state)")
        x_new = np.asarray(true_system.step(x[run], to_sys[modes], rng), dtype=float)
        if x_new.shape != (run.size, x.shape[1]):
            raise DimensionError(
                f"true_system.step(x, modes, rng) must return the next states, shape (k, n) = "
                f"({run.size}, {x.shape[1]}) like x; got {x_new.shape}")
        x[run] = x_new
        steps[run] += 1
        q_new = locate(x_new)
        out = q_new < 0
        status[run[out]] = VIOLATED  # leaving X: the absorbing, non-accepting outside state
        ok = run[~out]
        q[ok] = q_new[~out]
        s[ok] = res.dfa_delta[s[ok], res.label_letters[q[ok]]]
        status[ok] = np.where(res.dfa_accepting[s[ok]], SATISFIED,
                              np.where(sink[s[ok]], VIOLATED, RUNNING))
        if record:
            hist.append(x.copy())
    paths = []
    if record:
        h = np.stack(hist)  # (T + 1, R, n)
        paths = [h[: steps[r] + 1, r] for r in range(len(x))]
    return Trajectories(paths=paths, outcome=status, steps=steps)


# --------------------------------------------------------------------------- validation
@dataclass(frozen=True, eq=False)
class ValidationReport:
    """Monte-Carlo comparison of empirical satisfaction with ``[p_low, p_up]`` per cell.

    Attributes
    ----------
    cells : (C,) int array, the cells tested
    n_per_cell, max_steps : int
    confidence : float
    satisfied, capped : (C,) int arrays (runs per cell)
    empirical : (C,) float, satisfied / n_per_cell (capped counted as not satisfied)
    wilson_low : (C,) float, lower Wilson bound of the satisfied count (checked against p_up)
    wilson_up : (C,) float, upper Wilson bound of satisfied + capped (checked against p_low)
    p_low, p_up : (C,) float
    outside : (K,) int array, cells whose interval misses the Wilson interval
    containment_rate : float, fraction of tested cells not in ``outside``
    expected_outside : float, ``C * (1 - confidence)``, an upper bound on the expected number
        of cells flagged by chance when the bounds are correct (each check is one-sided at
        level (1 - confidence)/2, two checks per cell)
    """

    cells: np.ndarray
    n_per_cell: int
    max_steps: int
    confidence: float
    satisfied: np.ndarray
    capped: np.ndarray
    empirical: np.ndarray
    wilson_low: np.ndarray
    wilson_up: np.ndarray
    p_low: np.ndarray
    p_up: np.ndarray
    outside: np.ndarray
    containment_rate: float
    expected_outside: float

    def summary(self) -> str:
        """A few lines of text for terminals and logs."""
        c = len(self.cells)
        lines = [
            f"Monte-Carlo validation: {c} cells x {self.n_per_cell} runs, step cap {self.max_steps}, "
            f"Wilson {100 * self.confidence:g} %",
            f"  capped runs: {int(self.capped.sum())} of {c * self.n_per_cell} "
            "(counted as satisfied for the p_low check, as not satisfied for the p_up check)",
            f"  containment: {c - len(self.outside)}/{c} cells = {100 * self.containment_rate:.2f} % "
            f"(chance alone flags <= {self.expected_outside:.2f} cells on average)",
        ]
        if c:
            lo_margin = self.wilson_up - self.p_low  # < 0 means p_low is contradicted
            up_margin = self.p_up - self.wilson_low  # < 0 means p_up is contradicted
            j, k = int(np.argmin(lo_margin)), int(np.argmin(up_margin))
            lines.append(
                f"  tightest cells: {int(self.cells[j])} (p_low {self.p_low[j]:.3f} vs Wilson upper "
                f"{self.wilson_up[j]:.3f}), {int(self.cells[k])} (p_up {self.p_up[k]:.3f} vs Wilson "
                f"lower {self.wilson_low[k]:.3f}); mean empirical {np.mean(self.empirical):.3f} vs "
                f"mean [p_low, p_up] = [{np.mean(self.p_low):.3f}, {np.mean(self.p_up):.3f}]"
            )
        for j in np.flatnonzero(np.isin(self.cells, self.outside))[:20]:
            lines.append(
                f"  OUTSIDE cell {int(self.cells[j])}: empirical {self.empirical[j]:.3f} "
                f"(Wilson [{self.wilson_low[j]:.3f}, {self.wilson_up[j]:.3f}]) vs "
                f"[p_low, p_up] = [{self.p_low[j]:.3f}, {self.p_up[j]:.3f}]"
            )
        return "\n".join(lines)


def validate(result_or_controller, true_system, *, n_per_cell: int = 100, max_steps: int = MAX_STEPS,
             rng=None, confidence: float = 0.999, cells=None) -> ValidationReport:
    """Simulate the true system under the controller from random states in each cell.

    Parameters
    ----------
    result_or_controller : ResultFile, pipeline Result, result dict, or path to a result
    true_system : see :func:`simulate`
    n_per_cell : int, runs per cell, initial states uniform in the cell
    max_steps : int, step cap (ignored in favour of the horizon for k-step results)
    rng : seed or Generator
    confidence : float, per-cell two-sided Wilson confidence
    cells : (C,) int array, optional; default all cells

    Returns
    -------
    ValidationReport
    """
    res = _as_result_file(result_or_controller)
    if n_per_cell < 1 or max_steps < 1:
        raise InvalidInputError(
            f"n_per_cell and max_steps must be >= 1; got {n_per_cell!r}, {max_steps!r}"
        )
    rng = np.random.default_rng(rng)
    if res.horizon is not None:
        max_steps = int(res.horizon)
    cells = np.arange(res.n_cells) if cells is None else np.asarray(cells, dtype=np.int64)
    if cells.ndim != 1 or np.any((cells < 0) | (cells >= res.n_cells)):
        raise InvalidInputError(f"cells must be indices in [0, {res.n_cells}); got {cells!r}")
    owner = np.repeat(cells, n_per_cell)
    lo, up = res.cells_lower[owner], res.cells_upper[owner]
    x0 = lo + rng.random(lo.shape) * (up - lo)
    traj = simulate(res, true_system, x0, max_steps=max_steps, rng=rng)
    outcome = traj.outcome.reshape(len(cells), n_per_cell)
    sat = np.sum(outcome == SATISFIED, axis=1)
    capped = np.sum(outcome == RUNNING, axis=1)
    if res.horizon is not None:
        capped = np.zeros_like(capped)  # k-step: undecided at the horizon means not satisfied
    wl, _ = wilson_interval(sat, n_per_cell, confidence)
    _, wu = wilson_interval(sat + capped, n_per_cell, confidence)
    p_low, p_up = res.p_low[cells], res.p_up[cells]
    bad = (p_low > wu) | (p_up < wl)
    outside = cells[bad]
    return ValidationReport(
        cells=cells, n_per_cell=int(n_per_cell), max_steps=int(max_steps),
        confidence=float(confidence), satisfied=sat, capped=capped,
        empirical=sat / n_per_cell, wilson_low=wl, wilson_up=wu, p_low=p_low, p_up=p_up,
        outside=outside, containment_rate=1.0 - len(outside) / max(len(cells), 1),
        expected_outside=len(cells) * (1.0 - confidence),
    )
