"""``cli.end_process``: the console script's end without the interpreter's teardown.

It must keep what a normal exit guarantees: the status, everything printed (stdout to a pipe is block-buffered),
the threads that are not daemons finished, the ``atexit`` functions run (temporary folders' finalizers among
them), and 120 where the flush fails, as Python's own exit. Each case runs in a fresh interpreter.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap


def _run(code: str, **kw) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env.pop("PYTHONUNBUFFERED", None)  # stdout to a pipe block-buffered, as a user's (some CI machines set it)
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=60,
                          env=env, **kw)


def test_status_output_threads_and_atexit_survive(tmp_path):
    """Status 3; 20,000 printed lines all arrive (more than a pipe's buffer); a worker thread that is still
    sleeping finishes its file; an atexit function and a TemporaryDirectory's finalizer run."""
    code = f"""
        import atexit, pathlib, sys, tempfile, threading, time
        from robust_imdp.cli import end_process
        out = pathlib.Path({str(tmp_path)!r})
        def late():
            time.sleep(0.3)
            (out / "thread.txt").write_text("done")
        threading.Thread(target=late).start()
        atexit.register(lambda: (out / "atexit.txt").write_text("ran"))
        keep = tempfile.TemporaryDirectory(dir=out)
        (out / "tmpname.txt").write_text(keep.name)
        for i in range(20000):
            print(f"line {{i}}")
        print("err line", file=sys.stderr)
        end_process(3)
        print("never")
    """
    proc = _run(code)
    assert proc.returncode == 3, proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) == 20000 and lines[-1] == "line 19999"
    assert "err line" in proc.stderr and "never" not in proc.stdout
    assert (tmp_path / "thread.txt").read_text() == "done"
    assert (tmp_path / "atexit.txt").read_text() == "ran"
    tmp_name = (tmp_path / "tmpname.txt").read_text()
    assert not __import__("pathlib").Path(tmp_name).exists()  # the finalizer removed the folder


def test_closed_pipe_exits_120():
    """The reader of stdout has gone: the flush fails and the status is 120 (Python's own exit's)."""
    code = """
        import os, sys
        from robust_imdp.cli import end_process
        r, w = os.pipe()
        os.close(r)
        sys.stdout = os.fdopen(w, "w", buffering=1 << 16)
        sys.stdout.write("x" * 100)
        end_process(0)
    """
    proc = _run(code)
    assert proc.returncode == 120, proc.stderr


def test_console_script_status(tmp_path):
    """``console_main`` ends with main's status: 1 for a missing problem file, 0 for ``--version``."""
    bad = _run("import sys; sys.argv = ['robust-imdp', 'run', 'missing.toml', '--out', 'o']\n"
               "from robust_imdp.cli import console_main; console_main()", cwd=tmp_path)
    assert bad.returncode == 1 and "robust-imdp: error:" in bad.stderr and "Traceback" not in bad.stderr
    ok = _run("import sys; sys.argv = ['robust-imdp', '--version']\n"
              "from robust_imdp.cli import console_main; console_main()")
    assert ok.returncode == 0 and ok.stdout.startswith("robust-imdp ")
