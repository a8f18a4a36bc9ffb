"""Plain JSON values from numpy-bearing structures (no robust_imdp imports: usable by every layer).

The result file (``io.result_to_dict``), the cache's diagnostics (``pipeline``) and the
validation report (``cli``) all go through :func:`jsonable`, so they write the same numbers.
"""

from __future__ import annotations

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
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj
