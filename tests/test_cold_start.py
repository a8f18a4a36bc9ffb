"""The first run in a fresh clone: numba kernels cached, a warm-up step, an honest pre-flight estimate.

The pre-flight estimate of the bound stage is checked with a deterministic cost model instead of
a clock: ``rkhs.bound_chunk`` computes its real result but reports ``seconds`` from a fixed cost
per cell, and the first call of a run (where numba compiles or loads the kernels) reports a huge
time. The estimate must then equal the tasks' reported time, whatever the first call costs and
however badly the threads scale.
"""

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from robust_imdp.bounds import rkhs
from robust_imdp.errors import InvalidInputError
from robust_imdp.pipeline.run import synthesize_from_data
from robust_imdp.bounds.rkhs import CELL_BLOCK

from test_chunks import problem

COMPILE_S = 1000.0  # what the first call of a run reports (compiling the kernels)


def fake_cost(monkeypatch, per_cell: float):
    """Make ``bound_chunk`` report ``per_cell`` s per cell (whatever its threads: no speed-up) and
    COMPILE_S on its first call; returns the list of (n_cells, threads, reported seconds) calls."""
    real = rkhs.bound_chunk
    calls = []

    def timed(*args, threads=None, **kwargs):
        out = real(*args, threads=threads, **kwargs)
        k = int(np.shape(args[4])[0])
        out["seconds"] = COMPILE_S if not calls else per_cell * k
        calls.append((k, threads, out["seconds"]))
        return out

    monkeypatch.setattr(rkhs, "bound_chunk", timed)
    return calls


def estimate(err: str) -> float:
    """The "about X s on N cores" of the bound stage's pre-flight line."""
    m = re.search(r"pre-flight: .* cell bounds; about \d+ s of work .*, about (\d+) s on \d+ cores?", err)
    assert m, err
    return float(m.group(1))


def sizes(err: str):
    m = re.search(r"pre-flight: ([\d,]+) cells x (\d+) modes x \d+ outputs = ", err)
    return int(m.group(1).replace(",", "")), int(m.group(2))


@pytest.mark.parametrize("workers", [1, None])  # in process on 1 thread / on numba threads on all cores
def test_preflight_estimate_is_not_polluted_by_compilation(monkeypatch, capsys, workers):
    calls = fake_cost(monkeypatch, per_cell=1.0)
    synthesize_from_data(problem(cell=0.5), workers=workers, chunk_cells=16)
    err = capsys.readouterr().err
    N, M = sizes(err)
    assert calls[0][2] == COMPILE_S and calls[0][0] == 1  # the compiling call: one cell, not timed
    # the tasks (N x M cells and modes at 1 s each) run one after another in process: the stage
    # takes N * M s of reported time; printed to whole seconds. Before: the compiling call was
    # the pilot (1000 s / 16 cells), an estimate 60x too high.
    assert estimate(err) == pytest.approx(N * M * 1.0, abs=0.5)


def test_pilot_runs_on_the_threads_of_the_tasks(monkeypatch, capsys):
    # threads that give no speed-up (a loaded machine): the old rule, a 1-thread pilot divided by
    # the cores, said half the tasks' time on 2 cores
    calls = fake_cost(monkeypatch, per_cell=1.0)
    synthesize_from_data(problem(cell=0.5), workers=None, chunk_cells=16)
    err = capsys.readouterr().err
    N, M = sizes(err)
    threads = calls[-1][1]
    assert calls[1][1] == threads and calls[1][0] == min(N, CELL_BLOCK * threads)  # the pilot
    assert estimate(err) == pytest.approx(N * M * 1.0, abs=0.5)


def test_every_kernel_is_cached_on_disk():
    from numba.core.caching import NullCache

    from robust_imdp.warmup import kernels

    ks = kernels()
    assert len(ks) > 30 and {"solvers.solve_components", "bounds._optimal_cells_coef", "bounds._local_cells_into"} <= set(ks)
    uncached = [name for name, d in ks.items() if isinstance(d._cache, NullCache)]
    assert uncached == []  # a kernel without cache=True compiles again in every process


def test_warmup_rejects_an_unknown_case():
    from robust_imdp.warmup import warm

    with pytest.raises(InvalidInputError, match=r"warm-up cases must be among optimal, .*; got 'fast'"):
        warm(["optimal", "fast"])


@pytest.mark.slow
def test_warmup_solver_case_reaches_every_solver_path():
    # in a fresh process (kernels loaded from the cache, or compiled): the "solver" case must
    # type the end-component (deflation), floor and wide-row kernels, which the small pipeline runs miss
    code = (
        "import json\n"
        "from robust_imdp import warmup\n"
        "warmup.warm(['solver'], progress=False)\n"
        "ks = warmup.kernels()\n"
        "need = ['solvers.stay_exit_bounds', 'solvers.response_end_components', 'solvers.dd_prefix',"
        " 'solvers.solve_components', 'solvers.bellman_layer', 'solvers.fill_local_order']\n"
        "print(json.dumps({'untyped': [k for k in need if not ks[k].signatures],"
        " 'perm_dtypes': sorted({str(s[1].dtype) for s in ks['solvers.fill_local_order'].signatures})}))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    doc = json.loads(out.strip().splitlines()[-1])
    assert doc["untyped"] == []
    # successor orders of rows up to 256 / 65536 entries (uint8 / uint16): both specialisations
    assert doc["perm_dtypes"] == ["uint16", "uint8"]
