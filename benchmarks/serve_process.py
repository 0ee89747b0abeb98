"""A real ``iris-serve`` process on 127.0.0.1, started and stopped by the caller.

``ServeProcess(MODEL_DIR, *ARGS, token=None)`` runs
``python -m iris_runtime.serve.cli MODEL_DIR --host 127.0.0.1 --port 0 [--token-file F] ARGS``
from the repository with ``OMP_NUM_THREADS=1``, reads the bound port from its JSON "listening"
log line (waiting at most ``timeout`` s) and keeps every line it logs. The benchmarks that drive
a server (``fuzz_http.py``, ``viewer_drag.py``, ``serve_load.py``) and the tests' ``IrisServer``
(tests/test_serve.py) share it. Every wait is bounded; ``stop()`` sends SIGTERM, then kills.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import urllib.request
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


class ServeProcess:
    """``iris-serve MODEL_DIR --port 0 ... ARGS`` on 127.0.0.1: ``url``, ``port``, ``proc``,
    ``lines`` (its log, one JSON record a line), ``error_lines()``, ``metric()``, ``stop()``.

    ``token``: written to a temporary file passed as ``--token-file`` (removed by ``stop()``);
    ``env``: variables added to the server's environment; ``timeout``: seconds to wait for the
    "listening" line. A server that exits or stays silent that long is stopped and
    ``RuntimeError`` raised, with the last lines of its log."""

    def __init__(self, model_dir, *args: str, token: str | None = None, timeout: float = 180.0,
                 env: dict[str, str] | None = None):
        self._tmp = None
        token_args: list[str] = []
        if token is not None:
            self._tmp = tempfile.TemporaryDirectory(prefix="iris-serve-")
            token_file = Path(self._tmp.name) / "token"
            token_file.write_text(token + "\n")
            token_args = ["--token-file", str(token_file)]
        cmd = [sys.executable, "-m", "iris_runtime.serve.cli", str(model_dir), "--host",
               "127.0.0.1", "--port", "0", *token_args, *args]
        self.proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True,
                                     env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})})
        self.lines: list[str] = []
        self.port: int | None = None
        self._ready = threading.Event()
        threading.Thread(target=self._drain, daemon=True).start()
        if not self._ready.wait(timeout) or self.port is None:
            self.stop()
            raise RuntimeError("iris-serve did not start:\n" + "\n".join(self.lines[-20:]))
        self.url = f"http://127.0.0.1:{self.port}"

    def _drain(self) -> None:
        """Keep the server's log lines; the first "listening" line gives the port."""
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))
            if self.port is None and '"listening"' in line:
                self.port = json.loads(line)["port"]
                self._ready.set()
        self._ready.set()                                  # exited before listening

    def error_lines(self) -> list[str]:
        """The log lines at level "error"."""
        return [line for line in list(self.lines) if '"level": "error"' in line]

    def metric(self, name: str, labels: str = "") -> float:
        """The value of metric ``name{labels}`` in /metrics (0 when absent)."""
        text = urllib.request.urlopen(self.url + "/metrics", timeout=30).read().decode()
        key = name + (("{" + labels + "}") if labels else "")
        for line in text.splitlines():
            if line.startswith(key + " "):
                return float(line.split()[1])
        return 0.0

    def stop(self, timeout: float = 30.0) -> int | None:
        """SIGTERM, up to ``timeout`` s for the exit, then SIGKILL (10 s more); remove the token
        file. The exit code (None only if even SIGKILL did not end it in time)."""
        try:
            if self.proc.poll() is None:
                self.proc.send_signal(signal.SIGTERM)
                try:
                    self.proc.wait(timeout)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    try:
                        self.proc.wait(10)
                    except subprocess.TimeoutExpired:
                        pass
        finally:
            if self._tmp is not None:
                self._tmp.cleanup()
                self._tmp = None
        return self.proc.returncode
