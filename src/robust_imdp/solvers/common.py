"""What every solver module shares: the :class:`Adversary` / :class:`Objective` enums, the controller
code :class:`Control` of the engine and its kernels, the result type :class:`ReachabilityResult`,
and the checks of targets, masks and strategies (one implementation, used by the engine, the
product and the LP cross-checks)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, IntEnum

import numpy as np

from robust_imdp.errors import DimensionError, InvalidInputError
from robust_imdp.models.imdp import IMDP


class Adversary(str, Enum):
    """How the probabilities inside the intervals are resolved.

    PESSIMISTIC works against the objective (the robust value), OPTIMISTIC with it.
    """

    PESSIMISTIC = "pessimistic"
    OPTIMISTIC = "optimistic"


class Objective(str, Enum):
    """Whether the controller maximises or minimises the reachability probability."""

    MAXIMIZE = "maximize"
    MINIMIZE = "minimize"


class Control(IntEnum):
    """What the controller does at a node: the ``ctrl`` of the engine and its kernels.

    The values are compiled into the numba kernels as constants (numba's cache does not track
    them): never renumber them.
    """

    MAXIMISE = 0  # maximises over the rows of the state
    MINIMISE = 1  # minimises over them
    FIXED = 2  # takes the row of a given strategy


def control_of(objective) -> Control:
    """The controller code of an objective (``"maximize"`` -> MAXIMISE, ``"minimize"`` -> MINIMISE)."""
    return Control.MAXIMISE if enum_value(Objective, objective, "objective") is Objective.MAXIMIZE else Control.MINIMISE


def enum_value(cls, value, name):
    """``value`` (a member of ``cls`` or its string) as a member of ``cls``; InvalidInputError otherwise."""
    try:
        return cls(value.value if isinstance(value, Enum) else value)
    except ValueError:
        allowed = ", ".join(repr(m.value) for m in cls)
        raise InvalidInputError(f"{name} must be one of {allowed}; got {value!r}") from None


@dataclass(frozen=True)
class ReachabilityResult:
    """Sound bracket of a reachability value.

    Attributes
    ----------
    lower, upper : (n,) float arrays
        ``lower <= true value <= upper`` for every state (rounded outward).
    strategy : (n,) int array, or (k, n) with a horizon
        Choice index within each state (``strategy[t]`` is used at time t for k-step).
    iterations : int
        Unbounded, default method: the largest number of Bellman sweeps (lower, upper and guess
        checks) spent on one strongly connected component; ``method="interval"``: lower/upper
        sweep pairs.  k-step: k.
    precision : float
        Achieved ``max(upper - lower)``.
    converged : bool
        ``precision <= requested precision``.
    """

    lower: np.ndarray
    upper: np.ndarray
    strategy: np.ndarray
    iterations: int
    precision: float
    converged: bool


def adversary_maximises(adversary, objective) -> bool:
    """True when the adversary picks the distribution maximising the reachability value."""
    a = enum_value(Adversary, adversary, "adversary")
    o = enum_value(Objective, objective, "objective")
    return (a is Adversary.OPTIMISTIC) == (o is Objective.MAXIMIZE)


def as_mask(x, n, name, allow_none=False, item="index"):
    """A boolean mask of length ``n`` from a mask or a 1-D index array (``None``: all False when
    ``allow_none``); ``item`` names an index in the out-of-range message ("index" or "state")."""
    if x is None:
        if allow_none:
            return np.zeros(n, dtype=bool)
        raise InvalidInputError(f"{name} must be a boolean mask of length {n} or an index array; got None")
    a = np.asarray(x)
    if a.dtype == bool:
        if a.shape != (n,):
            raise DimensionError(f"{name} as a boolean mask must have shape ({n},); got {a.shape}")
        return a.copy()
    if a.ndim != 1 or (a.size and not np.issubdtype(a.dtype, np.integer)):
        raise InvalidInputError(f"{name} must be a boolean mask of length {n} or a 1-D integer index array; "
                                f"got dtype {a.dtype}, shape {a.shape}")
    a = a.astype(np.int64)  # an empty list arrives as float
    bad = a[(a < 0) | (a >= n)]
    if bad.size:
        raise InvalidInputError(f"{name} holds {item} {int(bad[0])} outside [0, {n})")
    m = np.zeros(n, dtype=bool)
    m[a] = True
    return m


def target_avoid(n, target, avoid, item="index"):
    """Masks of ``target`` (non-empty) and ``avoid`` (optional), disjoint, over ``n`` states."""
    t = as_mask(target, n, "target", item=item)
    z = as_mask(avoid, n, "avoid", allow_none=True, item=item)
    if not t.any():
        raise InvalidInputError("target must contain at least one state; got an empty target")
    both = np.flatnonzero(t & z)
    if both.size:
        raise InvalidInputError(f"target and avoid must be disjoint; state {int(both[0])} is in both")
    return t, z


def check_strategy(imdp: IMDP, strategy, name="strategy") -> np.ndarray:
    """Validate a stationary ``(n,)`` or time-varying ``(k, n)`` strategy of choice indices."""
    s = np.asarray(strategy)
    n = imdp.n_states
    if s.ndim not in (1, 2) or s.shape[-1] != n:
        raise DimensionError(f"{name} must have shape ({n},) or (k, {n}); got {s.shape}")
    if s.size and not np.issubdtype(s.dtype, np.integer):
        raise InvalidInputError(f"{name} must hold integer choice indices; got dtype {s.dtype}")
    s = s.astype(np.int64)
    nch = np.diff(imdp.state_ptr)
    bad = np.argwhere((s < 0) | (s >= nch))
    if bad.size:
        idx = tuple(int(i) for i in bad[0])
        q = idx[-1]
        raise InvalidInputError(f"{name}{list(idx)} = {int(s[idx])} is not a choice of state {q} "
                                f"(it has {int(nch[q])} choices)")
    return s


__all__ = ["Adversary", "Objective", "Control", "ReachabilityResult", "adversary_maximises", "check_strategy"]
