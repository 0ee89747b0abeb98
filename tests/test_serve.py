"""iris-serve against a real server process: the contract of docs/SERVING.md.

Each server is a subprocess (``python -m iris_runtime.serve.cli MODEL --port 0``) on 127.0.0.1,
started from an exported model (``model_dir``: IRIS_TEST_MODEL_DIR in the torch-free CI
environment), read from its JSON log for the bound port, with bounded waits, and always stopped
(SIGTERM, then SIGKILL) by its fixture. Renders are compared with ``IrisRuntime.render`` in this
process on the same photos and pose. Also here: the ONNX Runtime ``providers`` pass-through
(CUDA where onnxruntime has it).
"""
from __future__ import annotations

import dataclasses
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
pytest.importorskip("fastapi")
pytest.importorskip("uvicorn")
pytest.importorskip("prometheus_client")
from PIL import Image  # noqa: E402

from benchmarks.serve_process import ServeProcess  # noqa: E402
from iris_runtime import IrisRuntime  # noqa: E402
from iris_runtime.errors import InputError  # noqa: E402

from .tolerances import encoder_tol  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PHOTOS = sorted((REPO / "samples" / "heldout-1000003").glob("frame_*.png"))
START_TIMEOUT = 120.0


class IrisServer(ServeProcess):
    """A running ``iris-serve`` subprocess (``benchmarks/serve_process.py``): ``url``, ``proc``,
    ``lines``, ``logs`` (its JSON lines parsed), ``stop()`` (the exit code); ``env``: variables
    added to its environment."""

    def __init__(self, model_dir, *args: str, env: dict[str, str] | None = None):
        super().__init__(model_dir, *args, env=env, timeout=START_TIMEOUT)

    @property
    def logs(self) -> list[dict]:
        return [json.loads(line) for line in list(self.lines) if line.startswith("{")]


@pytest.fixture(scope="module")
def server(model_dir):
    """Two workers and tight limits, so that every limit can be hit with small requests."""
    srv = IrisServer(model_dir, "--workers", "2", "--queue", "16", "--max-photos", "4",
                     "--max-upload-mb", "1", "--max-photo-pixels", "100000",
                     "--max-output-pixels", "4096", "--max-orbit-frames", "8")
    try:
        yield srv
    finally:
        srv.stop()


@pytest.fixture(scope="module")
def client(server):
    with httpx.Client(base_url=server.url, timeout=120.0) as c:
        yield c


@pytest.fixture(scope="module")
def scene(client):
    """Photos 0-2 encoded by the server: (its JSON, the photo paths)."""
    r = client.post("/scenes", files=[("images", (p.name, p.read_bytes(), "image/png"))
                                      for p in PHOTOS[:3]])
    assert r.status_code == 201, r.text
    return r.json(), PHOTOS[:3]


@pytest.fixture(scope="module")
def rt(model_dir):
    return IrisRuntime(model_dir, threads=1)


def png_pixels(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)))


def novel_pose(scene_json) -> list:
    """Input view 1's pose turned by 5 degrees about its y axis: no input camera's."""
    T = np.array(scene_json["world_from_cam"][1])
    a = np.deg2rad(5.0)
    turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    T[:3, :3] = T[:3, :3] @ turn
    return T.tolist()


def away_pose(scene_json) -> np.ndarray:
    """A camera one unit behind input view 1, looking away from the scene: every sample of its
    rays lies behind the photos' cameras, so no ray meets a photo's view."""
    T = np.array(scene_json["world_from_cam"][1])
    forward = T[:3, 2].copy()
    T[:3, 0], T[:3, 2] = -T[:3, 0], -T[:3, 2]          # turned half a turn about its y axis
    T[:3, 3] -= forward
    return T


def render(client, scene_id, pose, **fields):
    return client.post(f"/scenes/{scene_id}/render", json={"world_from_cam": pose, **fields})


# -- the contract --------------------------------------------------------------------------------

def test_serve_and_batch_import_torch_free():
    code = ("import sys; sys.modules['torch'] = None\n"
            "import iris_runtime.serve, iris_runtime.serve.cli, iris_runtime.batch\n"
            "assert 'torch' not in [m for m, v in sys.modules.items() if v is not None]\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


def test_healthz(client, rt):
    r = client.get("/healthz")
    assert r.status_code == 200
    body = r.json()
    assert body["status"] == "ok"
    assert body["model"]["format"] == "iris-model"
    assert body["model"]["default_cameras"] == rt.default_cameras
    assert body["model"]["image_size"] == list(rt.image_size)
    assert body["model"]["name"]
    assert body["limits"]["max_photos"] == 4
    # FastAPI's own schema, from the routes' Pydantic models and File/Form declarations.
    spec = client.get("/openapi.json").json()
    schemas = spec["components"]["schemas"]

    def body_schema(path, method, ctype):
        ref = spec["paths"][path][method]["requestBody"]["content"][ctype]["schema"]["$ref"]
        return schemas[ref.rsplit("/", 1)[1]]

    render_body = body_schema("/scenes/{scene_id}/render", "post", "application/json")
    assert "world_from_cam" in render_body["properties"]
    assert set(render_body["properties"]["quality"]["anyOf"][0]["enum"]) == \
        set(body["model"]["quality_presets"])
    scene_body = body_schema("/scenes", "post", "multipart/form-data")
    assert scene_body["required"] == ["images"]
    assert scene_body["properties"]["images"]["minItems"] == 2
    assert "image" in body_schema("/scenes/{scene_id}/locate", "post",
                                  "multipart/form-data")["properties"]
    for path, methods in spec["paths"].items():
        for method, op in methods.items():       # every error is the service's one error body
            for status, answer in op["responses"].items():
                if not status.startswith("2"):
                    assert answer["content"]["application/json"]["schema"]["$ref"] == \
                        "#/components/schemas/ErrorOut", (path, method, status)
    assert "HTTPValidationError" not in schemas
    assert client.get("/docs").status_code == 404                 # no page that needs a CDN


def test_scene_json_matches_runtime_encode(scene, rt, client):
    body, paths = scene
    assert set(body) >= {"scene_id", "views", "world_from_cam", "intrinsics", "focal",
                         "camera_source", "image_size"}
    ref = rt.encode(paths)
    assert body["views"] == 3 and body["camera_source"] == ref.camera_source
    # The server's runtime has CPUs // workers threads, this one 1: on a machine with more than
    # two CPUs a thread split may change the encoder's float32 rounding (tests/tolerances.py:
    # ~3e-5 on poses, focal relative). Another scene's cameras are off by > 1e-2.
    config = rt.manifest.config
    np.testing.assert_allclose(body["world_from_cam"], ref.world_from_cam, rtol=0,
                               atol=encoder_tol(config, 3, "cameras",
                                                max(1.0, float(np.abs(ref.world_from_cam).max()))))
    np.testing.assert_allclose(body["intrinsics"], ref.K, rtol=encoder_tol(config, 3, "focal"))
    assert client.get(f"/scenes/{body['scene_id']}").json() == body


def test_render_equals_runtime_render(scene, rt, client):
    body, paths = scene
    pose = novel_pose(body)
    r = render(client, body["scene_id"], pose, height=24, width=20)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    served = png_pixels(r.content)
    expected = rt.render(paths, np.array(pose), height=24, width=20)     # one shot, same photos
    assert served.shape == expected.shape == (24, 20, 3)
    assert np.abs(served.astype(int) - expected.astype(int)).max() <= 1
    coverage = rt.render(paths, np.array(pose), height=24, width=20, depth=True).coverage
    assert float(r.headers["x-iris-coverage"]) == pytest.approx(coverage, abs=1e-4)
    assert coverage > 0.5
    # Depth on request: iris-render's 16-bit encoding of the same render's depth.
    r = render(client, body["scene_id"], pose, height=24, width=20, depth=True)
    assert r.status_code == 200 and float(r.headers["x-iris-depth-far"]) == rt.far
    depth = png_pixels(r.content)
    assert depth.dtype == np.uint16 and depth.shape == (24, 20)
    ref = rt.render(paths, np.array(pose), height=24, width=20, depth=True).depth
    expected = np.rint(np.clip(ref / rt.far, 0, 1) * 65535)
    assert np.abs(depth.astype(float) - expected).max() <= 2


def test_a_view_of_nothing_is_refused(scene, rt, client):
    """A camera that sees none of the scene (``away_pose``): the service says so (422 naming
    world_from_cam), instead of a 200 with the renderer's empty-ray colour."""
    body, paths = scene
    T = away_pose(body)
    assert rt.render(paths, T, height=8, width=8, depth=True).coverage == 0
    r = render(client, body["scene_id"], T.tolist(), height=8, width=8)
    assert r.status_code == 422, r.text
    error = r.json()["error"]
    assert error["type"] == "invalid" and "world_from_cam" in error["message"]
    assert "sees none of the scene" in error["message"]


def test_quality_preset_equals_runtime(scene, rt, client):
    body, paths = scene
    pose = novel_pose(body)
    served = png_pixels(render(client, body["scene_id"], pose, height=16, width=16,
                               quality="fast").content)
    expected = rt.render(rt.encode(paths), np.array(pose), height=16, width=16, quality="fast")
    assert np.abs(served.astype(int) - expected.astype(int)).max() <= 1


def test_eight_concurrent_renders_equal_the_serial_one(scene, client):
    body, _ = scene
    pose = novel_pose(body)
    serial = png_pixels(render(client, body["scene_id"], pose, height=16, width=16).content)
    with ThreadPoolExecutor(8) as ex:
        responses = list(ex.map(lambda _: render(client, body["scene_id"], pose, height=16,
                                                 width=16), range(8)))
    assert [r.status_code for r in responses] == [200] * 8
    for r in responses:
        assert np.abs(png_pixels(r.content).astype(int) - serial.astype(int)).max() <= 1


def test_locate_equals_runtime_locate(scene, rt, client):
    body, paths = scene
    photo = PHOTOS[5]
    r = client.post(f"/scenes/{body['scene_id']}/locate",
                    files={"image": (photo.name, photo.read_bytes(), "image/png")})
    assert r.status_code == 200, r.text
    expected = rt.locate(rt.encode(paths), str(photo))
    np.testing.assert_allclose(r.json()["world_from_cam"], expected, atol=1e-4)


def test_cameras_picture_and_orbit(scene, rt, client):
    from iris_runtime.camera_plot import draw_cameras
    from iris_runtime.orbit import orbit_poses
    body, _ = scene
    sid = body["scene_id"]
    T, K = np.array(body["world_from_cam"]), np.array(body["intrinsics"])
    r = client.get(f"/scenes/{sid}/cameras.png")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    what = "predicted" if body["camera_source"] == "model" else body["camera_source"]
    expected = draw_cameras(T, K, size=(480, 640), title=f"{what} cameras of the 3 input(s)")
    np.testing.assert_array_equal(png_pixels(r.content), expected)
    r = client.get(f"/scenes/{sid}/orbit", params={"frames": 3})
    np.testing.assert_allclose(r.json()["world_from_cam"],
                               orbit_poses(T, 3, near=rt.near, far=rt.unit_range[1]), atol=1e-12)
    r = client.post(f"/scenes/{sid}/orbit.mp4", json={"frames": 2, "height": 16, "width": 16})
    assert r.status_code == 200 and r.headers["content-type"] == "video/mp4"
    assert r.content[4:8] == b"ftyp"


def test_delete(client):
    files = [("images", (p.name, p.read_bytes(), "image/png")) for p in PHOTOS[3:5]]
    sid = client.post("/scenes", files=files).json()["scene_id"]
    assert client.delete(f"/scenes/{sid}").status_code == 204
    for r in (client.get(f"/scenes/{sid}"), client.delete(f"/scenes/{sid}"),
              render(client, sid, np.eye(4).tolist())):
        assert r.status_code == 404 and r.json()["error"]["type"] == "not_found"


def _png_bytes(h: int, w: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.full((h, w, 3), 90, np.uint8)).save(buf, format="PNG")
    return buf.getvalue()


def test_bad_requests_get_4xx_json_and_the_server_stays_healthy(scene, client, server):
    sid = scene[0]["scene_id"]
    eye = np.eye(4).tolist()
    photo = ("images", ("a.png", PHOTOS[0].read_bytes(), "image/png"))
    cases = [  # (kind, request, status, error type, text the message must contain)
        ("unknown scene", lambda: client.get("/scenes/nope"), 404, "not_found", "scene_id"),
        ("render of an unknown scene", lambda: render(client, "nope", eye), 404, "not_found",
         "scene_id"),
        ("one photo", lambda: client.post("/scenes", files=[photo]), 422, "invalid", "images"),
        ("unreadable photo", lambda: client.post("/scenes", files=[
            ("images", ("x.png", b"not an image", "image/png")), photo]), 400, "bad_image",
         "images[0]"),
        ("photos in the wrong field", lambda: client.post("/scenes", files=[
            ("photos", ("a.png", PHOTOS[0].read_bytes(), "image/png"))] * 2), 422, "invalid",
         "images"),
        ("JSON instead of multipart", lambda: client.post("/scenes", json={"images": []}), 415,
         "unsupported_media_type", "multipart"),
        ("too many photos", lambda: client.post("/scenes", files=[photo] * 5), 413, "too_large",
         "images"),
        ("body over the byte limit", lambda: client.post("/scenes", files=[
            ("images", ("big.bin", os.urandom(1_200_000), "image/png")), photo]), 413,
         "too_large", "request body"),
        ("photo over the pixel limit", lambda: client.post("/scenes", files=[
            ("images", ("wide.png", _png_bytes(400, 400), "image/png")), photo]), 413,
         "too_large", "images[0]"),
        ("unknown cameras", lambda: client.post("/scenes", files=[photo, photo],
                                                data={"cameras": "magic"}), 422, "invalid",
         "cameras"),
        ("broken JSON", lambda: client.post(f"/scenes/{sid}/render", content=b"{not json",
                                            headers={"content-type": "application/json"}), 400,
         "bad_request", "JSON"),
        ("form instead of JSON", lambda: client.post(f"/scenes/{sid}/render", data={"a": "1"}),
         415, "unsupported_media_type", "application/json"),
        ("non-rigid pose", lambda: render(client, sid, (2 * np.eye(4)).tolist()), 422, "invalid",
         "world_from_cam"),
        ("3x3 pose", lambda: render(client, sid, np.eye(3).tolist()), 422, "invalid",
         "world_from_cam"),
        ("NaN in the pose", lambda: client.post(
            f"/scenes/{sid}/render", headers={"content-type": "application/json"},
            content=b'{"world_from_cam": [[NaN,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}'), 422,
         "invalid", "world_from_cam"),
        ("pose of strings", lambda: render(client, sid, [["a"] * 4] * 4), 422, "invalid",
         "world_from_cam"),
        ("negative height", lambda: render(client, sid, eye, height=-4), 422, "invalid", "height"),
        ("output over the pixel limit", lambda: render(client, sid, eye, height=128, width=128),
         413, "too_large", "height, width"),
        ("unknown quality", lambda: render(client, sid, eye, quality="ultra"), 422, "invalid",
         "quality"),
        ("unknown field", lambda: render(client, sid, eye, colour="red"), 422, "invalid", "colour"),
        ("seq without stream", lambda: render(client, sid, eye, seq=3), 422, "invalid", "stream"),
        ("stream without seq", lambda: render(client, sid, eye, stream="s"), 422, "invalid", "seq"),
        ("stream not a token", lambda: render(client, sid, eye, stream="a b", seq=1), 422,
         "invalid", "stream"),
        ("negative seq", lambda: render(client, sid, eye, stream="s", seq=-1), 422, "invalid",
         "seq"),
        ("locate without a photo", lambda: client.post(f"/scenes/{sid}/locate", files=[photo]),
         422, "invalid", "image"),
        ("too many orbit frames", lambda: client.get(f"/scenes/{sid}/orbit",
                                                     params={"frames": 9}), 413, "too_large",
         "frames"),
        ("orbit frames not a number", lambda: client.get(f"/scenes/{sid}/orbit",
                                                         params={"frames": "x"}), 422, "invalid",
         "frames"),
        ("wrong method", lambda: client.put(f"/scenes/{sid}"), 405, "method_not_allowed", "PUT"),
        ("unknown route", lambda: client.get("/nowhere"), 404, "not_found", "/nowhere"),
    ]
    kinds = set()
    for kind, send, status, type_, text in cases:
        r = send()
        assert r.status_code == status, (kind, r.status_code, r.text)
        body = r.json()
        assert set(body) == {"error"} and set(body["error"]) == {"type", "message"}, kind
        assert body["error"]["type"] == type_, (kind, body)
        assert text in body["error"]["message"], (kind, body)
        assert "Traceback" not in r.text and 'File "' not in r.text, kind
        kinds.add(kind)
    assert len(kinds) >= 11
    assert client.get("/healthz").status_code == 200
    assert render(client, sid, eye, height=8, width=8).status_code == 200
    assert not any(rec.get("level") == "error" for rec in server.logs)       # no 500 logged


def test_metrics_and_access_log(scene, client, server):
    text = client.get("/metrics").text
    assert 'iris_http_requests_total{method="POST",route="/scenes/{scene_id}/render",status="200"}' \
        in text
    assert "iris_http_request_duration_seconds_bucket" in text
    assert "iris_queue_depth" in text and "iris_jobs_running" in text
    assert 'iris_job_duration_seconds_count{kind="render"}' in text
    scenes = float(next(line.split()[1] for line in text.splitlines()
                        if line.startswith("iris_scenes ")))
    assert scenes >= 1
    access = [rec for rec in server.logs if rec.get("logger") == "iris.access"]
    assert access and all({"request_id", "method", "path", "route", "status", "duration_ms"}
                          <= set(rec) for rec in access)
    assert any(rec["route"] == "/scenes/{scene_id}/render" and rec["status"] == 200
               for rec in access)


# -- operating it ------------------------------------------------------------------------------

def _wait_metric(client, name: str, value: float, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for line in client.get("/metrics").text.splitlines():
            if line.startswith(name + " ") and float(line.split()[1]) >= value:
                return
        time.sleep(0.05)
    raise AssertionError(f"{name} never reached {value}")


def test_token_backpressure_and_graceful_shutdown(model_dir, tmp_path):
    token_file = tmp_path / "token"
    token_file.write_text("s3cret-token\n")
    srv = IrisServer(model_dir, "--workers", "1", "--queue", "1", "--queue-timeout", "1",
                     "--token-file", str(token_file), "--shutdown-timeout", "120")
    auth = {"Authorization": "Bearer s3cret-token"}
    files = [("images", (p.name, p.read_bytes(), "image/png")) for p in PHOTOS[:2]]
    try:
        with httpx.Client(base_url=srv.url, timeout=120.0, headers=auth) as c, \
                httpx.Client(base_url=srv.url, timeout=120.0) as anonymous:
            assert anonymous.get("/healthz").status_code == 200        # open for probes
            for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "s3cret"}):
                r = anonymous.post("/scenes", files=files, headers=headers)
                assert r.status_code == 401 and r.json()["error"]["type"] == "unauthorized"
                assert r.headers["www-authenticate"].startswith("Bearer")
            r = c.post("/scenes", files=files)
            assert r.status_code == 201
            sid = r.json()["scene_id"]
            eye = np.eye(4).tolist()
            with ThreadPoolExecutor(2) as ex:
                # A long job holds the only worker; the next job waits in the queue (503 after
                # the 1 s queue timeout); one more finds worker and queue full: 429 at once.
                long_job = ex.submit(c.post, f"/scenes/{sid}/orbit.mp4",
                                     json={"frames": 6, "height": 48, "width": 48})
                _wait_metric(c, "iris_jobs_running", 1)
                waiting = ex.submit(render, c, sid, eye)
                _wait_metric(c, "iris_queue_depth", 1)
                busy = render(c, sid, eye)
                assert busy.status_code == 429 and busy.json()["error"]["type"] == "busy"
                assert int(busy.headers["retry-after"]) >= 1
                r = waiting.result(60)
                assert r.status_code == 503 and r.json()["error"]["type"] == "unavailable"
                assert int(r.headers["retry-after"]) >= 1
                assert not long_job.done()        # the shutdown below catches it running
                # Graceful shutdown: SIGTERM while the long job runs; it still completes.
                srv.proc.send_signal(signal.SIGTERM)
                done = long_job.result(120)
            assert done.status_code == 200 and done.content[4:8] == b"ftyp"
        # uvicorn re-raises the signal once it has shut down: exit status "killed by SIGTERM".
        assert srv.proc.wait(60) in (0, -signal.SIGTERM)
        messages = [rec["message"] for rec in srv.logs]
        assert "shutting down: refusing new jobs, waiting for running ones" in messages
        assert "stopped" in messages
        text = "\n".join(srv.lines)
        assert "s3cret-token" not in text                           # never logged
    finally:
        srv.stop()


def _metric(client, line_start: str) -> float:
    for line in client.get("/metrics").text.splitlines():
        if line.startswith(line_start + " "):
            return float(line.split()[1])
    return 0.0


def test_stale_render_of_a_stream_is_dropped_while_queued(model_dir):
    """Two renders of one stream wait behind a long render on the only worker: the newer one's
    arrival answers the older one 409 superseded at once, before the worker is free, and it is
    never rendered; a request older than the stream's latest is refused on arrival; another
    stream and requests without a stream are not affected."""
    srv = IrisServer(model_dir, "--workers", "1", "--queue", "8", "--queue-timeout", "60")
    files = [("images", (p.name, p.read_bytes(), "image/png")) for p in PHOTOS[:2]]
    try:
        with httpx.Client(base_url=srv.url, timeout=60.0) as c, ThreadPoolExecutor(4) as ex:
            body = c.post("/scenes", files=files).json()
            sid, pose = body["scene_id"], novel_pose(body)
            small = {"height": 8, "width": 8, "quality": "fast"}
            assert render(c, sid, pose, stream="warm", seq=0, **small).status_code == 200
            renders0 = _metric(c, 'iris_job_duration_seconds_count{kind="render"}')
            # A second or more on the only worker, even on a quiet machine.
            blocker = ex.submit(render, c, sid, pose, height=64, width=64, quality="exact")
            _wait_metric(c, "iris_jobs_running", 1)
            older = ex.submit(render, c, sid, pose, stream="viewer-1", seq=1, **small)
            _wait_metric(c, "iris_queue_depth", 1)
            other = ex.submit(render, c, sid, pose, stream="viewer-2", seq=1, **small)
            _wait_metric(c, "iris_queue_depth", 2)
            newer = ex.submit(render, c, sid, pose, stream="viewer-1", seq=2, **small)
            r = older.result(30)
            assert not blocker.done()           # answered while the only worker was still busy
            assert r.status_code == 409, r.text
            assert r.json()["error"]["type"] == "superseded"
            assert "seq 2" in r.json()["error"]["message"]
            assert r.headers["x-iris-superseded-by"] == "2"
            late = render(c, sid, pose, stream="viewer-1", seq=1, **small)   # stale on arrival
            assert late.status_code == 409 and late.json()["error"]["type"] == "superseded"
            assert late.headers["x-iris-superseded-by"] == "2"
            r = newer.result(60)
            assert r.status_code == 200 and r.headers["x-iris-seq"] == "2"
            assert other.result(60).status_code == 200
            assert blocker.result(60).status_code == 200
            again = render(c, sid, pose, stream="viewer-1", seq=2, **small)  # a retry: same seq
            assert again.status_code == 200
            # Rendered: the blocker, the other stream's, the newer one and the retry; not the
            # two superseded ones.
            renders = _metric(c, 'iris_job_duration_seconds_count{kind="render"}') - renders0
            assert renders == 4
            assert _metric(c, 'iris_jobs_rejected_total{reason="superseded"}') == 2
            statuses = [(rec["path"], rec["status"]) for rec in srv.logs
                        if rec.get("logger") == "iris.access"]
            assert statuses.count((f"/scenes/{sid}/render", 409)) == 2
    finally:
        srv.stop()


def test_pool_hands_workers_over_in_order_and_drops_superseded_waiters():
    """The worker pool in process: waiting jobs take the worker first come first served; a
    waiter whose ``superseded`` future is done leaves the queue at once without running; a
    cancelled waiter leaves its place; the worker count is never exceeded."""
    import asyncio

    from iris_runtime.serve.errors import Superseded
    from iris_runtime.serve.pool import WorkerPool
    from iris_runtime.serve.streams import Streams

    async def scenario():
        pool = WorkerPool(1, 8, 30.0)
        streams = Streams(max_streams=2)
        gate, ran = threading.Event(), []

        def job(name):
            if name == "first":
                gate.wait(10)
            ran.append(name)
            return name

        first = asyncio.ensure_future(pool.run("t", job, "first"))
        await asyncio.sleep(0.05)
        t1 = streams.admit("s", 1)
        stale = asyncio.ensure_future(pool.run("t", job, "stale", superseded=t1.superseded))
        plain = asyncio.ensure_future(pool.run("t", job, "plain"))
        gone = asyncio.ensure_future(pool.run("t", job, "gone"))
        await asyncio.sleep(0.05)
        assert pool.waiting == 3 and pool.running == 1
        gone.cancel()
        t2 = streams.admit("s", 2)                     # stale's stream moves on
        with pytest.raises(Superseded):
            await asyncio.wait_for(stale, 5)
        with pytest.raises(Superseded):
            streams.admit("s", 1)
        fresh = asyncio.ensure_future(pool.run("t", job, "fresh", superseded=t2.superseded))
        await asyncio.sleep(0.05)
        assert pool.waiting == 2 and pool.running == 1   # plain and fresh wait; first runs
        gate.set()
        assert await asyncio.wait_for(asyncio.gather(first, plain, fresh), 10) == \
            ["first", "plain", "fresh"]
        assert ran == ["first", "plain", "fresh"] and pool.running == 0 and pool.waiting == 0
        streams.release(t1)
        streams.release(t2)
        streams.admit("a", 0)
        streams.admit("b", 0)                          # "s" is forgotten (max_streams=2)
        assert len(streams) == 2 and streams.latest("s") is None
        pool.shutdown()

    asyncio.run(scenario())


def test_startup_errors_are_one_line(tmp_path, model_dir):
    for args, text in (([str(tmp_path / "missing")], "missing"),
                       ([str(model_dir), "--providers", "NoSuchProvider"], "providers"),
                       ([str(model_dir), "--token-file", str(tmp_path / "none")],
                        "--token-file")):
        out = subprocess.run([sys.executable, "-m", "iris_runtime.serve.cli", *args],
                             cwd=REPO, capture_output=True, text=True, timeout=120)
        assert out.returncode == 2, out.stderr
        assert out.stderr.startswith("iris-serve: error:") and text in out.stderr
        assert "Traceback" not in out.stderr


# -- ONNX Runtime execution providers ----------------------------------------------------------

def test_providers_are_checked_and_passed_through(model_dir, rt):
    import onnxruntime as ort
    for bad in (["NoSuchExecutionProvider"], "CPUExecutionProvider", [], ["CPUExecutionProvider"] * 2):
        with pytest.raises(InputError, match="providers"):
            IrisRuntime(model_dir, providers=bad)
    assert "CPUExecutionProvider" in ort.get_available_providers()
    cpu = IrisRuntime(model_dir, threads=1, providers=["CPUExecutionProvider"])
    assert cpu.providers == ("CPUExecutionProvider",) == rt.providers
    scene = rt.encode(PHOTOS[:2])
    np.testing.assert_array_equal(cpu.render(scene, 1, height=8, width=8),
                                  rt.render(scene, 1, height=8, width=8))
    out = subprocess.run([sys.executable, "-m", "iris_runtime.cli", str(model_dir),
                          str(PHOTOS[0]), "-o", "unused", "--providers", "Nope"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "providers" in out.stderr and "Traceback" not in out.stderr


def test_cuda_provider_renders_like_the_cpu(model_dir, rt):
    import onnxruntime as ort
    if "CUDAExecutionProvider" not in ort.get_available_providers():
        pytest.skip("onnxruntime has no CUDAExecutionProvider here (needs onnxruntime-gpu and a "
                    "GPU)")
    gpu = IrisRuntime(model_dir, providers=["CUDAExecutionProvider", "CPUExecutionProvider"])
    scene = gpu.encode(PHOTOS[:3])
    assert gpu._session("renderer").get_providers()[0] == "CUDAExecutionProvider"
    ref = rt.encode(PHOTOS[:3])
    np.testing.assert_allclose(scene.world_from_cam, ref.world_from_cam, atol=1e-3)
    diff = gpu.render(ref, 1, height=32, width=32).astype(int) - rt.render(ref, 1, height=32,
                                                                          width=32)
    assert np.abs(diff).max() <= 2


# -- the scene store (in process) ----------------------------------------------------------------

def test_scene_store_is_lru_and_bounded(rt):
    from iris_runtime.serve.errors import NotFound, PayloadTooLarge
    from iris_runtime.serve.store import SceneStore, scene_nbytes
    scene = rt.encode(PHOTOS[:2], cameras="model")      # no head's poses kept beside them
    size = scene_nbytes(scene)
    # The camera head's poses kept beside solved cameras count too.
    with_head = dataclasses.replace(scene, encoder_world_from_cam=scene.world_from_cam)
    assert scene_nbytes(with_head) == size + scene.world_from_cam.nbytes
    evicted = []
    store = SceneStore(max_bytes=3 * size, max_scenes=2, on_evict=lambda: evicted.append(1))
    a, b = store.put(scene, "model"), store.put(scene, "model")
    store.get(a.scene_id)                                   # a is now the most recently used
    c = store.put(scene, "model")                           # over max_scenes: b goes
    assert len(evicted) == 1 and len(store) == 2 and store.nbytes == 2 * size
    with pytest.raises(NotFound, match="evicted"):
        store.get(b.scene_id)
    assert store.get(a.scene_id).scene is scene and store.get(c.scene_id).scene is scene
    small = SceneStore(max_bytes=size - 1, max_scenes=4)
    with pytest.raises(PayloadTooLarge, match="--store-mb"):
        small.put(scene, "model")
    store.delete(a.scene_id)
    with pytest.raises(NotFound):
        store.delete(a.scene_id)
    assert store.nbytes == size


# -- docs/SERVING.md's error table, row by row, against real servers -----------------------------

SERVING_MD = REPO / "docs" / "SERVING.md"


def documented_errors() -> list[dict]:
    """The rows of docs/SERVING.md's "Errors" table: status, type, when, header."""
    section = SERVING_MD.read_text(encoding="utf-8").split("### Errors", 1)[1]
    section = section.split("\n#", 1)[0]
    rows = []
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and cells[0].isdigit():
            assert len(cells) == 4, line
            rows.append({"status": int(cells[0]), "type": cells[1].strip("`"), "when": cells[2],
                         "header": cells[3].strip("`")})
    return rows


def multipart(files, fields=()) -> tuple[bytes, str]:
    """(body, Content-Type) of a multipart request, as httpx makes it."""
    req = httpx.Request("POST", "http://x/", files=files, data=dict(fields))
    return req.read(), req.headers["content-type"]


def png_header(width: int, height: int) -> bytes:
    """A PNG whose header declares width x height (a decompression bomb when large)."""
    import struct
    import zlib

    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0,
                                                             0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


class Probe:
    """One request that should get a row of the table: ``key`` is text of the row's "when"."""

    def __init__(self, status, type_, key, send, *message):
        self.status, self.type, self.key, self.send, self.message = status, type_, key, send, \
            message

    def matches(self, row) -> bool:
        return (row["status"], row["type"]) == (self.status, self.type) and self.key in row["when"]

    def check(self, r, row) -> None:
        what = (self.status, self.type, self.key)
        assert r.status_code == self.status, (what, r.status_code, r.text)
        body = r.json()
        assert set(body) == {"error"} and set(body["error"]) == {"type", "message"}, what
        assert body["error"]["type"] == self.type, (what, body)
        for text in self.message:
            assert text in body["error"]["message"], (what, text, body)
        assert "Traceback" not in r.text and 'File "' not in r.text, what
        if row["header"]:
            assert row["header"].split(":")[0].lower() in r.headers, (what, dict(r.headers))


def _metric_value(client, name: str) -> float:
    return next(float(line.split()[1]) for line in client.get("/metrics").text.splitlines()
                if line.startswith(name + " "))


def _expected_retry_after(client, waiting: int, workers: int = 1) -> int:
    import math

    from iris_runtime.serve.pool import RETRY_AFTER_MAX, RETRY_AFTER_MIN
    mean = _metric_value(client, "iris_job_service_seconds")
    return min(RETRY_AFTER_MAX, max(RETRY_AFTER_MIN, math.ceil((waiting + 1) * mean / workers)))


def _request_probes(c, scene_json: dict, photo: bytes) -> list[Probe]:
    """Probes of rows a single request reaches (server of ``test_documented_error_table``;
    ``scene_json`` what creating its scene answered)."""
    sid = scene_json["scene_id"]
    eye = np.eye(4).tolist()
    J = {"content-type": "application/json"}
    tiny = _png_bytes(8, 8)

    def scenes(*photos, **fields):
        return c.post("/scenes", files=[("images", (f"p{i}.png", p, "image/png"))
                                        for i, p in enumerate(photos)], data=fields)

    def rnd(**fields):
        return c.post(f"/scenes/{sid}/render", json={"world_from_cam": eye, **fields})

    body, ctype = multipart([("images", ("a.png", photo, "image/png"))] * 2)
    return [
        Probe(400, "bad_request", "not valid JSON",
              lambda: c.post(f"/scenes/{sid}/render", content=b"{not json", headers=J), "JSON"),
        Probe(400, "bad_request", "cannot be parsed", lambda: c.post(
            "/scenes", content=b"x", headers={"content-type": "multipart/form-data"}),
              "boundary"),
        Probe(400, "bad_request", "cut short", lambda: c.post(
            "/scenes", content=body[:len(body) // 2], headers={"content-type": ctype}),
              "closing boundary"),
        Probe(400, "bad_image", "cannot decode", lambda: scenes(b"not an image", photo),
              "images[0]"),
        Probe(401, "unauthorized", "token missing", lambda: c.get(
            f"/scenes/{sid}", headers={"Authorization": "Bearer wrong"}), "Authorization"),
        Probe(404, "not_found", "unknown scene", lambda: c.get("/scenes/nope"), "'nope'"),
        Probe(404, "not_found", "unknown route", lambda: c.get("/nowhere"), "/nowhere"),
        Probe(405, "method_not_allowed", "does not take", lambda: c.put(f"/scenes/{sid}"), "PUT"),
        Probe(413, "too_large", "multipart body over", lambda: scenes(os.urandom(1_100_000), photo),
              "1048576", "--max-upload-mb"),
        Probe(413, "too_large", "JSON body over", lambda: c.post(
            f"/scenes/{sid}/render", content=b" " * 70_000 + b"{}", headers=J), "70002", "65536"),
        Probe(413, "too_large", "more photos than", lambda: scenes(*[tiny] * 17),
              "images", "at most 16", "--max-photos"),
        Probe(413, "too_large", "more photos than", lambda: c.post(
            f"/scenes/{sid}/locate", files=[("image", ("a.png", photo, "image/png"))] * 2),
              "image", "at most 1", "one photo"),
        Probe(413, "too_large", "more than 16 text fields", lambda: scenes(
            photo, photo, **{f"f{i}": "x" for i in range(17)}), "16"),
        Probe(413, "too_large", "header declares",
              lambda: scenes(png_header(40_000, 30_000), photo), "images[0]", "40000x30000 = 1200000000", "100000", "--max-photo-pixels"),
        Probe(413, "too_large", "output over", lambda: rnd(height=5000, width=5000),
              "5000x5000 = 25000000", "at most 4096", "--max-output-pixels"),
        Probe(413, "too_large", "orbit frames over", lambda: c.get(
            f"/scenes/{sid}/orbit", params={"frames": 9}), "frames: 9", "at most 8"),
        Probe(413, "too_large", "bigger than the whole store", lambda: scenes(*[tiny] * 12),
              "--store-mb"),
        Probe(415, "unsupported_media_type", "JSON where multipart",
              lambda: c.post("/scenes", json={"images": []}), "multipart/form-data"),
        Probe(415, "unsupported_media_type", "JSON where multipart",
              lambda: c.post(f"/scenes/{sid}/render", data={"a": "1"}), "application/json"),
        Probe(422, "invalid", "request model refuses", lambda: rnd(height=-4), "height", "-4"),
        Probe(422, "invalid", "request model refuses", lambda: rnd(colour="red"), "colour"),
        Probe(422, "invalid", "request model refuses", lambda: scenes(photo), "images", "2"),
        Probe(422, "invalid", "does not take", lambda: c.post(
            "/scenes", files=[("photos", ("a.png", photo, "image/png"))] * 2), "photos"),
        Probe(422, "invalid", "runtime refuses", lambda: rnd(world_from_cam=(2 * np.eye(4))
                                                             .tolist()), "world_from_cam"),
        Probe(422, "invalid", "runtime refuses", lambda: rnd(world_from_cam=[
            [1, 0, 0, 1e7], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "world_from_cam",
              "1e+07", "MAX_POSE_DISTANCE"),
        Probe(422, "invalid", "runtime refuses", lambda: scenes(photo, photo, cameras="magic"),
              "cameras", "magic"),
        Probe(422, "invalid", "sees none of the scene", lambda: rnd(
            world_from_cam=away_pose(scene_json).tolist()), "world_from_cam", "sees none"),
        Probe(422, "invalid", "`seq` without `stream`", lambda: rnd(seq=3), "stream"),
        Probe(422, "invalid", "odd or 1-pixel", lambda: c.post(
            f"/scenes/{sid}/orbit.mp4", json={"frames": 2, "height": 15, "width": 16}), "15x16"),
    ]


@pytest.mark.filterwarnings("ignore:Using `httpx` with `starlette.testclient`")
def test_documented_error_table(model_dir, tmp_path):
    """Every row of docs/SERVING.md's error table is what a real server answers: a request per
    row (several for some) gets the row's status, type and header, with a message naming the
    field, the value and the limit; every probe matches a row. 500 model_error: the server's
    int8 renderer file changed after start-up; 501: a server with OpenCV's FFMPEG back end off;
    503 at shutdown: SIGTERM with a request waiting; 500 internal: in process (a bug cannot be
    asked for)."""
    import shutil
    rows = documented_errors()
    assert len(rows) >= 25
    model = tmp_path / "model"
    shutil.copytree(model_dir, model)
    (tmp_path / "token").write_text("tok\n")
    srv = IrisServer(model, "--workers", "1", "--queue", "1", "--queue-timeout", "1",
                     "--shutdown-timeout", "0.5", "--token-file", str(tmp_path / "token"),
                     "--max-photos", "16", "--max-upload-mb", "1", "--max-photo-pixels", "100000",
                     "--max-output-pixels", "4096", "--max-orbit-frames", "8", "--store-mb", "1")
    photo = PHOTOS[0].read_bytes()
    probed = []
    try:
        with httpx.Client(base_url=srv.url, timeout=120.0, headers={
                "Authorization": "Bearer tok"}) as c, ThreadPoolExecutor(3) as ex:
            r = c.post("/scenes", files=[("images", (p.name, p.read_bytes(), "image/png"))
                                         for p in PHOTOS[:2]])
            assert r.status_code == 201, r.text
            created = r.json()
            sid = created["scene_id"]
            pose = novel_pose(created)
            small = {"world_from_cam": pose, "height": 8, "width": 8}

            def run(probe):
                (row,) = [row for row in rows if probe.matches(row)]
                r = probe.send()
                probe.check(r, row)
                probed.append(row["when"])
                return r
            for probe in _request_probes(c, created, photo):
                run(probe)
            assert c.post(f"/scenes/{sid}/render", json={**small, "stream": "s", "seq": 5}) \
                .status_code == 200
            run(Probe(409, "superseded", "older than the stream's latest", lambda: c.post(
                f"/scenes/{sid}/render", json={**small, "stream": "s", "seq": 4}), "seq 5"))
            # A long render holds the only worker: one job waits (503 after the 1 s queue
            # timeout), the next finds the queue full (429).
            long_render = {"world_from_cam": pose, "height": 64, "width": 64, "quality": "exact"}
            blocker = ex.submit(c.post, f"/scenes/{sid}/render", json=long_render)
            _wait_metric(c, "iris_jobs_running", 1)
            waiting = ex.submit(c.post, f"/scenes/{sid}/render", json=small)
            _wait_metric(c, "iris_queue_depth", 1)
            # Retry-After: (jobs waiting + 1) x the measured mean job time / workers.
            expected = _expected_retry_after(c, waiting=1)
            r = run(Probe(429, "busy", "queue full", lambda: c.post(
                f"/scenes/{sid}/render", json=small), "--queue"))
            assert int(r.headers["retry-after"]) == expected
            expected = _expected_retry_after(c, waiting=0)
            r = run(Probe(503, "unavailable", "--queue-timeout", lambda: waiting.result(60),
                          "--queue-timeout"))
            assert int(r.headers["retry-after"]) == expected
            assert blocker.result(120).status_code == 200
            assert int(c.post(f"/scenes/{sid}/render", json=small).status_code) == 200
            # The model breaks after start-up: the int8 renderer is loaded at its first use.
            with open(model / "renderer.int8.onnx", "r+b") as f:
                f.seek(100)
                f.write(b"tampered")
            run(Probe(500, "model_error", "model failed", lambda: c.post(
                f"/scenes/{sid}/render", json={**small, "precision": "int8"}), "model failed"))
            # Shutdown: a request still waiting when --shutdown-timeout ends gets 503.
            blocker = ex.submit(c.post, f"/scenes/{sid}/render", json=long_render)
            _wait_metric(c, "iris_jobs_running", 1)
            waiting = ex.submit(c.post, f"/scenes/{sid}/render", json=small)
            _wait_metric(c, "iris_queue_depth", 1)
            srv.proc.send_signal(signal.SIGTERM)
            run(Probe(503, "unavailable", "shutting down", lambda: waiting.result(60), "shut down"))
            blocker.result(120)
        tracebacks = [line for line in srv.lines if "Traceback" in line]
        assert not tracebacks, tracebacks[0][:3000]
    finally:
        srv.stop()
    probed += _probe_unsupported_and_internal(model_dir, rows)
    assert sorted(set(probed)) == sorted({row["when"] for row in rows}), \
        "rows of docs/SERVING.md's error table that no request checked"


def _probe_unsupported_and_internal(model_dir, rows) -> list[str]:
    """501 on a real server without OpenCV's FFMPEG back end; 500 internal in process."""
    from starlette.testclient import TestClient

    from iris_runtime.serve.app import ServeConfig, create_app
    done = []
    srv = IrisServer(model_dir, "--workers", "1", env={"OPENCV_VIDEOIO_PRIORITY_FFMPEG": "0"})
    try:
        with httpx.Client(base_url=srv.url, timeout=120.0) as c:
            sid = c.post("/scenes", files=[("images", (p.name, p.read_bytes(), "image/png"))
                                           for p in PHOTOS[:2]]).json()["scene_id"]
            probe = Probe(501, "unsupported", "no mp4v encoder", lambda: c.post(
                f"/scenes/{sid}/orbit.mp4", json={"frames": 2, "height": 8, "width": 8}), "mp4v")
            (row,) = [row for row in rows if probe.matches(row)]
            probe.check(probe.send(), row)
            done.append(row["when"])
    finally:
        srv.stop()
    rt = IrisRuntime(model_dir, threads=1)

    def broken_render(*args, **kwargs):
        raise RuntimeError("a bug")
    rt.render = broken_render
    with TestClient(create_app(rt, ServeConfig()), raise_server_exceptions=False) as c:
        sid = c.post("/scenes", files=[("images", (p.name, p.read_bytes(), "image/png"))
                                       for p in PHOTOS[:2]]).json()["scene_id"]
        probe = Probe(500, "internal", "a bug", lambda: c.post(
            f"/scenes/{sid}/render", json={"world_from_cam": np.eye(4).tolist()}), "logged")
        (row,) = [row for row in rows if probe.matches(row)]
        r = probe.send()
        probe.check(r, row)
        assert "a bug" not in r.text
        done.append(row["when"])
    return done
