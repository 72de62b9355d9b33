// articast browser avatar: a bound, textured head scan (the server's --scan, docs/DENSE_TRANSFER.md)
// animated like the dense face, linearly from the streamed alpha (x = mean + sum_k alpha_k
// basis_k over the scan's points), drawn with its texture. The render mesh splits a point where
// the texture atlas has a seam (render_index: the point of each render vertex); normals are
// computed on the points, so a seam does not show in the shading. The facets across the lips
// are not in the render mesh (bind-dense leaves them out): where the mouth opens, a dark cavity
// the server adds behind the lips shows (points after the scan's, uv -1).
//
// loadScan(...) resolves to null when the server shows no scan (404), so the page is unchanged.

import { faceNormals, morph } from "./math.js";

const VS = `attribute vec3 p; attribute vec3 n; attribute vec2 uv; uniform mat4 mvp;
uniform mat3 rot; varying vec3 vn; varying vec2 vuv;
void main() { vn = rot * n; vuv = vec2(uv.x, 1.0 - uv.y); gl_Position = mvp * vec4(p, 1.0); }`;
const FS = `precision mediump float; varying vec3 vn; varying vec2 vuv; uniform sampler2D tex;
void main() { vec3 l = normalize(vec3(-0.3, 0.4, 1.0));
  float d = abs(dot(normalize(vn), l));
  // the mouth cavity (uv -1, -1) and the inside of the scan: dark
  gl_FragColor = vuv.x < -0.5 || !gl_FrontFacing ? vec4(vec3(0.2, 0.05, 0.06) * (0.4 + 0.6 * d), 1.0)
                                               : vec4(texture2D(tex, vuv).rgb * (0.55 + 0.6 * d), 1.0); }`;

function compile(gl, type, src) {
  const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
  return s;
}

class Scan {
  constructor(gl, d, k, image) {
    this.gl = gl; this.k = k; this.m = d.n_points;
    this.mean = new Float32Array(d.mean); this.basis = new Float32Array(d.basis);
    this.tri = new Uint32Array(d.triangles); this.index = new Uint32Array(d.render_index);
    this.rtri = new Uint32Array(d.render_triangles);
    this.pos = new Float32Array(this.mean.length); this.nrm = new Float32Array(this.mean.length);
    const r = this.index.length;
    this.rpos = new Float32Array(3 * r); this.rnrm = new Float32Array(3 * r);
    // where to look from: the scan's box centre, far enough for the whole head to fit
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < this.mean.length; i += 3)
      for (let j = 0; j < 3; j++) { lo[j] = Math.min(lo[j], this.mean[i + j]); hi[j] = Math.max(hi[j], this.mean[i + j]); }
    this.centre = lo.map((v, j) => (v + hi[j]) / 2);
    const half = Math.max(hi[0] - lo[0], hi[1] - lo[1]) / 2;
    this.distance = 1.1 * half / Math.tan(0.25) + (hi[2] - lo[2]) / 2;
    const prog = (this.prog = gl.createProgram());
    gl.attachShader(prog, compile(gl, gl.VERTEX_SHADER, VS));
    gl.attachShader(prog, compile(gl, gl.FRAGMENT_SHADER, FS));
    gl.linkProgram(prog);
    this.loc = { p: gl.getAttribLocation(prog, "p"), n: gl.getAttribLocation(prog, "n"),
                 uv: gl.getAttribLocation(prog, "uv"), mvp: gl.getUniformLocation(prog, "mvp"),
                 rot: gl.getUniformLocation(prog, "rot"), tex: gl.getUniformLocation(prog, "tex") };
    this.pb = gl.createBuffer(); this.nb = gl.createBuffer();
    this.ub = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, this.ub);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(d.uv), gl.STATIC_DRAW);
    this.ib = gl.createBuffer(); gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.ib);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, this.rtri, gl.STATIC_DRAW);
    this.tex = gl.createTexture(); gl.bindTexture(gl.TEXTURE_2D, this.tex);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, image);
    for (const [p, v] of [[gl.TEXTURE_MIN_FILTER, gl.LINEAR], [gl.TEXTURE_MAG_FILTER, gl.LINEAR],
                          [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE]])
      gl.texParameteri(gl.TEXTURE_2D, p, v);
  }
  update(alpha) {
    const pos = this.pos, nrm = this.nrm;
    morph(pos, this.mean, this.basis, alpha, this.k);
    faceNormals(pos, this.tri, nrm);
    const idx = this.index, rp = this.rpos, rn = this.rnrm;
    for (let r = 0; r < idx.length; r++) {
      const i = 3 * idx[r], l = Math.hypot(nrm[i], nrm[i + 1], nrm[i + 2]) || 1;
      for (let j = 0; j < 3; j++) { rp[3 * r + j] = pos[i + j]; rn[3 * r + j] = nrm[i + j] / l; }
    }
  }
  draw(mvp, rot) {
    const gl = this.gl, loc = this.loc;
    gl.useProgram(this.prog);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.pb); gl.bufferData(gl.ARRAY_BUFFER, this.rpos, gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(loc.p); gl.vertexAttribPointer(loc.p, 3, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.nb); gl.bufferData(gl.ARRAY_BUFFER, this.rnrm, gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(loc.n); gl.vertexAttribPointer(loc.n, 3, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.ub);
    gl.enableVertexAttribArray(loc.uv); gl.vertexAttribPointer(loc.uv, 2, gl.FLOAT, false, 0, 0);
    gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, this.tex); gl.uniform1i(loc.tex, 0);
    gl.uniformMatrix4fv(loc.mvp, false, mvp); gl.uniformMatrix3fv(loc.rot, false, rot);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.ib);
    gl.drawElements(gl.TRIANGLES, this.rtri.length, gl.UNSIGNED_INT, 0);
    gl.disableVertexAttribArray(loc.uv); // the other meshes' programs do not use it
  }
}

// The session's scan, or null when the server has none. k: the number of parameters.
export async function loadScan(gl, session, k, headers) {
  if (!gl) return null;
  const base = `/api/sessions/${encodeURIComponent(session)}/scan`;
  const r = await fetch(base, { headers });
  if (r.status === 404) return null;
  if (!r.ok) throw new Error(`scan: ${r.status} ${(await r.json()).detail || ""}`);
  const d = await r.json();
  const t = await fetch(`${base}/texture`, { headers });
  if (!t.ok) throw new Error(`scan texture: ${t.status}`);
  const image = await createImageBitmap(await t.blob());
  return new Scan(gl, d, k, image);
}
