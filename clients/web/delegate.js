// The speaker's own face (their delegate), in three.js: the full-face mesh moved linearly by
// the streamed articulatory parameters (x = mean + sum_k alpha_k basis_k) and textured with
// their own texture, itself linear in the parameters (T = T0 + sum_k alpha_k T_k: the inner
// mouth and teeth appear as the jaw opens), lit softly over the lighting the texture already
// carries. Its eyes are the speaker's own, painted in the texture: the fragment shader shuts
// them on a blink (the lid's own skin, from the texture around the eye, comes down over the
// opening) and slides the painted eye within its opening with the gaze (eyeLids below); the
// mesh's wide, squint and brow shapes move its vertices (the `upper` targets the server
// sends: the VRM export's), weighted as the stream's ARKit eye and brow shapes are
// (core/outputs/upper.py: arkitUpper below). A mesh other than MediaPipe's 468 points keeps
// the vertex lids (eyeBlink, eyeLook*). Nothing is drawn over the eyes.
// Fetched once per hello from hello.delegate_url with the page's token
// (GET /api/sessions/NAME/delegate, service/delegate.py documents the JSON).
import * as THREE from "three";
import { linear } from "./face.js";

const MAX_MODES = 8;
const VS = `varying vec3 vn; varying vec2 vuv;
void main() { vn = normalize(normalMatrix * normal); vuv = uv;
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0); }`;
const FS = `varying vec3 vn; varying vec2 vuv;
uniform sampler2D tex; uniform sampler2D modes; uniform float alpha[${MAX_MODES}];
uniform vec2 grid; uniform float scale; uniform int k; uniform float inset;
// the eyes (eyeLids below): per eye its opening in the texture (an ellipse: centre, half axes),
// the lid's colour (above, below), how shut it is and where its iris looks (texture units)
uniform vec2 eyeC[2]; uniform vec2 eyeR[2]; uniform vec3 lidCol[2]; uniform vec3 lidLow[2]; uniform float shut[2];
uniform vec2 look[2];
vec3 at(vec2 uv) {
  vec3 c = texture2D(tex, uv).rgb;
  vec2 t = clamp(uv, inset, 1.0 - inset);
  for (int i = 0; i < ${MAX_MODES}; i++) {
    if (i >= k) break;
    float col = mod(float(i), grid.x), row = floor(float(i) / grid.x);
    c += alpha[i] * (texture2D(modes, (vec2(col, row) + t) / grid).rgb - 128.0 / 255.0) * scale;
  }
  return c;
}
void main() {
  vec2 uv = vuv;
  float lid = 0.0; vec3 lc = vec3(0.0);
  for (int e = 0; e < 2; e++) {
    vec2 q = (vuv - eyeC[e]) / eyeR[e];
    float r = length(q);
    // the iris follows the gaze: the painted eye slides within its opening, less towards the
    // rim and not past it (the slide's gradient stays under 1: no fold)
    // (each way by its own axis: the same shift along a row, so the iris keeps its shape)
    uv -= look[e] * vec2(clamp(1.0 - q.x * q.x, 0.0, 1.0) * (1.0 - smoothstep(0.8, 1.2, abs(q.y))),
                         clamp(1.0 - q.y * q.y, 0.0, 1.0) * (1.0 - smoothstep(0.8, 1.2, abs(q.x))));
    // the upper lid comes down over the opening (v grows downwards): above its edge the lid's
    // skin; shut, the whole opening and its rim, with the lashes' line low on it
    float edge = -1.3 + 2.7 * shut[e], rim = 1.0 - smoothstep(0.9, 1.25, r);
    float cover = rim * (1.0 - smoothstep(edge - 0.15, edge, q.y));
    float line = min(edge, 0.7);
    float lash = smoothstep(line - 0.3, line - 0.1, q.y) * (1.0 - smoothstep(line - 0.1, line + 0.05, q.y));
    lid = max(lid, cover); lc += cover * mix(lidCol[e], lidLow[e], smoothstep(-1.0, 1.0, q.y)) * (1.0 - 0.35 * lash * step(0.05, shut[e]));
  }
  vec3 c = at(uv);
  if (lid > 0.0) c = mix(c, lc / max(lid, 1e-3), lid);
  float d = abs(dot(normalize(vn), normalize(vec3(-0.3, 0.4, 1.0))));
  gl_FragColor = vec4(clamp(c, 0.0, 1.0) * (0.8 + 0.25 * d), 1.0);
}`;

function image(url) {
  return new Promise((resolve, reject) => {
    const img = new Image(); img.onload = () => resolve(img); img.onerror = reject; img.src = url;
  });
}
function texture(img) {
  const t = new THREE.Texture(img);
  t.flipY = false; // uv v down, the image's rows
  t.colorSpace = THREE.NoColorSpace; t.generateMipmaps = false;
  t.minFilter = THREE.LinearFilter; t.magFilter = THREE.LinearFilter;
  t.wrapS = t.wrapT = THREE.ClampToEdgeWrapping; t.needsUpdate = true;
  return t;
}
const clamp01 = (x) => Math.min(1, Math.max(0, x));

// MediaPipe's 468-point face mesh (the delegate's): each eye's lid contour, upper then lower
// (core/delegate/vrm.py's _EYES), the speaker's left first
const EYE_RINGS = [[466, 388, 387, 386, 385, 384, 398, 263, 249, 390, 373, 374, 380, 381, 382, 362],
  [246, 161, 160, 159, 158, 157, 173, 33, 7, 163, 144, 145, 153, 154, 155, 133]];
const GAZE_FULL_DEG = 30; // the stream's full look (core/outputs/upper.py)
const LOOK = [0.35, 0.3]; // how far a full look slides the painted eye, of the half axes
// The eyes in the texture (null for another mesh): per eye the ellipse around its lid
// contour in texture units (grown a little: the painted eye reaches past the landmarks), the
// colour of the lid (the skin just above the eye, median), and how texture u, v go with the
// head frame's x, y (for the gaze's direction).
function eyeLids(d, img) {
  if (d.n_vertices !== 468) return null;
  const c = document.createElement("canvas"); c.width = img.width; c.height = img.height;
  const g = c.getContext("2d", { willReadFrequently: true }); g.drawImage(img, 0, 0);
  const px = g.getImageData(0, 0, c.width, c.height).data;
  const eyes = EYE_RINGS.map((ring) => {
    const us = ring.map((i) => d.uv[2 * i]), vs = ring.map((i) => d.uv[2 * i + 1]);
    const u0 = Math.min(...us), u1 = Math.max(...us), v0 = Math.min(...vs), v1 = Math.max(...vs);
    const centre = [(u0 + u1) / 2, (v0 + v1) / 2], half = [0.56 * (u1 - u0), 0.7 * (v1 - v0)];
    const median = (a) => (a.sort((p, q) => p - q), a[a.length >> 1] ?? 0.7);
    const skin = (lifts) => { // the texture's median colour on rows this far above the middle
      const col = [[], [], []];
      for (let t = -0.6; t <= 0.6; t += 0.05) for (const lift of lifts) {
        const x = Math.round((centre[0] + t * half[0]) * c.width), y = Math.round((centre[1] - lift * half[1]) * c.height);
        if (x < 0 || y < 0 || x >= c.width || y >= c.height) continue;
        for (let ch = 0; ch < 3; ch++) col[ch].push(px[4 * (y * c.width + x) + ch] / 255);
      }
      return col.map(median);
    };
    const x = ring.reduce((s, i) => s + d.mean[3 * i], 0) / ring.length;
    const y = ring.reduce((s, i) => s + d.mean[3 * i + 1], 0) / ring.length;
    return { centre, half, colour: skin([1.5, 1.7, 1.9]), low: skin([-1.5, -1.7, -1.9]), x, y, u: centre[0], v: centre[1] };
  });
  const [l, r] = eyes;
  const su = Math.sign((l.u - r.u) / (l.x - r.x)) || 1; // u per x (the eyes side by side)
  let sv = 0; // v per y: from the ring's own spread (upper lid above the lower)
  for (const ring of EYE_RINGS) sv += (d.uv[2 * ring[3] + 1] - d.uv[2 * ring[11] + 1]) * (d.mean[3 * ring[3] + 1] - d.mean[3 * ring[11] + 1]);
  return { eyes, su, sv: Math.sign(sv) || -1 };
}

// ARKit eye and brow weights of a frame's `eyes` and `brows` blocks (core/outputs/upper.py's
// arkit_upper, with the full scales `u` the server sends): only what was seen.
export function arkitUpper(eyes, brows, u) {
  const out = {};
  if (eyes && eyes.ok && eyes.closure_left != null && eyes.closure_right != null) {
    out.eyeBlinkLeft = clamp01(eyes.closure_left); out.eyeBlinkRight = clamp01(eyes.closure_right);
    const yaw = eyes.gaze_yaw_deg || 0, pitch = eyes.gaze_pitch_deg || 0;
    const toLeft = clamp01(yaw / u.gaze_full_deg), toRight = clamp01(-yaw / u.gaze_full_deg);
    const up = clamp01(pitch / u.gaze_full_deg), down = clamp01(-pitch / u.gaze_full_deg);
    Object.assign(out, { eyeLookOutLeft: toLeft, eyeLookInRight: toLeft, eyeLookInLeft: toRight,
      eyeLookOutRight: toRight, eyeLookUpLeft: up, eyeLookUpRight: up, eyeLookDownLeft: down,
      eyeLookDownRight: down });
    for (const side of ["Left", "Right"]) {
      const wide = eyes[`wide_${side.toLowerCase()}`], lower = eyes[`lower_lid_${side.toLowerCase()}`];
      if (wide != null) out[`eyeWide${side}`] = clamp01((wide - u.wide_dead) / u.wide_full);
      if (lower != null) out[`eyeSquint${side}`] = clamp01(lower / u.squint_full);
    }
  }
  if (brows && brows.ok && brows.raise_inner_left_mm != null) {
    out.browInnerUp = clamp01((brows.raise_inner_left_mm + brows.raise_inner_right_mm) / 2 / u.brow_full_mm);
    out.browOuterUpLeft = clamp01(brows.raise_outer_left_mm / u.brow_full_mm);
    out.browOuterUpRight = clamp01(brows.raise_outer_right_mm / u.brow_full_mm);
    out.browDownLeft = clamp01(-brows.raise_inner_left_mm / u.brow_down_full_mm);
    out.browDownRight = clamp01(-brows.raise_inner_right_mm / u.brow_down_full_mm);
  }
  return out;
}

export class Delegate {
  constructor(d, tex, modes) {
    this.k = Math.min(d.param_names.length, MAX_MODES);
    this.mean = Float32Array.from(d.mean); this.basis = Float32Array.from(d.basis);
    this.m = d.n_vertices; this.upper = d.upper || null; this.weights = {};
    const g = (this.geometry = new THREE.BufferGeometry());
    this.position = new THREE.BufferAttribute(new Float32Array(this.mean.length), 3);
    this.position.setUsage(THREE.DynamicDrawUsage);
    g.setAttribute("position", this.position);
    g.setAttribute("uv", new THREE.Float32BufferAttribute(d.uv, 2));
    g.setIndex(Array.from(d.triangles));
    this.alpha = new Array(MAX_MODES).fill(0);
    this.material = new THREE.ShaderMaterial({
      vertexShader: VS, fragmentShader: FS, side: THREE.DoubleSide,
      uniforms: { tex: { value: texture(tex) }, modes: { value: texture(modes) },
                  alpha: { value: this.alpha }, grid: { value: new THREE.Vector2(...d.modes_grid) },
                  scale: { value: d.modes_scale }, k: { value: this.k },
                  inset: { value: 0.5 / tex.width },
                  eyeC: { value: [new THREE.Vector2(-9, -9), new THREE.Vector2(-9, -9)] },
                  eyeR: { value: [new THREE.Vector2(1, 1), new THREE.Vector2(1, 1)] },
                  lidCol: { value: [new THREE.Vector3(), new THREE.Vector3()] },
                  lidLow: { value: [new THREE.Vector3(), new THREE.Vector3()] },
                  shut: { value: [0, 0] }, look: { value: [new THREE.Vector2(), new THREE.Vector2()] } } });
    this.lids = eyeLids(d, tex);
    if (this.lids) this.lids.eyes.forEach((e, i) => {
      this.material.uniforms.eyeC.value[i].set(...e.centre);
      this.material.uniforms.eyeR.value[i].set(...e.half);
      this.material.uniforms.lidCol.value[i].set(...e.colour);
      this.material.uniforms.lidLow.value[i].set(...e.low);
    });
    this.object = new THREE.Mesh(g, this.material);
    this.update(new Array(this.k).fill(0), null, null);
  }
  // the shape at alpha, its lids, eyes and brows as the frame's blocks say, its normals
  update(alpha, eyes, brows) {
    for (let k = 0; k < MAX_MODES; k++) this.alpha[k] = k < this.k ? alpha[k] || 0 : 0;
    const pos = this.position.array;
    linear(pos, this.mean, this.basis, alpha, this.k);
    this.weights = this.upper ? arkitUpper(eyes, brows, this.upper) : {};
    this.eyesShown(eyes);
    for (const [name, w] of Object.entries(this.weights)) {
      // with the eyes in the texture (eyeLids), the lids and irises are drawn there: the
      // mesh's lid and eye vertices do not squash the painted eye into a slit
      if (this.lids && name.startsWith("eyeBlink") || this.lids && name.startsWith("eyeLook")) continue;
      const t = this.upper.targets[name];
      if (!t || !w) continue;
      for (let j = 0; j < t.index.length; j++) {
        const i = 3 * t.index[j];
        pos[i] += w * t.delta[3 * j]; pos[i + 1] += w * t.delta[3 * j + 1]; pos[i + 2] += w * t.delta[3 * j + 2];
      }
    }
    this.position.needsUpdate = true;
    this.geometry.computeVertexNormals();
    this.geometry.computeBoundingSphere();
  }
  // the lids' closure and the irises' look of a frame's eyes block: what the server saw (eyes
  // it did not see are left as they were drawn last)
  eyesShown(eyes) {
    const u = this.material.uniforms;
    if (!this.lids || !eyes || !eyes.ok || eyes.closure_left == null) return;
    const full = (this.upper && this.upper.gaze_full_deg) || GAZE_FULL_DEG;
    const yaw = Math.max(-1, Math.min(1, (eyes.gaze_yaw_deg || 0) / full));
    const pitch = Math.max(-1, Math.min(1, (eyes.gaze_pitch_deg || 0) / full));
    // yaw > 0: towards the speaker's left (+x); pitch > 0: up (+y)
    this.lids.eyes.forEach((e, i) => {
      u.shut.value[i] = clamp01(i === 0 ? eyes.closure_left : eyes.closure_right);
      u.look.value[i].set(this.lids.su * yaw * LOOK[0] * e.half[0], this.lids.sv * pitch * LOOK[1] * e.half[1]);
    });
    this.shut = [...u.shut.value];
  }
  dispose() {
    this.geometry.dispose(); this.material.dispose();
    this.material.uniforms.tex.value.dispose(); this.material.uniforms.modes.value.dispose();
  }
}

// The delegate of a hello (null when the session offers none): fetched with the page's token.
export async function loadDelegate(url, headers) {
  if (!url) return null;
  const r = await fetch(url, { headers, cache: "no-store" });
  if (!r.ok) throw new Error(`delegate: HTTP ${r.status}`);
  const d = await r.json();
  const [tex, modes] = await Promise.all([image(d.texture), image(d.modes)]);
  return new Delegate(d, tex, modes);
}
