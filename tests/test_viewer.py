"""The viewer page at / in a real headless browser (Debian's chromium + chromium-driver, driven by
selenium) against a real iris-serve process: upload photos, wait for the solved cameras and a
rendered view, check its pixels against the API's render of the same pose, drag to orbit.

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
from selenium.webdriver.support.ui import Select, WebDriverWait  # noqa: E402

from tests.test_serve import PHOTOS, IrisServer  # noqa: E402

BROWSER = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")
                if shutil.which(n)), None)
DRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(
    BROWSER is None or DRIVER is None,
    reason="no headless browser: apt-get install chromium chromium-driver")
WAIT = 180.0


@pytest.fixture(scope="module")
def server(model_dir):
    srv = IrisServer(model_dir, "--workers", "2")
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


def api_render(url: str, scene_id: str, pose, height: int, width: int, quality: str):
    r = httpx.post(f"{url}/scenes/{scene_id}/render", timeout=120,
                   json={"world_from_cam": pose, "height": height, "width": width,
                         "quality": quality})
    assert r.status_code == 200, r.text
    return np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB"))


def test_viewer_uploads_shows_cameras_renders_and_orbits(browser, server):
    d, wait = browser, WebDriverWait(browser, WAIT)
    d.get(server.url + "/")
    wait.until(lambda d: d.find_element(By.ID, "model").text.startswith("model "))
    assert not d.find_element(By.ID, "encode").is_enabled()
    photos = PHOTOS[:4]
    d.find_element(By.ID, "photos").send_keys("\n".join(str(p) for p in photos))
    Select(d.find_element(By.ID, "quality")).select_by_value("fast")   # quick renders
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

    # The page shows exactly what the API renders for that pose and size.
    ds = d.execute_script("return Object.assign({}, document.getElementById('view').dataset)")
    pose = json.loads(ds["pose"])
    np.testing.assert_allclose(pose, scene["world_from_cam"][0], atol=1e-12)
    shown = canvas_pixels(d)
    expected = api_render(server.url, scene_id, pose, int(ds["height"]), int(ds["width"]),
                          ds["quality"])
    assert shown.shape == expected.shape == (*scene["image_size"], 3)
    assert np.abs(shown.astype(int) - expected.astype(int)).max() <= 1
    assert shown.std() > 1.0                                      # a picture, not a blank

    # Dragging turns the camera about the scene centre and renders the new view.
    before = renders(d)
    canvas = d.find_element(By.ID, "view")
    ActionChains(d).move_to_element(canvas).click_and_hold().move_by_offset(40, 0) \
        .move_by_offset(40, 10).release().perform()
    wait.until(lambda d: renders(d) > before and not d.execute_script("return pumping"))
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

    shot = os.environ.get("IRIS_VIEWER_SCREENSHOT")
    if shot:
        Select(d.find_element(By.ID, "size")).select_by_value("2")      # twice the model's
        Select(d.find_element(By.ID, "quality")).select_by_value("exact")
        n = renders(d)
        buttons[1].click()
        wait.until(lambda d: renders(d) > n and not d.execute_script("return pumping"))
        d.save_screenshot(shot)
