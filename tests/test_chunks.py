"""Chunked stages (issue 10): the result is the same bytes for any chunking and any number of
workers (in process, a real two-process Dask LocalCluster), finished chunks survive an
interruption, and the pre-flight check refuses a run that cannot fit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from robust_imdp.pipeline import bound_rkhs as pl_bound_rkhs
from robust_imdp.pipeline import parallel
from robust_imdp.abstraction.rows import CellBounds, abstract, abstract_rows, assemble_abstraction
from robust_imdp.casestudies.systems import get_case_study
from robust_imdp.cli import main
from robust_imdp.errors import ResourceError
from robust_imdp.models.geometry import Box, Partition
from robust_imdp.io.files import result_to_dict
from robust_imdp.models.noise import TruncatedGaussianNoise
from robust_imdp.pipeline.preflight import estimate_resources
from robust_imdp.pipeline.problem import Problem
from robust_imdp.pipeline.run import synthesize_from_data
from robust_imdp.models.system import AffineMap, Dataset

CASE = get_case_study("three_mode_linear")


def problem(cell=0.5, n=40):
    sysm = CASE.system
    x, u, xn = sysm.sample_dataset(n, CASE.lower, CASE.upper, rng=3)
    return Problem(
        space_lower=np.array(CASE.lower), space_upper=np.array(CASE.upper), cell_size=np.array([cell, cell]),
        regions=CASE.regions, formula="G !obs & F des", threshold=0.9, horizon=None,
        data=Dataset(x, u, xn, modes=sysm.mode_names), mode_names=sysm.mode_names,
        maps=tuple(AffineMap.zero(2) for _ in range(3)), noise=TruncatedGaussianNoise(sysm.sigma, sysm.bound),
        rkhs_bound=CASE.rkhs_bound, gp_options={"lengthscale": 2.0}, misspecification=CASE.misspecification)


def canonical(res) -> str:
    """result.json without the timings (also the margins' seconds) and the advice (the contract: identical bytes otherwise). The advice is
    left out because its default budget is a share of the run's wall time, so which levers it estimates depends
    on the machine's load; its estimates themselves are compared on a two-process cluster in test_advice."""
    doc = result_to_dict(res)
    doc.pop("timings")
    doc.get("diagnostics", {}).pop("advice", None)
    doc.get("diagnostics", {}).get("margins", {}).pop("seconds", None)
    return json.dumps(doc, sort_keys=True)


def test_abstraction_rows_in_chunks_equal_the_whole():
    rng = np.random.default_rng(0)
    part = Partition(Box([-1.0, -1.0], [1.0, 1.0]), [0.25, 0.25], [])
    c = 0.5 * (part.cells_lower + part.cells_upper)
    lo = np.stack([c * 0.7 - 0.05, c[:, ::-1] * 0.9 - 0.1]) + rng.uniform(-0.02, 0.0, (2, part.n_cells, 2))
    hi = lo + rng.uniform(0.02, 0.3, lo.shape)
    cb = CellBounds(lo, hi, None)
    noise = TruncatedGaussianNoise([0.05, 0.05], [0.1, 0.1])
    whole = abstract(part, cb, noise)
    pieces = [abstract_rows(part, CellBounds(lo[:, s:s + 5], hi[:, s:s + 5], None), noise)
              for s in range(0, part.n_cells, 5)]
    chunked = assemble_abstraction(part, pieces)
    for name in ("state_ptr", "row_ptr", "col", "lower", "upper", "floor"):
        np.testing.assert_array_equal(getattr(chunked.imdp, name), getattr(whole.imdp, name), err_msg=name)
    np.testing.assert_array_equal(chunked.containing_cell, whole.containing_cell)
    with pytest.raises(Exception, match="cover"):
        assemble_abstraction(part, pieces[:-1])


@pytest.mark.slow
def test_result_identical_for_any_chunking_and_threads():
    p = problem()
    base = canonical(synthesize_from_data(p, progress=False, workers=1))
    assert canonical(synthesize_from_data(p, progress=False, workers=1, chunk_cells=16)) == base
    assert canonical(synthesize_from_data(p, progress=False, workers=1, chunk_cells=48)) == base
    # in process with two numba threads (what workers=None picks for small work)
    with parallel.InProcess(threads=2) as sched:
        assert sched.n_workers == 2  # cores in use
    two = synthesize_from_data(p, progress=False, workers=None, chunk_cells=32)
    assert canonical(two) == base


@pytest.mark.slow
def test_result_identical_on_a_two_process_local_cluster():
    # A real distributed.LocalCluster with 2 single-threaded worker processes (the CI's one Dask
    # test): the data are scattered once, chunks run in any order, the bytes are the same.
    distributed = pytest.importorskip("distributed")  # a declared dependency; skip only if broken
    p = problem()
    base = canonical(synthesize_from_data(p, progress=False, workers=1))
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=50) as cluster, distributed.Client(cluster) as client:
        res = synthesize_from_data(p, progress=False, client=client, chunk_cells=16)
        assert len(client.scheduler_info()["workers"]) == 2
    assert canonical(res) == base


def test_resume_computes_only_the_missing_chunks(tmp_path, monkeypatch):
    p = problem()
    calls = []
    import robust_imdp.pipeline.run as pl

    real = pl_bound_rkhs._bound_task

    def counted(*args, **kwargs):  # call 1 is the pre-flight pilot block, then the chunks
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(pl_bound_rkhs, "_bound_task", counted)
    with pytest.raises(KeyboardInterrupt):  # a Ctrl-C during the third chunk
        synthesize_from_data(p, progress=False, abstraction_cache=tmp_path, chunk_cells=16, workers=1)
    assert len(list(tmp_path.glob("bounds-*.parts/m*.npz"))) == 2
    calls.clear()
    monkeypatch.setattr(pl_bound_rkhs, "_bound_task", lambda *a, **k: (calls.append(1), real(*a, **k))[1])
    res = synthesize_from_data(p, progress=False, abstraction_cache=tmp_path, chunk_cells=16, workers=1)
    assert len(calls) == 1 + 3 * 4 - 2  # the pilot + 3 modes x 4 chunks of 16 cells, 2 already saved
    monkeypatch.undo()
    assert canonical(res) == canonical(synthesize_from_data(p, progress=False, workers=1))


def test_preflight_refuses_a_grid_that_cannot_fit(capsys):
    p = problem(cell=0.0005)  # 64 million cells by mistake
    est = estimate_resources(p)
    assert est["n_cells"] == 8000 ** 2 and est["bytes"] > 1e11
    with pytest.raises(ResourceError, match=r"64,000,000 cells x 3 modes need about .* GB.*coarser"):
        synthesize_from_data(p, progress=False)


def test_estimate_scales_with_the_grid():
    small, big = estimate_resources(problem(cell=0.5)), estimate_resources(problem(cell=0.25))
    assert big["n_cells"] == 4 * small["n_cells"] == 256
    assert big["bytes"] > small["bytes"]


def test_open_scheduler_rules():
    s = parallel.open_scheduler(workers=1)
    assert isinstance(s, parallel.InProcess) and s.threads == 1
    s = parallel.open_scheduler(workers=None)  # the default never starts processes
    assert isinstance(s, parallel.InProcess) and s.threads == parallel.local_cores()
    with pytest.raises(ValueError, match="workers must be a positive integer"):
        parallel.open_scheduler(workers=0)
    with pytest.raises(ValueError, match="scheduler must be an address"):
        parallel.open_scheduler(scheduler="localhost")


def test_cli_interrupt_exits_130_with_one_line(tmp_path, capsys, monkeypatch):
    import robust_imdp.pipeline.run as pl

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(pl, "synthesize_from_data", interrupted)
    (tmp_path / "p.toml").write_text("")
    from robust_imdp.casestudies.systems import write_problem_files

    path = write_problem_files("three_mode_linear", tmp_path)
    code = main(["run", str(path), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 130
    assert err.count("\n") == 1 and "interrupted" in err and "run the same command again" in err
