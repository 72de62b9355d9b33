// One peer tracker in Node.js, fed frames by benchmarks/peers.py (not run by hand):
//
//     node benchmarks/peer_worker_faceapi.cjs faceapi CONFIG_JSON OUT_JSON  < frames
//
// face-api.js (@vladmandic/face-api, MIT; its models ship in the npm package) on
// TensorFlow.js's WebAssembly backend, one thread: a landmark family of its own for the
// judge (a 68-point network, iBUG 300-W's numbering, trained apart from dlib's regression
// trees and OpenSeeFace's networks). Everything comes from the folder that
// benchmarks/setup_peers.py filled (CONFIG_JSON's "modules": its node_modules); nothing of it
// enters the repository.
//
// Standard input as benchmarks/peer_worker.py reads it: one JSON line {"n", "h", "w"}, then N
// raw BGR uint8 frames of H x W x 3 bytes. The loop a user would write for video: the SSD
// MobileNet v1 detector on the first frame, every REDETECT frames and after a frame it found
// no face in; in between, the landmarks in a box grown from the previous frame's landmarks
// the way the last detection's box sat about its landmarks (face-api.js's landmark network
// gives no presence score to tell a lost face by). Each frame's own work is timed (wall:
// process.hrtime; CPU: process.cpuUsage), reading the frame from the pipe is not. OUT_JSON:
// {"scheme": "ibug68", "points": N x (68 x [x, y] or null), "ms": [...], "cpu_ms": [...]}.
"use strict";

const fs = require("fs");
const path = require("path");

const REDETECT = 15;

function readExactly(fd, size) {
  const buf = Buffer.alloc(size);
  let got = 0;
  while (got < size) {
    let n = 0;
    try {
      n = fs.readSync(fd, buf, got, size - got, null);
    } catch (e) {
      if (e.code === "EAGAIN") continue;
      throw e;
    }
    if (n === 0) throw new Error(`frame stream ended after ${got} of ${size} bytes`);
    got += n;
  }
  return buf;
}

function readLine(fd) {
  const bytes = [];
  const one = Buffer.alloc(1);
  for (;;) {
    const n = fs.readSync(fd, one, 0, 1, null);
    if (n === 0) throw new Error("no header line on standard input");
    if (one[0] === 10) break;
    bytes.push(one[0]);
  }
  return Buffer.from(bytes).toString();
}

function bbox(points) {
  let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
  for (const [x, y] of points) {
    x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x); y1 = Math.max(y1, y);
  }
  return { cx: (x0 + x1) / 2, cy: (y0 + y1) / 2, side: Math.max(x1 - x0, y1 - y0) };
}

async function main() {
  const [, , method, cfgText, out] = process.argv;
  if (method !== "faceapi") throw new Error(`unknown method ${method}`);
  const cfg = JSON.parse(cfgText);
  const req = (name) => require(path.join(cfg.modules, name));
  const wasm = req("@tensorflow/tfjs-backend-wasm");
  const faceapi = req("@vladmandic/face-api/dist/face-api.node-wasm.js");
  const tf = faceapi.tf;
  wasm.setThreadsCount(1);
  await tf.setBackend("wasm");
  await tf.ready();
  const models = path.join(cfg.modules, "@vladmandic/face-api/model");
  await faceapi.nets.ssdMobilenetv1.loadFromDisk(models);
  await faceapi.nets.faceLandmark68Net.loadFromDisk(models);
  const options = new faceapi.SsdMobilenetv1Options({ minConfidence: 0.5, maxResults: 1 });

  const fd = 0;
  const head = JSON.parse(readLine(fd));
  const n = head.n, h = head.h, w = head.w;
  const points = [], ms = [], cpu = [];
  let prev = null; // the previous frame's landmarks
  let fit = null; // how the last detection's box sat about its landmarks
  let sinceDetect = 0;
  const rgb = new Int32Array(h * w * 3);

  async function landmarksIn(image, box) {
    // face-api.js's extractFaceTensors: the box rounded and clipped to the image
    const x0 = Math.max(0, Math.floor(box.x)), y0 = Math.max(0, Math.floor(box.y));
    const x1 = Math.min(w, Math.floor(box.x + box.width));
    const y1 = Math.min(h, Math.floor(box.y + box.height));
    if (x1 - x0 < 8 || y1 - y0 < 8) return null;
    const crop = tf.slice(image, [y0, x0, 0], [y1 - y0, x1 - x0, 3]);
    const lm = await faceapi.nets.faceLandmark68Net.detectLandmarks(crop);
    crop.dispose();
    return lm.positions.map((p) => [p.x + x0, p.y + y0]);
  }

  for (let i = 0; i < n; i++) {
    const raw = readExactly(fd, h * w * 3);
    const t0 = process.hrtime.bigint();
    const c0 = process.cpuUsage();
    for (let j = 0; j < raw.length; j += 3) {
      rgb[j] = raw[j + 2]; rgb[j + 1] = raw[j + 1]; rgb[j + 2] = raw[j];
    }
    const image = tf.tensor3d(rgb, [h, w, 3], "int32");
    let got = null;
    if (prev === null || fit === null || sinceDetect >= REDETECT) {
      const det = await faceapi.detectSingleFace(image, options);
      sinceDetect = 0;
      if (det) {
        got = await landmarksIn(image, det.box);
        if (got) {
          const b = bbox(got);
          fit = { dx: (det.box.x + det.box.width / 2 - b.cx) / b.side,
                  dy: (det.box.y + det.box.height / 2 - b.cy) / b.side,
                  sw: det.box.width / b.side, sh: det.box.height / b.side };
        }
      }
    } else {
      const b = bbox(prev);
      const bw = fit.sw * b.side, bh = fit.sh * b.side;
      got = await landmarksIn(image, { x: b.cx + fit.dx * b.side - bw / 2,
                                       y: b.cy + fit.dy * b.side - bh / 2,
                                       width: bw, height: bh });
      sinceDetect += 1;
    }
    image.dispose();
    const c = process.cpuUsage(c0);
    ms.push(Number(process.hrtime.bigint() - t0) / 1e6);
    cpu.push((c.user + c.system) / 1000);
    prev = got;
    points.push(got);
  }
  fs.writeFileSync(out, JSON.stringify({ scheme: "ibug68", points, ms, cpu_ms: cpu }));
}

main().catch((e) => {
  process.stderr.write(`${e && e.message ? e.message : e}\n`);
  process.exit(1);
});
