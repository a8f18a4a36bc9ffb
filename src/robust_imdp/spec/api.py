"""The one way to get a DFA from a specification: :func:`to_dfa`.

A DFA is anything with the duck type of docs/ARCHITECTURE.md ("DFA (duck type used by
``product.py``)"): ``atoms``, ``n_states``, ``initial``, ``accepting``, ``delta``, ``step``,
``accepts``, ``letter_of``.  Such an object is returned as is; an LTLf formula (a string or a
parsed :class:`~robust_imdp.spec.ltlf.Formula`) goes through :func:`~robust_imdp.spec.dfa.ltlf_to_dfa`.

How to add a specification logic: one new module ``spec/<logic>.py`` whose translation returns
an object of the DFA duck type (e.g. a :class:`~robust_imdp.spec.dfa.DFA` built with
``DFA.from_table``), and one branch in :func:`to_dfa` that recognises its input.
"""

from __future__ import annotations

from typing import Any, Sequence, get_args

from robust_imdp.errors import InvalidInputError
from robust_imdp.spec.dfa import SEMANTICS, SpecKind, check_reading, classify, ltlf_to_dfa, resolve_semantics
from robust_imdp.spec.ltlf import Formula

#: The attributes of the DFA duck type.
DFA_ATTRIBUTES = ("atoms", "n_states", "initial", "accepting", "delta", "step", "accepts", "letter_of")


def is_dfa(obj: Any) -> bool:
    """Whether ``obj`` has every attribute of the DFA duck type (:data:`DFA_ATTRIBUTES`)."""
    return all(hasattr(obj, a) for a in DFA_ATTRIBUTES)


def to_dfa(spec: Any, atoms: Sequence[str] | None = None):
    """The DFA of ``spec``: a DFA (duck type) as is, an LTLf formula (str or Formula) through
    :func:`~robust_imdp.spec.dfa.ltlf_to_dfa` with alphabet order ``atoms`` (default: the
    formula's atoms, sorted).  ``atoms`` is not used for a DFA (it has its own)."""
    if is_dfa(spec):
        return spec
    if isinstance(spec, (str,) + get_args(Formula)):
        return ltlf_to_dfa(spec, atoms)
    raise InvalidInputError(f"a specification must be an LTLf formula (str) or a DFA (with "
                            f"{', '.join(DFA_ATTRIBUTES)}); got {type(spec).__name__}")


__all__ = ["to_dfa", "is_dfa", "DFA_ATTRIBUTES", "classify", "resolve_semantics", "check_reading", "SpecKind",
           "SEMANTICS"]
