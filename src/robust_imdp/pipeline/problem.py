"""The problem of a run: :class:`Problem` (data, modes, noise, grid, regions, specification, bound and
abstraction options) and the per-mode settings it resolves to.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from robust_imdp.bounds import methods
from robust_imdp.errors import InvalidInputError
from robust_imdp.spec.dfa import SEMANTICS  # the values of ``semantics``: the reading of the formula


CLASS_NAMES = ("yes", "no", "maybe")
GUARANTEES = ("confidence", "paper")
#: ``[abstraction].transitions``: Thm 1's containment bounds or the exact per-axis integrals (the values of
#: ``abstraction.rows.TRANSITIONS``, kept here so that importing the problem does not load the abstraction).
TRANSITIONS = ("thm1", "exact")
#: The default of ``transitions``: the exact bounds, never looser than Thm 1's entry by entry and never a Q_yes
#: cell lost on any benchmark (docs/abstraction.md, "When each wins"; benchmarks/results/exact_marginals.md).
DEFAULT_TRANSITIONS = "exact"
#: ``[abstraction].form``: the factored model (per-axis marginals, docs/factored.md) where it applies ("auto"),
#: always ("factored"), or the joint IMDP ("joint"); the values of ``abstraction.factored.FORMS``.
FORMS = ("auto", "factored", "joint")
#: Without a horizon, "auto" takes the factored form only where the joint exact rows are expected more than this
#: many times longer than the factored rows' stored numbers (Problem.form_choice: below it the joint form's
#: component-wise unbounded solves are far faster); with a horizon, wherever the joint rows are longer.
FACTORED_MIN_RATIO = 4
#: How the unknown part is bounded over a cell (see :class:`Problem`): the method registry's names.
ERROR_BOUNDS = methods.ERROR_BOUNDS
#: Failure probability allowed to the assumption check's noise bound when the noise is unbounded.
CHECK_DELTA = 1e-6
#: With ``local_points=None``: modes with more data points than this use local weights (100 points).
LOCAL_AUTO = 1000
LOCAL_DEFAULT = 100


def pool_size(local_points: int | None, m: int) -> int | None:
    """The local pool of a mode with ``m`` data points: ``local_points``, or with None ``LOCAL_DEFAULT``
    above ``LOCAL_AUTO`` points; None (all points) where that pool would hold every point."""
    k = local_points if local_points is not None else (None if m <= LOCAL_AUTO else LOCAL_DEFAULT)
    return None if k is None or k >= m else int(k)


#: The ``tight`` preset's ``split_tol`` (:meth:`Problem.tightened`) in 1-D and 2-D: on the benchmark family it
#: reaches the per-cell optimal boxes' Q_yes where ``rkhs.SPLIT_TOL`` (1.5e-3) does not (2-D r/l 0.5: 118 of
#: 118 against 109 at 1.3x the bound time; benchmarks/results/split_tol_sweep.md, tight_preset.md).
TIGHT_SPLIT_TOL = 4e-4
#: ... and from 3-D on: ``rkhs.SPLIT_TOL`` (a test checks they are equal). The sub-boxes per cell grow as
#: ``(term / split_tol)^(d/2)``: on the family's 3-D r/l 0.125 configuration with all points, 4e-4 took 491 s
#: and 1.5e-3 142 s, both for Q_yes 392, at load about 4 (tight_preset_4e-4_3d.md, tight_preset.md), and
#: 1.5e-3 already meets the slack target there.
TIGHT_SPLIT_TOL_3D = 1.5e-3


#: The ``tight`` preset's budget: at most this many certification boxes (cells x sub-boxes) per mode and
#: output, so that a fine grid does not turn the preset into an hours-long bound stage. The family's 3-D
#: grid (512 cells x 216 sub-boxes = 110,592) fits, the 16^3 unicycle gets 3 pieces per axis instead of 5,
#: and a 64^3 grid gets none (benchmarks/results/tight_problems.md).
TIGHT_MAX_BOXES = 131072


def tight_split_tol(dim: int, n_cells: int | None = None, taylor_term: float | None = None) -> float | None:
    """The ``tight`` preset's ``split_tol``: :data:`TIGHT_SPLIT_TOL` up to 2-D, :data:`TIGHT_SPLIT_TOL_3D` from
    3-D on, raised where ``n_cells`` cells of largest Taylor term ``taylor_term`` (``rkhs.split_term``) would
    otherwise need more than :data:`TIGHT_MAX_BOXES` sub-boxes; None (no sub-boxes) where not even two
    pieces per axis fit. A choice of sub-boxes only: any split is sound."""
    tol = TIGHT_SPLIT_TOL if int(dim) <= 2 else TIGHT_SPLIT_TOL_3D
    if n_cells is None or taylor_term is None:
        return tol
    s_fit = int(np.floor((TIGHT_MAX_BOXES / max(int(n_cells), 1)) ** (1.0 / int(dim)) + 1e-9))
    if s_fit < 2:
        return None
    from robust_imdp.bounds.rkhs_model import MAX_SUB

    if s_fit >= int(np.floor(MAX_SUB ** (1.0 / int(dim)) + 1e-9)):  # the cap of split_counts binds first
        return tol
    # s = ceil(sqrt(term / tol)) <= s_fit (rkhs.split_counts) for every cell with a term up to taylor_term
    return max(tol, float(taylor_term) / s_fit ** 2 * (1 + 1e-6))


def tight_line(problem) -> str:
    """What the ``tight`` preset chose for ``problem`` (a :meth:`Problem.tightened` copy), in one line."""
    split = (f"{problem.split_tol:g}" if problem.split_tol is not None else
             f"none (sub-boxes of this grid would exceed {TIGHT_MAX_BOXES:,} boxes per mode and output)")
    pool = "all points" if problem.local_points is None else problem.local_points
    return f"tight preset: split_tol = {split}, local_points = {pool}"


def cell_taylor_term(cell_size, lengthscale, rkhs_bound: float) -> float:
    """``rkhs.split_term`` of a cell of ``cell_size`` (its Taylor term ``B rho(t_max)``, with the bound stage's
    inflated B and rounded-up ``t_max``): what ``rkhs.split_counts`` weighs against ``split_tol``."""
    from robust_imdp._fp import up
    from robust_imdp._kernels import inv_l2_up, norm_inflation
    from robust_imdp.bounds.rkhs_model import split_term, t_max_up

    r = 0.5 * np.asarray(cell_size, float).reshape(1, -1)
    n = r.shape[1]
    G = float(up(float(rkhs_bound) * norm_inflation(n)))
    return float(split_term(t_max_up(r, inv_l2_up(lengthscale, n)), G)[0])


def tight_settings(points_per_mode, dim: int, local_points: int | None = None, split_tol: float | None = None, *,
                   n_cells: int | None = None, taylor_term: float | None = None) -> dict:
    """The ``tight`` preset's ``split_tol`` and ``local_points`` for ``dim`` dimensions and modes of
    ``points_per_mode`` points; a value the user gave (not None) is kept.

    ``split_tol``: :func:`tight_split_tol` (with ``n_cells`` and the grid's largest Taylor term
    ``taylor_term``, within the box budget). ``local_points``: unchanged where every mode already uses all
    its points (at most ``LOCAL_AUTO``), else the advice's pool lever's proposal
    (``synthesis.advice.pool_proposal``) for the default pool and the largest mode: all points for every
    mode up to ``POOL_ALL_MAX`` (2,048) points per mode, else pools of 400.
    """
    from robust_imdp.synthesis.advice import pool_proposal  # one rule for the lever and the preset

    m = int(max(points_per_mode)) if len(points_per_mode) else 0
    if local_points is None and m > LOCAL_AUTO:
        local_points = pool_proposal(LOCAL_DEFAULT, m)
    if split_tol is None:
        split_tol = tight_split_tol(dim, n_cells, taylor_term)
    return {"split_tol": split_tol, "local_points": local_points}


#: Defaults of the GP route's image / std bounds: target certified gap, branch-and-bound boxes per cell.
BOUND_TOL = 1e-3
BOUND_MAX_BOXES = 2000


# --------------------------------------------------------------------------- the problem file's tables
# Read-only views of a Problem grouped like the problem file's tables (``problem.space.cell_size``,
# ``problem.learning.error_bound``). The Problem itself keeps the flat attributes as its storage: the
# flat constructor, ``replace(cell_size=...)``, flat reads and the cache keys stay exactly as they are,
# and a view is built from them on each read (it holds the same objects, no copies).
@dataclass(frozen=True, eq=False)
class SpaceConfig:
    """``[space]``: the compact set X, the grid size and the dimension names."""

    lower: np.ndarray
    upper: np.ndarray
    cell_size: np.ndarray
    names: tuple | None
    periodic: tuple | None = None


@dataclass(frozen=True, eq=False)
class SpecConfig:
    """``[spec]`` with the ``[[regions.NAME]]`` its formula's atoms name."""

    formula: str
    threshold: float
    horizon: int | None
    regions: dict
    semantics: str = "auto"


@dataclass(frozen=True, eq=False)
class LearningConfig:
    """``[learning]`` (formerly ``[gp]``): the assumption and how the unknown part is bounded."""

    rkhs_bound: Any
    lengthscale: Any
    misspecification: Any
    error_bound: str
    iid_noise: bool
    local_points: int | None
    gp_options: dict
    bound_tol: float
    bound_max_boxes: int
    split_tol: float | None = None

    @property
    def method(self) -> methods.BoundMethod:
        """The error-bound method's registry entry (``bounds.methods``)."""
        return methods.get(self.error_bound)


@dataclass(frozen=True, eq=False)
class AbstractionConfig:
    """``[abstraction]``: how the bounds become an IMDP and what the guarantee is."""

    eta: Any
    eps_rule: str
    combine: str
    guarantee: str
    confidence: float
    transitions: str = DEFAULT_TRANSITIONS
    form: str = "auto"


@dataclass(frozen=True, eq=False)
class Problem:
    """Everything the pipeline needs, as plain values.

    Attributes
    ----------
    space_lower, space_upper, cell_size : (n,) float arrays
        The compact set X and the grid size.
    regions : dict str -> list of (lower (n,), upper (n,)) pairs
        Named regions (the formula's atoms), each a union of boxes.
    formula : str
        LTLf formula over the region names.
    threshold : float in [0, 1]
    horizon : int or None
        k-step horizon; None for the unbounded problem.
    data : system.Dataset or None
        ``x``, ``u`` (mode indices), ``x_next``. None for known dynamics: every component of every mode known
        (``rkhs_bound = 0``), see :attr:`known`.
    mode_names : tuple of str
    maps : tuple of system.AffineMap
        Known part ``f_u(x) = A x + b`` per mode, in ``mode_names`` order.
    noise : noise model (``noise.TruncatedGaussianNoise`` etc.)
    rkhs_bound : float, list per component or dict per mode
        The user's assumption B on the RKHS norm of every unknown component (unit-amplitude SE
        kernel; see ``gp.RKHSErrorBound``); 0 marks a known component, and ``rkhs_bound = 0`` a known
        system (:attr:`known`: no data, no learning, no assumption check).
    gp_options : dict
        Passed to ``gp.learn`` (e.g. ``lengthscale``, ``signal_variance``, ``optimize``,
        ``info_gain``).
    bound_tol : float
        Target certified gap of the image / std bounds.
    bound_max_boxes : int
        Branch-and-bound budget per cell and problem (bounds stay sound, only looser).
    eta : (n,) float array or None
        Noise threshold of Thm 1; None = the noise model's default.
    transitions : {"exact", "thm1"}
        How the transition bounds are computed (``[abstraction].transitions``; docs/abstraction.md):
        ``"exact"`` (default), the exact minimum and maximum over each image box of the noise's mass in
        every target (never looser than Thm 1 per entry, and the only ones that certify anything when the
        noise is wider than a cell; ``eta`` and ``eps_rule`` are unused there), or ``"thm1"``, the paper's
        Thm 1 (its containment events; needed to reproduce the paper).
    form : {"auto", "factored", "joint"}
        How the abstraction is stored and solved (``[abstraction].form``; docs/factored.md, "In the pipeline"):
        "factored", one interval vector per (cell, mode, axis) solved axis by axis (needs ``transitions =
        "exact"``, ``combine = "product"`` and image boxes that hold the whole error: not the GP route with
        ``guarantee = "paper"``); "joint", one interval per (cell, mode, successor); "auto" (default), the
        factored form where it applies (:meth:`form_choice`). Refined cells are always joint.
    guarantee : {"confidence", "paper"}
        How the GP error enters the abstraction. ``"confidence"`` (default, sound for the one
        fixed system that produced the data): the error bound of every GP is taken at one
        data-confidence level and folded into the image boxes
        (``abstraction.confidence_cell_bounds``); every printed bound then holds with
        probability >= ``confidence`` over the data. ``"paper"``: Thm 1 as printed (with the
        corrected complements), where the GP error probability multiplies each transition
        bound; that mixes a probability over the data into the transition probabilities and is
        kept to reproduce the paper (see docs/soundness_audit.md, finding F2).
    confidence : float in (0, 1)
        Data-confidence level of ``guarantee="confidence"`` and of the probabilistic events of
        the other error bounds (unbounded noise, ``iid_noise``); bounded noise without
        ``iid_noise`` needs none (the bounds then hold with probability 1).
    eps_rule : {"optimized", "paper"}
    combine : {"product", "union"}
    error_bound : {"optimal", "ridge", "chowdhury"}
        ``"optimal"`` (default): the tightest cell bounds consistent with ``||g|| <= B`` and the
        data under bounded noise (``rkhs.py``); ``"ridge"``: the same certificate with kernel-ridge
        weights (cheaper, looser); ``"chowdhury"``: GP posterior and the Chowdhury-Gopalan
        error bound (for reproducing the paper).
    misspecification : float >= 0
        tau: each unknown component is within tau (sup norm on X) of a function of RKHS norm
        <= B. Widens the bounds by about tau; makes constants and linear parts honest.
    iid_noise : bool
        The data noise is independent across samples, zero-mean and sub-Gaussian, and the
        inputs were chosen independently of it: intersect with the sub-Gaussian bound (holds
        with probability ``confidence`` over the data).
    local_points : int or None
        Let only the ``local_points`` data points nearest to each cell carry certificate weight
        (``rkhs.local_pools``): the cost per cell no longer grows with the data, and no m x m
        kernel matrix is built. None: all points up to ``LOCAL_AUTO`` points per mode, else 100.
    inputs : models.inputs.InputGrid or None
        The input grid the modes are the points of (``[inputs]`` with one ``[dynamics].f``): then
        ``mode_names`` are its names (``u=(17)``) and the controller returns input vectors too. None: modes
        stated one by one.
    semantics : {"auto", "reach", "safety"}
        The reading of the formula (``[spec].semantics``; README, "Two readings of a formula"): "reach", a
        path satisfies it when some prefix (within the horizon) is accepted; "safety", when no prefix is a
        bad prefix and the path stays in X; "auto" (default), the reading the formula's DFA gives
        (``spec.dfa.classify``: safety for a safety formula such as ``G safe``, reach otherwise).
    split_tol : float > 0 or None
        Sub-box certification (``[learning].split_tol``; ``rkhs.cell_ranges``): a cell whose Taylor
        remainder ``B sqrt(R(t_max))`` exceeds it is certified on ``s^d`` sub-boxes (``rkhs.split_counts``)
        and gets the hull of their ranges; tighter where cells are large against the lengthscale, at a
        higher bound cost (``docs/rkhs_bounds.md``). ``rkhs.SPLIT_TOL`` (1.5e-3) is the suggested value.
        None (the default): never split.
    refine : refine.RefineOptions, dict or None
        Adaptive refinement of the undecided cells after the first solve (the problem file's
        ``[refine]`` table: ``max_cells``, ``max_rounds``, ``min_cell_size``, ``time_budget``,
        ``split``, ``growth``; see :mod:`robust_imdp.synthesis.refine`). None: the uniform grid only.
    dim_names : tuple of n str, or None
        Names of the dimensions (the problem file's ``[space].names``): figure axes, messages and
        ``result.json``'s ``space.names``. None: ``x_1 .. x_n``.
    periodic : tuple of n bool, or None
        Periodic dimensions (``[space].periodic``; period ``upper - lower``): states wrap there,
        X is left only through the other dimensions, residuals are taken modulo the period
        (docs/periodic.md). None (the default, also for all False): no periodic dimension.

    :meth:`from_arrays` builds a Problem from numpy arrays (the Python counterpart of a problem
    file).

    The attributes are flat (the constructor's keywords); read-only views group them like the
    problem file's tables: ``space`` (:class:`SpaceConfig`), ``spec`` (:class:`SpecConfig`),
    ``learning`` (:class:`LearningConfig`), ``abstraction`` (:class:`AbstractionConfig`), and
    ``refine``; ``method`` is the error-bound method's entry in ``bounds.methods``.
    """

    space_lower: np.ndarray
    space_upper: np.ndarray
    cell_size: np.ndarray
    regions: dict
    formula: str
    threshold: float
    horizon: int | None
    data: Any
    mode_names: tuple
    maps: tuple
    noise: Any
    rkhs_bound: float
    gp_options: dict = field(default_factory=dict)
    bound_tol: float = BOUND_TOL
    bound_max_boxes: int = BOUND_MAX_BOXES
    eta: Any = None
    eps_rule: str = "optimized"
    combine: str = "product"
    guarantee: str = "confidence"
    confidence: float = 0.99
    error_bound: str = "optimal"
    misspecification: float = 0.0
    iid_noise: bool = False
    local_points: int | None = None
    refine: Any = None
    dim_names: tuple | None = None
    periodic: tuple | None = None
    split_tol: float | None = None
    semantics: str = "auto"
    inputs: Any = None
    transitions: str = DEFAULT_TRANSITIONS
    form: str = "auto"

    def __post_init__(self):
        if np.ndim(self.cell_size) == 0:  # one number: the same width on every axis (as from_arrays reads it)
            n = int(np.size(self.space_lower))
            object.__setattr__(self, "cell_size", np.full(n, float(self.cell_size)))
        if self.periodic is not None:
            from robust_imdp.models.geometry import check_periodic

            object.__setattr__(self, "periodic", check_periodic(self.periodic, int(np.size(self.space_lower))))
        if self.dim_names is not None:
            n = int(np.size(self.space_lower))
            names = self.dim_names
            if (isinstance(names, str) or len(names) != n or not all(isinstance(v, str) and v for v in names)
                    or len(set(names)) != len(names)):
                raise InvalidInputError(
                    f"dim_names must be {n} distinct non-empty names (one per dimension) or None; got {names!r}")
            object.__setattr__(self, "dim_names", tuple(names))
        if self.guarantee not in GUARANTEES:
            raise InvalidInputError(f"guarantee must be one of {GUARANTEES}; got {self.guarantee!r}")
        if self.semantics not in SEMANTICS:
            raise InvalidInputError(f"semantics must be one of {', '.join(map(repr, SEMANTICS))} (the reading of "
                                    f"the formula); got {self.semantics!r}")
        c = float(self.confidence)
        if not 0.0 < c < 1.0:
            raise InvalidInputError(f"confidence must lie in (0, 1); got {self.confidence!r}")
        try:  # checked here, not only in synthesize: a bad threshold must fail before the long stages
            t_ok = not isinstance(self.threshold, bool) and 0.0 <= float(self.threshold) <= 1.0
        except (TypeError, ValueError):
            t_ok = False
        if not t_ok:
            raise InvalidInputError(f"threshold must be a probability in [0, 1]; got {self.threshold!r}")
        h = self.horizon
        if h is not None and (isinstance(h, bool) or not isinstance(h, (int, np.integer)) or h < 1):
            raise InvalidInputError(f"horizon must be None (unbounded) or an integer >= 1; got {h!r}")
        method = methods.get(self.error_bound)  # the method's rules and messages live in the registry
        method.check_guarantee(self.guarantee)
        # one number (checked here as before), or per mode and component (checked by _check_known_parts)
        tau = float(self.misspecification) if np.ndim(self.misspecification) == 0 and not isinstance(
            self.misspecification, dict) else float(_settings(self).misspecification.max())
        if not (np.isfinite(tau) and tau >= 0):
            raise InvalidInputError(f"misspecification must be a finite float >= 0; got {self.misspecification!r}")
        if self.local_points is not None and (int(self.local_points) != self.local_points or self.local_points < 1):
            raise InvalidInputError(f"local_points must be a positive integer or None; got {self.local_points!r}")
        if self.split_tol is not None:
            ok = not isinstance(self.split_tol, bool) and isinstance(self.split_tol, (int, float, np.floating))
            if not ok or not (np.isfinite(float(self.split_tol)) and float(self.split_tol) > 0):
                raise InvalidInputError(f"split_tol must be a finite float > 0 (certify a cell on sub-boxes where "
                                        f"its Taylor term exceeds it) or None (never); got {self.split_tol!r}")
            method.check_split()
        method.check_noise_options(tau, self.iid_noise)
        if self.transitions not in TRANSITIONS:
            raise InvalidInputError(f"transitions must be one of {', '.join(TRANSITIONS)}; got {self.transitions!r}")
        if self.form not in FORMS:
            raise InvalidInputError(f"form must be one of {', '.join(FORMS)} (how the abstraction is stored); got "
                                    f"{self.form!r}")
        if self.form == "factored" and self.factored_reason() is not None:
            raise InvalidInputError(f"form = 'factored' does not apply: {self.factored_reason()}")
        method.check_gp_options(self.gp_options)
        self._check_known_parts()
        if self.inputs is not None:
            grid = self.inputs
            if tuple(getattr(grid, "mode_names", ())) != tuple(self.mode_names):
                raise InvalidInputError(
                    f"inputs must be the input grid whose points are the modes (its mode_names equal mode_names); got "
                    f"{type(grid).__name__} with {len(getattr(grid, 'mode_names', ()))} points for "
                    f"{len(self.mode_names)} modes")
        if self.refine is not None:
            from robust_imdp.synthesis.refine import RefineOptions

            object.__setattr__(self, "refine", RefineOptions.from_dict(self.refine))
            method.check_refine(self.iid_noise)

    def _check_known_parts(self) -> None:
        """Every mode's known part has the known-part interface; the assumption resolves per mode and component."""
        n = int(np.size(self.space_lower))
        maps = tuple(self.maps)
        if len(maps) != len(self.mode_names):
            raise InvalidInputError(f"maps must give one known part per mode ({len(self.mode_names)}: "
                                    f"{list(self.mode_names)}); got {len(maps)}")
        for name, m in zip(self.mode_names, maps):
            missing = [a for a in ("dim", "image_bounds", "fingerprint") if not hasattr(m, a)] + \
                ([] if callable(m) else ["__call__"])
            if missing:
                raise InvalidInputError(
                    f"maps: the known part of mode {name!r} must be a system.AffineMap or a known.KnownDynamics "
                    f"(it needs {missing}); got {type(m).__name__} {m!r}")
            if int(m.dim) != n:
                raise InvalidInputError(f"maps: the known part of mode {name!r} must act on {n} dimensions like "
                                        f"space_lower; got dimension {m.dim}")
        settings = _settings(self)  # raises on a wrong form, naming rkhs_bound / lengthscale / misspecification
        if np.all(settings.known):  # known dynamics: nothing is learned, the data (if any) are not used
            return
        if self.data is None:
            raise InvalidInputError(
                "data are needed for the unknown components (rkhs_bound > 0: mode, component "
                + ", ".join(f"{self.mode_names[u]!r} {i + 1}" for u, i in np.argwhere(~settings.known)[:3])
                + (" ..." if np.count_nonzero(~settings.known) > 3 else "")
                + "); only a problem whose every component is known (rkhs_bound = 0) takes data=None")
        nonlinear = [name for name, m in zip(self.mode_names, maps) if not _is_affine(m)]
        self.method.check_known_parts(nonlinear, settings.uniform, self.rkhs_bound, self.gp_options.get("lengthscale"))

    # ----------------------------------------------------------------- views by table
    @property
    def space(self) -> SpaceConfig:
        return SpaceConfig(self.space_lower, self.space_upper, self.cell_size, self.dim_names, self.periodic)

    @property
    def spec(self) -> SpecConfig:
        return SpecConfig(self.formula, self.threshold, self.horizon, self.regions, self.semantics)

    @property
    def learning(self) -> LearningConfig:
        return LearningConfig(self.rkhs_bound, self.gp_options.get("lengthscale"), self.misspecification,
                              self.error_bound, self.iid_noise, self.local_points, self.gp_options, self.bound_tol,
                              self.bound_max_boxes, self.split_tol)

    @property
    def abstraction(self) -> AbstractionConfig:
        return AbstractionConfig(self.eta, self.eps_rule, self.combine, self.guarantee, self.confidence,
                                 self.transitions, self.form)

    def factored_reason(self) -> str | None:
        """Why the factored form does not apply to this problem's grid, or None when it does (the settings'
        part of ``abstraction.factored.factored_reason``: the grid is a grid, every noise model has independent
        components)."""
        if self.transitions != "exact":
            return (f"transitions = {self.transitions!r}: Thm 1's bounds are containment events of the joint image, "
                    "not per-axis marginals (the factored form needs transitions = 'exact')")
        if self.combine != "product":
            return (f"combine = {self.combine!r} assumes no independence between the noise's components: only "
                    "Frechet's joint bounds hold, not a product of per-axis laws")
        if self.guarantee == "paper" and not self.known:
            return ("guarantee = 'paper' mixes the laws on and off the GP error event (the P_g mixture), which is no "
                    "product of per-axis laws")
        return None

    def form_choice(self) -> tuple:
        """``(form, why)``: the form the run's grid abstraction takes ("factored" or "joint") and why, in words.

        "auto" takes the factored form where it applies and its rows are expected smaller than the joint exact
        rows (``abstraction.factored.row_sizes``: a joint row lists about ``prod_i`` of the per-axis successors, a
        factored one stores ``sum_i (2 k_i + 4)`` numbers) -- without a horizon, more than
        :data:`FACTORED_MIN_RATIO` times smaller: there its pessimistic value is never below the joint IMDP's
        (docs/factored.md, Theorem 2) and it costs less. Where the joint rows are short (noise narrower than a
        cell, as in the case studies) the joint form is kept: as fast there, and its unbounded solves have the
        end-component deflation that makes p_up tight. Without a horizon the joint form is also kept where its
        rows are only a little longer: its unbounded solve goes component by component, where the factored solver
        sweeps the whole product until its values settle (the 4-D vehicle at 24^4, 81 successors against 40
        numbers: synthesis 25 s joint, over 2,100 s factored; docs/factored.md, "In the pipeline";
        benchmarks/results/factored_pipeline.md). The choice depends on the problem (whether it has a horizon,
        not which) and not on the machine, so a cached abstraction is reused when only the formula, threshold or
        horizon length change.
        """
        why_not = self.factored_reason()
        if self.form == "joint":
            return "joint", "[abstraction].form = 'joint'"
        if why_not is not None:  # form "auto" (an explicit "factored" that does not apply is refused above)
            return "joint", f"auto: the factored form does not apply ({why_not})"
        if self.form == "factored":
            return "factored", "[abstraction].form = 'factored'"
        from robust_imdp.abstraction.factored import row_sizes

        joint, numbers = row_sizes(self.space_lower, self.space_upper, self.cell_size, self.noise)
        unbounded_short = self.horizon is None and joint <= FACTORED_MIN_RATIO * numbers
        if joint > numbers and not unbounded_short:
            return "factored", (f"auto: it applies (a grid, exact per-axis bounds, independent noise components, image "
                                f"boxes that hold the whole error) and stores about {numbers} numbers per row where "
                                f"the joint IMDP would list about {joint:,} successors; its value is never below the "
                                "joint IMDP's")
        if unbounded_short and joint > numbers:
            return "joint", (f"auto: no horizon and the joint rows are not much longer (about {joint:,} successors per "
                             f"row against {numbers} numbers factored, at most {FACTORED_MIN_RATIO} x): the joint "
                             "form's unbounded solve goes component by component and deflates end components, far "
                             "faster than the factored sweeps; [abstraction].form = 'factored' forces the factored "
                             "form")
        return "joint", (f"auto: the joint rows are short (about {joint:,} successors per row against {numbers} "
                         "numbers factored): the joint form is as fast, and its unbounded solves deflate end "
                         "components; [abstraction].form = 'factored' forces the factored form")

    def abstraction_options(self) -> dict:
        """The keyword options of ``abstraction.abstract`` / ``abstract_rows`` this problem asks for (one place)."""
        return {"eta": self.eta, "eps_rule": self.eps_rule, "combine": self.combine, "transitions": self.transitions}

    @property
    def method(self) -> methods.BoundMethod:
        """The error-bound method's registry entry: ask its capabilities, not its name."""
        return methods.get(self.error_bound)

    def tightened(self) -> "Problem":
        """A copy with the ``tight`` preset (:func:`tight_settings`; ``robust-imdp run --tight``): certification
        sub-boxes down to a Taylor term of :data:`TIGHT_SPLIT_TOL` (1-D, 2-D) or :data:`TIGHT_SPLIT_TOL_3D`
        (3-D and up) and, where local pools would be used, all of a mode's points up to 2,048 per mode (else
        pools of 400). ``split_tol`` and ``local_points`` the problem already sets are kept. Tighter bounds where
        cells are large against the lengthscale, at several times the bound time
        (benchmarks/results/tight_preset.md on the benchmark family, tight_problems.md on the case studies).

        Raises InvalidInputError for an error-bound method without sub-box certificates (the GP route). A known
        system (:attr:`known`) has nothing to tighten: it is returned as it is.
        """
        if self.known:
            return self
        self.method.check_split()
        counts = np.bincount(np.asarray(self.data.u, dtype=np.int64), minlength=len(self.mode_names))
        return self.replace(**tight_settings(counts, int(np.size(self.space_lower)), self.local_points,
                                             self.split_tol, n_cells=self.n_grid_cells,
                                             taylor_term=self.grid_taylor_term()))

    @property
    def known(self) -> bool:
        """Every component of every mode is known (``rkhs_bound`` 0 everywhere): "known dynamics", nothing is
        learned, no data are needed and no assumption is checked (the bounds hold with probability 1 under the
        noise model)."""
        return bool(np.all(_settings(self).known))

    @property
    def n_grid_cells(self) -> int:
        """Cells of the plain grid of ``cell_size`` over X (regions that do not fit it add a few cells)."""
        lo, up, cs = (np.asarray(a, float) for a in (self.space_lower, self.space_upper, self.cell_size))
        return int(np.prod(np.ceil((up - lo) / cs - 1e-9)))

    def grid_taylor_term(self) -> float:
        """The largest Taylor term of a grid cell over the modes and components (:func:`cell_taylor_term`;
        0 for known components): what ``rkhs.split_counts`` weighs against ``split_tol``. Cells that the
        regions cut are smaller."""
        st = _settings(self)
        return max([cell_taylor_term(self.cell_size, st.lengthscale[u, i], float(st.rkhs_bound[u, i]))
                    for u in range(st.rkhs_bound.shape[0]) for i in range(st.rkhs_bound.shape[1])
                    if st.rkhs_bound[u, i] > 0], default=0.0)

    def replace(self, **changes) -> "Problem":
        """A copy with some attributes changed (e.g. ``formula=...``)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        unknown = set(changes) - set(values)
        if unknown:
            raise InvalidInputError(f"Problem has no attributes {sorted(unknown)}")
        values.update(changes)
        return Problem(**values)

    def calibrate(self, *, folds: int = 5, rng=0, keep_lengthscale: bool = False, workers: int | None = None,
                  scheduler: str | None = None, progress=None):
        """Suggest ``rkhs_bound`` and ``lengthscale`` per mode and component from the data: evidence, not proof.

        ``bounds.calibrate.calibrate_problem`` (docs/calibration.md): the GP likelihood and cross-validation
        curves of the lengthscale, the certified minimum norm, held-out violations of the certified bound per
        B with a Clopper-Pearson bound, and affine trends. The problem itself is not changed; the result's
        ``suggested`` holds the values in the shapes of ``[learning]`` (``learning_table()`` as TOML).

        Parameters
        ----------
        folds : int >= 2
        rng : seed of the subsets and folds
        keep_lengthscale : bool
            Keep this problem's lengthscale (e.g. one per input dimension) and calibrate B only.
        workers, scheduler
            Where the components run, as in ``synthesize_from_data`` (``pipeline.parallel.open_scheduler``).
        progress : callable(str), optional
            One line per finished component.

        Returns
        -------
        bounds.calibrate.Calibration
        """
        from robust_imdp.bounds.calibrate import calibrate_problem
        from robust_imdp.pipeline.parallel import open_scheduler

        with open_scheduler(workers=workers, scheduler=scheduler) as sched:
            return calibrate_problem(self, folds=folds, rng=rng, keep_lengthscale=keep_lengthscale, scheduler=sched,
                                     progress=progress)

    @classmethod
    def from_arrays(cls, x, u, x_next, *, lower, upper, cell_size, regions, formula, threshold, modes, noise,
                    rkhs_bound, horizon=None, lengthscale=None, names=None, **options) -> "Problem":
        """A Problem from numpy arrays: the Python counterpart of a problem file.

        Parameters
        ----------
        x, x_next : (m, n) float arrays, or None
            The sampled states and their successors (``[data]``); None (with ``u``) for known dynamics
            (``rkhs_bound = 0``: every component of every mode known, :attr:`known`).
        u : (m,) array of mode names (str), or of mode indices into ``modes``; or None
        lower, upper : (n,) float arrays
            The compact set X (``[space]``).
        cell_size : float or (n,) float array
        regions : dict str -> box or list of boxes
            A box is a pair ``(lower (n,), upper (n,))`` (``[[regions.NAME]]``).
        formula : str
            LTLf over the region names (``[spec]``).
        threshold : float in [0, 1]
        modes : dict str -> (A (n, n), b (n,)), system.AffineMap, known.KnownDynamics, a list of n
            expression strings in ``x1..xn`` or a pair (casadi expression (n, 1), casadi symbol (n, 1))
            The known part ``f_u`` of each mode, in mode order (``[modes.NAME]``: ``A``/``b`` or ``f``).
            With ``inputs`` (an ``InputGrid``, one of the ``**options``): the dynamics ``f(x, u)`` once, a list
            of n expressions in ``x1..xn, u1..um`` (``[dynamics].f``); the modes are the grid's points, and ``u``
            of the data may hold input vectors ``(m_samples, m)`` on the grid.
        noise : noise model (``TruncatedGaussianNoise``, ``GaussianNoise``, ``UniformNoise``)
        rkhs_bound : float, list of n floats or dict mode -> either
            The assumption B (``[learning].rkhs_bound``), per mode and component where given so; 0 marks a
            known component (``robust_imdp.bounds.assumptions``).
        horizon : int or None
        lengthscale : float, (n,) float array (per input dimension), per-component list or dict per mode
            The kernel lengthscale (``[learning].lengthscale``, kept in ``gp_options``).
        names : sequence of n str, optional
            Dimension names (``[space].names``).
        **options
            Any other attribute of :class:`Problem` (``error_bound``, ``misspecification``,
            ``local_points``, ``eta``, ``confidence``, ``refine``, ...).

        Returns
        -------
        Problem

        Example
        -------
        A robot that moves 0.3 east or north per step, to reach ``goal`` without touching
        ``obstacle`` (the data here are exact: ``x_next - f_u(x) = 0``):

        >>> import numpy as np
        >>> from robust_imdp import Problem, TruncatedGaussianNoise, synthesize_from_data
        >>> rng = np.random.default_rng(0)
        >>> x = rng.uniform(0, 4, (200, 2))
        >>> u = np.where(np.arange(200) < 100, "east", "north")
        >>> x_next = x + np.where(u[:, None] == "east", [0.3, 0.0], [0.0, 0.3])
        >>> problem = Problem.from_arrays(
        ...     x, u, x_next, lower=[0, 0], upper=[4, 4], cell_size=0.5,
        ...     regions={"goal": ([3, 3], [4, 4]), "obstacle": ([1.5, 1], [2.5, 3])},
        ...     formula="G !obstacle & F goal", threshold=0.9,
        ...     modes={"east": (np.eye(2), [0.3, 0]), "north": (np.eye(2), [0, 0.3])},
        ...     noise=TruncatedGaussianNoise([0.01, 0.01], [0.02, 0.02]), rkhs_bound=0.2,
        ...     lengthscale=1.0, names=("x", "y"))
        >>> problem.mode_names, problem.dim_names
        (('east', 'north'), ('x', 'y'))
        >>> result = synthesize_from_data(problem, progress=False)  # doctest: +SKIP
        """
        from robust_imdp.errors import DimensionError
        from robust_imdp.models.system import AffineMap, Dataset

        lo = np.asarray(lower, dtype=float).reshape(-1)
        up = np.asarray(upper, dtype=float).reshape(-1)
        n = lo.size
        if up.shape != (n,):
            raise DimensionError(f"upper must have {n} entries like lower; got {np.shape(upper)}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(up)) and np.all(lo < up)):
            raise InvalidInputError(f"lower and upper must be finite with lower < upper in every dimension; got "
                                    f"lower={lo.tolist()}, upper={up.tolist()}")
        h = np.asarray(cell_size, dtype=float)
        h = np.full(n, float(h)) if h.ndim == 0 else h.reshape(-1)
        if h.shape != (n,) or not np.all(np.isfinite(h)) or np.any(h <= 0):
            raise InvalidInputError(f"cell_size must be a number > 0 or {n} numbers > 0 (one per dimension); got "
                                    f"{np.asarray(cell_size).tolist()!r}")
        _check_noise(noise, n)
        grid = options.get("inputs")
        if grid is not None:  # one f(x, u) for every point of the grid
            from robust_imdp.models.inputs import input_modes

            if isinstance(modes, dict) or isinstance(modes, str) or not isinstance(modes, (list, tuple)) \
                    or len(modes) != n:
                raise InvalidInputError(f"with inputs, modes must be the dynamics f(x, u): a list of {n} expressions "
                                        f"in x1..x{n}, u1..u{grid.n_inputs} (one per component); got {modes!r}")
            maps = list(input_modes(list(modes), grid, name="modes"))
            modes = dict(zip(grid.mode_names, maps))
        elif not isinstance(modes, dict) or not modes:
            raise InvalidInputError(f"modes must be a dict name -> (A, b) or AffineMap, with at least one mode; "
                                    f"got {modes!r}")
        else:
            maps = []
            for name, m in modes.items():
                m = _known_part(m, name)
                if m.dim != n:
                    raise DimensionError(f"modes[{name!r}] must act on {n} dimensions like lower; got "
                                         + (f"A of shape {m.A.shape}" if _is_affine(m) else f"{m.dim} components"))
                maps.append(m)
        if not isinstance(regions, dict):
            raise InvalidInputError(f"regions must be a dict name -> box or list of boxes; got {regions!r}")
        boxes = {}
        for name, value in regions.items():
            try:
                arr = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                arr = None
            if arr is not None and arr.shape == (2, n):
                arr = arr[None]
            if arr is None or arr.ndim != 3 or arr.shape[1:] != (2, n) or arr.shape[0] == 0:
                raise InvalidInputError(f"regions[{name!r}] must be a box (lower, upper) or a list of boxes of "
                                        f"{n} numbers each; got {value!r}")
            boxes[str(name)] = [(a[0], a[1]) for a in arr]
        _check_regions(boxes, lo, up, options.get("periodic"))
        _check_formula(formula, boxes)
        unknown = sorted(set(options) - {f.name for f in fields(cls)})
        if unknown:
            raise InvalidInputError(f"Problem.from_arrays got unknown options {unknown}; the other arguments "
                                    f"are attributes of Problem: {[f.name for f in fields(cls)]}")
        gp_options = dict(options.pop("gp_options", None) or {})
        if lengthscale is not None:
            gp_options["lengthscale"] = lengthscale
        given = [a is not None for a in (x, u, x_next)]
        if any(given) and not all(given):
            raise InvalidInputError(f"x, u and x_next must all be given (the data) or all be None (known dynamics, "
                                    f"rkhs_bound = 0); got {['x', 'u', 'x_next'][given.index(False)]} = None")
        data = None
        if all(given):
            if grid is not None and np.asarray(u).dtype.kind not in "UO":  # input vectors: their grid points
                u = grid.index(np.asarray(u, dtype=float).reshape(len(u), -1), what="u")
            data = Dataset(x, u, x_next, modes=tuple(modes))
            if data.dim != n:
                raise DimensionError(f"x must have {n} columns like lower; got shape {np.shape(x)}")
        return cls(space_lower=lo, space_upper=up, cell_size=h, regions=boxes, formula=formula,
                   threshold=threshold, horizon=horizon, data=data, mode_names=tuple(modes), maps=tuple(maps),
                   noise=noise, rkhs_bound=rkhs_bound, gp_options=gp_options,
                   dim_names=None if names is None else tuple(names), **options)

    def __repr__(self) -> str:  # a few lines: the dataclass default prints every data array
        lo, up = np.asarray(self.space_lower, float), np.asarray(self.space_upper, float)
        h = np.broadcast_to(np.asarray(self.cell_size, float), lo.shape)
        shape = [int(round(v)) for v in (up - lo) / h]
        names = self.dim_names or tuple(f"x_{j + 1}" for j in range(lo.size))
        box = ", ".join(f"{v} in [{a:g}, {b:g}]" for v, a, b in zip(names, lo, up))
        m = int(np.asarray(getattr(self.data, "u", ())).shape[0])
        samples = "known dynamics (no data)" if self.data is None else f"{m} samples"
        return (f"Problem({lo.size}-D, {int(np.prod(shape))} cells ({' x '.join(map(str, shape))}); {box}\n"
                f"  formula {self.formula!r}, threshold {float(self.threshold):g}"
                f"{'' if self.horizon is None else f', horizon {self.horizon}'}"
                f"{'' if self.semantics == 'auto' else f', semantics {self.semantics!r}'}; regions {list(self.regions)}\n"
                f"  modes {_modes_text(self.mode_names) if self.inputs is None else repr(self.inputs)}, {samples}, "
                f"{type(self.noise).__name__}, "
                f"rkhs_bound {_setting_text(self.rkhs_bound)}, error_bound {self.error_bound!r})")


def _check_noise(noise, n: int) -> None:
    """``from_arrays``' noise: a noise model of ``models.noise`` acting on ``n`` dimensions."""
    from robust_imdp.models.noise import NoiseModel

    if not isinstance(noise, NoiseModel):
        raise InvalidInputError(
            f"noise must be a noise model: TruncatedGaussianNoise(sigma, bound), GaussianNoise(sigma) or "
            f"UniformNoise(bound) (robust_imdp.models.noise, each with {n} values per argument); got "
            f"{type(noise).__name__} {noise!r}")
    if int(noise.dim) != n:
        raise InvalidInputError(f"noise must act on {n} dimensions like lower; got {noise!r} ({noise.dim} dimensions)")


def _check_regions(boxes: dict, lo: np.ndarray, up: np.ndarray, periodic) -> None:
    """``from_arrays``' regions: every box has lower < upper and lies in X, except on a periodic dimension, where
    it may cross the seam by at most one period (docs/periodic.md; ``geometry.wrap_region_boxes`` cuts it)."""
    flags = np.zeros(lo.size, dtype=bool) if periodic is None else np.asarray(periodic, dtype=bool).reshape(-1)
    if flags.shape != lo.shape:
        return  # Problem's own check of ``periodic`` names the mismatch
    for name, pairs in boxes.items():
        for j, (a, b) in enumerate(pairs):
            where = f"regions[{name!r}]" + (f" box {j}" if len(pairs) > 1 else "")
            if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(a < b)):
                raise InvalidInputError(f"{where} needs finite lower < upper in every dimension; got lower={a.tolist()}, "
                                        f"upper={b.tolist()}")
            out = np.flatnonzero(((a < lo) | (b > up)) & ~flags)
            if out.size:
                k = int(out[0])
                raise InvalidInputError(
                    f"{where} = [{a.tolist()}, {b.tolist()}] lies outside X = [{lo.tolist()}, {up.tolist()}] in "
                    f"dimension {k + 1}; a region box must lie inside X (only on a periodic dimension may it cross the "
                    "seam)")
            wide = np.flatnonzero(flags & (b - a > up - lo))
            if wide.size:
                k = int(wide[0])
                raise InvalidInputError(f"{where} is {b[k] - a[k]:g} wide in dimension {k + 1}, which is periodic with "
                                        f"period {up[k] - lo[k]:g}; a region box may be at most one period wide")


def _check_formula(formula, boxes: dict) -> None:
    """``from_arrays``' formula: LTLf text that parses (``FormulaSyntaxError`` shows where) and names only regions
    (``UnknownAtomError``); checked at construction, not at synthesis."""
    from robust_imdp.errors import UnknownAtomError
    from robust_imdp.spec.ltlf import atoms_of

    if not isinstance(formula, str) or not formula.strip():
        raise InvalidInputError(f"formula must be a non-empty LTLf string over the region names; got {formula!r}")
    unknown = sorted(atoms_of(formula) - set(boxes))
    if unknown:
        raise UnknownAtomError(f"formula {formula!r} names regions {unknown} that are not defined; known regions: "
                               f"{sorted(boxes)}")


def _modes_text(names) -> str:
    """The mode names for a one-line summary: all of them up to 8, else the first three, a count and the last."""
    names = list(names)
    if len(names) <= 8:
        return str(names)
    return f"[{', '.join(map(repr, names[:3]))}, ... ({len(names)} modes), {names[-1]!r}]"


def _is_affine(m) -> bool:
    """The affine fast path: ``f_u(x) = A x + b`` bounded jointly with ``g_u`` at the cell vertices (eq. C)."""
    return hasattr(m, "A") and hasattr(m, "b")


def _known_part(m, name):
    """A mode's known part from the forms :meth:`Problem.from_arrays` accepts."""
    from robust_imdp.models.known import KnownDynamics, _is_casadi
    from robust_imdp.models.system import AffineMap

    if isinstance(m, (AffineMap, KnownDynamics)):
        return m
    if isinstance(m, (list, tuple)) and m and all(isinstance(e, str) for e in m):
        return KnownDynamics(list(m), name=f"modes[{name!r}]")
    if isinstance(m, (list, tuple)) and len(m) == 2 and _is_casadi(m[0]):
        return KnownDynamics(m[0], m[1], name=f"modes[{name!r}]")
    try:
        A, b = m
    except (TypeError, ValueError):
        raise InvalidInputError(
            f"modes must give (A, b) or an AffineMap for mode {name!r}; got {m!r} (a nonlinear known part: a "
            "KnownDynamics, a list of expressions in x1..xn or a pair (casadi expression, casadi symbol))") from None
    return AffineMap(A, b)


def _settings(problem):
    """The assumption per mode and component (``assumptions.Settings``)."""
    from robust_imdp.bounds.assumptions import resolve

    return resolve(problem.rkhs_bound, problem.gp_options.get("lengthscale"), problem.misspecification,
                   problem.mode_names, int(np.size(problem.space_lower)))


def _setting_text(value) -> str:
    try:
        return f"{float(value):g}"
    except (TypeError, ValueError):
        return repr(value)


def _setting_value(value):
    """A setting as the cache keys and result files carry it: a float when it is one number (as before)."""
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, dict):
        return {str(k): _setting_value(v) for k, v in value.items()}
    return np.asarray(value, dtype=float).tolist()


def _map_key(m):
    """What the cache keys fingerprint of a known part: (A, b) for an affine one (as before), else its digest."""
    if _is_affine(m):
        return (np.asarray(m.A, float), np.asarray(m.b, float))
    return ("known", m.fingerprint())
