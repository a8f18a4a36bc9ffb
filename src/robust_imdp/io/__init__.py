"""Files: problem files (TOML), data files, result files, model exchange (Storm DRN, PRISM)."""

from robust_imdp._lazy import exports

__getattr__, __dir__ = exports(__name__, ["files", "problem_file", "problem_writer", "data_file", "result_file", "formats"])
