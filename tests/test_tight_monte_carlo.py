"""Monte Carlo of abstraction -> synthesis -> controller on a problem whose brackets are TIGHT.

Why a special problem. A Monte-Carlo check can only catch ``p_low x 1.01`` where the true
satisfaction probability is within 1 % of ``p_low``. Thm 1 gives such bounds only in one
situation: the image of a cell is a point centred in the target cell, so the exact probability
``P[|v| <= margin]`` of staying in the target is the printed lower bound (an image of positive
width w loses about ``phi(m/sigma) w/sigma`` of it at the worst point; a target hit off-centre
keeps only the smaller margin). The problem below is built from exactly that.

True system (2-D, known, "move to a cell centre"): ``x' = c(x) + d_u + v`` where ``c(x)`` is
the centre of x's cell (a sample-and-hold on the grid), ``d_fwd1 = (1, 0)``, ``d_fwd2 = (2, 0)``
and ``v`` truncated Gaussian: axis 0 ``sigma 0.01, bound 0.02`` (a move never leaves its target
column), axis 1 ``sigma 0.25, bound 2.0`` (lateral slips). The image box of a cell is the single
point ``c_q + d_u`` -- an exact image box, rounded by nothing.

Map (columns 0..12 of width 1; rows of height 1, row 6 split at 6.45 and 6.55):

* rows 1 and 3 are lanes between obstacle rows 0, 2, 4; lane A (row 1) ends in ``des`` at
  column 12, lane B (row 3) at column 9. From a lane cell D columns before ``des`` the best
  plan jumps two columns at a time: ``p = s^ceil(D/2)``, ``s = P[|v_1| <= 0.5] = 0.9545``,
  and the bound is tight because every lateral slip ends in an obstacle (value 0), exactly
  what the pessimistic adversary does with the mass it controls. 21 cells with
  ``0.756 <= p_low <= 0.955``.
* a trap: the free cell [10, 11] x [6.45, 6.55] (everything else in rows 5-7 up to column 10 is
  an obstacle); in columns 11 and 12 the strip [6.45, 6.55] is an obstacle flanked by ``des``
  (rows 5, 7 and the rest of row 6). Both moves land in the centre of an obstacle cell, so a
  run succeeds only by slipping out of it: ``P = 1 - P[|v_1| <= 0.05] = 0.8415`` = ``p_up``
  (a tight upper bound: the optimistic adversary's best is to leave the obstacle with all the
  mass its lower bound allows), ``p_low = 0``.

The abstraction's default eps rule and floor are used unchanged.

Statistics. Per cell and side a Wilson interval at z = 4.5 (one-sided tail 3.4e-6): with
130 cells and 2 sides the chance that a sound result is flagged anywhere is <= 8.8e-4.
Sample sizes per cell are chosen so that a 1 % relative error of a bound strictly inside
(0, 1) is detectable with power >= 0.99: ``0.01 p >= (4.5 + 2.33) SE(p)``.
"""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from scipy import special

from robust_imdp.abstraction.rows import CellBounds, abstract
from robust_imdp.synthesis.controller import Controller
from robust_imdp.spec.dfa import ltlf_to_dfa
from robust_imdp.models.geometry import Box, Partition, Region
from robust_imdp.models.noise import TruncatedGaussianNoise
from robust_imdp.synthesis.core import synthesize

from soundness_checks import check_frequencies

K = 13  # columns
SIGMA = np.array([0.01, 0.25])
BOUND = np.array([0.02, 2.0])
SHIFTS = np.array([[1.0, 0.0], [2.0, 0.0]])  # fwd1, fwd2
Z = 4.5  # per cell and side: P[Z > 4.5] = 3.4e-6
Z_POWER = 2.3263  # one-sided 99 % quantile: power of the 1 % detection
S_LANE = special.erf(0.5 / (SIGMA[1] * np.sqrt(2)))  # P[|v_1| <= 0.5] = 0.9545
S_TRAP = special.erf(0.05 / (SIGMA[1] * np.sqrt(2)))  # P[|v_1| <= 0.05] = 0.1585


def corridor_partition():
    def box(x0, x1, y0, y1):
        return Box([x0, y0], [x1, y1])

    obs = [box(0, K, 0, 1), box(0, K, 2, 3), box(0, K, 4, 5), box(0, K - 3, 5, 8),
           box(K - 3, K - 2, 5, 6.45), box(K - 3, K - 2, 6.55, 8), box(K - 2, K, 6.45, 6.55)]
    des = [box(K - 1, K, 1, 2), box(K - 4, K - 3, 3, 4), box(K - 2, K, 5, 6.45), box(K - 2, K, 6.55, 8)]
    return Partition(Box([0.0, 0.0], [float(K), 8.0]), 1.0, [Region("obs", obs), Region("des", des)])


def true_system_arrays(part):
    centres = 0.5 * (part.cells_lower + part.cells_upper)
    return centres


@pytest.fixture(scope="module")
def corridor():
    part = corridor_partition()
    centres = true_system_arrays(part)
    img = np.stack([centres + d for d in SHIFTS])  # (2, N, 2): the image of every cell is one point
    noise = TruncatedGaussianNoise(SIGMA, BOUND)
    ab = abstract(part, CellBounds(img, img), noise)
    res = synthesize(ab.imdp, part.labels, part.atoms, ltlf_to_dfa("G !obs & F des"), threshold=0.5,
                     outside_state=part.outside_state)
    return part, centres, res


def cell_of(part, x, y):
    return int(part.locate(np.array([[x, y]]))[0])


# --------------------------------------------------------------------------- simulation (numba)
@njit(cache=True)
def _truncnorm(sigma, bound):
    while True:  # rejection: exactly N(0, sigma^2) conditioned on |v| <= bound
        v = np.random.normal(0.0, sigma)
        if abs(v) <= bound:
            return v


@njit(cache=True)
def _locate(x0, x1, bp0, bp1, lo, hi):
    """Cell of (x0, x1) or -1 outside X: Controller.locate's convention (half-open, last closed)."""
    if x0 < lo[0] or x0 > hi[0] or x1 < lo[1] or x1 > hi[1]:
        return -1
    i = min(np.searchsorted(bp0, x0, side="right") - 1, bp0.size - 2)
    j = min(np.searchsorted(bp1, x1, side="right") - 1, bp1.size - 2)
    return i * (bp1.size - 1) + j


@njit(cache=True)
def run_one(q0, noise, bp0, bp1, lo, hi, centres, shifts, strategy, delta, initial, accepting, sink, letters,
            sigma, bound, max_steps):
    """One closed-loop run from cell q0; returns (satisfied, steps, capped).

    The controller's rule (controller module doc): s = delta[initial][L(q0)]; while s is neither
    accepting nor a sink apply strategy[q, s], step, stop as violated outside X, else advance
    the DFA with the new cell's letter. ``noise`` (max_steps, 2) is used when it has rows,
    else fresh truncated Gaussian noise is drawn.
    """
    q = q0
    s = delta[initial, letters[q]]
    t = 0
    while True:
        if accepting[s]:
            return True, t, False
        if sink[s]:
            return False, t, False
        if t == max_steps:
            return False, t, True
        u = strategy[q, s]
        if noise.shape[0] > 0:
            v0, v1 = noise[t, 0], noise[t, 1]
        else:
            v0, v1 = _truncnorm(sigma[0], bound[0]), _truncnorm(sigma[1], bound[1])
        x0 = centres[q, 0] + shifts[u, 0] + v0
        x1 = centres[q, 1] + shifts[u, 1] + v1
        q = _locate(x0, x1, bp0, bp1, lo, hi)
        t += 1
        if q < 0:
            return False, t, False  # left X: violation
        s = delta[s, letters[q]]


@njit(cache=True)
def simulate(cells, n_runs, seed, bp0, bp1, lo, hi, centres, shifts, strategy, delta, initial, accepting, sink,
             letters, sigma, bound, max_steps):
    np.random.seed(seed)
    hits = np.zeros(cells.size, dtype=np.int64)
    capped = 0
    empty = np.zeros((0, 2))
    for c in range(cells.size):
        for _ in range(n_runs[c]):
            ok, _, cap = run_one(cells[c], empty, bp0, bp1, lo, hi, centres, shifts, strategy, delta, initial,
                                 accepting, sink, letters, sigma, bound, max_steps)
            hits[c] += ok
            capped += cap
    return hits, capped


def controller_tables(ctrl: Controller, centres):
    """The arrays run_one needs, read from a Controller (so the simulation runs its tables)."""
    bp0, bp1 = ctrl.breakpoints
    return (bp0, bp1, ctrl.space_lower, ctrl.space_upper, centres, SHIFTS, ctrl.strategy, ctrl.dfa_delta,
            ctrl.dfa_initial, ctrl.dfa_accepting, ctrl.dfa_sink, ctrl.cell_letters, SIGMA, BOUND)


MAX_STEPS = 40  # every run ends within K steps (moves are forward only); capped runs are counted


def runs_needed(p):
    """Smallest power of 2 with 0.01 p >= (Z + Z_POWER) SE(p) (at least 2^12)."""
    n = ((Z + Z_POWER) / (0.01 * p)) ** 2 * p * (1 - p)
    return int(2 ** max(12, int(np.ceil(np.log2(max(n, 1.0))))))


def informative(res):
    """Cells with a bound strictly inside (0, 1) (p_low or p_up) and per-cell sample sizes."""
    inside_low = (res.p_low > 0) & (res.p_low < 1)
    inside_up = (res.p_up > 0) & (res.p_up < 1) & (res.p_up > 1e-3)  # floor-only p_up ~ 1e-7 excluded
    n = np.full(res.n_cells, 2 ** 12)
    for q in np.flatnonzero(inside_low | inside_up):
        p = min(res.p_low[q] if inside_low[q] else 1.0, res.p_up[q] if inside_up[q] else 1.0)
        n[q] = runs_needed(p)
    return inside_low, inside_up, n


# --------------------------------------------------------------------------- tests
def test_corridor_bounds_are_the_hand_derived_probabilities(corridor):
    """p_low = s^ceil(D/2) along the lanes; p_up = 1 - s_trap in front of the trap (module doc).

    Tolerance 1e-9: the solver's precision 1e-8 is on the bracket width; p_low is its lower
    end, within 1e-12 relative of the exact product (rounding of each factor).
    """
    part, _, res = corridor
    for row_y, des_col in ((1.5, K - 1), (3.5, K - 4)):
        for col in range(des_col):
            q = cell_of(part, col + 0.5, row_y)
            D = des_col - col
            assert res.p_low[q] == pytest.approx(S_LANE ** int(np.ceil(D / 2)), abs=1e-8), (col, row_y)
            if D % 2 == 0:  # fwd2 is the unique best move (fwd1 costs one extra slip); odd D ties
                assert res.strategy[q, res.initial_dfa_state[q]] == 1
    trap = cell_of(part, K - 3 + 0.5, 6.5)
    assert part.labels[trap] == 0  # the one free cell of row 6
    assert res.p_low[trap] == 0.0
    assert res.p_up[trap] == pytest.approx(1 - S_TRAP, abs=1e-8)


def test_numba_simulation_runs_the_controller_exactly(corridor):
    """run_one (numba, on the Controller's tables) against Controller.reset/act on the same noise:
    identical outcome and length for 300 runs from random starts (covers every lane and the trap)."""
    part, centres, res = corridor
    ctrl = res.controller(part)
    tables = controller_tables(ctrl, centres)
    rng = np.random.default_rng(2024)
    noise_model = TruncatedGaussianNoise(SIGMA, BOUND)
    for _ in range(300):
        q0 = int(rng.integers(part.n_cells))
        x = rng.uniform(part.cells_lower[q0], part.cells_upper[q0])
        noise = noise_model.sample(MAX_STEPS, rng)
        ok, steps, cap = run_one(q0, noise, *tables, MAX_STEPS)
        ctrl.reset(x)
        t = 0
        while (u := ctrl.act(x)) is not None:
            x = centres[ctrl.cell] + SHIFTS[u] + noise[t]
            t += 1
        assert (ctrl.status == "satisfied", ctrl.time) == (bool(ok), int(steps)) and not cap


@pytest.fixture(scope="module")
def simulated(corridor):
    part, centres, res = corridor
    inside_low, inside_up, n = informative(res)
    cells = np.arange(part.n_cells)
    hits, capped = simulate(cells, n, 12345, *controller_tables(res.controller(part), centres), MAX_STEPS)
    return hits, n, capped, inside_low, inside_up


@pytest.mark.slow
def test_frequencies_lie_in_tight_brackets(corridor, simulated):
    """Every cell's satisfaction frequency lies in [p_low, p_up] (z = 4.5, module doc), at least
    20 cells have 0 < p_low < 1 with a detectable 1 % error, and no run hit the step cap."""
    _, _, res = corridor
    hits, n, capped, inside_low, inside_up = simulated
    assert capped == 0
    assert check_frequencies(hits, n, res.p_low, res.p_up, Z) == 0
    detectable = inside_low & (0.01 * res.p_low >= (Z + Z_POWER) * np.sqrt(res.p_low * (1 - res.p_low) / n))
    assert detectable.sum() >= 20, detectable.sum()
    assert inside_up.sum() == 1  # the trap cell (every other p_up is 1, 0 or a floor-sized ~1e-7)


@pytest.mark.slow
def test_one_percent_errors_of_p_low_and_p_up_are_caught(corridor, simulated):
    """The same check with p_low x 1.01 / p_up x 0.99 (unsound by 1 % where the bracket is tight).

    Each informative cell is flagged with probability >= 0.99 (the shift is >= 6.8 SE of the
    frequency, which sits at the tight bound); we require >= 20 flagged p_low cells (of 21;
    P[two misses] < 0.02 at the minimum power) and the trap cell's p_up."""
    _, _, res = corridor
    hits, n, _, inside_low, inside_up = simulated
    low_flags = check_frequencies(hits[inside_low], n[inside_low], res.p_low[inside_low] * 1.01,
                                  res.p_up[inside_low], Z)
    assert low_flags >= 20
    up_flags = check_frequencies(hits[inside_up], n[inside_up], res.p_low[inside_up], res.p_up[inside_up] * 0.99, Z)
    assert up_flags == inside_up.sum() == 1


def test_a_worse_controller_is_caught(corridor):
    """Sensitivity of the controller check: the same tables with fwd1 instead of fwd2 (twice the
    slips) must fall below p_low in the lane cells (s^D < s^ceil(D/2) for D >= 2)."""
    part, centres, res = corridor
    ctrl = res.controller(part)
    tables = list(controller_tables(ctrl, centres))
    tables[6] = np.zeros_like(ctrl.strategy)  # strategy: always fwd1
    lane = np.array([cell_of(part, c + 0.5, 1.5) for c in range(K - 3)])  # D >= 2
    n = np.full(lane.size, 2 ** 13)
    hits, capped = simulate(lane, n, 7, *tables, MAX_STEPS)
    assert capped == 0
    assert check_frequencies(hits, n, res.p_low[lane], res.p_up[lane], Z) == lane.size
