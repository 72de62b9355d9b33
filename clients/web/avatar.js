// articast browser avatar: subscribes over WebSocket, animates the face mesh linearly from the
// streamed articulatory parameters (x = mean + sum_k alpha_k basis_k, the dense modes when the
// server offers them), shades it with WebGL, shows the parameters, pose, latency and fps, and
// reconnects by itself. No network but the articast server; no build step.
//
// Newest frame only: a message only replaces `latest`; one requestAnimationFrame loop draws
// it (and updates the panel) at most once per display frame. However slow the machine, nothing
// queues in the page: frames that arrive between two display frames are counted, not drawn.
// Latency shown = capture -> on screen (wall clock; the server's `t_capture`).
import { faceNormals, mat4Perspective, mat4Multiply, mat4Translate, morph, normalise3,
         rotationFromAxisAngle, transpose3 } from "./math.js";
import { loadScan } from "./scan.js";
import { loadDelegate } from "./delegate.js";
import { drawUpper, upperAnchors } from "./eyes.js";

const params = new URLSearchParams(location.search);
// the server's token, if it has one, comes in this page's URL (?token=...) and goes on
const token = params.get("token");
const authHeaders = token ? { Authorization: `Bearer ${token}` } : {};
function withToken(url) {
  if (!token) return url;
  return url + (url.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token);
}
const state = (window.articast = {
  frames: 0, rendered: 0, connects: 0, connected: false, hello: null, alpha: null, status: "",
  error: "", final: "", mesh: "", lastSeq: -1, fps: 0, latencyMs: null,
  latencies: [], // capture -> on screen, ms, one per drawn frame (the last 20 000)
});
const $ = (id) => document.getElementById(id);
const canvas = $("canvas");
const gl = canvas.getContext("webgl", { preserveDrawingBuffer: true, antialias: true });

// ----------------------------------------------------------------------------- rendering
// per-point labels of the dense face (hello's dense mesh): 0 skin, 1 lips, 2 teeth, 3 mouth
const VS = `attribute vec3 p; attribute vec3 n; attribute float lab; uniform mat4 mvp;
uniform mat3 rot; uniform vec3 colour; varying vec3 vn; varying vec3 vc;
void main() { vn = rot * n; gl_Position = mvp * vec4(p, 1.0);
  vc = lab < 0.5 ? colour : lab < 1.5 ? vec3(0.72, 0.33, 0.36)
     : lab < 2.5 ? vec3(0.93, 0.92, 0.86) : vec3(0.22, 0.05, 0.07); }`;
const FS = `precision mediump float; varying vec3 vn; varying vec3 vc; uniform float unlit;
void main() { vec3 l = normalize(vec3(-0.3, 0.4, 1.0));
  float d = abs(dot(normalize(vn), l));
  gl_FragColor = vec4(vc * mix(0.35 + 0.75 * d, 1.0, unlit), 1.0); }`;

function shader(type, src) {
  const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
  return s;
}
let prog = null, loc = {};
if (gl) {
  prog = gl.createProgram();
  gl.attachShader(prog, shader(gl.VERTEX_SHADER, VS));
  gl.attachShader(prog, shader(gl.FRAGMENT_SHADER, FS));
  gl.linkProgram(prog);
  loc = { p: gl.getAttribLocation(prog, "p"), n: gl.getAttribLocation(prog, "n"),
          lab: gl.getAttribLocation(prog, "lab"),
          mvp: gl.getUniformLocation(prog, "mvp"), rot: gl.getUniformLocation(prog, "rot"),
          colour: gl.getUniformLocation(prog, "colour"), unlit: gl.getUniformLocation(prog, "unlit") };
  gl.enable(gl.DEPTH_TEST);
}

class Mesh {
  // mean: Float32Array(3M), basis: Float32Array(K*3M), triangles: array of indices
  constructor(mean, basis, triangles, k, labels) {
    this.mean = mean; this.basis = basis; this.k = k; this.m = mean.length / 3;
    this.labels = labels && labels.length === this.m ? new Float32Array(labels) : null;
    this.tri = new Uint32Array(triangles);
    this.pos = new Float32Array(mean.length); this.nrm = new Float32Array(mean.length);
    const edges = new Set();
    for (let t = 0; t < this.tri.length; t += 3)
      for (let e = 0; e < 3; e++) {
        const a = this.tri[t + e], b = this.tri[t + (e + 1) % 3];
        edges.add(a < b ? a * 1e6 + b : b * 1e6 + a);
      }
    this.lines = new Uint32Array(edges.size * 2);
    let i = 0; for (const e of edges) { this.lines[i++] = Math.floor(e / 1e6); this.lines[i++] = e % 1e6; }
    if (gl) {
      this.pb = gl.createBuffer(); this.nb = gl.createBuffer();
      if (this.labels) {
        this.labb = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, this.labb);
        gl.bufferData(gl.ARRAY_BUFFER, this.labels, gl.STATIC_DRAW);
      }
      this.ib = gl.createBuffer(); gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.ib);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, this.tri, gl.STATIC_DRAW);
      this.lb = gl.createBuffer(); gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.lb);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, this.lines, gl.STATIC_DRAW);
    }
  }
  update(alpha) {
    morph(this.pos, this.mean, this.basis, alpha, this.k);
    faceNormals(this.pos, this.tri, this.nrm);
    normalise3(this.nrm);
  }
  draw(mvp, rot, colour, wire) {
    gl.useProgram(prog);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.pb); gl.bufferData(gl.ARRAY_BUFFER, this.pos, gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(loc.p); gl.vertexAttribPointer(loc.p, 3, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.nb); gl.bufferData(gl.ARRAY_BUFFER, this.nrm, gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(loc.n); gl.vertexAttribPointer(loc.n, 3, gl.FLOAT, false, 0, 0);
    if (this.labels && !wire) {
      gl.bindBuffer(gl.ARRAY_BUFFER, this.labb);
      gl.enableVertexAttribArray(loc.lab); gl.vertexAttribPointer(loc.lab, 1, gl.FLOAT, false, 0, 0);
    } else { gl.disableVertexAttribArray(loc.lab); gl.vertexAttrib1f(loc.lab, 0); }
    gl.uniformMatrix4fv(loc.mvp, false, mvp); gl.uniformMatrix3fv(loc.rot, false, rot);
    gl.uniform3fv(loc.colour, colour); gl.uniform1f(loc.unlit, wire ? 1 : 0);
    if (wire) {
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.lb);
      gl.drawElements(gl.LINES, this.lines.length, gl.UNSIGNED_INT, 0);
    } else {
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.ib);
      gl.drawElements(gl.TRIANGLES, this.tri.length, gl.UNSIGNED_INT, 0);
    }
  }
}
if (gl) gl.getExtension("OES_element_index_uint");

let sparse = null, dense = null, centre = [0, 0, 0], firstRot = null, pose = null, scan = null, delegate = null, upper = null;

function render() {
  if (!gl || !sparse || !state.alpha) return;
  const w = canvas.clientWidth || canvas.width, h = canvas.clientHeight || canvas.height;
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  gl.viewport(0, 0, canvas.width, canvas.height);
  gl.clearColor(0.19, 0.2, 0.23, 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  // the head frame: x = speaker's left (the viewer's right), y up, z towards the viewer
  let rot = [1, 0, 0, 0, 1, 0, 0, 0, 1];
  if ($("headpose").checked && pose && pose.head) {
    // the server's head pose relative to the speaker's neutral (R_n^T R, in the head frame)
    rot = rotationFromAxisAngle(pose.head.rotation);
  } else if ($("headpose").checked && pose && firstRot) {
    // an older server: relative to the first frame seen here, R0^T R
    rot = mat3Mul(transpose3(firstRot), rotationFromAxisAngle(pose.rotation));
  }
  const useScan = scan && $("scan").checked; // a whole head: its own centre, further away
  const model = mat4FromRot(rot, useScan ? scan.centre : centre);
  const proj = mat4Perspective(0.5, canvas.width / canvas.height, 50, 2000);
  const view = mat4Translate(0, 0, useScan ? -scan.distance : -380);
  const mvp = mat4Multiply(proj, mat4Multiply(view, model));
  const rot3 = new Float32Array([rot[0], rot[3], rot[6], rot[1], rot[4], rot[7], rot[2], rot[5], rot[8]]);
  const useDense = dense && $("dense").checked;
  const mesh = useDense ? dense : sparse;
  if (useScan) { scan.update(state.alpha); scan.draw(mvp, rot3); }
  else if (delegate && $("delegate").checked) { delegate.update(state.alpha); delegate.draw(mvp, rot3); }
  else { mesh.update(state.alpha); mesh.draw(mvp, rot3, [0.86, 0.66, 0.56], false); }
  if ($("wire").checked) { sparse.update(state.alpha); sparse.draw(mvp, rot3, [0.2, 0.9, 0.6], true); }
  drawUpper($("upper"), mvp, upper, state.eyes, state.brows); // eyes.js: eyes and brows
}
function mat3Mul(a, b) {
  const o = new Array(9);
  for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++)
    o[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
  return o;
}
function mat4FromRot(r, c) { // rotate about the face centre c (row-major r), column-major out
  const t = [c[0] - (r[0] * c[0] + r[1] * c[1] + r[2] * c[2]),
             c[1] - (r[3] * c[0] + r[4] * c[1] + r[5] * c[2]),
             c[2] - (r[6] * c[0] + r[7] * c[1] + r[8] * c[2])];
  return new Float32Array([r[0], r[3], r[6], 0, r[1], r[4], r[7], 0, r[2], r[5], r[8], 0,
                           t[0] - c[0], t[1] - c[1], t[2] - c[2], 1]);
}

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
const TOKEN_FIX = "this server needs a token: open this page with &token=TOKEN in its URL " +
  "(the server's ARTICAST_TOKEN or --token-file)";
function stop(text) { // a refusal or an end: said once, never retried
  final = text; state.final = text; status(text, true); overlay(text);
}
async function refusal() { // why the server would not let us in, if it says so (else "")
  try {
    const r = await fetch("/api/sessions", { headers: authHeaders });
    if (r.status === 401) return token ? "the server refused this page's token: " + TOKEN_FIX : TOKEN_FIX;
    if (r.status === 429) return "the server refused this page's token too often: " + TOKEN_FIX +
      "; then wait a minute";
    if (r.status === 403) return "the server refused this page: " + ((await r.json()).detail || "forbidden");
  } catch (e) { /* unreachable: a network problem, retried */ }
  return "";
}
async function chooseSession() {
  if (params.get("session")) return params.get("session");
  const r = await fetch("/api/sessions", { headers: authHeaders });
  if ([401, 403, 429].includes(r.status)) throw new Error("refused");
  const list = await r.json();
  if (!list.length) throw new Error("the server has no session");
  return list[0].name;
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
  state.hello = h; firstRot = null;
  startPreview(h.preview_url || null);
  $("session").textContent = h.session; setupBars(h.param_names);
  const g = h.geometry; if (!g) { status("this session has no face model", true); return; }
  const k = h.param_names.length;
  sparse = new Mesh(new Float32Array(g.mean), new Float32Array(g.basis), g.triangles, k);
  centre = [0, 0, 0];
  for (let i = 0; i < g.mean.length; i += 3) for (let d = 0; d < 3; d++) centre[d] += g.mean[i + d] * 3 / g.mean.length;
  upper = upperAnchors(g);
  state.mesh = `sparse ${sparse.m} points`; $("mesh").textContent = state.mesh;
  dense = null; delegate = null; state.delegate = "";
  loadDelegate(gl, h.delegate_url, authHeaders).then((d) => { // the speaker's own face
    if (d && state.hello === h) { delegate = d; state.delegate = `textured, ${d.m} points`; }
  }).catch((e) => console.warn("delegate unavailable", e));
  if (h.dense_url) {
    try {
      const d = await (await fetch(h.dense_url, { headers: authHeaders })).json();
      dense = new Mesh(new Float32Array(d.mean), new Float32Array(d.basis), d.triangles, k, d.labels);
      state.mesh = `dense ${dense.m} points (sparse ${sparse.m})`; $("mesh").textContent = state.mesh;
    } catch (e) { console.warn("dense mesh unavailable", e); }
  }
  scan = null;
  try {
    scan = await loadScan(gl, h.session, k, authHeaders);
    if (scan) { state.mesh = `scan ${scan.m} points (sparse ${sparse.m})`; $("mesh").textContent = state.mesh; }
  } catch (e) { console.warn("head scan unavailable", e); state.scanError = String(e); }
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
  const names = state.hello.param_names, a = f.values.articulatory || {};
  state.alpha = names.map((n) => a[n] || 0);
  state.eyes = f.eyes || null; state.brows = f.brows || null;
  if (f.values.pose) { pose = f.values.pose; if (!firstRot && f.quality.ok) firstRot = rotationFromAxisAngle(pose.rotation); }
  showBars(state.alpha);
  $("quality").textContent = f.quality.ok ? `ok, ${f.quality.evals} evals` : `not ok: ${f.quality.reason}`;
  $("quality").className = f.quality.ok ? "good" : "bad";
  if (pose) $("pose").textContent = pose.translation.map((v) => v.toFixed(0)).join(", ") + " mm";
  render();
  state.rendered++;
  // end to end: captured on the server -> drawn here (same host, or NTP-synced hosts)
  const ms = Math.max(0, Date.now() - f.t_capture * 1000);
  state.latencyMs = ms; state.latencies.push(ms);
  if (state.latencies.length > 20000) state.latencies.splice(0, 10000);
  $("latency").textContent = `${ms | 0} ms`;
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
function socketUrl() { // the one place the WebSocket URL is built
  const proto = location.protocol === "https:" ? "wss" : "ws";
  return withToken(params.get("ws") || `${proto}://${location.host}/ws`);
}
function retry(why) {
  status(`${why}: reconnecting in ${(delay / 1000).toFixed(1)} s`, true);
  overlay(`${why}: reconnecting in ${(delay / 1000).toFixed(1)} s…`);
  setTimeout(connect, delay); delay = Math.min(delay * 2, 5000);
}
if (!gl) status("WebGL is not available in this browser", true);
overlay("connecting to the articast server…");
requestAnimationFrame(draw);
connect();
