"""robust_imdp: formally guaranteed switching controllers from data.

Pipeline (one subpackage per part, plain data between stages; layers in docs/ARCHITECTURE.md)::

    models (data, known parts, noise) -> bounds (certified cell ranges) -> abstraction (Thm 1)
    -> spec (LTLf -> DFA) -> solvers (product, value iteration) -> synthesis (strategy, classes,
    controller, refinement, advice, where to sample) -> pipeline (the run) -> io (files)
    -> validate / improve / plotting / cli

The flat layout's module paths (``robust_imdp.solve``, ``robust_imdp.rkhs``, ...) still import,
with a DeprecationWarning naming the new one (``robust_imdp._compat``).

The most used names are re-exported here (``__all__``; ``docs/api.md`` lists every module's).
Heavy optional back-ends stay out of the import: cvxpy/clarabel (``robust_imdp.solvers.lp``),
stormpy (``robust_imdp.io.formats``) and matplotlib (``robust_imdp.plotting``) are imported only
when those modules are used. The default (RKHS) bound route (``robust_imdp.bounds.rkhs``) and the
validation names (``robust_imdp.validate``, which imports scipy.stats) load on first use.
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
from robust_imdp.models.imdp import IMDP
from robust_imdp.solvers.api import (
    Adversary,
    Objective,
    ReachabilityResult,
    evaluate_strategy,
    solve_reachability,
)
from robust_imdp.solvers.product import (
    ProductResult,
    evaluate_product_strategy,
    materialize_product,
    solve_product,
)
from robust_imdp.spec.ltlf import atoms_of, holds, parse
from robust_imdp.spec.dfa import DFA, ltlf_to_dfa
from robust_imdp.models.geometry import Box, Partition, Region
from robust_imdp.models.noise import GaussianNoise, NoiseModel, TruncatedGaussianNoise, UniformNoise
from robust_imdp.models.system import AffineMap, Dataset, SwitchedSystem, residuals
from robust_imdp.bounds.gp import GaussianProcess, LearnedModel, RKHSErrorBound, learn
from robust_imdp.bounds.gp_cells import ImageBounds, PosteriorBounds, bound_image, bound_posterior
from robust_imdp.abstraction.rows import Abstraction, CellBounds, abstract, confidence_cell_bounds
from robust_imdp.synthesis.core import SynthesisResult, synthesize
from robust_imdp.synthesis.controller import Controller
from robust_imdp.pipeline.problem import Problem
from robust_imdp.pipeline.result import Result
from robust_imdp.pipeline.run import resynthesize, synthesize_from_data
from robust_imdp.io.files import load_problem, load_result, save_problem, save_result

__version__ = "0.1.0"

if not any(isinstance(f, _OldPaths) for f in _sys.meta_path):
    _sys.meta_path.append(_OldPaths())  # last: only names no real module has

#: Names imported on first use, with their modules: the default (RKHS) bound route and validation.
#: ``validate`` is the module ``robust_imdp.validate`` (callable: it runs its ``validate`` function).
_LAZY = {
    **{name: "robust_imdp.bounds.rkhs" for name in (
        "KernelModel", "CellRange", "ImageRanges", "NormCheck",
        "cell_ranges", "image_ranges", "min_rkhs_norm", "check_assumption")},
    **{name: "robust_imdp.validate" for name in ("validate", "simulate", "ValidationReport")},
}

__getattr__, __dir__ = lazy_names(__name__, _LAZY)

__all__ = [
    *_errors,
    "IMDP",
    "Adversary", "Objective", "ReachabilityResult", "evaluate_strategy", "solve_reachability",
    "ProductResult", "evaluate_product_strategy", "materialize_product", "solve_product",
    "atoms_of", "holds", "parse", "DFA", "ltlf_to_dfa",
    "Box", "Partition", "Region",
    "GaussianNoise", "NoiseModel", "TruncatedGaussianNoise", "UniformNoise",
    "AffineMap", "Dataset", "SwitchedSystem", "residuals",
    "GaussianProcess", "LearnedModel", "RKHSErrorBound", "learn",
    "ImageBounds", "PosteriorBounds", "bound_image", "bound_posterior",
    "Abstraction", "CellBounds", "abstract", "confidence_cell_bounds",
    "SynthesisResult", "synthesize", "Controller",
    "Problem", "Result", "resynthesize", "synthesize_from_data",
    "load_problem", "load_result", "save_problem", "save_result",
    *_LAZY,
]
