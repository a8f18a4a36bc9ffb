"""Test-suite configuration.

Hypothesis runs derandomized: every property test draws the same examples on every machine,
so CI cannot turn red on a never-seen example (the "seed every random test" rule); the
examples themselves still cover the stated ranges. Deadlines are off because numba compiles
on first call.
"""

from hypothesis import settings

settings.register_profile("robust_imdp", derandomize=True, deadline=None, print_blob=True)
settings.load_profile("robust_imdp")
