"""Dragging in the viewer: frames shown per second while the camera moves, and the time from the
end of the drag to the full frame, in a headless Chromium against a real iris-serve process.

The script starts ``iris-serve MODEL_DIR`` on 127.0.0.1 (``--port 0``) and Debian's chromium
through selenium and chromedriver (as tests/test_viewer.py does), sizes the page's view to
``--view-px`` CSS pixels (device scale 1: the full frame, rendered at the view's displayed size,
is then ``--view-px`` square for a square model; 256 by default), uploads sample photos in the
page, and then, per mode, runs ``--drags`` scripted drags: each starts from input view 0 (its
full frame shown), presses the mouse in the middle of the view, moves it ``--dx`` x ``--dy`` CSS
pixels at ``--hz`` mouse events per second for ``--drag-seconds`` seconds (real input events,
Chrome DevTools' ``Input.dispatchMouseEvent``, alternating right and left), releases it, and
waits for the full frame of the last pose. From the page's own record (``window.viewerStats``:
every frame drawn, with its time, kind and size; the drags' press, last move and release) and a
``fetch`` wrapper installed by this script (render requests in flight at once):

- ``fps_during_drag``: frames drawn between press and release / the drag's seconds;
- ``release_to_full_ms``: release -> the full frame of the final pose drawn (and from the last
  move, ``last_move_to_full_ms``; ``full_frame_ms``: that frame's round trip);
- ``preview_ms``: round trips of the frames drawn during the drag; ``max_in_flight``: render
  requests in flight at once (the page promises 1); requests sent, aborted by the page, and
  answered 409 superseded (the server's count from /metrics as well).

The full frame is the page's default unless ``--size`` / ``--quality`` choose otherwise: the
view's displayed size ("view") at the server's default quality (no ``quality`` sent: "auto" for
explicit-colour models). Modes: ``preview`` (the page's default previews while moving: "fast" at
160x160 for the shipped 64x64 model, drawn scaled to the view; ``--preview-quality`` /
``--preview-size`` choose others) and ``off`` (full frames while moving too). Every loop is
bounded (drags, mouse events, seconds); the server and the browser are started and stopped by
this script.

    python benchmarks/viewer_drag.py MODEL_DIR                            # defaults below
    python benchmarks/viewer_drag.py out/model --drags 3 --modes preview,off \\
        --note "quiet machine" --json benchmarks/results/viewer_drag.json
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.serve_process import ServeProcess  # noqa: E402

PHOTOS = sorted((REPO / "samples" / "heldout-1000003").glob("frame_*.png"))
MAX_DRAGS = 20
MAX_DRAG_SECONDS = 10.0

#: Counts the page's render requests in flight and logs each one's time, size, quality and seq
#: (installed before the drags): an independent check of the page's "one request in flight".
FETCH_PROBE = """
if (!window.__renderProbe) {
  const probe = window.__renderProbe = { inflight: 0, max: 0, sent: 0, log: [] };
  const fetch0 = window.fetch.bind(window);
  window.fetch = function (url, options) {
    if (!/\\/render$/.test(String(url))) return fetch0(url, options);
    probe.inflight++; probe.sent++; probe.max = Math.max(probe.max, probe.inflight);
    const body = JSON.parse(options.body);
    probe.log.push({ t: performance.now(), width: body.width, height: body.height,
                     quality: "quality" in body ? body.quality : null, seq: body.seq });
    if (probe.log.length > 1000) probe.log.shift();
    const p = fetch0(url, options);
    const done = () => { probe.inflight--; };
    p.then(done, done);
    return p;
  };
}
window.__renderProbe.max = window.__renderProbe.inflight;
return true;
"""


def find_browser() -> tuple[str | None, str | None]:
    browser = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")
                    if shutil.which(n)), None)
    return browser, shutil.which("chromedriver")


def start_browser(window: str = "1440,960"):
    """Headless Chromium through selenium (no driver download: SE_OFFLINE)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    browser, driver = find_browser()
    if browser is None or driver is None:
        raise SystemExit("viewer_drag: no chromium/chromedriver (apt-get install chromium "
                         "chromium-driver)")
    os.environ.setdefault("SE_OFFLINE", "true")
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                f"--window-size={window}", "--force-device-scale-factor=1"):
        options.add_argument(arg)
    d = webdriver.Chrome(service=Service(executable_path=driver), options=options)
    d.set_page_load_timeout(60)
    d.set_script_timeout(60)
    return d


def wait_for(driver, script: str, timeout: float, what: str, poll: float = 0.02, args=()):
    """Poll ``script`` (JS returning a truthy value; ``args`` as ``arguments``) until it holds,
    at most ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = driver.execute_script(script, *args)
        if value:
            return value
        time.sleep(poll)
    raise TimeoutError(f"viewer_drag: {what} did not happen within {timeout:g} s")


#: The page's settings as it will send them: the full frame's and the previews' [H, W] and
#: quality ("" for the full frame: the server's default), the view's displayed size.
PAGE_SETTINGS = """
const p = previewSettings(), f = fullSettings();
return { full_size: f.size, full_quality: f.quality, size_menu: document.getElementById('size').value,
         preview_size: p && p.size, preview_quality: p && p.quality, view_size: viewSize(),
         view_css_px: [document.getElementById('view').clientWidth,
                       document.getElementById('view').clientHeight],
         device_pixel_ratio: window.devicePixelRatio, default_quality: state.model.default_quality };
"""


def set_view_px(driver, px: int | None, timeout: float = 30.0) -> list[int]:
    """Size the page's view to ``px`` CSS pixels square (None: the page's own layout) and wait
    until the page has seen it (its Size menu names the view's size); the view's size [H, W] in
    device pixels, what a full frame at "view" is rendered at."""
    driver.execute_script("document.getElementById('stage').style.width = arguments[0];",
                          "" if px is None else f"{int(px)}px")
    return wait_for(driver, "const v = state.model && viewSize();"
                    "const o = document.querySelector(\"#size option[value='view']\");"
                    "const w = document.getElementById('view').clientWidth;"
                    "return v && (arguments[0] === null || w === arguments[0]) && o && "
                    "o.textContent === `view (${v[1]}×${v[0]})` && v;",
                    timeout, "the view's new size", args=(px,))


def open_scene(driver, url: str, photos, timeout: float = 180.0, quality: str | None = None,
               size: str | None = None, cameras: str | None = None,
               view_px: int | None = None) -> dict:
    """Load the viewer, upload ``photos`` (full frames in ``quality`` at ``size``, cameras
    ``cameras``: the page's menu values, when given; the view sized to ``view_px`` CSS pixels,
    ``set_view_px``, when given), wait for the first full frame; the scene JSON."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select
    driver.get(url + "/")
    wait_for(driver, "return document.getElementById('model').textContent.startsWith('model ')",
             60, "the page's model line")
    if view_px is not None:
        set_view_px(driver, view_px)
    if quality is not None:
        Select(driver.find_element(By.ID, "quality")).select_by_value(quality)
    if size is not None:
        Select(driver.find_element(By.ID, "size")).select_by_value(size)
    if cameras is not None:
        Select(driver.find_element(By.ID, "cameras")).select_by_value(cameras)
    driver.find_element(By.ID, "photos").send_keys("\n".join(str(p) for p in photos))
    driver.find_element(By.ID, "encode").click()
    wait_for(driver, "return document.getElementById('view').dataset.kind === 'full' && !pumping",
             timeout, "the first view")
    driver.execute_script("document.getElementById('view').scrollIntoView({block: 'center'})")
    return driver.execute_script("return state.scene")


def mouse(driver, kind: str, x: float, y: float, buttons: int) -> None:
    driver.execute_cdp_cmd("Input.dispatchMouseEvent", {
        "type": kind, "x": x, "y": y, "button": "left", "buttons": buttons,
        "clickCount": 0 if kind == "mouseMoved" else 1})


def cdp_drag(driver, dx: float, dy: float, seconds: float, hz: float = 60.0,
             hold: float = 0.0) -> dict:
    """Press in the middle of the view, move by (dx, dy) CSS px over ``seconds`` s at ``hz``
    events per second (bounded: at most seconds * hz + 1 moves), wait ``hold`` s, release."""
    seconds = min(float(seconds), MAX_DRAG_SECONDS)
    left, top, w, h = driver.execute_script(
        "const r = document.getElementById('view').getBoundingClientRect();"
        "return [r.left, r.top, r.width, r.height];")
    x0, y0 = left + w / 2, top + h / 2
    mouse(driver, "mousePressed", x0, y0, 1)
    t0 = time.monotonic()
    moves, max_moves = 0, int(seconds * hz) + 1
    while moves < max_moves:
        frac = min((time.monotonic() - t0) / seconds, 1.0) if seconds > 0 else 1.0
        mouse(driver, "mouseMoved", x0 + dx * frac, y0 + dy * frac, 1)
        moves += 1
        if frac >= 1.0:
            break
        time.sleep(max(0.0, t0 + moves / hz - time.monotonic()))
    if hold > 0:
        time.sleep(hold)
    mouse(driver, "mouseReleased", x0 + dx, y0 + dy, 0)
    return {"moves": moves, "seconds": time.monotonic() - t0}


def reset_to_view0(driver, timeout: float) -> None:
    from selenium.webdriver.common.by import By
    driver.find_element(By.CSS_SELECTOR, "#view-buttons button[data-view='0']").click()
    wait_for(driver, "const c = document.getElementById('view'); return !pumping && "
             "c.dataset.kind === 'full' && c.dataset.pose === "
             "JSON.stringify(state.scene.world_from_cam[0]);", timeout, "view 0's full frame")


def measure_drag(driver, dx: float, dy: float, seconds: float, hz: float,
                 timeout: float) -> dict:
    """One drag (``cdp_drag``) and what the page showed: see the module docstring."""
    driver.execute_script(FETCH_PROBE)
    before = driver.execute_script("const s = window.viewerStats; return {sent: s.sent, "
                                   "aborted: s.aborted, superseded: s.superseded, "
                                   "drags: s.drags.length};")
    moved = cdp_drag(driver, dx, dy, seconds, hz)
    wait_for(driver, "const c = document.getElementById('view'); const d = viewerStats.drags;"
             "return !pumping && c.dataset.kind === 'full' && d.length > 0 && d[d.length-1].end"
             " && JSON.stringify(state.pose) === c.dataset.pose;", timeout, "the full frame")
    st = driver.execute_script("return window.viewerStats")
    probe = driver.execute_script("return window.__renderProbe")
    drag = st["drags"][-1]
    start, end, last = drag["start"], drag["end"], drag["lastMove"] or drag["start"]
    during = [f for f in st["frames"] if start < f["t"] <= end]
    full = next(f for f in st["frames"] if f["t"] > last and f["kind"] == "full")
    return {
        "drag_s": round((end - start) / 1000.0, 3), "mouse_moves": moved["moves"],
        "pointer_moves_seen": drag["moves"],
        "frames_during_drag": len(during),
        "fps_during_drag": round(len(during) / max((end - start) / 1000.0, 1e-9), 2),
        "preview_ms": [round(f["ms"], 1) for f in during],
        "frame_sizes_during_drag": sorted({f"{f['width']}x{f['height']} "
                                           f"{f['quality'] or 'default'}" for f in during}),
        "release_to_full_ms": round(max(full["t"] - end, 0.0), 1),
        "last_move_to_full_ms": round(full["t"] - last, 1),
        "full_frame_ms": round(full["ms"], 1),
        "full_frame": f"{full['width']}x{full['height']} {full['quality'] or 'default'}",
        "requests_sent": st["sent"] - before["sent"],
        "aborted_by_page": st["aborted"] - before["aborted"],
        "superseded_409": st["superseded"] - before["superseded"],
        "max_in_flight": probe["max"],
    }


def summary(drags: list[dict]) -> dict:
    med = lambda k: round(statistics.median(d[k] for d in drags), 2)    # noqa: E731
    previews = [ms for d in drags for ms in d["preview_ms"]]
    return {"drags": len(drags), "fps_during_drag_median": med("fps_during_drag"),
            "fps_during_drag_range": [min(d["fps_during_drag"] for d in drags),
                                      max(d["fps_during_drag"] for d in drags)],
            "release_to_full_ms_median": med("release_to_full_ms"),
            "last_move_to_full_ms_median": med("last_move_to_full_ms"),
            "full_frame_ms_median": med("full_frame_ms"),
            "full_frames": sorted({d["full_frame"] for d in drags}),
            "preview_ms_median": round(statistics.median(previews), 1) if previews else None,
            "max_in_flight": max(d["max_in_flight"] for d in drags)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model_dir")
    p.add_argument("--photos", type=int, default=4, help="sample photos uploaded (default 4)")
    p.add_argument("--drags", type=int, default=3, help=f"drags per mode (at most {MAX_DRAGS})")
    p.add_argument("--drag-seconds", type=float, default=2.0,
                   help=f"seconds of one drag (at most {MAX_DRAG_SECONDS:g})")
    p.add_argument("--hz", type=float, default=60.0, help="mouse events per second (default 60)")
    p.add_argument("--dx", type=float, default=240.0,
                   help="CSS px of one drag across (default 240)")
    p.add_argument("--dy", type=float, default=30.0, help="CSS px of one drag down (default 30)")
    p.add_argument("--view-px", type=int, default=256,
                   help="CSS px of the page's (square) view; device scale 1, so the full frame "
                   "at the view's size is this many pixels (default 256; 0: the page's layout)")
    p.add_argument("--size", default=None, help="full frame: the page's Size value (default "
                   "'view': the view's displayed size; 1, 2, 4, 8: multiples of the model's)")
    p.add_argument("--quality", default=None, help="full frame quality preset (default: none "
                   "sent, the server's default, 'auto' for explicit-colour models)")
    p.add_argument("--preview-quality", default=None, help="preview preset in mode 'preview' "
                   "(default: the page's, 'fast')")
    p.add_argument("--preview-size", default=None, help="preview size as a multiple of the "
                   "model's resolution: 0.5, 1, 2, 2.5, 4 (default: the page's, 2.5 with 'fast' "
                   "on an explicit-colour model)")
    p.add_argument("--modes", default="preview,off", help="comma-separated: preview, off")
    p.add_argument("--workers", type=int, default=2, help="iris-serve --workers (default 2)")
    p.add_argument("--threads", type=int, default=1, help="iris-serve --threads (default 1)")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for a frame")
    p.add_argument("--note", default="", help="conditions of the run, recorded in the JSON")
    p.add_argument("--json", default=None, help="write the results here")
    args = p.parse_args(argv)
    if not 1 <= args.drags <= MAX_DRAGS or not 0 < args.drag_seconds <= MAX_DRAG_SECONDS:
        p.error(f"--drags 1..{MAX_DRAGS} and --drag-seconds (0, {MAX_DRAG_SECONDS:g}] expected")
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes or any(m not in ("preview", "off") for m in modes):
        p.error("--modes: preview and/or off")

    from selenium.webdriver.support.ui import Select
    from selenium.webdriver.common.by import By
    load_start = os.getloadavg()
    try:
        server = ServeProcess(args.model_dir, "--workers", str(args.workers), "--threads",
                              str(args.threads))
    except RuntimeError:
        raise SystemExit("viewer_drag: iris-serve did not start") from None
    driver = None
    results: dict = {}
    try:
        driver = start_browser()
        scene = open_scene(driver, server.url, PHOTOS[:args.photos], args.timeout,
                           quality=args.quality, size=args.size, view_px=args.view_px or None)
        if args.preview_size is not None:
            Select(driver.find_element(By.ID, "preview-size")).select_by_value(args.preview_size)
        preview_quality = args.preview_quality or driver.execute_script(
            "return document.getElementById('preview-quality').value")
        sweep = float(driver.execute_script("return document.getElementById('view').dataset"
                                            ".sweepDeg"))
        width = float(driver.execute_script("return document.getElementById('view')"
                                            ".clientWidth"))
        page = {}
        for mode in modes:
            Select(driver.find_element(By.ID, "preview-quality")).select_by_value(
                preview_quality if mode == "preview" else "")
            page[mode] = driver.execute_script(PAGE_SETTINGS)
            print(f"{mode}: page settings {json.dumps(page[mode])}", file=sys.stderr)
            superseded0 = server.metric("iris_jobs_rejected_total", 'reason="superseded"')
            drags = []
            for i in range(args.drags):
                reset_to_view0(driver, args.timeout)
                sign = 1 if i % 2 == 0 else -1
                drags.append(measure_drag(driver, sign * args.dx, args.dy, args.drag_seconds,
                                          args.hz, args.timeout))
                print(f"{mode} drag {i}: {json.dumps(drags[-1])}", file=sys.stderr)
            results[mode] = {
                "page_settings": page[mode],
                "summary": summary(drags),
                "server_superseded_409": server.metric("iris_jobs_rejected_total",
                                                       'reason="superseded"') - superseded0,
                "drags": drags}
        version = driver.capabilities.get("browserVersion")
    finally:
        if driver is not None:
            driver.quit()
        server.stop()
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, text=True,
                                capture_output=True, timeout=30).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    out = {
        "command": "benchmarks/viewer_drag.py " + " ".join(sys.argv[1:] if argv is None
                                                           else argv),
        "note": args.note,
        "commit": commit,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "python": platform.python_version(), "chromium": version,
                    "load_avg_start": [round(x, 2) for x in load_start],
                    "load_avg_end": [round(x, 2) for x in os.getloadavg()]},
        "server": {"workers": args.workers, "threads": args.threads},
        "scene": {"photos": args.photos, "views": scene["views"],
                  "camera_source": scene["camera_source"]},
        "page": {"view_px": args.view_px, "full_size": args.size or "view (page default)",
                 "full_quality": args.quality or "server default",
                 "preview_quality": preview_quality,
                 "preview_size": args.preview_size or "page default",
                 "drag_sweep_deg_per_view_width": sweep, "view_width_css_px": width,
                 "drag_px": [args.dx, args.dy], "drag_seconds": args.drag_seconds,
                 "mouse_hz": args.hz},
        "modes": results,
    }
    text = json.dumps(out, indent=2)
    print(json.dumps({m: r["summary"] for m, r in results.items()}, indent=2))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
