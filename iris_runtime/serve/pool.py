"""The render worker pool: blocking runtime calls (encode, render, locate) on a fixed number of
threads, with a bounded queue in front and backpressure instead of an unbounded backlog.

ONNX Runtime, OpenCV and numpy release the GIL in their kernels, so threads over one shared
``IrisRuntime`` (which is thread-safe) run jobs in parallel without a copy of the model per
worker. Admission is decided on the event loop, before any work:

- ``workers`` jobs run at once; up to ``queue`` more wait for a worker;
- a job that finds both full is refused at once with ``Busy`` (429 + ``Retry-After``);
- a job that waits longer than ``queue_timeout`` seconds is refused with ``Unavailable`` (503 +
  ``Retry-After``), as is every job after ``close()`` (graceful shutdown).

``Retry-After`` is the expected wait: jobs ahead of the caller times the mean job time (an
exponential average) over the workers. A worker's slot is released when its thread finishes,
not when the request that asked for it goes away, so the pool never runs more than ``workers``
jobs whatever the clients do.
"""
from __future__ import annotations

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

from .errors import Busy, Unavailable

__all__ = ["WorkerPool"]

T = TypeVar("T")


class WorkerPool:
    """``workers`` threads behind a queue of ``queue`` places (see the module docstring).
    ``on_job(kind, seconds)`` is called after every job (metrics); ``on_reject(reason)`` after
    every refusal ("busy", "timeout", "shutdown")."""

    def __init__(self, workers: int, queue: int, queue_timeout: float, *,
                 on_job: Callable[[str, float], None] | None = None,
                 on_reject: Callable[[str], None] | None = None):
        if workers < 1 or queue < 0 or not queue_timeout > 0:
            raise ValueError("workers >= 1, queue >= 0 and queue_timeout > 0 expected")
        self.workers, self.queue, self.queue_timeout = int(workers), int(queue), float(queue_timeout)
        self._executor = ThreadPoolExecutor(self.workers, thread_name_prefix="iris-worker")
        self._slots: asyncio.Semaphore | None = None          # made on the serving loop
        self._waiting = 0
        self._running = 0
        self._closed = False
        self._mean_s = 1.0                                    # until a job has been timed
        self._on_job = on_job or (lambda kind, s: None)
        self._on_reject = on_reject or (lambda reason: None)

    @property
    def waiting(self) -> int:
        """Jobs admitted and waiting for a worker (the queue depth)."""
        return self._waiting

    @property
    def running(self) -> int:
        return self._running

    def _retry_after(self) -> float:
        return (self._waiting + 1) * self._mean_s / self.workers

    def _reject(self, exc_type, reason: str, message: str):
        self._on_reject(reason)
        return exc_type(message, retry_after=self._retry_after())

    async def run(self, kind: str, fn: Callable[..., T], *args) -> T:
        """``fn(*args)`` on a worker thread, or ``Busy`` / ``Unavailable`` (see the module
        docstring). ``kind`` names the job in metrics ("encode", "render", ...)."""
        if self._closed:
            raise self._reject(Unavailable, "shutdown", "the server is shutting down; retry on "
                               "another instance or after the restart")
        if self._slots is None:
            self._slots = asyncio.Semaphore(self.workers)
        if self._running + self._waiting >= self.workers + self.queue:
            raise self._reject(Busy, "busy", f"all {self.workers} workers are busy and "
                               f"{self._waiting} requests wait; retry later")
        self._waiting += 1
        try:
            await asyncio.wait_for(self._slots.acquire(), self.queue_timeout)
        except asyncio.TimeoutError:
            raise self._reject(Unavailable, "timeout", f"waited {self.queue_timeout:g} s for a "
                               f"worker (server overloaded); retry later") from None
        finally:
            self._waiting -= 1
        if self._closed:
            self._slots.release()
            raise self._reject(Unavailable, "shutdown", "the server is shutting down")
        self._running += 1
        loop = asyncio.get_running_loop()
        future = loop.run_in_executor(self._executor, self._timed, kind, fn, args)
        future.add_done_callback(self._release)
        # Shielded: a cancelled request leaves its job to finish; the slot is freed only then.
        return await asyncio.shield(future)

    def _timed(self, kind: str, fn, args):
        t0 = time.perf_counter()
        try:
            return fn(*args)
        finally:
            seconds = time.perf_counter() - t0
            self._mean_s = 0.8 * self._mean_s + 0.2 * seconds
            self._on_job(kind, seconds)

    def _release(self, _future) -> None:
        self._running -= 1
        self._slots.release()

    def close(self) -> None:
        """Refuse new jobs (503); jobs already admitted finish."""
        self._closed = True

    def shutdown(self) -> None:
        """``close`` and wait for the running jobs' threads."""
        self.close()
        self._executor.shutdown(wait=True)
