"""Prometheus metrics of the service (prometheus-client), on a registry of the app's own so that
several apps in one process (tests) never share counters.

- ``iris_http_requests_total{method, route, status}`` and
  ``iris_http_request_duration_seconds{method, route}``: every request, by route *template*
  (``/scenes/{scene_id}/render``, so ids never make new series; unmatched paths are
  ``<unmatched>``);
- ``iris_job_duration_seconds{kind}``: time on a worker per job kind (encode, render, locate,
  orbit, cameras); ``iris_jobs_rejected_total{reason}``: busy (429), timeout and shutdown (503),
  superseded (409: a render of a stream made stale by a newer one, never rendered);
- ``iris_queue_depth``, ``iris_jobs_running``, ``iris_scenes``, ``iris_scene_store_bytes``,
  ``iris_scene_evictions_total``: read from the pool and the store at scrape time;
- ``iris_job_service_seconds``: the pool's exponentially weighted mean time of a job on a worker,
  from which ``Retry-After`` is estimated (``pool.WorkerPool.retry_after``);
- ``process_*`` (resident memory, CPU seconds, open files) and ``python_*``: the standard
  collectors.
"""
from __future__ import annotations

from prometheus_client import (CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram,
                               PlatformCollector, ProcessCollector, generate_latest)

__all__ = ["Metrics"]

# Latency buckets: a health check is ~1 ms, a render of a model-size view 0.1-10 s, an orbit video
# or an encode with the camera solve of many photos up to minutes.
_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0)


class Metrics:
    def __init__(self):
        r = self.registry = CollectorRegistry()
        ProcessCollector(registry=r)
        PlatformCollector(registry=r)
        self.requests = Counter("iris_http_requests", "HTTP requests by route template and status",
                                ["method", "route", "status"], registry=r)
        self.latency = Histogram("iris_http_request_duration_seconds",
                                 "HTTP request latency by route template", ["method", "route"],
                                 buckets=_BUCKETS, registry=r)
        self.jobs = Histogram("iris_job_duration_seconds", "Time on a worker per job kind",
                              ["kind"], buckets=_BUCKETS, registry=r)
        self.rejected = Counter("iris_jobs_rejected", "Jobs refused by the worker pool",
                                ["reason"], registry=r)
        self.queue_depth = Gauge("iris_queue_depth", "Jobs waiting for a worker", registry=r)
        self.running = Gauge("iris_jobs_running", "Jobs running on a worker", registry=r)
        self.service_seconds = Gauge("iris_job_service_seconds", "Exponentially weighted mean "
                                     "time of a job on a worker (Retry-After's estimate)",
                                     registry=r)
        self.scenes = Gauge("iris_scenes", "Scenes held in the scene store", registry=r)
        self.store_bytes = Gauge("iris_scene_store_bytes", "Bytes of the scenes held", registry=r)
        self.evictions = Counter("iris_scene_evictions", "Scenes evicted from the store (LRU)",
                                 registry=r)

    def bind(self, pool, store) -> None:
        """Read the gauges from ``pool`` and ``store`` at scrape time."""
        self.queue_depth.set_function(lambda: pool.waiting)
        self.running.set_function(lambda: pool.running)
        self.service_seconds.set_function(lambda: pool.mean_seconds)
        self.scenes.set_function(lambda: len(store))
        self.store_bytes.set_function(lambda: store.nbytes)

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        self.requests.labels(method, route, str(status)).inc()
        self.latency.labels(method, route).observe(seconds)

    def observe_job(self, kind: str, seconds: float) -> None:
        self.jobs.labels(kind).observe(seconds)

    def observe_reject(self, reason: str) -> None:
        self.rejected.labels(reason).inc()

    def exposition(self) -> tuple[bytes, str]:
        """(body, content type) of a scrape."""
        return generate_latest(self.registry), CONTENT_TYPE_LATEST
