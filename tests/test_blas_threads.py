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


def test_idle_openmp_threads_sleep_soon_unless_the_user_chose(monkeypatch):
    monkeypatch.delenv("GOMP_SPINCOUNT", raising=False)
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    assert _blas.quiet_openmp_waits() and os.environ["GOMP_SPINCOUNT"] == _blas.OMP_SPIN
    monkeypatch.setenv("GOMP_SPINCOUNT", "300000")  # the user's value is kept
    assert not _blas.quiet_openmp_waits() and os.environ["GOMP_SPINCOUNT"] == "300000"
    monkeypatch.delenv("GOMP_SPINCOUNT")
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")  # so is the user's wait policy (it decides the spinning)
    assert not _blas.quiet_openmp_waits() and "GOMP_SPINCOUNT" not in os.environ


def test_the_command_sets_the_spin_count_before_the_openmp_runtime_loads(tmp_path):
    """In a fresh process the command line sets GOMP_SPINCOUNT before numba loads libgomp (which reads it then)."""
    import subprocess
    import sys

    code = ("import os, sys\n"
            "from robust_imdp import cli\n"
            "import numba.np.ufunc.parallel as par\n"
            "seen = []\n"
            "orig = par._launch_threads\n"
            "def spy():\n"
            "    seen.append(os.environ.get('GOMP_SPINCOUNT'))\n"
            "    return orig()\n"
            "par._launch_threads = spy\n"
            "rc = cli.main(['run', sys.argv[2], '--out', sys.argv[1], '--quiet', '--advice', 'off', '--margins', 'off',"
            " '--no-figures'])\n"
            "print(rc, seen[:1])\n")
    import shutil
    from pathlib import Path

    src = Path(__file__).resolve().parents[1] / "examples" / "problems"
    shutil.copy(src / "three_mode_linear_data.csv", tmp_path)
    text = (src / "three_mode_linear.toml").read_text().replace("cell_size = [0.125, 0.125]", "cell_size = [0.5, 0.5]")
    (tmp_path / "p.toml").write_text(text)
    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT", "OMP_WAIT_POLICY")}
    p = subprocess.run([sys.executable, "-c", code, str(tmp_path / "out"), str(tmp_path / "p.toml")],
                       capture_output=True, text=True, env=env, cwd=tmp_path, timeout=900)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.split()[-1] == f"['{_blas.OMP_SPIN}']", p.stdout
