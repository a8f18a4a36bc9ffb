"""Exception and warning classes of robust_imdp.

Every exception subclasses a built-in (``ValueError``, ``RuntimeError``, ...) so
callers can catch it without importing this module, and every message names the
argument, the expected form and what was received, e.g.::

    DimensionError("x_next must have shape (m, 2) like x; got (m, 3)")

For example, an interval MDP row whose lower bounds sum to more than 1 is refused, and the
error is both an :class:`InvalidIntervalError` and a ``ValueError``:

>>> from robust_imdp import IMDP, InvalidIntervalError
>>> try:
...     IMDP.from_dense(lower=[[[0.6, 0.6]], [[0.0, 1.0]]], upper=[[[0.7, 0.7]], [[0.0, 1.0]]])
... except ValueError as exc:
...     print(type(exc).__name__, isinstance(exc, InvalidIntervalError), "|", exc)
InvalidIntervalError True | row 0 (state 0, action 0): sum of lower bounds 1.2 > 1 (excess 0.2)
"""

from __future__ import annotations


class RobustImdpError(Exception):
    """Base class of every exception raised on purpose by robust_imdp."""


# --------------------------------------------------------------------------- bad input
class InvalidInputError(RobustImdpError, ValueError):
    """An argument does not have the expected form or value."""


class DimensionError(InvalidInputError):
    """An array has the wrong shape or length."""


class InvalidIntervalError(InvalidInputError):
    """A probability interval violates 0 <= lower <= upper <= 1 or the row-sum conditions."""


class InvalidModelError(InvalidInputError):
    """A model (IMDP, DFA, system) is structurally invalid (indices, missing choices, ...)."""


class FormulaSyntaxError(InvalidInputError):
    """An LTLf formula cannot be parsed; the message shows the position with a caret."""


class ExpressionError(InvalidInputError):
    """An expression of known dynamics cannot be parsed (syntax, unknown symbol, unsupported operation)."""


class ExpressionDomainError(ExpressionError):
    """A known-dynamics expression is undefined (or overflows) on part of a box or at a point."""


class UnknownAtomError(InvalidInputError):
    """A formula or DFA names an atomic proposition that no region defines."""


class OutsideDomainError(InvalidInputError):
    """A continuous state lies outside the compact set X where the abstraction is defined."""


class ProblemFileError(InvalidInputError):
    """A problem file (TOML) or data file is missing a key, has a misspelt key or a bad value."""


# --------------------------------------------------------------------------- run-time failures
class VacuousSpecificationError(InvalidInputError):
    """Under the reading in use, the specification is decided by the cells' own labels alone (every cell
    satisfies it at time 0, or no trace can violate it), so its probability would say nothing about the
    dynamics; the message says what to write instead (README, "Two readings of a formula")."""


class AssumptionError(InvalidInputError):
    """The data refute a stated assumption (e.g. no function of RKHS norm <= B explains them).

    Raised before any result is written: the guarantees would rest on a false premise.
    """


class ResourceError(RobustImdpError, MemoryError):
    """A run would not fit the machine (pre-flight estimate); raised before any heavy work."""


class ConvergenceError(RobustImdpError, RuntimeError):
    """An iterative solver or optimiser did not reach the requested precision."""


class SoundnessError(RobustImdpError, RuntimeError):
    """An internal soundness check failed (e.g. a row with sum(lower) > 1 after rounding).

    This always indicates a bug or an input that breaks a stated assumption; it is
    never silently repaired.
    """


# --------------------------------------------------------------------------- interrupts
def interrupt_in(exc: BaseException | None) -> KeyboardInterrupt | None:
    """The ``KeyboardInterrupt`` behind ``exc`` (itself, or in its ``__cause__``/``__context__`` chain).

    Ctrl-C arrives as a flag that the interpreter turns into ``KeyboardInterrupt`` at the next
    Python bytecode it runs. When that is a callback inside compiled code (a numba kernel boxing
    its result, a C extension), the caller sees ``SystemError: ... returned a result with an
    exception set`` caused by the interrupt, or a wrapper exception raised from it: those are the
    interrupt too. Returns None when no interrupt is in the chain.
    """
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ if exc.__cause__ is not None else exc.__context__
    return None


# --------------------------------------------------------------------------- warnings
class RobustImdpWarning(UserWarning):
    """Base class of warnings issued by robust_imdp."""


class ConvergenceWarning(RobustImdpWarning):
    """A solver stopped before its precision target; the reported bounds stay sound but loose."""


class AssumptionWarning(RobustImdpWarning):
    """A user assumption looks doubtful (e.g. the RKHS bound B is below the norm of the posterior mean)."""


class SpecificationWarning(RobustImdpWarning):
    """The reading of the specification drops part of it, or some cells satisfy it by their own label alone
    (README, "Two readings of a formula")."""


class RegionOverlapWarning(RobustImdpWarning):
    """Two regions of the formula overlap (e.g. goal and obstacle): cells there carry both labels."""


__all__ = [
    "RobustImdpError",
    "InvalidInputError",
    "DimensionError",
    "InvalidIntervalError",
    "InvalidModelError",
    "FormulaSyntaxError",
    "UnknownAtomError",
    "ExpressionError",
    "ExpressionDomainError",
    "OutsideDomainError",
    "AssumptionError",
    "VacuousSpecificationError",
    "ProblemFileError",
    "ResourceError",
    "ConvergenceError",
    "SoundnessError",
    "RobustImdpWarning",
    "ConvergenceWarning",
    "AssumptionWarning",
    "SpecificationWarning",
    "RegionOverlapWarning",
]
