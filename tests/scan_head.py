"""A whole head scan made from the built-in speaker's model, for the tests of
:mod:`articast.core.dense.scan`: the model's face, extended past its outline by rings that
wrap back round the cranium and down the neck and close at the back, Loop-subdivided (so the
scan's points are not the model's), in another frame (rotated, shifted) and unit (metres),
with its 68 iBUG landmarks from the model's feature points.

Ground truth: Loop subdivision is linear in the control points, so the face part of the scan
at posture alpha is the subdivision of ``model.shape(alpha)`` (the extension held still).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from articast.core.dense.subdivide import loop_subdivide
from articast.core.model.camera import rotation_matrix
from articast.core.model.face import FaceModel
from articast.core.synthetic import default_speaker

OUTLINE = np.arange(352, 384)  # the speaker's outermost grid ring, in angle order
RINGS = 6


@dataclass(frozen=True)
class HeadScan:
    model: FaceModel
    head: np.ndarray  # (M, 3) mm, head frame
    triangles: np.ndarray  # (Q, 3)
    face: np.ndarray  # (M,) bool: point made from the model's face (ground truth known)
    landmarks_head: np.ndarray  # (68, 3) mm head frame
    rotation: np.ndarray  # scan = (rotation @ head + shift) / 1000
    shift: np.ndarray

    @property
    def scan(self) -> np.ndarray:
        return self.to_scan(self.head)

    @property
    def landmarks(self) -> np.ndarray:
        return self.to_scan(self.landmarks_head)

    def to_scan(self, x: np.ndarray) -> np.ndarray:
        return (x @ self.rotation.T + self.shift) / 1000.0

    def truth(self, alpha: np.ndarray) -> np.ndarray:
        """(M, 3) mm head frame: the face points at posture alpha (the rest unchanged)."""
        moved, tris = _control_mesh(self.model, self.model.shape(alpha))
        out = self.head.copy()
        out[self.face] = loop_subdivide(moved, tris, 1)[0][self.face]
        return out


def _control_mesh(model: FaceModel, shape: np.ndarray, closed_mouth: bool = False
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The model's surface plus extension rings (fixed: they do not move with alpha); with
    ``closed_mouth``, facets across the mouth opening join the inner lip contour's upper and
    lower points (as a scan with its lips together has)."""
    rest = model.mean
    outline = rest[OUTLINE]
    centre = np.array([0.0, -10.0, 0.0])
    radial = outline[:, :2] - centre[:2]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    rings = []
    for j in range(1, RINGS + 1):
        f = j / RINGS
        xy = outline[:, :2] + radial * 25.0 * np.sin(np.pi * f / 1.2)
        z = outline[:, 2] - 110.0 * f
        rings.append(np.column_stack([xy, z]))
    back = np.array([[0.0, -10.0, -140.0]])
    verts = np.concatenate([shape, *rings, back])
    n, m = len(shape), len(OUTLINE)
    ring_ids = [OUTLINE] + [n + j * m + np.arange(m) for j in range(RINGS)]
    tris = [model.triangles]
    for r0, r1 in zip(ring_ids[:-1], ring_ids[1:], strict=True):
        a, b = r0, np.roll(r0, -1)
        c, d = np.roll(r1, -1), r1
        tris += [np.c_[a, d, b], np.c_[b, d, c]]  # outwards: away from the face's front
    last = ring_ids[-1]
    tris.append(np.c_[last, np.full(m, len(verts) - 1), np.roll(last, -1)])
    if closed_mouth:  # inner contour: 0 and 16 the corners, 1-15 upper, 17-31 lower
        fill = [(0, 1, 31), (15, 16, 17)]
        for i in range(1, 15):
            fill += [(i, i + 1, 32 - i), (i + 1, 31 - i, 32 - i)]
        fill_arr = np.array(fill)
        up = np.cross(rest[fill_arr[:, 1]] - rest[fill_arr[:, 0]],
                      rest[fill_arr[:, 2]] - rest[fill_arr[:, 0]])[:, 2] > 0
        tris.append(np.where(up[:, None], fill_arr, fill_arr[:, ::-1]))
    return verts, np.concatenate(tris).astype(np.int64)


def _eye(centre: np.ndarray, left_to_right: bool) -> np.ndarray:
    ang = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    ring = np.column_stack([-12 * np.cos(ang), 4 * np.sin(ang), np.zeros(6)])
    return centre + (ring if left_to_right else ring * [-1, 1, 1]) + [0.0, 0.0, -1.0]


@lru_cache(maxsize=2)
def head_scan(closed_mouth: bool = False) -> HeadScan:
    """The test head; ``closed_mouth``: its lips joined (no ``truth`` for it)."""
    model = default_speaker(0).model()
    verts, tris = _control_mesh(model, model.mean, closed_mouth)
    head, dense_tris = loop_subdivide(verts, tris, 1)
    probe = np.c_[model.stats.max, model.stats.min].T
    face = np.zeros(len(head), bool)
    for a in probe:  # the points the model's motion reaches through the subdivision
        moved = loop_subdivide(_control_mesh(model, model.shape(a))[0], tris, 1)[0]
        face |= np.linalg.norm(moved - head, axis=1) > 1e-9
    fp = {k: model.mean[i] for k, i in model.feature_points.items()}
    lm = np.repeat(model.mean[[model.point("9.15")]], 68, axis=0) + np.linspace(-5, 5, 68)[:, None]
    lm[54], lm[48], lm[51], lm[57], lm[33] = fp["8.3"], fp["8.4"], fp["8.1"], fp["8.2"], fp["9.15"]
    lm[42:48] = _eye(fp["3.5"], False)  # iBUG 42-47: the speaker's left eye (image right)
    lm[36:42] = _eye(fp["3.6"], True)
    rot = rotation_matrix([0.3, -0.5, 0.2])
    return HeadScan(model, head, dense_tris.astype(np.int64), face, lm, rot,
                    np.array([40.0, -250.0, 900.0]))


def write_obj(path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    lines = [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in triangles]
    path.write_text("\n".join(lines) + "\n")


def write_ljson(path, points: np.ndarray, menpo3d_order: bool = True) -> None:
    """menpo v3 .ljson; with ``menpo3d_order`` the groups are listed as in menpo3d's
    james.ljson (eyes before brows), the masks saying where each group is."""
    groups = [("chin", 0, 17), ("leyebrow", 17, 5), ("reyebrow", 22, 5), ("nose", 27, 9),
              ("leye", 36, 6), ("reye", 42, 6), ("mouth", 48, 20)]
    order = ["chin", "leye", "reye", "leyebrow", "nose", "reyebrow", "mouth"]
    if not menpo3d_order:
        order = [g[0] for g in groups]
    spans = {name: (first, size) for name, first, size in groups}
    listed, labels, at = [], [], 0
    for name in order:
        first, size = spans[name]
        listed += points[first:first + size].tolist()
        labels.append({"label": name, "mask": list(range(at, at + size))})
        at += size
    doc = {"version": 3, "groups": {"LJSON": {
        "landmarks": {"points": listed, "connectivity": []}, "labels": labels}}}
    path.write_text(json.dumps(doc))


def write_pts(path, points: np.ndarray) -> None:
    body = "\n".join(f"{x:.9f} {y:.9f} {z:.9f}" for x, y, z in points)
    path.write_text(f"version: 1\nn_points: {len(points)}\n{{\n{body}\n}}\n")


def write_textured(folder, scan: HeadScan | None = None) -> dict:
    """The head as a textured scan in ``folder``: head.obj (v/vt, mtllib), head.mtl, head.png
    (top half blue, bottom half green, in the texture's v), head.ljson. Returns the paths."""
    import cv2

    h = scan or head_scan()
    x = h.head
    u = np.arctan2(x[:, 0], x[:, 2]) / (2 * np.pi) + 0.5
    v = (x[:, 1] - x[:, 1].min()) / np.ptp(x[:, 1])
    img = np.zeros((64, 64, 3), np.uint8)
    img[:32] = (255, 0, 0)  # BGR blue: the top rows, v near 1
    img[32:] = (0, 200, 0)
    cv2.imwrite(str(folder / "head.png"), img)
    (folder / "head.mtl").write_text("newmtl skin\nKd 1 1 1\nmap_Kd head.png\n")
    lines = ["mtllib head.mtl"] + [f"v {a:.9f} {b:.9f} {c:.9f}" for a, b, c in h.scan]
    lines += [f"vt {a:.6f} {b:.6f}" for a, b in zip(u, v, strict=True)]
    lines += ["usemtl skin"] + [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}"
                                for a, b, c in h.triangles]
    (folder / "head.obj").write_text("\n".join(lines) + "\n")
    write_ljson(folder / "head.ljson", h.landmarks)
    return {k: folder / f"head.{k}" for k in ("obj", "mtl", "png", "ljson")}
