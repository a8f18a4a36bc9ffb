"""What one run carries through its stages: progress lines and stage times (:class:`_Log`) and where the
chunked work runs (:class:`_Run`).
"""

from __future__ import annotations

import sys
import time

from robust_imdp.errors import InvalidInputError, interrupt_in

#: The abstraction's rows are built in tasks of at most this many cells (the run's abstraction stage,
#: ``pipeline.run``; a margins factor's rows, ``pipeline.margins``).
MAX_ROW_CELLS = 4096


# --------------------------------------------------------------------------- helpers
class _Log:
    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.timings: dict[str, float] = {}
        self.t0 = time.perf_counter()

    def stage(self, name: str):
        log = self

        class _Stage:
            def __enter__(self):
                self.t = time.perf_counter()
                if log.enabled:
                    print(f"[robust-imdp] {name} ...", file=sys.stderr, flush=True)
                return self

            def __exit__(self, kind, exc, tb):
                dt = time.perf_counter() - self.t
                log.timings[name] = log.timings.get(name, 0.0) + dt
                if exc is not None and not isinstance(exc, KeyboardInterrupt) and interrupt_in(exc) is not None:
                    # Ctrl-C seen inside compiled code surfaces as a SystemError caused by it
                    # (errors.interrupt_in): the caller gets the interrupt, as from Python code
                    raise KeyboardInterrupt(f"interrupted during the {name} stage") from exc
                return False

        return _Stage()

    def info(self, text: str) -> None:
        if self.enabled:
            print(f"[robust-imdp]   {text}", file=sys.stderr, flush=True)

    def progress(self, what: str, done: int, total: int, t0: float, every: float = 2.0, resumed: int = 0) -> None:
        """A progress line (count, elapsed time, estimate of the rest), at most every ``every`` s.

        ``resumed`` of the ``done`` units were loaded from the cache, not computed since ``t0``:
        the estimate divides the units left by the rate of this process, ``(done - resumed) / elapsed``.
        """
        now = time.perf_counter()
        if not self.enabled or (done < total and now - getattr(self, "_last", 0.0) < every):
            return
        self._last = now
        el = now - t0
        rest = ""
        if 0 < done - resumed and done < total:
            rest = f", about {el / (done - resumed) * (total - done):.0f} s left"
        print(f"[robust-imdp]   {what}: {done}/{total} ({100 * done / max(total, 1):.0f} %), {el:.1f} s{rest}",
              file=sys.stderr, flush=True)


class _Run:
    """Scheduler options of one run; the scheduler is started on first use and closed at the end."""

    def __init__(self, client=None, workers=None, scheduler=None, chunk_cells=None, check_resources=True):
        self.client, self.workers, self.scheduler_address = client, workers, scheduler
        self.chunk_cells = chunk_cells
        self.check_resources = check_resources
        self.sched = None

    def scheduler(self, log: "_Log"):
        from robust_imdp.pipeline.parallel import open_scheduler

        if self.sched is None:
            self.sched = open_scheduler(workers=self.workers, scheduler=self.scheduler_address, client=self.client)
            log.info(f"scheduler: {self.sched.description}")
        return self.sched

    def close(self) -> None:
        if self.sched is not None:
            self.sched.close()
            self.sched = None


def _serial():
    from robust_imdp.pipeline.parallel import InProcess

    return InProcess(threads=1)


def _chunk_cells(run: "_Run", n_cells: int, default: int) -> int:
    """Cells per task: a multiple of rkhs.CELL_BLOCK (so the result does not depend on it)."""
    from robust_imdp.bounds.rkhs import CELL_BLOCK

    c = default if run.chunk_cells is None else int(run.chunk_cells)
    if c < 1:
        raise InvalidInputError(f"chunk_cells must be a positive integer; got {run.chunk_cells!r}")
    return max(CELL_BLOCK, -(-min(c, max(n_cells, 1)) // CELL_BLOCK) * CELL_BLOCK)
