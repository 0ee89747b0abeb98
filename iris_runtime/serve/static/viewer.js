// The IRIS viewer: a client of the iris-serve API and nothing else (docs/SERVING.md).
// Poses are world_from_cam 4x4 (rows), OpenCV axes, in the frame of the scene's view 0.
"use strict";

const $ = (id) => document.getElementById(id);
const canvas = $("view");
const ctx = canvas.getContext("2d");
const state = { model: null, files: [], scene: null, pose: null, centre: null, up: null,
                playing: false };

// ---- API -------------------------------------------------------------------------------------
function authHeaders() {
  const token = $("token").value.trim() || sessionStorage.getItem("iris-token") || "";
  return token ? { Authorization: `Bearer ${token}` } : {};
}

async function api(path, options = {}) {
  const headers = { ...(options.headers || {}), ...authHeaders() };
  const res = await fetch(path, { ...options, headers });
  if (res.ok) return res;
  if (res.status === 401) $("token-row").hidden = false;
  let message = `${res.status} ${res.statusText}`;
  try {
    const body = await res.json();
    if (body && body.error) message = `${res.status} ${body.error.type}: ${body.error.message}`;
  } catch (_) { /* not JSON */ }
  throw new Error(message);
}

function showError(err) {
  const box = $("error");
  box.textContent = String(err.message || err);
  box.hidden = false;
  clearTimeout(showError.timer);
  showError.timer = setTimeout(() => { box.hidden = true; }, 9000);
}

// ---- pose maths (3x3 and 4x4 as arrays of rows) ----------------------------------------------
const col = (R, j) => [R[0][j], R[1][j], R[2][j]];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const scale = (a, s) => a.map((x) => x * s);
const sub = (a, b) => a.map((x, i) => x - b[i]);
const add = (a, b) => a.map((x, i) => x + b[i]);
const unit = (a) => scale(a, 1 / Math.max(Math.hypot(...a), 1e-12));
const matvec = (M, v) => M.map((r) => dot(r, v));
const matmul = (A, B) => A.map((r) => [0, 1, 2].map((j) => dot(r, col(B, j))));

function rodrigues(axis, angle) {          // rotation by `angle` about unit `axis`
  const [x, y, z] = unit(axis), c = Math.cos(angle), s = Math.sin(angle), t = 1 - c;
  return [[t * x * x + c, t * x * y - s * z, t * x * z + s * y],
          [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
          [t * x * z - s * y, t * y * z + s * x, t * z * z + c]];
}

function rigid(R, C) {                     // re-orthonormalise (Gram-Schmidt) and pack a 4x4
  const x = unit(col(R, 0));
  const y = unit(sub(col(R, 1), scale(x, dot(x, col(R, 1)))));
  const z = cross(x, y);
  return [[x[0], y[0], z[0], C[0]], [x[1], y[1], z[1], C[1]], [x[2], y[2], z[2], C[2]], [0, 0, 0, 1]];
}

// Turn the camera about the scene centre: yaw about the scene's up, pitch about the camera's x.
function orbitPose(T, yaw, pitch) {
  const R = T.slice(0, 3).map((r) => r.slice(0, 3));
  const C = T.slice(0, 3).map((r) => r[3]);
  const M = matmul(rodrigues(col(R, 0), pitch), rodrigues(state.up, yaw));
  return rigid(matmul(M, R), add(state.centre, matvec(M, sub(C, state.centre))));
}

// ---- rendering: one request in flight, the latest pose wins ----------------------------------
let wanted = null, pumping = null;

function show(pose) {
  wanted = pose;
  state.pose = pose;
  if (!pumping) pumping = pump();
  return pumping;
}

async function pump() {
  $("busy").hidden = false;
  try {
    while (wanted) {
      const pose = wanted;
      wanted = null;
      await renderOnce(pose);
    }
  } catch (err) {
    showError(err);
  } finally {
    pumping = null;
    $("busy").hidden = true;
  }
}

function outputSize() {
  const k = Number($("size").value || 1), [H, W] = state.model.image_size;
  return [H * k, W * k];
}

async function renderOnce(pose) {
  const t0 = performance.now();
  const [height, width] = outputSize();
  const quality = $("quality").value;
  const res = await api(`/scenes/${state.scene.scene_id}/render`, {
    method: "POST", headers: { "Content-Type": "application/json" },
    body: JSON.stringify({ world_from_cam: pose, height, width, quality }),
  });
  const bitmap = await createImageBitmap(await res.blob(),
    { colorSpaceConversion: "none", premultiplyAlpha: "none" });
  canvas.width = bitmap.width;
  canvas.height = bitmap.height;
  ctx.drawImage(bitmap, 0, 0);
  $("stage-hint").hidden = true;
  Object.assign(canvas.dataset, {
    renders: String(Number(canvas.dataset.renders) + 1), pose: JSON.stringify(pose),
    height: String(height), width: String(width), quality,
  });
  $("render-info").textContent =
    `${width}×${height} ${quality} · ${(performance.now() - t0).toFixed(0)} ms round trip`;
}

// ---- photos and encoding ---------------------------------------------------------------------
function setFiles(list) {
  state.files = Array.from(list).filter((f) => f.type.startsWith("image/") || /\.(png|jpe?g|webp|bmp|tiff?)$/i.test(f.name));
  const thumbs = $("thumbs");
  thumbs.replaceChildren(...state.files.map((f) => {
    const img = document.createElement("img");
    img.src = URL.createObjectURL(f);
    img.alt = f.name;
    img.title = f.name;
    return img;
  }));
  $("drop-text").textContent = state.files.length
    ? `${state.files.length} photo(s) chosen` : "Choose two or more photos of one scene, or drop them here";
  $("encode").disabled = state.files.length < 2;
}

async function encode() {
  const form = new FormData();
  state.files.forEach((f) => form.append("images", f, f.name));
  if ($("cameras").value) form.append("cameras", $("cameras").value);
  $("encode").disabled = true;
  $("encode").textContent = "Encoding…";
  try {
    if (state.scene) {         // the previous scene is no longer shown: free it on the server
      api(`/scenes/${state.scene.scene_id}`, { method: "DELETE" }).catch(() => {});
    }
    const scene = await (await api("/scenes", { method: "POST", body: form })).json();
    state.scene = scene;
    const token = $("token").value.trim();
    if (token) sessionStorage.setItem("iris-token", token);
    describeScene(scene);
    await Promise.all([loadCameras(scene), loadOrbit(scene, 2)]);
    show(scene.world_from_cam[0]);
  } catch (err) {
    showError(err);
  } finally {
    $("encode").disabled = state.files.length < 2;
    $("encode").textContent = "Encode scene";
  }
}

function describeScene(scene) {
  const facts = {
    scene: scene.scene_id, views: scene.views,
    cameras: scene.camera_source, "focal fx/W, fy/H": scene.focal.map((f) => f.toFixed(4)).join(", "),
    resolution: `${scene.image_size[1]}×${scene.image_size[0]}`,
  };
  const dl = $("scene-info");
  dl.replaceChildren(...Object.entries(facts).flatMap(([k, v]) => {
    const dt = document.createElement("dt"), dd = document.createElement("dd");
    dt.textContent = k;
    dd.textContent = v;
    return [dt, dd];
  }));
  dl.hidden = false;
  const buttons = $("view-buttons");
  buttons.replaceChildren(...scene.world_from_cam.map((T, i) => {
    const b = document.createElement("button");
    b.textContent = `view ${i}`;
    b.dataset.view = String(i);
    b.onclick = () => {
      buttons.querySelectorAll("button").forEach((x) => x.classList.toggle("active", x === b));
      show(T);
    };
    return b;
  }));
  // The scene's up: minus the mean of the cameras' y axes (OpenCV: y points down).
  state.up = unit(scene.world_from_cam.reduce((acc, T) => sub(acc, col(T, 1)), [0, 0, 0]));
  $("play").disabled = $("download").disabled = false;
}

async function loadCameras(scene) {
  const blob = await (await api(`/scenes/${scene.scene_id}/cameras.png`)).blob();
  const img = $("cameras-img");
  await new Promise((resolve, reject) => {
    img.onload = resolve;
    img.onerror = () => reject(new Error("the cameras picture did not load"));
    img.src = URL.createObjectURL(blob);
  });
  img.hidden = false;
  $("cameras-hint").hidden = true;
}

async function loadOrbit(scene, frames) {
  const orbit = await (await api(`/scenes/${scene.scene_id}/orbit?frames=${frames}`)).json();
  state.centre = orbit.centre;
  return orbit.world_from_cam;
}

// ---- orbit: play and download ----------------------------------------------------------------
function frames() {
  const n = Math.round(Number($("frames").value));
  return Math.min(Math.max(Number.isFinite(n) ? n : 24, 2), state.model.limits.max_orbit_frames);
}

async function play() {
  if (state.playing) { state.playing = false; return; }
  state.playing = true;
  $("play").textContent = "Stop";
  try {
    const poses = await loadOrbit(state.scene, frames());
    for (const T of poses) {
      if (!state.playing) break;
      await show(T);
    }
  } catch (err) {
    showError(err);
  } finally {
    state.playing = false;
    $("play").textContent = "Play orbit";
  }
}

async function download() {
  const [height, width] = outputSize();
  const button = $("download");
  button.disabled = true;
  button.textContent = "Rendering video…";
  try {
    const res = await api(`/scenes/${state.scene.scene_id}/orbit.mp4`, {
      method: "POST", headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ frames: frames(), height, width, quality: $("quality").value }),
    });
    const a = document.createElement("a");
    a.href = URL.createObjectURL(await res.blob());
    a.download = "orbit.mp4";
    a.click();
  } catch (err) {
    showError(err);
  } finally {
    button.disabled = false;
    button.textContent = "Download orbit video";
  }
}

// ---- dragging ---------------------------------------------------------------------------------
let drag = null;
canvas.addEventListener("pointerdown", (e) => {
  if (!state.scene || !state.pose) return;
  drag = { x: e.clientX, y: e.clientY, pose: state.pose };
  canvas.setPointerCapture(e.pointerId);
  canvas.classList.add("dragging");
});
canvas.addEventListener("pointermove", (e) => {
  if (!drag) return;
  const k = Math.PI / canvas.clientWidth;     // a drag across the view turns half a circle
  show(orbitPose(drag.pose, (e.clientX - drag.x) * k, -(e.clientY - drag.y) * k));
});
const endDrag = () => { drag = null; canvas.classList.remove("dragging"); };
canvas.addEventListener("pointerup", endDrag);
canvas.addEventListener("pointercancel", endDrag);

// ---- start -------------------------------------------------------------------------------------
async function start() {
  $("photos").addEventListener("change", (e) => setFiles(e.target.files));
  const drop = $("drop");
  drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => {
    e.preventDefault();
    drop.classList.remove("over");
    setFiles(e.dataTransfer.files);
  });
  $("encode").onclick = encode;
  $("play").onclick = play;
  $("download").onclick = download;
  for (const id of ["size", "quality"]) {
    $(id).addEventListener("change", () => { if (state.pose && state.scene) show(state.pose); });
  }
  try {
    const health = await (await fetch("/healthz")).json();
    state.model = { ...health.model, limits: health.limits };
    const [H, W] = health.model.image_size;
    $("model").textContent = `model ${health.model.name} · ${W}×${H} · cameras ` +
      `${health.model.default_cameras}` + (health.auth ? " · token required" : "");
    $("token-row").hidden = !health.auth;
    $("size").replaceChildren(...[1, 2, 4].filter((k) => k * k * H * W <= health.limits.max_output_pixels)
      .map((k) => new Option(`${W * k}×${H * k}`, String(k))));
  } catch (err) {
    $("model").textContent = "server unreachable";
    showError(err);
  }
}

start();
