"""``iris-serve``: an HTTP service over ``IrisRuntime`` (optional extra ``[serve]``: FastAPI,
uvicorn, python-multipart, prometheus-client; torch-free like the rest of ``iris_runtime``).

One module per job: ``app`` (``create_app``: the routers put together), ``routes/`` (one
FastAPI router per concern, each route a call of the runtime's public API), ``models`` (the
request and response bodies as Pydantic models, from which FastAPI writes the OpenAPI schema),
``routing`` (what is checked before a body is read), ``service`` (the state the routes share and
the server's own limits), ``errors`` (every error as ``{"error": {"type", "message"}}`` and the
one status table), ``store`` (the memory-bounded LRU of encoded scenes), ``pool`` (the bounded
worker pool, its backpressure and ``Retry-After``), ``metrics`` (Prometheus), ``observe`` (request
ids, body limit, JSON access logs), ``cli`` (the command), ``static/`` (the viewer page). The
contract and how to operate it: docs/SERVING.md.
"""
__all__ = ["ServeConfig", "RenderRequest", "OrbitRequest", "create_app", "warm_up"]


def __getattr__(name: str):
    # Lazy: ``iris-serve`` imports this package before it can say that fastapi is missing.
    if name in __all__:
        from . import app
        return getattr(app, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
