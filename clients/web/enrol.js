// The room's guided enrolment (issue 41, item 2; service/room_enrol.py, docs/ROOM.md): the
// participant's own camera is recorded here with MediaRecorder for RECORD_S seconds while the
// page says what to do (read a text aloud, blink, turn the head each way, smile: what the
// enrolment needs to tell pose from articulation and to calibrate the eyes), the clip is
// uploaded once with their participant token, and the server's enrolment is followed until
// their speaker folder is in place. Why not the WebRTC stream the server already receives: its
// bitrate adapts down (a few hundred kbit/s on a loaded machine, frames dropped), and the
// enrolment's texture and landmarks want every frame at the camera's quality; a local
// recording at 2.5 Mbit/s costs ~8 MB of upload once.

export const RECORD_S = 24; // the enrolment's 20 s minimum plus a margin (the server refuses < 18 s)
export const READ =
  "Papa and Bob ate a big apple pie. Who knew the blue moon would loom so soon? " +
  "Fifi sees three green leaves. Oh, Otto, open wide and say 'ah'. " +
  "We owe you a few cool shoes, and a wide, wide sea.";
// [from s, to s, what to do]: the reading fills the time the other gestures leave
export const STEPS = [
  [0, 9, "Read this aloud, clearly, with your face to the camera"],
  [9, 12, "Blink twice, slowly"],
  [12, 15, "Turn your head slowly to your left, and back"],
  [15, 18, "Now to your right, and back"],
  [18, 21, "Smile broadly, then relax"],
  [21, RECORD_S, "Read on, aloud"],
];

export function step(t) { // what to do t seconds into the recording
  for (const [a, b, what] of STEPS) if (t >= a && t < b) return what;
  return "Done: keep still a moment";
}

function recorderType() {
  const types = ["video/webm;codecs=vp8", "video/webm", "video/mp4"];
  if (typeof MediaRecorder === "undefined") return null;
  for (const t of types) if (MediaRecorder.isTypeSupported(t)) return t;
  return "";
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

// One guided enrolment. `ui`: {step(text), read(text|null), bar(fraction), count(text)};
// `hook`: an object the test reads (state, stage, progress, detail, bytes, type, token: the
// participant's token once enrolled);
// `signal`: an AbortSignal (the cancel button, the page closing). Resolves to the server's
// last status ({state: "done"|"failed"|"cancelled", detail, warnings}).
export async function enrol({ name, token, stream, ui, hook, signal, countdown = 3 }) {
  const url = `/room/api/enrol/${encodeURIComponent(name)}`;
  const headers = { "X-Participant-Token": token };
  const set = (o) => Object.assign(hook, o);
  const type = recorderType();
  if (type === null) return set({ state: "failed", detail: "this browser cannot record its camera (no MediaRecorder)" });
  const video = stream.getVideoTracks();
  if (!video.length) return set({ state: "failed", detail: "no camera: the enrolment needs your face" });
  // -------------------------------------------------------------- the countdown
  set({ state: "countdown", stage: "", progress: 0, detail: "" });
  for (let k = countdown; k > 0; k--) {
    if (signal.aborted) return set({ state: "cancelled", detail: "cancelled" });
    ui.step(`Recording in ${k}…`); ui.read(READ); ui.count(""); await sleep(1000);
  }
  // -------------------------------------------------------------- the recording
  const rec = new MediaRecorder(new MediaStream(video), { mimeType: type || undefined, videoBitsPerSecond: 2500000 });
  const chunks = [];
  rec.ondataavailable = (e) => { if (e.data && e.data.size) chunks.push(e.data); };
  const stopped = new Promise((r) => { rec.onstop = r; });
  set({ state: "recording", type: rec.mimeType });
  rec.start(1000);
  const t0 = performance.now();
  while (!signal.aborted) {
    const t = (performance.now() - t0) / 1000;
    if (t >= RECORD_S) break;
    const what = step(t);
    ui.step(what); ui.read(what.startsWith("Read") ? READ : null);
    ui.bar(t / RECORD_S); ui.count(`recording: ${Math.ceil(RECORD_S - t)} s left`);
    await sleep(200);
  }
  rec.stop(); await stopped;
  ui.read(null);
  if (signal.aborted) return set({ state: "cancelled", detail: "cancelled: nothing was sent" });
  const clip = new Blob(chunks, { type: rec.mimeType || type || "video/webm" });
  // -------------------------------------------------------------- the upload
  set({ state: "uploading", bytes: clip.size });
  ui.step("Sending the clip to the room's server…"); ui.bar(0); ui.count(`${(clip.size / 2 ** 20).toFixed(1)} MB`);
  let r;
  try {
    r = await fetch(url, { method: "POST", body: clip, signal,
      headers: { ...headers, "Content-Type": clip.type.split(";")[0] } });
  } catch (e) {
    return set({ state: signal.aborted ? "cancelled" : "failed",
      detail: signal.aborted ? "cancelled" : "the room's server cannot be reached: " + e.message });
  }
  if (!r.ok) return set({ state: "failed", detail: await detailOf(r) });
  // the name's token once enrolled (bound to the new folder's secret; the old one stops
  // admitting when the folder is in place): the page asks with it from now on
  const bound = (await r.json()).token;
  set({ token: bound });
  headers["X-Participant-Token"] = bound;
  // -------------------------------------------------------------- the server's work
  const started = performance.now();
  while (true) {
    if (signal.aborted) {
      await fetch(url + "/cancel", { method: "POST", headers, keepalive: true }).catch(() => {});
      return set({ state: "cancelled", detail: "cancelled" });
    }
    try {
      r = await fetch(url, { headers, signal });
      if (!r.ok) return set({ state: "failed", detail: await detailOf(r) });
      const job = (await r.json()).job || { state: "failed", detail: "the server forgot the enrolment" };
      set({ state: job.state, stage: job.stage, progress: job.progress, detail: job.detail, warnings: job.warnings });
      const secs = Math.round((performance.now() - started) / 1000);
      if (job.state !== "running") return hook;
      ui.step(`Building your face model: ${job.stage}…`); ui.bar(job.progress);
      ui.count(`${Math.round(100 * job.progress)} % · ${secs} s (about a minute)`);
    } catch (e) {
      if (!signal.aborted) return set({ state: "failed", detail: "the room's server cannot be reached: " + e.message });
    }
    await sleep(500);
  }
}

async function detailOf(r) {
  let d = "";
  try { d = (await r.json()).detail || ""; } catch (e) { /* not JSON */ }
  if (typeof d !== "string") d = JSON.stringify(d);
  return `the room refused the enrolment (${r.status}): ${d}`;
}
