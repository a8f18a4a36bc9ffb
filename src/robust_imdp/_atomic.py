"""An atomic counter for numba's parallel kernels: dynamic scheduling of work units on numba's "omp" layer.

numba's ``prange`` splits its iterations statically on the "omp" threading layer, also under
``numba.parallel_chunksize(n)`` (the chunks of ``n`` iterations are dealt out round-robin, not taken as threads
come free). When the units' costs differ (the bound kernels' active-set iterations), a static split leaves one
thread idle at the end of every call: on a 4,096-cell slice of the 2-D benchmark the two lanes of the cyclic split
had 1.21 s and 1.57 s of work (the cells' costs alternate with the grid's period). With :func:`fetch_add`, a kernel
runs ``prange`` over its lanes and every lane takes the next unit from a shared counter until none is left::

    counter = np.zeros(1, dtype=np.int64)
    for t in numba.prange(lanes):
        while True:
            j = fetch_add(counter, 0, 1)
            if j >= n_units:
                break
            ...  # unit j

Every unit is taken exactly once (the read-modify-write is one atomic instruction); which lane takes it cannot
change a number where the units are independent (their own workspaces, results in their own slots).

numba's parfor passes do not see the counter's write (an intrinsic has no declared effects): a read of
``counter[0]`` after the ``prange`` in the same function may be moved before the loop (it returned 0 in a test).
The counter is for taking units only; the kernels never read it after the loop.
"""

from __future__ import annotations

from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


@intrinsic
def fetch_add(typingctx, counters, index, value):
    """``old = counters[index]; counters[index] += value; return old`` as one atomic instruction (int64 array).

    Sequentially consistent (LLVM ``atomicrmw add ... seq_cst``); no bounds check (the callers index a counter
    array of their own)."""
    if not (isinstance(counters, types.Array) and counters.dtype == types.int64 and counters.ndim == 1):
        return None
    if not (isinstance(index, types.Integer) and isinstance(value, types.Integer)):
        return None
    sig = types.int64(counters, index, value)

    def codegen(context, builder, signature, args):
        ary_t, idx_t, val_t = signature.args
        ary = context.make_array(ary_t)(context, builder, args[0])
        idx = context.cast(builder, args[1], idx_t, types.intp)
        val = context.cast(builder, args[2], val_t, types.int64)
        ptr = cgutils.get_item_pointer(context, builder, ary_t, ary, [idx], wraparound=False)
        return builder.atomic_rmw("add", ptr, val, "seq_cst")

    return sig, codegen
