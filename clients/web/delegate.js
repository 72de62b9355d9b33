// The speaker's own face (their delegate), in three.js: the full-face mesh moved linearly by
// the streamed articulatory parameters (x = mean + sum_k alpha_k basis_k) and textured with
// their own texture, itself linear in the parameters (T = T0 + sum_k alpha_k T_k: the inner
// mouth and teeth appear as the jaw opens), lit softly over the lighting the texture already
// carries. Its eyes are the speaker's own, painted in the texture: the lids close on a blink
// and the eyes move with the gaze by moving the mesh's own lid and eye vertices (the
// `upper` targets the server sends: the VRM export's eyeBlink, eyeLook*, eyeWide, eyeSquint
// and brow shapes), weighted as the stream's ARKit eye and brow shapes are
// (core/outputs/upper.py: arkitUpper below). Nothing is drawn over them.
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
void main() {
  vec3 c = texture2D(tex, vuv).rgb;
  vec2 t = clamp(vuv, inset, 1.0 - inset);
  for (int i = 0; i < ${MAX_MODES}; i++) {
    if (i >= k) break;
    float col = mod(float(i), grid.x), row = floor(float(i) / grid.x);
    c += alpha[i] * (texture2D(modes, (vec2(col, row) + t) / grid).rgb - 128.0 / 255.0) * scale;
  }
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
                  inset: { value: 0.5 / tex.width } } });
    this.object = new THREE.Mesh(g, this.material);
    this.update(new Array(this.k).fill(0), null, null);
  }
  // the shape at alpha, its lids, eyes and brows as the frame's blocks say, its normals
  update(alpha, eyes, brows) {
    for (let k = 0; k < MAX_MODES; k++) this.alpha[k] = k < this.k ? alpha[k] || 0 : 0;
    const pos = this.position.array;
    linear(pos, this.mean, this.basis, alpha, this.k);
    this.weights = this.upper ? arkitUpper(eyes, brows, this.upper) : {};
    for (const [name, w] of Object.entries(this.weights)) {
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
