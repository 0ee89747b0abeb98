// The IRIS viewer: a client of the iris-serve API and nothing else (docs/SERVING.md).
// Poses are world_from_cam 4x4 (rows), OpenCV axes, in the frame of the scene's view 0.
"use strict";

const $ = (id) => document.getElementById(id);
const canvas = $("view");
const ctx = canvas.getContext("2d");
const state = { model: null, files: [], scene: null, pose: null, centre: null, up: null,
                frame: null, playing: false };

// The full frame is rendered at the view's displayed size (the canvas's box in device pixels,
// at the model's aspect, at most the server's --max-output-pixels; or a size chosen in the menu)
// with the server's default quality (no "quality" sent unless one is chosen), and drawn pixel
// for pixel. While the camera moves the page asks for quick frames ("preview": a quick preset at
// a small size, drawn scaled to the view); SETTLE_MS after the last move it asks for the full
// frame. One render request is in flight at a time and at most one pose waits behind it (the
// latest); a full frame made stale by a newer pose is aborted. Every request carries this page's
// render stream and a growing seq, so the server drops a request of ours still waiting in its
// queue when a newer one arrives (409 "superseded", docs/SERVING.md).
const SETTLE_MS = 150;
// Previews: the first of these presets the server offers for this model ...
const PREVIEW_PRESETS = ["fast", "adaptive", "balanced"];
// ... at these multiples of the model's size. The default is 2.5 (160x160 for a 64x64 model)
// where the preview is "fast" on an explicit-colour model. "fast" marches half the output's
// rows and columns, and a march above the model's resolution takes two scales
// (iris_runtime.quality): at 160x160 a 20x20 field and 80x80 colours from the photos, at 128x128
// the model's full 64x64 grid, several times slower and no sharper. Other models preview at half
// the model's size.
const PREVIEW_SIZES = [0.5, 1, 2, 2.5, 4];
const RESIZE_MS = 250;            // the view's size settled: re-render the full frame at it
const STREAM = "viewer-" + Array.from(crypto.getRandomValues(new Uint8Array(8)),
  (b) => b.toString(16).padStart(2, "0")).join("");

// What the page did, for tests and benchmarks/viewer_drag.py (bounded lists).
const stats = window.viewerStats = {
  stream: STREAM, sent: 0, inflight: 0, maxInflight: 0, aborted: 0, superseded: 0, busy: 0,
  frames: [], drags: [],
};
const keep = (list, item, n = 500) => { list.push(item); if (list.length > n) list.shift(); };

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
  let message = `${res.status} ${res.statusText}`, type = "";
  try {
    const body = await res.json();
    if (body && body.error) {
      type = body.error.type;
      message = `${res.status} ${body.error.type}: ${body.error.message}`;
    }
  } catch (_) { /* not JSON */ }
  throw Object.assign(new Error(message), { status: res.status, type });
}

function showError(err) {
  const box = $("error");
  box.textContent = String(err.message || err);
  box.hidden = false;
  clearTimeout(showError.timer);
  showError.timer = setTimeout(() => { box.hidden = true; }, 9000);
}

// ---- pose maths (3x3 and 4x4 as arrays of rows) ----------------------------------------------
const DEG = Math.PI / 180;
const col = (R, j) => [R[0][j], R[1][j], R[2][j]];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const scale = (a, s) => a.map((x) => x * s);
const sub = (a, b) => a.map((x, i) => x - b[i]);
const add = (a, b) => a.map((x, i) => x + b[i]);
const norm = (a) => Math.hypot(...a);
const unit = (a) => scale(a, 1 / Math.max(norm(a), 1e-12));
const matvec = (M, v) => M.map((r) => dot(r, v));
const matmul = (A, B) => A.map((r) => [0, 1, 2].map((j) => dot(r, col(B, j))));
const clamp = (x, lo, hi) => Math.min(Math.max(x, lo), hi);
const wrap = (a) => Math.atan2(Math.sin(a), Math.cos(a));           // into (-pi, pi]
const horizontal = (v, up) => sub(v, scale(up, dot(v, up)));

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

// ---- the neighbourhood the photos cover ------------------------------------------------------
// Camera positions as angles about the scene centre: azimuth about the scene's up, elevation
// above the horizontal plane. The photos cover the arc of azimuths between their cameras (the
// circle minus its largest gap) and their range of elevations; the drag may leave that by MARGIN
// (at least MIN_MARGIN, else MARGIN_FRACTION of the larger span) and no further, and one drag
// across the view sweeps the covered arc plus both margins (at least MIN_SWEEP, at most half a
// circle), so the sensitivity follows the scene's camera spread. A view more than TOLERANCE
// outside the covered ranges is flagged as outside.
const MIN_MARGIN = 6 * DEG, MARGIN_FRACTION = 0.2, TOLERANCE = 2 * DEG;
const MIN_SWEEP = 15 * DEG, MAX_SWEEP = Math.PI, MAX_ELEVATION = 80 * DEG;

function coverageFrame(scene, centre, up) {
  const dirs = scene.world_from_cam.map((T) => unit(sub(col(T, 3), centre)));
  let e1 = horizontal(dirs.reduce(add, [0, 0, 0]), up);
  if (norm(e1) < 1e-6 * dirs.length) e1 = horizontal(dirs[0], up);
  if (norm(e1) < 1e-9) e1 = horizontal(Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0], up);
  e1 = unit(e1);
  const raw = dirs.map((d) => Math.atan2(dot(d, cross(up, e1)), dot(d, e1)));
  const sorted = [...raw].sort((a, b) => a - b);
  let gap = sorted[0] + 2 * Math.PI - sorted[sorted.length - 1], first = sorted[0];
  for (let i = 1; i < sorted.length; i++) {
    if (sorted[i] - sorted[i - 1] > gap) { gap = sorted[i] - sorted[i - 1]; first = sorted[i]; }
  }
  const span = 2 * Math.PI - gap, mid = first + span / 2;      // the covered arc, re-centred on 0
  e1 = unit(add(scale(e1, Math.cos(mid)), scale(cross(up, e1), Math.sin(mid))));
  const e2 = cross(up, e1);
  const az = dirs.map((d) => Math.atan2(dot(d, e2), dot(d, e1)));
  const el = dirs.map((d) => Math.asin(clamp(dot(d, up), -1, 1)));
  const elMin = Math.min(...el), elMax = Math.max(...el);
  const margin = Math.max(MIN_MARGIN, MARGIN_FRACTION * Math.max(span, elMax - elMin));
  const fullCircle = gap <= 2 * margin;
  return {
    centre, up, e1, e2, az, el, span, margin, fullCircle,
    azMin: -span / 2, azMax: span / 2, elMin, elMax,
    azLo: fullCircle ? -Math.PI : -span / 2 - margin, azHi: fullCircle ? Math.PI : span / 2 + margin,
    elLo: Math.max(elMin - margin, -MAX_ELEVATION), elHi: Math.min(elMax + margin, MAX_ELEVATION),
    sweep: clamp(fullCircle ? MAX_SWEEP : span + 2 * margin, MIN_SWEEP, MAX_SWEEP),
  };
}

function anglesOf(T, f = state.frame) {
  const d = unit(sub(col(T, 3), f.centre));
  return { az: Math.atan2(dot(d, f.e2), dot(d, f.e1)), el: Math.asin(clamp(dot(d, f.up), -1, 1)) };
}

function inside(a, f = state.frame) {
  return (f.fullCircle || (a.az >= f.azMin - TOLERANCE && a.az <= f.azMax + TOLERANCE)) &&
    a.el >= f.elMin - TOLERANCE && a.el <= f.elMax + TOLERANCE;
}

// Turn camera T about the scene centre: its azimuth by dAz, then its elevation by dEl (both
// exact, radius kept), the camera turning with its position.
function turn(T, dAz, dEl) {
  const f = state.frame;
  const R = T.slice(0, 3).map((r) => r.slice(0, 3));
  const C = col(T, 3);
  const yaw = rodrigues(f.up, dAz);
  const h = horizontal(matvec(yaw, sub(C, f.centre)), f.up);
  const axis = norm(h) > 1e-9 ? cross(unit(h), f.up) : f.e2;
  const M = matmul(rodrigues(axis, dEl), yaw);
  return rigid(matmul(M, R), add(f.centre, matvec(M, sub(C, f.centre))));
}

function showCoverage(pose) {
  const f = state.frame;
  if (!f) return;
  const a = anglesOf(pose);
  const out = !inside(a);
  $("outside").hidden = !out;
  $("stage").classList.toggle("outside", out);
  canvas.dataset.coverage = out ? "outside" : "inside";
  drawMap(a, out);
}

function drawMap(a, out) {                 // azimuth across, elevation up; degrees to scale
  const f = state.frame, map = $("coverage-map");
  const pad = 2 * DEG;
  const x0 = Math.min(f.azLo, a.az) - pad, x1 = Math.max(f.azHi, a.az) + pad;
  const y0 = Math.min(f.elLo, a.el) - pad, y1 = Math.max(f.elHi, a.el) + pad;
  const W = 132, H = clamp(Math.round(W * (y1 - y0) / (x1 - x0)), 28, 72);
  const dpr = window.devicePixelRatio || 1;
  map.width = W * dpr; map.height = H * dpr;
  map.style.width = `${W}px`; map.style.height = `${H}px`;
  const g = map.getContext("2d");
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  const X = (az) => 4 + (W - 8) * (az - x0) / (x1 - x0);
  const Y = (el) => H - 4 - (H - 8) * (el - y0) / (y1 - y0);
  g.clearRect(0, 0, W, H);
  g.strokeStyle = "rgba(255,255,255,0.35)"; g.setLineDash([3, 3]);
  g.strokeRect(X(f.azLo), Y(f.elHi), X(f.azHi) - X(f.azLo), Y(f.elLo) - Y(f.elHi));
  g.setLineDash([]);
  g.fillStyle = "rgba(95,145,235,0.35)";
  const lo = f.fullCircle ? f.azLo : f.azMin - TOLERANCE, hi = f.fullCircle ? f.azHi : f.azMax + TOLERANCE;
  g.fillRect(X(lo), Y(f.elMax + TOLERANCE), X(hi) - X(lo), Y(f.elMin - TOLERANCE) - Y(f.elMax + TOLERANCE));
  g.fillStyle = "#ffffff";
  f.az.forEach((az, i) => { g.fillRect(X(az) - 1.5, Y(f.el[i]) - 1.5, 3, 3); });
  g.fillStyle = out ? "#f5a524" : "#3ddc84";
  g.beginPath(); g.arc(X(a.az), Y(a.el), 3.5, 0, 2 * Math.PI); g.fill();
  map.hidden = false;
}

// ---- rendering: one request in flight, the latest pose wins ----------------------------------
const render = { seq: 0, wanted: null, inflight: null, shown: null };
let pumping = null;

// quality "": the server's default (the request carries no "quality").
const fullSettings = () => ({ size: outputSize(), quality: $("quality").value });
function previewSettings() {
  const q = $("preview-quality").value;
  if (!q) return null;                                 // "off": full frames while moving too
  const k = Number($("preview-size").value || 1), [H, W] = state.model.image_size;
  return { size: [Math.max(1, Math.round(H * k)), Math.max(1, Math.round(W * k))], quality: q };
}
const qualityName = (q) => q || (state.model.default_quality
  ? `default (model's: ${state.model.default_quality})` : "default (model's)");
const sameSettings = (a, b) => a.quality === b.quality && a.size[0] === b.size[0] && a.size[1] === b.size[1];

// Ask for `pose` as a "full" frame or a "preview"; `moving`: the camera is being dragged (more
// poses are coming). Returns a promise that settles when the page has no render left to do.
function request(pose, kind = "full", moving = false) {
  state.pose = pose;
  let settings = kind === "preview" ? previewSettings() : null;
  if (!settings) { kind = "full"; settings = fullSettings(); }
  const job = { pose, kind, settings };
  const cur = render.inflight, shown = render.shown;
  const same = (j) => j && j.pose === pose && j.kind === kind && sameSettings(j.settings, settings);
  if (kind === "full" && (same(cur) || (!cur && same(shown)))) {
    render.wanted = null;                              // already there, or on its way
    return pumping || Promise.resolve();
  }
  render.wanted = job;
  // Stale requests: a full frame in flight is slow, so a jump to another pose, the camera coming
  // to rest elsewhere or the first preview of a drag stop waiting for it (abort: its answer is
  // never drawn; the server drops it if it still waits for a worker, as this request's larger
  // seq arrives). A preview in flight is quick and is drawn; while the camera moves with
  // previews off, a full frame in flight is drawn too (aborting each would show nothing).
  // Either way the newest pose alone waits behind it.
  if (cur && cur.kind === "full" && (!moving || kind === "preview")) cur.controller.abort();
  if (!pumping) pumping = pump();
  return pumping;
}
const show = (pose) => request(pose, "full");

async function pump() {
  $("busy").hidden = false;
  try {
    while (render.wanted) {
      const job = render.wanted;
      render.wanted = null;
      await renderOnce(job);
    }
  } finally {
    pumping = null;
    $("busy").hidden = true;
  }
}

// The full frame's size: the menu's multiple of the model's, or ("view") the view's size.
function outputSize() {
  const [H, W] = state.model.image_size, v = $("size").value;
  if (v === "view" || v === "") return viewSize() || [H, W];
  const k = Number(v);
  return [H * k, W * k];
}

// The view's displayed size in device pixels at the model's aspect (the canvas box, which
// letterboxes a frame of another aspect), at most the server's output limit: [H, W], or null
// while the canvas is not laid out.
function viewSize() {
  const [H, W] = state.model.image_size, dpr = window.devicePixelRatio || 1;
  const bw = canvas.clientWidth * dpr, bh = canvas.clientHeight * dpr;
  if (!(bw > 0 && bh > 0)) return null;
  const max = state.model.limits.max_output_pixels;
  const s = Math.min(bw / W, bh / H, Math.sqrt(max / (H * W)));
  let h = Math.max(1, Math.round(H * s)), w = Math.max(1, Math.round(W * s));
  if (h * w > max) { h = Math.max(1, Math.floor(H * s)); w = Math.max(1, Math.floor(W * s)); }
  return [h, w];
}

// The Size menu's first entry names the view's current size; when the view is resized (window,
// zoom, device pixel ratio) and that entry is chosen, the full frame follows once it settles.
let resizeTimer = null;
function viewResized() {
  const option = $("size").querySelector("option[value='view']");
  const size = state.model && viewSize();
  if (option && size) option.textContent = `view (${size[1]}×${size[0]})`;
  clearTimeout(resizeTimer);
  resizeTimer = setTimeout(() => {
    if ($("size").value === "view" && state.scene && state.pose && !drag && !state.playing) {
      show(state.pose);                              // nothing is sent when the size is unchanged
    }
  }, RESIZE_MS);
}

async function renderOnce(job) {
  const { pose, kind, settings } = job;
  const [height, width] = settings.size, quality = settings.quality;
  const body = { world_from_cam: pose, height, width, stream: STREAM };
  if (quality) body.quality = quality;                 // else the server's default
  const seq = ++render.seq;
  const controller = new AbortController();
  render.inflight = { ...job, seq, controller };
  stats.sent++;
  stats.inflight++;
  stats.maxInflight = Math.max(stats.maxInflight, stats.inflight);
  const t0 = performance.now();
  try {
    const res = await api(`/scenes/${state.scene.scene_id}/render`, {
      method: "POST", headers: { "Content-Type": "application/json" }, signal: controller.signal,
      body: JSON.stringify({ ...body, seq }),
    });
    const bitmap = await createImageBitmap(await res.blob(),
      { colorSpaceConversion: "none", premultiplyAlpha: "none" });
    if (render.shown && seq <= render.shown.seq) {            // a newer frame is on screen
      bitmap.close();
      return;
    }
    if (kind === "full") {                   // pixel for pixel: the canvas takes the frame's size
      canvas.width = bitmap.width;
      canvas.height = bitmap.height;
      ctx.drawImage(bitmap, 0, 0);
    } else {                                 // a preview, scaled to the full frame's size
      const [fh, fw] = fullSettings().size;
      if (canvas.width !== fw || canvas.height !== fh) { canvas.width = fw; canvas.height = fh; }
      ctx.imageSmoothingEnabled = true;
      ctx.imageSmoothingQuality = "high";
      ctx.drawImage(bitmap, 0, 0, fw, fh);
    }
    bitmap.close();
    render.shown = { ...job, seq };
    $("stage-hint").hidden = true;
    Object.assign(canvas.dataset, {
      renders: String(Number(canvas.dataset.renders) + 1), pose: JSON.stringify(pose),
      height: String(height), width: String(width), quality, kind, seq: String(seq),
    });
    const ms = performance.now() - t0;
    keep(stats.frames, { t: performance.now(), kind, seq, width, height, quality, ms,
                         canvas: [canvas.width, canvas.height] });
    showCoverage(pose);
    $("render-info").textContent = `${width}×${height} ${qualityName(quality)}` +
      (kind === "preview" ? " (moving)" : "") + ` · ${ms.toFixed(0)} ms round trip`;
  } catch (err) {
    if (err.name === "AbortError") stats.aborted++;          // a newer pose made it stale
    else if (err.status === 409) stats.superseded++;          // the server said the same
    else if (err.status === 429 && kind === "preview") stats.busy++;   // the next move asks again
    else showError(err);
  } finally {
    stats.inflight--;
    render.inflight = null;
  }
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
    render.shown = null;
    const token = $("token").value.trim();
    if (token) sessionStorage.setItem("iris-token", token);
    describeScene(scene);
    await Promise.all([loadCameras(scene), loadOrbit(scene, 2)]);
    state.frame = coverageFrame(scene, state.centre, state.up);
    describeCoverage();
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
  checkFrames();
}

function describeCoverage() {
  const f = state.frame, deg = (a) => `${(a / DEG).toFixed(0)}°`;
  const photos = f.fullCircle ? "all around the scene" : `${deg(f.span)} around the scene`;
  $("drag-hint").textContent = `Drag the view to orbit the scene centre. The photos span ` +
    `${photos} and ${deg(f.elMax - f.elMin)} in height; a drag across the view turns ` +
    `${deg(f.sweep)}, and the orbit stops ${deg(f.margin)} outside the photos' views.`;
  canvas.dataset.sweepDeg = (f.sweep / DEG).toFixed(3);
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
// The frames box takes 2..the server's --max-orbit-frames; anything else is refused and said so
// (never silently clamped), and the orbit buttons wait for a valid number.
function frames() {
  const input = $("frames"), max = state.model ? state.model.limits.max_orbit_frames : 120;
  const text = input.value.trim(), n = Number(text);
  if (!/^\d+$/.test(text) || n < 2 || n > max) {
    return { n: null, message: text === "" ? "give a number of frames" :
      (Number.isFinite(n) && n > max ? `at most ${max} frames (the server's --max-orbit-frames)`
        : `a whole number from 2 to ${max}`) };
  }
  return { n, message: "" };
}

function checkFrames() {
  const { n, message } = frames();
  const input = $("frames");
  input.setCustomValidity(message);
  input.setAttribute("aria-invalid", n === null ? "true" : "false");
  $("frames-error").textContent = message;
  $("frames-error").hidden = n !== null;
  const ready = Boolean(state.scene) && n !== null;
  $("play").disabled = !ready && !state.playing;
  $("download").disabled = !ready;
  return n;
}

async function play() {
  if (state.playing) { state.playing = false; return; }
  const n = checkFrames();
  if (n === null) return;
  state.playing = true;
  $("play").textContent = "Stop";
  try {
    const poses = await loadOrbit(state.scene, n);
    for (const T of poses) {
      if (!state.playing) break;
      await show(T);
    }
  } catch (err) {
    showError(err);
  } finally {
    state.playing = false;
    $("play").textContent = "Play orbit";
    checkFrames();
  }
}

async function download() {
  const n = checkFrames();
  if (n === null) return;
  // The frames' size, made even: the mp4v encoder drops an odd row or column.
  const [height, width] = outputSize().map((x) => Math.max(2, x - (x % 2)));
  const button = $("download");
  button.disabled = true;
  button.textContent = "Rendering video…";
  try {
    const body = { frames: n, height, width };
    if ($("quality").value) body.quality = $("quality").value;     // else the server's default
    const res = await api(`/scenes/${state.scene.scene_id}/orbit.mp4`, {
      method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body),
    });
    const a = document.createElement("a");
    a.href = URL.createObjectURL(await res.blob());
    a.download = "orbit.mp4";
    a.click();
  } catch (err) {
    showError(err);
  } finally {
    button.textContent = "Download orbit video";
    checkFrames();
  }
}

// ---- dragging ---------------------------------------------------------------------------------
// Grab the scene: dragging right turns it right (the camera goes left about the centre), dragging
// down shows it from higher up. Previews while the pointer moves, the full frame SETTLE_MS after
// the last move (or at once when the pointer is released).
let drag = null, settle = null;
canvas.addEventListener("pointerdown", (e) => {
  if (!state.scene || !state.pose || !state.frame) return;
  const f = state.frame, a = anglesOf(state.pose);
  const R = state.pose.slice(0, 3).map((r) => r.slice(0, 3));
  const towards = cross(f.up, unit(horizontal(sub(col(state.pose, 3), f.centre), f.up)));
  drag = { x: e.clientX, y: e.clientY, pose: state.pose, az0: a.az, el0: a.el,
           sx: dot(col(R, 0), towards) > 0 ? -1 : 1, k: f.sweep / Math.max(canvas.clientWidth, 1),
           moved: false };
  keep(stats.drags, { start: performance.now(), end: null, lastMove: null, moves: 0 }, 50);
  try { canvas.setPointerCapture(e.pointerId); } catch (_) { /* synthetic pointer */ }
  canvas.classList.add("dragging");
});
canvas.addEventListener("pointermove", (e) => {
  if (!drag) return;
  const f = state.frame;
  let az = drag.az0 + drag.sx * (e.clientX - drag.x) * drag.k;
  let el = drag.el0 + (e.clientY - drag.y) * drag.k;
  if (!f.fullCircle) az = clamp(az, Math.min(f.azLo, drag.az0), Math.max(f.azHi, drag.az0));
  el = clamp(el, Math.min(f.elLo, drag.el0), Math.max(f.elHi, drag.el0));
  drag.moved = true;
  const d = stats.drags[stats.drags.length - 1];
  d.lastMove = performance.now();
  d.moves++;
  request(turn(drag.pose, az - drag.az0, el - drag.el0), "preview", true);
  clearTimeout(settle);
  settle = setTimeout(() => request(state.pose, "full"), SETTLE_MS);
});
function endDrag() {
  if (!drag) return;
  const moved = drag.moved;
  drag = null;
  canvas.classList.remove("dragging");
  stats.drags[stats.drags.length - 1].end = performance.now();
  clearTimeout(settle);
  if (moved) request(state.pose, "full");
}
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
  $("frames").addEventListener("input", checkFrames);
  $("token-row").addEventListener("submit", (e) => e.preventDefault());
  for (const id of ["size", "quality"]) {
    $(id).addEventListener("change", () => { if (state.pose && state.scene) show(state.pose); });
  }
  new ResizeObserver(viewResized).observe(canvas);
  try {
    const health = await (await fetch("/healthz")).json();
    state.model = { ...health.model, limits: health.limits };
    const [H, W] = health.model.image_size, maxPixels = health.limits.max_output_pixels;
    $("model").textContent = `model ${health.model.name} · ${W}×${H} · cameras ` +
      `${health.model.default_cameras}` + (health.auth ? " · token required" : "");
    $("token-row").hidden = !health.auth;
    // Size: the view's displayed size first (the default), then multiples of the model's.
    $("size").replaceChildren(new Option("view", "view"),
      ...[1, 2, 4, 8].filter((k) => k * k * H * W <= maxPixels)
        .map((k) => new Option(`${W * k}×${H * k}`, String(k))));
    viewResized();
    // The presets this server renders for this model (/healthz), in its order, after its default.
    const presets = health.model.quality_presets;
    $("quality").replaceChildren(new Option(qualityName(""), ""),
      ...presets.map((q) => new Option(q, q)));
    $("preview-quality").replaceChildren(...presets.map((q) => new Option(q, q)),
      new Option("off (full frames)", ""));
    const preview = PREVIEW_PRESETS.find((q) => presets.includes(q)) || "";
    $("preview-quality").value = preview;
    $("preview-size").replaceChildren(...PREVIEW_SIZES
      .filter((k) => Math.round(H * k) * Math.round(W * k) <= maxPixels)
      .map((k) => new Option(`${Math.round(W * k)}×${Math.round(H * k)}`, String(k))));
    $("preview-size").value = preview === "fast" && health.model.explicit_rgb ? "2.5" : "0.5";
    if (!$("preview-size").value) $("preview-size").selectedIndex = 0;
    const max = health.limits.max_orbit_frames;
    $("frames").max = String(max);
    $("frames-limit").textContent = `2–${max}`;
    checkFrames();
  } catch (err) {
    $("model").textContent = "server unreachable";
    showError(err);
  }
}

start();
