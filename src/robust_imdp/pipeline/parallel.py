"""Where the chunked stages run: in this process, or on Dask (the only module that imports dask).

The bound and abstraction stages are lists of pure tasks (``rkhs.bound_chunk``,
``abstraction.abstract_rows``). A :class:`Scheduler` runs such a list and yields the results as
they complete, with their task index, so the caller can save each one at once (resumable runs)
and report progress; the caller assembles them in task order, so the result does not depend on
the scheduler, the number of workers or the order of completion.

* :class:`InProcess` -- a plain loop in this process; numba's own threads use ``threads`` cores.
* :class:`DaskScheduler` -- a ``distributed.Client``: a local cluster of single-threaded worker
  processes (``workers`` > 1), or any existing cluster (``scheduler="tcp://host:8786"`` or a
  ``client``). Large inputs shared by many tasks are scattered once (:meth:`Scheduler.share`).

:func:`open_scheduler` picks one: an explicit client or address wins; else ``workers=1`` runs in
process on one core, ``workers=N`` (N > 1) starts a local cluster of N processes, and
``workers=None`` (the default) runs in process with numba threads on all local cores. The default
never starts a Dask cluster: a local cluster starts its workers with the ``spawn`` method, which
re-imports the caller's main module, so a user's script without an ``if __name__ ==
"__main__":`` guard would run again in every worker (the ``robust-imdp`` command is safe; so are
scripts with the guard).

**Side work.** Work that is serial in itself and does not feed the next stage at once (the assumption
check's SOCPs, the figures) runs *beside* the stages (:meth:`Scheduler.run_beside`): on a Dask cluster as
tasks like the others; in process on several cores in a :class:`SideLane`, a few helper processes started
with ``python -c`` (no ``multiprocessing``: the caller's main module is never imported again), one BLAS and
numba thread each, fed pickled module-level functions over pipes. The numba stages keep every core busy
meanwhile, so the side work overlaps them instead of adding to the run (docs/ARCHITECTURE.md, "Where the
cores go"). One core (``workers=1``) runs everything in this process, in order, as before.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
from collections import deque
from concurrent.futures import Future
from typing import Any, Callable, Iterator, Sequence

from robust_imdp.errors import InvalidInputError

__all__ = ["Scheduler", "InProcess", "DaskScheduler", "SideLane", "SideLaneError", "open_scheduler", "local_cores",
           "side_lane", "current_lane", "side_helpers", "SIDE_MIN_CELL_MODES"]

log = logging.getLogger(__name__)

def local_cores() -> int:
    """Cores this process may use (the affinity mask where the OS reports one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


class Scheduler:
    """Runs lists of pure tasks; see the module docstring."""

    n_workers: int = 1
    description: str = ""

    def share(self, obj: Any) -> Any:
        """A handle of ``obj`` to pass to many tasks (sent to the workers once)."""
        return obj

    def run(self, fn: Callable, args: Sequence[tuple], kwargs: dict | None = None) -> Iterator[tuple[int, Any]]:
        """Yield ``(index, fn(*args[index], **kwargs))`` for every task, in order of completion."""
        raise NotImplementedError

    def run_overlapping(self, fn: Callable, args: Sequence[tuple], kwargs: dict | None = None
                        ) -> Iterator[tuple[int, Any]]:
        """:meth:`run` for tasks that may run two at a time in one process (``fn`` thread-safe): in process on several
        cores, :class:`InProcess` keeps a second task going beside the first; elsewhere the same as :meth:`run`."""
        return self.run(fn, args, kwargs)

    #: Whether :meth:`run_beside`, called from another thread, runs concurrently with this scheduler's own tasks.
    concurrent_side: bool = False
    #: Where side work runs (for progress lines).
    side_description: str = "in this process"

    def run_beside(self, fn: Callable, args: Sequence[tuple], kwargs: dict | None = None) -> list:
        """``[fn(*args[i], **kwargs) for i]`` in the tasks' order, as side work (see the module docstring).

        Blocks until all are done. Where :attr:`concurrent_side` is true, a thread calling it leaves the
        caller's thread free to run the stages' tasks meanwhile; otherwise the tasks run here and now.
        """
        out = [None] * len(args)
        for i, r in self.run(fn, args, kwargs):
            out[i] = r
        return out

    def use_side_lane(self) -> bool:
        """Start the side work's helper processes where this scheduler has none and can use them (in process on
        several cores); returns :attr:`concurrent_side`."""
        return self.concurrent_side

    def close(self) -> None:
        """Release the workers (a no-op for schedulers this object did not start)."""

    def __enter__(self) -> "Scheduler":
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False


#: Tasks at a time of :meth:`InProcess.run_overlapping`.
_OVERLAP = 2
_TASK_POOL = None
_TASK_POOL_LOCK = threading.Lock()


def _task_pool():
    """The process's threads of :meth:`InProcess.run_overlapping` (started on first use and kept, with their numba
    threads: no thread start per stage)."""
    global _TASK_POOL
    with _TASK_POOL_LOCK:
        if _TASK_POOL is None:
            from concurrent.futures import ThreadPoolExecutor

            _TASK_POOL = ThreadPoolExecutor(max_workers=_OVERLAP, thread_name_prefix="robust-imdp task")
        return _TASK_POOL


class InProcess(Scheduler):
    """A plain loop in this process; ``threads`` is the number of numba threads of each task.

    With more than one thread, side work (:meth:`run_beside`) runs in a :class:`SideLane` once
    :meth:`use_side_lane` is called: the one of an enclosing :func:`side_lane`, else one it starts (and
    closes in :meth:`close`).
    """

    def __init__(self, threads: int = 1):
        self.threads = max(1, int(threads))
        self.n_workers = self.threads  # cores in use (numba threads inside each task)
        self.description = f"in process, {self.threads} thread{'s' if self.threads > 1 else ''}"
        self.lane: "SideLane | None" = None
        self._own_lane = False

    def run(self, fn, args, kwargs=None):
        kw = dict(kwargs or {})
        for i, a in enumerate(args):
            yield i, fn(*a, threads=self.threads, **kw)

    def run_overlapping(self, fn, args, kwargs=None):
        """Two tasks at a time on several threads, each with every numba thread; results in task order.

        One task at a time leaves a core idle wherever a task runs Python (its set-up, its last piece of eq. C) and
        at the end of each of its parallel kernels, while the last work unit finishes (on the unicycle at 32^3:
        about 2 s of the bound stage's 50 on 2 cores). With a second task's kernels beside it, a lane that comes
        free has work (the tasks' numbers are their own: the same results).
        """
        if self.threads == 1 or len(args) < 2:
            yield from self.run(fn, args, kwargs)
            return
        kw = dict(kwargs or {})
        pool = _task_pool()
        pending: deque = deque()
        try:
            for i in range(len(args)):
                while len(pending) < _OVERLAP and i + len(pending) < len(args):
                    pending.append(pool.submit(fn, *args[i + len(pending)], threads=self.threads, **kw))
                yield i, pending.popleft().result()
        finally:  # an error or an interrupt: the tasks not started are dropped, a running one ends on its own
            for f in pending:
                f.cancel()

    @property
    def concurrent_side(self) -> bool:
        return self.lane is not None

    @property
    def side_description(self) -> str:
        if self.lane is None:
            return "in this process"
        n = len(self.lane.helpers)
        return f"{n} helper process{'es' if n > 1 else ''}"

    def use_side_lane(self) -> bool:
        if self.lane is None and self.threads > 1:
            self.lane = current_lane()
            if self.lane is None:
                try:
                    self.lane, self._own_lane = SideLane(side_helpers(self.threads)), True
                except OSError as exc:  # no interpreter to start (an embedded Python): side work stays in process
                    log.info("side work stays in process: %s", exc)
        return self.concurrent_side

    def run_beside(self, fn, args, kwargs=None):
        if self.lane is None:
            return super().run_beside(fn, args, kwargs)
        kw = dict(kwargs or {})
        futures = [self.lane.submit(fn, *a, threads=1, **kw) for a in args]
        return [f.result() for f in futures]

    def close(self):
        if self._own_lane and self.lane is not None:
            self.lane.close()
        self.lane, self._own_lane = None, False


class DaskScheduler(Scheduler):
    """Tasks on a ``distributed.Client``; each task runs numba on one thread (one task per core).

    Parameters
    ----------
    client : distributed.Client
    owned : bool
        Close the client and its cluster in :meth:`close` (when :func:`open_scheduler` started it).
    """

    def __init__(self, client, owned: bool = False):
        self.client = client
        self.owned = owned
        info = client.scheduler_info()
        workers = info.get("workers", {})
        self.n_workers = max(1, sum(int(w.get("nthreads", 1)) for w in workers.values()))
        self.description = f"Dask at {client.scheduler.address} ({len(workers)} workers, {self.n_workers} threads)"

    #: side work runs as tasks on the cluster beside the stages' (a thread may call run_beside meanwhile)
    concurrent_side = True
    side_description = "tasks on the Dask cluster"

    def share(self, obj):
        # hash=False: a fresh key per call. With the default content hash, two stages scattering the same object
        # share one key, and the first to release its future deletes the data under the other's tasks
        # ("lost dependencies").
        return self.client.scatter(obj, broadcast=True, hash=False)

    def run(self, fn, args, kwargs=None):
        from distributed import as_completed

        kw = dict(kwargs or {})
        futures = [self.client.submit(fn, *a, threads=1, pure=False, **kw) for a in args]
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for fut in as_completed(futures):
                yield index[fut.key], fut.result()
        finally:
            for f in futures:
                f.cancel()

    def close(self):
        if self.owned:
            cluster = getattr(self.client, "cluster", None)
            self.client.close()
            if cluster is not None:
                cluster.close()


LOCAL_PROFILER_KEY = "distributed.worker.profile.enabled"


def open_scheduler(*, workers: int | None = None, scheduler: str | None = None, client: Any = None) -> Scheduler:
    """Pick and start a scheduler (see the module docstring).

    Parameters
    ----------
    workers : int, optional
        1: in process on one core; N > 1: a local cluster of N worker processes; None: in process
        with numba threads on all local cores.
    scheduler : str, optional
        Address of a running Dask scheduler, e.g. ``"tcp://host:8786"``.
    client : distributed.Client, optional
        An existing client (used as is, never closed here).

    Returns
    -------
    Scheduler
    """
    if client is not None:
        return DaskScheduler(client, owned=False)
    if scheduler is not None:
        if not isinstance(scheduler, str) or "://" not in scheduler:
            raise InvalidInputError(f"scheduler must be an address like 'tcp://host:8786'; got {scheduler!r}")
        from distributed import Client

        return DaskScheduler(Client(scheduler), owned=True)
    if workers is not None and (int(workers) != workers or int(workers) < 1):
        raise InvalidInputError(f"workers must be a positive integer; got {workers!r}")
    if workers is None or int(workers) == 1:
        return InProcess(threads=local_cores() if workers is None else 1)
    n = int(workers)
    import dask
    from distributed import Client, LocalCluster

    # No dashboard, so no use for the workers' statistical profiler, which samples the task
    # thread every 10 ms (benchmarks/scale.py: the summed task time of the bound stage on 2
    # workers fell from 39.7 s to 38.3 s without it; 35.1 s in one process)
    with dask.config.set({LOCAL_PROFILER_KEY: False}):
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=logging.ERROR)
    log.info("started a local Dask cluster with %d worker processes", n)
    return DaskScheduler(Client(cluster), owned=True)


# ---------------------------------------------------------------------------------------------- side work
#: Side work goes to helper processes only from this many (cell, mode) pairs on: below it the bound stage is
#: too short to hide a helper's start-up (an interpreter, numpy, numba and the task's modules: about a second
#: of CPU), and the check and the figures cost a fraction of a second in process.
SIDE_MIN_CELL_MODES = 8192
#: The helpers' environment: one BLAS / OpenMP / numba thread each (the stages' numba threads hold the cores;
#: the SOCPs' and figures' matrices are small, and several BLAS threads spinning beside them cost more than
#: they give). The BLAS results do not depend on the thread count for the check's matrices
#: (tests/test_side_lane.py compares the bits with the in-process check).
SIDE_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
            "NUMBA_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
_HEADER = 8  # bytes of a message's length


class SideLaneError(RuntimeError):
    """The side lane could not run a task (a helper ended, the lane was closed, the task or its answer could not
    be pickled): not the task's own failure, so the caller may run it in process instead."""


def side_helpers(cores: int) -> int:
    """Helper processes of a side lane beside ``cores`` busy cores: one up to 4 cores, then one per 4, at most 4."""
    return max(1, min(4, int(cores) // 4))


def _send(stream, obj) -> None:
    import pickle

    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    stream.write(len(data).to_bytes(_HEADER, "little") + data)
    stream.flush()


def _receive(stream, raw: bool = False):
    """The next message (its pickled bytes with ``raw``), or raise EOFError when the other side has closed the
    pipe."""
    import pickle

    head = stream.read(_HEADER)
    if len(head) < _HEADER:
        raise EOFError("the pipe was closed")
    n = int.from_bytes(head, "little")
    data = stream.read(n)
    if len(data) < n:
        raise EOFError("the pipe was closed in a message")
    return data if raw else pickle.loads(data)


class _Helper:
    """One helper process of a :class:`SideLane` and the thread that reads its answers."""

    def __init__(self, lane: "SideLane", index: int, preload: Sequence[str]):
        import subprocess
        import sys

        import robust_imdp

        env = dict(os.environ, **SIDE_ENV)
        # the helper imports the same robust_imdp as this process, whatever sys.path the caller set up
        root = os.path.dirname(os.path.dirname(os.path.abspath(robust_imdp.__file__)))
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        code = "from robust_imdp.pipeline.parallel import _helper_main; _helper_main()"
        # a session of its own: Ctrl-C in the terminal reaches this process only, which closes the lane
        self.proc = subprocess.Popen([sys.executable, "-c", code, *preload], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, env=env, start_new_session=True)
        self.lane, self.index = lane, index
        self.current: "tuple | None" = None  # (task id, future) of the task it runs
        self.reader = threading.Thread(target=self._read, name=f"robust-imdp side helper {index}", daemon=True)
        self.reader.start()
        # tasks are pickled and written by a thread of their own: a task larger than the pipe's buffer would block
        # the caller until the helper reads it, and a helper still starting (its imports: a second or more) reads
        # nothing yet (the run's thread waited there, outside every stage)
        self.outbox: "queue.Queue" = queue.Queue()
        self.sender = threading.Thread(target=self._write, name=f"robust-imdp side sender {index}", daemon=True)
        self.sender.start()

    def _write(self) -> None:
        import pickle

        while True:
            item = self.outbox.get()
            if item is None:
                return
            tid, fut, message = item
            try:
                data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
            except Exception as exc:  # the task cannot be pickled: its failure, the helper takes the next one
                self.lane._unsent(self, tid, fut, exc)
                continue
            try:
                self.proc.stdin.write(len(data).to_bytes(_HEADER, "little") + data)
                self.proc.stdin.flush()
            except Exception as exc:  # the helper is gone (its reader reports it) or the lane closed its pipe
                self.lane._unsent(self, tid, fut, exc)

    def _read(self) -> None:
        import pickle

        while True:
            try:
                data = _receive(self.proc.stdout, raw=True)
            except BaseException as exc:  # the helper died or the lane closed it
                self.lane._lost(self, exc)
                return
            try:
                tid, ok, value, text = pickle.loads(data)
            except Exception as exc:  # a whole answer this process cannot unpickle: the task's failure, not the helper's
                tid, ok, text = None, False, ""  # None: the one task this helper runs
                value = SideLaneError(f"the answer could not be read back: {type(exc).__name__}: {exc}")
            self.lane._done(self, tid, ok, value, text)


class SideLane:
    """Helper processes for side work (see the module docstring): :meth:`submit` a module-level function
    and its arguments (picklable), get a ``concurrent.futures.Future``.

    Tasks go to the first idle helper, in the order submitted. A task's exception is raised by its future's
    ``result()`` (with the helper's traceback as a note). A helper that dies fails its task with
    ``RuntimeError`` and the lane's queued tasks with it. Use it as a context manager or call :meth:`close`
    (helpers also exit when this process's end of their pipe closes).

    Parameters
    ----------
    n_helpers : int
    preload : sequence of str
        Modules every helper imports as it starts (beside this process's work), e.g. ``robust_imdp.plotting``.
    """

    def __init__(self, n_helpers: int = 1, preload: Sequence[str] = ()):
        self._lock = threading.Lock()
        self._queue: deque = deque()
        self._closed = False
        self._next = 0
        self.helpers: list = []
        self._idle: list = []
        try:
            for i in range(max(1, int(n_helpers))):
                helper = _Helper(self, i, tuple(preload))
                with self._lock:
                    self.helpers.append(helper)
                    if helper.proc.returncode is None and not getattr(helper, "lost", False):
                        self._idle.append(helper)
        except BaseException:
            self.close()
            raise

    def submit(self, fn: "Callable | str", *args, **kwargs) -> Future:
        """Run ``fn(*args, **kwargs)`` in a helper; its future. ``fn``: a module-level function, or its name
        ``"module:function"`` (imported by the helper only: e.g. a plotting function, so that this process does
        not import matplotlib)."""
        fut: Future = Future()
        with self._lock:
            if self._closed or all(getattr(h, "lost", False) for h in self.helpers):
                raise SideLaneError("the side lane is closed" if self._closed else "every side-work helper ended")
            self._next += 1
            self._queue.append((self._next, fut, fn, args, kwargs))
            self._dispatch()
        return fut

    def _dispatch(self) -> None:
        """Send queued tasks to idle helpers (with the lock held)."""
        while self._queue and self._idle:
            helper = self._idle.pop(0)
            tid, fut, fn, args, kwargs = self._queue.popleft()
            if not fut.set_running_or_notify_cancel():
                self._idle.insert(0, helper)
                continue
            helper.current = (tid, fut)
            helper.outbox.put((tid, fut, (tid, fn, args, kwargs)))  # pickled and written by its sender thread

    def _unsent(self, helper: "_Helper", tid: int, fut: Future, exc: BaseException) -> None:
        """A task the sender could not pickle or write: it fails with a SideLaneError, the helper is idle again."""
        with self._lock:
            if helper.current is not None and helper.current[0] == tid:
                helper.current = None
                if not self._closed and not getattr(helper, "lost", False):
                    self._idle.insert(0, helper)
                    self._dispatch()
        err = SideLaneError(f"the side lane could not send the task: {type(exc).__name__}: {exc}")
        err.__cause__ = exc
        if not fut.done():
            fut.set_exception(err)

    def _done(self, helper: _Helper, tid: int, ok: bool, value, text: str) -> None:
        with self._lock:
            current, helper.current = helper.current, None
            if not self._closed:
                self._idle.append(helper)
                self._dispatch()
        if current is None or (tid is not None and current[0] != tid):
            return
        fut = current[1]
        if ok:
            fut.set_result(value)
        else:
            if text and hasattr(value, "add_note"):
                value.add_note(f"in the side-work helper process:\n{text}")
            fut.set_exception(value)

    def _lost(self, helper: _Helper, exc: BaseException) -> None:
        with self._lock:
            helper.lost = True
            current, helper.current = helper.current, None
            closed = self._closed
            if helper in self._idle:
                self._idle.remove(helper)
            # the queue waits for a helper still alive; with none left it fails
            orphans = [] if any(not getattr(h, "lost", False) for h in self.helpers) else list(self._queue)
            if orphans:
                self._queue.clear()
        why = SideLaneError("the side lane was closed" if closed else
                            f"a side-work helper process ended (exit status {helper.proc.poll()}): {exc}")
        for item in ([current] if current else []) + [(o[0], o[1]) for o in orphans]:
            if not item[1].done():
                item[1].set_exception(why)

    def close(self, timeout: float = 5.0) -> None:
        """Stop the helpers (their running tasks are abandoned, queued ones cancelled)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            queued, self._queue = list(self._queue), deque()
        for _, fut, *_ in queued:
            fut.cancel()
        for h in self.helpers:
            h.outbox.put(None)  # its sender ends (after a write in progress: the pipe closes below either way)
            try:
                h.proc.stdin.close()  # the helper's loop ends at the end of its input
            except OSError:
                pass
        for h in self.helpers:
            try:
                h.proc.wait(timeout=timeout if h.current is None else 0.5)
            except Exception:
                h.proc.kill()
                h.proc.wait()
            h.reader.join(timeout=timeout)
            h.proc.stdout.close()

    def __enter__(self) -> "SideLane":
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False

    def __del__(self):
        try:
            self.close(timeout=0.5)
        except Exception:
            pass


_LANES: list = []


class side_lane:  # noqa: N801 - used as a function: ``with side_lane(...) as lane``
    """A :class:`SideLane` that the runs inside the ``with`` block use for their side work (see
    :func:`current_lane`), closed at the end of the block; ``None`` when there is no use for one (one core, or
    ``enabled`` false).

    Parameters
    ----------
    enabled : bool
    n_helpers : int, optional
        Default :func:`side_helpers` of the local cores.
    preload : sequence of str
    """

    def __init__(self, enabled: bool = True, n_helpers: int | None = None, preload: Sequence[str] = ()):
        self.lane = None
        cores = local_cores()
        if enabled and cores > 1:
            try:
                self.lane = SideLane(side_helpers(cores) if n_helpers is None else n_helpers, preload)
            except OSError as exc:
                log.info("side work stays in process: %s", exc)

    def __enter__(self) -> "SideLane | None":
        if self.lane is not None:
            _LANES.append(self.lane)
        return self.lane

    def __exit__(self, *exc) -> bool:
        if self.lane is not None:
            if self.lane in _LANES:
                _LANES.remove(self.lane)
            self.lane.close()
        return False


def current_lane() -> "SideLane | None":
    """The side lane of the innermost :func:`side_lane` block, or None."""
    return _LANES[-1] if _LANES else None


def _helper_main() -> None:
    """The loop of a side-work helper process: import the modules named on its command line, then run each
    task it reads (``(id, fn, args, kwargs)``) and send back ``(id, ok, value or exception, traceback text)``,
    until its input ends."""
    import importlib
    import signal
    import sys
    import traceback

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # this process's parent decides when to stop
    proto = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # a task's prints go to stderr, not into the answers
    sys.stdout = sys.stderr
    for name in sys.argv[1:]:
        try:
            importlib.import_module(name)
        except Exception:  # the task that needs it will say why
            pass
    source = sys.stdin.buffer
    import pickle

    while True:
        try:
            data = _receive(source, raw=True)
        except EOFError:
            # the lane closed: leave at once (the interpreter's teardown of numba, matplotlib and cvxpy took 0.3 s,
            # which the run waited for after its last output); every answer has been sent and flushed
            sys.stderr.flush()
            os._exit(0)
        try:
            tid, fn, args, kwargs = pickle.loads(data)
        except Exception as exc:  # a task this process cannot unpickle (e.g. its module is not importable here)
            # its id is inside what could not be read: None stands for the one task a helper runs at a time
            _send(proto, (None, False, SideLaneError(f"the task could not be read by the helper: "
                                                     f"{type(exc).__name__}: {exc}"), ""))
            continue
        try:
            if isinstance(fn, str):  # "module:function"
                module, _, name = fn.partition(":")
                fn = getattr(importlib.import_module(module), name)
            answer = (tid, True, fn(*args, **kwargs), "")
        except BaseException as exc:  # noqa: BLE001 - every failure goes back to the caller
            answer = (tid, False, exc, traceback.format_exc())
        try:
            _send(proto, answer)
        except Exception as exc:  # an unpicklable result or exception: its text instead
            _send(proto, (tid, False, SideLaneError(f"the answer could not be sent back: {type(exc).__name__}: "
                                                    f"{exc}"), answer[3]))
