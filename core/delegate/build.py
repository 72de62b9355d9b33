"""The delegate file (``SPEAKER_DIR/delegate.npz``) and how it is made.

A delegate is the speaker's own face for the remote end: the full-face mesh fitted to the
speaker and moved by their model (:mod:`~articast.core.delegate.geometry`) and its texture,
linear in the articulation (:mod:`~articast.core.delegate.texture`). It is personal data (a
picture of a face): the server serves it only with the session's token, never logs it, and
``serve --no-delegate`` serves none.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from articast.core.bundle import load_bundle, reading, require, save_bundle
from articast.core.delegate.geometry import DelegateMesh, fit_mesh
from articast.core.delegate.texture import (
    MIN_WEIGHT,
    TEXTURE_SIZE,
    build_texture,
    texture_at,
    uv_raster,
)
from articast.core.errors import InputError
from articast.core.model.camera import Camera, Pose
from articast.core.model.face import FaceModel

DELEGATE_KIND = "articast-delegate"
DELEGATE_VERSION = 1
DELEGATE_FILE = "delegate.npz"
MAX_TEXTURE_FRAMES = 150
"""Frames a delegate's texture is fitted on (spread over the clip; more add little)."""


@dataclass(frozen=True, eq=False)
class Delegate:
    """mesh : the moving surface; texture : (S, S, 3) uint8 BGR, T0 at alpha = 0;
    texture_modes : (K, S, S, 3) float32 grey levels per unit alpha (``tex lin``; stored as
        int8 half grey levels, so within +-63.5 per s.d.);
    seen : (S, S) float32, the weight each texel was seen with (0: filled);
    param_names : the model's K parameter names; report : how it was made."""

    mesh: DelegateMesh
    texture: np.ndarray
    texture_modes: np.ndarray
    seen: np.ndarray
    param_names: tuple[str, ...]
    report: dict[str, Any] = field(default_factory=dict)

    def texture_at(self, alpha: np.ndarray) -> np.ndarray:
        """(S, S, 3) uint8 BGR texture at ``alpha``."""
        return texture_at(self.texture.astype(np.float32), self.texture_modes, alpha)

    def save(self, path: str | os.PathLike[str]) -> None:
        m = self.mesh
        arrays = {"vertices": m.vertices, "modes": m.modes, "uv": m.uv,
                  "triangles": m.triangles, "model_index": m.model_index,
                  "texture": self.texture,
                  "texture_modes": np.clip(np.round(self.texture_modes * 2), -127, 127
                                           ).astype(np.int8),
                  "seen": self.seen.astype(np.float32)}
        save_bundle(path, DELEGATE_KIND, DELEGATE_VERSION, arrays,
                    {"param_names": list(self.param_names), "report": self.report})

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Delegate:
        arrays, meta = load_bundle(path, DELEGATE_KIND, (DELEGATE_VERSION,))
        with reading(path, "delegate"):
            for key in ("vertices", "modes", "uv", "triangles", "model_index", "texture",
                        "texture_modes", "seen"):
                require(key in arrays, path, f"missing array {key!r}")
            v, modes, uv, tri = (arrays[k] for k in ("vertices", "modes", "uv", "triangles"))
            n = len(v)
            require(v.ndim == 2 and v.shape[1] == 3 and n > 0, path, "vertices must be (V, 3)")
            require(modes.ndim == 3 and modes.shape[1:] == (n, 3), path,
                    f"modes must be (K, {n}, 3)")
            require(uv.shape == (n, 2), path, f"uv must be ({n}, 2)")
            # what the avatar and the glTF export draw: texture coordinates in the texture,
            # and a surface (every vertex at one place, or uv of 1e15, loaded silently)
            require(bool(np.all((uv >= -0.01) & (uv <= 1.01))), path,
                    "uv must lie within [0, 1]")
            spread = (np.linalg.svd(v - v.mean(axis=0), compute_uv=False) if n >= 3
                      else np.zeros(2))
            require(float(spread[1]) > 1e-3, path,
                    "the vertices do not span a surface (all at one place, or on one line)")
            require(tri.ndim == 2 and tri.shape[1] == 3 and tri.size > 0
                    and tri.min() >= 0 and tri.max() < n, path,
                    "triangles must index the vertices")
            tex = arrays["texture"]
            require(tex.dtype == np.uint8 and tex.ndim == 3 and tex.shape[2] == 3
                    and tex.shape[0] == tex.shape[1] and tex.shape[0] >= 8, path,
                    "texture must be (S, S, 3) uint8")
            k = modes.shape[0]
            tm = arrays["texture_modes"]
            require(tm.shape == (k, *tex.shape) and tm.dtype == np.int8, path,
                    f"texture_modes must be ({k}, S, S, 3) int8")
            require(arrays["model_index"].shape == (n,), path, f"model_index must be ({n},)")
            require(arrays["seen"].shape == tex.shape[:2], path, "seen must be (S, S)")
            names = tuple(str(x) for x in meta.get("param_names", []))
            require(len(names) == k, path, f"{len(names)} parameter names for {k} modes")
            mesh = DelegateMesh(v.astype(np.float64), modes.astype(np.float64),
                                uv.astype(np.float64), tri.astype(np.int32),
                                arrays["model_index"].astype(np.int64))
            report = meta.get("report")
            return cls(mesh, tex, tm.astype(np.float32) / 2.0,
                       arrays["seen"].astype(np.float32), names,
                       report if isinstance(report, dict) else {})


def build_delegate(model: FaceModel, camera: Camera,
                   frames: Sequence[tuple[np.ndarray, np.ndarray, Pose]],
                   size: int = TEXTURE_SIZE) -> Delegate:
    """The delegate of ``model`` textured from ``frames`` (image BGR uint8 at the camera's
    size, alpha (K,), pose): the speaker's frames at their tracked states."""
    if not frames:
        raise InputError("a delegate needs frames of the speaker at tracked states")
    mesh = fit_mesh(model)
    t0, modes, seen = build_texture(mesh, frames, camera, size, support=mesh.support())
    covered = len(uv_raster(mesh.uv, mesh.triangles, size).texel)
    report = {"frames": len(frames), "texture_size": int(size), "vertices": len(mesh.vertices),
              "triangles": len(mesh.triangles),
              "texels_seen_pct": round(100.0 * float((seen >= MIN_WEIGHT).sum()) / covered, 1)}
    return Delegate(mesh, np.clip(np.round(t0), 0, 255).astype(np.uint8),
                    np.clip(modes, -63.5, 63.5).astype(np.float32), seen,
                    tuple(model.param_names), report)


def tracked_frames(speaker: Any, images: Sequence[np.ndarray], finder: Any,
                   max_frames: int = MAX_TEXTURE_FRAMES, times: Any = None
                   ) -> list[tuple[np.ndarray, np.ndarray, Pose]]:
    """The speaker's ``images`` (in clip order) tracked live, as a subscriber would see them
    (:class:`~articast.core.faces.live.LiveTracker`, the bundled face finder ``finder``): at
    most ``max_frames`` of the frames it marks ok, spread over the clip, each with its state.
    times : (F,) when each image was taken, s (default 25 a second)."""
    from articast.core.faces.live import LiveTracker
    from articast.core.faces.scheme import mediapipe_scheme

    live = LiveTracker(speaker, finder, mediapipe_scheme(speaker.rig))
    good = []
    for i, img in enumerate(images):
        res = live.track(img, float(times[i]) if times is not None else i / 25.0)
        if res.ok:
            good.append((img, np.asarray(res.alpha, np.float64), res.pose))
    if len(good) > max_frames:
        pick = np.linspace(0, len(good) - 1, max_frames).round().astype(int)
        good = [good[i] for i in pick]
    return good
