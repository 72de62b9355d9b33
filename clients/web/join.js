// The participant page: the webcam (getUserMedia) sent to the server over WebRTC as session
// NAME (POST /api/sessions/NAME/webrtc with the SDP offer, the token as for the other API
// routes), and that session's tracked frames followed over the WebSocket. Every refusal is
// said on the page in one line: a denied or missing camera, an insecure page, a refused
// token, offer or name, a connection that failed.
import { keepResolution } from "./connect.js";

const params = new URLSearchParams(location.search);
const token = params.get("token");
const $ = (id) => document.getElementById(id);
const state = { status: "", final: "", connection: "", frames: 0, ok: 0, apertures: [] };
window.articastJoin = state; // for tests and the curious

function status(text, bad) {
  const s = $("status"); s.textContent = text; s.className = bad ? "bad" : "good";
  state.status = text; if (bad) state.final = text;
}

const TOKEN_FIX = "open this page with &token=TOKEN in its URL (the server's ARTICAST_TOKEN " +
  "or --token-file)";

function cameraProblem(e) {
  const name = e && e.name;
  if (name === "NotAllowedError" || name === "SecurityError")
    return "the camera was denied: allow it for this page (the camera icon in the address " +
      "bar) and join again";
  if (name === "NotFoundError" || name === "OverconstrainedError")
    return "no camera was found: plug one in and join again";
  if (name === "NotReadableError" || name === "AbortError")
    return "the camera could not be started: another program may be using it";
  return "the camera could not be opened: " + (e && e.message ? e.message : String(e));
}

async function refusal(r) {
  let detail = "";
  try { detail = (await r.json()).detail || ""; } catch (e) { /* not JSON */ }
  if (typeof detail !== "string") detail = JSON.stringify(detail);
  if (r.status === 401) return (token ? "the server refused this page's token: " :
    "this server needs a token: ") + TOKEN_FIX;
  if (r.status === 403) return "the server refused to start a session: " + detail;
  if (r.status === 409) return "the server refused the name: " + detail;
  if (r.status === 501) return "this server cannot receive video: " + detail;
  if (r.status === 400) return "the server refused the offer: " + detail;
  return `the server refused to join (${r.status}): ${detail}`;
}

function gathered(pc) { // the server answers once: send the offer with every candidate
  if (pc.iceGatheringState === "complete") return Promise.resolve();
  return new Promise((resolve) => {
    const done = () => { if (pc.iceGatheringState === "complete") resolve(); };
    pc.addEventListener("icegatheringstatechange", done);
    setTimeout(resolve, 3000); // loopback gathers in milliseconds; do not hang on a slow STUN
  });
}

let pc = null, ws = null, stream = null;

function follow(name) { // the session's own tracked frames, as a subscriber
  const url = new URL("/ws", location.href);
  url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
  if (token) url.searchParams.set("token", token);
  ws = new WebSocket(url);
  ws.onopen = () => ws.send(JSON.stringify({ type: "subscribe", session: name,
    streams: ["articulatory"] }));
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data);
    if (m.type === "frame") {
      state.frames += 1;
      $("frames").textContent = String(state.frames);
      if (m.quality && m.quality.ok && m.lips) {
        state.ok += 1;
        state.apertures.push(m.lips.aperture_mm);
        if (state.apertures.length > 600) state.apertures.shift();
        $("aperture").textContent = m.lips.aperture_mm.toFixed(1) + " mm";
      }
    } else if (m.type === "status") {
      if (m.state === "running") status(`joined as ${name}: your face is tracked`);
      else if (["failed", "ended", "unavailable", "stalled", "restarting"].includes(m.state))
        status(`session ${m.state}: ${m.detail}`, m.state !== "ended");
      else status(`session ${m.state}: ${m.detail}`);
    } else if (m.type === "error") {
      status("the server said: " + m.reason, true);
    }
  };
}

async function join(name) {
  state.final = "";
  if (!window.isSecureContext || !navigator.mediaDevices) {
    status("the camera needs a secure page: open this page over https:// (or on localhost)", true);
    return;
  }
  status("asking for the camera…");
  try {
    stream = await navigator.mediaDevices.getUserMedia({
      video: { width: { ideal: 640 }, height: { ideal: 480 }, frameRate: { ideal: 30 } },
      audio: $("audio").checked });
  } catch (e) { status(cameraProblem(e), true); return; }
  $("self").srcObject = stream;
  pc = new RTCPeerConnection({ iceServers: [] }); // loopback and LAN: no STUN/TURN needed
  // the tracker needs the resolution its camera was calibrated for: short of CPU or bandwidth,
  // the browser is to lower the frame rate, not the resolution (Chromium's fake camera went
  // to 480x360 and 320x240 without this: benchmarks/fake_camera.py)
  for (const track of stream.getTracks()) {
    if (track.kind === "video") track.contentHint = "detail";
    pc.addTrack(track, stream);
  }
  pc.onconnectionstatechange = () => {
    state.connection = pc.connectionState;
    $("connection").textContent = pc.connectionState;
    if (pc.connectionState === "failed")
      status("the connection to the server failed (a network between you needs TURN)", true);
  };
  status("connecting…");
  await pc.setLocalDescription(await pc.createOffer());
  await gathered(pc);
  const body = { type: "offer", sdp: pc.localDescription.sdp };
  if (params.get("speaker")) body.speaker = params.get("speaker");
  let r;
  try {
    r = await fetch(`/api/sessions/${encodeURIComponent(name)}/webrtc`, {
      method: "POST", body: JSON.stringify(body),
      headers: { "Content-Type": "application/json",
                 ...(token ? { Authorization: `Bearer ${token}` } : {}) } });
  } catch (e) { status("the server cannot be reached: " + e.message, true); leave(); return; }
  if (!r.ok) { status(await refusal(r), true); leave(true); return; }
  const answer = await r.json();
  await pc.setRemoteDescription({ type: "answer", sdp: answer.sdp });
  keepResolution(pc);
  $("session").textContent = name;
  $("join").disabled = true; $("leave").disabled = false;
  status(`sending your camera as ${name}; the tracker is starting…`);
  follow(name);
}

function leave(keepStatus) {
  if (ws) { ws.close(); ws = null; }
  if (pc) { pc.close(); pc = null; }
  if (stream) { for (const t of stream.getTracks()) t.stop(); stream = null; }
  $("join").disabled = false; $("leave").disabled = true;
  if (keepStatus !== true) status("left");
}

$("form").addEventListener("submit", (ev) => { ev.preventDefault(); join($("name").value); });
$("leave").addEventListener("click", () => leave());
$("audio").checked = params.get("audio") === "1";
if (params.get("session")) { $("name").value = params.get("session"); join(params.get("session")); }
