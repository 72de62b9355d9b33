// articast VRM avatar: any VRM (0.x or 1.0) driven live from a session's stream, drawn with
// three.js and @pixiv/three-vrm (served by the articast server itself: clients/web/vendor,
// remade by tools/fetch_web_vendor.py; no other network).
//
// Which VRM: ?vrm=URL (a file of this server), else the session speaker's own face
// (GET /api/sessions/NAME/vrm, made by the server as `articast export-vrm` does), or a file
// dropped on the page.
//
// What drives it, per frame (the newest only: messages replace `latest`, one
// requestAnimationFrame loop applies and draws it):
// * perfect sync (the VRM has the ARKit blendshape names as custom expressions): every ARKit
//   weight of the stream's `arkit` block (mouth, jaw, eyes, brows) on the expression of that
//   name; the look-at and blink presets stay at rest (the eyeLook*/eyeBlink* shapes do it);
// * otherwise the presets: aa ih ou ee oh from the articulation (the VRM vowels of
//   core/outputs/vowels.py, computed here from the session's model in hello), blinkLeft /
//   blinkRight from the eyes' closure, the look-at (yaw, pitch) from the gaze;
// * the head bone from pose.head (the head relative to the speaker's neutral).
// Eyes or brows the server says were not seen are left at rest, never set as open eyes.
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { VRMLoaderPlugin, VRMUtils } from "@pixiv/three-vrm";
import { authHeaders, chooseSession, params, refusal, socketUrl, noteLatency, noteDraw } from "./connect.js";

const ARKIT = ["eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft",
  "eyeSquintLeft", "eyeWideLeft", "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight",
  "eyeLookOutRight", "eyeLookUpRight", "eyeSquintRight", "eyeWideRight", "jawForward", "jawLeft",
  "jawRight", "jawOpen", "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight",
  "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight", "mouthDimpleLeft",
  "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight", "mouthRollLower", "mouthRollUpper",
  "mouthShrugLower", "mouthShrugUpper", "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft",
  "mouthLowerDownRight", "mouthUpperUpLeft", "mouthUpperUpRight", "browDownLeft", "browDownRight",
  "browInnerUp", "browOuterUpLeft", "browOuterUpRight", "cheekPuff", "cheekSquintLeft",
  "cheekSquintRight", "noseSneerLeft", "noseSneerRight", "tongueOut"];
const PRESETS = ["aa", "ih", "ou", "ee", "oh", "blinkLeft", "blinkRight", "lookUp", "lookDown",
  "lookLeft", "lookRight"];
const state = (window.articast = {
  frames: 0, rendered: 0, connects: 0, connected: false, hello: null, status: "", error: "",
  final: "", lastSeq: -1, fps: 0, latencyMs: null, latencies: [],
  vrm: "", mode: "", vrmError: "",
  applied: [], // what was applied, per drawn frame: {seq, expr: {name: weight}, morph: {...}}
});
const $ = (id) => document.getElementById(id);

// ----------------------------------------------------------------------------- VRM vowels
// core/outputs/vowels.py, ported: four linear measures of the model's feature points,
// calibrated by the training ranges, and the Gaussian membership of each vowel's prototype.
const FEATURES = [[[["2.1", 1, -1]], false], [[["2.2", 1, 1], ["2.3", 1, -1]], false],
  [[["8.3", 0, 1], ["8.4", 0, -1]], true], [[["8.1", 2, 0.5], ["8.2", 2, 0.5]], true]];
const PROTOTYPES = [[0.95, 0.80, 0.35, -0.95], [0.25, 0.35, 0.80, -0.50], [0.35, 0.55, -0.60, 0.65],
  [0.45, 0.50, 0.70, -0.60], [0.50, 0.70, -0.40, 0.30], [0.00, 0.20, 0.50, -0.15]];
const VOWELS = ["aa", "ih", "ou", "ee", "oh"], SIGMA = 0.15;
export function vowelMapper(hello) {
  const g = hello.geometry, st = hello.param_stats;
  if (!g || !st || !g.feature_points) return null;
  const fp = g.feature_points, k = hello.param_names.length, n = g.mean.length / 3;
  const feats = [];
  for (const [terms, signed] of FEATURES) {
    if (!terms.every(([p]) => p in fp)) return null;
    const grad = new Float64Array(k);
    for (let j = 0; j < k; j++)
      for (const [p, ax, c] of terms) grad[j] += c * g.basis[j * n * 3 + fp[p] * 3 + ax];
    let hi = 0, lo = 0;
    for (let j = 0; j < k; j++) {
      const a = grad[j] * st.min[j], b = grad[j] * st.max[j];
      hi += Math.max(0, a, b) ** 2; lo += Math.max(0, -Math.min(a, b)) ** 2;
    }
    hi = Math.sqrt(hi); lo = -Math.sqrt(lo);
    hi = hi < 1e-9 ? 1.0 : Math.max(hi, lo + 2.0);
    feats.push({ grad, lo, hi, signed });
  }
  return (alpha) => {
    const f = feats.map(({ grad, lo, hi, signed }) => {
      let m = 0; for (let j = 0; j < k; j++) m += grad[j] * alpha[j];
      if (!signed) return (m - lo) / (hi - lo);
      return m > 0 ? m / hi : m / (lo < 0 ? -lo : 1.0);
    });
    const d2 = PROTOTYPES.map((p) => p.reduce((s, v, i) => s + (f[i] - v) ** 2, 0));
    const lo = Math.min(...d2), e = d2.map((d) => Math.exp(-(d - lo) / (2 * SIGMA * SIGMA)));
    const sum = e.reduce((a, b) => a + b, 0);
    return Object.fromEntries(VOWELS.map((v, i) => [v, e[i] / sum]));
  };
}

// ----------------------------------------------------------------------------- scene
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(window.devicePixelRatio || 1);
renderer.outputColorSpace = THREE.SRGBColorSpace;
$("view").prepend(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x30343a);
const camera = new THREE.PerspectiveCamera(28, 1, 0.05, 20);
scene.add(new THREE.AmbientLight(0xffffff, 1.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
sun.position.set(-0.5, 1.0, 2.0);
scene.add(sun);
const loader = new GLTFLoader();
loader.register((parser) => new VRMLoaderPlugin(parser));
let vrm = null, perfectSync = false, faceMesh = null, vowels = null, lastUpdate = performance.now();

function frameHead() { // the camera in front of the face, looking at the eyes
  const head = vrm.humanoid.getNormalizedBoneNode("head");
  vrm.scene.updateMatrixWorld(true);
  const eyes = head.getWorldPosition(new THREE.Vector3());
  if (vrm.lookAt) eyes.add(vrm.lookAt.offsetFromHeadBone.clone());
  camera.position.set(eyes.x, eyes.y, eyes.z + 0.62);
  camera.lookAt(eyes.x, eyes.y - 0.02, eyes.z);
}
async function loadVrm(url, label) {
  state.vrm = ""; state.vrmError = ""; $("avatar").textContent = `loading ${label}…`;
  let gltf;
  try { gltf = await loader.loadAsync(url); } catch (e) {
    state.vrmError = `${label}: ${e.message || e}`; $("avatar").textContent = state.vrmError;
    $("avatar").className = "bad"; return;
  }
  const v = gltf.userData.vrm;
  if (!v) { state.vrmError = `${label}: not a VRM (no VRMC_vrm / VRM extension)`; $("avatar").textContent = state.vrmError; return; }
  VRMUtils.rotateVRM0(v); // a VRM 0.x faces -z: turn it to face the viewer as 1.0 does
  if (vrm) { scene.remove(vrm.scene); VRMUtils.deepDispose(vrm.scene); }
  vrm = v; scene.add(vrm.scene);
  const em = vrm.expressionManager;
  const custom = em ? Object.keys(em.customExpressionMap) : [];
  perfectSync = ["jawOpen", "eyeBlinkLeft", "eyeBlinkRight"].every((n) => custom.includes(n));
  faceMesh = null;
  vrm.scene.traverse((o) => { if (!faceMesh && o.morphTargetDictionary && o.morphTargetInfluences) faceMesh = o; });
  if (vrm.lookAt) vrm.lookAt.autoUpdate = false;
  frameHead();
  const name = (vrm.meta && (vrm.meta.name || vrm.meta.title)) || label;
  state.vrm = `${name}: ${custom.length} custom, ${em ? Object.keys(em.presetExpressionMap).length : 0} preset expressions`;
  state.mode = perfectSync ? "perfect sync (ARKit expressions)" : "VRM presets (vowels, blink, look-at)";
  $("avatar").textContent = state.vrm; $("avatar").className = ""; $("mode").textContent = state.mode;
}

// ----------------------------------------------------------------------------- applying
const clamp01 = (x) => Math.min(1, Math.max(0, x));
function apply(f) {
  const em = vrm.expressionManager, set = {};
  const put = (n, w) => { if (em.getExpression(n)) { em.setValue(n, w); set[n] = em.getValue(n); } };
  const names = state.hello.param_names, a = f.values.articulatory || {};
  const alpha = names.map((n) => a[n] || 0);
  const eyes = f.eyes && f.eyes.ok ? f.eyes : null;
  if (perfectSync && f.values.arkit) {
    const w = f.values.arkit;
    for (const n of ARKIT) if (n in w) put(n, w[n]); // absent (unseen eyes): left as they were
    for (const n of PRESETS) put(n, 0);
    if (vrm.lookAt) { vrm.lookAt.yaw = 0; vrm.lookAt.pitch = 0; }
  } else {
    const vw = vowels ? vowels(alpha) : null;
    for (const v of VOWELS) put(v, vw ? vw[v] : 0);
    if (eyes) {
      put("blinkLeft", clamp01(eyes.closure_left)); put("blinkRight", clamp01(eyes.closure_right));
      if (vrm.lookAt) { vrm.lookAt.yaw = eyes.gaze_yaw_deg || 0; vrm.lookAt.pitch = eyes.gaze_pitch_deg || 0; }
    }
  }
  const head = vrm.humanoid.getNormalizedBoneNode("head");
  const p = f.values.pose && f.values.pose.head;
  if (head) {
    if ($("headpose").checked && p && f.quality.ok) {
      const r = new THREE.Vector3(...p.rotation), th = r.length();
      head.quaternion.setFromAxisAngle(th > 1e-12 ? r.divideScalar(th) : new THREE.Vector3(0, 1, 0), th);
    } else if (!$("headpose").checked) head.quaternion.identity();
  }
  const t = performance.now();
  vrm.update(Math.min(0.1, (t - lastUpdate) / 1000)); lastUpdate = t;
  const morph = {};
  if (faceMesh) for (const [n, i] of Object.entries(faceMesh.morphTargetDictionary)) morph[n] = faceMesh.morphTargetInfluences[i];
  const expr = {};
  for (const n of Object.keys(set)) expr[n] = em.getValue(n);
  if (vrm.lookAt) for (const n of ["lookUp", "lookDown", "lookLeft", "lookRight"]) if (em.getExpression(n)) expr[n] = em.getValue(n);
  state.applied.push({ seq: f.seq, expr, morph });
  if (state.applied.length > 2000) state.applied.splice(0, 1000);
}

// ----------------------------------------------------------------------------- connection
function status(text, bad) { const s = $("status"); s.textContent = text; s.className = bad ? "bad" : "good"; state.status = text; }
function overlay(text) { const o = $("overlay"); if (o.textContent !== text) o.textContent = text; o.hidden = !text; }
let delay = 250, final = "", streams = ["articulatory", "pose", "arkit"], session = null, vrmFor = null;
function stop(text) { final = text; state.final = text; status(text, true); overlay(text); }
function sameOrigin(url) { // a VRM named in the URL: this server's files only
  try { return new URL(url, location.href).origin === location.origin; } catch (e) { return false; }
}
async function onHello(h) {
  state.hello = h; $("session").textContent = h.session;
  vowels = vowelMapper(h);
  if (vrmFor === h.session) return; // a reconnect or restart: keep the avatar
  vrmFor = h.session;
  const named = params.get("vrm");
  if (named) {
    if (!sameOrigin(named)) { state.vrmError = "?vrm= must name a file of this server"; $("avatar").textContent = state.vrmError; return; }
    const r = await fetch(named, { headers: authHeaders });
    if (!r.ok) { state.vrmError = `${named}: HTTP ${r.status}`; $("avatar").textContent = state.vrmError; return; }
    await loadVrm(URL.createObjectURL(await r.blob()), named);
  } else if (h.delegate_url) {
    const r = await fetch(`/api/sessions/${encodeURIComponent(h.session)}/vrm`, { headers: authHeaders });
    if (r.ok) await loadVrm(URL.createObjectURL(await r.blob()), `${h.session}'s own face`);
    else { state.vrmError = `the speaker's VRM: HTTP ${r.status}`; $("avatar").textContent = `${state.vrmError}: drop a .vrm file`; }
  } else $("avatar").textContent = "this session has no face of its own: drop a .vrm file, or give ?vrm=URL";
}
let latest = null, rateMark = { t: 0, frames: 0 };
function draw(now) {
  requestAnimationFrame(draw);
  if (now - rateMark.t >= 1000) {
    if (rateMark.t) state.fps = (state.frames - rateMark.frames) * 1000 / (now - rateMark.t);
    rateMark = { t: now, frames: state.frames };
    $("fps").textContent = state.connected ? state.fps.toFixed(1) : "–";
  }
  const el = renderer.domElement, w = el.clientWidth, h = el.clientHeight;
  if (w && h && (el.width !== Math.floor(w * renderer.getPixelRatio()) || el.height !== Math.floor(h * renderer.getPixelRatio()))) {
    renderer.setSize(w, h, false); camera.aspect = w / h; camera.updateProjectionMatrix();
  }
  const f = latest;
  if (!f || !state.hello || !vrm) { if (vrm) renderer.render(scene, camera); return; }
  latest = null;
  const t0 = performance.now();
  $("quality").textContent = f.quality.ok ? "ok" : `not ok: ${f.quality.reason}`;
  $("quality").className = f.quality.ok ? "good" : "bad";
  apply(f);
  renderer.render(scene, camera);
  noteDraw(state, t0);
  state.rendered++;
  $("latency").textContent = `${noteLatency(state, f) | 0} ms`;
  overlay("");
}
async function connect() {
  try { session = await chooseSession(); } catch (e) {
    const why = await refusal();
    return why ? stop(why) : retry(`no session yet (${e.message})`);
  }
  const ws = new WebSocket(socketUrl());
  let opened = false;
  const subscribe = () => ws.send(JSON.stringify({ type: "subscribe", session, streams,
    rate: params.get("rate") ? Number(params.get("rate")) : null }));
  ws.onopen = () => {
    opened = true; state.connected = true; state.connects++; delay = 250;
    status(`connected to ${session}`);
    if (!state.rendered) overlay(`waiting for the first frame of ${session}…`);
    subscribe();
  };
  ws.onmessage = async (ev) => {
    const m = JSON.parse(ev.data);
    if (m.type === "hello") await onHello(m);
    else if (m.type === "frame" && state.hello) { latest = m; state.frames++; state.lastSeq = m.seq; }
    else if (m.type === "status") {
      const text = `${m.session}: ${m.state} ${m.detail || ""}`;
      status(text, m.state !== "running");
      if (["ended", "failed", "stopped"].includes(m.state)) { stop(text); ws.close(); }
    } else if (m.type === "error") {
      state.error = m.reason;
      if (m.code === "unavailable_stream" && streams.includes("arkit")) { // a model without them
        streams = ["articulatory", "pose"]; subscribe(); return;
      }
      status(`error: ${m.reason}`, true);
      if (m.code === "unknown_session") { stop(`no session "${session}" on this server`); ws.close(); }
    }
  };
  ws.onclose = async () => {
    state.connected = false;
    if (final) return;
    const why = opened ? "" : await refusal();
    if (why) stop(why); else retry("disconnected");
  };
}
function retry(why) {
  status(`${why}: reconnecting in ${(delay / 1000).toFixed(1)} s`, true);
  overlay(`${why}: reconnecting in ${(delay / 1000).toFixed(1)} s…`);
  setTimeout(connect, delay); delay = Math.min(delay * 2, 5000);
}
// a dropped or chosen file: worn at once (it never leaves this browser)
function wear(file) { if (file) loadVrm(URL.createObjectURL(file), file.name); }
$("file").onchange = (e) => wear(e.target.files[0]);
const drop = $("drop");
document.body.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
document.body.addEventListener("dragleave", () => drop.classList.remove("over"));
document.body.addEventListener("drop", (e) => { e.preventDefault(); drop.classList.remove("over"); wear(e.dataTransfer.files[0]); });
overlay("connecting to the articast server…");
requestAnimationFrame(draw);
connect();
