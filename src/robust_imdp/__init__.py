"""robust_imdp: formally guaranteed switching controllers from data.

Pipeline (one module per stage, plain data between stages)::

    learn (gp) -> bound (bounds) -> abstract (abstraction) -> specify (ltlf, dfa)
    -> product -> solve -> synthesize (synthesis) -> controller / validate -> plot (plotting)

The most used names are re-exported here. Heavy optional back-ends stay out of the import:
cvxpy/clarabel (``robust_imdp.lp``), stormpy (``robust_imdp.formats``) and matplotlib
(``robust_imdp.plotting``) are imported only when those modules are used.
"""

from robust_imdp.errors import *  # noqa: F401,F403
from robust_imdp.imdp import IMDP
from robust_imdp.solve import (
    Adversary,
    Objective,
    ReachabilityResult,
    evaluate_strategy,
    solve_reachability,
)
from robust_imdp.product import (
    ProductResult,
    evaluate_product_strategy,
    materialize_product,
    solve_product,
)
from robust_imdp.ltlf import atoms_of, holds, parse
from robust_imdp.dfa import DFA, ltlf_to_dfa
from robust_imdp.geometry import Box, Partition, Region
from robust_imdp.noise import GaussianNoise, NoiseModel, TruncatedGaussianNoise, UniformNoise
from robust_imdp.system import AffineMap, Dataset, SwitchedSystem, residuals
from robust_imdp.gp import GaussianProcess, LearnedModel, RKHSErrorBound, learn
from robust_imdp.bounds import ImageBounds, PosteriorBounds, bound_image, bound_posterior
from robust_imdp.abstraction import Abstraction, CellBounds, abstract, confidence_cell_bounds
from robust_imdp.synthesis import SynthesisResult, synthesize
from robust_imdp.controller import Controller
from robust_imdp.pipeline import Problem, Result, synthesize_from_data
from robust_imdp.io import load_problem, load_result, save_result

__version__ = "0.1.0"
