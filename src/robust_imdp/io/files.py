"""Problem files (TOML), data files (CSV / NPZ) and result files (JSON + NPZ): the names of the
three modules that own them, in one place (the module that held all three).

* :mod:`robust_imdp.io.problem_file`: TOML -> ``Problem`` (``parse_problem_dict``, ``parse_problem_file``,
  ``load_problem``, ``make_noise``; the problem file contract);
* :mod:`robust_imdp.io.data_file`: ``.csv`` / ``.npz`` data files (``read_data_file``, ``write_data_file``)
  and the load-time checks of the samples;
* :mod:`robust_imdp.io.result_file`: ``result.json`` / ``result.npz`` (``result_to_dict``, ``save_result``,
  ``load_result``, ``ResultFile``, ``as_result_file``);
* :mod:`robust_imdp.io.problem_writer`: ``Problem`` -> problem file and data file (``save_problem``,
  ``problem_to_toml``).
"""

from __future__ import annotations

from robust_imdp.errors import ProblemFileError
from robust_imdp.io.data_file import FEW_SAMPLES, read_data_file, write_data_file  # noqa: F401
from robust_imdp.io.problem_file import (
    COMBINE_RULES, EPS_RULES, load_problem, make_noise, parse_problem_dict, parse_problem_file,  # noqa: F401
)
from robust_imdp.io.result_file import (
    CLASS_NAMES, RESULT_FORMAT, ResultFile, as_result_file, load_result, result_to_dict, save_result,  # noqa: F401
)
from robust_imdp.io.problem_writer import problem_to_toml, save_problem  # noqa: F401

__all__ = [
    "ProblemFileError",
    "parse_problem_file",
    "parse_problem_dict",
    "load_problem",
    "make_noise",
    "read_data_file",
    "write_data_file",
    "result_to_dict",
    "save_result",
    "load_result",
    "ResultFile",
    "as_result_file",
    "save_problem",
    "problem_to_toml",
]
