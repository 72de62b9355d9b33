// Small column-major 4x4 and row-major 3x3 helpers for the avatar (no dependencies).
export function mat4Perspective(fovy, aspect, near, far) {
  const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
  return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1,
                           0, 0, 2 * far * near * nf, 0]);
}
export function mat4Translate(x, y, z) {
  return new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, x, y, z, 1]);
}
export function mat4Multiply(a, b) {
  const o = new Float32Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let s = 0; for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
    o[c * 4 + r] = s;
  }
  return o;
}
export function rotationFromAxisAngle(r) { // Rodrigues, row-major 3x3
  const th = Math.hypot(r[0], r[1], r[2]);
  if (th < 1e-12) return [1, 0, 0, 0, 1, 0, 0, 0, 1];
  const [x, y, z] = r.map((v) => v / th), c = Math.cos(th), s = Math.sin(th), t = 1 - c;
  return [t * x * x + c, t * x * y - s * z, t * x * z + s * y,
          t * x * y + s * z, t * y * y + c, t * y * z - s * x,
          t * x * z - s * y, t * y * z + s * x, t * z * z + c];
}
export function transpose3(m) { return [m[0], m[3], m[6], m[1], m[4], m[7], m[2], m[5], m[8]]; }

// A linear mesh's points at alpha: pos = mean + sum_k alpha_k basis_k (basis: k blocks of
// mean.length values).
export function morph(pos, mean, basis, alpha, k) {
  const n = mean.length;
  pos.set(mean);
  for (let m = 0; m < k; m++) {
    const a = alpha[m]; if (!a) continue;
    const off = m * n; for (let i = 0; i < n; i++) pos[i] += a * basis[off + i];
  }
}
// Area-weighted vertex normals of the triangles tri (not normalised: normalise3 does that).
export function faceNormals(pos, tri, nrm) {
  nrm.fill(0);
  for (let i = 0; i < tri.length; i += 3) {
    const a = 3 * tri[i], b = 3 * tri[i + 1], c = 3 * tri[i + 2];
    const ux = pos[b] - pos[a], uy = pos[b + 1] - pos[a + 1], uz = pos[b + 2] - pos[a + 2];
    const vx = pos[c] - pos[a], vy = pos[c + 1] - pos[a + 1], vz = pos[c + 2] - pos[a + 2];
    const nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
    for (const j of [a, b, c]) { nrm[j] += nx; nrm[j + 1] += ny; nrm[j + 2] += nz; }
  }
}
export function normalise3(v) {
  for (let i = 0; i < v.length; i += 3) {
    const l = Math.hypot(v[i], v[i + 1], v[i + 2]) || 1;
    v[i] /= l; v[i + 1] /= l; v[i + 2] /= l;
  }
}
