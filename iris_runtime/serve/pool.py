"""The render worker pool: blocking runtime calls (encode, render, locate) on a fixed number of
threads, with a bounded queue in front and backpressure instead of an unbounded backlog.

ONNX Runtime, OpenCV and numpy release the GIL in their kernels, so threads over one shared
``IrisRuntime`` (which is thread-safe) run jobs in parallel without a copy of the model per
worker. Admission is decided on the event loop, before any work:

- ``workers`` jobs run at once; up to ``queue`` more wait for a worker;
- a job that finds both full is refused at once with ``Busy`` (429 + ``Retry-After``);
- a job that waits longer than ``queue_timeout`` seconds is refused with ``Unavailable`` (503 +
  ``Retry-After``), as is every job after ``close()`` (graceful shutdown);
- a job given a ``superseded`` future (a render of a stream, ``streams.Streams``) leaves the queue
  as soon as that future is done, without running, with ``Superseded`` (409).

Waiting jobs take the workers in arrival order (a FIFO of waiters; a freed worker is handed to the
first one still waiting).

``Retry-After`` (``retry_after``) is the wait the queue's own measurements predict for a request
arriving now: its place in line (the jobs waiting, plus itself) times the service time of a job
(an exponentially weighted mean of the jobs' measured times on a worker, the newest weighing
``EWMA_WEIGHT``; ``FIRST_GUESS_S`` until a job has been timed), shared by the workers; rounded up
to whole seconds and kept within ``RETRY_AFTER_MIN``..``RETRY_AFTER_MAX``. A worker's slot is
released when its thread finishes, not when the request that asked for it goes away, so the pool
never runs more than ``workers`` jobs whatever the clients do.
"""
from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

from .errors import Busy, Superseded, Unavailable

__all__ = ["WorkerPool", "EWMA_WEIGHT", "FIRST_GUESS_S", "RETRY_AFTER_MIN", "RETRY_AFTER_MAX"]

T = TypeVar("T")

#: Weight of the newest job in the mean service time: a job 10 jobs back weighs 0.2 x 0.8^10,
#: 2 %, so the mean follows a change of load within some ten jobs.
EWMA_WEIGHT = 0.2
#: The mean service time before any job has been timed (seconds).
FIRST_GUESS_S = 1.0
#: ``Retry-After`` bounds (whole seconds): at least 1, so that no client is told to retry at once
#: in a loop; at most 120, so that one outlier (a long orbit video) cannot send clients away for
#: long.
RETRY_AFTER_MIN, RETRY_AFTER_MAX = 1, 120


class WorkerPool:
    """``workers`` threads behind a queue of ``queue`` places (see the module docstring).
    ``on_job(kind, seconds)`` is called after every job (metrics); ``on_reject(reason)`` after
    every refusal ("busy", "timeout", "shutdown", "superseded")."""

    def __init__(self, workers: int, queue: int, queue_timeout: float, *,
                 on_job: Callable[[str, float], None] | None = None,
                 on_reject: Callable[[str], None] | None = None):
        if workers < 1 or queue < 0 or not queue_timeout > 0:
            raise ValueError("workers >= 1, queue >= 0 and queue_timeout > 0 expected")
        self.workers, self.queue = int(workers), int(queue)
        self.queue_timeout = float(queue_timeout)
        self._executor = ThreadPoolExecutor(self.workers, thread_name_prefix="iris-worker")
        self._free = self.workers                            # workers without a job
        self._waiters: deque[asyncio.Future] = deque()        # jobs waiting, first come first
        self._waiting = 0
        self._running = 0
        self._closed = False
        self._mean_s = FIRST_GUESS_S                          # until a job has been timed
        self._on_job = on_job or (lambda kind, s: None)
        self._on_reject = on_reject or (lambda reason: None)

    @property
    def waiting(self) -> int:
        """Jobs admitted and waiting for a worker (the queue depth)."""
        return self._waiting

    @property
    def running(self) -> int:
        return self._running

    @property
    def mean_seconds(self) -> float:
        """The mean service time of a job (exponentially weighted, see the module docstring)."""
        return self._mean_s

    def retry_after(self) -> int:
        """Whole seconds until a request arriving now would get a worker, as the queue's
        measured service time predicts: (jobs waiting + 1) x mean service time / workers, rounded
        up, within ``RETRY_AFTER_MIN``..``RETRY_AFTER_MAX``."""
        estimate = (self._waiting + 1) * self._mean_s / self.workers
        return min(RETRY_AFTER_MAX, max(RETRY_AFTER_MIN, math.ceil(estimate)))

    def _reject(self, exc_type, reason: str, message: str):
        self._on_reject(reason)
        return exc_type(message, retry_after=self.retry_after())

    def _superseded(self, superseded: asyncio.Future) -> Superseded:
        self._on_reject("superseded")
        newer = superseded.result()
        return Superseded(f"seq: a newer request of this stream (seq {newer}) arrived while this "
                          f"one waited for a worker; nothing was rendered", newer=newer)

    async def run(self, kind: str, fn: Callable[..., T], *args,
                  superseded: asyncio.Future | None = None) -> T:
        """``fn(*args)`` on a worker thread, or ``Busy`` / ``Unavailable`` / ``Superseded`` (see
        the module docstring). ``kind`` names the job in metrics ("encode", "render", ...);
        ``superseded``: a future that is done when the job is no longer wanted."""
        if self._closed:
            raise self._reject(Unavailable, "shutdown", "the server is shutting down; retry on "
                               "another instance or after the restart")
        if superseded is not None and superseded.done() and not superseded.cancelled():
            raise self._superseded(superseded)
        if self._running + self._waiting >= self.workers + self.queue:
            raise self._reject(Busy, "busy", f"all {self.workers} worker(s) are busy and the "
                               f"queue is full ({self._waiting} of {self.queue} places, "
                               f"iris-serve --queue); retry after the Retry-After seconds")
        await self._acquire(superseded)
        if self._closed:
            self._hand_over()
            raise self._reject(Unavailable, "shutdown", "the server is shutting down")
        self._running += 1
        loop = asyncio.get_running_loop()
        future = loop.run_in_executor(self._executor, self._timed, kind, fn, args)
        future.add_done_callback(self._release)
        # Shielded: a cancelled request leaves its job to finish; the worker is freed only then.
        return await asyncio.shield(future)

    async def _acquire(self, superseded: asyncio.Future | None) -> None:
        """Take a worker: at once when one is free and nobody waits, else wait in line until one
        is handed over, the queue timeout passes or ``superseded`` is done."""
        if self._free > 0 and not self._waiters:
            self._free -= 1
            return
        slot = asyncio.get_running_loop().create_future()
        self._waiters.append(slot)
        self._waiting += 1
        try:
            await asyncio.wait([slot] if superseded is None else [slot, superseded],
                               timeout=self.queue_timeout, return_when=asyncio.FIRST_COMPLETED)
        except BaseException:                      # the request itself was cancelled
            self._leave(slot)
            raise
        finally:
            self._waiting -= 1
        stale = superseded is not None and superseded.done() and not superseded.cancelled()
        if slot.done() and not stale:
            return
        self._leave(slot)
        if stale:
            raise self._superseded(superseded)
        raise self._reject(Unavailable, "timeout", f"waited {self.queue_timeout:g} s for a "
                           f"worker, the most a job may wait (iris-serve --queue-timeout): the "
                           f"server is overloaded; retry after the Retry-After seconds")

    def _leave(self, slot: asyncio.Future) -> None:
        """A waiter gives up: out of the line, or, if a worker was already handed to it, the
        worker goes to the next one."""
        if slot.done() and not slot.cancelled():
            self._hand_over()
        else:
            slot.cancel()
            try:
                self._waiters.remove(slot)
            except ValueError:
                pass

    def _hand_over(self) -> None:
        """A worker is free: to the first job still waiting, else back to the free ones."""
        while self._waiters:
            slot = self._waiters.popleft()
            if not slot.done():
                slot.set_result(None)
                return
        self._free += 1

    def _timed(self, kind: str, fn, args):
        t0 = time.perf_counter()
        try:
            return fn(*args)
        finally:
            seconds = time.perf_counter() - t0
            self._mean_s += EWMA_WEIGHT * (seconds - self._mean_s)
            self._on_job(kind, seconds)

    def _release(self, _future) -> None:
        self._running -= 1
        self._hand_over()

    def close(self) -> None:
        """Refuse new jobs (503); jobs already admitted finish."""
        self._closed = True

    def shutdown(self) -> None:
        """``close`` and wait for the running jobs' threads."""
        self.close()
        self._executor.shutdown(wait=True)
