"""Plain JSON values from numpy-bearing structures (no robust_imdp imports: usable by every layer).

The result file (``io.result_to_dict``), the cache's diagnostics (``pipeline``) and the
validation report (``cli``) all go through :func:`jsonable`, so they write the same numbers.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["jsonable"]


def jsonable(obj):
    """``obj`` with numpy arrays and scalars turned into lists and Python numbers.

    Dicts get ``str`` keys, tuples become lists, and non-finite floats become ``None`` (JSON has
    no NaN or infinity). Anything else is returned as it is (``json.dumps`` then refuses what it
    cannot write).

    >>> jsonable({1: np.array([0.5, np.inf]), "n": np.int64(3), "t": (np.float64(0.25), "a")})
    {'1': [0.5, None], 'n': 3, 't': [0.25, 'a']}
    """
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _array(obj)
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _array(a: np.ndarray):
    """``jsonable(a.tolist())`` without walking the list where the dtype says what ``tolist`` gives.

    ``tolist`` of a bool, int, unsigned or str array gives Python bools, ints and strs (nothing to change); of a
    float16/32/64 array Python floats, of which the non-finite ones become ``None`` (set on an object copy,
    whose ``tolist`` keeps the other floats, -0.0 included). Every other array (object, complex, bytes, dates,
    long double, subclasses such as masked arrays) takes the element-wise route.
    """
    kind = a.dtype.kind
    if type(a) is np.ndarray and kind in "biuUf" and not (kind == "f" and a.dtype.itemsize > 8):
        if kind == "f":
            finite = np.isfinite(a)
            if not finite.all():
                out = a.astype(object)
                out[~finite] = None
                return out.tolist()
        return a.tolist()
    return jsonable(a.tolist())
