"""The error-bound methods: how the unknown part ``g_u`` is bounded over a cell, one registry entry each.

A :class:`BoundMethod` declares what a method reads and what it can do (named capabilities), and
raises the errors a problem or a problem file gets when it asks a method for something it cannot
do. Modules ask the registry (``get(name).refine``, ``get(name).route`` ...) instead of comparing
the method's name.

Each method names its bound stage, a :class:`CellBounder`, by a dotted path
(``"robust_imdp.pipeline.bound_rkhs:learn_and_bound"``), and, with ``refine`` or ``advice_pilot``,
its bounder of new cells (:class:`NewCellBounder`); ``pipeline/bound_stage.py`` dispatches through
:meth:`BoundMethod.stage` / :meth:`BoundMethod.new_cells_stage`, which import them on first use (a
string, not an import: bounds/ stays below pipeline/).

**A new error-bound method** = one new module (its bound stage, e.g. ``pipeline/bound_mymethod.py``
with ``learn_and_bound``, built on ``bound_stage``'s shared helpers: ``_prepare``, ``_diagnostics``)
plus one :data:`METHODS` entry here naming it and its capabilities: 1 existing code file. Nothing
else compares method names (``Problem``, the problem file, the cache keys and the advice ask the
capabilities). The bookkeeping every new module gets: its row in docs/ARCHITECTURE.md
(tests/test_architecture.py), its name in its package's lazy list (``pipeline/__init__.py``) and
docs/api.md regenerated (tests/test_api_docs.py).

The checks keep the messages the problem (``InvalidInputError``) and the problem file
(``ProblemFileError``, prefixed by the file) gave before the registry existed; the names in them
("'optimal' or 'ridge'") are the registry's methods that have the capability.
"""

from __future__ import annotations

import difflib
import importlib
from dataclasses import dataclass
from typing import Callable, Protocol

from robust_imdp.errors import InvalidInputError, ProblemFileError

#: [gp] keys (``Problem.gp_options`` entries) that configure a GP posterior: read by a method with
#: ``gp_posterior`` only (``gp.learn``, ``gp_cells.bound_image``).
GP_POSTERIOR_KEYS = ("signal_variance", "optimize", "info_gain", "bound_tol", "bound_max_boxes")


class CellBounder(Protocol):
    """A method's bound stage over the grid's cells (``BoundMethod.bounder`` names it).

    ``bounder(problem, partition, log, run=None, cache_dir=None) -> (cell_bounds, error_models, diagnostics)``:
    ``cell_bounds`` an ``abstraction.cell_bounds.CellBounds``, ``error_models`` the per-mode GP error
    bounds the abstraction folds in or None (the boxes hold the whole error), ``diagnostics`` a dict
    (``pipeline.bound_stage._diagnostics`` plus the method's own keys). ``run``: the run's scheduler
    options (``pipeline.runtime._Run``), ``cache_dir``: where chunks and the check are saved, or None.
    """

    def __call__(self, problem, partition, log, run=None, cache_dir=None) -> tuple: ...


class NewCellBounder(Protocol):
    """A method's bounder of new cells (``BoundMethod.new_cells``; refinement and the advice's pilot cells).

    ``new_cells(problem, partition, log, run, task=None) -> bound_cells``, ``bound_cells(lower, upper) ->
    (image_lower, image_upper)`` (each ``(n_modes, k, n)``): boxes on the same event as the grid's.
    ``task``: the function each chunk runs (None: the bound stage's).
    """

    def __call__(self, problem, partition, log, run, task=None) -> Callable: ...


def _resolve(path: str):
    """The object a ``"package.module:name"`` path names (the module imported on first use)."""
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class BoundMethod:
    """One error-bound method (``Problem.error_bound`` / ``[gp].error_bound``).

    Attributes
    ----------
    name : str
    route : {"rkhs", "gp"}
        ``"rkhs"``: the deterministic certificate of ``bounds.rkhs`` under bounded noise;
        ``"gp"``: a GP posterior and a probabilistic error bound (``bounds.gp``).
    weights : str or None
        The ``method`` argument of ``rkhs.bound_chunk`` (``"optimal"`` or ``"ridge"``) on the RKHS route.
    bounder : str
        ``"module:function"`` of the method's bound stage, a :class:`CellBounder` (:meth:`stage`).
    new_cells : str or None
        ``"module:function"`` of its bounder of new cells, a :class:`NewCellBounder`
        (:meth:`new_cells_stage`); needed with ``refine`` or ``advice_pilot``, else None.
    options : tuple of str
        The ``gp_options`` keys the method reads.
    misspecification, iid_noise, local_points, refine, nonlinear_known, per_component : bool
        The method takes a misspecification tau > 0, ``iid_noise``, ``local_points``, adaptive
        refinement (new cells bounded on the grid's event), a nonlinear known part ``f_u``, and per
        mode / per component assumptions (``bounds.assumptions``).
    gp_posterior : bool
        It fits a GP posterior (takes :data:`GP_POSTERIOR_KEYS`).
    paper_guarantee : bool
        It supports ``guarantee="paper"`` (Thm 1 as printed).
    advice_pilot : bool
        The advice can bound pilot cells with it (a pilot bound stage exists).
    local_lambda : bool
        With local points it picks one ridge lambda per mode for all chunks (``rkhs.local_lambda``).
    confidence_in_bounds : bool
        The bound stage's boxes depend on ``confidence`` (its noise and iid events), so the bounds'
        cache key holds it.
    margins : bool
        Its bound stage certifies the boxes at larger factors of B with the same certificate weights, so a
        run reports assumption margins (``pipeline/margins.py``).
    """

    name: str
    route: str
    bounder: str
    new_cells: str | None = None
    weights: str | None = None
    options: tuple = ("lengthscale",)
    misspecification: bool = False
    iid_noise: bool = False
    local_points: bool = False
    split: bool = False
    refine: bool = False
    nonlinear_known: bool = False
    per_component: bool = False
    gp_posterior: bool = False
    paper_guarantee: bool = False
    advice_pilot: bool = False
    local_lambda: bool = False
    confidence_in_bounds: bool = False
    margins: bool = False

    def __post_init__(self):
        if (self.refine or self.advice_pilot) and self.new_cells is None:
            raise ValueError(f"error-bound method {self.name!r}: refine and advice_pilot need a bounder of "
                             "new cells (new_cells)")

    # ------------------------------------------------------------------ bound stages
    def stage(self) -> CellBounder:
        """The method's bound stage (:class:`CellBounder`), imported on first use."""
        return _resolve(self.bounder)

    def new_cells_stage(self) -> NewCellBounder:
        """The method's bounder of new cells (:class:`NewCellBounder`), imported on first use."""
        if self.new_cells is None:
            raise InvalidInputError(f"error_bound {self.name!r} has no bounder of new cells (refinement and the "
                                    f"advice's pilot cells need error_bound {_names('refine')})")
        return _resolve(self.new_cells)

    # ------------------------------------------------------------------ Problem (InvalidInputError)
    def check_guarantee(self, guarantee: str) -> None:
        if guarantee == "paper" and not self.paper_guarantee:
            raise InvalidInputError(
                f"guarantee 'paper' (Thm 1 as printed) needs error_bound {_names('paper_guarantee')}; "
                f"got {self.name!r}")

    def check_noise_options(self, tau: float, iid_noise) -> None:
        """misspecification > 0 and iid_noise need a method that takes them."""
        if (tau > 0 and not self.misspecification) or (iid_noise and not self.iid_noise):
            raise InvalidInputError(
                f"misspecification and iid_noise apply to error_bound {_names('misspecification')} only; the "
                f"{_ROUTE_TEXT[self.route]} (error_bound '{self.name}') has neither; got misspecification={tau!r}, "
                f"iid_noise={iid_noise!r}")

    def check_gp_options(self, gp_options: dict) -> None:
        """Without a GP posterior only the lengthscale is read."""
        if not self.gp_posterior:
            extra = sorted(set(gp_options) - set(self.options))
            if extra:
                raise InvalidInputError(
                    f"gp_options {extra} apply only to error_bound {_names('gp_posterior')} (a GP posterior); "
                    f"error_bound {self.name!r} uses the unit-amplitude kernel with the given lengthscale only")

    def check_known_parts(self, nonlinear_modes: list, uniform: bool, rkhs_bound, lengthscale) -> None:
        """A nonlinear known part and per-mode / per-component assumptions need a method that takes them."""
        if nonlinear_modes and not self.nonlinear_known:
            raise InvalidInputError(
                f"error_bound '{self.name}' (the {_ROUTE_TEXT[self.route]}, bounds.bound_image) bounds f_u + mu "
                f"jointly for an affine f_u = A x + b only; modes {nonlinear_modes} have a nonlinear known part f: "
                f"use error_bound {_names('nonlinear_known')}")
        if not uniform and not self.per_component:
            raise InvalidInputError(
                f"error_bound '{self.name}' (the {_ROUTE_TEXT[self.route]}) takes one rkhs_bound, one lengthscale "
                f"and no known components; per-mode or per-component values need error_bound "
                f"{_names('per_component')}; got rkhs_bound={rkhs_bound!r}, lengthscale={lengthscale!r}")

    def check_refine(self, iid_noise) -> None:
        """New cells need bounds of the same statement: the GP route folds the error in at the end,
        and iid_noise's union bound counts the cells of the grid."""
        if not self.refine or iid_noise:
            raise InvalidInputError(
                f"[refine] needs error_bound {_names('refine')} without iid_noise (the bounds of new cells "
                f"must hold on the same event); got error_bound={self.name!r}, iid_noise={iid_noise!r}")

    # ------------------------------------------------------------------ problem files (ProblemFileError)
    def check_file_options(self, gp_in: dict, where: str) -> None:
        """The [gp] table's GP-posterior keys need a method with a GP posterior."""
        if not self.gp_posterior:
            gp_only = [k for k in GP_POSTERIOR_KEYS if k in gp_in]
            if gp_only:
                post = _names("gp_posterior", '"')
                raise ProblemFileError(
                    f"{where}: [gp].{gp_only[0]} applies only to error_bound = {post} (a GP posterior); "
                    f"error_bound = \"{self.name}\" uses the unit-amplitude kernel with the given lengthscale "
                    f"only: remove the key or set error_bound = {post}")

    def check_split(self) -> None:
        if not self.split:
            names = _names("split", "'")
            raise InvalidInputError(f"split_tol applies to error_bound = {names} only (sub-box certificates of the "
                                    f"RKHS route); error_bound = {self.name!r} has none: remove it")

    def check_file_split(self, where: str) -> None:
        if not self.split:
            names = _names("split", '"')
            raise ProblemFileError(f"{where}: [learning].split_tol applies to error_bound = {names} only")

    def check_file_local_points(self, where: str) -> None:
        if not self.local_points:
            names = _names("local_points", '"')
            raise ProblemFileError(f"{where}: [gp].local_points applies to error_bound = {names} only")

    def check_file_refine(self, iid_noise, where: str) -> None:
        if not self.refine or iid_noise:
            names = _names("refine", '"')
            raise ProblemFileError(f"{where}: [refine] needs [gp].error_bound = {names} without "
                                   "iid_noise (the bounds of new cells must hold on the same event as the grid's)")

    def check_file(self, gp_in: dict, where: str, refine: bool = False) -> None:
        """Every problem-file rule of the method, in the order ``io.files.parse_problem_dict`` applies them."""
        self.check_file_options(gp_in, where)
        if "local_points" in gp_in:
            self.check_file_local_points(where)
        if refine:
            self.check_file_refine(gp_in.get("iid_noise"), where)

    def check(self, options: dict, where: str | None = None) -> None:
        """Every rule of the method for ``options`` (Problem attribute names), in the order
        ``Problem.__post_init__`` applies them; with ``where`` (a problem file) the file's rules instead.

        ``options``: ``guarantee``, ``misspecification`` (the largest tau, a float), ``iid_noise``,
        ``gp_options``, ``nonlinear_modes``, ``uniform`` (one assumption), ``rkhs_bound``, ``refine``
        (bool); absent keys are not checked. For a file: the [gp] table's keys and ``refine``.
        """
        if where is not None:
            self.check_file(options, where, bool(options.get("refine")) if "refine" in options else False)
            return
        if "guarantee" in options:
            self.check_guarantee(options["guarantee"])
        if "misspecification" in options or "iid_noise" in options:
            self.check_noise_options(options.get("misspecification", 0.0), options.get("iid_noise", False))
        gp_options = options.get("gp_options", {})
        self.check_gp_options(gp_options)
        if "nonlinear_modes" in options or "uniform" in options:
            self.check_known_parts(options.get("nonlinear_modes", []), options.get("uniform", True),
                                   options.get("rkhs_bound"), gp_options.get("lengthscale"))
        if options.get("refine"):
            self.check_refine(options.get("iid_noise", False))


_ROUTE_TEXT = {"gp": "GP route", "rkhs": "RKHS route"}

_RKHS = dict(route="rkhs", bounder="robust_imdp.pipeline.bound_rkhs:learn_and_bound",
             new_cells="robust_imdp.pipeline.bound_rkhs:cell_bounder", misspecification=True, iid_noise=True,
             local_points=True, split=True, refine=True, nonlinear_known=True, per_component=True, advice_pilot=True,
             confidence_in_bounds=True, margins=True)

#: The registry, in the order the documentation lists the methods (the default first).
METHODS: dict[str, BoundMethod] = {
    "optimal": BoundMethod("optimal", weights="optimal", **_RKHS),
    "ridge": BoundMethod("ridge", weights="ridge", local_lambda=True, **_RKHS),
    "chowdhury": BoundMethod("chowdhury", route="gp", bounder="robust_imdp.pipeline.bound_gp:learn_and_bound",
                             options=("lengthscale",) + GP_POSTERIOR_KEYS, gp_posterior=True, paper_guarantee=True),
}
#: The method names (``Problem.error_bound`` values), default first.
ERROR_BOUNDS = tuple(METHODS)
DEFAULT = "optimal"


def _names(capability: str, quote: str = "'") -> str:
    """The registry's methods with ``capability``, quoted and joined by "or" (as the messages name them)."""
    return " or ".join(f"{quote}{m.name}{quote}" for m in METHODS.values() if getattr(m, capability))


def _suggest(key: str, valid) -> str:
    close = difflib.get_close_matches(key, list(valid), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else f" (valid keys: {', '.join(valid)})"


def get(name, where: str | None = None) -> BoundMethod:
    """The method called ``name``; an unknown name raises InvalidInputError naming the choices
    (ProblemFileError prefixed by ``where`` and with a suggestion, for a problem file)."""
    method = METHODS.get(name) if isinstance(name, str) else None
    if method is not None:
        return method
    if where is None:
        raise InvalidInputError(f"error_bound must be one of {ERROR_BOUNDS}; got {name!r}")
    raise ProblemFileError(
        f"{where}: [gp].error_bound must be one of {', '.join(ERROR_BOUNDS)}; got {name!r}"
        + (_suggest(str(name), ERROR_BOUNDS) if isinstance(name, str) else ""))
