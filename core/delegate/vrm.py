"""The delegate as a VRM 1.0 avatar (``.vrm``: glTF 2.0 binary with the ``VRMC_vrm``
extension), for the apps people use avatars in (three-vrm, UniVRM-based apps, VSeeFace,
Warudo, cluster).

**Skeleton.** The humanoid's required bones (hips, spine, head, both arms' upperArm, lowerArm,
hand, both legs' upperLeg, lowerLeg, foot) plus chest, neck and the shoulders, as a node
hierarchy in a T-pose (translations only, metres, y up, facing +z, the character's left +x),
proportioned for a 1.7 m adult: they carry no geometry. The face (the delegate's mesh, the
glTF export's, :mod:`~articast.core.delegate.gltf`) is a child node of the head bone, placed so
that the head turns about a pivot behind the face at the mouth's height (:func:`head_pivot`).

**Morph targets** on the face mesh (``mesh.extras.targetNames``), all made from the speaker's
own fitted mesh:

* the articulatory parameters (``jaw1`` ... ``lar1``), as the glTF export's: a weight of
  ``alpha_k`` each gives the model's own geometry;
* the ARKit mouth and jaw shapes the stream sends for this model (mouthFunnel and mouthPucker
  included), **fitted so that together they reproduce the speaker**: a perfect-sync app sets
  every shape's weight at once, and the glTF export's per-shape targets (each the smallest
  articulation that gives its measure full scale) overlap, so their sum under the stream's
  weights overshoots (on the synthetic speaker's model, p95 of the worst model point
  29 mm, the motion itself being 10 mm); here each target is a combination of the model's
  modes fitted by least squares over articulations spread like speech
  (:func:`perfect_sync_targets`: held-out p95 about 1 mm);
* the five vowels ``aa ih ou ee oh``: the articulation within the training range whose jaw,
  aperture, spread and protrusion (:class:`~articast.core.outputs.vowels.VowelMapper`) come
  nearest that vowel's prototype (bounded least squares, the smallest such articulation);
* the upper face, as the stream's ARKit eye and brow shapes are defined
  (:mod:`articast.core.outputs.upper`): eyeBlink (the upper lid onto the lower lid, the skin
  above following), eyeWide (the upper lid raised by half the eye's opening: WIDE_DEAD +
  WIDE_FULL of its travel), eyeSquint (the lower lid raised by SQUINT_FULL of the opening),
  eyeLook{Up,Down,In,Out} (the eye's opening, with the eye painted in it, moved
  :data:`GAZE_MM` within its socket: the delegate has no eyeball geometry, its eyes are the
  enrolment's mean eyes painted on the surface), browInnerUp / browOuterUp (BROW_FULL_MM up)
  and browDown (BROW_DOWN_FULL_MM down). MediaPipe's mesh topology names the lids and brows.

**Lids** (a second primitive of the face mesh, :func:`lid_sheets`): the face's eyes are
painted in its texture, and eyeBlink moving the upper lid's vertices onto the lower lid only
squashes the painted eye into a slit (issue 40: 61-63 % of each eye still showed at closure
1 on the avatar page before its shader drew the lids). Each eye has a sheet of the lid's
own skin: two rows along the upper lid's margin (corners included), both at the margin at
rest (no area: nothing drawn), :data:`LID_FORWARD_MM` in front of the face. eyeBlink raises
the top row (:data:`LID_RISE`) and carries the bottom row down with the margin onto the lower
lid:
the sheet covers the opening in the lid's skin colour (:func:`lid_colours`, a flat colour
from the texture between the eye and the brow), darker at the margin. eyeSquint raises its
bottom row with the lower lid (shut and squinting, the lower lid rises above the opening's
rest). Under every other target both rows follow their margin vertex (eyeWide raises the
margin: the sheet stays a line on it). A VRM app drives the sheet with the face, by the
same weights (the sheet primitive has the same targets).

**Expressions** (``VRMC_vrm.expressions``): the presets ``aa ih ou ee oh blink blinkLeft
blinkRight lookUp lookDown lookLeft lookRight neutral`` bound to those targets (``neutral``
binds nothing: the mean face is the neutral one; happy/angry/sad/relaxed/surprised are left
out, as the spec allows), and the 52 ARKit blendshape names as custom expressions ("perfect
sync"); the ones the model does not drive (cheeks, nose sneer, tongue: the stream always
sends 0) bind nothing. ``lookAt`` is of type ``expression`` (lookUp/Down/Left/Right reach 1
at the stream's GAZE_FULL_DEG, as its eyeLook* shapes do). ``firstPerson`` marks the face
third-person only (a first-person camera sits inside the head).

"Left" is the character's own left throughout (VRM 1.0 and ARKit agree; the head frame's +x).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from articast.core.delegate.geometry import DelegateMesh
from articast.core.delegate.gltf import _ARRAY, _ELEMENTS, _normals, mesh_document, pack_glb
from articast.core.errors import InputError
from articast.core.model.face import FaceModel
from articast.core.outputs.arkit import ARKIT_BLENDSHAPES, ArkitMapper, full_scale, measure_gradient
from articast.core.outputs.upper import (
    BROW_DOWN_FULL_MM,
    BROW_FULL_MM,
    GAZE_FULL_DEG,
    SQUINT_FULL,
    WIDE_DEAD,
    WIDE_FULL,
)
from articast.core.outputs.vowels import FEATURES, PROTOTYPES

VRM_PRESETS: tuple[str, ...] = ("aa", "ih", "ou", "ee", "oh", "blink", "blinkLeft",
                                "blinkRight", "lookUp", "lookDown", "lookLeft", "lookRight",
                                "neutral")
"""The VRM 1.0 preset expressions written (the spec's emotion presets are optional)."""
VOWEL_PRESETS = {"A": "aa", "I": "ih", "U": "ou", "E": "ee", "O": "oh"}
GAZE_MM = 2.5
"""How far a full eyeLook* weight moves the eye's opening within its socket (mm)."""

# MediaPipe's 468-point face mesh: the lids (the corners on the lower lid) and the brows,
# the speaker's left (+x) first
_EYES = {"Left": ([466, 388, 387, 386, 385, 384, 398],
                  [263, 249, 390, 373, 374, 380, 381, 382, 362]),
         "Right": ([246, 161, 160, 159, 158, 157, 173],
                   [33, 7, 163, 144, 145, 153, 154, 155, 133])}
_BROWS = {"Left": [300, 293, 334, 296, 336, 276, 283, 282, 295, 285],
          "Right": [70, 63, 105, 66, 107, 46, 53, 52, 65, 55]}
N_VERTICES = 468

# (bone, parent, translation from the parent, m): a T-pose facing +z, the character's left +x
_SKELETON: tuple[tuple[str, str | None, tuple[float, float, float]], ...] = (
    ("hips", None, (0.0, 0.95, 0.0)),
    ("spine", "hips", (0.0, 0.10, 0.0)),
    ("chest", "spine", (0.0, 0.15, 0.0)),
    ("neck", "chest", (0.0, 0.20, 0.0)),
    ("head", "neck", (0.0, 0.10, 0.0)),
    ("leftShoulder", "chest", (0.04, 0.17, 0.0)),
    ("leftUpperArm", "leftShoulder", (0.12, 0.0, 0.0)),
    ("leftLowerArm", "leftUpperArm", (0.28, 0.0, 0.0)),
    ("leftHand", "leftLowerArm", (0.25, 0.0, 0.0)),
    ("rightShoulder", "chest", (-0.04, 0.17, 0.0)),
    ("rightUpperArm", "rightShoulder", (-0.12, 0.0, 0.0)),
    ("rightLowerArm", "rightUpperArm", (-0.28, 0.0, 0.0)),
    ("rightHand", "rightLowerArm", (-0.25, 0.0, 0.0)),
    ("leftUpperLeg", "hips", (0.09, -0.05, 0.0)),
    ("leftLowerLeg", "leftUpperLeg", (0.0, -0.42, 0.0)),
    ("leftFoot", "leftLowerLeg", (0.0, -0.40, 0.0)),
    ("rightUpperLeg", "hips", (-0.09, -0.05, 0.0)),
    ("rightLowerLeg", "rightUpperLeg", (0.0, -0.42, 0.0)),
    ("rightFoot", "rightLowerLeg", (0.0, -0.40, 0.0)),
)
REQUIRED_BONES = ("hips", "spine", "head", "leftUpperArm", "leftLowerArm", "leftHand",
                  "rightUpperArm", "rightLowerArm", "rightHand", "leftUpperLeg",
                  "leftLowerLeg", "leftFoot", "rightUpperLeg", "rightLowerLeg", "rightFoot")
"""VRM 1.0's required humanoid bones."""


def _min_norm(gradients: np.ndarray, values: np.ndarray, model: FaceModel,
              scale: np.ndarray | None = None) -> np.ndarray:
    """(K,) the alpha within the training range whose measures ``gradients @ alpha`` come
    nearest ``values`` (each in units of its ``scale``, default 1), the smallest such alpha
    (a light ridge, 1e-3, picks it among the many: K parameters, fewer measures)."""
    from scipy.optimize import lsq_linear

    s = np.ones(len(values)) if scale is None else np.asarray(scale, float)
    a = np.vstack([gradients / s[:, None], np.sqrt(1e-3) * np.eye(gradients.shape[1])])
    b = np.concatenate([values / s, np.zeros(gradients.shape[1])])
    lo, hi = np.minimum(model.stats.min, 0.0), np.maximum(model.stats.max, 0.0)
    hi = np.maximum(hi, lo + 1e-9)  # a parameter that never moved in training (lar1): held
    return np.asarray(lsq_linear(a, b, bounds=(lo, hi)).x)


def perfect_sync_targets(model: FaceModel, mesh: DelegateMesh, samples: int = 2000
                         ) -> dict[str, np.ndarray]:
    """The ARKit mouth and jaw shapes the stream sends for this model (mouthFunnel and
    mouthPucker included), (V, 3) mm each, fitted so that their sum under the stream's
    weights reproduces the model (module docstring): each target is a combination of the
    model's modes, ``C @ modes``, with ``C`` the least-squares solution of ``W C = A`` over
    ``samples`` articulations ``A`` (each parameter Gaussian with its training s.d., clipped
    to its training range, seeded: the same file every time) and their weights ``W``
    (:class:`~articast.core.outputs.arkit.ArkitMapper`), a light ridge (1e-3) for shapes that
    never act together."""
    mapper = ArkitMapper(model)
    names = [n for n in mapper.populated if not n.startswith(("eye", "brow"))]
    if not names:
        return {}
    rng = np.random.default_rng(0)
    st = model.stats
    a = np.clip(rng.normal(0.0, 1.0, (samples, model.n_params)) * st.std, st.min, st.max)
    cols = [ARKIT_BLENDSHAPES.index(n) for n in names]
    w = mapper.weights(a)[:, cols]
    ridge = 1e-3 * samples
    coef = np.linalg.solve(w.T @ w + ridge * np.eye(len(names)), w.T @ a)  # (S, K)
    return {n: np.tensordot(c, mesh.modes, 1) for n, c in zip(names, coef, strict=True)}


def vowel_targets(model: FaceModel, mesh: DelegateMesh) -> dict[str, np.ndarray]:
    """The five vowels ``aa ih ou ee oh`` (module docstring), (V, 3) mm each."""
    if not all(p in model.feature_points for terms, _ in FEATURES.values() for p, _, _ in terms):
        return {}
    g = np.stack([measure_gradient(model, t) for t, _ in FEATURES.values()])  # (4, K)
    scales = [full_scale(model, gi, two_sided=True) for gi in g]
    unit = np.array([(hi if np.isfinite(hi) else 1.0) - lo for lo, hi in scales])
    out = {}
    for vowel, preset in VOWEL_PRESETS.items():
        m = []
        for f, (lo, hi), (_, signed) in zip(PROTOTYPES[vowel], scales, FEATURES.values(),
                                            strict=True):
            hi = hi if np.isfinite(hi) else 1.0
            if not signed:
                m.append(lo + f * (hi - lo))
            else:
                m.append(f * hi if f > 0 else f * (-lo if lo < 0 else 1.0))
        out[preset] = np.tensordot(_min_norm(g, np.array(m), model, unit), mesh.modes, 1)
    return out


def _falloff(v: np.ndarray, anchors: np.ndarray, moves: np.ndarray, sigma: float,
             fixed: np.ndarray) -> np.ndarray:
    """(V, 3): every vertex moved as its nearest anchor, by exp(-(d / sigma)^2) of its
    distance d to that anchor; the ``fixed`` vertices (indices) not at all."""
    d = np.linalg.norm(v[:, None] - v[anchors][None], axis=2)  # (V, A)
    near = d.argmin(1)
    w = np.exp(-(d[np.arange(len(v)), near] / sigma) ** 2)
    out = w[:, None] * moves[near]
    out[anchors] = moves
    out[fixed] = 0.0
    return out


def _lid_gap(v: np.ndarray, upper: list[int], lower: list[int]) -> np.ndarray:
    """(len(upper), 3): each upper-lid vertex to the lower lid below it (the lower lid's
    y and z interpolated at its x)."""
    lo = v[lower]
    order = np.argsort(lo[:, 0])
    out = np.zeros((len(upper), 3))
    for i, u in enumerate(upper):
        x = v[u, 0]
        out[i, 1] = np.interp(x, lo[order, 0], lo[order, 1]) - v[u, 1]
        out[i, 2] = np.interp(x, lo[order, 0], lo[order, 2]) - v[u, 2]
    return out


def upper_face_targets(mesh: DelegateMesh) -> dict[str, np.ndarray]:
    """The ARKit eye and brow shapes (module docstring), (V, 3) mm each, named as the
    stream's."""
    v = mesh.vertices
    if v.shape != (N_VERTICES, 3):
        raise InputError(f"a VRM face needs the {N_VERTICES}-vertex face mesh of 'articast "
                         f"delegate', not {len(v)} vertices")
    out: dict[str, np.ndarray] = {}
    for side, (upper, lower) in _EYES.items():
        gap = _lid_gap(v, upper, lower)  # (U, 3) upper lid -> lower lid
        opening = float(np.median(-gap[:, 1]))
        corners = [lower[0], lower[-1]]
        lid = _falloff(v, np.array(upper), gap, 4.0, np.array(lower))
        out[f"eyeBlink{side}"] = lid
        out[f"eyeWide{side}"] = _falloff(v, np.array(upper),
                                         np.tile([0.0, (WIDE_DEAD + WIDE_FULL) * opening, 0.0],
                                                 (len(upper), 1)), 4.0, np.array(lower))
        inner = np.array([i for i in lower if i not in corners])
        out[f"eyeSquint{side}"] = _falloff(v, inner, np.tile(
            [0.0, SQUINT_FULL * opening, 0.0], (len(inner), 1)), 4.0, np.array(upper))
        ring = np.array(upper + lower)
        centre = v[ring].mean(0)
        half = float(np.ptp(v[ring, 0])) / 2
        w = np.exp(-(np.linalg.norm(v - centre, axis=1) / (0.6 * half)) ** 2)
        outward = 1.0 if side == "Left" else -1.0  # away from the nose: +x for the left eye
        for name, way in (("Up", (0.0, 1.0, 0.0)), ("Down", (0.0, -1.0, 0.0)),
                          ("Out", (outward, 0.0, 0.0)), ("In", (-outward, 0.0, 0.0))):
            out[f"eyeLook{name}{side}"] = w[:, None] * (GAZE_MM * np.array(way))[None]
    mid = float(np.median(v[:, 0]))
    for side, brow in _BROWS.items():
        b = np.array(brow)
        dx = np.abs(v[b, 0] - mid)
        inner = np.clip((dx.max() - dx) / max(float(np.ptp(dx)), 1e-6), 0, 1)  # 1: inner end
        fixed = np.array(sum(_EYES[side], []))
        for name, weight, mm in (("browInnerUp", inner, BROW_FULL_MM),
                                 (f"browOuterUp{side}", 1 - inner, BROW_FULL_MM),
                                 (f"browDown{side}", inner, -BROW_DOWN_FULL_MM)):
            moves = np.zeros((len(b), 3))
            moves[:, 1] = weight * mm
            moved = _falloff(v, b, moves, 6.0, fixed)
            out[name] = out[name] + moved if name in out else moved
    return out


LID_SHADE = 0.7
"""The sheet's bottom row (the lid's margin, where the lashes are) is the skin this dark."""
LID_RISE = 0.8
"""At a blink the sheet's top row rises this fraction of the eye's opening above the lid's
margin (the texture's eye reaches above the mesh's margin: on the synthetic speaker the
top half of the painted eye stayed in sight above a sheet that started at the margin)."""
LID_BELOW = 0.25
"""At a blink the sheet's bottom row goes this fraction of the opening past the lower lid."""
LID_SPREAD = 0.25
"""At a blink the sheet spreads along the eye's axis, its corners this fraction of the
half width past the eye's."""
LID_FORWARD_MM = 1.6
"""How far in front of the face (along its normals) the lid sheets sit: over the eye at a
blink, in front of the face's own lid skin, which eyeBlink brings down over the opening and
forward (up to ~1.2 mm on the synthetic speaker's mesh) carrying the paint of the eye's top
(the texture's eye reaches above the mesh's lid margin): at 0.4 mm it hid the sheet."""


def lid_sheets(mesh: DelegateMesh, targets: list[tuple[str, np.ndarray]]
               ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Both eyes' lid sheets (module docstring): vertices (N, 3) mm at rest, triangles
    (T, 3) (counter-clockwise from the front, as the face's)
    and, per target of ``targets`` (name, (V, 3) mm displacement of the face's vertices, in
    the face primitive's order), the sheets' (N, 3) displacement."""
    v = mesh.vertices
    normals = _normals(v, np.asarray(mesh.triangles))
    verts: list[np.ndarray] = []
    tris: list[tuple[int, int, int]] = []
    sources: list[np.ndarray] = []
    tops: list[np.ndarray] = []
    sides: list[str] = []
    for side, (upper, lower) in _EYES.items():
        row = np.array([lower[0], *upper, lower[-1]])  # the margin, corner to corner
        base = sum(len(x) for x in verts)
        n = len(row)
        at = v[row] + LID_FORWARD_MM * normals[row]
        verts += [at, at]  # top row, then bottom row
        for i in range(n - 1):
            a, b, c, d = base + i, base + i + 1, base + n + i, base + n + i + 1
            tris += [(a, c, b), (b, c, d)]
        sources += [row, row]
        tops += [np.ones(n, bool), np.zeros(n, bool)]
        sides += [side] * (2 * n)
    vs, src, top = np.vstack(verts), np.concatenate(sources), np.concatenate(tops)
    tri = np.array(tris, np.int32)
    # (the winding: counter-clockwise from the front, as the face's, each triangle checked on
    # the sheets' shut shape against the face's normals)
    moves = []
    blink_of = {f"eyeBlink{s_}": s_ for s_ in _EYES}
    squint_of = {f"eyeSquint{s_}": s_ for s_ in _EYES}
    side_arr = np.array(sides)
    for name, disp in targets:
        m = disp[src].copy()
        if name in blink_of:  # the top row rises as the bottom comes down: the sheet
            # opens over the eye and the painted eye's top above the mesh's lid margin
            # (which the face's own lid skin brings down at a blink)
            side = blink_of[name]
            sel = top & (side_arr == side)
            m[sel, :2] = -LID_RISE * m[sel, :2]  # (forward as the margin: over the skin)
            low = ~top & (side_arr == side)
            m[low, :2] *= 1.0 + LID_BELOW  # (past the lower lid: the paint reaches below it)
            # both rows spread along the eye's axis past its corners (the paint reaches
            # beyond the mesh's corners too)
            rows = np.flatnonzero(side_arr == side)
            ends = v[[_EYES[side][1][0], _EYES[side][1][-1]]]
            centre, axis = ends.mean(0), (ends[1] - ends[0]) / 2.0
            along = ((v[src[rows]] - centre) @ axis) / float(axis @ axis)
            m[rows] += LID_SPREAD * along[:, None] * axis[None]
        if name in squint_of:  # the bottom row rides the raised lower lid: shut and
            # squinting, the lower lid rises over the opening's rest and the sheet must
            # still reach it (open, the sheet turns its back and is not drawn)
            side = squint_of[name]
            below = np.array(_EYES[side][1])
            order = below[np.argsort(v[below, 0])]
            rows = np.flatnonzero(~top & (side_arr == side))
            for j in range(3):
                m[rows, j] += np.interp(v[src[rows], 0], v[order, 0], disp[order, j])
        moves.append(m)
    shut = vs.copy()
    for (name, _), m in zip(targets, moves, strict=True):
        if name in blink_of:
            shut += m
    p = shut[tri]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    face_n = normals[src[tri[:, 0]]]
    back = np.sum(fn * face_n, axis=1) < 0  # (the eyes' lid lists run opposite ways)
    tri[back] = tri[back][:, [0, 2, 1]]
    return vs, tri, moves


def lid_colours(mesh: DelegateMesh, texture: np.ndarray, n_rows: tuple[int, ...]
                ) -> np.ndarray:
    """(N, 4) linear RGBA vertex colours of the sheets (:func:`lid_sheets`' vertices, eye by
    eye, top row then bottom row of ``n_rows`` vertices each): each eye's lid skin, the
    median of ``texture`` (S, S, 3 uint8 BGR, sRGB) between its upper lid and its brow
    (40-60 % of the way: the texture's eye reaches above the mesh's lid margin, the brow
    below its points), the bottom row :data:`LID_SHADE` of it. A flat colour, not the
    texture: the lid's own pixels in the texture are mostly the painted eye's top."""
    size = texture.shape[0]
    out = []
    for (side, (upper, _)), n in zip(_EYES.items(), n_rows, strict=True):
        lid = mesh.uv[upper].mean(0)
        brow = mesh.uv[_BROWS[side]].mean(0)
        pts = [lid + f * (brow - lid) + d for f in (0.4, 0.5, 0.6)
               for d in ((mesh.uv[upper] - lid) * 0.6)]
        px = np.clip(np.round(np.array(pts) * (size - 1)).astype(int), 0, size - 1)
        bgr = np.median(texture[px[:, 1], px[:, 0]].astype(np.float64), axis=0) / 255.0
        srgb = bgr[::-1]
        lin = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
        top = np.append(lin, 1.0)
        bottom = np.append(lin * LID_SHADE, 1.0)
        out += [np.tile(top, (n, 1)), np.tile(bottom, (n, 1))]
    return np.vstack(out)


def head_pivot(mesh: DelegateMesh) -> np.ndarray:
    """(3,) mm, head frame: where the head turns about (the head bone), an average adult's:
    the face's middle in x, a third of the way from chin to brow in y (about the mouth),
    100 mm behind the most forward point (the nose tip)."""
    v = mesh.vertices
    lo, hi = v.min(0), v.max(0)
    return np.array([(lo[0] + hi[0]) / 2, lo[1] + 0.35 * (hi[1] - lo[1]), hi[2] - 100.0])


def _expression(binds: list[tuple[int, float]], node: int) -> dict[str, Any]:
    return {"morphTargetBinds": [{"node": node, "index": i, "weight": w} for i, w in binds],
            "isBinary": False, "overrideBlink": "none", "overrideLookAt": "none",
            "overrideMouth": "none"}


def vrm_targets(model: FaceModel, mesh: DelegateMesh, arkit: bool = True
                ) -> dict[str, np.ndarray]:
    """Every named morph target of the VRM's face after the parameters' (module docstring):
    ARKit (mouth, jaw, eyes, brows; with ``arkit``), then the vowels; the eye and brow
    shapes are written either way (blink and look-at need them)."""
    out: dict[str, np.ndarray] = {}
    if arkit:
        out.update(perfect_sync_targets(model, mesh))
    out.update(upper_face_targets(mesh))
    out.update(vowel_targets(model, mesh))
    return out


def to_vrm(model: FaceModel, mesh: DelegateMesh, texture: np.ndarray | None = None,
           name: str = "speaker", authors: tuple[str, ...] = (), arkit: bool = True,
           version: str = "") -> bytes:
    """The VRM 1.0 binary of the speaker's face on a humanoid skeleton (module docstring).
    arkit : False leaves the perfect-sync custom expressions out (an avatar driven by the
    presets only); texture : (S, S, 3) uint8 BGR or None."""
    if len(model.param_names) != mesh.modes.shape[0]:
        raise InputError(f"the mesh has {mesh.modes.shape[0]} modes for a model of "
                         f"{len(model.param_names)} parameters")
    targets = vrm_targets(model, mesh, arkit)
    doc, b = mesh_document(mesh, tuple(model.param_names), texture, targets, name, unlit=True)
    doc["asset"]["generator"] = "articast export-vrm"
    if texture is not None:  # (without a texture the eyes are not painted: nothing to cover)
        named = list(zip(model.param_names, mesh.modes, strict=True)) + list(targets.items())
        sv, stri, smoves = lid_sheets(mesh, named)
        rows = tuple(len(up) + 2 for up, _ in _EYES.values())
        colours = lid_colours(mesh, texture, rows)
        sheet = {"attributes": {
            "POSITION": b.accessor((sv * 1e-3).astype(np.float32), "VEC3", _ARRAY, True),
            "NORMAL": b.accessor(_normals(sv + np.sum([m for m, (n, _) in zip(
                smoves, named, strict=True) if n.startswith("eyeBlink")], axis=0),
                stri).astype(np.float32), "VEC3", _ARRAY, False),
            "COLOR_0": b.accessor(colours.astype(np.float32), "VEC4", _ARRAY, False)},
            "indices": b.accessor(stri.astype(np.uint16).reshape(-1), "SCALAR", _ELEMENTS,
                                  False),
            "material": len(doc["materials"]), "mode": 4,
            "targets": [{"POSITION": b.accessor((m * 1e-3).astype(np.float32), "VEC3", _ARRAY,
                                                True)} for m in smoves]}
        doc["meshes"][0]["primitives"].append(sheet)
        doc["materials"].append({"name": f"{name} lids", "pbrMetallicRoughness": {
            "metallicFactor": 0.0, "roughnessFactor": 0.85},
            "extensions": {"KHR_materials_unlit": {}}})
    index = {n: i for i, n in enumerate(doc["meshes"][0]["extras"]["targetNames"])}
    # nodes: the bones in order, then the face (a child of the head)
    bones = {bone: i for i, (bone, _, _) in enumerate(_SKELETON)}
    nodes: list[dict[str, Any]] = [{"name": bone, "translation": list(t)}
                                   for bone, _, t in _SKELETON]
    for bone, parent, _ in _SKELETON:
        if parent is not None:
            nodes[bones[parent]].setdefault("children", []).append(bones[bone])
    face = len(nodes)
    pivot = head_pivot(mesh) * 1e-3
    nodes.append({"name": f"{name} face", "mesh": 0,
                  "translation": [float(-x) for x in pivot]})
    nodes[bones["head"]]["children"] = [face]
    doc["nodes"] = nodes
    doc["scenes"] = [{"nodes": [bones["hips"]]}]

    def bind(*names: str) -> dict[str, Any]:
        return _expression([(index[n], 1.0) for n in names if n in index], face)

    preset = {v: bind(v) for v in VOWEL_PRESETS.values()}
    preset.update({
        "blink": bind("eyeBlinkLeft", "eyeBlinkRight"), "blinkLeft": bind("eyeBlinkLeft"),
        "blinkRight": bind("eyeBlinkRight"),
        "lookUp": bind("eyeLookUpLeft", "eyeLookUpRight"),
        "lookDown": bind("eyeLookDownLeft", "eyeLookDownRight"),
        # the character's left: the left eye outwards, the right eye inwards
        "lookLeft": bind("eyeLookOutLeft", "eyeLookInRight"),
        "lookRight": bind("eyeLookInLeft", "eyeLookOutRight"),
        "neutral": _expression([], face)})
    expressions: dict[str, Any] = {"preset": preset}
    if arkit:
        expressions["custom"] = {n: bind(n) for n in ARKIT_BLENDSHAPES}
    eyes = mesh.vertices[sum(_EYES["Left"], []) + sum(_EYES["Right"], [])].mean(0) * 1e-3
    gaze = {"inputMaxValue": GAZE_FULL_DEG, "outputScale": 1.0}
    vrm = {
        "specVersion": "1.0",
        "meta": {
            "name": name, "version": version or "1", "authors": list(authors) or [name],
            "licenseUrl": "https://vrm.dev/licenses/1.0/",
            # a picture of a real person's face: theirs only, unless they say otherwise
            "avatarPermission": "onlyAuthor", "allowExcessivelyViolentUsage": False,
            "allowExcessivelySexualUsage": False, "commercialUsage": "personalNonProfit",
            "allowPoliticalOrReligiousUsage": False, "allowAntisocialOrHateUsage": False,
            "creditNotation": "required", "allowRedistribution": False,
            "modification": "prohibited"},
        "humanoid": {"humanBones": {bone: {"node": bones[bone]} for bone, _, _ in _SKELETON}},
        "firstPerson": {"meshAnnotations": [{"node": face, "type": "thirdPersonOnly"}]},
        "lookAt": {"type": "expression",
                   "offsetFromHeadBone": [float(x) for x in eyes - pivot],
                   "rangeMapHorizontalInner": gaze, "rangeMapHorizontalOuter": gaze,
                   "rangeMapVerticalDown": gaze, "rangeMapVerticalUp": gaze},
        "expressions": expressions,
    }
    doc["extensionsUsed"] = [*doc.get("extensionsUsed", []), "VRMC_vrm"]
    doc["extensions"] = {"VRMC_vrm": vrm}
    return pack_glb(doc, b)
