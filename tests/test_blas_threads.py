"""A run's results do not depend on the BLAS thread count (robust_imdp._blas): LAPACK's threaded LU gives
other bits on two threads than on one, and the data fit behind the eps diagnostics, the advice and the
nominal model went through it. The run holds BLAS to one thread, so a process whose BLAS has two threads
(what a 2-core machine gives by default) and one with one thread (``taskset -c 0``) get the same bits."""
from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np
import pytest

from robust_imdp import _blas
from robust_imdp.pipeline import run as run_mod

ROOT = Path(__file__).resolve().parents[1]


def _counts():
    return [get() for _, get in _blas._loaded()]


def test_blas_threads_sets_and_restores():
    libs = _blas._loaded()
    if not libs:
        pytest.skip("no BLAS library with a thread-count entry point found in this process")
    before = _counts()
    old_env = os.environ.get("OPENBLAS_NUM_THREADS")
    with _blas.blas_threads(1):
        assert _counts() == [1] * len(libs)
        assert os.environ["OPENBLAS_NUM_THREADS"] == "1"
    assert _counts() == before
    assert os.environ.get("OPENBLAS_NUM_THREADS") == old_env


def _problem():
    from robust_imdp.io.files import load_problem

    p = load_problem(ROOT / "examples" / "problems" / "three_mode_linear.toml")
    import dataclasses

    return dataclasses.replace(p, cell_size=np.array([0.5, 0.5]))  # 64 cells: the data fit is the same 600 points


def _run(threads, pin=True, monkeypatch=None):
    if not pin:
        monkeypatch.setattr(run_mod, "blas_threads", lambda n: contextlib.nullcontext())
    with _blas.blas_threads(threads):  # the process's BLAS as the machine would give it
        r = run_mod.synthesize_from_data(_problem(), progress=False, advice=False, margins=False, workers=1)
    return r


@pytest.mark.skipif((os.cpu_count() or 1) < 2 or not _blas._loaded(), reason="needs 2 cores and a known BLAS")
def test_run_is_the_same_for_one_and_two_blas_threads(monkeypatch):
    one = _run(1)
    two = _run(2)
    assert one.diagnostics["eps"] == two.diagnostics["eps"]  # the data fit's bits (compared as parsed numbers)
    for name in ("p_low", "p_up", "strategy"):
        assert np.array_equal(getattr(one.synthesis, name), getattr(two.synthesis, name))
    # teeth: without the pin the two-thread run's fit differs (LAPACK's threaded LU)
    loose = _run(2, pin=False, monkeypatch=monkeypatch)
    assert loose.diagnostics["eps"] != one.diagnostics["eps"]
