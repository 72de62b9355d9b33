"""Guided iterative PCA (METHOD.md §1) and direct inversion of the model.

A *posture corpus* is V postures x N points x 3 coordinates (mm, head frame) with point
names, point groups, posture names, triangles and MPEG-4 feature-point labels.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from articast.core.bundle import load_bundle, reading, require, save_bundle
from articast.core.errors import InputError
from articast.core.model.face import PARAM_NAMES, FaceModel, ParamStats

CORPUS_KIND = "posture-corpus"
CORPUS_VERSION = 1

LIPS = ("lip_inner", "lip_outer", "lip_beads")

# name -> (groups of the guide subset, coordinates used, sign rule (axis, group, +1/-1))
# The sign rule fixes each parameter's direction so that alpha > 0 means what the paper's
# nomograms name first: jaw1 opens, lips1 spreads, lips2 raises the lower lip, lips3 lowers the
# upper lip, lips4 raises the corners, jaw2 advances the jaw, lar1 raises the throat.
GUIDES: dict[str, tuple[tuple[str, ...], tuple[int, ...], tuple[str, str, int]]] = {
    "jaw1": (("jaw_line", "lower_teeth"), (1,), ("y", "jaw_line", -1)),
    "lips1": (LIPS, (0, 1, 2), ("width", "lip_outer", +1)),
    "lips2": (("lower_lip",), (1,), ("y", "lower_lip", +1)),
    "lips3": (("upper_lip",), (1,), ("y", "upper_lip", -1)),
    "lips4": (LIPS, (1,), ("corners_y", "lip_outer", +1)),
    "jaw2": (("jaw_line", "lower_teeth"), (2,), ("z", "jaw_line", +1)),
    "lar1": (("__not_lips_teeth__",), (0, 1, 2), ("y", "rest", +1)),
}


@dataclass(frozen=True, eq=False)
class Corpus:
    """A posture corpus.

    postures : (V, N, 3) float64 mm, head frame.
    controls : optional (V, C) generating controls (ground truth of a synthetic corpus).
    """

    postures: np.ndarray
    posture_names: tuple[str, ...]
    point_names: tuple[str, ...]
    groups: Mapping[str, np.ndarray]
    triangles: np.ndarray
    feature_points: Mapping[str, int] = field(default_factory=dict)
    fapu_overrides: Mapping[str, float] = field(default_factory=dict)
    controls: np.ndarray | None = None
    control_names: tuple[str, ...] = ()
    name: str = "speaker"

    def __post_init__(self) -> None:
        x = np.asarray(self.postures, dtype=np.float64)
        if x.ndim != 3 or x.shape[2] != 3:
            raise InputError(f"postures must have shape (V, N, 3), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise InputError("postures contain NaN or infinite coordinates")
        v, n, _ = x.shape
        if len(self.posture_names) != v:
            raise InputError(f"{len(self.posture_names)} posture names for {v} postures")
        if len(self.point_names) != n:
            raise InputError(f"{len(self.point_names)} point names for {n} points")
        object.__setattr__(self, "postures", x)
        object.__setattr__(self, "posture_names", tuple(self.posture_names))
        object.__setattr__(self, "point_names", tuple(self.point_names))
        object.__setattr__(
            self, "groups", {g: np.asarray(i, np.int64).ravel() for g, i in self.groups.items()}
        )
        object.__setattr__(self, "triangles", np.asarray(self.triangles, np.int32).reshape(-1, 3))
        if self.controls is not None:
            c = np.asarray(self.controls, np.float64)
            if c.ndim != 2 or c.shape[0] != v:
                raise InputError(f"controls must have shape ({v}, C), got {c.shape}")
            object.__setattr__(self, "controls", c)

    def save(self, path: str | os.PathLike[str]) -> None:
        arrays = {"postures": self.postures, "triangles": self.triangles}
        arrays.update({f"group__{g}": i for g, i in self.groups.items()})
        if self.controls is not None:
            arrays["controls"] = self.controls
        meta = {
            "name": self.name,
            "posture_names": list(self.posture_names),
            "point_names": list(self.point_names),
            "groups": list(self.groups),
            "feature_points": {k: int(v) for k, v in self.feature_points.items()},
            "fapu_overrides": dict(self.fapu_overrides),
            "control_names": list(self.control_names),
        }
        save_bundle(path, CORPUS_KIND, CORPUS_VERSION, arrays, meta)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Corpus:
        arrays, meta = load_bundle(path, CORPUS_KIND, (CORPUS_VERSION,))
        with reading(path, "corpus"):
            require("postures" in arrays, path, "missing array 'postures'")
            x = arrays["postures"]
            require(x.ndim == 3 and x.shape[2] == 3, path,
                    f"postures have shape {x.shape}, expected (V, N, 3)")
            v, n, _ = x.shape
            require(len(meta.get("posture_names", [])) == v, path, "posture names do not match")
            require(len(meta.get("point_names", [])) == n, path, "point names do not match")
            groups = {g: arrays.get(f"group__{g}", np.zeros(0, np.int64)) for g in meta["groups"]}
            for g, i in groups.items():
                require(i.size == 0 or (i.min() >= 0 and i.max() < n), path,
                        f"group {g!r} indexes points that do not exist")
            tri = arrays.get("triangles", np.zeros((0, 3), np.int32))
            require(tri.size == 0 or (tri.min() >= 0 and tri.max() < n), path,
                    "triangles index points that do not exist")
            return cls(x, tuple(meta["posture_names"]), tuple(meta["point_names"]), groups, tri,
                       meta.get("feature_points", {}), meta.get("fapu_overrides", {}),
                       arrays.get("controls"), tuple(meta.get("control_names", [])),
                       str(meta.get("name", "speaker")))


@dataclass(frozen=True)
class VarianceTable:
    """Per-step variance explained (%) and reconstruction error of the corpus."""

    names: tuple[str, ...]
    variance_pct: np.ndarray  # (K,)
    cumulative_pct: np.ndarray  # (K,)
    rms_mm_per_posture: dict[str, float]

    def format(self) -> str:
        """Text like the paper's Table 1."""
        lines = ["parameter   variance %   cumulative %", "---------   ----------   ------------"]
        for n, v, c in zip(self.names, self.variance_pct, self.cumulative_pct, strict=True):
            lines.append(f"{n:<9}   {v:10.2f}   {c:12.2f}")
        rms = np.array(list(self.rms_mm_per_posture.values()))
        lines.append("")
        lines.append(
            f"direct inversion RMS over {rms.size} postures: median {np.median(rms):.3f} mm, "
            f"mean {rms.mean():.3f} mm, max {rms.max():.3f} mm"
        )
        return "\n".join(lines)

    def to_json(self) -> dict:
        return {
            "variance": {n: float(v) for n, v in zip(self.names, self.variance_pct, strict=True)},
            "cumulative": float(self.cumulative_pct[-1]),
            "cumulative_per_parameter": {
                n: float(v) for n, v in zip(self.names, self.cumulative_pct, strict=True)
            },
            "rms_mm_per_posture": self.rms_mm_per_posture,
        }


def _guide_columns(name: str, groups: Mapping[str, np.ndarray], n: int) -> np.ndarray:
    """Flat column indices (into N*3) of parameter ``name``'s guide subset."""
    gnames, coords, _ = GUIDES[name]
    if gnames == ("__not_lips_teeth__",):
        excluded = np.concatenate([groups.get(g, np.zeros(0, np.int64)) for g in
                                   (*LIPS, "upper_lip", "lower_lip", "lower_teeth")])
        pts = np.setdiff1d(np.arange(n), excluded)
    else:
        pts = np.unique(np.concatenate(
            [groups.get(g, np.zeros(0, np.int64)) for g in gnames]
        )).astype(np.int64)
        if pts.size == 0:
            raise InputError(
                f"{name} needs point group(s) {' or '.join(gnames)}, which the corpus lacks"
            )
    return (pts[:, None] * 3 + np.asarray(coords)[None, :]).ravel()


def _sign(name: str, b: np.ndarray, groups: Mapping[str, np.ndarray], mean: np.ndarray) -> float:
    """+1 or -1 so that the parameter's positive direction follows :data:`GUIDES`."""
    kind, group, want = GUIDES[name][2]
    idx = groups.get(group, np.zeros(0, np.int64))
    if idx.size == 0:
        return 1.0
    if kind in ("y", "z"):
        score = b[idx, "xyz".index(kind)].mean()
    elif kind == "width":  # outward x motion of points on either side
        score = (b[idx, 0] * np.sign(mean[idx, 0] - mean[idx, 0].mean())).mean()
    else:  # corners_y: y motion of the two most lateral points
        order = np.argsort(mean[idx, 0])
        score = b[idx[[order[0], order[-1]]], 1].mean()
    return 1.0 if score * want >= 0 else -1.0


def build_model(
    corpus: Corpus, names: tuple[str, ...] = PARAM_NAMES,
    unmoved: Mapping[str, tuple[str, ...]] | None = None,
) -> tuple[FaceModel, VarianceTable]:
    """Guided iterative PCA of ``corpus`` -> (model, variance table).

    For each parameter in order: first principal component of the residual restricted to its
    guide subset, centred and scaled to unit variance; the whole residual is regressed on it
    and deflated.
    unmoved : parameter name -> point groups its basis does not move (their regression on the
        parameter is set to zero, so their motion stays in the residual for the parameters
        after it); none by default.
    """
    x = corpus.postures
    v, n, _ = x.shape
    if v < len(names) + 1:
        raise InputError(f"{v} postures cannot determine {len(names)} parameters")
    mean = x.mean(0)
    r = (x - mean).reshape(v, -1)
    total = float((r**2).sum())
    if np.ptp(x, axis=0).max() < 1e-9:
        raise InputError("all postures are identical: nothing to model")
    basis, scores, explained = [], [], []
    for name in names:
        cols = _guide_columns(name, corpus.groups, n)
        sub = r[:, cols]
        _, s, vt = np.linalg.svd(sub, full_matrices=False)
        if s[0] <= 1e-9 * np.sqrt(total):
            raise InputError(f"guide subset of {name} has no variance left: corpus is degenerate")
        p = sub @ vt[0]
        p = (p - p.mean()) / p.std()
        b = r.T @ p / (p @ p)
        for g in (unmoved or {}).get(name, ()):
            rows = corpus.groups.get(g, np.zeros(0, np.int64))
            b.reshape(n, 3)[rows] = 0.0
        sgn = _sign(name, b.reshape(n, 3), corpus.groups, mean)
        p, b = p * sgn, b * sgn
        before = float((r**2).sum())
        r = r - np.outer(p, b)
        explained.append(100.0 * (before - float((r**2).sum())) / total)
        basis.append(b.reshape(n, 3))
        scores.append(p)
    scores_arr = np.stack(scores, 1)
    model = FaceModel(
        mean=mean,
        basis=np.stack(basis),
        param_names=tuple(names),
        stats=ParamStats.from_scores(scores_arr),
        point_names=corpus.point_names,
        groups=corpus.groups,
        triangles=corpus.triangles,
        feature_points=corpus.feature_points,
        fapu_overrides=corpus.fapu_overrides,
        name=corpus.name,
    )
    alpha = invert(model, x)
    err = model.shape(alpha) - x
    rms = np.sqrt((err**2).sum(-1).mean(-1))
    var = np.array(explained)
    table = VarianceTable(
        tuple(names), var, np.cumsum(var),
        {p: float(e) for p, e in zip(corpus.posture_names, rms, strict=True)},
    )
    return model, table


def invert(
    model: FaceModel, points: np.ndarray, subset: np.ndarray | None = None
) -> np.ndarray:
    """Direct inversion: least-squares alpha from 3D points.

    points : (..., N, 3) mm head frame (or (..., len(subset), 3) with ``subset``).
    Returns alpha (..., K).
    """
    pts = np.asarray(points, dtype=np.float64)
    idx = np.arange(model.n_points) if subset is None else np.asarray(subset)
    if pts.shape[-2:] != (idx.size, 3):
        raise InputError(f"points must end in ({idx.size}, 3), got {pts.shape}")
    a = model.basis[:, idx, :].reshape(model.n_params, -1).T  # (3M, K)
    rhs = (pts - model.mean[idx]).reshape(pts.shape[:-2] + (-1,))
    sol, *_ = np.linalg.lstsq(a, rhs.reshape(-1, a.shape[0]).T, rcond=None)
    return sol.T.reshape(pts.shape[:-2] + (model.n_params,))
