"""The run's cache: checksummed entries, fsync before rename, the cached assumption check, resume ETA."""

import os
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from robust_imdp.pipeline import bound_rkhs as pl_bound_rkhs
from robust_imdp.pipeline import bound_stage as pl_bound_stage
from robust_imdp.pipeline import cache as pl_cache
from robust_imdp.pipeline import preflight as pl_preflight
from robust_imdp.pipeline import runtime as pl_runtime
import robust_imdp.pipeline.run as pipeline
import robust_imdp.bounds.rkhs as rkhs
from robust_imdp.errors import RobustImdpWarning
from robust_imdp.io.files import load_problem
from problem_texts import write_one_d



@pytest.fixture
def problem(tmp_path):
    # x+ = 0.5 x + 1 + 0.1 sin(x) + v: 16 cells, 30 points (seeded)
    write_one_d(tmp_path)
    return load_problem(tmp_path / "p.toml")


def _run(problem, cache, **kw):
    return pipeline.synthesize_from_data(problem, progress=False, abstraction_cache=cache, **kw)


@pytest.fixture
def count_checks(monkeypatch):
    calls = []
    real = rkhs.check_assumption

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(rkhs, "check_assumption", counted)
    return calls


# --------------------------------------------------------------------------- the assumption check
def test_the_assumption_check_is_cached_under_the_data_and_assumption_key(problem, tmp_path, count_checks):
    cache = tmp_path / "cache"
    first = _run(problem, cache)
    assert len(count_checks) == 1
    # a new grid: new bounds, same data and assumption -> the check is not run again
    finer = _run(problem.replace(cell_size=np.array([0.125])), cache)
    assert len(count_checks) == 1
    assert finer.diagnostics["assumption"]["min_norm"] == first.diagnostics["assumption"]["min_norm"]
    # a resume (bound chunks saved, the bounds file not written yet) does not run it either
    for f in cache.glob("abstraction-*"):
        f.unlink()
    for f in cache.glob("bounds-*.npz*"):
        f.unlink()
    again = _run(problem, cache)
    assert len(count_checks) == 1
    np.testing.assert_array_equal(again.synthesis.p_low, first.synthesis.p_low)
    # another assumption (B) or other data: the check runs
    _run(problem.replace(rkhs_bound=2.0), cache)
    assert len(count_checks) == 2
    d = problem.data
    moved = type(d)(d.x, d.u, d.x_next + 1e-4, modes=d.modes)
    _run(problem.replace(data=moved), cache)
    assert len(count_checks) == 3


def test_check_key_ignores_the_grid_and_formula_but_not_the_assumption(problem):
    k = pl_cache.check_key(problem)
    assert pl_cache.check_key(problem.replace(cell_size=np.array([0.5]), formula="G des", threshold=0.5)) == k
    for change in ({"rkhs_bound": 1.5}, {"misspecification": 0.01}, {"gp_options": {"lengthscale": 0.5}}):
        assert pl_cache.check_key(problem.replace(**change)) != k, change


# --------------------------------------------------------------------------- damaged entries
def _truncate(f):
    f.write_bytes(f.read_bytes()[: f.stat().st_size // 2])


def _flip_last_byte(f):
    b = bytearray(f.read_bytes())
    b[-1] ^= 0xFF
    f.write_bytes(bytes(b))


def _empty(f):
    f.write_bytes(b"")


# (entry to damage, entries to delete so that the damaged one is read)
ENTRIES = [
    ("abstraction-*.npz", []),
    ("abstraction-*.json", []),
    ("bounds-*.npz", ["abstraction-*"]),
    ("bounds-*.parts/m0-c0-*.npz", ["abstraction-*", "bounds-*.npz*"]),
    ("check-*.json", ["abstraction-*", "bounds-*.npz*", "bounds-*.parts/*"]),
]


@pytest.mark.parametrize("entry,delete,damage", [(*ENTRIES[0], d) for d in (_truncate, _flip_last_byte, _empty)]
                         + [(e, d, _truncate) for e, d in ENTRIES[1:]])
def test_a_damaged_cache_entry_gives_one_warning_and_is_computed_again(problem, tmp_path, entry, delete, damage):
    cache = tmp_path / "cache"
    first = _run(problem, cache)
    for pattern in delete:
        for f in cache.glob(pattern):
            f.unlink()
    (target,) = list(cache.glob(entry))
    damage(target)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        again = _run(problem, cache)
    ours = [w for w in seen if issubclass(w.category, RobustImdpWarning) and "cache entry" in str(w.message)]
    assert len(ours) == 1, [str(w.message) for w in seen]
    assert str(target) in str(ours[0].message) and "computing it again" in str(ours[0].message)
    np.testing.assert_array_equal(again.synthesis.p_low, first.synthesis.p_low)
    np.testing.assert_array_equal(again.synthesis.p_up, first.synthesis.p_up)
    assert pl_cache.cache_entry_problem(target) is None  # rewritten, with its checksum
    with warnings.catch_warnings(record=True) as seen:  # and the next run is quiet
        warnings.simplefilter("always")
        _run(problem, cache)
    assert not [w for w in seen if "cache entry" in str(w.message)]


def test_an_entry_without_its_checksum_is_not_trusted(problem, tmp_path):
    cache = tmp_path / "cache"
    _run(problem, cache)
    (f,) = list(cache.glob("abstraction-*.npz"))
    os.unlink(str(f) + ".sha256")
    assert "no readable checksum file" in pl_cache.cache_entry_problem(f)
    with pytest.warns(RobustImdpWarning, match="no readable checksum file"):
        res = _run(problem, cache)
    assert not res.from_cache


def test_cache_entries_are_flushed_to_disk_before_they_are_renamed(problem, tmp_path, monkeypatch):
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    def replace(src, dst, *a, **k):
        events.append(("replace", os.fspath(src)))
        events.append(("into", os.fspath(dst)))
        return real_replace(src, dst, *a, **k)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    cache = tmp_path / "cache"
    _run(problem, cache)
    renamed = [src for kind, src in events if kind == "replace" and str(cache) in src]
    targets = {dst for kind, dst in events if kind == "into"}
    entries = {os.fspath(p) for p in cache.rglob("*") if p.is_file()}
    # every file of the cache (entries and their checksums) was renamed into place (also files renamed and later
    # merged away: the bound stage's chunk parts, written when a chunk finishes, then joined into one entry) ...
    assert len(entries) >= 10 and entries <= targets
    for src in renamed:  # ... after its temporary file was flushed
        i = events.index(("replace", src))
        assert ("fsync", src) in events[:i], src


def test_fsync_only_cannot_leave_an_empty_complete_looking_entry(tmp_path):
    # A crash after the rename but before the data reach the disk could leave an empty file
    # under the final name; here the checksum file says how many bytes must be there.
    f = tmp_path / "e.npz"
    pl_cache.write_cache_entry(f, lambda tmp: np.savez(tmp, a=np.arange(5)))
    assert pl_cache.cache_entry_problem(f) is None
    f.write_bytes(b"")
    assert "0 bytes" in pl_cache.cache_entry_problem(f)
    assert not list(tmp_path.glob(".*part*"))  # no temporary files left


# --------------------------------------------------------------------------- resume ETA
def test_the_eta_after_a_resume_uses_the_rate_of_this_process(problem, tmp_path, monkeypatch, capsys):
    # 16 chunks of 16 cells in 1-D (256 cells); 12 resumed from the cache; each new chunk takes
    # 10 s of a fake clock. After the first new one: 3 chunks left at 10 s each = 30 s. Dividing
    # the elapsed time by all 13 finished chunks said "about 2 s left" (the "3 s left"
    # for a stage that took 72 s).
    p = problem.replace(cell_size=np.array([4.0 / 256]))
    cache = tmp_path / "cache"
    clock = [0.0]
    for module in (pl_runtime, pl_bound_rkhs):  # the stage's clock and the progress line's
        monkeypatch.setattr(module, "time", SimpleNamespace(perf_counter=lambda: clock[0]))
    monkeypatch.setattr(pl_bound_stage, "_check_assumption",
                        lambda problem, data, log, cache_dir=None, run=None: ((rkhs.NormCheck(0, 0, 0.1, 30),), np.array([0.01])))

    def fake_task(X, Y, A, b, lower, upper, local, *, threads=1, **settings):
        clock[0] += 10.0
        k = lower.shape[0]
        return {"lower": np.full((k, 1), 1.0), "upper": np.full((k, 1), 3.0), "eps": np.zeros((k, 1)),
                "support": np.zeros((k, 1), dtype=np.int64), "n_unconverged": 0, "seconds": 10.0}

    monkeypatch.setattr(pl_bound_rkhs, "_bound_task", fake_task)
    part = pl_runtime._Run(workers=1, chunk_cells=16)
    from robust_imdp.models.geometry import Box, Partition

    partition = Partition(Box(p.space_lower, p.space_upper), p.cell_size, pl_preflight._region_objects(p))
    assert partition.n_cells == 256
    pl_bound_stage._learn_and_bound(p, partition, pl_runtime._Log(False), part, cache)
    parts = sorted(cache.glob("bounds-*.parts/m0-c*-16.npz"), key=lambda f: int(f.name.split("-c")[1].split("-")[0]))
    assert len(parts) == 16
    for f in parts[12:]:  # an interrupted run: 12 of 16 chunks were saved
        f.unlink()
    clock[0] = 1000.0
    capsys.readouterr()
    pl_bound_stage._learn_and_bound(p, partition, pl_runtime._Log(True), pl_runtime._Run(workers=1, chunk_cells=16), cache)
    err = capsys.readouterr().err
    assert "resumed: 12 of 16 bound chunks" in err
    assert "bound: 13/16 (81 %), 10.0 s, about 30 s left" in err, err
    assert "bound: 15/16 (94 %), 30.0 s, about 10 s left" in err, err


def test_a_damaged_bounds_file_does_not_break_the_advice_stage(problem, tmp_path):
    # The abstraction comes from the cache and the advice stage reads the bounds file: damaged,
    # it is skipped with the one warning, not a BadZipFile.
    cache = tmp_path / "cache"
    _run(problem, cache, advice=True)
    (target,) = list(cache.glob("bounds-*.npz"))
    _truncate(target)
    with pytest.warns(RobustImdpWarning, match="cache entry .*bounds-.*computing it again"):
        res = _run(problem, cache, advice=True)
    assert res.from_cache


def test_result_files_are_flushed_to_disk_before_they_are_renamed(problem, tmp_path, monkeypatch):
    from robust_imdp.io.files import save_result

    res = _run(problem, None)
    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"))),
                                                 real_fsync(fd))[1])
    monkeypatch.setattr(os, "replace", lambda a, b: (events.append(("replace", os.fspath(a))), real_replace(a, b))[1])
    save_result(res, tmp_path / "o")
    renamed = [src for kind, src in events if kind == "replace"]
    assert len(renamed) == 2  # result.npz, then result.json
    for src in renamed:
        assert ("fsync", src) in events[:events.index(("replace", src))], src
