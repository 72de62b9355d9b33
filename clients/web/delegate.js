// The speaker's own face (their delegate): the full-face mesh moved linearly by the streamed
// articulatory parameters (x = mean + sum_k alpha_k basis_k) and textured with their own
// texture, itself linear in the parameters (T = T0 + sum_k alpha_k T_k: the inner mouth and
// teeth appear as the jaw opens), lit softly over the lighting the texture already carries.
// Fetched once per hello from hello.delegate_url with the page's token
// (GET /api/sessions/NAME/delegate, service/delegate.py documents the JSON).

import { faceNormals, morph, normalise3 } from "./math.js";

const VS = `attribute vec3 p; attribute vec3 n; attribute vec2 uv; uniform mat4 mvp;
uniform mat3 rot; varying vec3 vn; varying vec2 vuv;
void main() { vn = rot * n; vuv = uv; gl_Position = mvp * vec4(p, 1.0); }`;
const MAX_MODES = 8;
const FS = `precision mediump float; varying vec3 vn; varying vec2 vuv;
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

function compile(gl, type, src) {
  const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
  return s;
}

function image(url) {
  return new Promise((resolve, reject) => {
    const img = new Image(); img.onload = () => resolve(img); img.onerror = reject; img.src = url;
  });
}

function texture(gl, img) {
  const t = gl.createTexture(); gl.bindTexture(gl.TEXTURE_2D, t);
  gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, img);
  for (const [p, v] of [[gl.TEXTURE_MIN_FILTER, gl.LINEAR], [gl.TEXTURE_MAG_FILTER, gl.LINEAR],
                        [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE]])
    gl.texParameteri(gl.TEXTURE_2D, p, v);
  return t;
}

export class Delegate {
  constructor(gl, d, tex, modes) {
    this.gl = gl; this.k = Math.min(d.param_names.length, MAX_MODES);
    this.mean = new Float32Array(d.mean); this.basis = new Float32Array(d.basis);
    this.m = d.n_vertices;
    this.tri = this.m < 65536 ? new Uint16Array(d.triangles) : new Uint32Array(d.triangles);
    this.pos = new Float32Array(this.mean.length); this.nrm = new Float32Array(this.mean.length);
    this.grid = d.modes_grid; this.scale = d.modes_scale; this.inset = 0.5 / tex.width;
    const prog = (this.prog = gl.createProgram());
    gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(prog);
    if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
    this.loc = {};
    for (const a of ["p", "n", "uv"]) this.loc[a] = gl.getAttribLocation(prog, a);
    for (const u of ["mvp", "rot", "tex", "modes", "alpha", "grid", "scale", "k", "inset"])
      this.loc[u] = gl.getUniformLocation(prog, u);
    this.tex = texture(gl, tex); this.modes = texture(gl, modes);
    this.pb = gl.createBuffer(); this.nb = gl.createBuffer();
    this.ub = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, this.ub);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(d.uv), gl.STATIC_DRAW);
    this.ib = gl.createBuffer(); gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.ib);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, this.tri, gl.STATIC_DRAW);
    this.alpha = new Float32Array(MAX_MODES);
  }
  update(alpha) { // the shape at alpha, and its vertex normals
    this.alpha.fill(0);
    for (let k = 0; k < this.k; k++) this.alpha[k] = alpha[k] || 0;
    morph(this.pos, this.mean, this.basis, alpha, this.k);
    faceNormals(this.pos, this.tri, this.nrm);
    normalise3(this.nrm);
  }
  draw(mvp, rot) {
    const gl = this.gl, loc = this.loc;
    gl.useProgram(this.prog);
    const attrs = [[this.pb, loc.p, 3, this.pos], [this.nb, loc.n, 3, this.nrm], [this.ub, loc.uv, 2, null]];
    for (const [buf, at, size, data] of attrs) {
      gl.bindBuffer(gl.ARRAY_BUFFER, buf);
      if (data) gl.bufferData(gl.ARRAY_BUFFER, data, gl.DYNAMIC_DRAW);
      gl.enableVertexAttribArray(at); gl.vertexAttribPointer(at, size, gl.FLOAT, false, 0, 0);
    }
    gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, this.tex);
    gl.activeTexture(gl.TEXTURE1); gl.bindTexture(gl.TEXTURE_2D, this.modes);
    gl.uniform1i(loc.tex, 0); gl.uniform1i(loc.modes, 1);
    gl.uniformMatrix4fv(loc.mvp, false, mvp); gl.uniformMatrix3fv(loc.rot, false, rot);
    gl.uniform1fv(loc.alpha, this.alpha); gl.uniform2f(loc.grid, this.grid[0], this.grid[1]);
    gl.uniform1f(loc.scale, this.scale); gl.uniform1i(loc.k, this.k);
    gl.uniform1f(loc.inset, this.inset);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.ib);
    gl.drawElements(gl.TRIANGLES, this.tri.length,
                    this.tri instanceof Uint16Array ? gl.UNSIGNED_SHORT : gl.UNSIGNED_INT, 0);
    gl.disableVertexAttribArray(loc.uv); // the generic face's program has no such array
    gl.activeTexture(gl.TEXTURE0);
  }
}

// The delegate of a hello (null when the session offers none): fetched with the page's token.
export async function loadDelegate(gl, url, headers) {
  if (!gl || !url) return null;
  const r = await fetch(url, { headers, cache: "no-store" });
  if (!r.ok) throw new Error(`delegate: HTTP ${r.status}`);
  const d = await r.json();
  const [tex, modes] = await Promise.all([image(d.texture), image(d.modes)]);
  return new Delegate(gl, d, tex, modes);
}
