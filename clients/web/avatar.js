// articast browser avatar: subscribes over WebSocket, animates the face mesh linearly from the
// streamed articulatory parameters (x = mean + sum_k alpha_k basis_k, the dense modes when the
// server offers them), draws it with three.js (served by the articast server itself:
// clients/web/vendor, remade by tools/fetch_web_vendor.py), shows the parameters, pose, latency
// and fps, and reconnects by itself. No network but the articast server; no build step.
//
// What it draws: the server's bound head scan (hello.scan_url, `serve --scan`), else the
// speaker's own textured face (hello.delegate_url, delegate.js: its own eyes, whose lids close
// on a blink), else the model's face (dense when served) completed into a closed head with
// eyes and brows (eyes.js). Until the delegate or the scan has loaded, the generic head.
//
// Newest frame only: a message only replaces `latest`; one requestAnimationFrame loop draws
// it (and updates the panel) at most once per display frame. However slow the machine, nothing
// queues in the page: frames that arrive between two display frames are counted, not drawn.
// Latency shown = capture -> on screen (wall clock; the server's `t_capture`).
import * as THREE from "three";
import { LinearFace } from "./face.js";
import { loadScan } from "./scan.js";
import { loadDelegate } from "./delegate.js";
import { Head } from "./eyes.js";
import { authHeaders, chooseSession, params, refusal, socketUrl, withToken, noteLatency, noteDraw } from "./connect.js";

const state = (window.articast = {
  frames: 0, rendered: 0, connects: 0, connected: false, hello: null, alpha: null, status: "",
  error: "", final: "", mesh: "", lastSeq: -1, fps: 0, latencyMs: null, delegate: "",
  latencies: [], // capture -> on screen, ms, one per drawn frame (the last 20 000)
  drawn: "", // what the last drawn frame showed: "scan", "delegate" or "generic"
});
const $ = (id) => document.getElementById(id);
const SKIN = [0.86, 0.66, 0.56];

// ----------------------------------------------------------------------------- scene
// The colours are used as given (no colour management): the shading is the earlier page's,
// ambient 0.35 + diffuse 0.75 from the upper left (three.js divides a light by pi).
THREE.ColorManagement.enabled = false;
let renderer = null;
try {
  renderer = new THREE.WebGLRenderer({ canvas: $("canvas"), antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
  renderer.setClearColor(new THREE.Color(0.19, 0.2, 0.23), 1);
} catch (e) { renderer = null; }
const scene = new THREE.Scene();
scene.add(new THREE.AmbientLight(0xffffff, 0.35 * Math.PI));
const sun = new THREE.DirectionalLight(0xffffff, 0.75 * Math.PI);
sun.position.set(-0.3, 0.4, 1.0); // towards the light, from the origin (its target)
scene.add(sun);
// the head frame: x = speaker's left (the viewer's right), y up, z towards the viewer, mm
const camera = new THREE.PerspectiveCamera(0.5 * 180 / Math.PI, 1, 50, 2000);
const head = new THREE.Group(); // turned by the head pose about the face's centre (origin)
const face = new THREE.Group(); // the head frame, shifted so that its centre is the origin
head.add(face); scene.add(head);
const headQ = new THREE.Quaternion(), firstQ = new THREE.Quaternion(), axis = new THREE.Vector3();
function axisAngle(r, q) { // a rotation vector (axis * angle, radians) as a quaternion
  const th = Math.hypot(r[0], r[1], r[2]);
  return th < 1e-12 ? q.identity() : q.setFromAxisAngle(axis.set(r[0] / th, r[1] / th, r[2] / th), th);
}

let sparse = null, dense = null, wire = null, centre = [0, 0, 0], haveFirst = false, pose = null,
    scan = null, delegate = null, generic = null;

function show(objects) { // the face group holds exactly these
  for (const o of [...face.children]) if (!objects.includes(o)) face.remove(o);
  for (const o of objects) if (o && o.parent !== face) face.add(o);
}
function render() {
  if (!renderer || !sparse || !state.alpha) return;
  const el = renderer.domElement, w = el.clientWidth || el.width, h = el.clientHeight || el.height;
  const pr = renderer.getPixelRatio();
  if (el.width !== Math.floor(w * pr) || el.height !== Math.floor(h * pr)) renderer.setSize(w, h, false);
  if (camera.aspect !== w / h) { camera.aspect = w / h; camera.updateProjectionMatrix(); }
  if ($("headpose").checked && pose && pose.head) {
    // the server's head pose relative to the speaker's neutral (R_n^T R, in the head frame)
    axisAngle(pose.head.rotation, head.quaternion);
  } else if ($("headpose").checked && pose && haveFirst) {
    // an older server: relative to the first frame seen here, R0^T R
    head.quaternion.copy(firstQ).invert().multiply(axisAngle(pose.rotation, headQ));
  } else head.quaternion.identity();
  const useScan = scan && $("scan").checked; // a whole head: its own centre, further away
  const c = useScan ? scan.centre : centre;
  face.position.set(-c[0], -c[1], -c[2]);
  camera.position.set(0, 0, useScan ? scan.distance : 380);
  const useDense = dense && $("dense").checked;
  const shown = [];
  if (useScan) { scan.update(state.alpha); shown.push(scan.object); state.drawn = "scan"; }
  else if (delegate && $("delegate").checked) {
    delegate.update(state.alpha, state.eyes, state.brows); shown.push(delegate.object);
    state.drawn = "delegate";
  } else {
    const mesh = useDense ? dense : sparse;
    mesh.update(state.alpha); shown.push(mesh.object);
    if (generic) { generic.update(state.eyes, state.brows); shown.push(generic.object); }
    state.drawn = "generic";
  }
  if ($("wire").checked) { if (shown[0] !== sparse.object) sparse.update(state.alpha); shown.push(wire); }
  show(shown);
  renderer.render(scene, camera);
}

// where vertices of the drawn delegate are on the page (CSS px from the canvas's top left), as
// last drawn: for the tests and the pictures (tests/test_delegate_eyes.py finds the eyes so)
state.screenPoints = (ids) => {
  if (!delegate || state.drawn !== "delegate") return null;
  const el = renderer.domElement, r = el.getBoundingClientRect(), p = delegate.position.array;
  delegate.object.updateWorldMatrix(true, false);
  return ids.map((i) => {
    const v = new THREE.Vector3(p[3 * i], p[3 * i + 1], p[3 * i + 2]).applyMatrix4(delegate.object.matrixWorld).project(camera);
    return [r.left + (v.x + 1) / 2 * r.width, r.top + (1 - v.y) / 2 * r.height];
  });
};

// ----------------------------------------------------------------------------- panel
const bars = [];
function setupBars(names) {
  $("bars").innerHTML = "";
  bars.length = 0;
  for (const n of names) {
    const d = document.createElement("div"); d.className = "bar";
    d.innerHTML = `<span>${n}</span><div class="track"><div class="zero"></div><div class="fill"></div></div><b>0</b>`;
    $("bars").appendChild(d); bars.push(d);
  }
}
function showBars(alpha) {
  alpha.forEach((a, i) => {
    const v = Math.max(-3, Math.min(3, a)) / 6, f = bars[i].querySelector(".fill");
    f.style.left = `${50 + Math.min(0, v) * 100}%`; f.style.width = `${Math.abs(v) * 100}%`;
    bars[i].querySelector("b").textContent = a.toFixed(2);
  });
}
function status(text, bad) { const s = $("status"); s.textContent = text; s.className = bad ? "bad" : "good"; state.status = text; }

// ----------------------------------------------------------------------------- connection
let delay = 250, final = "";
function stop(text) { // a refusal or an end: said once, never retried
  final = text; state.final = text; status(text, true); overlay(text);
}
// the server's tracking preview (opt-in per session): newest JPEG only, at most 5 per second
let previewUrl = null, previewTimer = null;
function startPreview(url) {
  previewUrl = url; $("previewbox").hidden = !url; state.previews = state.previews || 0;
  if (!url || previewTimer) return;
  const img = $("preview");
  const next = () => {
    if (!previewUrl) { previewTimer = null; return; }
    const t0 = performance.now();
    img.onload = () => { state.previews++; previewTimer = setTimeout(next, Math.max(0, 200 - (performance.now() - t0))); };
    img.onerror = () => { previewTimer = setTimeout(next, 1000); };
    img.src = withToken(`${previewUrl}?n=${state.previews}`);
  };
  previewTimer = setTimeout(next, 0);
}
async function onHello(h) {
  state.hello = h; haveFirst = false;
  startPreview(h.preview_url || null);
  $("session").textContent = h.session; setupBars(h.param_names);
  const g = h.geometry; if (!g) { status("this session has no face model", true); return; }
  const k = h.param_names.length;
  for (const old of [sparse, dense, delegate, scan, generic]) if (old && old.dispose) old.dispose();
  sparse = new LinearFace(g.mean, g.basis, g.triangles, k, null, SKIN);
  wire = sparse.wire([0.2, 0.9, 0.6]);
  centre = [0, 0, 0];
  for (let i = 0; i < g.mean.length; i += 3) for (let d = 0; d < 3; d++) centre[d] += g.mean[i + d] * 3 / g.mean.length;
  generic = new Head(g);
  state.mesh = `sparse ${sparse.m} points`; $("mesh").textContent = state.mesh;
  dense = null; delegate = null; scan = null; state.delegate = "";
  if (!renderer) return;
  loadDelegate(h.delegate_url, authHeaders).then((d) => { // the speaker's own face
    if (d && state.hello === h) { delegate = d; state.delegate = `textured, ${d.m} points`; }
  }).catch((e) => console.warn("delegate unavailable", e));
  if (h.dense_url) {
    try {
      const d = await (await fetch(h.dense_url, { headers: authHeaders })).json();
      dense = new LinearFace(d.mean, d.basis, d.triangles, k, d.labels, SKIN);
      state.mesh = `dense ${dense.m} points (sparse ${sparse.m})`; $("mesh").textContent = state.mesh;
    } catch (e) { console.warn("dense mesh unavailable", e); }
  }
  if (h.scan_url) { // only a server with --scan names one
    try {
      scan = await loadScan(h.scan_url, k, authHeaders);
      state.mesh = `scan ${scan.m} points (sparse ${sparse.m})`; $("mesh").textContent = state.mesh;
    } catch (e) { console.warn("head scan unavailable", e); state.scanError = String(e); }
  }
}
let latest = null, rateMark = { t: 0, frames: 0 };
function onFrame(f) { // cheap: the drawing happens in draw(), once per display frame
  latest = f; state.frames++; state.lastSeq = f.seq;
}
function draw(now) {
  requestAnimationFrame(draw);
  if (now - rateMark.t >= 1000) { // received frames per second, over the last second
    if (rateMark.t) state.fps = (state.frames - rateMark.frames) * 1000 / (now - rateMark.t);
    rateMark = { t: now, frames: state.frames };
    $("fps").textContent = state.connected ? state.fps.toFixed(1) : "–";
  }
  const f = latest;
  if (!f || !state.hello) return;
  latest = null;
  const t0 = performance.now();
  const names = state.hello.param_names, a = f.values.articulatory || {};
  state.alpha = names.map((n) => a[n] || 0);
  state.eyes = f.eyes || null; state.brows = f.brows || null;
  if (f.values.pose) {
    pose = f.values.pose;
    if (!haveFirst && f.quality.ok) { axisAngle(pose.rotation, firstQ); haveFirst = true; }
  }
  showBars(state.alpha);
  $("quality").textContent = f.quality.ok ? `ok, ${f.quality.evals} evals` : `not ok: ${f.quality.reason}`;
  $("quality").className = f.quality.ok ? "good" : "bad";
  if (pose) $("pose").textContent = pose.translation.map((v) => v.toFixed(0)).join(", ") + " mm";
  render();
  noteDraw(state, t0);
  state.rendered++;
  $("latency").textContent = `${noteLatency(state, f) | 0} ms`;
  overlay("");
}
function overlay(text) { // what the view says while there is no face to show
  const o = $("overlay");
  if (o.textContent !== text) o.textContent = text;
  o.hidden = !text;
}
async function connect() {
  let session;
  try { session = await chooseSession(); } catch (e) {
    const why = await refusal();
    return why ? stop(why) : retry(`no session yet (${e.message})`);
  }
  const ws = new WebSocket(socketUrl());
  let opened = false;
  ws.onopen = () => {
    opened = true;
    state.connected = true; state.connects++; delay = 250; status(`connected to ${session}`);
    if (!state.rendered) overlay(`waiting for the first frame of ${session}…`);
    ws.send(JSON.stringify({ type: "subscribe", session, streams: ["articulatory", "pose"],
                             rate: params.get("rate") ? Number(params.get("rate")) : null }));
  };
  ws.onmessage = async (ev) => {
    const m = JSON.parse(ev.data);
    if (m.type === "hello") await onHello(m);
    else if (m.type === "frame" && state.hello) onFrame(m);
    else if (m.type === "status") {
      const text = `${m.session}: ${m.state} ${m.detail || ""}`;
      status(text, m.state !== "running");
      if (!state.rendered || m.state !== "running") overlay(m.state === "running" ? "" : text);
      if (["ended", "failed", "stopped"].includes(m.state)) { stop(text); ws.close(); }
    }
    else if (m.type === "error") {
      state.error = m.reason; status(`error: ${m.reason}`, true);
      if (m.code === "unknown_session") { stop(`no session "${session}" on this server`); ws.close(); }
    }
  };
  ws.onclose = async () => {
    state.connected = false;
    if (final) return;
    const why = opened ? "" : await refusal(); // a refused handshake: the browser hides the 401
    if (why) stop(why); else retry("disconnected");
  };
}
function retry(why) {
  status(`${why}: reconnecting in ${(delay / 1000).toFixed(1)} s`, true);
  overlay(`${why}: reconnecting in ${(delay / 1000).toFixed(1)} s…`);
  setTimeout(connect, delay); delay = Math.min(delay * 2, 5000);
}
if (!renderer) status("WebGL is not available in this browser", true);
overlay("connecting to the articast server…");
requestAnimationFrame(draw);
connect();
