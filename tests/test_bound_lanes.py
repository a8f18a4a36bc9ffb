"""The bound stage's work on every core, with the same bits (docs/ARCHITECTURE.md, the bound kernels):

* the kernels' lanes take their blocks of cells from a shared counter as they come free (``rkhs_model._lanes``,
  ``_atomic.fetch_add``; the counter itself: ``test_atomic.py``): any number of lanes gives the same arrays, for the local kernel (``_local_cells_coef``) and the global one (``_optimal_cells_coef``);
* the local pools come from a k-d tree kept per process and a query split over the threads: the same indices as a
  fresh ``cKDTree`` queried on one thread;
* eq. C's combination of the vertex values takes every output of a chunk in one call: the same bits as one output
  at a time (the soundness of eq. C itself is checked in ``test_rkhs.py`` / ``test_rkhs_local.py``);
* the bound chunks are saved beside the stage (``bound_rkhs._PartWriter``): every chunk computed is on disk when the
  stage ends, and a failed write stops the stage with its error, as before.
"""

from __future__ import annotations

import time

import numba
import numpy as np
import pytest

from robust_imdp.bounds import rkhs, rkhs_local
from robust_imdp.bounds.rkhs_model import _blocks, _combine_vertices, scaled_ranges


def _cells(rng, n_cells: int, d: int, width: float = 0.3):
    lo = rng.uniform(-1.0, 1.0, (n_cells, d))
    return lo, lo + width


def _local_inputs(seed: int = 0, n_cells: int = 80, d: int = 2, m: int = 120, k: int = 12):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1.5, 1.5, (m, d))
    Y = np.column_stack([np.sin(2 * X[:, 0]), np.cos(X[:, -1])]) + rng.uniform(-0.01, 0.01, (m, 2))
    lo, up = _cells(rng, n_cells, d)
    ls = np.full(d, 0.8)
    c, r = rkhs.cell_centres(lo, up)
    signs = rkhs.vertex_signs(d)
    pools = rkhs_local.local_pools(X, lo, up, ls, k)
    one = np.arange(n_cells, dtype=np.int64)
    ptr = _blocks(n_cells, one, n_cells, rkhs.CELL_BLOCK)
    lin = np.zeros((n_cells, signs.shape[0], 2))
    inv_l2 = rkhs._inv_l2(ls, d)
    return (rkhs._writable(X), rkhs._writable(Y), inv_l2, c, r, signs, pools), ptr, one, lin


@pytest.mark.parametrize("optimal", [True, False])
def test_local_kernel_same_bits_for_any_number_of_lanes(optimal):
    args, ptr, group, lin = _local_inputs()
    assert ptr.shape[0] - 1 >= 5  # several blocks, so lanes matter
    common = (1e-4, np.array([0.02, 0.02]), np.zeros(2), 1.3, optimal, 2000, 1e-9, ptr, group, lin)
    ref = rkhs_local._local_cells_coef(*args, *common, 1)
    for lanes in (2, 3, 7, 64):  # 64 > blocks: capped at the blocks
        out = rkhs_local._local_cells_coef(*args, *common, lanes)
        for a, b in zip(ref, out):
            np.testing.assert_array_equal(a, b)


def test_global_kernel_same_bits_for_any_number_of_lanes():
    rng = np.random.default_rng(1)
    d, m, n_cells = 2, 40, 70
    X = rng.uniform(-1.5, 1.5, (m, d))
    y = np.sin(2 * X[:, 0]) + rng.uniform(-0.01, 0.01, m)
    model = rkhs.KernelModel(X, y, 0.8)
    lo, up = _cells(rng, n_cells, d)
    c, r = rkhs.cell_centres(lo, up)
    signs = rkhs.vertex_signs(d)
    one = np.arange(n_cells, dtype=np.int64)
    ptr = _blocks(n_cells, one, n_cells, rkhs.CELL_BLOCK)
    lin = np.zeros((n_cells, signs.shape[0]))
    common = (model.X, model.y, model.K, model.K_err, model.inv_l2, c, r, signs, 0.02, 1.3, m, 2000, 1e-9, ptr,
              lin, True, one)
    ref = rkhs._optimal_cells_coef(*common, 1)
    for lanes in (2, 3, 5):
        for a, b in zip(ref, rkhs._optimal_cells_coef(*common, lanes)):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("lanes", [1, 2, 3])
def test_local_kernel_counts_every_block_of_every_piece(lanes):
    # the thread beside the kernel starts eq. C of a piece when its count is full: every block counted once, in its
    # own piece (piece = block // piece_blocks), and the values the same as one piece
    args, ptr, group, lin = _local_inputs()
    n_blocks = ptr.shape[0] - 1
    common = (1e-4, np.array([0.02, 0.02]), np.zeros(2), 1.3, True, 2000, 1e-9, ptr, group, lin)
    ref = rkhs_local._local_cells_coef(*args, *common, 1)
    out = [np.empty_like(ref[0]), np.zeros_like(ref[1]), np.empty_like(ref[2])]
    done = np.zeros(-(-n_blocks // 2), dtype=np.int64)
    rkhs_local._local_cells_into(*args, *common, lanes, *out, done, 2)
    expect = [min(2, n_blocks - 2 * p) for p in range(done.shape[0])]
    assert [rkhs_local._blocks_done(done, p) for p in range(done.shape[0])] == expect
    for a, b in zip(ref, out):
        np.testing.assert_array_equal(a, b)


def test_local_pools_same_as_a_fresh_tree_on_one_thread():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(2)
    X = rng.uniform(-2, 2, (500, 3))
    ls = np.array([4.0, 1.5, 1.5])
    lo, up = _cells(rng, 300, 3, 0.1)
    scale = np.sqrt(rkhs._inv_l2(ls, 3))
    _, want = cKDTree(X * scale).query(0.5 * (lo + up) * scale, k=20, workers=1)
    for _ in range(2):  # the second call takes the kept tree
        np.testing.assert_array_equal(rkhs_local.local_pools(X, lo, up, ls, 20), want)
    assert rkhs_local._tree(X * scale) is rkhs_local._tree(np.array(X * scale))  # kept per bytes, not per object
    X2 = X.copy()
    X2[0, 0] += 1e-9  # other bytes: another tree
    assert rkhs_local._tree(X2 * scale) is not rkhs_local._tree(X * scale)


def test_combine_vertices_all_outputs_in_one_call_same_bits():
    rng = np.random.default_rng(3)
    n_out, N, V = 3, 50, 8
    lin_v = rng.normal(size=(n_out, N, V))
    lin_err = np.abs(rng.normal(size=(n_out, N, V))) * 1e-15
    su = rng.normal(size=(n_out, N, V)) + 1.0
    sl = su - np.abs(rng.normal(size=(n_out, N, V)))
    cu, cl = np.abs(rng.normal(size=(2, n_out, N, V)))
    t_max = rng.uniform(0.0, 0.5, N)
    lo, up, tay = _combine_vertices(lin_v, lin_err, su, sl, t_max, 1.7, 1e-3)
    starts = np.arange(0, N, 5)
    s_lo, s_up = scaled_ranges(lin_v, lin_err, su, sl, cu, cl, t_max, 1.7, 1e-3, [2.0, 3.5], starts)
    assert s_lo.shape == (2, n_out, len(starts))
    for i in range(n_out):
        one = _combine_vertices(lin_v[i], lin_err[i], su[i], sl[i], t_max, 1.7, 1e-3)
        for a, b in zip((lo[i], up[i], tay[i]), one):
            np.testing.assert_array_equal(a, b)
        o_lo, o_up = scaled_ranges(lin_v[i], lin_err[i], su[i], sl[i], cu[i], cl[i], t_max, 1.7, 1e-3, [2.0, 3.5],
                                   starts)
        np.testing.assert_array_equal(s_lo[:, i], o_lo)
        np.testing.assert_array_equal(s_up[:, i], o_up)


def test_part_writer_keeps_every_chunk_and_raises_a_failed_write(tmp_path, monkeypatch):
    from robust_imdp.pipeline import bound_rkhs
    from robust_imdp.pipeline.cache import _load_npz

    w = bound_rkhs._PartWriter()
    for j in range(3 * w.QUEUED):  # more than the queue holds: put waits, nothing is dropped
        w.put(tmp_path / f"c{j}.npz", {"lower": np.full((2, 3), float(j))})
    w.close()
    for j in range(3 * w.QUEUED):
        np.testing.assert_array_equal(_load_npz(tmp_path / f"c{j}.npz")["lower"], np.full((2, 3), float(j)))

    def broken(path, write):
        raise OSError(f"disk full writing {path}")

    monkeypatch.setattr(bound_rkhs, "write_cache_entry", broken)
    w = bound_rkhs._PartWriter()
    w.put(tmp_path / "x.npz", {"lower": np.zeros((1, 1))})
    with pytest.raises(OSError, match="disk full"):
        w.close()
    w = bound_rkhs._PartWriter()
    w.put(tmp_path / "y.npz", {"lower": np.zeros((1, 1))})
    for _ in range(200):  # the failure reaches the next put (the stage stops at its next chunk)
        if w.error is not None:
            break
        time.sleep(0.01)
    with pytest.raises(OSError, match="disk full"):
        w.put(tmp_path / "z.npz", {"lower": np.zeros((1, 1))})
    w.close(raise_error=False)  # a stage already stopping by another error keeps that one


def test_grid_chunk_larger_in_process_only():
    from robust_imdp.pipeline import bound_rkhs
    from robust_imdp.pipeline.runtime import _Run, _chunk_cells

    assert bound_rkhs._grid_chunk(_Run()) == bound_rkhs.CHUNK_CELLS_IN_PROCESS  # all cores, in process
    assert bound_rkhs._grid_chunk(_Run(workers=1)) == bound_rkhs.CHUNK_CELLS_IN_PROCESS
    assert bound_rkhs._grid_chunk(_Run(workers=2)) == bound_rkhs.CHUNK_CELLS  # a local Dask cluster
    assert bound_rkhs._grid_chunk(_Run(scheduler="tcp://h:8786")) == bound_rkhs.CHUNK_CELLS
    assert bound_rkhs._grid_chunk(_Run(client=object())) == bound_rkhs.CHUNK_CELLS
    run = _Run(chunk_cells=48)  # the run's own chunk_cells wins
    assert _chunk_cells(run, 10_000, bound_rkhs._grid_chunk(run)) == 48
    assert bound_rkhs.CHUNK_CELLS_IN_PROCESS % rkhs.CELL_BLOCK == 0  # whole blocks: the same bits as any chunking


@pytest.mark.parametrize("method", ["optimal", "ridge"])
def test_local_chunk_in_pieces_same_bits_as_in_one(monkeypatch, method):
    # on several threads a chunk's eq. C runs piece by piece (rkhs_local._cells_piece) in a thread beside the chunk's
    # one kernel call, each piece once its blocks are written; forced here with 3 lanes and pieces of 2 blocks, with
    # sub-boxes, the iid event and the margins' scales
    rng = np.random.default_rng(4)
    d, m = 2, 150
    X = rng.uniform(-1.5, 1.5, (m, d))
    Y = np.column_stack([np.sin(2 * X[:, 0]), X[:, 1] ** 2]) + rng.uniform(-0.01, 0.01, (m, 2))
    lo, up = _cells(rng, 90, d, 0.4)
    kw = dict(lengthscale=0.7, rkhs_bound=2.0, noise_bound=0.01, misspecification=1e-3, method=method,
              iid_factor=2.5, iid_theta=0.005, local_points=12, local_lambda=1e-4, split_tol=2e-3,
              scales=(1.5, 3.0))
    A, b = np.eye(2), np.array([0.1, -0.2])
    monkeypatch.setattr(rkhs_local, "_lanes", lambda: 1)
    one = rkhs.bound_chunk(X, Y, A, b, lo, up, **kw)
    monkeypatch.setattr(rkhs_local, "_lanes", lambda: 3)
    monkeypatch.setattr(rkhs_local, "PIECE_BLOCKS", 2)
    calls = []
    real = rkhs_local._cells_piece
    monkeypatch.setattr(rkhs_local, "_cells_piece", lambda *a: (calls.append(1), real(*a))[1])
    pieces = rkhs.bound_chunk(X, Y, A, b, lo, up, **kw)
    assert len(calls) == 3  # 90 cells: blocks of 16 -> 6 blocks -> 3 pieces
    for key in ("lower", "upper", "eps", "support", "scaled_lower", "scaled_upper"):
        np.testing.assert_array_equal(pieces[key], one[key], err_msg=key)


def test_a_kernel_that_leaves_a_piece_unwritten_is_an_error_not_a_hang(monkeypatch):
    # the thread beside the kernel waits for each piece's count; once the kernel has returned, a count short of
    # the piece's blocks can never fill: an error (never eq. C of unwritten values, never a wait without end)
    rng = np.random.default_rng(5)
    d, m = 2, 100
    X = rng.uniform(-1.5, 1.5, (m, d))
    Y = np.sin(2 * X[:, :1]) + rng.uniform(-0.01, 0.01, (m, 1))
    lo, up = _cells(rng, 90, d, 0.4)
    monkeypatch.setattr(rkhs_local, "_lanes", lambda: 3)
    monkeypatch.setattr(rkhs_local, "PIECE_BLOCKS", 2)
    monkeypatch.setattr(rkhs_local, "_local_cells_into", lambda *a: None)  # writes nothing, counts nothing
    with pytest.raises(RuntimeError, match="without writing every block of piece 0"):
        rkhs.bound_chunk(X, Y, np.eye(2)[:1], np.zeros(1), lo, up, lengthscale=0.7, rkhs_bound=2.0,
                         noise_bound=0.01, method="optimal", local_points=12)
