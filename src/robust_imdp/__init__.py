"""robust_imdp: formally guaranteed switching controllers from data.

Pipeline (one subpackage per part, plain data between stages; layers in docs/ARCHITECTURE.md)::

    models (data, known parts, noise) -> bounds (certified cell ranges) -> abstraction (Thm 1)
    -> spec (LTLf -> DFA) -> solvers (product, value iteration) -> synthesis (strategy, classes,
    controller, refinement, advice, where to sample) -> pipeline (the run) -> io (files)
    -> validate / improve / plotting / cli

The flat layout's module paths (``robust_imdp.solve``, ``robust_imdp.rkhs``, ...) still import,
with a DeprecationWarning naming the new one (``robust_imdp._compat``).

The most used names are re-exported here (``__all__``; ``docs/api.md`` lists every module's), each
imported on first use: ``import robust_imdp`` (and so every ``import robust_imdp.<module>``, e.g. in a
helper process) loads the package's errors only. Heavy optional back-ends stay out of the import:
cvxpy/clarabel (``robust_imdp.solvers.lp``), stormpy (``robust_imdp.io.formats``) and matplotlib
(``robust_imdp.plotting``) are imported only when those modules are used.
``robust_imdp.validate`` is the validation module, and calling it calls its ``validate`` function.

Example
-------
A 1-D system that moves 0.75 right or left per step, to reach ``goal`` without touching ``pit``
(the data are exact: ``x_next - f_u(x) = 0``, the noise is at most 0.01):

>>> import numpy as np
>>> from robust_imdp import Problem, UniformNoise, synthesize_from_data
>>> rng = np.random.default_rng(0)
>>> x = rng.uniform(0, 4, (40, 1))
>>> u = np.where(np.arange(40) < 20, "right", "left")
>>> x_next = x + np.where(u[:, None] == "right", 0.75, -0.75)
>>> problem = Problem.from_arrays(
...     x, u, x_next, lower=[0], upper=[4], cell_size=0.5,
...     regions={"goal": ([3], [4]), "pit": ([1.5], [2])}, formula="G !pit & F goal",
...     threshold=0.9, modes={"right": ([[1.0]], [0.75]), "left": ([[1.0]], [-0.75])},
...     noise=UniformNoise(0.01), rkhs_bound=0.1, lengthscale=1.0)
>>> result = synthesize_from_data(problem, progress=False)

Every cell right of the pit is guaranteed (``yes``: p_low >= 0.9), the pit itself is ``no``,
and left of it the controller may still cross the pit's edge (``maybe``):

>>> result.classes.tolist()
['maybe', 'maybe', 'maybe', 'no', 'yes', 'yes', 'yes', 'yes']
>>> result.p_low.tolist()
[0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0]
>>> result.controller().reset([2.2]).act([2.2])
'right'
"""

import sys as _sys

from robust_imdp._compat import OldPaths as _OldPaths
from robust_imdp._lazy import lazy_names
from robust_imdp.errors import *  # noqa: F401,F403
from robust_imdp.errors import __all__ as _errors

#: The re-exported names and their modules (imported on first use, PEP 562: ``import robust_imdp`` and every
#: ``import robust_imdp.<module>`` load only the package's errors; a run imports the stages it uses).
_NAMES = {
    "robust_imdp.models.imdp": ("IMDP",),
    "robust_imdp.solvers.api": ("Adversary", "Objective", "ReachabilityResult", "evaluate_strategy",
                                "solve_reachability"),
    "robust_imdp.solvers.product": ("ProductResult", "evaluate_product_strategy", "materialize_product",
                                    "solve_product"),
    "robust_imdp.spec.ltlf": ("atoms_of", "holds", "parse"),
    "robust_imdp.spec.dfa": ("DFA", "ltlf_to_dfa"),
    "robust_imdp.models.geometry": ("Box", "Partition", "Region"),
    "robust_imdp.models.noise": ("GaussianNoise", "NoiseModel", "TruncatedGaussianNoise", "UniformNoise"),
    "robust_imdp.models.system": ("AffineMap", "Dataset", "SwitchedSystem", "residuals"),
    "robust_imdp.models.inputs": ("InputGrid",),
    "robust_imdp.bounds.gp": ("GaussianProcess", "LearnedModel", "RKHSErrorBound", "learn"),
    "robust_imdp.bounds.gp_cells": ("ImageBounds", "PosteriorBounds", "bound_image", "bound_posterior"),
    "robust_imdp.abstraction.rows": ("Abstraction", "CellBounds", "abstract", "confidence_cell_bounds"),
    "robust_imdp.synthesis.core": ("SynthesisResult", "synthesize"),
    "robust_imdp.synthesis.controller": ("Controller",),
    "robust_imdp.pipeline.problem": ("Problem",),
    "robust_imdp.pipeline.result": ("Result",),
    "robust_imdp.pipeline.run": ("resynthesize", "synthesize_from_data"),
    "robust_imdp.io.files": ("load_problem", "load_result", "save_problem", "save_result"),
}

__version__ = "0.1.0"

if not any(isinstance(f, _OldPaths) for f in _sys.meta_path):
    _sys.meta_path.append(_OldPaths())  # last: only names no real module has

#: Further names, with their modules: the default (RKHS) bound route and validation. ``validate`` is the
#: module ``robust_imdp.validate`` (callable: it runs its ``validate`` function).
_LAZY = {
    **{name: "robust_imdp.bounds.rkhs" for name in (
        "KernelModel", "CellRange", "ImageRanges", "NormCheck",
        "cell_ranges", "image_ranges", "min_rkhs_norm", "check_assumption")},
    **{name: "robust_imdp.validate" for name in ("validate", "simulate", "ValidationReport")},
}

__getattr__, __dir__ = lazy_names(__name__, {**{name: module for module, names in _NAMES.items() for name in names},
                                              **_LAZY})

__all__ = [
    *_errors,
    "IMDP",
    "Adversary", "Objective", "ReachabilityResult", "evaluate_strategy", "solve_reachability",
    "ProductResult", "evaluate_product_strategy", "materialize_product", "solve_product",
    "atoms_of", "holds", "parse", "DFA", "ltlf_to_dfa",
    "Box", "Partition", "Region",
    "GaussianNoise", "NoiseModel", "TruncatedGaussianNoise", "UniformNoise",
    "AffineMap", "Dataset", "SwitchedSystem", "residuals", "InputGrid",
    "GaussianProcess", "LearnedModel", "RKHSErrorBound", "learn",
    "ImageBounds", "PosteriorBounds", "bound_image", "bound_posterior",
    "Abstraction", "CellBounds", "abstract", "confidence_cell_bounds",
    "SynthesisResult", "synthesize", "Controller",
    "Problem", "Result", "resynthesize", "synthesize_from_data",
    "load_problem", "load_result", "save_problem", "save_result",
    *_LAZY,
]
