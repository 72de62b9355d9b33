// articast browser avatar: the generic face's upper half, in three.js, so that the generic
// face (the model's sparse or dense mesh, which may stop at the nose) is a closed head with no
// hole: a head (an ellipsoid whose middle is at the eyes, as a face's is, reaching from the
// chin to as far above them; the face mesh lies in front of it), two eyeballs in it whose
// upper lids come down with the stream's closure and whose irises turn with the gaze, and
// brows that rise and fall (mm from the speaker's neutral). Eyes or brows the server says were
// not seen (ok false: a head-mounted camera, a turned head) rest half shut and still, never as
// open eyes looking ahead. Everything is in the head frame (mm: x the speaker's left, y up,
// z towards the viewer) and turns with the face.
import * as THREE from "three";

const EYE_RADIUS = 11.5, EYE_HALF_HEIGHT = 5, IRIS = 5, PUPIL = 2.2; // mm
const EYE_BULGE = 6; // mm of the eyeball in front of the head's surface
const OPEN = Math.asin(EYE_HALF_HEIGHT / EYE_RADIUS); // the lids' edges, from the eye's middle
const SHUT = 2 * OPEN; // how far the upper lid turns down to meet the lower one
const UNSEEN = 0.55; // the closure of eyes the server did not see
// brow ends: x from the face's middle, y above the eye centre (the canonical face's)
const BROW_INNER = [18, 22], BROW_OUTER = [45, 15];
const SKIN = [0.86, 0.66, 0.56];

// Where the eyes sit (head frame): the model's eye centres (MPEG-4 points 3.5, 3.6) when it
// has them; else from its lip corners (8.3, 8.4) as on an average face (MediaPipe's canonical
// face: the eyes 70 mm above and 5 mm behind the corners' middle, ES0 apart, 63 mm by
// default); else above the mesh.
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

function irisTexture() { // the eyeball's colours, equirectangular: the iris where +z points
  const c = document.createElement("canvas"); c.width = 256; c.height = 128;
  const x = c.getContext("2d");
  x.fillStyle = "#eeeae4"; x.fillRect(0, 0, 256, 128);
  const r = 128 * IRIS / EYE_RADIUS / Math.PI, p = 128 * PUPIL / EYE_RADIUS / Math.PI;
  x.fillStyle = "#5a3e2c"; x.beginPath(); x.arc(64, 64, r, 0, 2 * Math.PI); x.fill();
  x.fillStyle = "#111"; x.beginPath(); x.arc(64, 64, p, 0, 2 * Math.PI); x.fill();
  const t = new THREE.CanvasTexture(c);
  t.colorSpace = THREE.NoColorSpace;
  return t;
}

// The generic head (module comment) for a face model: hello.geometry `g`.
export class Head {
  constructor(g) {
    const a = (this.anchors = upperAnchors(g)), m = (this.mean = g.mean);
    let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < m.length; i += 3)
      for (let d = 0; d < 3; d++) { lo[d] = Math.min(lo[d], m[i + d]); hi[d] = Math.max(hi[d], m[i + d]); }
    const eyeY = (a.left[1] + a.right[1]) / 2, eyeZ = (a.left[2] + a.right[2]) / 2;
    const eyeX = Math.abs(a.left[0] - a.right[0]) / 2;
    // the head: its middle at the eyes, from the chin (at most 1.35 times its half width) to as
    // far above; as wide as the face (and
    // wide enough for the eyes); deep as an adult's; its surface just behind the eyes' fronts
    // and behind the face's middle between the eyes and the chin (so that it shows in front)
    const rx = Math.max(1.04 * (hi[0] - lo[0]) / 2, 1.9 * eyeX), ry = Math.min(0.97 * (eyeY - lo[1]), 1.35 * rx);
    const rz = 1.3 * rx, cx = a.cx, cy = eyeY + 0.03 * ry;
    const front = (x, y) => rz * Math.sqrt(Math.max(0, 1 - ((x - cx) / rx) ** 2 - ((y - cy) / ry) ** 2));
    let cz = eyeZ - 3 - front(a.left[0], eyeY);
    for (let i = 0; i < m.length; i += 3)
      if (m[i + 1] < eyeY - 15 && m[i + 1] > cy - 0.6 * ry && Math.abs(m[i] - cx) < 0.5 * rx)
        cz = Math.min(cz, m[i + 2] - 2 - front(m[i], m[i + 1]));
    this.centre = [cx, cy, cz];
    this.radii = [rx, ry, rz];
    this.object = new THREE.Group();
    const skin = new THREE.MeshLambertMaterial({ color: new THREE.Color(...SKIN) });
    const head = new THREE.Mesh(new THREE.SphereGeometry(1, 64, 48), skin);
    head.scale.set(rx, ry, rz); head.position.set(...this.centre);
    this.object.add(head);
    const ball = new THREE.MeshLambertMaterial({ map: irisTexture() });
    const lash = new THREE.MeshLambertMaterial({ color: 0x3a2620 });
    this.eyes = {};
    for (const side of ["left", "right"]) {
      const c = a[side];
      const eye = new THREE.Group(); // the eye's centre of rotation
      // in front of the head's surface and of the face mesh where that reaches the eye
      const z = Math.max(this.surfaceZ(c[0], c[1]) + EYE_BULGE, this.meshFront(m, c[0], c[1], 9) + 2);
      eye.position.set(c[0], c[1], z - EYE_RADIUS);
      const globe = new THREE.Mesh(new THREE.SphereGeometry(EYE_RADIUS, 32, 24), ball);
      globe.rotation.order = "YXZ";
      const upper = new THREE.Group(); // the upper lid, turned down about the eye's centre
      const front = [0, Math.PI]; // phi: the front half (z >= 0)
      upper.add(new THREE.Mesh(new THREE.SphereGeometry(EYE_RADIUS + 0.7, 32, 12, ...front, 0, Math.PI / 2 - OPEN), skin));
      upper.add(new THREE.Mesh(new THREE.SphereGeometry(EYE_RADIUS + 0.8, 32, 2, ...front, Math.PI / 2 - OPEN - 0.09, 0.09), lash));
      const lower = new THREE.Mesh(new THREE.SphereGeometry(EYE_RADIUS + 0.6, 32, 12, ...front, Math.PI / 2 + OPEN, Math.PI / 2 - OPEN), skin);
      eye.add(globe, upper, lower);
      this.object.add(eye);
      this.eyes[side] = { globe, upper };
    }
    this.browMaterial = new THREE.MeshLambertMaterial({ color: 0x3b2a22 });
    this.brows = {}; this.browKey = "";
    this.update(null, null);
  }
  meshFront(m, x, y, r) { // the face mesh's most forward z within r mm of (x, y)
    let z = -Infinity;
    for (let i = 0; i < m.length; i += 3)
      if ((m[i] - x) ** 2 + (m[i + 1] - y) ** 2 < r * r) z = Math.max(z, m[i + 2]);
    return z;
  }
  surfaceZ(x, y) { // the head's front at (x, y), head frame
    const [cx, cy, cz] = this.centre, [rx, ry, rz] = this.radii;
    return cz + rz * Math.sqrt(Math.max(0, 1 - ((x - cx) / rx) ** 2 - ((y - cy) / ry) ** 2));
  }
  // one frame: eyes = the frame's `eyes` block (or null), brows = its `brows` block (or null)
  update(eyes, brows) {
    const seen = !!(eyes && eyes.ok), browsSeen = !!(brows && brows.ok);
    for (const side of ["left", "right"]) {
      const e = this.eyes[side];
      const closure = seen ? Math.min(1, Math.max(0, eyes[`closure_${side}`] || 0)) : UNSEEN;
      e.upper.rotation.x = closure * SHUT;
      const yaw = seen ? (eyes.gaze_yaw_deg || 0) * Math.PI / 180 : 0;
      const pitch = seen ? (eyes.gaze_pitch_deg || 0) * Math.PI / 180 : 0;
      e.globe.rotation.set(-pitch, yaw, 0);
    }
    const raise = (k) => (browsSeen ? brows[k] || 0 : 0);
    const r = ["inner_left", "outer_left", "inner_right", "outer_right"].map((k) => raise(`raise_${k}_mm`));
    const key = r.map((v) => v.toFixed(1)).join();
    if (key === this.browKey) return;
    this.browKey = key;
    const a = this.anchors;
    for (const [i, side] of [[0, "left"], [2, "right"]]) {
      const sign = side === "left" ? 1 : -1, c = a[side];
      const on = (x, y, lift) => new THREE.Vector3(x, y, Math.max(this.surfaceZ(x, y), this.meshFront(this.mean, x, y, 6)) + lift);
      const inner = on(a.cx + sign * BROW_INNER[0], c[1] + BROW_INNER[1] + r[i], 1.5);
      const outer = on(a.cx + sign * BROW_OUTER[0], c[1] + BROW_OUTER[1] + r[i + 1], 1.5);
      const mx = (inner.x + outer.x) / 2, my = (inner.y + outer.y) / 2 + 3;
      const curve = new THREE.CatmullRomCurve3([inner, on(mx, my, 1.5), outer]);
      const old = this.brows[side];
      if (old) { this.object.remove(old); old.geometry.dispose(); }
      const brow = new THREE.Mesh(new THREE.TubeGeometry(curve, 16, 2.2, 6, false), this.browMaterial);
      this.brows[side] = brow; this.object.add(brow);
    }
  }
}
