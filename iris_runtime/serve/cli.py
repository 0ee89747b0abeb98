"""``iris-serve MODEL_DIR [--host 127.0.0.1] [--port 8000] ...``: the HTTP service on uvicorn.

Loads the model once, runs both graphs on blank photos (a broken model stops here, with one line
on stderr and exit code 2, before any client sees it), then serves ``iris_runtime.serve.app`` on
uvicorn. Logs are JSON lines on stderr; the first line after start-up is ``{"message":
"listening", "host", "port"}`` with the bound port (``--port 0`` picks a free one). SIGTERM or
Ctrl-C shut down gracefully: the socket closes, requests in flight finish (up to
``--shutdown-timeout`` seconds), then the worker pool drains. How to operate it:
docs/SERVING.md.
"""
from __future__ import annotations

import argparse
import logging
import logging.config
import os
import sys
from pathlib import Path

from ..cli import EXIT_ERROR, _Parser, _non_negative, _positive, providers_arg

__all__ = ["build_parser", "main"]

log = logging.getLogger("iris.serve")


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds > 0, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected seconds > 0, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    cpus = len(os.sched_getaffinity(0))
    p = _Parser(prog="iris-serve",
                description="Serve an exported IRIS model over HTTP (FastAPI on uvicorn, ONNX "
                            "Runtime, no torch): POST /scenes with photos, then POST "
                            "/scenes/{id}/render with a pose; a viewer page at /. "
                            "See docs/SERVING.md.")
    p.add_argument("model_dir", metavar="MODEL_DIR", help="directory written by iris-export")
    net = p.add_argument_group("network")
    net.add_argument("--host", default="127.0.0.1",
                     help="address to bind (default 127.0.0.1; 0.0.0.0 exposes it to the network)")
    net.add_argument("--port", type=_non_negative, default=8000,
                     help="port (default 8000; 0: a free port, logged as 'listening')")
    net.add_argument("--token-file", metavar="FILE",
                     help="require 'Authorization: Bearer <token>' on /scenes, the token being "
                          "the first line of FILE (default: no authentication)")
    work = p.add_argument_group("work and backpressure")
    work.add_argument("--workers", type=_positive, default=cpus,
                      help=f"jobs (encode, render, locate) running at once (default: the usable "
                           f"CPUs, {cpus})")
    work.add_argument("--threads", type=_positive, default=None,
                      help="ONNX Runtime intra-op threads per job (default: CPUs // workers)")
    work.add_argument("--queue", type=_non_negative, default=8,
                      help="jobs waiting for a worker before requests get 429 (default 8)")
    work.add_argument("--queue-timeout", type=_seconds, default=30.0,
                      help="seconds a job may wait for a worker before 503 (default 30)")
    work.add_argument("--precision", choices=["float32", "int8"], default="float32",
                      help="default renderer graph (requests may ask for the other)")
    work.add_argument("--providers", type=providers_arg, default=None, metavar="A,B",
                      help="ONNX Runtime execution providers in priority order, e.g. "
                           "CUDAExecutionProvider,CPUExecutionProvider (default: the CPU)")
    lim = p.add_argument_group("limits (over a limit: 413)")
    lim.add_argument("--store-mb", type=_positive, default=512,
                     help="memory of the scene store, least recently used scenes evicted "
                          "(default 512)")
    lim.add_argument("--max-scenes", type=_positive, default=256,
                     help="scenes held at most (default 256)")
    lim.add_argument("--max-photos", type=_positive, default=16,
                     help="photos per POST /scenes (default 16, and at most the model's)")
    lim.add_argument("--max-upload-mb", type=_positive, default=64,
                     help="request body size (default 64)")
    lim.add_argument("--max-photo-pixels", type=_positive, default=40_000_000,
                     help="pixels per uploaded photo (default 40000000)")
    lim.add_argument("--max-output-pixels", type=_positive, default=1024 * 1024,
                     help="pixels per rendered view (default 1048576 = 1024x1024)")
    lim.add_argument("--max-orbit-frames", type=_positive, default=120,
                     help="frames per orbit video (default 120)")
    ops = p.add_argument_group("operation")
    ops.add_argument("--shutdown-timeout", type=_seconds, default=30.0,
                     help="seconds requests in flight get to finish on SIGTERM (default 30)")
    ops.add_argument("--log-level", choices=["debug", "info", "warning", "error"],
                     default="info", help="log level (JSON lines on stderr; default info)")
    return p


def read_token(path: str) -> str:
    """The bearer token: the first line of ``path``, stripped; ``ValueError`` when empty."""
    try:
        lines = Path(path).read_text(encoding="utf-8").strip().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"--token-file {path}: cannot read it "
                         f"({getattr(exc, 'strerror', None) or exc})") from None
    if not lines or not lines[0].strip():
        raise ValueError(f"--token-file {path}: the file holds no token")
    return lines[0].strip()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        import uvicorn
        from .app import ServeConfig, create_app, warm_up
        from .observe import log_config
    except ImportError as exc:
        print(f"iris-serve: error: {exc.name} is not installed; pip install 'iris-nvs[serve]'",
              file=sys.stderr)
        return EXIT_ERROR
    from ..errors import IrisError
    from ..limits import MAX_OUTPUT_PIXELS
    from ..runtime import IrisRuntime

    logging.config.dictConfig(log_config(args.log_level))
    try:
        token = read_token(args.token_file) if args.token_file else None
        if args.max_output_pixels > MAX_OUTPUT_PIXELS:
            raise ValueError(f"--max-output-pixels: at most {MAX_OUTPUT_PIXELS} (the runtime's)")
        threads = args.threads or max(1, len(os.sched_getaffinity(0)) // args.workers)
        rt = IrisRuntime(args.model_dir, threads=threads, precision=args.precision,
                         providers=args.providers)
        warm_up(rt)
        config = ServeConfig(
            workers=args.workers, queue=args.queue, queue_timeout=args.queue_timeout,
            store_bytes=args.store_mb * 2**20, max_scenes=args.max_scenes,
            max_photos=args.max_photos, max_upload_bytes=args.max_upload_mb * 2**20,
            max_photo_pixels=args.max_photo_pixels, max_output_pixels=args.max_output_pixels,
            max_orbit_frames=args.max_orbit_frames, token=token)
    except (IrisError, OSError, ValueError) as exc:
        print(f"iris-serve: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}",
              file=sys.stderr)
        return EXIT_ERROR

    class Server(uvicorn.Server):
        async def startup(self, sockets=None):
            await super().startup(sockets)
            for server in self.servers:
                for sock in server.sockets:
                    host, port = sock.getsockname()[:2]
                    log.info("listening", extra={"fields": {"host": host, "port": port}})

    server = Server(uvicorn.Config(
        create_app(rt, config), host=args.host, port=args.port, log_config=None,
        access_log=False, lifespan="on", server_header=False,
        timeout_graceful_shutdown=args.shutdown_timeout))
    try:
        server.run()
    except KeyboardInterrupt:
        pass
    return 0 if server.started else EXIT_ERROR


if __name__ == "__main__":
    sys.exit(main())
