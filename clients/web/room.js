// The meeting room's page (issue 41; service/room.py, docs/ROOM.md): join with a name and the
// room's token (?room=ROOM) or a participant token from the host (?key=PTOKEN); the camera and
// microphone go to the server over WebRTC, with receive-only audio slots the server fills with
// the others' voices; the room socket brings every member's session (hello, frames, status).
// Every member's delegate stands in one three.js scene, side by side with their name, each
// driven by its own stream; the one whose lips move most is highlighted.
//
// The audio's clock. A frame's t_capture is when the server received its video frame; the
// voice captured with it reached the server then too, and plays here D ms later (the relay,
// the network, this page's jitter buffer: measured from the receiver's stats once a second,
// see audioDelay). So a member's frame is shown at t_capture + D (on this page's clock: the
// server's plus the offset measured on the socket), not when it arrives; a frame that comes
// later than that (tracking took longer than the audio's path) is shown at once, and the
// audio's jitter buffer is asked to wait that much longer (jitterBufferTarget), so that the
// voice waits for the lips instead. Your own delegate (self-view) is shown at once.
import * as THREE from "three";
import { LinearFace } from "./face.js";
import { Head } from "./eyes.js";
import { loadDelegate } from "./delegate.js";
import { keepResolution } from "./connect.js";
import { enrol } from "./enrol.js";

const params = new URLSearchParams(location.search);
const $ = (id) => document.getElementById(id);
const state = (window.articastRoom = {
  status: "", final: "", you: "", connection: "", joined: false, speaking: "", members: {},
  offsetMs: null, left: [], enrol: { state: "" }, link: "", maxFramerate: 0, rejoined: [],
});
// A dropped connection (the server closes the room socket with DROPPED: the video or the
// connection ended, the session failed; not a leave, a delete or a refusal) is joined again by
// itself, REJOIN_MS later, twice that the next time, at most MAX_REJOINS times in a row; a
// membership that lasted STEADY_MS starts the count again.
const DROPPED = 4001, REJOIN_MS = 2000, MAX_REJOINS = 4, STEADY_MS = 60000;
let rejoins = 0, rejoinTimer = null, joinedAt = 0;
const SKIN = [0.86, 0.66, 0.56], SPACING = 210, NTP_UNIX_MS = 2208988800000;
const MAX_FPS = Number(params.get("fps")) || 30;

function status(text, bad) {
  const s = $("status"); s.textContent = text; s.className = bad ? "bad" : "good";
  state.status = text; if (bad) state.final = text;
}

// ----------------------------------------------------------------------------- scene
THREE.ColorManagement.enabled = false;
let renderer = null;
try {
  renderer = new THREE.WebGLRenderer({ canvas: $("canvas"), antialias: false });
  renderer.setPixelRatio(1);
  renderer.outputColorSpace = THREE.LinearSRGBColorSpace;
  renderer.setClearColor(new THREE.Color(0.19, 0.2, 0.23), 1);
} catch (e) { renderer = null; }
const scene = new THREE.Scene();
scene.add(new THREE.AmbientLight(0xffffff, 0.35 * Math.PI));
const sun = new THREE.DirectionalLight(0xffffff, 0.75 * Math.PI);
sun.position.set(-0.3, 0.4, 1.0);
scene.add(sun);
const camera = new THREE.PerspectiveCamera(30, 2, 50, 5000);
const axis = new THREE.Vector3();
function axisAngle(r, q) {
  const th = Math.hypot(r[0], r[1], r[2]);
  return th < 1e-12 ? q.identity() : q.setFromAxisAngle(axis.set(r[0] / th, r[1] / th, r[2] / th), th);
}

function label(text) { // a name under the delegate; gold while speaking
  const c = document.createElement("canvas"); c.width = 256; c.height = 48;
  const tex = new THREE.CanvasTexture(c); tex.colorSpace = THREE.NoColorSpace;
  const sprite = new THREE.Sprite(new THREE.SpriteMaterial({ map: tex, depthTest: false }));
  sprite.scale.set(160, 30, 1);
  let shown = null;
  const draw = (speaking) => {
    if (shown === speaking) return; shown = speaking;
    const x = c.getContext("2d"); x.clearRect(0, 0, 256, 48);
    x.fillStyle = speaking ? "#fc3" : "#0008"; x.fillRect(0, 0, 256, 48);
    x.fillStyle = speaking ? "#111" : "#eee"; x.font = "bold 26px system-ui, sans-serif";
    x.textAlign = "center"; x.textBaseline = "middle"; x.fillText(text.slice(0, 18), 128, 25);
    tex.needsUpdate = true;
  };
  draw(false);
  return { sprite, draw, dispose: () => { tex.dispose(); sprite.material.dispose(); } };
}

const members = new Map(); // name -> member
function member(info) {
  const m = {
    name: info.name, self: info.self, slot: info.slot, root: new THREE.Group(),
    head: new THREE.Group(), face: new THREE.Group(), hello: null, sparse: null, generic: null,
    delegate: null, queue: [], alpha: null, eyes: null, brows: null, pose: null,
    audioDelayMs: null, delayMethod: "", latencies: [], dirty: false,
    label: label(info.name),
    ring: new THREE.Mesh(new THREE.RingGeometry(112, 120, 48),
                         new THREE.MeshBasicMaterial({ color: 0xffcc33 })),
    hook: { received: [], applied: [], offsets: [], audioDelayMs: null, delayMethod: "", drawn: "" },
  };
  m.head.add(m.face); m.root.add(m.head);
  m.label.sprite.position.set(0, -125, 40); m.root.add(m.label.sprite);
  m.ring.position.set(0, 0, -90); m.ring.visible = false; m.root.add(m.ring);
  scene.add(m.root);
  state.members[m.name] = m.hook;
  return m;
}
function dispose(m) {
  scene.remove(m.root);
  m.root.traverse((o) => { if (o.geometry) o.geometry.dispose(); if (o.material && o.material.dispose) o.material.dispose(); });
  if (m.delegate) m.delegate.dispose();
  m.label.dispose();
  delete state.members[m.name];
  state.left.push(m.name);
}
function layout() {
  const list = [...members.values()];
  list.forEach((m, i) => m.root.position.set((i - (list.length - 1) / 2) * SPACING, 0, 0));
  const width = Math.max(1, list.length) * SPACING;
  camera.position.set(0, 0, Math.max(520, width / (2 * Math.tan(THREE.MathUtils.degToRad(15)) * camera.aspect) * 1.05));
  camera.lookAt(0, 0, 0);
  $("people").innerHTML = list.map((m) => `<b data-name="${m.name}">${m.name}${m.self ? " (you)" : ""}</b>`).join(" · ");
}

async function onHello(m, h) {
  m.hello = h;
  const g = h.geometry; if (!g) return;
  for (const old of [m.sparse, m.generic, m.delegate]) if (old && old.dispose) old.dispose();
  m.sparse = new LinearFace(g.mean, g.basis, g.triangles, h.param_names.length, null, SKIN);
  m.generic = new Head(g); m.delegate = null;
  const c = [0, 0, 0];
  for (let i = 0; i < g.mean.length; i += 3) for (let d = 0; d < 3; d++) c[d] += g.mean[i + d] * 3 / g.mean.length;
  m.face.position.set(-c[0], -c[1], -c[2]);
  m.dirty = true;
  if (h.delegate_url && renderer) { // their enrolled face, for the room's members only
    loadDelegate(`/room/api/delegate/${encodeURIComponent(m.name)}`, auth()).then((d) => {
      if (d && m.hello === h) { m.delegate = d; m.dirty = true; }
    }).catch((e) => console.warn("delegate unavailable", e));
  }
}

// ----------------------------------------------------------------------------- the clock
function onFrame(m, f) {
  const nowMs = Date.now();
  const sample = nowMs - f.t_sent * 1000; // the server's clock to this page's (+ one-way delay)
  m.hook.offsets.push(sample); if (m.hook.offsets.length > 200) m.hook.offsets.shift();
  state.offsetMs = state.offsetMs === null ? sample : Math.min(state.offsetMs, sample);
  const a = f.lips && f.quality && f.quality.ok ? f.lips.aperture_mm : null;
  const captured = f.t_capture * 1000 + state.offsetMs; // on this page's clock
  m.latencies.push(nowMs - captured); if (m.latencies.length > 100) m.latencies.shift();
  const delay = m.self || m.audioDelayMs === null ? 0 : m.audioDelayMs;
  const due = m.self ? nowMs : captured + delay;
  m.hook.received.push([f.t, a, f.t_capture, nowMs]);
  if (m.hook.received.length > 5000) m.hook.received.splice(0, 1000);
  m.queue.push({ f, a, due, captured });
  if (m.queue.length > 90) m.queue.shift();
}

function median(xs) { const s = [...xs].sort((p, q) => p - q); return s.length ? s[s.length >> 1] : null; }

async function audioDelay(m) { // ms from the server's receipt of a voice to its playout here
  if (!pc || !m.slot) return;
  const t = pc.getTransceivers().find((x) => x.mid === m.slot);
  if (!t) return;
  let jb = null, playout = null, rtt = null, at = null;
  const stats = await t.receiver.getStats();
  stats.forEach((r) => {
    if (r.type === "inbound-rtp" && r.kind === "audio") {
      if (r.jitterBufferEmittedCount > 0) { // over the last second (the totals average since joining)
        const prev = m.jbTotals, n = r.jitterBufferEmittedCount - (prev ? prev[1] : 0);
        jb = 1000 * (r.jitterBufferDelay - (prev && n > 0 ? prev[0] : 0)) /
          (prev && n > 0 ? n : r.jitterBufferEmittedCount);
        m.jbTotals = [r.jitterBufferDelay, r.jitterBufferEmittedCount];
      }
      if (r.estimatedPlayoutTimestamp) { playout = r.estimatedPlayoutTimestamp; at = r.timestamp; }
      // how the voice arrives (for the benchmark and the test's log): RTP arrival jitter, lost
      // packets, and the share of played samples the jitter buffer had to make up
      m.hook.arrival = { jitterMs: 1000 * (r.jitter || 0), lost: r.packetsLost || 0,
        concealed: r.totalSamplesReceived ? r.concealedSamples / r.totalSamplesReceived : null };
    }
    if (r.type === "candidate-pair" && r.nominated && r.currentRoundTripTime != null) rtt = 1000 * r.currentRoundTripTime;
  });
  const RELAY_MS = 0; // the server forwards the Opus packets as they come (service/media.py)
  let d = null, how = "";
  if (playout !== null && state.offsetMs !== null) {
    // what plays now left the server at `playout` (its NTP clock, from its sender reports)
    const x = (performance.timeOrigin + at) - (playout - NTP_UNIX_MS + state.offsetMs) + RELAY_MS;
    if (x > 0 && x < 3000) { d = x; how = "estimatedPlayoutTimestamp"; }
  }
  if (d === null && jb !== null) { d = (rtt || 0) / 2 + jb + RELAY_MS; how = "jitter buffer + rtt/2"; }
  if (d === null) return;
  m.audioDelayMs = d; m.hook.audioDelayMs = d; m.hook.delayMethod = how; m.hook.jitterMs = jb;
  // the voice waits for the lips: a jitter buffer as long as the animation is late
  const late = median(m.latencies);
  if (late !== null && "jitterBufferTarget" in t.receiver) {
    const target = Math.max(0, Math.min(1000, late - (d - (jb || 0))));
    try { t.receiver.jitterBufferTarget = target; m.hook.jitterTarget = target; } catch (e) { /* older browser */ }
  }
}

// ----------------------------------------------------------------------------- drawing
let lastDraw = 0;
function speakingScore(m) { // the spread of the lip aperture over the last 1.5 s applied
  const now = Date.now(), xs = [];
  for (let i = m.hook.applied.length - 1; i >= 0; i--) {
    const r = m.hook.applied[i]; if (now - r[3] > 1500) break; if (r[1] !== null) xs.push(r[1]);
  }
  if (xs.length < 3) return 0;
  const mu = xs.reduce((p, q) => p + q, 0) / xs.length;
  return Math.sqrt(xs.reduce((p, q) => p + (q - mu) * (q - mu), 0) / xs.length);
}
function apply(m, item) {
  const f = item.f, names = m.hello.param_names, a = f.values.articulatory || {};
  m.alpha = names.map((n) => a[n] || 0); m.eyes = f.eyes || null; m.brows = f.brows || null;
  if (f.values.pose) m.pose = f.values.pose;
  m.hook.applied.push([f.t, item.a, f.t_capture, Date.now(), item.due]);
  if (m.hook.applied.length > 5000) m.hook.applied.splice(0, 1000);
  m.dirty = true;
}
function draw(now) {
  requestAnimationFrame(draw);
  if (now - lastDraw < 1000 / MAX_FPS) return;
  lastDraw = now;
  const wall = Date.now();
  let changed = false;
  for (const m of members.values()) {
    if (!m.hello) continue;
    let next = null;
    while (m.queue.length && m.queue[0].due <= wall) next = m.queue.shift();
    if (next) apply(m, next);
    if (!m.dirty || !m.alpha) continue;
    m.dirty = false; changed = true;
    if (m.pose && m.pose.head) axisAngle(m.pose.head.rotation, m.head.quaternion);
    const shown = [];
    if (m.delegate) { m.delegate.update(m.alpha, m.eyes, m.brows); shown.push(m.delegate.object); m.hook.drawn = "delegate"; }
    else if (m.sparse) {
      m.sparse.update(m.alpha); shown.push(m.sparse.object);
      if (m.generic) { m.generic.update(m.eyes, m.brows); shown.push(m.generic.object); }
      m.hook.drawn = "generic";
    }
    for (const o of [...m.face.children]) if (!shown.includes(o)) m.face.remove(o);
    for (const o of shown) if (o.parent !== m.face) m.face.add(o);
  }
  let best = "", bestScore = 0.6; // mm: lips at rest move less
  for (const m of members.values()) { const s = speakingScore(m); if (s > bestScore) { best = m.name; bestScore = s; } }
  if (best !== state.speaking) {
    state.speaking = best; changed = true;
    for (const m of members.values()) { m.label.draw(m.name === best); m.ring.visible = m.name === best; }
    for (const b of document.querySelectorAll("#people b")) b.className = b.dataset.name === best ? "speaking" : "";
  }
  if (changed && renderer) {
    const el = renderer.domElement, w = el.clientWidth || el.width, h = el.clientHeight || el.height;
    if (el.width !== w || el.height !== h) { renderer.setSize(w, h, false); camera.aspect = w / h; camera.updateProjectionMatrix(); layout(); }
    renderer.render(scene, camera);
  }
}

// ----------------------------------------------------------------------------- joining
let pc = null, ws = null, stream = null, ptoken = params.get("key") || "", timer = null;
const auth = () => ({ "X-Participant-Token": ptoken });

async function refusal(r, what) {
  let detail = "";
  try { detail = (await r.json()).detail || ""; } catch (e) { /* not JSON */ }
  if (typeof detail !== "string") detail = JSON.stringify(detail);
  if (r.status === 401) return `the room refused this page's token (${what}): open the room's URL as the host gave it`;
  if (r.status === 429) return "the room refused: " + detail;
  return `the room refused to ${what} (${r.status}): ${detail}`;
}
function cameraProblem(e) {
  const name = e && e.name;
  if (name === "NotAllowedError" || name === "SecurityError")
    return "the camera was denied: allow it for this page and join again";
  if (name === "NotFoundError" || name === "OverconstrainedError") return "no camera was found: plug one in and join again";
  return "the camera could not be opened: " + (e && e.message ? e.message : String(e));
}
function gathered(pc) {
  if (pc.iceGatheringState === "complete") return Promise.resolve();
  return new Promise((resolve) => {
    pc.addEventListener("icegatheringstatechange", () => { if (pc.iceGatheringState === "complete") resolve(); });
    setTimeout(resolve, 3000);
  });
}
const post = (url, headers, body) => fetch(url, { method: "POST", body: JSON.stringify(body),
  headers: { "Content-Type": "application/json", ...headers } });

// joined: true; false when refused or impossible; "retry" when the server could not be
// reached or was busy with this name (a transient failure: a rejoin tries again)
async function join(name) {
  state.final = "";
  if (!window.isSecureContext || !navigator.mediaDevices) {
    status("the camera needs a secure page: open this page over https:// (or on localhost)", true); return false;
  }
  let slots = 7, maxFps = 0, r;
  try {
    if (!ptoken) {
      r = await post("/room/api/join", { "X-Room-Token": params.get("room") || "" }, { name });
      if (!r.ok) { status(await refusal(r, "join"), true); return false; }
      const j = await r.json(); ptoken = j.token; slots = j.slots; maxFps = j.max_fps || 0; $("roomname").textContent = j.room;
    } else {
      r = await fetch("/room/api/me", { headers: auth() });
      if (!r.ok) { status(await refusal(r, "join"), true); return false; }
      const j = await r.json(); slots = j.slots; maxFps = j.max_fps || 0; name = j.name; $("roomname").textContent = j.room;
    }
  } catch (e) { status("the room's server cannot be reached: " + e.message, true); return "retry"; }
  state.you = name;
  status("asking for the camera and microphone…");
  const video = { width: { ideal: 640 }, height: { ideal: 480 }, frameRate: { ideal: 30 } };
  try {
    stream = await navigator.mediaDevices.getUserMedia({ video, audio: params.get("audio") !== "0" });
  } catch (e) {
    try { stream = await navigator.mediaDevices.getUserMedia({ video }); status("no microphone: joining without sound"); }
    catch (e2) { status(cameraProblem(e), true); return false; }
  }
  $("self").srcObject = stream;
  pc = new RTCPeerConnection({ iceServers: [] });
  // the tracker needs the resolution its camera was calibrated for: short of CPU or bandwidth,
  // the browser is to lower the frame rate, not the resolution (the server scales back a
  // smaller frame, but a blurred face tracks worse)
  for (const track of stream.getTracks()) {
    if (track.kind === "video") track.contentHint = "detail";
    // no more frames than the server's tracker takes (max_fps): each one sent is decoded
    pc.addTransceiver(track, { direction: "sendonly", streams: [stream],
      ...(track.kind === "video" && maxFps > 0 ? { sendEncodings: [{ maxFramerate: maxFps }] } : {}) });
  }
  for (let i = 0; i < slots; i++) pc.addTransceiver("audio", { direction: "recvonly" });
  pc.ontrack = (e) => { // a slot: the server points it at another member's microphone
    if (e.track.kind !== "audio") return;
    const el = document.createElement("audio"); el.autoplay = true;
    el.srcObject = new MediaStream([e.track]); document.body.appendChild(el);
    el.play().catch(() => { /* autoplay: the join click allows it */ });
  };
  pc.onconnectionstatechange = () => {
    state.connection = pc ? pc.connectionState : "closed";
    if (pc && pc.connectionState === "failed") status("the connection to the room failed (a network between you needs TURN)", true);
  };
  await pc.setLocalDescription(await pc.createOffer());
  await gathered(pc);
  try {
    r = await post("/room/api/offer", auth(), { type: "offer", sdp: pc.localDescription.sdp });
  } catch (e) { status("the room's server cannot be reached: " + e.message, true); leave(true); return "retry"; }
  if (!r.ok) {
    const transient = r.status === 409 || r.status >= 500; // (the last session still ending)
    status(await refusal(r, "take your offer"), true); leave(true); return transient ? "retry" : false;
  }
  const answer = await r.json();
  await pc.setRemoteDescription({ type: "answer", sdp: answer.sdp });
  keepResolution(pc, maxFps).then((cap) => { state.maxFramerate = cap; });
  $("join").disabled = true; $("leave").disabled = false; state.joined = true; joinedAt = performance.now();
  status(`joined as ${name}; the tracker is starting…`);
  follow();
  timer = setInterval(() => { for (const m of members.values()) if (!m.self) audioDelay(m).catch(() => {}); }, 1000);
  return true;
}

function follow() {
  const url = new URL("/room/ws", location.href);
  url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
  url.searchParams.set("key", ptoken);
  ws = new WebSocket(url);
  ws.onmessage = async (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.type === "members") {
      const seen = new Set();
      let changed = false;
      for (const info of msg.members) {
        seen.add(info.name);
        const m = members.get(info.name);
        if (!m) { members.set(info.name, member(info)); changed = true; } else m.slot = info.slot;
      }
      for (const [n, m] of members) if (!seen.has(n)) { dispose(m); members.delete(n); changed = true; }
      if (changed) { layout(); render(); }
    } else if (msg.type === "hello") {
      const m = members.get(msg.session); if (m) await onHello(m, msg);
    } else if (msg.type === "frame") {
      const m = members.get(msg.session); if (m && m.hello) onFrame(m, msg);
      if (m && m.self && state.status.includes("starting")) status(`joined as ${state.you}: your face is tracked`);
    } else if (msg.type === "status") {
      if (msg.session === state.you && ["failed", "unavailable"].includes(msg.state)) status(`your session ${msg.state}: ${msg.detail}`, true);
    } else if (msg.type === "error") status("the room said: " + msg.reason, true);
  };
  ws.onclose = (ev) => {
    const was = state.joined, why = `the room closed the connection${ev.reason ? ": " + ev.reason : ""}`;
    if (was) status(why, true);
    leave(true);
    if (was && ev.code === DROPPED) rejoinLater(ev.reason || "your connection dropped", state.you);
  };
}
function rejoinLater(why, name) {
  if (performance.now() - joinedAt > STEADY_MS) rejoins = 0;
  if (rejoins >= MAX_REJOINS) { status(`${why}; it failed ${rejoins} times in a row: join again when your network is steady`, true); return; }
  const delay = REJOIN_MS * 2 ** rejoins++;
  status(`${why}: joining again in ${(delay / 1000).toFixed(0)} s…`);
  state.rejoined.push({ reason: why, delayMs: delay });
  $("join").disabled = true; $("leave").disabled = false; // (leave: stay out)
  rejoinTimer = setTimeout(async () => {
    rejoinTimer = null;
    if ((await join(name)) === "retry") rejoinLater(state.final || why, name);
  }, delay);
}
function render() { if (renderer) renderer.render(scene, camera); }

function leave(keepStatus) {
  state.joined = false;
  if (rejoinTimer && keepStatus !== true) { clearTimeout(rejoinTimer); rejoinTimer = null; } // the button: stay out
  if (timer) { clearInterval(timer); timer = null; }
  if (ws) { const w = ws; ws = null; w.onclose = null; w.close(); }
  if (pc) { pc.close(); pc = null; }
  if (stream) { for (const t of stream.getTracks()) t.stop(); stream = null; }
  for (const [n, m] of members) { dispose(m); members.delete(n); }
  if (!params.get("key") && !personal) ptoken = "";
  $("join").disabled = false; $("leave").disabled = true;
  if (keepStatus !== true) status("left");
}

// ----------------------------------------------------------------------------- enrolment
// (clients/web/enrol.js): the participant's token first (the room token's /join), their own
// camera recorded here, the clip uploaded, the server's work followed; then the page keeps
// their token (an enrolled name is joined with it only: ?key=, shown as their own link) and
// joins again, so that the room tracks them with their speaker folder.
let personal = false, enrolling = null;
async function token(name) {
  if (ptoken) return (await (await fetch("/room/api/me", { headers: auth() })).json()).name;
  const r = await post("/room/api/join", { "X-Room-Token": params.get("room") || "" }, { name });
  if (!r.ok) { status(await refusal(r, "enrol you"), true); return ""; }
  ptoken = (await r.json()).token; return name;
}
function keepToken() { // an enrolled name joins with its own token: this page's URL carries it
  personal = true;
  const link = new URL("/room", location.href); link.searchParams.set("key", ptoken);
  state.link = link.href;
  history.replaceState(null, "", "?key=" + encodeURIComponent(ptoken));
}
async function enrolMe(name, thenJoin) {
  if (enrolling) return;
  if (!window.isSecureContext || !navigator.mediaDevices) {
    status("the camera needs a secure page: open this page over https:// (or on localhost)", true); return;
  }
  try { name = await token(name); } catch (e) { status("the room's server cannot be reached: " + e.message, true); return; }
  if (!name) return;
  const wasJoined = state.joined;
  let cam = stream, own = false;
  if (!cam) {
    try { cam = await navigator.mediaDevices.getUserMedia({ video: { width: { ideal: 640 }, height: { ideal: 480 }, frameRate: { ideal: 30 } } }); own = true; }
    catch (e) { status(cameraProblem(e), true); return; }
    $("self").srcObject = cam;
  }
  enrolling = new AbortController();
  $("guide").hidden = false; $("enrol").disabled = true; $("stop").disabled = false;
  $("join").disabled = true; // (one camera, one thing at a time: joining comes after)
  status(`enrolling ${name}: follow the steps below`);
  const ui = {
    step: (t) => { $("step").textContent = t; },
    read: (t) => { $("read").hidden = !t; if (t) $("read").textContent = t; },
    bar: (f) => { $("bar").value = f; }, count: (t) => { $("count").textContent = t; },
  };
  state.enrol = { state: "starting" };
  const done = await enrol({ name, token: ptoken, stream: cam, ui, hook: state.enrol, signal: enrolling.signal,
    countdown: Number(params.get("countdown") ?? 3) });
  enrolling = null; $("enrol").disabled = false; $("stop").disabled = true;
  $("join").disabled = state.joined;
  if (own && !state.joined) { for (const t of cam.getTracks()) t.stop(); $("self").srcObject = null; }
  if (done.state !== "done") {
    ui.step(done.state === "cancelled" ? "Enrolment cancelled" : "Enrolment failed");
    status(done.detail || done.state, done.state === "failed"); return;
  }
  ptoken = done.token; keepToken();
  $("forget").hidden = false;
  ui.step("Enrolled: your delegate shows your own face"); ui.bar(1);
  ui.count((done.warnings || []).length ? "note: " + done.warnings.join("; ") : "");
  status(`enrolled ${name}; keep this page's address (your own link): ${state.link}`);
  if (wasJoined) { leave(true); await join(name); } // tracked again, with the speaker folder
  else if (thenJoin) await join(name);
}
async function forget() {
  const name = state.you || $("name").value;
  if (!ptoken || !name) return;
  const r = await fetch(`/room/api/enrol/${encodeURIComponent(name)}`, { method: "DELETE", headers: auth() });
  if (!r.ok) { status(await refusal(r, "delete your enrolment"), true); return; }
  const j = await r.json();
  state.enrol = { state: "deleted" }; $("forget").hidden = true; $("guide").hidden = true;
  // the token was bound to the folder: the name is an ordinary one again (the room token's)
  if (j.deleted) {
    personal = false; ptoken = "";
    if (params.get("room")) history.replaceState(null, "", "?room=" + encodeURIComponent(params.get("room")));
  }
  status(j.deleted ? `your speaker folder is deleted; to join again, open the room's URL${params.get("room") ? " (this page's)" : ""}` : "you had no enrolment here");
}
addEventListener("pagehide", () => { // closed mid-enrolment: the server stops it (it would after 20 s)
  if (!enrolling) return;
  enrolling.abort();
  const name = state.you || $("name").value;
  fetch(`/room/api/enrol/${encodeURIComponent(name)}/cancel`, { method: "POST", headers: auth(), keepalive: true }).catch(() => {});
});

$("form").addEventListener("submit", (ev) => { ev.preventDefault(); join($("name").value); });
$("leave").addEventListener("click", () => leave());
$("enrol").addEventListener("click", () => enrolMe(state.joined ? state.you : $("name").value, false));
$("stop").addEventListener("click", () => { if (enrolling) enrolling.abort(); });
$("forget").addEventListener("click", () => forget());
window.articastLeave = () => leave(); window.articastJoin = (n) => join(n || $("name").value);
window.articastEnrol = (n, thenJoin) => enrolMe(n || $("name").value, thenJoin);
if (!renderer) status("WebGL is not available in this browser", true);
requestAnimationFrame(draw);
if (params.get("key")) { personal = true; $("forget").hidden = false; }
if (params.get("name") && params.get("enrol") === "1") { $("name").value = params.get("name"); enrolMe(params.get("name"), true); }
else if (params.get("name")) { $("name").value = params.get("name"); join(params.get("name")); }
else if (params.get("key")) join("");
