// quatrack viewer: stream the webcam or a video file over /v1/objects/{name}/track and draw each
// answer: wireframe + axes at the pose (object -> camera, X_cam = R(q) X_obj + t, q = [w, x, y, z]),
// status, latency, and scrolling plots of position and orientation with 3-sigma bands.
// Lock-step: one frame in flight, so the drawn frame is the one the pose is for.
"use strict";

const $ = (id) => document.getElementById(id);
const state = { run: 0, ws: null, running: false, edges: [], bbox: null, camera: null, count: 0, history: [], t0: 0 };
const HISTORY = 200;
const COLOURS = { tracking: "rgb(0,220,0)", init: "rgb(255,215,0)" };
const AXIS_RGB = [[221, 51, 51], [34, 153, 34], [51, 51, 221]];  // x, y, z
const AXIS_COLOURS = AXIS_RGB.map(([r, g, b]) => `rgb(${r},${g},${b})`);
const AXIS_BANDS = AXIS_RGB.map(([r, g, b]) => `rgba(${r},${g},${b},0.25)`);
// The codes of a frame the server refuses on arrival, before numbering it (service/codes.py
// REFUSED_FRAME; tests/test_viewer_ux.py checks that the two lists are equal): such an error,
// without "frame", is the answer to the frame just sent. Any other error without "frame" (a
// refused frame header: out_of_order, bad_message) is not, and the frame's answer still comes.
const REFUSED_FRAME = new Set(["camera_required", "rate_limited", "too_large", "unsupported_image"]);

// The service's root, from this script's own URL (…/viewer/viewer.js → …/): every request and the
// socket are made relative to it, so the page works behind a proxy serving the service under a
// path prefix (the page at /quatrack/viewer/); absolute paths (/v1/…) left the prefix.
const ROOT = new URL("../", (document.currentScript && document.currentScript.src) || location.href);
function api(path) { return new URL(path, ROOT); }  // path: relative, "v1/…"

function token() { return $("token").value.trim(); }
function headers() { return token() ? { Authorization: "Bearer " + token() } : {}; }
function message(text) { $("message").textContent = text || ""; }

function apiError(error, status) {  // an Error carrying the service's error code (and the HTTP status)
  const e = new Error(error ? error.code + ": " + error.message : "HTTP " + status);
  e.code = error && error.code; e.status = status;
  return e;
}

async function getJSON(path) {
  const r = await fetch(api(path), { headers: headers() });
  const body = await r.json().catch(() => ({}));
  if (!r.ok) throw apiError(body.error, r.status);
  return body;
}

let listing = 0;  // the latest object list asked for: an older answer coming later is dropped
let listNote = "";  // what the list said in the message line (cleared only by the list)
let listLoad = Promise.resolve();  // the latest list's loading: a run waits for it
let listedToken = null;  // the token the latest list was asked with
let listError = "";  // why the latest list failed ("" when it did not): a run says it, not "pick an object"

function listMessage(text, say = true) {
  if (say && (text || $("message").textContent === listNote)) message(text);
  listNote = text;
}

function brokenReason(o) {  // the model's error without the object's name, which the list says already
  const named = `object '${o.name}': `;
  return o.error.startsWith(named) ? o.error.slice(named.length) : o.error;
}

function unauthorizedText() {  // a 401: what to do about it
  return "unauthorized: " + (token() ? "the token was refused; type the server's token in the token field"
                                     : "the server has a token; type the server's token in the token field");
}

function loadObjects(say = true) {  // say: false keeps the message line (a run's error stays said)
  listedToken = token();
  listLoad = listObjects(say);
  return listLoad;
}

async function listObjects(say) {
  const mine = ++listing;
  const sel = $("object");
  try {
    const list = await getJSON("v1/objects");
    if (mine !== listing) return;
    const keep = sel.value;
    sel.innerHTML = "";
    const broken = [];
    for (const o of list.objects) {  // a model that cannot be loaded is listed, not chosen
      const opt = new Option(o.error ? `${o.name} (broken)` : o.name, o.name);
      if (o.error) { opt.disabled = true; opt.title = brokenReason(o); broken.push(`${o.name}: ${brokenReason(o)}`); }
      sel.add(opt);
    }
    const usable = [...sel.options].filter((o) => !o.disabled);
    sel.value = usable.some((o) => o.value === keep) ? keep : usable.length ? usable[0].value : "";
    listError = "";
    if (!list.objects.length) listMessage("no trained object on this server (quatrack train SPEC.json, then reload objects)", say);
    else listMessage(broken.length ? `${broken.length} object(s) cannot be loaded: ${broken.join("; ")}` : "", say);
  } catch (e) {
    if (mine !== listing) return;
    sel.innerHTML = "";  // (what an earlier token listed is not offered)
    listError = "objects: " + (e instanceof TypeError ? "the server does not answer"
                               : e.status === 401 ? unauthorizedText() : e.message);
    listMessage(listError, say);
  }
}

// --- geometry ---------------------------------------------------------------------------------
function rotation(q) {  // R(q) for q = [w, x, y, z] (Hamilton), rows
  const [w, x, y, z] = q;
  return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
          [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
          [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]];
}

function project(cam, R, t, X) {  // tracking/camera.py's pinhole with OpenCV's k1..k6, p1, p2; null behind the camera
  const xc = R[0][0] * X[0] + R[0][1] * X[1] + R[0][2] * X[2] + t[0];
  const yc = R[1][0] * X[0] + R[1][1] * X[1] + R[1][2] * X[2] + t[1];
  const zc = R[2][0] * X[0] + R[2][1] * X[1] + R[2][2] * X[2] + t[2];
  if (zc <= 1e-9) return null;
  const x = xc / zc, y = yc / zc, d = cam.dist_coeffs || [];
  const [k1 = 0, k2 = 0, p1 = 0, p2 = 0, k3 = 0, k4 = 0, k5 = 0, k6 = 0] = d;  // (k4..k6: the rational model)
  const r2 = x * x + y * y;
  const radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)));
  const xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x);
  const yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y;
  return [cam.fx * xd + cam.cx, cam.fy * yd + cam.cy];
}

function polyline(ctx, cam, R, t, a, b, n) {  // a segment sampled so lens distortion bends it
  ctx.beginPath();
  let pen = false;
  for (let i = 0; i <= n; i++) {
    const s = i / n;
    const p = project(cam, R, t, [a[0] + (b[0] - a[0]) * s, a[1] + (b[1] - a[1]) * s, a[2] + (b[2] - a[2]) * s]);
    if (!p) { pen = false; continue; }
    if (pen) ctx.lineTo(p[0], p[1]); else ctx.moveTo(p[0], p[1]);
    pen = true;
  }
  ctx.stroke();
}

function rotvecDeg(q) {  // full rotation vector (axis * angle), degrees
  let [w, x, y, z] = q;
  if (w < 0) { w = -w; x = -x; y = -y; z = -z; }
  const s = Math.hypot(x, y, z);
  const k = s < 1e-12 ? 2 : 2 * Math.atan2(s, w) / s;
  return [x * k * 180 / Math.PI, y * k * 180 / Math.PI, z * k * 180 / Math.PI];
}

// --- drawing ----------------------------------------------------------------------------------
function drawFrame(frame, msg, rttMs) {
  const c = $("overlay"), ctx = c.getContext("2d");
  if (c.width !== frame.width || c.height !== frame.height) { c.width = frame.width; c.height = frame.height; }
  ctx.drawImage(frame, 0, 0);
  if (msg.pose) {
    const R = rotation(msg.pose.q_wxyz), t = msg.pose.t, cam = state.camera;
    ctx.lineWidth = 2;
    ctx.strokeStyle = COLOURS[msg.status] || "#fff";
    for (const [a, b] of state.edges) polyline(ctx, cam, R, t, a, b, 8);
    if (state.bbox) {
      const [lo, hi] = state.bbox;
      const L = 0.3 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
      for (let k = 0; k < 3; k++) {
        const end = lo.slice(); end[k] += L;
        ctx.strokeStyle = AXIS_COLOURS[k];
        polyline(ctx, cam, R, t, lo, end, 1);
      }
    }
  }
  $("status").textContent = msg.status;
  $("latency").textContent = `${rttMs.toFixed(0)} ms round trip, ${msg.latency_ms.toFixed(0)} ms server`;
  state.count += 1;
  $("pose-count").textContent = String(state.count);
  $("last-pose").textContent = JSON.stringify({ frame: msg.frame, status: msg.status, pose: msg.pose,
                                                 width: frame.width, height: frame.height });
}

function record(msg) {
  let row = null;
  if (msg.pose) {
    const sd = msg.covariance ? msg.covariance.map((r, i) => Math.sqrt(Math.max(r[i], 0))) : [0, 0, 0, 0, 0, 0];
    row = { p: msg.pose.t, sp: sd.slice(0, 3), r: rotvecDeg(msg.pose.q_wxyz), sr: sd.slice(3).map((v) => v * 180 / Math.PI) };
  }
  state.history.push(row);
  if (state.history.length > HISTORY) state.history.shift();
  plot($("plot-position"), "p", "sp");
  plot($("plot-orientation"), "r", "sr");
}

function plot(canvas, key, sigmaKey) {  // one panel per axis, each with its own range
  const ctx = canvas.getContext("2d"), W = canvas.width, H = canvas.height, h = state.history, ph = H / 3;
  ctx.clearRect(0, 0, W, H);
  ctx.font = "10px sans-serif";
  for (let k = 0; k < 3; k++) {
    const top = k * ph;
    let lo = Infinity, hi = -Infinity;
    for (const row of h) if (row) {
      lo = Math.min(lo, row[key][k] - 3 * row[sigmaKey][k]);
      hi = Math.max(hi, row[key][k] + 3 * row[sigmaKey][k]);
    }
    ctx.strokeStyle = "#ddd";
    ctx.strokeRect(40.5, top + 2.5, W - 45, ph - 5);
    if (!isFinite(lo)) continue;
    if (hi - lo < 1e-9) { lo -= 1; hi += 1; }
    const pad = 0.05 * (hi - lo); lo -= pad; hi += pad;
    const X = (i) => 40 + (W - 45) * i / (HISTORY - 1), Y = (v) => top + ph - 3 - (ph - 6) * (v - lo) / (hi - lo);
    ctx.fillStyle = AXIS_BANDS[k];  // the 3-sigma band, then the value; a lost frame breaks both
    ctx.strokeStyle = AXIS_COLOURS[k];
    let run = [];
    const flush = () => {
      if (run.length) {
        ctx.beginPath();
        run.forEach(([i, r], j) => (j ? ctx.lineTo : ctx.moveTo).call(ctx, X(i), Y(r[key][k] + 3 * r[sigmaKey][k])));
        for (let j = run.length - 1; j >= 0; j--) ctx.lineTo(X(run[j][0]), Y(run[j][1][key][k] - 3 * run[j][1][sigmaKey][k]));
        ctx.fill();
        ctx.beginPath();
        run.forEach(([i, r], j) => (j ? ctx.lineTo : ctx.moveTo).call(ctx, X(i), Y(r[key][k])));
        ctx.stroke();
      }
      run = [];
    };
    h.forEach((r, i) => { if (r) run.push([i, r]); else flush(); });
    flush();
    ctx.fillStyle = "#333";
    ctx.fillText(hi.toFixed(1), 2, top + 12);
    ctx.fillText(lo.toFixed(1), 2, top + ph - 4);
    ctx.fillStyle = AXIS_COLOURS[k];
    ctx.fillText("xyz"[k], 30, top + ph / 2 + 3);
  }
}

// --- streaming --------------------------------------------------------------------------------
const CAMERA_FORM = '{"width": 640, "height": 480, "fx": …, "fy": …, "cx": …, "cy": …, "dist_coeffs": [k1, k2, p1, p2, k3]}';

function pastedCamera() {  // the pasted calibration, checked before anything starts; null: none
  const text = $("camera").value.trim();
  if (!text) return null;
  let cam;
  try { cam = JSON.parse(text); } catch (e) { throw new Error(`camera: not JSON (${e.message}); paste the camera file, ${CAMERA_FORM}`); }
  if (!cam || typeof cam !== "object" || Array.isArray(cam)) throw new Error(`camera: a JSON object is expected, ${CAMERA_FORM}`);
  const bad = ["fx", "fy", "cx", "cy"].filter((k) => typeof cam[k] !== "number" || !isFinite(cam[k]));
  if (bad.length) throw new Error(`camera: ${bad.join(", ")} missing or not a number (pixels), ${CAMERA_FORM}`);
  const size = ["width", "height"].filter((k) => cam[k] != null);
  if (size.length === 1 || size.some((k) => !Number.isInteger(cam[k]) || cam[k] <= 0)) {
    throw new Error("camera: width and height must be given together, as whole numbers of pixels (or both left out)");
  }
  const d = cam.dist_coeffs;
  if (d != null && (!Array.isArray(d) || ![0, 4, 5, 8].includes(d.length) || d.some((x) => typeof x !== "number"))) {
    throw new Error("camera: dist_coeffs must be 4, 5 or 8 numbers in OpenCV's order (k1, k2, p1, p2[, k3[, k4, k5, k6]])");
  }
  return cam;
}

function cameraFor(cam, w, h) {  // the camera of a w×h video: the pasted one, scaled to it, or a guess
  if (!cam) {
    const f = 0.5 * w / Math.tan(30 * Math.PI / 180);
    return { fx: f, fy: f, cx: w / 2, cy: h / 2, width: w, height: h, guessed: true };  // (the service learns no views from a guess)
  }
  const cw = cam.width || w, ch = cam.height || h;
  if (cw === w && ch === h) return { ...cam, width: w, height: h };
  if (Math.abs(w * ch - h * cw) > 0.01 * w * ch) {  // a crop or another camera: no scaling makes it fit
    throw new Error(`the video is ${w}×${h} but the pasted camera is ${cw}×${ch} (another aspect ratio): ` +
                    `paste this camera's calibration at ${w}×${h}, or empty the camera field to guess one`);
  }
  const sx = w / cw, sy = h / ch;  // the same camera at another resolution
  return { ...cam, fx: cam.fx * sx, cx: cam.cx * sx, fy: cam.fy * sy, cy: cam.cy * sy, width: w, height: h, scaled: true };
}

function stop(reason) {  // ends the current run (it ends quietly: its own errors are not shown)
  state.running = false;
  if (state.ws) { try { state.ws.close(); } catch (e) { /* already closed */ } }
  state.ws = null;
  const v = $("video");
  if (v.srcObject) { v.srcObject.getTracks().forEach((t) => t.stop()); v.srcObject = null; }
  v.pause();
  $("stop").disabled = true;
  $("status").textContent = "stopped";
  if (reason) message(reason);
}

function answersTheFrame(msg) {  // lock-step: the one frame in flight is the one answered
  if (msg.type === "pose") return true;
  return msg.type === "error" && ("frame" in msg || REFUSED_FRAME.has(msg.error && msg.error.code));
}

const CLOSE_CODES = { 1001: "the server is going away", 1006: "connection lost: the server stopped or the network failed",
                      1008: "refused", 1011: "server error", 1012: "the server is restarting", 1013: "the server is busy" };

function errorText(msg) { return msg.error ? msg.error.code + ": " + msg.error.message : "unexpected " + JSON.stringify(msg).slice(0, 80); }

function answerError(msg) {  // an answer that is not the one awaited, as an Error (with the service's code)
  if (msg.type !== "error" || !msg.error) return new Error(errorText(msg));
  const e = apiError(msg.error);
  if (msg.error.code === "unauthorized") e.message = "WebSocket " + unauthorizedText();
  return e;
}

const GONE = new Set([1001, 1006, 1011, 1012]);  // closes after which the server may come back

function channel(ws) {  // the socket's messages in order, and its end whenever it comes: handlers
  // set only while awaiting missed a close that came in between (a server restarting while the
  // frame was being encoded), and the page then waited for ever, still saying "tracking"
  const queue = [], waiting = [];
  let opened = false, end = null, last = null;
  const finish = (err) => { if (!end) { end = err; for (const w of waiting.splice(0)) w.reject(err); } };
  const deliver = (msg) => { const w = waiting.shift(); if (w) w.resolve(msg); else queue.push(msg); };
  ws.onopen = () => { opened = true; deliver({ type: "open" }); };
  ws.onmessage = (e) => {
    try { last = JSON.parse(e.data); } catch (x) { last = { type: "error", error: { code: "bad_answer", message: "not JSON" } }; }
    deliver(last);
  };
  ws.onclose = (e) => {
    if (!opened) {  // (the service opens a browser's socket to say why it refuses it: this is not the service's word)
      finish(new Error(`cannot open the WebSocket (${e.code}${e.reason ? " " + e.reason : ""}): the server is not ` +
                       "reachable at this address, or a proxy in front of it refused the connection"));
    } else {  // (an error just before the close says why: idle_timeout, ...)
      const why = e.reason || CLOSE_CODES[e.code] || "";
      const said = last && last.type === "error" && !("frame" in last) && !why.startsWith(last.error.code + ":")
        ? "; " + errorText(last) : "";
      finish(new Error(`connection closed (${e.code}${why ? " " + why : ""})${said}` +
                       (GONE.has(e.code) ? "; start again when the server is back" : "")));
    }
  };
  return { next: () => (queue.length ? Promise.resolve(queue.shift()) : end ? Promise.reject(end)
                        : new Promise((resolve, reject) => waiting.push({ resolve, reject }))) };
}

async function start(id, source) {  // id: this run; a stop or a newer run makes it end quietly
  const current = () => state.running && state.run === id;
  if (token() !== listedToken) loadObjects();  // (a token typed, its list not asked for yet)
  const pasted = pastedCamera();
  for (let p = null; p !== listLoad;) await (p = listLoad);  // (the list still loading: the token typed and webcam clicked at once)
  if (!current()) return;
  const name = $("object").value;
  if (!name) throw new Error(listError || "pick an object");
  const v = $("video");
  await source();
  if (!current()) return;
  await videoReady(v);
  if (!current()) return;
  const w = v.videoWidth, h = v.videoHeight;
  if (!w || !h) throw new Error("this file has no picture (audio only?)");
  await v.play();
  const mesh = await getJSON(`v1/objects/${encodeURIComponent(name)}/mesh`);
  const camera = cameraFor(pasted, w, h);
  if (!current()) return;  // (a newer run's wireframe, camera and count are not touched)
  state.edges = mesh.edges; state.bbox = mesh.bbox; state.camera = camera;
  state.count = 0; state.history = [];
  $("drop").classList.add("hidden");
  message(camera.guessed ? "camera guessed (60° field of view): paste your calibration for accurate poses"
          : camera.scaled ? `the pasted ${pasted.width}×${pasted.height} camera is scaled to the video's ${w}×${h}` : "");
  const url = api(`v1/objects/${encodeURIComponent(name)}/track`);
  url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
  if (token()) url.search = "?token=" + encodeURIComponent(token());
  const ws = new WebSocket(url.href);
  state.ws = ws;
  const answers = channel(ws);
  try {
    await answers.next();  // open
    if (!current()) return;
    const { scaled, ...sent } = state.camera;
    ws.send(JSON.stringify({ ...sent, ack: true }));
    const ready = await answers.next();
    if (!current()) return;
    if (ready.type !== "ready") throw answerError(ready);
    const grab = document.createElement("canvas");
    grab.width = w; grab.height = h;
    const max = parseInt($("max-frames").value, 10);
    state.t0 = performance.now();
    let last = -1;
    while (current() && !(max > 0 && state.count >= max)) {
      grab.getContext("2d").drawImage(v, 0, 0, w, h);
      const frame = document.createElement("canvas");  // keep the sent frame: the pose is drawn on it
      frame.width = w; frame.height = h;
      frame.getContext("2d").drawImage(grab, 0, 0);
      const blob = await new Promise((res) => grab.toBlob(res, "image/jpeg", 0.9));
      if (!current()) return;
      if (!blob) throw new Error("the browser could not encode the frame as JPEG");
      let t = (performance.now() - state.t0) / 1000;
      if (t <= last) t = last + 1e-3;
      last = t;
      const sent = performance.now();
      ws.send(JSON.stringify({ type: "frame", time_s: t }));
      ws.send(blob);
      let msg = await answers.next();
      while (current() && !answersTheFrame(msg)) {  // (say it, and wait for the frame's own answer)
        if (msg.type === "error") message(errorText(msg));
        msg = await answers.next();
      }
      if (!current()) return;
      if (msg.type === "error") { message(errorText(msg)); continue; }
      drawFrame(frame, msg, performance.now() - sent);
      record(msg);
      if (v.ended) break;
    }
    if (current()) stop(state.count ? "" : "no pose received");
  } finally {
    if (state.ws !== ws) ws.close();  // (a stale run's socket: stop() closed only the current one)
  }
}

function videoReady(v) {  // the first picture decoded; a video the browser cannot play says so
  return new Promise((resolve, reject) => {
    if (v.readyState >= 2) { resolve(); return; }
    const done = (ok) => {
      v.removeEventListener("loadeddata", loaded); v.removeEventListener("error", failed);
      if (ok) resolve(); else reject(new Error(videoError(v)));
    };
    const loaded = () => done(true), failed = () => done(false);
    v.addEventListener("loadeddata", loaded);
    v.addEventListener("error", failed);
    if (v.error) done(false);
  });
}

function videoError(v) {
  const e = v.error, kinds = { 1: "aborted", 2: "network error", 3: "it cannot be decoded", 4: "format or codec not supported" };
  const what = e ? (kinds[e.code] || "error " + e.code) + (e.message ? ": " + e.message : "") : "unknown error";
  return `the browser cannot play this video (${what}); WebM (VP8, VP9) plays in every browser`;
}

function clearRun() {  // the previous run's count, answer, picture and plots, not shown as this one's
  state.count = 0; state.history = [];
  $("pose-count").textContent = "0";
  $("latency").textContent = "–";
  $("last-pose").textContent = "null";
  const c = $("overlay");
  c.getContext("2d").clearRect(0, 0, c.width, c.height);
  plot($("plot-position"), "p", "sp");
  plot($("plot-orientation"), "r", "sr");
}

const STALE_LIST = new Set(["unknown_object", "model_unavailable"]);  // the object list is out of date

function run(source, label) {  // source(current): sets the video's source (awaited)
  stop();
  clearRun();
  const id = ++state.run;
  state.running = true;
  const current = () => state.running && state.run === id;
  $("status").textContent = "starting";
  $("source").textContent = label;
  $("stop").disabled = false;
  start(id, () => source(current))
    .catch((e) => {
      if (!current()) return;
      stop(e.message);
      if (STALE_LIST.has(e.code)) loadObjects(false);  // (deleted or broken since listed; the message stays)
    })
    .finally(() => { state.done = id; });  // (the id of the latest run that has ended)
}

let fileURL = null;

$("webcam").onclick = () => run(async (current) => {
  const media = navigator.mediaDevices;
  if (!media || !media.getUserMedia) {
    throw new Error("webcam: the browser offers it only to secure pages (https, or http on localhost); open the viewer so, or drop a video file");
  }
  let stream;
  try { stream = await media.getUserMedia({ video: { width: 640, height: 480 }, audio: false }); }
  catch (e) { throw new Error(cameraError(e)); }
  if (!current()) { stream.getTracks().forEach((t) => t.stop()); return; }  // (a newer run took over: camera off)
  const v = $("video");
  v.removeAttribute("src");  // (v.src = "" queues an error event: "empty src")
  v.srcObject = stream;
}, "webcam");

function cameraError(e) {  // getUserMedia's refusal, with what to do next
  const next = {
    NotAllowedError: "the camera is not allowed for this page: allow it (the camera icon in the address bar) and click webcam again, or choose a video file",
    NotFoundError: "no camera found: connect one and click webcam again, or choose a video file",
    OverconstrainedError: "no camera found that gives 640×480: choose a video file",
    NotReadableError: "the camera is in use by another program: close it and click webcam again, or choose a video file",
  }[e && e.name];
  return "webcam: " + (next || `${e && e.message ? e.message : e}; choose a video file instead`);
}

function playFile(file) {
  run(async () => {
    const v = $("video");
    v.srcObject = null;
    if (fileURL) URL.revokeObjectURL(fileURL);
    v.src = fileURL = URL.createObjectURL(file);
    v.loop = false;
  }, file.name);
}

$("file").onchange = (e) => {  // (emptied: choosing the same file again starts it again)
  const file = e.target.files[0];
  e.target.value = "";
  if (file) playFile(file);
};
const view = $("view");
view.addEventListener("dragover", (e) => e.preventDefault());
view.addEventListener("drop", (e) => { e.preventDefault(); if (e.dataTransfer.files[0]) playFile(e.dataTransfer.files[0]); });
$("stop").onclick = () => stop("stopped by the user");
$("refresh").onclick = () => loadObjects();
$("token").addEventListener("change", () => loadObjects());
loadObjects();
