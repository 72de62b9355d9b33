"""A bound, textured head scan served to the browser avatar (``serve``/``demo --scan FILE``).

The file is a binding written by ``articast bind-dense SCAN --landmarks ...`` with its texture
(:mod:`articast.core.dense.texture`). Per session, the scan's dense modes are computed from
the session's model once (a fraction of a second) and served as JSON; the client animates the
scan linearly from the streamed alpha as it does the dense face, and draws it textured.
"""

from __future__ import annotations

import hashlib
import os
import threading
from typing import Any

import numpy as np

from articast.core.bundle import load_bundle
from articast.core.dense.texture import ScanTexture, mouth_cavity, texture_from_arrays
from articast.core.dense.transfer import BINDING_KIND, BINDING_VERSION, Binding, dense_modes
from articast.core.errors import InputError, ModelFileError
from articast.service.jsonsafe import dumps

MATCH_MM = 1e-3
"""The binding's sparse mesh and the session model's mean agree this closely (float32 on the
wire) when the scan was bound to that model."""


class ScanAsset:
    """The binding and its texture, loaded once at start-up; JSON per model, cached."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = str(path)
        self.binding = Binding.load(path)
        arrays, _ = load_bundle(path, BINDING_KIND, (BINDING_VERSION,))
        try:
            texture = texture_from_arrays(arrays, self.binding.n_dense, self.path)
        except InputError as exc:
            raise ModelFileError(str(exc)) from None
        if texture is None:
            raise ModelFileError(f"{path}: the binding has no texture: bind the scan with its "
                                 ".obj's material or --texture IMG (articast bind-dense)")
        self.texture: ScanTexture = texture
        self._json: dict[str, bytes] = {}
        self._lock = threading.Lock()

    def json_for(self, model: Any) -> bytes:
        """``{n_points, mean (3M), basis (K*3M), triangles (3Q), render_index (R), uv (2R),
        render_triangles (3Q'), texture_type, scan_points}`` for ``model``: the scan's points
        then those of the dark mouth cavity behind the lips (uv -1, -1;
        :func:`~articast.core.dense.texture.mouth_cavity`). :class:`InputError` when the scan
        was bound to another model. Blocking (call from a worker thread)."""
        mean = np.asarray(model.mean, np.float64)
        b = self.binding
        if mean.shape != b.sparse_vertices.shape or np.abs(
                mean - b.sparse_vertices).max() > MATCH_MM:
            raise InputError(f"the scan {os.path.basename(self.path)} was bound to another "
                             "model than this session's (bind it to the session's model)")
        key = hashlib.sha256(mean.astype(np.float32).tobytes()
                             + np.asarray(model.basis, np.float32).tobytes()).hexdigest()
        with self._lock:
            if key not in self._json:
                self._json[key] = self._build(model)
            return self._json[key]

    def _build(self, model: Any) -> bytes:
        b, t = self.binding, self.texture
        dmean, modes = dense_modes(b, model)
        # the facets the texture leaves out (across the lips) get a dark cavity behind them
        tris = b.dense_triangles
        drawn_keys = set(map(tuple, np.sort(t.render_index[t.triangles], axis=1).tolist()))
        drawn = np.array([tuple(r) in drawn_keys for r in np.sort(tris, axis=1).tolist()], bool)
        cav, cav_modes, cav_tris = mouth_cavity(dmean, modes, tris, drawn)
        m, c, r = b.n_dense, len(cav), len(t.render_index)
        # cavity facets index [points; cavity points]; in the render mesh the cavity's
        # render vertices follow the scan's (R), one per cavity facet corner point
        cav_points = np.unique(cav_tris)
        render_of = np.zeros(m + c, np.int64)
        render_of[cav_points] = r + np.arange(len(cav_points))
        return dumps({
            "n_points": m + c,
            "mean": np.concatenate([dmean, cav]).astype(np.float32).ravel().tolist(),
            "basis": np.concatenate([modes, cav_modes], axis=1).astype(np.float32).ravel()
            .tolist(),
            "triangles": np.concatenate([tris, cav_tris]).ravel().tolist(),
            "render_index": np.concatenate([t.render_index, cav_points]).tolist(),
            "uv": np.concatenate([t.uv, np.full((len(cav_points), 2), -1.0)]).astype(
                np.float32).ravel().tolist(),
            "render_triangles": np.concatenate([t.triangles, render_of[cav_tris]]).ravel()
            .tolist(),
            "texture_type": t.mime,
            "scan_points": m,
        }).encode()
