// articast browser avatar: a bound, textured head scan (the server's --scan, docs/DENSE_TRANSFER.md)
// animated like the dense face, linearly from the streamed alpha (x = mean + sum_k alpha_k
// basis_k over the scan's points), drawn in three.js with its texture. The render mesh splits
// a point where the texture atlas has a seam (render_index: the point of each render vertex);
// normals are computed on the points, so a seam does not show in the shading. The facets
// across the lips are not in the render mesh (bind-dense leaves them out): where the mouth
// opens, a dark cavity the server adds behind the lips shows (points after the scan's, uv -1).
//
// loadScan(url, ...) is called only when hello.scan_url names one (a server with --scan).
import * as THREE from "three";
import { linear } from "./face.js";

const VS = `varying vec3 vn; varying vec2 vuv;
void main() { vn = normalize(normalMatrix * normal); vuv = vec2(uv.x, 1.0 - uv.y);
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0); }`;
const FS = `varying vec3 vn; varying vec2 vuv; uniform sampler2D tex;
void main() { vec3 l = normalize(vec3(-0.3, 0.4, 1.0));
  float d = abs(dot(normalize(vn), l));
  // the mouth cavity (uv -1, -1) and the inside of the scan: dark
  gl_FragColor = vuv.x < -0.5 || !gl_FrontFacing ? vec4(vec3(0.2, 0.05, 0.06) * (0.4 + 0.6 * d), 1.0)
                                               : vec4(texture2D(tex, vuv).rgb * (0.55 + 0.6 * d), 1.0); }`;

class Scan {
  constructor(d, k, image) {
    this.k = k; this.m = d.n_points;
    this.mean = Float32Array.from(d.mean); this.basis = Float32Array.from(d.basis);
    this.index = Uint32Array.from(d.render_index);
    // the points' own mesh (not drawn): its normals are the render vertices'
    this.points = new THREE.BufferGeometry();
    this.points.setAttribute("position", new THREE.BufferAttribute(new Float32Array(this.mean.length), 3));
    this.points.setIndex(Array.from(d.triangles));
    const r = this.index.length, g = (this.geometry = new THREE.BufferGeometry());
    this.position = new THREE.BufferAttribute(new Float32Array(3 * r), 3);
    this.normal = new THREE.BufferAttribute(new Float32Array(3 * r), 3);
    this.position.setUsage(THREE.DynamicDrawUsage); this.normal.setUsage(THREE.DynamicDrawUsage);
    g.setAttribute("position", this.position); g.setAttribute("normal", this.normal);
    g.setAttribute("uv", new THREE.Float32BufferAttribute(d.uv, 2));
    g.setIndex(Array.from(d.render_triangles));
    // where to look from: the scan's box centre, far enough for the whole head to fit
    this.points.getAttribute("position").array.set(this.mean);
    this.points.computeBoundingBox();
    const box = this.points.boundingBox, size = box.getSize(new THREE.Vector3());
    this.centre = box.getCenter(new THREE.Vector3()).toArray();
    this.distance = 1.1 * Math.max(size.x, size.y) / 2 / Math.tan(0.25) + size.z / 2;
    const tex = new THREE.Texture(image);
    tex.flipY = false; tex.colorSpace = THREE.NoColorSpace; tex.generateMipmaps = false;
    tex.minFilter = THREE.LinearFilter; tex.wrapS = tex.wrapT = THREE.ClampToEdgeWrapping;
    tex.needsUpdate = true;
    this.material = new THREE.ShaderMaterial({ vertexShader: VS, fragmentShader: FS,
                                               side: THREE.DoubleSide, uniforms: { tex: { value: tex } } });
    this.object = new THREE.Mesh(g, this.material);
    this.update(new Array(k).fill(0));
  }
  update(alpha) {
    const p = this.points.getAttribute("position");
    linear(p.array, this.mean, this.basis, alpha, this.k);
    this.points.computeVertexNormals();
    const pos = p.array, nrm = this.points.getAttribute("normal").array;
    const idx = this.index, rp = this.position.array, rn = this.normal.array;
    for (let r = 0; r < idx.length; r++) {
      const i = 3 * idx[r];
      for (let j = 0; j < 3; j++) { rp[3 * r + j] = pos[i + j]; rn[3 * r + j] = nrm[i + j]; }
    }
    this.position.needsUpdate = true; this.normal.needsUpdate = true;
    this.geometry.computeBoundingSphere();
  }
  dispose() { this.geometry.dispose(); this.points.dispose(); this.material.dispose(); }
}

// The session's scan (hello.scan_url). k: the number of parameters.
export async function loadScan(url, k, headers) {
  const r = await fetch(url, { headers });
  if (!r.ok) {
    let why = ""; try { why = (await r.json()).detail || ""; } catch (e) { /* not JSON */ }
    throw new Error(`scan: ${r.status} ${why}`);
  }
  const d = await r.json();
  const t = await fetch(`${url}/texture`, { headers });
  if (!t.ok) throw new Error(`scan texture: ${t.status}`);
  const image = await createImageBitmap(await t.blob());
  return new Scan(d, k, image);
}
