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
never starts processes: a local cluster starts its workers with the ``spawn`` method, which
re-imports the caller's main module, so a user's script without an ``if __name__ ==
"__main__":`` guard would run again in every worker (the ``robust-imdp`` command is safe; so are
scripts with the guard).
"""

from __future__ import annotations

import logging
import os
from typing import Any, Callable, Iterator, Sequence

from robust_imdp.errors import InvalidInputError

__all__ = ["Scheduler", "InProcess", "DaskScheduler", "open_scheduler", "local_cores"]

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

    def close(self) -> None:
        """Release the workers (a no-op for schedulers this object did not start)."""

    def __enter__(self) -> "Scheduler":
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False


class InProcess(Scheduler):
    """A plain loop in this process; ``threads`` is the number of numba threads of each task."""

    def __init__(self, threads: int = 1):
        self.threads = max(1, int(threads))
        self.n_workers = self.threads  # cores in use (numba threads inside each task)
        self.description = f"in process, {self.threads} thread{'s' if self.threads > 1 else ''}"

    def run(self, fn, args, kwargs=None):
        kw = dict(kwargs or {})
        for i, a in enumerate(args):
            yield i, fn(*a, threads=self.threads, **kw)


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

    def share(self, obj):
        return self.client.scatter(obj, broadcast=True)

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
