"""robust_imdp: formally guaranteed switching controllers from data.

Pipeline (one module per stage, plain data between stages)::

    learn (gp) -> bound (bounds) -> abstract (abstraction) -> specify (ltlf, dfa)
    -> product -> solve -> synthesize (synthesis) -> controller / validate -> plot (plotting)

The most used names are re-exported here. Heavy optional back-ends stay out of the import:
cvxpy/clarabel (``robust_imdp.solvers.lp``), stormpy (``robust_imdp.io.formats``) and matplotlib
(``robust_imdp.plotting``) are imported only when those modules are used.
"""

from robust_imdp.errors import *  # noqa: F401,F403
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
from robust_imdp.pipeline.run import synthesize_from_data
from robust_imdp.io.files import load_problem, load_result, save_result

__version__ = "0.1.0"
