"""From data and a requirement to a controller with guarantees, in one call.

``synthesize_from_data(problem)`` chains the stages of the paper (Jackson et al., HSCC 2021):

1. **specify** -- LTLf formula to a minimal DFA (``dfa.ltlf_to_dfa``); checked first, so an
   unknown region fails before any expensive work;
2. **partition** -- grid over X respecting the labelled regions (``geometry.Partition``);
3. **check** -- the data-implied minimum RKHS norm of every mode and output
   (``rkhs.check_assumption``): a ``rkhs_bound`` the data refute is refused before any work;
4. **learn + bound** -- certified image boxes of ``f_u + g_u`` over every cell. Default
   (``error_bound="optimal"``): the optimal deterministic bound under bounded noise
   (``rkhs.image_ranges``; ``"ridge"`` is its cheaper closed form). ``"chowdhury"``: one GP
   per mode and output with the error bound of Chowdhury & Gopalan (2017, Thm 2)
   (``gp.learn``) and certified bounds of ``f_u + mu`` and of the posterior std
   (``bounds.bound_image``);
5. **abstract** -- the interval MDP of the paper's Thm 1 (``abstraction.abstract``);
6. **synthesize** -- product with the DFA, robust strategy, ``p_low``, ``p_up``, ``p_up_star``,
   ``error`` and the classes Q_yes / Q_no / Q_? (``synthesis.synthesize``).

Stages 3-5 depend only on the data, modes, noise, grid, regions and GP / abstraction options;
with ``abstraction_cache=DIR`` the learned cell bounds (stages 3-4) and the abstraction (5) are
saved under hashes of exactly their inputs: the abstraction is reused when only the formula,
threshold or horizon changes (:func:`resynthesize` does the same in memory), the cell bounds
also when only eta, the eps rule or the combination rule change.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

from robust_imdp.errors import InvalidInputError, UnknownAtomError, interrupt_in

__all__ = ["Problem", "Result", "synthesize_from_data", "resynthesize", "abstraction_key",
           "bounds_key", "estimate_resources"]

CLASS_NAMES = ("yes", "no", "maybe")
GUARANTEES = ("confidence", "paper")
#: How the unknown part is bounded over a cell (see :class:`Problem`).
ERROR_BOUNDS = ("optimal", "ridge", "chowdhury")
#: Failure probability allowed to the assumption check's noise bound when the noise is unbounded.
CHECK_DELTA = 1e-6
#: With ``local_points=None``: modes with more data points than this use local weights (100 points).
LOCAL_AUTO = 1000
LOCAL_DEFAULT = 100


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
    data : system.Dataset
        ``x``, ``u`` (mode indices), ``x_next``.
    mode_names : tuple of str
    maps : tuple of system.AffineMap
        Known part ``f_u(x) = A x + b`` per mode, in ``mode_names`` order.
    noise : noise model (``noise.TruncatedGaussianNoise`` etc.)
    rkhs_bound : float
        The user's assumption B on the RKHS norm of every unknown component (unit-amplitude SE
        kernel; see ``gp.RKHSErrorBound``).
    gp_options : dict
        Passed to ``gp.learn`` (e.g. ``lengthscale``, ``signal_variance``, ``optimize``,
        ``info_gain``).
    bound_tol : float
        Target certified gap of the image / std bounds.
    bound_max_boxes : int
        Branch-and-bound budget per cell and problem (bounds stay sound, only looser).
    eta : (n,) float array or None
        Noise threshold of Thm 1; None = the noise model's default.
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
    refine : refine.RefineOptions, dict or None
        Adaptive refinement of the undecided cells after the first solve (the problem file's
        ``[refine]`` table: ``max_cells``, ``max_rounds``, ``min_cell_size``, ``time_budget``,
        ``split``, ``growth``; see :mod:`robust_imdp.synthesis.refine`). None: the uniform grid only.
    dim_names : tuple of n str, or None
        Names of the dimensions (the problem file's ``[space].names``): figure axes, messages and
        ``result.json``'s ``space.names``. None: ``x_1 .. x_n``.

    :meth:`from_arrays` builds a Problem from numpy arrays (the Python counterpart of a problem
    file).
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
    bound_tol: float = 1e-3
    bound_max_boxes: int = 2000
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

    def __post_init__(self):
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
        if self.error_bound not in ERROR_BOUNDS:
            raise InvalidInputError(f"error_bound must be one of {ERROR_BOUNDS}; got {self.error_bound!r}")
        if self.guarantee == "paper" and self.error_bound != "chowdhury":
            raise InvalidInputError(
                f"guarantee 'paper' (Thm 1 as printed) needs error_bound 'chowdhury'; got {self.error_bound!r}")
        # one number (checked here as before), or per mode and component (checked by _check_known_parts)
        tau = float(self.misspecification) if np.ndim(self.misspecification) == 0 and not isinstance(
            self.misspecification, dict) else float(_settings(self).misspecification.max())
        if not (np.isfinite(tau) and tau >= 0):
            raise InvalidInputError(f"misspecification must be a finite float >= 0; got {self.misspecification!r}")
        if self.local_points is not None and (int(self.local_points) != self.local_points or self.local_points < 1):
            raise InvalidInputError(f"local_points must be a positive integer or None; got {self.local_points!r}")
        if self.error_bound == "chowdhury" and (tau > 0 or self.iid_noise):
            raise InvalidInputError(
                "misspecification and iid_noise apply to error_bound 'optimal' or 'ridge' only; the GP route "
                f"(error_bound 'chowdhury') has neither; got misspecification={tau!r}, iid_noise={self.iid_noise!r}")
        if self.error_bound != "chowdhury":
            extra = sorted(set(self.gp_options) - {"lengthscale"})
            if extra:
                raise InvalidInputError(
                    f"gp_options {extra} apply only to error_bound 'chowdhury' (a GP posterior); error_bound "
                    f"{self.error_bound!r} uses the unit-amplitude kernel with the given lengthscale only")
        self._check_known_parts()
        if self.refine is not None:
            from robust_imdp.synthesis.refine import RefineOptions

            object.__setattr__(self, "refine", RefineOptions.from_dict(self.refine))
            if self.error_bound == "chowdhury" or self.iid_noise:
                # new cells need bounds of the same statement: the GP route folds the error in at
                # the end, and iid_noise's union bound counts the cells of the grid
                raise InvalidInputError(
                    "[refine] needs error_bound 'optimal' or 'ridge' without iid_noise (the bounds of new cells "
                    f"must hold on the same event); got error_bound={self.error_bound!r}, iid_noise={self.iid_noise!r}")

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
        if self.error_bound == "chowdhury":
            nonlinear = [name for name, m in zip(self.mode_names, maps) if not _is_affine(m)]
            if nonlinear:
                raise InvalidInputError(
                    f"error_bound 'chowdhury' (the GP route, bounds.bound_image) bounds f_u + mu jointly for an affine "
                    f"f_u = A x + b only; modes {nonlinear} have a nonlinear known part f: use error_bound 'optimal' "
                    "or 'ridge'")
            if not settings.uniform:
                raise InvalidInputError(
                    "error_bound 'chowdhury' (the GP route) takes one rkhs_bound, one lengthscale and no known "
                    "components; per-mode or per-component values need error_bound 'optimal' or 'ridge'; got "
                    f"rkhs_bound={self.rkhs_bound!r}, lengthscale={self.gp_options.get('lengthscale')!r}")

    def replace(self, **changes) -> "Problem":
        """A copy with some attributes changed (e.g. ``formula=...``)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        unknown = set(changes) - set(values)
        if unknown:
            raise InvalidInputError(f"Problem has no attributes {sorted(unknown)}")
        values.update(changes)
        return Problem(**values)

    @classmethod
    def from_arrays(cls, x, u, x_next, *, lower, upper, cell_size, regions, formula, threshold, modes, noise,
                    rkhs_bound, horizon=None, lengthscale=None, names=None, **options) -> "Problem":
        """A Problem from numpy arrays: the Python counterpart of a problem file.

        Parameters
        ----------
        x, x_next : (m, n) float arrays
            The sampled states and their successors (``[data]``).
        u : (m,) array of mode names (str), or of mode indices into ``modes``
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
        noise : noise model (``TruncatedGaussianNoise``, ``GaussianNoise``, ``UniformNoise``)
        rkhs_bound : float, list of n floats or dict mode -> either
            The assumption B (``[gp].rkhs_bound``), per mode and component where given so; 0 marks a
            known component (``robust_imdp.bounds.assumptions``).
        horizon : int or None
        lengthscale : float, (n,) float array (per input dimension), per-component list or dict per mode
            The kernel lengthscale (``[gp].lengthscale``, kept in ``gp_options``).
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
        h = np.asarray(cell_size, dtype=float)
        h = np.full(n, float(h)) if h.ndim == 0 else h.reshape(-1)
        if not isinstance(modes, dict) or not modes:
            raise InvalidInputError(f"modes must be a dict name -> (A, b) or AffineMap, with at least one mode; "
                                    f"got {modes!r}")
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
        unknown = sorted(set(options) - {f.name for f in fields(cls)})
        if unknown:
            raise InvalidInputError(f"Problem.from_arrays got unknown options {unknown}; the other arguments "
                                    f"are attributes of Problem: {[f.name for f in fields(cls)]}")
        gp_options = dict(options.pop("gp_options", None) or {})
        if lengthscale is not None:
            gp_options["lengthscale"] = lengthscale
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
        return (f"Problem({lo.size}-D, {int(np.prod(shape))} cells ({' x '.join(map(str, shape))}); {box}\n"
                f"  formula {self.formula!r}, threshold {float(self.threshold):g}"
                f"{'' if self.horizon is None else f', horizon {self.horizon}'}; regions {list(self.regions)}\n"
                f"  modes {list(self.mode_names)}, {m} samples, {type(self.noise).__name__}, "
                f"rkhs_bound {_setting_text(self.rkhs_bound)}, error_bound {self.error_bound!r})")


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


@dataclass(frozen=True, eq=False)
class Result:
    """Output of :func:`synthesize_from_data`.

    Attributes
    ----------
    problem : Problem
    partition : geometry.Partition
    abstraction : abstraction.Abstraction
    dfa : dfa.DFA
    synthesis : synthesis.SynthesisResult
        ``strategy (n_cells, S)``, ``p_low``, ``p_up``, ``p_up_star``, ``error``, ``classes``.
    class_names : (n_cells,) str array
        ``"yes"`` / ``"no"`` / ``"maybe"`` per cell.
    timings : dict str -> float
        Seconds per stage (``specify``, ``partition``, ``learn``, ``bound``, ``abstract``,
        ``synthesize``, ``total``; ``load_abstraction`` when the cache was used).
    parameters : dict
        The settings that produced the result (JSON-able).
    from_cache : bool
        Whether the abstraction was reused.
    advice : dict
        Which lever (finer grid, more data, smaller B) would move most of X into Q_yes, estimated
        after the solve (``advice.Advice.to_dict()``; empty when not estimated, and after
        :func:`resynthesize`).
    diagnostics : dict
        Why cells are undecided (JSON-able): the stated confidence, the error radius ``eps``
        per mode and output (median, max, against the cell half-width), the mean number of
        successors per IMDP row and the assumption check (data-implied minimum RKHS norms).
    """

    problem: Problem
    partition: Any
    abstraction: Any
    dfa: Any
    synthesis: Any
    class_names: np.ndarray
    timings: dict
    parameters: dict
    from_cache: bool = False
    diagnostics: dict = field(default_factory=dict)
    advice: dict = field(default_factory=dict)

    # Convenience views used by io.result_to_dict and plotting.
    @property
    def mode_names(self) -> tuple:
        return tuple(self.problem.mode_names)

    @property
    def space_lower(self) -> np.ndarray:
        return np.asarray(self.problem.space_lower, float)

    @property
    def space_upper(self) -> np.ndarray:
        return np.asarray(self.problem.space_upper, float)

    @property
    def formula(self) -> str:
        return self.problem.formula

    @property
    def threshold(self) -> float:
        return float(self.problem.threshold)

    @property
    def horizon(self):
        return self.problem.horizon

    # Shortcuts to the synthesis and partition arrays (per cell, in the cells' index order).
    @property
    def p_low(self) -> np.ndarray:
        """(n_cells,) guaranteed lower bound of P(formula) under the strategy (``synthesis.p_low``)."""
        return self.synthesis.p_low

    @property
    def p_up(self) -> np.ndarray:
        """(n_cells,) upper bound of P(formula) under the strategy (``synthesis.p_up``)."""
        return self.synthesis.p_up

    @property
    def p_up_star(self) -> np.ndarray:
        """(n_cells,) upper bound of P(formula) over all strategies (``synthesis.p_up_star``)."""
        return self.synthesis.p_up_star

    @property
    def error(self) -> np.ndarray:
        """(n_cells,) ``p_up_star - p_low`` rounded up (``synthesis.error``)."""
        return self.synthesis.error

    @property
    def strategy(self) -> np.ndarray:
        """(n_cells, S) mode indices into ``mode_names`` ((k, n_cells, S) for a k-step horizon)."""
        return self.synthesis.strategy

    @property
    def classes(self) -> np.ndarray:
        """(n_cells,) ``"yes"`` / ``"no"`` / ``"maybe"`` (the same array as ``class_names``)."""
        return self.class_names

    @property
    def n_cells(self) -> int:
        return int(self.partition.n_cells)

    @property
    def cells_lower(self) -> np.ndarray:
        """(n_cells, n) lower corners of the cells (``partition.cells_lower``)."""
        return self.partition.cells_lower

    @property
    def cells_upper(self) -> np.ndarray:
        """(n_cells, n) upper corners of the cells (``partition.cells_upper``)."""
        return self.partition.cells_upper

    @property
    def dim_names(self):
        """The dimension names (``[space].names``), or None."""
        return getattr(self.problem, "dim_names", None)

    def __repr__(self) -> str:  # a few lines: the dataclass default prints every array (tens of KB)
        c = self.counts()
        return (f"Result({len(self.class_names)} cells: Q_yes {c['yes']}, Q_no {c['no']}, Q_? {c['maybe']}; "
                f"formula {self.formula!r}, threshold {self.threshold:g}\n"
                f"  mean p_low {float(np.mean(self.synthesis.p_low)):.4f}, mean error "
                f"{float(np.mean(self.synthesis.error)):.4f}; modes {list(self.mode_names)}; abstraction "
                f"{'reused from cache' if self.from_cache else 'built'}\n"
                f"  arrays: p_low, p_up, p_up_star, error, classes, strategy; summary() for the details)")

    def counts(self) -> dict:
        """Number of cells per class: ``{"yes": .., "no": .., "maybe": ..}``."""
        return {c: int(np.sum(self.class_names == c)) for c in CLASS_NAMES}

    def controller(self):
        """The refined switching controller (``controller.Controller``)."""
        return self.synthesis.controller(self.partition, self.mode_names)

    @property
    def no_strategy_can(self) -> np.ndarray:
        """(n_cells,) bool: ``p_up_star < threshold``: no controller at all meets the threshold."""
        return np.asarray(self.synthesis.p_up_star) < self.threshold

    def _no_line(self) -> str:
        """Q_no split into cells where no controller can meet the threshold (``p_up_star <
        threshold``) and cells that are "no" under this controller only."""
        no = self.class_names == "no"
        cannot = int(np.count_nonzero(no & self.no_strategy_can))
        return (f"Q_no: {cannot} where no controller can meet the threshold (p_up_star < "
                f"{self.threshold:g}), {int(np.count_nonzero(no)) - cannot} under this controller only")

    def summary(self) -> str:
        """Class counts (Q_no split by whether any controller could do better), mean error and
        stage times as text."""
        c = self.counts()
        n = len(self.class_names)
        times = ", ".join(f"{k} {v:.2f} s" for k, v in self.timings.items())
        lines = [
            f"formula {self.formula!r}, threshold {self.threshold:g}"
            + (f", horizon {self.horizon}" if self.horizon is not None else ""),
            f"cells: {n}  Q_yes {c['yes']}  Q_no {c['no']}  Q_? {c['maybe']}",
            self._no_line(),
            f"mean p_low {np.mean(self.synthesis.p_low):.4f}  mean error "
            f"{np.mean(self.synthesis.error):.4f}  (abstraction "
            f"{'reused from cache' if self.from_cache else 'built'})",
        ]
        why = diagnostics_line(self.diagnostics)
        if why:
            lines.append(why)
        if self.advice:
            from robust_imdp.synthesis.advice import advice_line

            lines.append(advice_line(self.advice))
        lines.append(f"stage times: {times}")
        return "\n".join(lines)


# --------------------------------------------------------------------------- helpers
class _Log:
    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.timings: dict[str, float] = {}
        self.t0 = time.perf_counter()

    def stage(self, name: str):
        log = self

        class _Stage:
            def __enter__(self):
                self.t = time.perf_counter()
                if log.enabled:
                    print(f"[robust-imdp] {name} ...", file=sys.stderr, flush=True)
                return self

            def __exit__(self, kind, exc, tb):
                dt = time.perf_counter() - self.t
                log.timings[name] = log.timings.get(name, 0.0) + dt
                if exc is not None and not isinstance(exc, KeyboardInterrupt) and interrupt_in(exc) is not None:
                    # Ctrl-C seen inside compiled code surfaces as a SystemError caused by it
                    # (errors.interrupt_in): the caller gets the interrupt, as from Python code
                    raise KeyboardInterrupt(f"interrupted during the {name} stage") from exc
                return False

        return _Stage()

    def info(self, text: str) -> None:
        if self.enabled:
            print(f"[robust-imdp]   {text}", file=sys.stderr, flush=True)

    def progress(self, what: str, done: int, total: int, t0: float, every: float = 2.0, resumed: int = 0) -> None:
        """A progress line (count, elapsed time, estimate of the rest), at most every ``every`` s.

        ``resumed`` of the ``done`` units were loaded from the cache, not computed since ``t0``:
        the estimate divides the units left by the rate of this process, ``(done - resumed) / elapsed``.
        """
        now = time.perf_counter()
        if not self.enabled or (done < total and now - getattr(self, "_last", 0.0) < every):
            return
        self._last = now
        el = now - t0
        rest = ""
        if 0 < done - resumed and done < total:
            rest = f", about {el / (done - resumed) * (total - done):.0f} s left"
        print(f"[robust-imdp]   {what}: {done}/{total} ({100 * done / max(total, 1):.0f} %), {el:.1f} s{rest}",
              file=sys.stderr, flush=True)


class _Run:
    """Scheduler options of one run; the scheduler is started on first use and closed at the end."""

    def __init__(self, client=None, workers=None, scheduler=None, chunk_cells=None, check_resources=True):
        self.client, self.workers, self.scheduler_address = client, workers, scheduler
        self.chunk_cells = chunk_cells
        self.check_resources = check_resources
        self.sched = None

    def scheduler(self, log: "_Log"):
        from robust_imdp.pipeline.parallel import open_scheduler

        if self.sched is None:
            self.sched = open_scheduler(workers=self.workers, scheduler=self.scheduler_address, client=self.client)
            log.info(f"scheduler: {self.sched.description}")
        return self.sched

    def close(self) -> None:
        if self.sched is not None:
            self.sched.close()
            self.sched = None


def _fingerprint(h, obj) -> None:
    """Feed a canonical description of ``obj`` into the hash ``h`` (arrays by value)."""
    if isinstance(obj, np.ndarray) or isinstance(obj, np.generic):
        a = np.ascontiguousarray(obj)
        h.update(f"nd{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    elif isinstance(obj, dict):
        h.update(b"{")
        for k in sorted(obj, key=str):
            _fingerprint(h, str(k))
            _fingerprint(h, obj[k])
        h.update(b"}")
    elif isinstance(obj, (list, tuple)):
        h.update(f"[{len(obj)}".encode())
        for v in obj:
            _fingerprint(h, v)
        h.update(b"]")
    elif obj is None or isinstance(obj, (bool, int, float, str)):
        h.update(f"{type(obj).__name__}:{obj!r};".encode())
    elif is_dataclass(obj):
        h.update(type(obj).__qualname__.encode())
        _fingerprint(h, {f.name: getattr(obj, f.name) for f in fields(obj)})
    elif hasattr(obj, "__dict__"):
        h.update(type(obj).__qualname__.encode())
        _fingerprint(h, {k: v for k, v in vars(obj).items() if not k.startswith("_")})
    else:
        h.update(repr(obj).encode())


def bounds_key(problem: Problem) -> str:
    """Hash of everything the learned cell bounds depend on (data, modes, noise, grid, GP)."""
    import robust_imdp

    h = hashlib.sha256()
    d = problem.data
    _fingerprint(h, [
        robust_imdp.__version__, problem.space_lower, problem.space_upper, problem.cell_size,
        {k: [(np.asarray(lo, float), np.asarray(up, float)) for lo, up in v]
         for k, v in problem.regions.items()},
        np.asarray(d.x, float), np.asarray(d.u), np.asarray(d.x_next, float),
        list(problem.mode_names), [_map_key(m) for m in problem.maps],
        problem.noise, _setting_value(problem.rkhs_bound), problem.gp_options, float(problem.bound_tol),
        int(problem.bound_max_boxes), problem.error_bound, _setting_value(problem.misspecification),
        bool(problem.iid_noise), float(problem.confidence) if problem.error_bound != "chowdhury" else None,
        problem.local_points,
    ])
    return h.hexdigest()[:20]


def abstraction_key(problem: Problem) -> str:
    """Hash of everything the abstraction depends on (not the formula, threshold, horizon)."""
    h = hashlib.sha256(bounds_key(problem).encode())
    _fingerprint(h, [None if problem.eta is None else np.asarray(problem.eta, float),
                     problem.eps_rule, problem.combine, problem.guarantee,
                     float(problem.confidence)])
    return h.hexdigest()[:20]


# --------------------------------------------------------------------------- cache entries
# Every file of the cache is an entry ``NAME`` with a checksum file ``NAME.sha256`` (sha256 of
# the bytes, their count, and NAME). An entry is written under a temporary name, flushed to disk
# (fsync) and renamed, so a crash leaves either the old entry, no entry, or an entry whose
# checksum does not match; an entry that does not match its checksum, or cannot be read, gets
# one warning line and is computed again.
CHECKSUM_SUFFIX = ".sha256"


def _checksum_file(path: Path) -> Path:
    return path.with_name(path.name + CHECKSUM_SUFFIX)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _fsync(path: Path, directory: bool = False) -> None:
    """Flush ``path`` (a file, or a directory's entries) to disk."""
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    except OSError:  # pragma: no cover - a directory that cannot be opened (non-POSIX)
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover - file systems without fsync of directories
        pass
    finally:
        os.close(fd)


def write_cache_entry(path, write) -> None:
    """Write the cache entry ``path`` with ``write(tmp_path)`` and its checksum file.

    ``tmp_path`` is a hidden file in the same directory with the same suffix (``np.savez``
    appends ``.npz`` to names without it). It is flushed to disk before it is renamed, and
    the checksum file is written the same way after it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.part{path.suffix}")
    side = _checksum_file(path)
    side_tmp = side.with_name(f".{side.name}.part")
    try:
        write(tmp)
        _fsync(tmp)
        side_tmp.write_text(f"{_sha256(tmp)} {tmp.stat().st_size} {path.name}\n")
        _fsync(side_tmp)
        os.replace(tmp, path)
        os.replace(side_tmp, side)
        _fsync(path.parent, directory=True)
    finally:
        for t in (tmp, side_tmp):
            t.unlink(missing_ok=True)


def cache_entry_problem(path) -> str | None:
    """Why the cache entry ``path`` cannot be trusted (no checksum, size or digest mismatch), or None."""
    path = Path(path)
    side = _checksum_file(path)
    try:
        fields_ = side.read_text(encoding="ascii").split()
    except (OSError, UnicodeDecodeError):
        return f"has no readable checksum file {side.name}"
    if len(fields_) != 3 or fields_[2] != path.name or not fields_[1].isdigit():
        return f"has a checksum file {side.name} for another entry or in another form"
    size = path.stat().st_size
    if size != int(fields_[1]):
        return f"is {size} bytes, its checksum file says {fields_[1]} (truncated or changed)"
    if _sha256(path) != fields_[0]:
        return "does not match its sha256 checksum (changed or damaged)"
    return None


def read_cache_entry(path, read):
    """``read(path)`` when the cache entry exists and matches its checksum, else None.

    A damaged entry (checksum mismatch, or ``read`` fails on it) gets one warning line and is
    deleted, so that the caller computes it again.
    """
    from robust_imdp.errors import RobustImdpWarning

    path = Path(path)
    if not path.exists():
        return None
    why = cache_entry_problem(path)
    if why is None:
        try:
            return read(path)
        except Exception as exc:  # a damaged or foreign file: any reader error means "recompute"
            if interrupt_in(exc) is not None:
                raise
            why = f"cannot be read ({type(exc).__name__}: {exc})"
    warnings.warn(f"cache entry {path} {why}; computing it again", RobustImdpWarning, stacklevel=2)
    for f in (path, _checksum_file(path)):
        f.unlink(missing_ok=True)
    return None


def _write_json_entry(path: Path, doc) -> None:
    from robust_imdp.jsonable import jsonable as _jsonable

    write_cache_entry(path, lambda tmp: tmp.write_text(json.dumps(_jsonable(doc)), encoding="utf-8"))


def _read_json(path: Path):
    return json.loads(path.read_text(encoding="utf-8"))


_EB_FIELDS = ("rkhs_bound", "sub_gaussian", "regulariser", "info_gain", "n_samples")


def _save_bounds(path: Path, cell_bounds, error_models, diagnostics: dict) -> None:
    from robust_imdp.jsonable import jsonable as _jsonable

    arrays = {k: np.asarray(getattr(cell_bounds, k)) for k in ("image_lower", "image_upper")}
    if cell_bounds.std_upper is not None:
        arrays["std_upper"] = np.asarray(cell_bounds.std_upper)
    if error_models is not None:
        for f in _EB_FIELDS:
            arrays[f"eb_{f}"] = np.array([[getattr(e, f) for e in row] for row in error_models])
    arrays["diagnostics"] = np.array(json.dumps(_jsonable(diagnostics)))
    write_cache_entry(path, lambda tmp: _savez(tmp, arrays))


def _savez(path: Path, arrays: dict) -> None:
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def _load_npz(path: Path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _load_bounds(path: Path):
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.bounds.gp import RKHSErrorBound

    with np.load(path, allow_pickle=False) as z:
        cb = CellBounds(z["image_lower"], z["image_upper"], z["std_upper"] if "std_upper" in z else None)
        cols = {f: z[f"eb_{f}"] for f in _EB_FIELDS} if "eb_rkhs_bound" in z else None
        diagnostics = json.loads(str(z["diagnostics"])) if "diagnostics" in z else {}
    if cols is None:
        return cb, None, diagnostics
    n_modes, n = cols["rkhs_bound"].shape
    models = tuple(tuple(RKHSErrorBound(**{f: (int(cols[f][u, i]) if f == "n_samples"
                                               else float(cols[f][u, i])) for f in _EB_FIELDS})
                         for i in range(n)) for u in range(n_modes))
    return cb, models, diagnostics


def _parameters(problem: Problem, abstraction) -> dict:
    noise = problem.noise
    params = {
        "space": {"lower": problem.space_lower, "upper": problem.space_upper},
        "cell_size": problem.cell_size,
        "n_data": int(np.asarray(problem.data.u).shape[0]),
        "rkhs_bound": _setting_value(problem.rkhs_bound),
        "gp_options": {k: v for k, v in problem.gp_options.items()},
        "bound_tol": float(problem.bound_tol),
        "bound_max_boxes": int(problem.bound_max_boxes),
        "noise": {"kind": type(noise).__name__,
                  **{k: v for k, v in vars(noise).items() if not k.startswith("_")}}
        if hasattr(noise, "__dict__") else repr(noise),
        "eta": None if problem.eta is None else problem.eta,
        "eta_used": getattr(abstraction, "eta", None),
        "eps_rule": problem.eps_rule,
        "combine": problem.combine,
        "guarantee": problem.guarantee,
        "confidence": float(problem.confidence) if problem.guarantee == "confidence" else None,
        "error_bound": problem.error_bound,
        "misspecification": _setting_value(problem.misspecification),
        "iid_noise": bool(problem.iid_noise),
        "local_points": problem.local_points,
        "abstraction_key": abstraction_key(problem),
        **({} if all(_is_affine(m) for m in problem.maps) else
           {"known_parts": {name: (None if _is_affine(m) else list(m.expressions))
                            for name, m in zip(problem.mode_names, problem.maps)}}),
        "refine": None if problem.refine is None else problem.refine.to_dict(),
    }
    from robust_imdp.jsonable import jsonable as _jsonable

    return _jsonable(params)


def _region_objects(problem: Problem):
    from robust_imdp.models.geometry import Box, Region

    return [Region(name, [Box(lo, up) for lo, up in boxes]) for name, boxes in problem.regions.items()]


def _warn_overlaps(problem: Problem, dfa) -> None:
    """Warn when two regions the formula names overlap: the cells there carry both labels.

    Regions the formula does not name are left alone (the paper's case study defines ``d2``
    equal to ``des`` on purpose). Boxes that share only a face do not overlap.
    """
    import warnings

    from robust_imdp.errors import RegionOverlapWarning
    from robust_imdp.models.geometry import region_overlaps

    used = [r for r in _region_objects(problem) if r.name in dfa.atoms]
    found = region_overlaps(used)
    pairs = list(dict.fromkeys((a, b) for a, b, _ in found))
    for a, b in pairs:
        boxes = [box for x, y, box in found if (x, y) == (a, b)]
        where = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in zip(boxes[0].lower, boxes[0].upper))
        more = f" (and {len(boxes) - 1} more boxes)" if len(boxes) > 1 else ""
        warnings.warn(
            f"regions {a!r} and {b!r} overlap in the box {where}{more}: cells there are labelled with both, "
            f"and the formula {problem.formula!r} reads both labels there; check the regions' boxes "
            "([[regions.NAME]] lower / upper)", RegionOverlapWarning, stacklevel=3)


def _check_atoms(dfa, problem: Problem) -> None:
    unknown = sorted(set(dfa.atoms) - set(problem.regions))
    if unknown:
        raise UnknownAtomError(
            f"formula {problem.formula!r} names regions {unknown} that are not defined; "
            f"known regions: {sorted(problem.regions)}"
        )


def _abstract_task(partition, cell_bounds, noise, *, threads=1, **options):
    """One chunk of the abstraction stage (a module-level function, so that workers can import it)."""
    from robust_imdp.abstraction.rows import abstract_rows

    return abstract_rows(partition, cell_bounds, noise, None, **options)


def _chunked_abstract(problem: Problem, partition, cell_bounds, log: _Log, run: _Run, chunk: int):
    """``abstraction.abstract`` for known image boxes, chunk by chunk on the run's scheduler."""
    from robust_imdp.abstraction.rows import CellBounds, assemble_abstraction

    N = partition.n_cells
    starts = list(range(0, N, chunk))
    sched = run.sched
    opts = {"eta": problem.eta, "eps_rule": problem.eps_rule, "combine": problem.combine}
    args = []
    part = partition if sched is None else sched.share(partition)
    for s0 in starts:
        sl = slice(s0, min(N, s0 + chunk))
        args.append((part, CellBounds(cell_bounds.image_lower[:, sl], cell_bounds.image_upper[:, sl], None),
                     problem.noise))
    pieces = [None] * len(args)
    t0 = time.perf_counter()
    runner = sched if sched is not None else _serial()
    for i, piece in runner.run(_abstract_task, args, opts):
        pieces[i] = piece
        log.progress("abstract", sum(p is not None for p in pieces), len(pieces), t0)
    return assemble_abstraction(partition, pieces)


def _serial():
    from robust_imdp.pipeline.parallel import InProcess

    return InProcess(threads=1)


def _build_abstraction(problem: Problem, partition, log: _Log, cache_dir=None, run: "_Run | None" = None):
    """Learn + bound (or load them from the cache) and abstract.

    Returns (abstraction, diagnostics, image boxes abstracted or None when the GP error enters
    the probabilities).
    """
    from robust_imdp.abstraction.rows import abstract, confidence_cell_bounds

    run = run if run is not None else _Run()

    bounds_file = None
    if cache_dir is not None:
        bounds_file = Path(cache_dir) / f"bounds-{bounds_key(problem)}.npz"
    loaded = None
    if bounds_file is not None and bounds_file.exists():
        with log.stage("load_bounds"):
            loaded = read_cache_entry(bounds_file, _load_bounds)
        if loaded is not None:
            log.info(f"reused learned cell bounds {bounds_file.name}")
    if loaded is not None:
        cell_bounds, error_models, diagnostics = loaded
    else:
        cell_bounds, error_models, diagnostics = _learn_and_bound(problem, partition, log, run, cache_dir)
        if bounds_file is not None:
            _save_bounds(bounds_file, cell_bounds, error_models, diagnostics)
    with log.stage("abstract"):
        if problem.guarantee == "confidence" and error_models is not None:
            # One data-confidence event for all GPs: the error is folded into the image boxes
            # and the abstraction is built as for known dynamics (eps = 0, P_g = 1).
            cell_bounds = confidence_cell_bounds(cell_bounds, error_models, problem.confidence)
            error_models = None
        if error_models is None:
            # at most 4096 cells per task, and at least two tasks per worker on a cluster
            # (the rows do not depend on the chunk size: tests/test_chunks.py)
            from robust_imdp.pipeline.parallel import DaskScheduler

            workers = run.sched.n_workers if isinstance(run.sched, DaskScheduler) else 1
            per_task = 4096 if workers <= 1 else min(4096, -(-partition.n_cells // (2 * workers)))
            abstraction = _chunked_abstract(problem, partition, cell_bounds, log, run,
                                            _chunk_cells(run, partition.n_cells, per_task))
        else:
            abstraction = abstract(partition, cell_bounds, problem.noise, error_models,
                                   eta=problem.eta, eps_rule=problem.eps_rule, combine=problem.combine)
    diagnostics = dict(diagnostics)
    diagnostics["successors_per_row"] = float(np.mean(abstraction.nnz_per_row))
    log.info(f"IMDP: {abstraction.imdp.n_states} states, {int(np.sum(abstraction.nnz_per_row))} "
             f"listed transitions ({diagnostics['successors_per_row']:.1f} per row)")
    return abstraction, diagnostics, (cell_bounds if error_models is None else None)


def _residual_data(problem: Problem):
    """Per mode: inputs, residuals ``x_next - f_u(x)`` and the samples' rows in the data set."""
    u = np.asarray(problem.data.u)
    out = []
    for m in range(len(problem.mode_names)):
        x, xn = problem.data.by_mode(m)
        out.append((x, xn - problem.maps[m](x), np.flatnonzero(u == m)))
    return out


def _one_setting(problem: Problem) -> bool:
    """Affine known parts and one assumption for every mode and component: the original path, unchanged."""
    return all(_is_affine(m) for m in problem.maps) and _settings(problem).uniform


def _affine_part(problem: Problem, u: int):
    """(A, b) of mode ``u``'s affine known part, or zeros for a nonlinear one (its range is added to g's)."""
    m = problem.maps[u]
    if _is_affine(m):
        return m.A, m.b
    n = int(np.size(problem.space_lower))
    return np.zeros((n, n)), np.zeros(n)


def _noise_allowance(problem: Problem, noise_bound) -> np.ndarray:
    """(n_modes, n) data-noise bound of the certificate per mode: the noise bound plus the residuals' rounding.

    Eq. W (docs/rkhs_bounds.md, section 1) needs ``|h(x_i) - y_i| <= dbar + tau`` for the residuals
    it is given. For a nonlinear known part the computed residual ``fl(x_next - fl(f(x)))`` is within
    ``r_i`` of the exact ``y_i`` (``KnownDynamics.residuals``, ``AffineMap.residuals`` for an affine
    part), so the certificate and the assumption check take ``dbar + max_i r_i`` per component,
    rounded up.
    """
    M, n = len(problem.mode_names), int(np.size(problem.space_lower))
    out = np.array(np.broadcast_to(np.asarray(noise_bound, float), (M, n)))
    for u, m in enumerate(problem.maps):
        x, xn = problem.data.by_mode(u)
        if x.shape[0]:
            rb = m.residuals(x, xn).bound.max(axis=0)
            out[u] = np.nextafter(out[u] + rb, np.inf)
    return out


def _shared_allowance(problem: Problem, noise_bound) -> np.ndarray:
    """(n,) the largest data-noise allowance over the modes (the one-setting path's single noise bound)."""
    return np.max(_noise_allowance(problem, noise_bound), axis=0)


def _known_ranges(problem: Problem, cells_lower, cells_upper) -> list:
    """Per mode: None (affine) or the certified range of the nonlinear known part over the cells
    (``KnownDynamics.image_bounds``; raises ``ExpressionDomainError`` where f is undefined)."""
    return [None if _is_affine(m) else m.image_bounds(cells_lower, cells_upper) for m in problem.maps]


def _add_known_range(lower, upper, ranges) -> None:
    """``g``'s certified range plus ``f``'s, in place: the image of ``f_u + g_u`` over each cell is in the
    Minkowski sum of the two ranges; the sum is rounded outward (``assumptions.add_ranges``)."""
    from robust_imdp.bounds.assumptions import add_ranges

    lower[...], upper[...] = add_ranges(lower, upper, ranges.lower, ranges.upper)


def _base_settings(problem: Problem, settings=None) -> dict:
    """The bound stage's problem-wide settings: the problem's own values with one assumption (as before);
    otherwise stand-ins (the largest B, the first lengthscale) that every mode's groups override."""
    if _settings(problem).uniform:
        return {"lengthscale": problem.gp_options.get("lengthscale", 1.0), "rkhs_bound": problem.rkhs_bound,
                "misspecification": problem.misspecification}
    st = _settings(problem) if settings is None else settings
    B = st.rkhs_bound
    return {"lengthscale": st.lengthscale[0, 0], "rkhs_bound": float(B.max()) if np.any(B > 0) else 1.0,
            "misspecification": float(st.misspecification.max())}


def _mode_extras(problem: Problem, data, partition, allowance, local) -> list:
    """Per mode: None (the original path) or the dict of ``assumptions.bound_mode_chunk``."""
    if _one_setting(problem):
        return [None] * len(problem.mode_names)
    from robust_imdp.bounds.rkhs import local_lambda

    st = _settings(problem)
    out = []
    for u in range(len(problem.mode_names)):
        extra = {"noise_bound": np.asarray(allowance, float)}
        if not st.uniform:
            extra["groups"] = st.groups(u)
            if problem.error_bound == "ridge" and local[u] is not None:
                # one ridge lambda per group, for all chunks (as _local_settings does per mode)
                extra["local_lambda"] = [
                    None if B == 0 else local_lambda(data[u][0], partition.cells_lower, partition.cells_upper,
                                                     lengthscale=L, rkhs_bound=B,
                                                     noise_l1=float(np.max(allowance[u][idx])) + tau, k=local[u][0])
                    for idx, B, L, tau in extra["groups"]]
        out.append(extra)
    return out


def _extra(mode) -> tuple:
    """The task's optional last argument: nothing on the original path (the tasks' arguments as before)."""
    return () if mode is None else (mode,)


def _known_gap(problem: Problem, partition, ranges, n_cells: int = 8) -> list:
    """Gap of the certified range of each nonlinear known part to the range it attains (sampling + IPOPT)
    on ``n_cells`` evenly spaced cells (``KnownDynamics.achieved_range``, ``gap_to``): a diagnostic."""
    rows = []
    N = partition.n_cells
    pick = np.unique(np.linspace(0, N - 1, min(n_cells, N)).round().astype(np.int64))
    lo, up = partition.cells_lower[pick], partition.cells_upper[pick]
    width = np.max(up - lo, axis=1)
    for u, (m, r) in enumerate(zip(problem.maps, ranges)):
        if r is None:
            continue
        from robust_imdp.models.known import ImageBounds

        sub = ImageBounds(r.lower[pick], r.upper[pick], r.leaves[pick])
        gap = m.achieved_range(lo, up).gap_to(sub)
        for i in range(gap.shape[1]):
            rows.append({"mode": problem.mode_names[u], "component": i + 1, "expression": m.expressions[i],
                         "cells": int(pick.size), "gap_max": float(gap[:, i].max()),
                         "gap_over_cell_width_max": float(np.max(gap[:, i] / width))})
    return rows


def _failure_budget(problem: Problem):
    """Split ``1 - confidence`` between the data-noise bound and the iid event (route 'optimal'/'ridge')."""
    fail = 1.0 - float(problem.confidence)
    bounded = bool(getattr(problem.noise, "bounded", False))
    if bounded:
        return 0.0, (fail if problem.iid_noise else 0.0)
    return (fail / 2, fail / 2) if problem.iid_noise else (fail, 0.0)


def check_key(problem: Problem) -> str:
    """Hash of everything the assumption check depends on: the data and the assumption.

    The data, the modes' known parts (the residuals), the noise model (its bound), the
    lengthscale, ``rkhs_bound`` and ``misspecification``; not the grid, regions or formula.
    """
    import robust_imdp

    h = hashlib.sha256(b"assumption-check")
    d = problem.data
    _fingerprint(h, [
        robust_imdp.__version__, np.asarray(d.x, float), np.asarray(d.u), np.asarray(d.x_next, float),
        list(problem.mode_names), [_map_key(m) for m in problem.maps],
        problem.noise, problem.gp_options.get("lengthscale", 1.0), _setting_value(problem.rkhs_bound),
        _setting_value(problem.misspecification), CHECK_DELTA,
    ])
    return h.hexdigest()[:20]


def _read_checks(path: Path):
    """The NormChecks and noise bound of a saved assumption check (ValueError/KeyError if malformed)."""
    from robust_imdp.bounds.rkhs import NormCheck

    doc = _read_json(path)
    checks = tuple(NormCheck(**c) for c in doc["checks"])
    if not checks:
        raise ValueError("no checks")
    return checks, np.asarray(doc["noise_bound"], float)


def _check_assumption(problem: Problem, data, log: _Log, cache_dir=None):
    from robust_imdp.bounds.rkhs import check_assumption, noise_bound_at_confidence

    m_total = sum(x.shape[0] for x, _, _ in data)
    nb, _ = noise_bound_at_confidence(problem.noise, m_total, CHECK_DELTA)
    # The check only passes or raises, and its result depends on the data and the assumption only
    # (check_key): a passed check is saved and reused by every run on the same data and assumption.
    check_file = None if cache_dir is None else Path(cache_dir) / f"check-{check_key(problem)}.json"
    cached = None if check_file is None else read_cache_entry(check_file, _read_checks)
    if cached is not None:
        checks, nb = cached
    else:
        with log.stage("check"):
            if _one_setting(problem):
                checks = check_assumption([(x, y) for x, y, _ in data],
                                          lengthscale=problem.gp_options.get("lengthscale", 1.0),
                                          rkhs_bound=problem.rkhs_bound, noise_bound=_shared_allowance(problem, nb),
                                          misspecification=problem.misspecification, mode_names=problem.mode_names,
                                          sample_index=[idx for _, _, idx in data])
            else:  # per mode and component, with the residuals' rounding in the noise allowance
                from robust_imdp.bounds.assumptions import check_modes

                checks = check_modes([(x, y) for x, y, _ in data], _settings(problem), _noise_allowance(problem, nb),
                                     mode_names=problem.mode_names, sample_index=[idx for _, _, idx in data])
        if check_file is not None:
            _write_json_entry(check_file, {"checks": [asdict(c) for c in checks], "noise_bound": nb})
    worst = max(checks, key=lambda c: c.minimum)
    log.info(f"assumption check{' (reused from the cache)' if cached is not None else ''}: the data need RKHS "
             f"norm >= {worst.minimum:.4g} (mode {problem.mode_names[worst.mode]}, component {worst.output + 1}); "
             f"rkhs_bound = {_setting_text(problem.rkhs_bound)}")
    return checks, nb


def _fitted(problem: Problem, data):
    """The data-fitted function of every mode (``advice.fit_modes``): known part plus a kernel-ridge fit."""
    from robust_imdp.synthesis.advice import fit_modes

    sigma = np.asarray(problem.noise.sub_gaussian_parameter(), float)
    if not _settings(problem).uniform:
        from robust_imdp.bounds.assumptions import fit_components

        return fit_components([(x, y) for x, y, _ in data], problem.maps, _settings(problem), sigma)
    # ridge parameter sigma^2 / B^2: the GP posterior mean with prior variance B^2 (kept >= 1e-6)
    lam = np.maximum(sigma / float(problem.rkhs_bound), 1e-3) ** 2
    return fit_modes([(x, y) for x, y, _ in data], problem.maps, problem.gp_options.get("lengthscale", 1.0), lam)


def _diagnostics(problem: Problem, partition, cell_bounds, data, checks, check_noise, confidence: float,
                 statement: str) -> dict:
    from robust_imdp.synthesis.advice import excess_radius

    half = 0.5 * np.asarray(problem.cell_size, float)
    # The error radius is the excess of each learned image box over the range of the data-fitted
    # function over the cell (advice.excess_radius): the same computation for every mode and
    # component, from the boxes and the fit alone (the bound stage's internal vertex radius depends
    # on which vertex problems its pruning solved, so on the component's position).
    flo, fhi = _fitted(problem, data).grid_ranges(partition.breakpoints)
    eps = excess_radius(np.asarray(cell_bounds.image_lower), np.asarray(cell_bounds.image_upper), flo, fhi)
    rows = []
    for u, name in enumerate(problem.mode_names):
        for i in range(eps.shape[2]):
            e = eps[u, :, i]
            rows.append({"mode": name, "component": i + 1, "median": float(np.median(e)), "max": float(np.max(e)),
                         "median_over_half_cell": float(np.median(e) / half[i])})
    return {
        "error_bound": problem.error_bound,
        "confidence": float(confidence),
        "statement": statement,
        "cell_half_width": half.tolist(),
        "eps": rows,
        "assumption": {
            **_assumption_diagnostics(problem, len(half)),
            "check_noise_bound": np.asarray(check_noise, float).tolist(),
            "min_norm": [{"mode": problem.mode_names[c.mode], "component": c.output + 1, "minimum": c.minimum,
                          "n_points": c.n_points} for c in checks],
        },
    }


def _assumption_diagnostics(problem: Problem, n: int) -> dict:
    """rkhs_bound, lengthscale, misspecification of the diagnostics (as before with one setting); per mode and
    component in ``per_component`` otherwise, with the largest B and tau and the smallest lengthscales on top."""
    st = _settings(problem)
    if st.uniform:
        return {"rkhs_bound": float(problem.rkhs_bound),
                "lengthscale": np.broadcast_to(np.asarray(problem.gp_options.get("lengthscale", 1.0), float),
                                               (n,)).tolist(),
                "misspecification": float(problem.misspecification)}
    return {"rkhs_bound": float(st.rkhs_bound.max()), "lengthscale": st.lengthscale.min(axis=(0, 1)).tolist(),
            "misspecification": float(st.misspecification.max()), "per_component": st.to_rows(problem.mode_names)}


def diagnostics_line(diag: dict) -> str:
    """One line saying why cells may be undecided (error radius, successors, assumption margin)."""
    if not diag or "eps" not in diag:
        return ""
    med = max(r["median"] for r in diag["eps"])
    mx = max(r["max"] for r in diag["eps"])
    half = min(diag["cell_half_width"])
    text = (f"error radius eps: median {med:.3g}, max {mx:.3g} (cell half-width {half:.3g})")
    if "successors_per_row" in diag:
        text += f"; {diag['successors_per_row']:.1f} successors per row"
    mins = [r["minimum"] for r in diag["assumption"]["min_norm"]]
    if mins:
        text += f"; data need ||g|| >= {max(mins):.3g} of B = {diag['assumption']['rkhs_bound']:g}"
    conf = diag.get("confidence")
    if conf is not None:
        text += "; holds with probability 1" if conf >= 1.0 else f"; holds with confidence {conf:g} over the data"
    return text


def _chunk_cells(run: "_Run", n_cells: int, default: int) -> int:
    """Cells per task: a multiple of rkhs.CELL_BLOCK (so the result does not depend on it)."""
    from robust_imdp.bounds.rkhs import CELL_BLOCK

    c = default if run.chunk_cells is None else int(run.chunk_cells)
    if c < 1:
        raise InvalidInputError(f"chunk_cells must be a positive integer; got {run.chunk_cells!r}")
    return max(CELL_BLOCK, -(-min(c, max(n_cells, 1)) // CELL_BLOCK) * CELL_BLOCK)


def _bound_task(X, Y, A, b, lower, upper, local, mode=None, *, threads=1, **settings):
    """One chunk of the bound stage; ``local`` = (points, ridge lambda) of the mode or None; ``mode``: None
    (the problem-wide settings) or the mode's own (``assumptions.bound_mode_chunk``)."""
    return _bound_work(X, Y, A, b, lower, upper, local, mode, threads=threads, **settings)


def _bound_work(X, Y, A, b, lower, upper, local, mode=None, *, threads=1, **settings):
    """The work of :func:`_bound_task` and :func:`_pilot_task`."""
    from robust_imdp.bounds.rkhs import bound_chunk

    if mode is not None:
        from robust_imdp.bounds.assumptions import bound_mode_chunk

        t0 = time.perf_counter()
        out = bound_mode_chunk(X, Y, A, b, lower, upper, local, mode, threads=threads, **settings)
        out["seconds"] = time.perf_counter() - t0
        return out

    if local is not None:
        settings = dict(settings, local_points=local[0], local_lambda=local[1])
    return bound_chunk(X, Y, A, b, lower, upper, threads=threads, **settings)


def _local_settings(problem: Problem, data, partition, noise_bound):
    """Per mode: None (all points) or (points, ridge lambda) of the local weights."""
    from robust_imdp.bounds.rkhs import local_lambda

    out = []
    for x, _, _ in data:
        k = problem.local_points
        if k is None:
            k = None if x.shape[0] <= LOCAL_AUTO else LOCAL_DEFAULT
        if k is None or k >= x.shape[0]:
            out.append(None)
            continue
        lam = None
        if problem.error_bound == "ridge":
            base = _base_settings(problem)
            lam = local_lambda(x, partition.cells_lower, partition.cells_upper,
                               lengthscale=base["lengthscale"], rkhs_bound=base["rkhs_bound"],
                               noise_l1=float(np.max(noise_bound)) + float(base["misspecification"]), k=k)
        out.append((int(k), lam))
    return out


def _check_part(part: dict, k: int, n: int) -> dict:
    """A saved bound chunk, checked to hold ``k`` cells x ``n`` outputs (else ValueError: computed again)."""
    for key in ("lower", "upper", "eps", "support"):
        if key not in part or np.shape(part[key]) != (k, n):
            raise ValueError(f"{key} must have shape ({k}, {n}); got "
                             f"{np.shape(part[key]) if key in part else 'no such array'}")
    if "n_unconverged" not in part:
        raise ValueError("n_unconverged is missing")
    return part


def _learn_and_bound(problem: Problem, partition, log: _Log, run: "_Run | None" = None, cache_dir=None):
    from robust_imdp.abstraction.rows import CellBounds

    run = run if run is not None else _Run()
    data = _residual_data(problem)
    # the known parts' certified ranges first: a function undefined on part of X is refused before
    # the long stages (ExpressionDomainError names the mode, the component and the box)
    known_ranges = _known_ranges(problem, partition.cells_lower, partition.cells_upper)
    checks, check_noise = _check_assumption(problem, data, log, cache_dir)
    if problem.error_bound == "chowdhury":
        return _learn_and_bound_gp(problem, partition, log, checks, check_noise)
    from robust_imdp.bounds.rkhs import CELL_BLOCK, check_ranges, hoeffding_factor, noise_bound_at_confidence

    data_fail, iid_delta = _failure_budget(problem)
    m_total = sum(x.shape[0] for x, _, _ in data)
    noise_bound, _ = noise_bound_at_confidence(problem.noise, m_total, data_fail if data_fail > 0 else 0.5)
    M, n, N = len(problem.mode_names), len(problem.space_lower), partition.n_cells
    lo, up = partition.cells_lower, partition.cells_upper
    iid_theta = problem.noise.sub_gaussian_parameter() if problem.iid_noise else None
    settings = {**_base_settings(problem), "noise_bound": _shared_allowance(problem, noise_bound),
                "method": problem.error_bound, "iid_theta": iid_theta,
                "iid_factor": None if iid_theta is None else hoeffding_factor(M * n * N * 2 ** n, iid_delta)}
    chunk = _chunk_cells(run, N, 256)
    tasks = [(u, s0) for u in range(M) for s0 in range(0, N, chunk)]
    local = _local_settings(problem, data, partition, noise_bound)
    # one allowance for every mode (the largest), as on the one-setting path: equal settings, equal bytes
    extras = _mode_extras(problem, data, partition, _shared_allowance(problem, noise_bound), local)
    if any(loc is not None for loc in local):
        log.info("local weights: " + ", ".join(f"mode {problem.mode_names[u]}: "
                                               + ("all points" if loc is None else f"{loc[0]} nearest points")
                                               for u, loc in enumerate(local)))
    parts_dir = None if cache_dir is None else Path(cache_dir) / f"bounds-{bounds_key(problem)}.parts"
    results: dict = {}
    if parts_dir is not None and parts_dir.exists():
        for u, s0 in tasks:
            part = read_cache_entry(parts_dir / f"m{u}-c{s0}-{chunk}.npz",
                                    lambda f, k=min(chunk, N - s0): _check_part(_load_npz(f), k, n))
            if part is not None:
                results[(u, s0)] = part
        if results:
            log.info(f"resumed: {len(results)} of {len(tasks)} bound chunks from {parts_dir}")
    missing = [t for t in tasks if t not in results]
    with log.stage("bound"):
        work = None
        if missing:
            # Pre-flight: time a few blocks of cells in this process and extrapolate.
            from robust_imdp.bounds import rkhs

            x0, y0, _ = data[0]
            A0, b0 = _affine_part(problem, 0)
            # The kernels' first call in a process compiles them (no warm-up at install) or loads
            # them from numba's cache (about 1 s): a one-cell call takes that time, so that the
            # timed pilot below measures bounding only.
            first = dict(settings) if local[0] is None else dict(settings, local_points=local[0][0],
                                                                 local_lambda=local[0][1])
            compile_s = rkhs.bound_chunk(x0, y0, A0, b0, lo[:1], up[:1], threads=1, **first)["seconds"]
            if compile_s > 5.0:
                log.info(f"pre-flight: numba compiled the bound kernels in {compile_s:.0f} s (once: cached for later "
                         "runs; `python -m robust_imdp.warmup` does it at install)")
            sched = run.scheduler(log)
            # One block per thread of a task, on that many threads: in process, the numba threads
            # share the cores with whatever else runs, and this measures the speed the tasks get.
            threads = int(getattr(sched, "threads", 1))
            k = min(N, CELL_BLOCK * threads)
            pilot = _bound_task(x0, y0, A0, b0, lo[:k], up[:k], local[0], *_extra(extras[0]), threads=threads,
                                **settings)
            per_cell = pilot["seconds"] / k  # wall seconds per cell and mode, on ``threads`` threads
            lanes = max(1, sched.n_workers // threads)  # tasks running at once
            wall = per_cell * N * M * len(missing) / len(tasks) / lanes
            log.info(f"pre-flight: {N:,} cells x {M} modes x {n} outputs = {N * M * n:,} cell bounds; about "
                     f"{wall * sched.n_workers:.0f} s of work ({per_cell * threads * 1e3:.2f} ms per cell and mode "
                     f"on one core), about {wall:.0f} s on {sched.n_workers} core{'s' if sched.n_workers > 1 else ''}")
            shared = [(sched.share(np.ascontiguousarray(x)), sched.share(np.ascontiguousarray(y)))
                      for x, y, _ in data]  # sent to the workers once
            args = [(*shared[u], *_affine_part(problem, u), lo[s0:s0 + chunk], up[s0:s0 + chunk],
                     local[u], *_extra(extras[u])) for u, s0 in missing]
            t0 = time.perf_counter()
            for i, res in sched.run(_bound_task, args, settings):
                key = missing[i]
                results[key] = res
                if parts_dir is not None:  # saved as it completes: an interrupted run resumes from here
                    write_cache_entry(parts_dir / f"m{key[0]}-c{key[1]}-{chunk}.npz",
                                      lambda tmp, r=res: _savez(tmp, {k: np.asarray(v) for k, v in r.items()}))
                log.progress("bound", len(results), len(tasks), t0, resumed=len(tasks) - len(missing))
    lower = np.empty((M, N, n))
    upper = np.empty((M, N, n))
    support = np.empty((M, N, n), dtype=np.int64)
    unconv = 0
    for (u, s0), r in results.items():
        sl = slice(s0, min(N, s0 + chunk))
        lower[u, sl], upper[u, sl], support[u, sl] = r["lower"], r["upper"], r["support"]
        unconv += int(r["n_unconverged"])
    for u in range(M):
        check_ranges(lower[u], upper[u], u)
        if known_ranges[u] is not None:  # f_u's certified range plus g_u's (the chunks bounded g_u alone)
            _add_known_range(lower[u], upper[u], known_ranges[u])
    confidence = 1.0 - data_fail - (iid_delta if iid_theta is not None else 0.0)
    log.info(f"bounded images of {N} cells x {M} modes x {n} outputs ({problem.error_bound} weights)")
    if confidence >= 1.0:
        statement = ("with probability 1, if every unknown component is within the misspecification of a "
                     "function of RKHS norm <= rkhs_bound and the data noise is within its bound")
    else:
        events = []
        if data_fail > 0:
            events.append(f"the data noise within {np.round(noise_bound, 6).tolist()} (probability >= "
                          f"{1 - data_fail:g})")
        if iid_delta > 0:
            events.append(f"the sub-Gaussian bound of independent noise (probability >= {1 - iid_delta:g})")
        statement = (f"with probability >= {confidence:g} over the data ({'; '.join(events)}), if every "
                     "unknown component is within the misspecification of a function of RKHS norm <= rkhs_bound")
    cell_bounds = CellBounds(lower, upper, None)
    diag = _diagnostics(problem, partition, cell_bounds, data, checks, check_noise, confidence, statement)
    diag["support_median"] = float(np.median(support))
    if any(r is not None for r in known_ranges):
        diag["known_part_gap"] = _known_gap(problem, partition, known_ranges)
    if unconv:
        diag["unconverged_vertex_problems"] = int(unconv)
    return cell_bounds, None, diag


def _learn_and_bound_gp(problem: Problem, partition, log: _Log, checks, check_noise):
    from robust_imdp.abstraction.rows import CellBounds
    from robust_imdp.bounds.gp_cells import bound_image
    from robust_imdp.bounds.gp import learn

    theta = problem.noise.sub_gaussian_parameter()
    with log.stage("learn"):
        learned = learn(problem.data, list(problem.maps), rkhs_bound=problem.rkhs_bound,
                        noise_theta=theta, **problem.gp_options)
    n_modes, n = len(problem.mode_names), len(problem.space_lower)
    log.info(f"learned {n_modes} modes x {n} outputs from {len(problem.data.u)} points")
    lo, up = partition.cells_lower, partition.cells_upper
    with log.stage("bound"):
        images = [bound_image(learned.gps[u], problem.maps[u].A, problem.maps[u].b, lo, up,
                              tol=problem.bound_tol, max_boxes=problem.bound_max_boxes)
                  for u in range(n_modes)]
    log.info(f"bounded images of {partition.n_cells} cells x {n_modes} modes")
    cell_bounds = CellBounds(
        image_lower=np.stack([im.lower for im in images]),
        image_upper=np.stack([im.upper for im in images]),
        std_upper=np.stack([im.std_upper for im in images]),
    )
    boxes = cell_bounds  # the error radius is measured on the boxes that are abstracted
    if problem.guarantee == "confidence":
        from robust_imdp.abstraction.rows import confidence_cell_bounds

        boxes = confidence_cell_bounds(cell_bounds, learned.error_bounds, problem.confidence)
    if problem.guarantee == "confidence":
        statement = (f"with probability >= {problem.confidence:g} over the data (Chowdhury-Gopalan error bound, "
                     "union bound over the GPs), if every unknown component has RKHS norm <= rkhs_bound")
        conf = float(problem.confidence)
    else:
        statement = ("Thm 1 as printed: mixes a probability over the data into the transition bounds; not a "
                     "guarantee for one fixed system (docs/soundness_audit.md, F2)")
        conf = None
    diag = _diagnostics(problem, partition, boxes, _residual_data(problem), checks, check_noise,
                        conf if conf is not None else float("nan"), statement)
    if conf is None:
        diag["confidence"] = None
    return cell_bounds, learned.error_bounds, diag


def _synthesize(problem: Problem, partition, abstraction, dfa, log: _Log):
    from robust_imdp.synthesis.core import synthesize

    with log.stage("synthesize"):
        syn = synthesize(abstraction.imdp, partition.labels, partition.atoms, dfa,
                         threshold=problem.threshold, horizon=problem.horizon,
                         outside_state=partition.outside_state)
    classes = _class_names(syn.classes, syn, problem.threshold)
    return syn, classes


def _class_names(classes, syn, threshold) -> np.ndarray:
    """Per-cell "yes"/"no"/"maybe" from whatever form SynthesisResult.classes has."""
    c = np.asarray(classes)
    if c.dtype.kind in "US":
        return c.astype(str)
    if c.dtype == object:
        return np.array([str(getattr(v, "value", v)).lower() for v in c])
    # Fall back to the definition (paper, Sec. 5): yes iff p_low >= threshold, no iff p_up < threshold.
    p_low, p_up = np.asarray(syn.p_low), np.asarray(syn.p_up)
    return np.where(p_low >= threshold, "yes", np.where(p_up < threshold, "no", "maybe"))


# --------------------------------------------------------------------------- entry points
def estimate_resources(problem: Problem, n_dfa_states: int = 4) -> dict:
    """Pre-flight estimate of a run's size and peak memory, before any heavy work.

    The cell count is that of the plain grid (regions that do not fit it add a few cells).
    Memory: IMDP rows of ``~3^n`` listed successors (24 bytes each: column, lower, upper) held
    about three times during assembly, the image boxes and their error radii, the partition, and
    the product solver's value arrays. Calibrated on the case studies and the 3-D study
    (``benchmarks/scale.py``) to over-estimate.

    Returns
    -------
    dict with ``n_cells``, ``n_modes``, ``n_outputs``, ``bytes`` (estimated peak) and
    ``available`` (bytes the machine has free now, or None if unknown).
    """
    lo, up, cs = (np.asarray(a, float) for a in (problem.space_lower, problem.space_upper, problem.cell_size))
    n = lo.size
    N = int(np.prod(np.ceil((up - lo) / cs - 1e-9)))
    M = len(problem.mode_names)
    succ = 3 ** n + 1
    imdp = N * M * (succ * 24 + 48)
    boxes = N * M * n * 8 * 8
    part = N * n * 8 * 6
    solver = N * M * max(int(n_dfa_states), 1) * 8 * 6
    return {"n_cells": N, "n_modes": M, "n_outputs": n, "bytes": int(3 * imdp + boxes + part + solver + 2e8),
            "available": _available_memory()}


def _available_memory() -> int | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover - non-Linux
        pass
    return None


def _preflight(problem: Problem, dfa, log: _Log, run: _Run) -> None:
    from robust_imdp.errors import ResourceError

    est = estimate_resources(problem, dfa.n_states)
    gb = est["bytes"] / 1e9
    avail = est["available"]
    log.info(f"pre-flight: {est['n_cells']:,} cells x {est['n_modes']} modes x {est['n_outputs']} outputs, "
             f"peak memory about {gb:.2f} GB" + (f" of {avail / 1e9:.1f} GB available" if avail else ""))
    if run.check_resources and avail is not None and est["bytes"] > 0.9 * avail:
        coarser = np.round(np.asarray(problem.cell_size, float) * 2, 6).tolist()
        raise ResourceError(
            f"pre-flight: {est['n_cells']:,} cells x {est['n_modes']} modes need about {gb:.1f} GB, more than the "
            f"{avail / 1e9:.1f} GB available: use a coarser [space].cell_size (e.g. {coarser}, which divides the "
            f"cells by {2 ** est['n_outputs']}); --scheduler moves the bound stage to a Dask cluster but not the "
            "abstraction; --yes runs anyway")


def synthesize_from_data(problem: Problem, *, progress: bool = True, abstraction_cache=None, client=None,
                         workers: int | None = None, scheduler: str | None = None, chunk_cells: int | None = None,
                         check_resources: bool = True, advice="auto") -> Result:
    """Learn, bound, abstract and synthesize: data and formula in, guarantees out.

    Parameters
    ----------
    problem : Problem
    progress : bool
        Print one line per stage (and counts, progress, time estimates) to stderr.
    abstraction_cache : str or Path, optional
        Directory where the abstraction is saved as ``abstraction-<key>.npz``; an existing file
        with the same key (see :func:`abstraction_key`) is loaded instead of re-running learn,
        bound and abstract. Finished chunks of the bound stage are saved there as they complete,
        so an interrupted run resumes where it stopped.
    client : distributed.Client, optional
        Run the chunked stages on this Dask cluster (the data are sent to the workers once).
    workers : int, optional
        Local cores: 1 runs in this process on one core, N > 1 starts a local Dask cluster of N
        processes (call it under ``if __name__ == "__main__":`` in scripts); None (default) runs in
        this process with numba threads on all cores.
    scheduler : str, optional
        Address of a running Dask scheduler (``"tcp://host:8786"``).
    chunk_cells : int, optional
        Cells per task (rounded up to a multiple of 16). The result does not depend on it, nor
        on the number of workers.
    check_resources : bool
        Refuse (``ResourceError``) when the pre-flight memory estimate exceeds the memory free.
    advice : {"auto", True, False}
        After the solve, estimate which lever (a 2x finer grid, more data, a smaller B) would move
        most of X into Q_yes (:func:`robust_imdp.synthesis.advice.advise`; ``result.advice``, the summary's
        ``advice:`` line and ``result.json``'s ``diagnostics.advice``). ``"auto"``: when the
        finer grid has at most ``advice.MAX_CELLS`` cells and about
        ``advice.MAX_AUTO_TRANSITIONS`` listed transitions (cells x modes x 3^d); it then costs
        three abstract + solve passes (one on the finer grid) and at most 16 pilot cells per mode
        of the bound stage, twice; True: always; False: never.

    Returns
    -------
    Result
    """
    from robust_imdp.spec.dfa import ltlf_to_dfa

    if advice not in ("auto", True, False):
        raise InvalidInputError(f"advice must be 'auto', True or False; got {advice!r}")
    log = _Log(progress)
    run = _Run(client=client, workers=workers, scheduler=scheduler, chunk_cells=chunk_cells,
               check_resources=check_resources)
    run.advice = advice
    with log.stage("specify"):
        dfa = ltlf_to_dfa(problem.formula)
        _check_atoms(dfa, problem)
    log.info(f"DFA: {dfa.n_states} states over atoms {list(dfa.atoms)}")
    _warn_overlaps(problem, dfa)
    _preflight(problem, dfa, log, run)
    try:
        return _synthesize_run(problem, dfa, log, run, abstraction_cache)
    finally:
        run.close()


def _synthesize_run(problem: Problem, dfa, log: _Log, run: _Run, abstraction_cache) -> Result:
    from robust_imdp.models.geometry import Box, Partition

    with log.stage("partition"):
        partition = Partition(Box(problem.space_lower, problem.space_upper), problem.cell_size,
                              _region_objects(problem), names=problem.dim_names)
    log.info(f"partition: {partition.n_cells} cells")

    abstraction, from_cache, diagnostics, cell_bounds = None, False, {}, None
    cache_file = diag_file = None
    if abstraction_cache is not None:
        cache_file = Path(abstraction_cache) / f"abstraction-{abstraction_key(problem)}.npz"
        diag_file = cache_file.with_suffix(".json")
        if cache_file.exists():
            with log.stage("load_abstraction"):
                entry = _load_abstraction_entry(cache_file)
            if entry is not None:
                abstraction, diagnostics = entry
                from_cache = True
                log.info(f"reused abstraction {cache_file.name}")
    if abstraction is None:
        abstraction, diagnostics, cell_bounds = _build_abstraction(problem, partition, log, abstraction_cache, run)
        if cache_file is not None:
            _save_abstraction_entry(cache_file, abstraction, diagnostics)
    why = diagnostics_line(diagnostics)
    if why:
        log.info(why)
    syn, classes = _synthesize(problem, partition, abstraction, dfa, log)
    advice = _advice(problem, partition, cell_bounds, dfa, classes, log, run, abstraction_cache, diagnostics)
    parameters = _parameters(problem, abstraction)
    if problem.refine is not None:  # issue 13: adaptive refinement of the undecided cells
        partition, abstraction, syn, classes, diagnostics, parameters["abstraction_key"] = _refine(
            problem, partition, abstraction, syn, cell_bounds, dfa, log, run, abstraction_cache, diagnostics)
    log.timings["total"] = time.perf_counter() - log.t0
    result = Result(problem=problem, partition=partition, abstraction=abstraction, dfa=dfa,
                    synthesis=syn, class_names=classes, timings=dict(log.timings),
                    parameters=parameters, from_cache=from_cache,
                    diagnostics=diagnostics, advice=advice)
    return result


def _load_abstraction_entry(cache_file: Path):
    """(abstraction, the JSON document saved beside it) from the cache, or None (absent or damaged)."""
    from robust_imdp.abstraction.rows import Abstraction

    doc = read_cache_entry(cache_file.with_suffix(".json"), _read_json)
    if doc is None:
        return None
    abstraction = read_cache_entry(cache_file, Abstraction.load)
    return None if abstraction is None else (abstraction, doc)


def _save_abstraction_entry(cache_file: Path, abstraction, doc: dict) -> None:
    """The JSON document first, the abstraction last: its presence means the pair is complete."""
    _write_json_entry(cache_file.with_suffix(".json"), doc)
    write_cache_entry(cache_file, abstraction.save)


def _advice(problem: Problem, partition, cell_bounds, dfa, classes, log: _Log, run: _Run, cache_dir,
            diagnostics: dict) -> dict:
    """:func:`robust_imdp.synthesis.advice.advise` as a JSON-able dict when the run asks for it, else ``{}``."""
    from robust_imdp.synthesis.advice import MAX_AUTO_TRANSITIONS, MAX_CELLS, advice_line, advise

    want = getattr(run, "advice", "auto")
    if not _settings(problem).uniform:
        return {}  # the smaller-B lever halves one B; per-mode and per-component assumptions have many
    n_fine = partition.n_cells * 2 ** partition.dim
    work = n_fine * len(problem.mode_names) * 3 ** partition.dim  # ~ listed transitions of the finer grid
    if (want is False or (want == "auto" and (n_fine > MAX_CELLS or work > MAX_AUTO_TRANSITIONS))
            or problem.error_bound == "chowdhury"):
        return {}  # the GP route has no pilot bound stage (its boxes come from bounds.bound_image)
    if cell_bounds is None and cache_dir is not None:  # the abstraction came from the cache: its boxes too
        bounds_file = Path(cache_dir) / f"bounds-{bounds_key(problem)}.npz"
        loaded = read_cache_entry(bounds_file, _load_bounds)  # None when absent or damaged
        if loaded is not None:
            cell_bounds = loaded[0]
    if cell_bounds is None:
        return {}
    from robust_imdp.bounds.rkhs import noise_bound_at_confidence

    data = _residual_data(problem)
    data_fail, _ = _failure_budget(problem)
    noise_bound, _ = noise_bound_at_confidence(problem.noise, sum(x.shape[0] for x, _, _ in data),
                                               data_fail if data_fail > 0 else 0.5)
    tau = float(problem.misspecification)
    # dense data pin g down to within the data-noise bound (a constant offset of the noise looks
    # like g); with iid noise the sub-Gaussian bound shrinks further, to tau
    floor = np.full(len(noise_bound), tau) if problem.iid_noise else np.asarray(noise_bound, float) + tau
    mins = [c["minimum"] for c in diagnostics.get("assumption", {}).get("min_norm", [])]
    bounders: dict = {}

    def bound_cells(lower, upper, rkhs_bound):
        if rkhs_bound not in bounders:
            bounders[rkhs_bound] = _cell_bounder(problem.replace(rkhs_bound=rkhs_bound), partition, _Log(False), run,
                                                 task=_pilot_task)
        return bounders[rkhs_bound](lower, upper)

    with log.stage("advice"):
        adv = advise(partition, cell_bounds, _fitted(problem, data), problem.noise, dfa, threshold=problem.threshold,
                     horizon=problem.horizon, classes=classes, noise_floor=floor, rkhs_bound=problem.rkhs_bound,
                     min_norm=max(mins, default=0.0),
                     abstraction_options={"eta": problem.eta, "eps_rule": problem.eps_rule,
                                          "combine": problem.combine},
                     bound_cells=bound_cells, max_cells=MAX_CELLS if want == "auto" else 2 ** 62)
    from robust_imdp.jsonable import jsonable as _jsonable

    out = _jsonable(adv.to_dict())
    log.info(advice_line(out))
    return out


def _pilot_task(*args, threads=1, **settings):
    """The advice's pilot cells: the work of :func:`_bound_task` (same arguments, including a mode's own
    settings) under its own name, so that progress does not count them as bound-stage chunks."""
    return _bound_work(*args, threads=threads, **settings)


def _cell_bounder(problem: Problem, partition, log: _Log, run: _Run, task=None):
    """``bound_cells(lower, upper) -> (image_lower, image_upper)`` for new cells: the bound stage's settings.

    The same data, noise bound (one event over the data, whatever the cells), weights and local
    pools as :func:`_learn_and_bound`, so a new cell's box holds on the same event as the grid's.
    """
    from robust_imdp.bounds.rkhs import check_ranges, noise_bound_at_confidence

    data = _residual_data(problem)
    data_fail, _ = _failure_budget(problem)
    m_total = sum(x.shape[0] for x, _, _ in data)
    noise_bound, _ = noise_bound_at_confidence(problem.noise, m_total, data_fail if data_fail > 0 else 0.5)
    settings = {**_base_settings(problem), "noise_bound": _shared_allowance(problem, noise_bound),
                "method": problem.error_bound, "iid_theta": None, "iid_factor": None}
    local = _local_settings(problem, data, partition, noise_bound)
    # one allowance for every mode (the largest), as on the one-setting path: equal settings, equal bytes
    extras = _mode_extras(problem, data, partition, _shared_allowance(problem, noise_bound), local)
    sched = run.scheduler(log)
    shared = [(sched.share(np.ascontiguousarray(x)), sched.share(np.ascontiguousarray(y))) for x, y, _ in data]
    M, n = len(problem.mode_names), len(problem.space_lower)

    def bound_cells(lower, upper):
        k = lower.shape[0]
        chunk = _chunk_cells(run, k, 256)
        tasks = [(u, s0) for u in range(M) for s0 in range(0, k, chunk)]
        args = [(*shared[u], *_affine_part(problem, u), lower[s0:s0 + chunk], upper[s0:s0 + chunk],
                 local[u], *_extra(extras[u])) for u, s0 in tasks]
        lo, hi = np.empty((M, k, n)), np.empty((M, k, n))
        for i, res in sched.run(task or _bound_task, args, settings):
            u, s0 = tasks[i]
            lo[u, s0:s0 + chunk], hi[u, s0:s0 + chunk] = res["lower"], res["upper"]
        known = _known_ranges(problem, lower, upper)
        for u in range(M):
            check_ranges(lo[u], hi[u], u)
            if known[u] is not None:  # f_u's certified range plus g_u's
                _add_known_range(lo[u], hi[u], known[u])
        return lo, hi

    return bound_cells


def refined_key(problem: Problem) -> str:
    """Hash of everything a refined abstraction depends on: the abstraction's, the options and the spec."""
    h = hashlib.sha256(abstraction_key(problem).encode())
    _fingerprint(h, [problem.refine.to_dict(), problem.formula, float(problem.threshold), problem.horizon])
    return h.hexdigest()[:20]


def _refine(problem: Problem, partition, abstraction, syn, cell_bounds, dfa, log: _Log, run: _Run, cache_dir,
            diagnostics):
    """Refinement rounds from the grid's result (``refine.refine``); cached under :func:`refined_key`."""
    from robust_imdp.models.geometry import BoxPartition
    from robust_imdp.jsonable import jsonable as _jsonable
    from robust_imdp.synthesis.refine import refine

    key = refined_key(problem)
    diagnostics = dict(diagnostics)
    cache_file = None if cache_dir is None else Path(cache_dir) / f"abstraction-{key}.npz"
    entry = None
    if cache_file is not None and cache_file.exists():
        with log.stage("load_abstraction"):
            entry = _load_abstraction_entry(cache_file)
    if entry is not None:
        abstraction, doc = entry
        diagnostics["refinement"] = doc.get("refinement")
        log.info(f"reused refined abstraction {cache_file.name}")
        partition = abstraction.partition
        syn, classes = _synthesize(problem, partition, abstraction, dfa, log)
        return partition, abstraction, syn, classes, diagnostics, key
    with log.stage("refine"):
        if cell_bounds is None:  # the grid's abstraction came from the cache: its boxes too
            cell_bounds = _build_abstraction(problem, partition, _Log(False), cache_dir, run)[2]
        out = refine(BoxPartition(partition), cell_bounds, _cell_bounder(problem, partition, log, run),
                     problem.noise, dfa, threshold=problem.threshold, horizon=problem.horizon,
                     options=problem.refine, abstraction=abstraction, synthesis=syn,
                     abstraction_options={"eta": problem.eta, "eps_rule": problem.eps_rule,
                                          "combine": problem.combine},
                     progress=log.info if log.enabled else None)
    diagnostics["refinement"] = _jsonable({"stopped": out.stopped, "options": problem.refine.to_dict(),
                                           "rounds": [r.to_dict() for r in out.rounds]})
    log.info(f"refinement stopped ({out.stopped}) at {out.partition.n_cells} cells")
    if cache_file is not None:
        _save_abstraction_entry(cache_file, out.abstraction, {"refinement": diagnostics["refinement"]})
    classes = _class_names(out.synthesis.classes, out.synthesis, problem.threshold)
    return out.partition, out.abstraction, out.synthesis, classes, diagnostics, key


def resynthesize(result: Result, *, formula: str | None = None, threshold: float | None = None,
                 horizon="keep", progress: bool = True) -> Result:
    """Solve a new formula / threshold / horizon on ``result``'s abstraction (no re-learning)."""
    from robust_imdp.spec.dfa import ltlf_to_dfa

    changes = {}
    if formula is not None:
        changes["formula"] = formula
    if threshold is not None:
        changes["threshold"] = threshold
    if horizon != "keep":
        changes["horizon"] = horizon
    problem = result.problem.replace(**changes)
    log = _Log(progress)
    with log.stage("specify"):
        dfa = ltlf_to_dfa(problem.formula)
        _check_atoms(dfa, problem)
    syn, classes = _synthesize(problem, result.partition, result.abstraction, dfa, log)
    log.timings["total"] = time.perf_counter() - log.t0
    out = Result(problem=problem, partition=result.partition, abstraction=result.abstraction,
                 dfa=dfa, synthesis=syn, class_names=classes, timings=dict(log.timings),
                 parameters=result.parameters, from_cache=True, diagnostics=result.diagnostics)
    return out
