"""The viewer page at / in a real headless browser (Debian's chromium + chromium-driver, driven by
selenium) against a real iris-serve process: upload photos, wait for the solved cameras and a
rendered view at the view's displayed size, check its pixels against the API's render of the
same pose and size, drag to orbit, resize the view; a scripted drag (real mouse events through
Chrome DevTools, benchmarks/viewer_drag.py's) shows quick previews drawn scaled to the view with
one render request in flight and the full frame at the view's size and the server's default
quality once the camera stops, turns the camera by an angle scaled to the photos' spread and
stops outside their views, flagged; the page's layout, favicon and orbit-frames limit.

Full frames are rendered at the view's displayed size; the tests size the view to 64-128 CSS
pixels (``set_view_px``) so that a render stays quick on a loaded machine whatever the model
(the random model CI uses renders "exact" by default, and "fast"/"auto" not at all).

Skipped, with the reason, only where no browser (or selenium) is installed. With
``IRIS_VIEWER_SCREENSHOT=PATH`` the test also saves a screenshot of the page there (how
docs/images/viewer.png was made, with the shipped model: docs/SERVING.md).
"""
from __future__ import annotations

import io
import json
import os
import shutil

import numpy as np
import pytest

httpx = pytest.importorskip("httpx")
pytest.importorskip("fastapi")
selenium = pytest.importorskip("selenium", reason="selenium is not installed")
from PIL import Image  # noqa: E402
from selenium import webdriver  # noqa: E402
from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402

from benchmarks.viewer_drag import (FETCH_PROBE, PAGE_SETTINGS, cdp_drag, open_scene,  # noqa: E402
                                    set_view_px, wait_for)
from tests.test_serve import PHOTOS, IrisServer  # noqa: E402

BROWSER = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")
                if shutil.which(n)), None)
DRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(
    BROWSER is None or DRIVER is None,
    reason="no headless browser: apt-get install chromium chromium-driver")
WAIT = 180.0
#: CSS px of the view in the tests (device scale 1): the full frame's size at "view".
VIEW_PX = 64
DRAG_VIEW_PX = 128


@pytest.fixture(scope="module")
def server(model_dir):
    srv = IrisServer(model_dir, "--workers", "2", "--max-orbit-frames", "60")
    try:
        yield srv
    finally:
        srv.stop()


@pytest.fixture(scope="module")
def browser():
    from selenium.webdriver.chrome.service import Service
    os.environ.setdefault("SE_OFFLINE", "true")          # never let selenium fetch a driver
    options = webdriver.ChromeOptions()
    options.binary_location = BROWSER
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1440,960", "--force-device-scale-factor=1"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(executable_path=DRIVER), options=options)
    driver.set_page_load_timeout(60)
    driver.set_script_timeout(60)
    try:
        yield driver
    finally:
        driver.quit()


def canvas_pixels(driver) -> np.ndarray:
    """The rendered view as the page holds it: the canvas's RGB pixels."""
    h, w, data = driver.execute_script(
        "const c = document.getElementById('view');"
        "const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
        "return [c.height, c.width, Array.from(d)];")
    return np.array(data, dtype=np.uint8).reshape(h, w, 4)[..., :3]


def renders(driver) -> int:
    return int(driver.execute_script("return document.getElementById('view').dataset.renders"))


def api_render(url: str, scene_id: str, pose, height: int, width: int, quality: str | None):
    """The API's render (``quality`` None or "": none sent, the server's default)."""
    body = {"world_from_cam": pose, "height": height, "width": width}
    if quality:
        body["quality"] = quality
    r = httpx.post(f"{url}/scenes/{scene_id}/render", timeout=120, json=body)
    assert r.status_code == 200, r.text
    return np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB"))


def model_info(url: str) -> dict:
    return httpx.get(f"{url}/healthz", timeout=30).json()["model"]


def quick_quality(url: str) -> str:
    """A quick preset this server renders for its model: "fast" (every model renders it; its
    two scales apply to explicit-colour models only), else "adaptive"."""
    presets = model_info(url)["quality_presets"]
    return "fast" if "fast" in presets else "adaptive"


def full_frame_of_current_pose(driver) -> bool:
    """The page is idle and shows the full frame of the pose it was last asked for."""
    return driver.execute_script(
        "const c = document.getElementById('view');"
        "return !pumping && c.dataset.kind === 'full' && c.dataset.pose === "
        "JSON.stringify(state.pose);")


def severe_console_messages(driver) -> list[str]:
    return [e["message"] for e in driver.get_log("browser") if e["level"] == "SEVERE"]


def test_viewer_uploads_shows_cameras_renders_and_orbits(browser, server):
    d, wait = browser, WebDriverWait(browser, WAIT)
    d.get(server.url + "/")
    wait.until(lambda d: d.find_element(By.ID, "model").text.startswith("model "))
    assert not d.find_element(By.ID, "encode").is_enabled()
    # By default the full frame is rendered at the view's displayed size, in device pixels, and
    # at the server's default quality (the menu's first entry).
    model = model_info(server.url)
    size, quality = Select(d.find_element(By.ID, "size")), Select(d.find_element(By.ID, "quality"))
    css = d.execute_script("const c = document.getElementById('view');"
                           "return [c.clientHeight, c.clientWidth, window.devicePixelRatio];")
    view = [round(css[0] * css[2]), round(css[1] * css[2])]
    assert size.first_selected_option.get_attribute("value") == "view"
    assert size.first_selected_option.text == f"view ({view[1]}×{view[0]})"
    assert quality.options[0].get_attribute("value") == ""
    assert quality.first_selected_option.get_attribute("value") == ""
    assert quality.options[0].text == f"default (model's: {model['default_quality']})"
    assert [o.get_attribute("value") for o in quality.options[1:]] == model["quality_presets"]
    page = d.execute_script(PAGE_SETTINGS)
    assert page["full_size"] == view and page["full_quality"] == ""
    # A small view (quick renders on a loaded machine) and a quick preset.
    assert set_view_px(d, VIEW_PX) == [VIEW_PX, VIEW_PX]
    photos = PHOTOS[:4]
    d.find_element(By.ID, "photos").send_keys("\n".join(str(p) for p in photos))
    quality.select_by_value(quick_quality(server.url))
    assert len(d.find_elements(By.CSS_SELECTOR, "#thumbs img")) == 4
    d.find_element(By.ID, "encode").click()

    # The solved cameras' picture and a first view (input view 0's pose) appear.
    wait.until(lambda d: d.execute_script(
        "const i = document.getElementById('cameras-img');"
        "return !i.hidden && i.complete && i.naturalWidth > 0;"))
    wait.until(lambda d: renders(d) >= 1)
    assert d.execute_script("return document.getElementById('cameras-img').naturalWidth") == 640
    buttons = d.find_elements(By.CSS_SELECTOR, "#view-buttons button")
    assert [b.text for b in buttons] == [f"view {i}" for i in range(4)]
    facts = d.find_element(By.ID, "scene-info").text
    assert "views" in facts and "4" in facts
    scene_id = d.execute_script("return state.scene.scene_id")
    scene = httpx.get(f"{server.url}/scenes/{scene_id}", timeout=30).json()
    assert scene["views"] == 4

    # The page shows exactly what the API renders for that pose and the view's size.
    ds = d.execute_script("return Object.assign({}, document.getElementById('view').dataset)")
    pose = json.loads(ds["pose"])
    np.testing.assert_allclose(pose, scene["world_from_cam"][0], atol=1e-12)
    shown = canvas_pixels(d)
    expected = api_render(server.url, scene_id, pose, int(ds["height"]), int(ds["width"]),
                          ds["quality"])
    assert shown.shape == expected.shape == (VIEW_PX, VIEW_PX, 3)
    assert np.abs(shown.astype(int) - expected.astype(int)).max() <= 1
    assert shown.std() > 1.0                                      # a picture, not a blank

    # Dragging turns the camera about the scene centre and renders the new view.
    before = renders(d)
    canvas = d.find_element(By.ID, "view")
    ActionChains(d).move_to_element(canvas).click_and_hold().move_by_offset(40, 0) \
        .move_by_offset(40, 10).release().perform()
    wait.until(lambda d: renders(d) > before and full_frame_of_current_pose(d))
    ds = d.execute_script("return Object.assign({}, document.getElementById('view').dataset)")
    moved = np.array(json.loads(ds["pose"]))
    centre = np.array(d.execute_script("return state.centre"))
    start = np.array(scene["world_from_cam"][0])
    assert np.abs(moved[:3, :3].T @ moved[:3, :3] - np.eye(3)).max() < 1e-9   # still rigid
    assert np.linalg.det(moved[:3, :3]) > 0
    assert np.isclose(np.linalg.norm(moved[:3, 3] - centre), np.linalg.norm(start[:3, 3] - centre))
    assert not np.allclose(moved, start, atol=1e-3)
    after = canvas_pixels(d)
    expected = api_render(server.url, scene_id, moved.tolist(), int(ds["height"]),
                          int(ds["width"]), ds["quality"])
    assert np.abs(after.astype(int) - expected.astype(int)).max() <= 1

    # The view resized: the full frame follows it (once the size settles), same pose.
    before = renders(d)
    assert set_view_px(d, VIEW_PX + 16) == [VIEW_PX + 16] * 2
    wait.until(lambda d: renders(d) > before and full_frame_of_current_pose(d))
    ds = d.execute_script("return Object.assign({}, document.getElementById('view').dataset)")
    assert (int(ds["height"]), int(ds["width"])) == (VIEW_PX + 16, VIEW_PX + 16)
    np.testing.assert_allclose(json.loads(ds["pose"]), moved, atol=1e-12)
    assert canvas_pixels(d).shape == (VIEW_PX + 16, VIEW_PX + 16, 3)

    # Play orbit renders the orbit's frames in turn, ending on the last one.
    frames = d.find_element(By.ID, "frames")
    frames.clear()
    frames.send_keys("3")
    before = renders(d)
    d.find_element(By.ID, "play").click()
    wait.until(lambda d: renders(d) >= before + 3 and not d.execute_script("return pumping")
               and d.find_element(By.ID, "play").text == "Play orbit")
    orbit = httpx.get(f"{server.url}/scenes/{scene_id}/orbit", params={"frames": 3},
                      timeout=30).json()["world_from_cam"]
    shown_pose = json.loads(d.execute_script("return document.getElementById('view').dataset.pose"))
    np.testing.assert_allclose(shown_pose, orbit[-1], atol=1e-12)

    # Download orbit video: the page fetches orbit.mp4 and offers it as a download.
    d.execute_script("window.__downloads = [];"
                     "HTMLAnchorElement.prototype.click = function () {"
                     "  window.__downloads.push([this.download, this.href]); };")
    d.find_element(By.ID, "download").click()
    wait.until(lambda d: d.execute_script("return window.__downloads.length") == 1)
    name, head = d.execute_async_script(
        "const done = arguments[arguments.length - 1];"
        "const [name, href] = window.__downloads[0];"
        "fetch(href).then(r => r.arrayBuffer()).then(b => done("
        "  [name, Array.from(new Uint8Array(b.slice(4, 8)))]));")
    assert name == "orbit.mp4" and bytes(head) == b"ftyp"

    # An input camera button jumps back to that camera's pose.
    buttons[2].click()
    wait.until(lambda d: json.loads(d.execute_script(
        "return document.getElementById('view').dataset.pose")) == scene["world_from_cam"][2]
        and not d.execute_script("return pumping"))
    assert d.find_element(By.ID, "error").get_attribute("hidden") is not None   # no error shown
    assert severe_console_messages(d) == []             # no 404 (favicon), no script error

    shot = os.environ.get("IRIS_VIEWER_SCREENSHOT")
    if shot:                               # docs/images/viewer.png (docs/SERVING.md says how)
        set_view_px(d, None)                                  # the page's own layout, and its
        quality.select_by_value("")                           # defaults: the view's size, the
        n = renders(d)                                        # server's default quality
        buttons[1].click()
        wait.until(lambda d: renders(d) > n and full_frame_of_current_pose(d))
        d.set_window_size(1440, 1000)                                   # the whole view card
        try:
            # The round-trip time under the view is this machine's at this moment (a test run,
            # maybe a loaded one): not a figure for the docs' picture.
            d.execute_script("window.scrollTo(0, 0);"
                             "document.getElementById('render-info').textContent = '';")
            d.save_screenshot(shot)
        finally:
            d.set_window_size(1440, 960)


# -- a moving camera ----------------------------------------------------------------------------

def expected_sweep_deg(scene: dict, centre) -> tuple[float, float, float]:
    """docs/SERVING.md's rule, from the scene's cameras: (degrees one drag across the view
    turns, the photos' azimuth span, the margin the orbit may leave it by)."""
    T = np.array(scene["world_from_cam"])
    up = -T[:, :3, 1].mean(0)
    up /= np.linalg.norm(up)
    d = T[:, :3, 3] - np.asarray(centre)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    e1 = d.mean(0) - (d.mean(0) @ up) * up
    e1 /= np.linalg.norm(e1)
    az = np.sort(np.degrees(np.arctan2(d @ np.cross(up, e1), d @ e1)))
    el = np.degrees(np.arcsin(np.clip(d @ up, -1, 1)))
    gap = max(np.diff(az).max(initial=0.0), az[0] + 360 - az[-1])
    span = 360 - gap
    margin = max(6.0, 0.2 * max(span, el.max() - el.min()))
    sweep = 180.0 if gap <= 2 * margin else float(np.clip(span + 2 * margin, 15, 180))
    return sweep, span, margin


def angle_about(centre, a, b) -> float:
    """Degrees between camera centres a and b seen from the scene centre."""
    u, v = np.asarray(a) - centre, np.asarray(b) - centre
    return float(np.degrees(np.arccos(np.clip(u @ v / np.linalg.norm(u) / np.linalg.norm(v),
                                              -1, 1))))


def test_drag_previews_with_one_request_in_flight_then_the_full_frame(browser, server):
    """A scripted drag (real mouse events): only previews (the page's default: "fast" at 2.5x the
    model's size for an explicit-colour model) are asked for while the mouse moves, drawn scaled
    to the view, never more than one render request in flight; holding still asks for the full
    frame SETTLE_MS later, at the view's displayed size and (explicit-colour models) the server's
    default quality, no "quality" sent; after the release that frame of the final pose is shown,
    equal bit for bit to the API's render of that pose at that size. The drag turns the camera
    about the scene centre by the angle the scene's camera spread gives, not half a circle per
    view width."""
    d = browser
    model = model_info(server.url)
    H, W = model["image_size"]
    # The server's default quality ("auto": two scales) where it is quick; the random model CI
    # uses has "exact" as its default, too slow at the view's size on a loaded machine.
    quality = None if model["explicit_rgb"] else "adaptive"
    # Cameras solved from the photos: the same geometry whatever model the server runs.
    scene = open_scene(d, server.url, PHOTOS[:4], WAIT, quality=quality, cameras="solve",
                       view_px=DRAG_VIEW_PX)
    page = d.execute_script(PAGE_SETTINGS)
    vh, vw = page["view_size"]
    assert [vh, vw] == [DRAG_VIEW_PX, DRAG_VIEW_PX] and page["full_size"] == [vh, vw]
    assert page["full_quality"] == (quality or "")
    ph, pw = page["preview_size"]
    if model["explicit_rgb"]:                    # the page's default previews
        assert (page["preview_quality"], ph, pw) == ("fast", round(2.5 * H), round(2.5 * W))
    else:
        # Every model renders "fast" (its two scales apply to explicit colour only): the
        # first preview preset, at half the model's size.
        assert (page["preview_quality"], ph, pw) == ("fast", round(H / 2), round(W / 2))
    centre = np.array(d.execute_script("return state.centre"))
    start = np.array(scene["world_from_cam"][0])
    sweep = float(d.execute_script("return document.getElementById('view').dataset.sweepDeg"))
    expected, span, margin = expected_sweep_deg(scene, centre)
    assert sweep == pytest.approx(expected, abs=0.01)
    assert sweep < 90                            # these photos span a few tens of degrees at most
    width = float(d.execute_script("return document.getElementById('view').clientWidth"))
    d.execute_script(FETCH_PROBE)
    dx = round(0.2 * width)                      # 0.2 sweep < margin: never at the orbit's limit
    cdp_drag(d, dx, 0, seconds=1.2, hz=60, hold=0.6)
    wait_for(d, "const c = document.getElementById('view'); return !pumping && "
             "c.dataset.kind === 'full' && c.dataset.pose === JSON.stringify(state.pose);",
             60, "the full frame after the drag")
    st = d.execute_script("return window.viewerStats")
    probe = d.execute_script("return window.__renderProbe")
    drag = st["drags"][-1]
    assert probe["max"] == 1 and st["maxInflight"] == 1          # never two renders in flight
    moving = [r for r in probe["log"] if drag["start"] < r["t"] <= drag["lastMove"]]
    assert moving and all((r["width"], r["height"], r["quality"])
                          == (pw, ph, page["preview_quality"]) for r in moving), moving
    drawn = [f for f in st["frames"] if drag["start"] < f["t"] <= drag["end"]
             and f["kind"] == "preview"]
    # Drawn scaled to the view: the canvas keeps the full frame's size.
    assert drawn and all((f["width"], f["height"], *f["canvas"]) == (pw, ph, vw, vh)
                         for f in drawn), drawn
    # Held still: the full frame was asked for SETTLE_MS (150 ms) after the last move, before
    # the release; before it at most the preview of the last pose, which waited behind the one
    # in flight; then nothing (the release finds the full frame on its way).
    after = [(r["width"], r["height"], r["quality"], r["t"]) for r in probe["log"]
             if r["t"] > drag["lastMove"]]
    fulls = [r for r in after if r[:3] == (vw, vh, quality)]        # quality None: not sent
    assert len(fulls) == 1 and len(after) <= 2 and after[-1] == fulls[0], after
    assert 130 <= fulls[0][3] - drag["lastMove"] and fulls[0][3] < drag["end"]
    ds = d.execute_script("return Object.assign({}, document.getElementById('view').dataset)")
    assert (int(ds["height"]), int(ds["width"]), ds["quality"]) == (vh, vw, quality or "")
    moved = np.array(json.loads(ds["pose"]))
    assert np.abs(moved[:3, :3].T @ moved[:3, :3] - np.eye(3)).max() < 1e-9
    assert np.isclose(np.linalg.norm(moved[:3, 3] - centre), np.linalg.norm(start[:3, 3] - centre))
    assert angle_about(centre, start[:3, 3], moved[:3, 3]) == pytest.approx(
        dx * sweep / width, rel=0.03)
    assert ds["coverage"] == "inside" and not d.find_element(By.ID, "outside").is_displayed()
    shown = canvas_pixels(d)
    expected_pixels = api_render(server.url, scene["scene_id"], moved.tolist(), vh, vw, quality)
    assert shown.shape == (vh, vw, 3)
    np.testing.assert_array_equal(shown, expected_pixels)             # bit for bit

    # Far past the photos: the orbit stops at their arc plus the margin, and says it is outside.
    turned = angle_about(centre, start[:3, 3], moved[:3, 3])
    cdp_drag(d, -3 * width, 0, seconds=0.6, hz=60)
    wait_for(d, "const c = document.getElementById('view'); return !pumping && "
             "c.dataset.kind === 'full' && c.dataset.pose === JSON.stringify(state.pose);",
             60, "the full frame after the second drag")
    far = np.array(json.loads(d.execute_script(
        "return document.getElementById('view').dataset.pose")))
    beyond = angle_about(centre, start[:3, 3], far[:3, 3])
    assert beyond <= span + margin + 0.5 + turned        # not 3 x sweep: stopped at the limit
    assert beyond >= margin - 0.5
    assert d.execute_script("return document.getElementById('view').dataset.coverage") == \
        "outside"
    assert d.find_element(By.ID, "outside").is_displayed()
    d.find_element(By.CSS_SELECTOR, "#view-buttons button[data-view='1']").click()
    wait_for(d, "return document.getElementById('view').dataset.coverage === 'inside' && "
             "!pumping", 60, "back inside at view 1")
    assert not d.find_element(By.ID, "outside").is_displayed()


# -- layout, favicon, limits ---------------------------------------------------------------------

OVERFLOW = """
const out = [];
for (const card of document.querySelectorAll('.card')) {
  const c = card.getBoundingClientRect();
  if (card.scrollWidth > card.clientWidth + 1) out.push(card.id + ' scrolls');
  for (const el of card.querySelectorAll('*')) {
    const r = el.getBoundingClientRect();
    if (r.width === 0 || r.height === 0) continue;
    if (r.right > c.right + 0.5 || r.left < c.left - 0.5)
      out.push(card.id + ' > ' + (el.id || el.tagName) + ' ' + r.left + '..' + r.right +
               ' outside ' + c.left + '..' + c.right);
  }
}
return out;
"""


def test_layout_favicon_and_orbit_frames_limit(browser, server):
    """Every card holds its content at four window widths (the Cameras menu overflowed its
    card); the favicon is served and nothing fails in the console; the orbit-frames box shows
    the server's limit and refuses a number over it instead of clamping it."""
    d = browser
    r = httpx.get(server.url + "/favicon.ico", timeout=30)
    assert r.status_code == 200 and r.headers["content-type"] == "image/x-icon"
    assert Image.open(io.BytesIO(r.content)).size[0] >= 16
    assert httpx.get(server.url + "/static/favicon.svg", timeout=30).status_code == 200
    d.get_log("browser")                                          # start from an empty log
    # The model's size, not the view's: resizing the window re-renders nothing.
    open_scene(d, server.url, PHOTOS[:3], WAIT, quality=quick_quality(server.url), size="1")
    assert d.execute_script("return document.querySelector('link[rel=icon]').href")
    Select(d.find_element(By.ID, "cameras")).select_by_value("refined")   # its longest option
    try:
        for size in ((1440, 960), (1180, 900), (1024, 900), (720, 900)):
            d.set_window_size(*size)
            assert d.execute_script(OVERFLOW) == [], size
    finally:
        d.set_window_size(1440, 960)

    frames = d.find_element(By.ID, "frames")
    assert d.find_element(By.ID, "frames-limit").text == "2–60"      # the server's limit
    assert frames.get_attribute("max") == "60"
    play, download = d.find_element(By.ID, "play"), d.find_element(By.ID, "download")
    assert play.is_enabled() and download.is_enabled()
    for text, message in (("9999", "at most 60"), ("61", "at most 60"), ("1", "2 to 60"),
                          ("", "give a number")):
        frames.clear()
        if text:
            frames.send_keys(text)
        else:
            frames.send_keys("5", Keys.BACKSPACE)
        assert frames.get_attribute("value") == text                 # kept, not clamped
        assert frames.get_attribute("aria-invalid") == "true"
        assert not d.execute_script("return document.getElementById('frames').validity.valid")
        error = d.find_element(By.ID, "frames-error")
        assert error.is_displayed() and message in error.text, (text, error.text)
        assert not play.is_enabled() and not download.is_enabled()
    frames.clear()
    frames.send_keys("60")
    assert frames.get_attribute("aria-invalid") == "false"
    assert not d.find_element(By.ID, "frames-error").is_displayed()
    assert play.is_enabled() and download.is_enabled()
    assert severe_console_messages(d) == []
