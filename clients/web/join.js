// The participant page: the webcam (getUserMedia) sent to the server over WebRTC as session
// NAME (POST /api/sessions/NAME/webrtc with the SDP offer, the token as for the other API
// routes), and that session's tracked frames followed over the WebSocket. Every refusal is
// said on the page in one line: a denied or missing camera, an insecure page, a refused
// token, offer or name, a connection that failed.
import { keepResolution } from "./connect.js";

const params = new URLSearchParams(location.search);
const token = params.get("token");
const $ = (id) => document.getElementById(id);
const state = { status: "", final: "", connection: "", frames: 0, ok: 0, apertures: [],
                rejoined: [] };
window.articastJoin = state; // for tests and the curious

// A dropped session (its video or connection ended, the session failed: the server's media
// process died, the network blinked) is joined again by itself after 2, 4, 8, 16 s while the
// failure is transient (unreachable, 409 while the old session ends, 429, 5xx), at most
// MAX_REJOINS times in a row (the count starts again after a minute joined). "leave" stops
// it; a session the server stopped on purpose ("stopped": removed by its operator) and a
// refusal (token, camera, offer) are not retried. As the room page does (room.js).
const REJOIN_MS = 2000, MAX_REJOINS = 4, STEADY_MS = 60000;
let rejoins = 0, rejoinTimer = null, joinedAt = 0, joinedAs = "";

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
      else if (m.state === "ended" || m.state === "failed") dropped(`session ${m.state}: ${m.detail}`);
      else if (m.state === "stopped") { // its operator stopped it: stay out
        status(`session stopped: ${m.detail}`, true); leave(true);
      } else if (["unavailable", "stalled", "restarting"].includes(m.state))
        status(`session ${m.state}: ${m.detail}`, true);
      else status(`session ${m.state}: ${m.detail}`);
    } else if (m.type === "error") {
      status("the server said: " + m.reason, true);
    }
  };
}

function dropped(why) { // the session went without the participant choosing it
  if (!joinedAs) return; // already dropped, or left
  const name = joinedAs;
  status(why, true);
  leave(true);
  rejoinLater(why, name);
}

function rejoinLater(why, name) {
  if (performance.now() - joinedAt > STEADY_MS) rejoins = 0;
  if (rejoins >= MAX_REJOINS) {
    status(`${why}; it failed ${rejoins} times in a row: join again when your network is steady`, true);
    return;
  }
  const delay = REJOIN_MS * 2 ** rejoins++;
  status(`${why}: joining again in ${(delay / 1000).toFixed(0)} s…`);
  state.rejoined.push({ reason: why, delayMs: delay, okBefore: state.ok });
  $("join").disabled = true; $("leave").disabled = false; // (leave: stay out)
  rejoinTimer = setTimeout(async () => {
    rejoinTimer = null;
    if ((await join(name)) === "retry") rejoinLater(state.final || why, name);
  }, delay);
}

// join(name) resolves to "joined", "retry" (a transient failure) or "refused"
async function join(name) {
  state.final = "";
  if (!window.isSecureContext || !navigator.mediaDevices) {
    status("the camera needs a secure page: open this page over https:// (or on localhost)", true);
    return "refused";
  }
  status("asking for the camera…");
  try {
    stream = await navigator.mediaDevices.getUserMedia({
      video: { width: { ideal: 640 }, height: { ideal: 480 }, frameRate: { ideal: 30 } },
      audio: $("audio").checked });
  } catch (e) { status(cameraProblem(e), true); return "refused"; }
  $("self").srcObject = stream;
  pc = new RTCPeerConnection({ iceServers: [] }); // loopback and LAN: no STUN/TURN needed
  // the tracker needs the resolution its camera was calibrated for: short of CPU or bandwidth,
  // the browser is to lower the frame rate, not the resolution (Chromium's fake camera went
  // to 480x360 and 320x240 without this: benchmarks/fake_camera.py)
  for (const track of stream.getTracks()) {
    if (track.kind === "video") track.contentHint = "detail";
    pc.addTrack(track, stream);
  }
  const mine = pc;
  pc.onconnectionstatechange = () => {
    if (pc !== mine) return; // an old connection closing after a rejoin
    state.connection = pc.connectionState;
    $("connection").textContent = pc.connectionState;
    if (pc.connectionState === "failed")
      dropped("the connection to the server failed (a network between you may need TURN)");
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
  } catch (e) { status("the server cannot be reached: " + e.message, true); leave(true); return "retry"; }
  if (!r.ok) {
    status(await refusal(r), true); leave(true);
    return [409, 429].includes(r.status) || r.status >= 500 ? "retry" : "refused";
  }
  const answer = await r.json();
  await pc.setRemoteDescription({ type: "answer", sdp: answer.sdp });
  keepResolution(pc);
  $("session").textContent = name;
  $("join").disabled = true; $("leave").disabled = false;
  status(`sending your camera as ${name}; the tracker is starting…`);
  joinedAs = name; joinedAt = performance.now();
  follow(name);
  return "joined";
}

function leave(keepStatus) {
  joinedAs = "";
  if (rejoinTimer && keepStatus !== true) { clearTimeout(rejoinTimer); rejoinTimer = null; } // the button: stay out
  if (ws) { const w = ws; ws = null; w.onmessage = null; w.close(); }
  if (pc) { pc.close(); pc = null; state.connection = "closed"; $("connection").textContent = "closed"; }
  if (stream) { for (const t of stream.getTracks()) t.stop(); stream = null; }
  $("join").disabled = false; $("leave").disabled = true;
  if (keepStatus !== true) status("left");
}

$("form").addEventListener("submit", (ev) => { ev.preventDefault(); join($("name").value); });
$("leave").addEventListener("click", () => leave());
$("audio").checked = params.get("audio") === "1";
if (params.get("session")) { $("name").value = params.get("session"); join(params.get("session")); }
