"""The abstraction's cache entry written beside the run on several cores (``run._save_abstraction_beside``).

On several cores the compressed abstraction file is written in a thread while the synthesis, the advice and the
margins run; the run returns only when the entry is complete (the same files as one core writes, and a second run
reuses them), and an error of that write reaches the caller. On one core it is written in the run's thread.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from robust_imdp.pipeline import run as run_module
from robust_imdp.pipeline.parallel import local_cores
from robust_imdp.pipeline.run import synthesize_from_data
from tests.test_pipeline import tiny_problem


def _entry(cache):
    npz = sorted(cache.glob("abstraction-*.npz"))
    assert len(npz) == 1 and npz[0].with_suffix(".json").exists()
    assert not list(cache.glob(".*part*"))  # no temporary file left
    with np.load(npz[0]) as z:
        return {k: z[k] for k in z.files}


@pytest.mark.parametrize("workers", [1, None])
def test_the_entry_is_complete_when_the_run_returns_and_reused(tmp_path, monkeypatch, workers):
    threads = []
    real = run_module.write_cache_entry

    def spy(path, write):
        threads.append(threading.current_thread().name)
        return real(path, write)

    in_place = []
    real_entry = run_module._save_abstraction_entry
    monkeypatch.setattr(run_module, "write_cache_entry", spy)
    monkeypatch.setattr(run_module, "_save_abstraction_entry",
                        lambda *a: (in_place.append(threading.current_thread().name), real_entry(*a))[1])
    first = synthesize_from_data(tiny_problem(), progress=False, abstraction_cache=tmp_path, workers=workers,
                                 advice=False)
    saved = _entry(tmp_path)
    if workers is None and local_cores() > 1:
        assert threads == ["robust-imdp cache writer"] and in_place == []  # beside the run
    else:
        assert threads == [] and in_place == [threading.current_thread().name]
    again = synthesize_from_data(tiny_problem(), progress=False, abstraction_cache=tmp_path, workers=workers,
                                 advice=False)
    assert again.from_cache and not first.from_cache
    np.testing.assert_array_equal(again.synthesis.p_low, first.synthesis.p_low)
    for k, v in _entry(tmp_path).items():
        np.testing.assert_array_equal(v, saved[k])


def test_the_writes_error_reaches_the_caller(tmp_path, monkeypatch):
    def broken(path, write):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(run_module, "write_cache_entry", broken)
    monkeypatch.setattr(run_module, "_save_abstraction_entry",
                        lambda f, a, d: (run_module._write_json_entry(f.with_suffix(".json"), d), broken(f, a.save)))
    with pytest.raises(OSError, match="No space left on device"):
        synthesize_from_data(tiny_problem(), progress=False, abstraction_cache=tmp_path, advice=False)
