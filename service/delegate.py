"""The speaker's delegate served to subscribers (``GET /api/sessions/NAME/delegate``).

A session tracked with a speaker folder that holds a delegate (``articast enroll`` writes
``delegate.npz``; ``articast delegate`` rebuilds it) offers it in its hello
(``delegate_url``), unless the server runs with ``--no-delegate``. It is a picture of the
speaker's face: served only with the session's token (like subscribing), with
``Cache-Control: no-store``, and never logged (nothing here logs; the access log names the
path only).

The JSON a browser animates (everything in the head frame, mm, like ``hello.geometry``):

``{n_vertices, param_names, mean (3V), basis (K*3V: vertices + sum_k alpha_k basis_k),
triangles (3T), uv (2V, v down), texture (data URL, PNG: T0, the texture at alpha = 0),
modes (data URL, PNG: the K texture modes side by side on a grid of modes_grid [columns,
rows] tiles of the texture's size, byte b meaning (b - 128) * modes_scale grey levels per
unit alpha), modes_grid, modes_scale, upper}``

``upper`` (null for a mesh other than MediaPipe's 468 points) moves the speaker's own lids,
eyes and brows as the stream's ARKit eye and brow shapes say (the VRM export's targets,
:func:`articast.core.delegate.vrm.upper_face_targets`: eyeBlink brings the upper lid onto the
lower lid, eyeLook* moves the painted eye within its socket): ``{targets: {NAME: {index,
delta}}}`` (the moved vertices and their moves, mm, 3 per vertex, at weight 1) and the full
scales the page turns the frame's ``eyes`` and ``brows`` blocks into weights with
(``gaze_full_deg``, ``brow_full_mm``, ``brow_down_full_mm``, ``wide_dead``, ``wide_full``,
``squint_full``, :mod:`articast.core.outputs.upper`).
"""

from __future__ import annotations

import base64
from pathlib import Path

import cv2
import numpy as np

from articast.core.delegate.build import DELEGATE_FILE, Delegate
from articast.core.delegate.geometry import DelegateMesh
from articast.core.errors import InputError
from articast.core.safe_io import check_confined
from articast.service.jsonsafe import dumps

MODES_SCALE = 0.5
"""Grey levels per unit alpha of one step of a mode byte (the file's own int8 step)."""


def delegate_path(speaker_dir: str, roots: tuple[str, ...] = ()) -> Path | None:
    """The delegate file of a speaker folder, or None when it has none; under ``roots``
    when given (a session added over HTTP)."""
    if not speaker_dir:
        return None
    path = Path(speaker_dir) / DELEGATE_FILE
    if not path.is_file():
        return None
    check_confined(path, roots, "delegate")
    return path


def _png(image: np.ndarray) -> str:
    ok, data = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise InputError("the delegate's texture could not be encoded")
    return "data:image/png;base64," + base64.b64encode(data.tobytes()).decode("ascii")


def delegate_payload(delegate: Delegate) -> dict:
    """The JSON document of the module docstring."""
    m = delegate.mesh
    k, s = len(delegate.param_names), delegate.texture.shape[0]
    cols = int(np.ceil(np.sqrt(k))) if k else 1
    rows = int(np.ceil(k / cols)) if k else 1
    grid = np.full((rows * s, cols * s, 3), 128, np.uint8)
    for i, mode in enumerate(delegate.texture_modes):
        r, c = divmod(i, cols)
        grid[r * s:(r + 1) * s, c * s:(c + 1) * s] = np.clip(
            np.round(128 + mode / MODES_SCALE), 1, 255).astype(np.uint8)
    return {"n_vertices": len(m.vertices), "param_names": list(delegate.param_names),
            "mean": np.round(m.vertices, 3).ravel().tolist(),
            "basis": np.round(m.modes, 4).ravel().tolist(),
            "triangles": m.triangles.ravel().tolist(),
            "uv": np.round(m.uv, 5).ravel().tolist(),
            "texture": _png(delegate.texture), "modes": _png(grid),
            "modes_grid": [cols, rows], "modes_scale": MODES_SCALE,
            "upper": upper_payload(m)}


def upper_payload(mesh: DelegateMesh) -> dict | None:
    """The ``upper`` block of the module docstring (None for a mesh it cannot name the lids
    of)."""
    from articast.core.delegate.vrm import N_VERTICES, upper_face_targets
    from articast.core.outputs import upper as U

    if mesh.vertices.shape != (N_VERTICES, 3):
        return None
    targets = {}
    for name, move in upper_face_targets(mesh).items():
        index = np.flatnonzero(np.abs(move).max(1) >= 1e-3)
        targets[name] = {"index": index.tolist(),
                         "delta": np.round(move[index], 3).ravel().tolist()}
    return {"targets": targets, "gaze_full_deg": U.GAZE_FULL_DEG, "brow_full_mm": U.BROW_FULL_MM,
            "brow_down_full_mm": U.BROW_DOWN_FULL_MM, "wide_dead": U.WIDE_DEAD,
            "wide_full": U.WIDE_FULL, "squint_full": U.SQUINT_FULL}


def delegate_json(path: Path, param_names: list[str]) -> bytes:
    """The payload of the delegate at ``path`` for a session whose model has
    ``param_names`` (one clear error when it was made for another model)."""
    delegate = Delegate.load(path)
    if list(delegate.param_names) != list(param_names):
        raise InputError(f"{path} was made for another model (parameters "
                         f"{list(delegate.param_names)}): rebuild it with 'articast delegate'")
    return dumps(delegate_payload(delegate)).encode()
