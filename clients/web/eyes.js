// articast browser avatar: the upper face above the tracked lips: two eyes that blink (the
// upper lid comes down with the closure) and look (the iris moves with the gaze), and brows
// that rise and fall (mm from the speaker's neutral), drawn on a 2D canvas laid over the WebGL
// view with the face mesh's own projection, so they turn with the head. Eyes or brows the
// server says were not seen (ok false: a head-mounted camera, a turned head) are drawn faint
// and still, never as open eyes looking ahead. No dependencies.

const EYE_HALF_WIDTH = 13, EYE_HALF_HEIGHT = 5, IRIS = 5, EYE_RADIUS = 11.5; // mm
// brow ends: x from the face's middle, y above the eye centre (the canonical face's)
const BROW_INNER = [18, 22], BROW_OUTER = [45, 15];

// Where the eyes sit (head frame, mm: x the speaker's left, y up, z towards the viewer): the
// model's eye centres (MPEG-4 points 3.5, 3.6) when it has them; else from its lip corners
// (8.3, 8.4) as on an average face (MediaPipe's canonical face: the eyes 70 mm above and 5 mm
// behind the corners' middle, ES0 apart, 63 mm by default); else above the mesh.
export function upperAnchors(g) {
  const fp = g.feature_points || {}, m = g.mean;
  const at = (name) => (name in fp ? [m[3 * fp[name]], m[3 * fp[name] + 1], m[3 * fp[name] + 2]] : null);
  let left = at("3.5"), right = at("3.6");
  if (!left || !right) {
    const a = at("8.3"), b = at("8.4"), half = ((g.fapu_overrides || {}).ES0 || 63) / 2;
    let c;
    if (a && b) c = [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2 + 70, (a[2] + b[2]) / 2 - 5];
    else {
      let top = -Infinity, front = -Infinity, cx = 0;
      for (let i = 0; i < m.length; i += 3) { cx += 3 * m[i] / m.length; top = Math.max(top, m[i + 1]); front = Math.max(front, m[i + 2]); }
      c = [cx, top + 18, front - 22];
    }
    left = [c[0] + half, c[1], c[2]]; right = [c[0] - half, c[1], c[2]];
  }
  return { left, right, cx: (left[0] + right[0]) / 2 };
}

function project(mvp, p, w, h) { // column-major mvp, head-frame point -> canvas px
  const x = mvp[0] * p[0] + mvp[4] * p[1] + mvp[8] * p[2] + mvp[12];
  const y = mvp[1] * p[0] + mvp[5] * p[1] + mvp[9] * p[2] + mvp[13];
  const q = mvp[3] * p[0] + mvp[7] * p[1] + mvp[11] * p[2] + mvp[15];
  return [(x / q + 1) * w / 2, (1 - y / q) * h / 2];
}

function path(ctx, mvp, pts, w, h, close) {
  ctx.beginPath();
  pts.forEach((p, i) => { const [u, v] = project(mvp, p, w, h); if (i) ctx.lineTo(u, v); else ctx.moveTo(u, v); });
  if (close) ctx.closePath();
}

function ellipse(c, rx, ry, n = 24, from = 0, to = 2 * Math.PI) {
  const out = [];
  for (let i = 0; i <= n; i++) {
    const t = from + (to - from) * i / n;
    out.push([c[0] + rx * Math.cos(t), c[1] + ry * Math.sin(t), c[2]]);
  }
  return out;
}

// One frame: eyes = the frame's `eyes` block (or null), brows = its `brows` block (or null).
export function drawUpper(canvas, mvp, anchors, eyes, brows) {
  const w = canvas.clientWidth || canvas.width, h = canvas.clientHeight || canvas.height;
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, w, h);
  if (!anchors) return;
  const seen = !!(eyes && eyes.ok), browsSeen = !!(brows && brows.ok);
  for (const side of ["left", "right"]) {
    const c = anchors[side], sign = side === "left" ? 1 : -1;
    const closure = seen ? Math.min(1, Math.max(0, eyes[`closure_${side}`] || 0)) : 0;
    ctx.globalAlpha = seen ? 1 : 0.25;
    // the eye's opening: an almond whose upper lid comes down with the closure
    const open = EYE_HALF_HEIGHT * (1 - closure);
    const lower = ellipse(c, EYE_HALF_WIDTH, EYE_HALF_HEIGHT, 16, 0, Math.PI).map(([x, y, z]) => [x, 2 * c[1] - y, z]);
    const upper = ellipse(c, EYE_HALF_WIDTH, 2 * open - EYE_HALF_HEIGHT, 16, Math.PI, 0);
    const almond = [...lower, ...upper.slice(1)];
    path(ctx, mvp, almond, w, h, true);
    ctx.fillStyle = "#eeeae4"; ctx.fill();
    if (seen && closure < 0.95) { // the iris where the gaze points, clipped by the lids
      ctx.save(); path(ctx, mvp, almond, w, h, true); ctx.clip();
      const yaw = (eyes.gaze_yaw_deg || 0) * Math.PI / 180, pitch = (eyes.gaze_pitch_deg || 0) * Math.PI / 180;
      const ic = [c[0] + EYE_RADIUS * Math.sin(yaw), c[1] + EYE_RADIUS * Math.sin(pitch), c[2] + 1];
      path(ctx, mvp, ellipse(ic, IRIS, IRIS), w, h, true);
      ctx.fillStyle = "#4a3426"; ctx.fill();
      path(ctx, mvp, ellipse(ic, IRIS * 0.45, IRIS * 0.45), w, h, true);
      ctx.fillStyle = "#111"; ctx.fill();
      ctx.restore();
    }
    path(ctx, mvp, almond, w, h, true);
    ctx.strokeStyle = "#5a3a30"; ctx.lineWidth = 2; ctx.stroke();
    // the brow: inner and outer ends raised by their mm from the neutral
    ctx.globalAlpha = browsSeen ? 1 : 0.25;
    const ri = browsSeen ? brows[`raise_inner_${side}_mm`] || 0 : 0;
    const ro = browsSeen ? brows[`raise_outer_${side}_mm`] || 0 : 0;
    const cx = anchors.cx;
    const inner = [cx + sign * BROW_INNER[0], c[1] + BROW_INNER[1] + ri, c[2] + 4];
    const outer = [cx + sign * BROW_OUTER[0], c[1] + BROW_OUTER[1] + ro, c[2] - 2];
    const mid = [(inner[0] + outer[0]) / 2, (inner[1] + outer[1]) / 2 + 3, c[2] + 3];
    path(ctx, mvp, [inner, mid, outer], w, h, false);
    ctx.strokeStyle = "#3b2a22"; ctx.lineWidth = 6; ctx.lineCap = "round"; ctx.stroke();
  }
  ctx.globalAlpha = 1;
}
