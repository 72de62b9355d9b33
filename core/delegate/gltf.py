"""The delegate as a glTF 2.0 binary (``.glb``): Blender, three.js, Unity and Unreal load it.

One mesh, one primitive: the delegate's vertices at alpha = 0 (metres, glTF's unit; the head
frame is glTF's own: y up, +z towards the viewer, right-handed), their normals, texture
coordinates and 16-bit indices; its texture (T0, the mean texture at alpha = 0) embedded as a
PNG. **Morph targets**, named in ``mesh.extras.targetNames`` (the convention three.js and
Blender read):

* one per articulatory parameter (``jaw1`` ... ``lar1``): the mode of that parameter, so a
  weight of ``alpha_k`` gives ``vertices + sum_k alpha_k modes[k]`` -- the model's own
  geometry at the model's points;
* one per ARKit blendshape the outputs compute as a linear measure
  (:data:`~articast.core.outputs.arkit.MEASURES`, "perfect sync" names such as ``jawOpen``,
  ``mouthSmileLeft``): the displacement from that shape's weight 0 to weight 1 (its
  measure's full scale, :func:`~articast.core.outputs.arkit.full_scale`) along the smallest
  articulation (in s.d.) that moves the measure so far. mouthFunnel and mouthPucker
  (products of two measures, not linear in alpha) are not exported.

The articulation-dependent part of the texture (``tex lin``) has no glTF equivalent and is
not exported: the browser avatar has it.
"""

from __future__ import annotations

import json
import struct

import cv2
import numpy as np

from articast.core.delegate.geometry import DelegateMesh
from articast.core.errors import InputError
from articast.core.model.face import FaceModel
from articast.core.outputs.arkit import MEASURES, TWO_SIDED, full_scale, measure_gradient

_FLOAT, _USHORT, _UINT = 5126, 5123, 5125
_ARRAY, _ELEMENTS = 34962, 34963


def arkit_targets(model: FaceModel, mesh: DelegateMesh) -> dict[str, np.ndarray]:
    """ARKit name -> (V, 3) mm displacement from weight 0 to weight 1 (module docstring)."""
    out = {}
    for name, terms in MEASURES.items():
        if not all(p in model.feature_points for p, _, _ in terms):
            continue
        g = measure_gradient(model, terms)  # mm of the measure per unit alpha
        lo, hi = full_scale(model, g, two_sided=name in TWO_SIDED)
        if not np.isfinite(hi) or float(g @ g) < 1e-12:
            continue  # nothing in this model moves the measure
        out[name] = np.tensordot(g * (hi - lo) / float(g @ g), mesh.modes, 1)
    return out


def _normals(v: np.ndarray, tri: np.ndarray) -> np.ndarray:
    p = v[tri]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    acc = np.zeros_like(v)
    for k in range(3):
        np.add.at(acc, tri[:, k], fn)
    n = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.where(n > 0, acc / np.maximum(n, 1e-12), np.array([0.0, 0.0, 1.0]))


class _Bin:
    def __init__(self) -> None:
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, raw: bytes, target: int | None = None) -> int:
        while len(self.data) % 4:
            self.data.append(0)
        v = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(raw)}
        if target is not None:
            v["target"] = target
        self.data += raw
        self.views.append(v)
        return len(self.views) - 1

    def accessor(self, arr: np.ndarray, kind: str, target: int | None, bounds: bool) -> int:
        ctype = {np.dtype(np.float32): _FLOAT, np.dtype(np.uint16): _USHORT,
                 np.dtype(np.uint32): _UINT}[arr.dtype]
        acc = {"bufferView": self.view(np.ascontiguousarray(arr).tobytes(), target),
               "componentType": ctype, "count": int(arr.shape[0]), "type": kind}
        if bounds:
            flat = arr.reshape(arr.shape[0], -1)
            acc["min"] = [float(x) for x in flat.min(0)]
            acc["max"] = [float(x) for x in flat.max(0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def mesh_document(mesh: DelegateMesh, param_names: tuple[str, ...],
                  texture: np.ndarray | None = None, arkit: dict[str, np.ndarray] | None = None,
                  name: str = "speaker", unlit: bool = False) -> tuple[dict, _Bin]:
    """The glTF document (one node ``0`` holding mesh ``0``) and its binary buffer, not yet
    packed: :func:`to_glb` packs it as is, :mod:`~articast.core.delegate.vrm` adds a skeleton
    and the VRM extension first. unlit : the texture shown as it is (``KHR_materials_unlit``:
    the texture already carries the enrolment's lighting)."""
    if len(param_names) != mesh.modes.shape[0]:
        raise InputError(f"{len(param_names)} names for {mesh.modes.shape[0]} modes")
    b = _Bin()
    v = (mesh.vertices * 1e-3).astype(np.float32)
    tri = np.asarray(mesh.triangles)
    index_type = np.uint16 if len(v) < 65535 else np.uint32
    attrs = {"POSITION": b.accessor(v, "VEC3", _ARRAY, True),
             "NORMAL": b.accessor(_normals(mesh.vertices, tri).astype(np.float32), "VEC3",
                                  _ARRAY, False)}
    if texture is not None:
        attrs["TEXCOORD_0"] = b.accessor(mesh.uv.astype(np.float32), "VEC2", _ARRAY, False)
    indices = b.accessor(tri.astype(index_type).reshape(-1), "SCALAR", _ELEMENTS, False)
    names = list(param_names)
    shapes = list(mesh.modes)
    for n, d in (arkit or {}).items():
        names.append(n)
        shapes.append(d)
    targets = [{"POSITION": b.accessor((d * 1e-3).astype(np.float32), "VEC3", _ARRAY, True)}
               for d in shapes]
    material: dict = {"name": f"{name} skin", "pbrMetallicRoughness": {
        "metallicFactor": 0.0, "roughnessFactor": 0.85}}
    if unlit:
        material["extensions"] = {"KHR_materials_unlit": {}}
    doc: dict = {"asset": {"version": "2.0", "generator": "articast export-gltf"},
                 "scene": 0, "scenes": [{"nodes": [0]}],
                 "nodes": [{"name": name, "mesh": 0}]}
    if unlit:
        doc["extensionsUsed"] = ["KHR_materials_unlit"]
    if texture is not None:
        ok, png = cv2.imencode(".png", np.ascontiguousarray(texture))
        if not ok:
            raise InputError("the delegate's texture could not be encoded as PNG")
        doc["images"] = [{"bufferView": b.view(png.tobytes()), "mimeType": "image/png"}]
        doc["samplers"] = [{"magFilter": 9729, "minFilter": 9729, "wrapS": 33071,
                            "wrapT": 33071}]
        doc["textures"] = [{"sampler": 0, "source": 0}]
        material["pbrMetallicRoughness"]["baseColorTexture"] = {"index": 0}
    else:
        material["pbrMetallicRoughness"]["baseColorFactor"] = [0.8, 0.6, 0.5, 1.0]
    doc["materials"] = [material]
    doc["meshes"] = [{"name": name, "primitives": [{"attributes": attrs, "indices": indices,
                                                    "material": 0, "mode": 4,
                                                    "targets": targets}],
                      "weights": [0.0] * len(targets), "extras": {"targetNames": names}}]
    return doc, b


def pack_glb(doc: dict, b: _Bin) -> bytes:
    """``doc`` and its buffer as one glTF 2.0 binary (``.glb``)."""
    doc = {**doc, "accessors": b.accessors, "bufferViews": b.views}
    while len(b.data) % 4:
        b.data.append(0)
    doc["buffers"] = [{"byteLength": len(b.data)}]
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + len(b.data)
    return b"".join([struct.pack("<4sII", b"glTF", 2, total),
                     struct.pack("<I4s", len(js), b"JSON"), js,
                     struct.pack("<I4s", len(b.data), b"BIN\x00"), bytes(b.data)])


def to_glb(mesh: DelegateMesh, param_names: tuple[str, ...], texture: np.ndarray | None = None,
           arkit: dict[str, np.ndarray] | None = None, name: str = "speaker") -> bytes:
    """The glTF 2.0 binary of ``mesh`` (module docstring). texture : (S, S, 3) uint8 BGR or
    None (untextured, skin-coloured); arkit : extra named targets, (V, 3) mm each."""
    return pack_glb(*mesh_document(mesh, param_names, texture, arkit, name))
