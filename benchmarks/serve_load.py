"""Load test of iris-serve: a real uvicorn process on 127.0.0.1, driven by an async httpx loop.

For encode (``POST /scenes``, 3 sample photos) and render (``POST /scenes/{id}/render``, one
novel pose), at 1, 4 and 16 concurrent clients: p50/p99 latency and throughput; then the same
with a burst of bad requests mixed in (every third request: broken JSON, a non-rigid pose, an
unknown scene, a negative size, an unknown field, an unreadable photo, one photo, JSON instead
of multipart). Counted per level: 5xx (must be 0), lost requests (no response; must be 0), bad
requests answered with anything but a 4xx JSON error (must be 0), good requests that failed
(must be 0), 429s (backpressure), and the server's resident memory (VmRSS) after each level,
against its value after a warm-up at the highest concurrency (and, for reference, after the first
request: "cold"). Every loop is bounded in requests and in seconds; the server is started and
stopped by this script.

    python benchmarks/serve_load.py MODEL_DIR                         # defaults below
    python benchmarks/serve_load.py MODEL_DIR --requests 24 --level-seconds 120 \\
        --json benchmarks/results/serve_load.json

The server runs with ``--workers`` (default 2) and a queue deep enough for 16 clients, so a
5xx would be a failure, not backpressure; its scene store keeps at most 8 scenes, so memory
stays bounded however many scenes the encode levels make. Results: docs/PERFORMANCE.md,
"Serving under load".
"""
from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.serve_process import ServeProcess  # noqa: E402

PHOTOS = sorted((REPO / "samples" / "heldout-1000003").glob("frame_*.png"))


def start_server(model_dir: str, workers: int, threads: int) -> ServeProcess:
    """iris-serve with ``workers`` workers of ``threads`` ORT threads, a queue of 64 (600 s) and
    at most 8 scenes stored."""
    try:
        return ServeProcess(model_dir, "--workers", str(workers), "--threads", str(threads),
                            "--queue", "64", "--queue-timeout", "600", "--max-scenes", "8")
    except RuntimeError:
        raise SystemExit("serve_load: iris-serve did not start") from None


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def files(photos) -> list:
    return [("images", (p.name, p.read_bytes(), "image/png")) for p in photos]


def requests_for(op: str, scene_id: str, pose: list, size: int, mixed: bool):
    """i -> (is_bad, coroutine factory) for request i of a level."""
    good_photos = files(PHOTOS[:3])
    render_body = {"world_from_cam": pose, "height": size, "width": size}
    bad_render = [
        lambda c: c.post(f"/scenes/{scene_id}/render", content=b"{broken",
                         headers={"content-type": "application/json"}),
        lambda c: c.post(f"/scenes/{scene_id}/render",
                         json={**render_body, "world_from_cam": (2 * np.eye(4)).tolist()}),
        lambda c: c.post("/scenes/no-such-scene/render", json=render_body),
        lambda c: c.post(f"/scenes/{scene_id}/render", json={**render_body, "height": -1}),
        lambda c: c.post(f"/scenes/{scene_id}/render", json={**render_body, "colour": 1}),
    ]
    bad_encode = [
        lambda c: c.post("/scenes", files=[("images", ("x.png", b"not a png", "image/png"))] * 2),
        lambda c: c.post("/scenes", files=good_photos[:1]),
        lambda c: c.post("/scenes", json={"images": []}),
    ]
    bad = bad_render if op == "render" else bad_encode

    def make(i: int):
        if mixed and i % 3 == 2:
            return True, bad[(i // 3) % len(bad)]
        if op == "render":
            return False, lambda c: c.post(f"/scenes/{scene_id}/render", json=render_body)
        return False, lambda c: c.post("/scenes", files=good_photos)
    return make


async def run_level(client, make, n: int, concurrency: int, seconds: float) -> dict:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + seconds
    counter = itertools.count()
    records = []

    async def worker():
        while True:
            i = next(counter)
            if i >= n or loop.time() > deadline:
                return
            is_bad, send = make(i)
            t0 = time.perf_counter()
            try:
                r = await send(client)
                status = r.status_code
                json_error = status >= 400 and set(r.json().get("error", {})) == {"type",
                                                                                  "message"}
            except Exception:                     # no response at all: a lost request
                status, json_error = None, False
            records.append((is_bad, status, json_error, time.perf_counter() - t0))

    t0 = time.perf_counter()
    await asyncio.gather(*(worker() for _ in range(concurrency)))
    wall = time.perf_counter() - t0
    good = [r for r in records if not r[0]]
    ok_latency = [r[3] for r in good if r[1] in (200, 201)]
    bad = [r for r in records if r[0]]
    pct = (lambda q: round(float(np.percentile(ok_latency, q)), 4) if ok_latency else None)
    return {"concurrency": concurrency, "sent": len(records), "good": len(good),
            "ok": len(ok_latency), "good_failed": len(good) - len(ok_latency), "bad": len(bad),
            "bad_answered_4xx_json": sum(1 for r in bad if r[1] is not None and 400 <= r[1] < 500
                                         and r[2]),
            "status_5xx": sum(1 for r in records if r[1] is not None and r[1] >= 500),
            "status_429": sum(1 for r in records if r[1] == 429),
            "lost": sum(1 for r in records if r[1] is None),
            "p50_s": pct(50), "p99_s": pct(99), "wall_s": round(wall, 3),
            "throughput_per_s": round(len(ok_latency) / wall, 3) if wall > 0 else None,
            "bad_p50_s": round(float(np.median([r[3] for r in bad])), 4) if bad else None}


def _shown(arg: str) -> str:
    """A command-line word as the results record it: an absolute path relative to the
    repository where it lies inside it, else its name alone (results name no machine's
    directories); other words as given."""
    if not os.path.isabs(arg):
        return arg
    p = Path(arg).resolve()
    return p.relative_to(REPO).as_posix() if p.is_relative_to(REPO) else p.name


async def main_async(args) -> dict:
    import httpx
    server = start_server(args.model_dir, args.workers, args.threads)
    out = {"command": " ".join(_shown(a) for a in sys.argv), "machine": {
        "cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
        "load_avg_start": os.getloadavg()}, "server": {"workers": args.workers,
                                                      "threads": args.threads},
        "requests_per_level": args.requests, "render_size": args.size, "levels": []}
    try:
        async with httpx.AsyncClient(base_url=server.url, timeout=600.0,
                                     limits=httpx.Limits(max_connections=32)) as client:
            health = (await client.get("/healthz")).json()
            out["model"] = health["model"]
            r = await client.post("/scenes", files=files(PHOTOS[:3]))      # warm-up scene
            scene = r.json()
            T = np.array(scene["world_from_cam"][1])
            a = np.deg2rad(5.0)
            T[:3, :3] = T[:3, :3] @ np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0],
                                               [-np.sin(a), 0, np.cos(a)]])
            pose = T.tolist()
            await client.post(f"/scenes/{scene['scene_id']}/render",
                              json={"world_from_cam": pose, "height": args.size,
                                    "width": args.size})
            out["rss_mb_cold"] = round(rss_mb(server.proc.pid), 1)
            # Warm-up at the highest concurrency: ONNX Runtime's arenas and the allocator's
            # per-thread pools grow to their working size once; "before" is the warm server.
            for op in ("render", "encode"):      # render first: encodes evict the scene
                make = requests_for(op, scene["scene_id"], pose, args.size, False)
                await run_level(client, make, max(args.concurrency), max(args.concurrency),
                                args.level_seconds)
            out["rss_mb_before"] = round(rss_mb(server.proc.pid), 1)
            for mixed in (False, True):
                for op in ("encode", "render"):
                    if op == "render":           # the encode levels may have evicted the scene
                        scene = (await client.post("/scenes", files=files(PHOTOS[:3]))).json()
                    for c in args.concurrency:
                        make = requests_for(op, scene["scene_id"], pose, args.size, mixed)
                        level = await run_level(client, make, args.requests, c,
                                                args.level_seconds)
                        level.update(op=op, mixed=mixed, rss_mb=round(rss_mb(server.proc.pid), 1))
                        out["levels"].append(level)
                        print(f"{op:6s} {'mixed' if mixed else 'clean'} c={c:2d}: "
                              f"p50 {level['p50_s']} s p99 {level['p99_s']} s "
                              f"{level['throughput_per_s']}/s 5xx {level['status_5xx']} "
                              f"lost {level['lost']} bad->4xx {level['bad_answered_4xx_json']}"
                              f"/{level['bad']} rss {level['rss_mb']} MB", flush=True)
            out["rss_mb_after"] = round(rss_mb(server.proc.pid), 1)
            out["metrics_tail"] = [line for line in (await client.get("/metrics")).text
                                   .splitlines() if line.startswith(("iris_jobs_rejected",
                                                                     "iris_scenes "))]
    finally:
        server.stop(60)
    out["machine"]["load_avg_end"] = os.getloadavg()
    levels = out["levels"]
    out["totals"] = {"status_5xx": sum(lv["status_5xx"] for lv in levels),
                     "lost": sum(lv["lost"] for lv in levels),
                     "good_failed": sum(lv["good_failed"] for lv in levels),
                     "bad_not_4xx_json": sum(lv["bad"] - lv["bad_answered_4xx_json"]
                                             for lv in levels)}
    return out


def markdown(out: dict) -> str:
    rows = ["| op | bad requests mixed in | clients | sent | p50 s | p99 s | ok/s | 5xx | lost "
            "| bad -> 4xx JSON | 429 | server RSS MB |", "|" + "---|" * 12]
    for lv in out["levels"]:
        rows.append(f"| {lv['op']} | {'1 in 3' if lv['mixed'] else 'none'} | "
                    f"{lv['concurrency']} | {lv['sent']} | {lv['p50_s']} | {lv['p99_s']} | "
                    f"{lv['throughput_per_s']} | {lv['status_5xx']} | {lv['lost']} | "
                    f"{lv['bad_answered_4xx_json']}/{lv['bad']} | {lv['status_429']} | "
                    f"{lv['rss_mb']} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir", help="an iris-export output directory")
    ap.add_argument("--requests", type=int, default=24, help="requests per level (default 24)")
    ap.add_argument("--level-seconds", type=float, default=300.0,
                    help="a level stops sending after this many seconds (default 300)")
    ap.add_argument("--concurrency", type=lambda s: [int(x) for x in s.split(",")],
                    default=[1, 4, 16], help="client counts (default 1,4,16)")
    ap.add_argument("--size", type=int, default=64, help="render size, pixels a side (default 64)")
    ap.add_argument("--workers", type=int, default=2, help="server workers (default 2)")
    ap.add_argument("--threads", type=int, default=1, help="ORT threads per worker (default 1)")
    ap.add_argument("--json", default=str(REPO / "benchmarks" / "results" / "serve_load.json"))
    args = ap.parse_args(argv)
    out = asyncio.run(main_async(args))
    Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    print(markdown(out))
    print(f"totals: {out['totals']}; RSS cold {out['rss_mb_cold']}, warm {out['rss_mb_before']} "
          f"-> {out['rss_mb_after']} MB after every level; "
          f"load average {out['machine']['load_avg_start']} -> {out['machine']['load_avg_end']}")
    t = out["totals"]
    return 0 if not (t["status_5xx"] or t["lost"] or t["bad_not_4xx_json"] or t["good_failed"]) \
        else 1


if __name__ == "__main__":
    sys.exit(main())
