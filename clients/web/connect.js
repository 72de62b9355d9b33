// What every page of the service needs to reach a session: the token from the page's URL,
// the session to follow, and why the server refused (shared by avatar.js and vrm.js).
export const params = new URLSearchParams(location.search);
// the server's token, if it has one, comes in this page's URL (?token=...) and goes on
export const token = params.get("token");
export const authHeaders = token ? { Authorization: `Bearer ${token}` } : {};
export function withToken(url) { // the WebSocket's (a browser sends no header there)
  if (!token) return url;
  return url + (url.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token);
}
export function socketUrl() { // the one place the WebSocket URL is built
  const proto = location.protocol === "https:" ? "wss" : "ws";
  return withToken(params.get("ws") || `${proto}://${location.host}/ws`);
}
export const TOKEN_FIX = "this server needs a token: open this page with &token=TOKEN in its URL " +
  "(the server's ARTICAST_TOKEN or --token-file)";
// a token was given and refused: it is wrong, not missing (issue 39)
const WRONG_TOKEN = "the server refused this page's token: it is not the server's; open this " +
  "page with the right one, &token=TOKEN in its URL (the server's ARTICAST_TOKEN or --token-file)";

export async function refusal() { // why the server would not let us in, if it says so (else "")
  try {
    const r = await fetch("/api/sessions", { headers: authHeaders });
    if (r.status === 401) return token ? WRONG_TOKEN : TOKEN_FIX;
    if (r.status === 429) return "the server refused this page's token too often: open this page " +
      "with the right one, &token=TOKEN in its URL (the server's ARTICAST_TOKEN or --token-file); " +
      "then wait a minute";
    if (r.status === 403) return "the server refused this page: " + ((await r.json()).detail || "forbidden");
  } catch (e) { /* unreachable: a network problem, retried */ }
  return "";
}

export async function chooseSession() { // ?session=NAME, else the server's first session
  if (params.get("session")) return params.get("session");
  const r = await fetch("/api/sessions", { headers: authHeaders });
  if ([401, 403, 429].includes(r.status)) throw new Error("refused");
  const list = await r.json();
  if (!list.length) throw new Error("the server has no session");
  return list[0].name;
}

export function noteLatency(state, frame) { // end to end: captured on the server -> drawn here
  // (same host, or NTP-synced hosts); kept for the page's readout and the tests
  const ms = Math.max(0, Date.now() - frame.t_capture * 1000);
  state.latencyMs = ms; state.latencies.push(ms);
  if (state.latencies.length > 20000) state.latencies.splice(0, 10000);
  return ms;
}

export function noteDraw(state, t0) { // the page's own time (ms, CPU) to apply and draw a frame
  // (benchmarks/page_latency.py compares the pages by it, beside the latency)
  const ms = performance.now() - t0;
  (state.drawMs = state.drawMs || []).push(ms);
  if (state.drawMs.length > 20000) state.drawMs.splice(0, 10000);
}

export function keepResolution(pc, maxFps = 0) { // a camera sent over WebRTC keeps its resolution under load
  // (Chromium lowers it by default: the tracker reads lips better from more pixels); with
  // maxFps, no more frames a second than that: the server decodes every frame it receives and
  // its tracker takes fewer (the room: the server's max_fps). One setParameters call: a
  // second one before the first settles is refused. Resolves to the sender's frame-rate cap.
  const done = [];
  for (const sender of pc.getSenders()) {
    if (!sender.track || sender.track.kind !== "video") continue;
    const p = sender.getParameters();
    p.degradationPreference = "maintain-resolution";
    if (maxFps > 0 && p.encodings && p.encodings.length) p.encodings[0].maxFramerate = maxFps;
    done.push(sender.setParameters(p).then(() => {
      const e = sender.getParameters().encodings; return e && e.length ? e[0].maxFramerate || 0 : 0;
    }).catch(() => 0 /* older browser: contentHint says the same; no cap */));
  }
  return Promise.all(done).then((caps) => caps[0] || 0);
}
