// articast browser avatar: a linear face mesh in three.js. Its points are the streamed
// articulation applied to the model (x = mean + sum_k alpha_k basis_k, METHOD.md), set on the
// geometry once per drawn frame; three.js computes the normals and does every transform.
import * as THREE from "three";

// pos = mean + sum_k alpha_k basis_k (basis: k blocks of mean.length values)
export function linear(pos, mean, basis, alpha, k) {
  const n = mean.length;
  pos.set(mean);
  for (let m = 0; m < k; m++) {
    const a = alpha[m]; if (!a) continue;
    const off = m * n; for (let i = 0; i < n; i++) pos[i] += a * basis[off + i];
  }
}

// per-point labels of the dense face (hello's dense mesh): 0 skin, 1 lips, 2 teeth, 3 mouth
const LABEL_COLOURS = [null, [0.72, 0.33, 0.36], [0.93, 0.92, 0.86], [0.22, 0.05, 0.07]];

// The model's face (sparse, or the dense face of hello.dense_url), shaded: skin, and the lips,
// teeth and mouth cavity where the dense face labels them. `object` goes into the scene.
export class LinearFace {
  constructor(mean, basis, triangles, k, labels, colour) {
    this.mean = Float32Array.from(mean); this.basis = Float32Array.from(basis);
    this.k = k; this.m = this.mean.length / 3;
    const g = (this.geometry = new THREE.BufferGeometry());
    this.position = new THREE.BufferAttribute(new Float32Array(this.mean.length), 3);
    this.position.setUsage(THREE.DynamicDrawUsage);
    g.setAttribute("position", this.position);
    g.setIndex(Array.from(triangles));
    const col = new Float32Array(this.mean.length);
    for (let i = 0; i < this.m; i++) {
      const c = (labels && labels.length === this.m && LABEL_COLOURS[labels[i]]) || colour;
      col.set(c, 3 * i);
    }
    g.setAttribute("color", new THREE.BufferAttribute(col, 3));
    this.object = new THREE.Mesh(g, new THREE.MeshLambertMaterial({ vertexColors: true,
                                                                    side: THREE.DoubleSide }));
    this.update(new Array(k).fill(0));
  }
  update(alpha) {
    linear(this.position.array, this.mean, this.basis, alpha, this.k);
    this.position.needsUpdate = true;
    this.geometry.computeVertexNormals();
    this.geometry.computeBoundingSphere();
  }
  // the mesh's edges as lines over the face (the "sparse mesh overlay"), sharing its points
  wire(colour) {
    const edges = new Set(), tri = this.geometry.index.array, lines = [];
    for (let t = 0; t < tri.length; t += 3)
      for (let e = 0; e < 3; e++) {
        const a = tri[t + e], b = tri[t + (e + 1) % 3], key = a < b ? a * 1e6 + b : b * 1e6 + a;
        if (!edges.has(key)) { edges.add(key); lines.push(a, b); }
      }
    const g = new THREE.BufferGeometry();
    g.setAttribute("position", this.position);
    g.setIndex(lines);
    const w = new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: new THREE.Color(...colour) }));
    w.frustumCulled = false;
    return w;
  }
  dispose() { this.geometry.dispose(); this.object.material.dispose(); }
}
