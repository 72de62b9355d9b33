"""``articast bind-dense``: bind a dense face scan to a speaker model for dense animation."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from articast.core.errors import InputError
from articast.service.jsonsafe import dumps


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bind-dense",
        help="bind a dense face scan (.obj) to a speaker model for dense-mesh animation",
        description=(
            "Register a dense scan to the model's mean mesh (point-to-plane ICP), bind each "
            "scan point to a facet of the model's mesh (METHOD.md section 5) and write the "
            "binding (.npz). Prints the registration residual, the share of points bound "
            "inside a facet's cell, and how far the linear dense modes stray from per-frame "
            "transfer over postures of the model's training range (the tolerance to expect "
            "when a client animates the scan from alpha)."
        ),
    )
    p.add_argument("scan", type=Path, help="dense mesh, Wavefront .obj, head frame")
    p.add_argument("--model", type=Path, required=True, help="speaker model (.npz) with "
                   "triangles")
    p.add_argument("-o", "--output", type=Path, required=True, help="binding file to write")
    p.add_argument("--scale", type=float, default=1.0,
                   help="multiply the scan's coordinates by this to get mm (1000 for metres)")
    p.add_argument("--no-register", action="store_true",
                   help="the scan is already in the model's frame: skip ICP")
    p.add_argument("--regularisation", type=float, default=3.0,
                   help="weight of the Sumner-Popovic term relative to the curvature terms")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_bind_dense)


def _bind_dense(args: argparse.Namespace) -> int:
    from articast.core.dense.mesh import load_obj
    from articast.core.dense.transfer import bind, linearity_error, register_and_bind
    from articast.core.model.face import FaceModel

    model = FaceModel.load(args.model)
    if len(model.triangles) == 0:
        raise InputError(f"{args.model}: the model has no triangles to bind a scan to")
    if not (np.isfinite(args.scale) and args.scale > 0):
        raise InputError(f"--scale must be positive, got {args.scale}")
    vertices, triangles = load_obj(args.scan)
    vertices = vertices * args.scale
    options = {"regularisation": args.regularisation}
    report: dict[str, object] = {"dense_points": len(vertices)}
    if args.no_register:
        binding = bind(model.mean, model.triangles, vertices,
                       dense_triangles=triangles if triangles.size else None, **options)
    else:
        binding, reg = register_and_bind(model.mean, model.triangles, vertices,
                                         triangles if triangles.size else None, **options)
        report.update(icp_rms_mm=round(reg.rms, 4), icp_converged=reg.converged,
                      icp_iterations=reg.iterations)
    binding.save(args.output)
    s = model.stats
    postures = np.random.default_rng(0).uniform(s.min, s.max, size=(32, model.n_params))
    err = linearity_error(binding, model, postures)
    report.update(inside_fraction=round(float(binding.inside.mean()), 4),
                  dense_modes_max_error_mm=round(float(err.max()), 4),
                  dense_modes_median_error_mm=round(float(np.median(err)), 4),
                  output=str(args.output))
    if args.json:
        print(dumps(report, indent=2))
    else:
        for key, value in report.items():
            print(f"{key}: {value}")
    return 0
