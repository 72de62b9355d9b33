"""``articast delegate`` (the speaker's textured 3D face, made from their clip),
``articast export-gltf`` (that face as a glTF 2.0 binary with one morph target per parameter)
and ``articast export-vrm`` (that face as a VRM 1.0 avatar)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from articast.core.errors import InputError
from articast.service.jsonsafe import dumps

MAX_TRACKED = 300
"""Frames of the clip tracked for the texture (spread over it); the texture uses 150 of the
ones tracked ok (:data:`~articast.core.delegate.build.MAX_TEXTURE_FRAMES`)."""


def register(sub: argparse._SubParsersAction) -> None:
    de = sub.add_parser(
        "delegate",
        help="make the speaker's own textured 3D face (their delegate) from their clip",
        description=(
            "Write SPEAKER_DIR/delegate.npz: the speaker's delegate, the face the remote end "
            "sees. Its surface is the face finder's full-face mesh fitted to the enrolled "
            "model and moved by it (the model's points exactly, the rest of the face by "
            "deformation transfer); its texture comes from the clip's frames, tracked as a "
            "live session tracks them: the mean texture plus the part that varies linearly "
            "with the articulation (inner mouth and teeth as the jaw opens), lighting evened "
            "out, what the camera never saw filled. 'articast enroll' already writes it; run "
            "this to rebuild it (the speaker folder keeps no pictures of the face, so give the "
            "enrolment clip again, or any clip of the same speaker with the same camera). "
            "A delegate is a picture of a face: 'articast serve' serves it only with the "
            "session's token, and 'serve --no-delegate' serves none. Then: 'articast "
            "export-gltf SPEAKER_DIR -o me.glb'. Example: articast delegate me/ --video "
            "me.mp4"
        ),
    )
    de.add_argument("speaker", type=Path, metavar="SPEAKER_DIR",
                    help="speaker folder from 'articast enroll'")
    de.add_argument("--video", type=Path,
                    help="a clip of the speaker (the enrolment clip, or another one with the "
                         "same camera); needed: the folder keeps no frames")
    from articast.service.commands.track import add_span_arguments

    add_span_arguments(de)
    de.add_argument("--json", action="store_true", help="print the report as JSON")
    de.add_argument("--quiet", action="store_true", help="no progress line")
    de.set_defaults(func=_delegate)

    ex = sub.add_parser(
        "export-gltf",
        help="export the speaker's face as glTF 2.0 (.glb) with morph targets",
        description=(
            "Write the speaker's face as one glTF 2.0 binary that Blender, three.js, Unity "
            "and Unreal load: the delegate's mesh (metres, y up, facing +z), its texture when "
            "the folder has a delegate ('articast delegate'; else an untextured skin colour), "
            "one morph target per articulatory parameter (jaw1 lips1 lips2 lips3 lips4 jaw2 "
            "lar1: set a target's weight to the streamed value and the mesh is the model's "
            "geometry) and one per ARKit mouth/jaw blendshape the stream computes, named as "
            "a perfect-sync avatar's (jawOpen, mouthSmileLeft, ...). The texture's "
            "articulation-dependent part has no glTF form and is left out. "
            "Example: articast export-gltf me/ -o me.glb"
        ),
    )
    ex.add_argument("speaker", type=Path, metavar="SPEAKER_DIR",
                    help="speaker folder from 'articast enroll'")
    ex.add_argument("-o", "--output", type=Path, required=True, help="the .glb file to write")
    ex.add_argument("--no-texture", action="store_true",
                    help="leave the texture out (a face picture) even when there is one")
    ex.add_argument("--no-arkit", action="store_true",
                    help="morph targets for the articulatory parameters only")
    ex.add_argument("--json", action="store_true", help="print what was written as JSON")
    ex.set_defaults(func=_export)

    vr = sub.add_parser(
        "export-vrm",
        help="export the speaker's face as a VRM 1.0 avatar (.vrm) for VRM apps",
        description=(
            "Write the speaker's face as a VRM 1.0 avatar (a glTF 2.0 binary with the VRMC_vrm "
            "extension) that VRM apps and three-vrm load: the delegate's textured face on a "
            "humanoid skeleton (the required bones, no body geometry), with the VRM "
            "expressions an app drives (aa ih ou ee oh, blink blinkLeft blinkRight, lookUp "
            "lookDown lookLeft lookRight, neutral), look-at by expression, and the 52 ARKit "
            "blendshapes as custom expressions ('perfect sync'), each a morph target made "
            "from the speaker's own model. A face is personal data: the file's licence lets "
            "only its author use it as an avatar (meta.avatarPermission onlyAuthor), no "
            "redistribution. The browser page /avatar/vrm.html drives it live. "
            "Example: articast export-vrm me/ -o me.vrm"
        ),
    )
    vr.add_argument("speaker", type=Path, metavar="SPEAKER_DIR",
                    help="speaker folder from 'articast enroll'")
    vr.add_argument("-o", "--output", type=Path, required=True, help="the .vrm file to write")
    vr.add_argument("--name", help="the avatar's name (default: the speaker's)")
    vr.add_argument("--author", action="append", default=[],
                    help="an author named in the file's meta (repeatable; default: the name)")
    vr.add_argument("--no-texture", action="store_true",
                    help="leave the texture out (a face picture) even when there is one")
    vr.add_argument("--no-arkit", action="store_true",
                    help="no perfect-sync custom expressions: the VRM presets only")
    vr.add_argument("--json", action="store_true", help="print what was written as JSON")
    vr.set_defaults(func=_export_vrm)


def read_clip(video: Path, span, max_frames: int) -> tuple[list[np.ndarray], np.ndarray]:
    """At most ``max_frames`` frames of ``video`` (of ``span``), evenly spread, with their
    times (s). Frames are kept at a stride that doubles whenever twice ``max_frames`` are
    held, so a long clip never fills the memory."""
    from articast.service.video import iter_video

    images: list[np.ndarray] = []
    times: list[float] = []
    stride = 1
    for k, (_, t, img) in enumerate(iter_video(video, span)):
        if k % stride:
            continue
        images.append(img)
        times.append(t)
        if len(images) >= 2 * max_frames:
            images, times, stride = images[::2], times[::2], stride * 2
    if len(images) > max_frames:
        pick = np.linspace(0, len(images) - 1, max_frames).round().astype(int)
        images, times = [images[i] for i in pick], [times[i] for i in pick]
    return images, np.array(times, np.float64)


def make_delegate(speaker, images: list[np.ndarray], times: np.ndarray, say=None):
    """The delegate of ``speaker`` from ``images`` (taken at ``times``, s): tracked live,
    then textured. One clear error when too few frames are tracked."""
    from articast.core.delegate.build import build_delegate, tracked_frames
    from articast.core.faces.finder import FaceFinder
    from articast.service.processors import fit_camera

    if not images:
        raise InputError("no frames to make a delegate from")
    h, w = images[0].shape[:2]
    camera = fit_camera(speaker.camera, w, h, what="the clip's frames")
    if camera is not speaker.camera:
        from dataclasses import replace

        speaker = replace(speaker, camera=camera)
    if images and len(images) > MAX_TRACKED:
        pick = np.linspace(0, len(images) - 1, MAX_TRACKED).round().astype(int)
        images, times = [images[i] for i in pick], times[pick]
    (say or (lambda _m: None))(f"tracking {len(images)} frames for the delegate's texture")
    states = tracked_frames(speaker, images, FaceFinder.load(), times=times)
    if len(states) < 10:
        raise InputError(f"only {len(states)} frames of the clip were tracked: is it a clip "
                         "of this speaker, with this camera?")
    return build_delegate(speaker.model, camera, states)


def _delegate(args: argparse.Namespace) -> int:
    from articast.core.delegate.build import DELEGATE_FILE
    from articast.core.faces.speaker import Speaker
    from articast.service.video import Span

    speaker = Speaker.load(args.speaker)
    if args.video is None:
        raise InputError("a delegate is made from frames of the speaker, and a speaker folder "
                         "keeps none (a face's pictures are not stored): give the enrolment "
                         "clip with --video CLIP")
    say = (lambda m: None) if args.quiet else (lambda m: print(f"delegate: {m}",
                                                                 file=sys.stderr))
    images, times = read_clip(args.video, Span(args.start, args.end), MAX_TRACKED)
    delegate = make_delegate(speaker, images, times, say)
    delegate.save(args.speaker / DELEGATE_FILE)
    out = {"delegate": str(args.speaker / DELEGATE_FILE), **delegate.report}
    if args.json:
        print(dumps(out, indent=1))
    else:
        print(f"wrote {out['delegate']}: {out['vertices']} vertices, texture "
              f"{out['texture_size']} px from {out['frames']} tracked frames "
              f"({out['texels_seen_pct']} % of the face seen, the rest filled)")
    return 0


def _face(args: argparse.Namespace, command: str, suffix: str):
    """(speaker, mesh, texture or None) of the speaker folder ``args.speaker``: the delegate's
    when the folder has one, else the untextured fitted mesh (said on stderr)."""
    from articast.core.delegate.build import DELEGATE_FILE, Delegate
    from articast.core.delegate.geometry import fit_mesh
    from articast.core.faces.speaker import Speaker

    speaker = Speaker.load(args.speaker)
    if args.output.is_dir():
        raise InputError(f"{args.output}: is a folder; give the {suffix} file to write")
    path = args.speaker / DELEGATE_FILE
    texture = None
    if path.is_file():
        delegate = Delegate.load(path)
        mesh = delegate.mesh
        if delegate.param_names != speaker.model.param_names or \
                mesh.modes.shape[0] != speaker.model.n_params:
            raise InputError(f"{path} was made for another model: rebuild it with "
                             f"'articast delegate {args.speaker} --video CLIP'")
        texture = None if args.no_texture else delegate.texture
    else:
        mesh = fit_mesh(speaker.model)
        if not args.no_texture:
            print(f"articast {command}: {args.speaker} has no delegate: the mesh is "
                  "untextured ('articast delegate' makes one)", file=sys.stderr)
    return speaker, mesh, texture


def _write(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    tmp.replace(path)


def _export(args: argparse.Namespace) -> int:
    from articast.core.delegate.gltf import arkit_targets, to_glb

    speaker, mesh, texture = _face(args, "export-gltf", ".glb")
    arkit = {} if args.no_arkit else arkit_targets(speaker.model, mesh)
    data = to_glb(mesh, speaker.model.param_names, texture, arkit, speaker.name)
    _write(args.output, data)
    targets = list(speaker.model.param_names) + list(arkit)
    out = {"output": str(args.output), "bytes": len(data), "vertices": len(mesh.vertices),
           "triangles": len(mesh.triangles), "textured": texture is not None,
           "morph_targets": targets}
    if args.json:
        print(dumps(out, indent=1))
    else:
        print(f"wrote {args.output}: {out['vertices']} vertices, "
              f"{len(targets)} morph targets "
              f"({'textured' if texture is not None else 'untextured'})")
    return 0


def _export_vrm(args: argparse.Namespace) -> int:
    from articast.core.delegate.vrm import VRM_PRESETS, to_vrm, vrm_targets

    speaker, mesh, texture = _face(args, "export-vrm", ".vrm")
    name = (args.name or speaker.name or "speaker").strip() or "speaker"
    data = to_vrm(speaker.model, mesh, texture, name=name,
                  authors=tuple(a for a in args.author if a.strip()), arkit=not args.no_arkit)
    _write(args.output, data)
    targets = list(speaker.model.param_names) + list(vrm_targets(speaker.model, mesh,
                                                                 not args.no_arkit))
    out = {"output": str(args.output), "bytes": len(data), "vertices": len(mesh.vertices),
           "textured": texture is not None, "morph_targets": targets,
           "expressions": list(VRM_PRESETS), "perfect_sync": not args.no_arkit}
    if args.json:
        print(dumps(out, indent=1))
    else:
        print(f"wrote {args.output}: VRM 1.0, {out['vertices']} vertices, "
              f"{len(targets)} morph targets, {len(VRM_PRESETS)} preset expressions"
              f"{', 52 perfect-sync (ARKit) ones' if not args.no_arkit else ''} "
              f"({'textured' if texture is not None else 'untextured'})")
    return 0
