"""The BLAS thread count of this process: :func:`blas_threads`.

LAPACK's factorisations (``np.linalg.solve``'s LU, Cholesky, ``eigh``) split their work by the BLAS
library's thread count, and the bits of their results depend on it: the data fit of the diagnostics,
the advice and the nominal model (``bounds.fit``) came out different on one core and on two. A run
therefore holds BLAS to one thread (:func:`robust_imdp.pipeline.run.synthesize_from_data`), as its
helper processes (``pipeline.parallel.SIDE_ENV``) and a Dask cluster's workers already are: the
same bits on any number of cores. The run's parallel work is its own (numba threads, tasks), so
nothing is lost, and no BLAS threads spin beside the numba ones.

How: the environment variables (read by a BLAS library when it is loaded, e.g. scipy's own
OpenBLAS on the first ``import scipy.linalg``) and, for the libraries already loaded, their
``*_set_num_threads`` entry points, found among the process's shared objects (``/proc/self/maps``;
elsewhere only the variables apply). Both are restored on exit.
"""

from __future__ import annotations

import contextlib
import ctypes
import os

__all__ = ["blas_threads", "quiet_openmp_waits", "OMP_SPIN"]

#: The variables BLAS libraries read for their thread count when they are loaded (not ``OMP_NUM_THREADS``:
#: numba's OpenMP threading layer would read it too).
BLAS_ENV = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")

#: (set, get) entry points by library family: OpenBLAS (plain, 64-bit-integer and scipy's builds) and MKL.
_ENTRY_POINTS = (("openblas_set_num_threads", "openblas_get_num_threads"),
                 ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
                 ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
                 ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
                 ("MKL_Set_Num_Threads", "MKL_Get_Max_Threads"))


def _loaded() -> list:
    """(set, get) ctypes functions of every BLAS library loaded in this process (Linux; [] elsewhere)."""
    try:
        with open("/proc/self/maps") as f:
            paths = sorted({line.split()[-1] for line in f
                            if line.rstrip().split()[-1].startswith("/")
                            and any(k in line.lower() for k in ("openblas", "mkl_rt", "libmkl"))})
    except OSError:
        return []
    out = []
    for p in paths:
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        for set_name, get_name in _ENTRY_POINTS:
            if hasattr(lib, set_name) and hasattr(lib, get_name):
                setter, getter = getattr(lib, set_name), getattr(lib, get_name)
                setter.restype, getter.restype = None, ctypes.c_int
                setter.argtypes = [ctypes.c_int]
                out.append((setter, getter))
                break
    return out


@contextlib.contextmanager
def blas_threads(n: int = 1):
    """Within the block, BLAS libraries use ``n`` threads: those loaded (their entry points) and those loaded
    during the block (the environment variables). On exit the variables and the loaded libraries' counts are
    restored; a library first loaded within the block keeps ``n``."""
    n = int(n)
    old_env = {k: os.environ.get(k) for k in BLAS_ENV}
    libs = _loaded()
    old = [getter() for _, getter in libs]
    for k in BLAS_ENV:
        os.environ[k] = str(n)
    for setter, _ in libs:
        setter(n)
    try:
        yield
    finally:
        for (setter, _), c in zip(libs, old):
            setter(c)
        for k, v in old_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


#: How long an idle OpenMP thread of numba's threading layer (GNU libgomp) spins before it sleeps, in spin
#: iterations (libgomp's default is 300,000, milliseconds): a run's side work (the check, the nominal model, the
#: margins, the figures) runs in helper processes beside the numba stages, and threads spinning at the end of
#: every parallel region took their cores (the bound stage's CPU seconds on 2 threads: +10-15 % spinning,
#: benchmarks/results/serial_parts.md). 10,000 iterations still catch back-to-back regions (a solver's sweeps).
OMP_SPIN = "10000"


def quiet_openmp_waits() -> bool:
    """Set ``GOMP_SPINCOUNT`` to :data:`OMP_SPIN` unless the user set it (``OMP_WAIT_POLICY`` too: it decides the
    spinning then); libgomp reads it when it is loaded, at a process's first parallel numba kernel, so it applies
    only where none ran yet. Returns whether the variable is now this module's value."""
    if "GOMP_SPINCOUNT" in os.environ or "OMP_WAIT_POLICY" in os.environ:
        return os.environ.get("GOMP_SPINCOUNT") == OMP_SPIN
    os.environ["GOMP_SPINCOUNT"] = OMP_SPIN
    return True
