"""robust_imdp: formally guaranteed switching controllers from data.

Pipeline: learn (gp) -> bound (bounds) -> abstract (abstraction) -> specify (ltlf, dfa)
-> product -> solve -> synthesize (synthesis) -> controller / simulate -> plot (plotting).
"""

from robust_imdp.errors import *  # noqa: F401,F403

__version__ = "0.1.0"
