"""A bounded property-based fuzz of iris-serve's HTTP API against a real server process
(``benchmarks/fuzz_http.py``'s Hypothesis strategies over every route, ~300 requests): no 5xx,
no traceback in any body, every error the one error body, and the server healthy after with no
error logged. The long run is ``python benchmarks/fuzz_http.py MODEL_DIR --requests 2000``."""
from __future__ import annotations

import pytest

pytest.importorskip("httpx")
pytest.importorskip("hypothesis")
pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")

from benchmarks.fuzz_http import FuzzServer, FuzzSession, fuzz  # noqa: E402

REQUESTS = 300


@pytest.fixture(scope="module")
def fuzz_server(model_dir):
    srv = FuzzServer(model_dir)
    try:
        yield srv
    finally:
        srv.stop()


def test_http_fuzz(fuzz_server):
    session = FuzzSession(fuzz_server.url, strict=True)
    fuzz(session, REQUESTS, derandomize=True)
    summary = session.summary()
    assert summary["requests"] >= REQUESTS * 0.9, summary
    assert summary["5xx"] == 0 and summary["tracebacks"] == 0, summary
    assert session.healthy()
    assert not fuzz_server.error_lines(), fuzz_server.error_lines()[:3]
    # The fuzz reached the routes' work, not only their refusals.
    assert summary["status"].get("200", 0) + summary["status"].get("201", 0) >= 20, summary
