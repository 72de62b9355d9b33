"""``articast bind-dense``: bind a dense face scan to a speaker model for dense animation."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from articast.core.errors import InputError

if TYPE_CHECKING:
    from articast.core.dense.texture import ScanTexture
from articast.service.jsonsafe import dumps


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bind-dense",
        help="bind a dense face or whole-head scan (.obj) to a speaker model for dense-mesh "
             "animation",
        description=(
            "Register a dense scan to the model's mean mesh, bind each scan point to a facet "
            "of the model's mesh (METHOD.md section 5) and write the binding (.npz). "
            "A scan in its own frame and unit (a real head scan, an artist's head) needs its "
            "68 iBUG landmarks in 3-D (--landmarks): the points they share with the model's "
            "MPEG-4 feature points (lip corners and mid points, nose base, eye centres) give "
            "a similarity (scale included), refined by ICP on the overlap; points within "
            "--support-mm of the model's surface move with the articulation, the rest of the "
            "head follows the head, with a smooth falloff over --falloff-mm (the neck follows "
            "the jaw partly). A failed alignment is refused with its reason. Without "
            "--landmarks the scan must already be roughly in the model's head frame (ICP from "
            "the identity). Prints the alignment, how many points are bound which way, the "
            "share bound inside a facet, and how far the linear dense modes stray from "
            "per-frame transfer over postures of the model's training range, over the points "
            "that move with the articulation (the tolerance to expect when a client animates "
            "the scan from alpha). The texture of the .obj (or --texture) is kept for the "
            "browser avatar: articast demo --scan BINDING. Example, for the demo's speaker: "
            "articast synth corpus --seed 1 -o corpus.npz; articast build-model corpus.npz -o "
            "speaker.npz; articast bind-dense james.obj --landmarks james.ljson --model "
            "speaker.npz -o james.npz (docs/DENSE_TRANSFER.md; python tools/fetch_scan.py "
            "fetches james)."
        ),
    )
    p.add_argument("scan", type=Path, help="dense mesh, Wavefront .obj")
    p.add_argument("--model", type=Path, required=True, help="speaker model (.npz) with "
                   "triangles")
    p.add_argument("-o", "--output", type=Path, required=True, help="binding file to write")
    p.add_argument("--landmarks", type=Path, default=None,
                   help="the scan's 68 iBUG landmarks in 3-D, same frame as the scan: .ljson "
                        "(menpo), .pts or .json (a list of 68 [x, y, z])")
    p.add_argument("--scale", type=float, default=1.0,
                   help="multiply the scan's coordinates by this to get mm (1000 for metres); "
                        "with --landmarks the scale is estimated")
    p.add_argument("--no-register", action="store_true",
                   help="the scan is already in the model's frame: skip ICP")
    p.add_argument("--support-mm", type=float, default=10.0,
                   help="with --landmarks: points this close to the model's surface move "
                        "fully with the articulation (default 10)")
    p.add_argument("--falloff-mm", type=float, default=40.0,
                   help="with --landmarks: beyond the support, the share of the motion falls "
                        "to 0 over this distance (default 40)")
    p.add_argument("--texture", type=Path, default=None,
                   help="the scan's texture image (JPEG or PNG), kept in the binding for the "
                        "browser avatar (articast serve/demo --scan); default: the map_Kd of "
                        "the .obj's mtllib when there is one. Needs texture coordinates (vt) "
                        "in the .obj")
    p.add_argument("--no-texture", action="store_true",
                   help="do not keep the .obj's texture in the binding")
    p.add_argument("--regularisation", type=float, default=3.0,
                   help="weight of the Sumner-Popovic term relative to the curvature terms")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_bind_dense)


def _positive(name: str, value: float) -> None:
    if not (np.isfinite(value) and value > 0):
        raise InputError(f"{name} must be positive, got {value}")


def _texture(args: argparse.Namespace, triangles: np.ndarray | None,
             drawn: np.ndarray) -> ScanTexture | None:
    """The scan's texture (given, or the .obj's material's), or None; ``drawn`` (Q,) the
    facets to draw."""
    from articast.core.dense.texture import MAX_TEXTURE_BYTES, material_image, scan_texture
    from articast.core.safe_io import read_regular_bytes

    if args.no_texture:
        return None
    text = read_regular_bytes(args.scan).decode("utf-8", errors="replace")
    image = args.texture or material_image(text, args.scan)
    if image is None:
        return None
    if triangles is None:
        raise InputError(f"{args.scan}: a texture needs the scan's facets (f lines)")
    data = read_regular_bytes(image, MAX_TEXTURE_BYTES)
    return scan_texture(text, triangles, data, str(args.scan), str(image), drawn)


def _bind_dense(args: argparse.Namespace) -> int:
    from articast.core.dense.mesh import load_obj
    from articast.core.dense.transfer import bind, linearity_error, register_and_bind
    from articast.core.model.face import FaceModel

    model = FaceModel.load(args.model)
    if len(model.triangles) == 0:
        raise InputError(f"{args.model}: the model has no triangles to bind a scan to")
    for name in ("scale", "support_mm", "falloff_mm"):
        _positive("--" + name.replace("_", "-"), getattr(args, name))
    if args.texture is not None and args.no_texture:
        raise InputError("--texture and --no-texture: give one of them")
    if args.landmarks is not None and args.no_register:
        raise InputError("--landmarks aligns the scan; --no-register says it is aligned: "
                         "give one of them")
    vertices, triangles = load_obj(args.scan)
    vertices = vertices * args.scale
    tris = triangles if triangles.size else None
    options = {"regularisation": args.regularisation}
    report: dict[str, object] = {"dense_points": len(vertices)}
    moving = None
    if args.landmarks is not None:
        from articast.core.dense.landmarks import load_landmarks
        from articast.core.dense.scan import align_scan, bind_scan

        landmarks = load_landmarks(args.landmarks) * args.scale
        al = align_scan(model, vertices, triangles, landmarks)
        report.update(scale_to_mm=round(al.transform.scale * args.scale, 6),
                      landmark_pairs=list(al.pairs),
                      landmark_rms_mm=round(al.landmark_rms_mm, 3),
                      icp_landmark_rms_mm=round(al.icp_landmark_rms_mm, 3),
                      overlap_fraction=round(al.overlap_fraction, 4),
                      icp_rms_mm=round(al.icp_rms_mm, 4), icp_converged=al.icp_converged,
                      icp_iterations=al.icp_iterations)
        binding, rep = bind_scan(model, al.transform.apply(vertices), tris,
                                 support_mm=args.support_mm, falloff_mm=args.falloff_mm,
                                 **options)
        moving = rep.articulated
        report.update(points_articulated=rep.n_articulated, points_border=rep.n_border,
                      points_head_only=rep.n_held, points_offset_not_turned=rep.n_unturned,
                      inside_fraction=round(rep.inside_support_fraction, 4))
    elif args.no_register:
        binding = bind(model.mean, model.triangles, vertices, dense_triangles=tris, **options)
    else:
        binding, reg = register_and_bind(model.mean, model.triangles, vertices, tris,
                                         **options)
        from articast.core.dense.scan import coverage

        covered = float(coverage(model, binding.dense_vertices, 12.0).mean())
        why = (f"did not converge (RMS {reg.rms:.2f} mm)" if not reg.converged else
               f"left {1 - covered:.0%} of the model's face without a scan point within "
               "12 mm" if covered < 0.5 else "")
        if why:
            raise InputError(f"{args.scan}: the ICP from the scan's own frame {why}: give the "
                             "scan's 68 iBUG landmarks with --landmarks FILE (.ljson, .pts or "
                             ".json), or --no-register if it is already in the model's head "
                             "frame in mm")
        report.update(icp_rms_mm=round(reg.rms, 4), icp_converged=reg.converged,
                      icp_iterations=reg.iterations)
    s = model.stats
    postures = np.random.default_rng(0).uniform(s.min, s.max, size=(32, model.n_params))
    err = linearity_error(binding, model, postures, points=moving)
    if moving is None:
        report["inside_fraction"] = round(float(binding.inside.mean()), 4)
    report.update(dense_modes_max_error_mm=round(float(err.max()), 4),
                  dense_modes_median_error_mm=round(float(np.median(err)), 4))
    from articast.core.dense.scan import mouth_facets

    opened = mouth_facets(binding, model)
    extra = _texture(args, tris, ~opened)
    if extra is not None:
        report["texture"] = f"{extra.mime}, {len(extra.image)} bytes, {len(extra.uv)} " \
            "render vertices"
        report["facets_across_the_lips_not_drawn"] = int(opened.sum())
    binding.save(args.output, extra=None if extra is None else extra.arrays())
    report["output"] = str(args.output)
    if args.json:
        print(dumps(report, indent=2))
    else:
        for key, value in report.items():
            print(f"{key}: {value}")
    return 0
