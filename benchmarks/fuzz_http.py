"""Property-based fuzz of iris-serve's HTTP API against a real server process.

    python benchmarks/fuzz_http.py MODEL_DIR --requests 2000 \
        [--json benchmarks/results/fuzz_http.json]

Starts ``iris-serve MODEL_DIR`` on 127.0.0.1 (a random port) with a bearer token and tight limits
(``SERVER_ARGS``: renders of at most 256 pixels, 2 orbit frames, 4 photos of at most 100000
pixels, 1 MB bodies), then sends ``--requests`` requests drawn by Hypothesis strategies over
every route (``REQUESTS``): methods, paths with the live scene's id, ids of deleted and made-up
scenes and unknown routes, Content-Types right and wrong, the token right, wrong or missing,
JSON bodies built from the request models' fields with values of every JSON type (NaN, inf,
huge and negative numbers, poses rigid, nearly rigid, non-rigid, far, of the wrong shape),
multipart bodies of real, generated, 16-bit, truncated, empty, random and bomb-sized photos
(a PNG header declaring billions of pixels), unknown and repeated fields, bodies cut short, and
query strings. Every answer must be below 500, carry no traceback, and an error must be the one
error body ``{"error": {"type", "message"}}``; the server must answer /healthz after, and log
no error. The JSON records the requests, the status histogram, the 5xx count, the traceback
count, the error bodies of the wrong shape, the routes hit, the seconds and the server's flags.

``tests/test_http_fuzz.py`` runs the same strategies for ~300 requests. Every loop is bounded
(``--requests``, and a per-request timeout), traffic goes to 127.0.0.1 only, and the script stops
the server itself.
"""
from __future__ import annotations

import argparse
import io
import json
import struct
import sys
import time
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.serve_process import ServeProcess  # noqa: E402

PHOTOS = sorted((REPO / "samples" / "heldout-1000003").glob("frame_*.png"))
TOKEN = "fuzz-token"
SERVER_ARGS = ("--workers", "1", "--queue", "4", "--max-photos", "4", "--max-upload-mb", "1",
               "--max-photo-pixels", "100000", "--max-output-pixels", "256",
               "--max-orbit-frames", "2", "--store-mb", "64", "--max-scenes", "64")
TRACEBACK_MARKS = ("Traceback (most recent call last)", 'File "')


# -- the server -----------------------------------------------------------------------------------

class FuzzServer(ServeProcess):
    """``iris-serve MODEL_DIR --port 0 --token-file ... SERVER_ARGS ARGS`` on 127.0.0.1 with the
    token ``TOKEN`` (``ServeProcess``: ``url``, ``lines``, ``error_lines()``, ``stop()``)."""

    def __init__(self, model_dir, *args: str, timeout: float = 180.0):
        super().__init__(model_dir, *SERVER_ARGS, *args, token=TOKEN, timeout=timeout)


# -- strategies -----------------------------------------------------------------------------------

def _png(a: np.ndarray, mode: str | None = None) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(a, mode).save(buf, format="PNG")
    return buf.getvalue()


def png_header(width: int, height: int) -> bytes:
    """A PNG whose header declares width x height and holds almost no data."""
    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))
    return (b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


@st.composite
def photos(draw) -> bytes:
    """One uploaded file: a sample photo, a generated image (grey, RGB, RGBA, 16-bit, JPEG; 1 to
    400 pixels a side), one cut short, random bytes, nothing, or a header declaring a bomb."""
    kind = draw(st.sampled_from(["sample"] * 6 + ["png", "png16", "jpeg", "cut", "bytes",
                                                  "empty", "bomb", "large"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    h, w = draw(st.integers(1, 48)), draw(st.integers(1, 48))
    if kind == "sample":
        return draw(st.sampled_from(PHOTOS)).read_bytes()
    if kind == "png":
        channels = draw(st.sampled_from([None, 3, 4]))
        shape = (h, w) if channels is None else (h, w, channels)
        return _png(rng.integers(0, 256, shape, dtype=np.uint8))
    if kind == "png16":
        return _png(rng.integers(0, 65536, (h, w), dtype=np.uint16))     # 16-bit grey
    if kind == "jpeg":
        buf = io.BytesIO()
        Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(buf, "JPEG")
        return buf.getvalue()
    if kind == "cut":
        data = PHOTOS[0].read_bytes()
        return data[:draw(st.integers(0, len(data) - 1))]
    if kind == "bytes":
        return draw(st.binary(max_size=256))
    if kind == "empty":
        return b""
    if kind == "bomb":
        return png_header(draw(st.integers(1, 2**31 - 1)), draw(st.integers(1, 2**31 - 1)))
    side = draw(st.integers(317, 420))                        # just over 100000 pixels
    return _png(np.full((side, side, 3), 90, np.uint8))


json_scalars = st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70),
                         st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12))
json_values = st.recursive(json_scalars, lambda inner: st.lists(inner, max_size=4)
                           | st.dictionaries(st.text(max_size=6), inner, max_size=4),
                           max_leaves=12)


@st.composite
def poses(draw):
    """A world_from_cam: rigid near the scene, rigid but far, nearly rigid (snapped), not rigid,
    with NaN/inf, of the wrong shape, or any JSON value."""
    kind = draw(st.sampled_from(["rigid", "rigid", "far", "near_rigid", "matrix", "shape",
                                 "any"]))
    q = np.array(draw(st.lists(st.floats(-1, 1), min_size=4, max_size=4)))
    q = q / np.linalg.norm(q) if np.linalg.norm(q) > 1e-3 else np.array([1.0, 0, 0, 0])
    w, x, y, z = q
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = draw(st.lists(st.floats(-0.5, 0.5), min_size=3, max_size=3))
    if kind == "far":
        T[:3, 3] *= draw(st.sampled_from([1e3, 1e6, 1e15, 1e300]))
    elif kind == "near_rigid":
        T[:3, :3] += draw(st.floats(1e-5, 2e-3)) * np.sign(R + 1e-9)
    elif kind == "matrix":
        cells = st.floats(allow_nan=True, allow_infinity=True) | st.integers(-10, 10)
        return draw(st.lists(st.lists(cells, min_size=4, max_size=4), min_size=4, max_size=4))
    elif kind == "shape":
        return draw(st.lists(st.lists(st.floats(-2, 2), max_size=5), max_size=5))
    elif kind == "any":
        return draw(json_values)
    return T.tolist()


sizes = st.one_of(st.integers(1, 16), st.integers(1, 16), st.integers(-3, 0),
                  st.integers(17, 2**40), st.sampled_from([2**63, -(2**63), 10**30]), json_scalars)
qualities = st.sampled_from(["auto", "exact", "balanced", "fast", "adaptive", "ultra", ""]) \
    | json_scalars
render_bodies = st.fixed_dictionaries(
    {"world_from_cam": poses(), "height": sizes},
    optional={"width": sizes, "quality": qualities,
              "precision": st.sampled_from(["float32", "int8", "fp16"]) | json_scalars,
              "depth": st.booleans() | json_scalars,
              "stream": st.sampled_from(["fuzz", "a b", "", "x" * 65]) | json_scalars,
              "seq": st.integers(-2, 2**54) | json_scalars,
              "colour": json_values})
orbit_bodies = st.fixed_dictionaries(
    {}, optional={"frames": st.integers(-1, 4) | json_scalars, "fps": st.integers(-1, 200)
                  | json_scalars, "height": sizes, "width": sizes, "quality": qualities,
                  "extra": json_values})
json_bodies = st.one_of(render_bodies, render_bodies, orbit_bodies, json_values)


@dataclass
class FuzzRequest:
    """One request: ``route`` names its kind; ``scene``: which scene id goes in the path."""
    route: str
    method: str
    scene: str = "live"                      # live, created, deleted, made-up
    json_body: object = None
    files: list = field(default_factory=list)
    fields: dict = field(default_factory=dict)
    ctype: str = "right"                     # right, wrong, none, odd
    auth: str = "right"                      # right, wrong, none
    cut: float | None = None                 # send only this fraction of the body
    query: dict = field(default_factory=dict)
    path: str = ""
    body: bytes | None = None


scenes = st.sampled_from(["live"] * 6 + ["created", "deleted", "made-up"])
auths = st.sampled_from(["right"] * 14 + ["wrong", "none"])
ctypes = st.sampled_from(["right"] * 14 + ["wrong", "none", "odd"])
cuts = st.sampled_from([None] * 9 + ["cut"]).flatmap(
    lambda c: st.none() if c is None else st.floats(0.0, 0.99))
file_fields = st.sampled_from(["images"] * 6 + ["image", "photos", "cameras"])


@st.composite
def multiparts(draw, field_name: str, most: int):
    files = [(draw(file_fields) if draw(st.integers(0, 19)) == 0 else field_name,
              (f"p{i}.png", draw(photos()), "image/png"))
             for i in range(draw(st.integers(0, most)))]
    values = st.sampled_from(["model", "epipolar", "refined", "", "magic"]) | st.text(max_size=10)
    fields = draw(st.sampled_from([{}, {}, {"cameras": "model"}, None]))
    if fields is None:
        fields = draw(st.dictionaries(st.sampled_from(["cameras", "images", "colour", "x"]),
                                      values, max_size=2))
    return files, fields


@st.composite
def requests(draw) -> FuzzRequest:
    route = draw(st.sampled_from(["scenes", "scenes", "render", "render", "render", "render",
                                  "locate", "orbit", "orbit.mp4", "get", "delete", "cameras",
                                  "health", "static", "random"]))
    common = {"scene": draw(scenes), "auth": draw(auths), "ctype": draw(ctypes)}
    if route in ("render", "orbit.mp4"):
        body = draw(orbit_bodies if route == "orbit.mp4" else json_bodies)
        return FuzzRequest(route, "POST", json_body=body, cut=draw(cuts), **common)
    if route in ("scenes", "locate"):
        files, fields = draw(multiparts("images" if route == "scenes" else "image",
                                        6 if route == "scenes" else 2))
        return FuzzRequest(route, "POST", files=files, fields=fields, cut=draw(cuts), **common)
    if route == "orbit":
        frames = draw(st.none() | st.integers(-2, 4).map(str) | st.text(max_size=6))
        return FuzzRequest(route, "GET", query={} if frames is None else {"frames": frames},
                           **common)
    if route in ("get", "delete", "cameras"):
        return FuzzRequest(route, "DELETE" if route == "delete" else "GET", **common)
    if route == "health":
        return FuzzRequest(route, "GET", path=draw(st.sampled_from(
            ["/healthz", "/metrics", "/", "/favicon.ico", "/openapi.json", "/docs"])), **common)
    if route == "static":
        return FuzzRequest(route, "GET", path="/static/" + draw(st.sampled_from(
            ["viewer.js", "viewer.css", "index.html", "../app.py", "nope", "%2e%2e/x"])),
                           **common)
    path = "/" + "/".join(draw(st.lists(st.sampled_from(
        ["scenes", "{id}", "render", "locate", "orbit", "x", "..", "%00", "healthz"]),
        max_size=4)))
    return FuzzRequest(route, draw(st.sampled_from(["GET", "POST", "PUT", "PATCH", "DELETE",
                                                    "HEAD", "OPTIONS"])), path=path,
                       body=draw(st.none() | st.binary(max_size=64)), **common)


# -- sending and checking -------------------------------------------------------------------------

class FuzzSession:
    """Sends ``FuzzRequest``s to a server and checks each answer; ``stats`` counts them.
    ``strict``: a failed check raises ``AssertionError`` (the test), else it is only counted."""

    def __init__(self, url: str, strict: bool = True, timeout: float = 120.0):
        self.client = httpx.Client(base_url=url, timeout=timeout)
        self.strict = strict
        self.statuses: Counter = Counter()
        self.routes: Counter = Counter()
        self.failures: list[dict] = []
        auth = {"Authorization": f"Bearer {TOKEN}"}
        files = [("images", (p.name, p.read_bytes(), "image/png")) for p in PHOTOS[:2]]
        self.live = self._new_scene(files, auth)
        self.deleted = self._new_scene(files, auth)
        assert self.client.delete(f"/scenes/{self.deleted}", headers=auth).status_code == 204
        self.created: list[str] = []

    def _new_scene(self, files, auth) -> str:
        r = self.client.post("/scenes", files=files, headers=auth)
        assert r.status_code == 201, r.text
        return r.json()["scene_id"]

    def _scene_id(self, which: str, route: str) -> str:
        if which == "live" and route == "delete":         # the live scene stays
            which = "created"
        if which == "created":
            return self.created[-1] if self.created else (
                self.deleted if route == "delete" else self.live)
        return {"deleted": self.deleted, "made-up": "no-such-scene"}.get(which, self.live)

    def build(self, req: FuzzRequest) -> httpx.Request:
        """The HTTP request ``req`` describes."""
        sid = self._scene_id(req.scene, req.route)
        headers = {}
        if req.auth == "right":
            headers["Authorization"] = f"Bearer {TOKEN}"
        elif req.auth == "wrong":
            headers["Authorization"] = "Bearer not-the-token"
        path = {"scenes": "/scenes", "render": f"/scenes/{sid}/render",
                "locate": f"/scenes/{sid}/locate", "orbit": f"/scenes/{sid}/orbit",
                "orbit.mp4": f"/scenes/{sid}/orbit.mp4", "get": f"/scenes/{sid}",
                "delete": f"/scenes/{sid}", "cameras": f"/scenes/{sid}/cameras.png"}.get(
            req.route, req.path.replace("{id}", sid))
        if req.json_body is not None or req.route in ("render", "orbit.mp4"):
            body = json.dumps(req.json_body, allow_nan=True).encode()
            ctype = "application/json"
        elif req.route in ("scenes", "locate"):
            made = httpx.Request("POST", "http://x/", files=req.files or None,
                                 data=req.fields or None)
            body = made.read()
            ctype = made.headers.get("content-type", "multipart/form-data")
            if not req.files:                   # httpx sends fields alone url-encoded
                ctype = made.headers.get("content-type", "application/x-www-form-urlencoded")
        else:
            body, ctype = req.body or b"", None
        if req.cut is not None:
            body = body[:int(len(body) * req.cut)]
        ctype = {"right": ctype, "wrong": "text/plain", "none": None,
                 "odd": "multipart/form-data; boundary=" if ctype and "json" in ctype
                 else "application/json; charset=utf-16"}[req.ctype]
        if ctype:
            headers["Content-Type"] = ctype
        return self.client.build_request(req.method, path, content=body or None,
                                         headers=headers, params=req.query or None)

    def send(self, req: FuzzRequest) -> httpx.Response:
        r = self.client.send(self.build(req))
        self.statuses[r.status_code] += 1
        self.routes[req.route] += 1
        if req.route == "scenes" and r.status_code == 201:
            self.created.append(r.json()["scene_id"])
        problems = self.check(req, r)
        if problems:
            self.failures.append({"request": repr(req)[:2000], "status": r.status_code,
                                  "problems": problems, "body": r.text[:500]})
            if self.strict:
                raise AssertionError(f"{problems}: {req!r:.1500} -> {r.status_code} "
                                     f"{r.text[:500]}")
        return r

    @staticmethod
    def check(req: FuzzRequest, r: httpx.Response) -> list[str]:
        """What is wrong with the answer ``r`` to ``req`` (nothing: [])."""
        problems = []
        if r.status_code >= 500:
            problems.append("5xx")
        ctype = r.headers.get("content-type", "")
        text = r.text if ("json" in ctype or "text" in ctype or "html" in ctype) else ""
        if any(mark in text for mark in TRACEBACK_MARKS) and "javascript" not in ctype:
            problems.append("traceback")
        if r.status_code >= 400 and req.method != "HEAD":
            try:
                body = r.json()
                ok = set(body) == {"error"} and set(body["error"]) == {"type", "message"}
            except ValueError:
                ok = False
            if not ok:
                problems.append("error body")
        return problems

    def healthy(self) -> bool:
        return self.client.get("/healthz").status_code == 200

    def summary(self) -> dict:
        return {"requests": sum(self.statuses.values()),
                "status": {str(k): v for k, v in sorted(self.statuses.items())},
                "5xx": sum(v for k, v in self.statuses.items() if k >= 500),
                "tracebacks": sum("traceback" in f["problems"] for f in self.failures),
                "error_bodies_of_wrong_shape": sum("error body" in f["problems"]
                                                   for f in self.failures),
                "routes": dict(sorted(self.routes.items())),
                "scenes_created": len(self.created)}


def fuzz(session: FuzzSession, n: int, derandomize: bool = False, shrink: bool = True) -> None:
    """``n`` requests drawn by Hypothesis (``requests()``) through ``session``."""
    phases = [Phase.generate, Phase.shrink] if shrink else [Phase.generate]

    @settings(max_examples=n, deadline=None, database=None, derandomize=derandomize,
              phases=phases, suppress_health_check=list(HealthCheck))
    @given(req=requests())
    def one(req):
        session.send(req)
    one()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model_dir")
    p.add_argument("--requests", type=int, default=2000)
    p.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "fuzz_http.json"))
    args = p.parse_args(argv)
    server = FuzzServer(args.model_dir)
    t0 = time.perf_counter()
    try:
        session = FuzzSession(server.url, strict=False)
        sent = 0
        while sent < args.requests:                 # Hypothesis may stop a run early
            fuzz(session, args.requests - sent, shrink=False)
            now = sum(session.statuses.values())
            if now == sent:
                break
            sent = now
        healthy = session.healthy()
        model = session.client.get("/healthz").json()["model"] if healthy else {}
        result = {**session.summary(), "healthy_after": healthy,
                  "server_log_errors": len(server.error_lines()),
                  "seconds": round(time.perf_counter() - t0, 1),
                  "server_args": list(SERVER_ARGS), "model_dir": args.model_dir,
                  "model": model.get("name"), "explicit_rgb": model.get("explicit_rgb"),
                  "failures": session.failures[:20]}
    finally:
        server.stop()
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "failures"}, indent=1))
    bad = result["5xx"] or result["tracebacks"] or result["error_bodies_of_wrong_shape"]
    return 1 if bad or not result["healthy_after"] else 0


if __name__ == "__main__":
    sys.exit(main())
