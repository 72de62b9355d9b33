"""The speaker's own face as a VRM 1.0 avatar, served to the browser's VRM page
(``GET /api/sessions/NAME/vrm``): what ``articast export-vrm`` writes, made from the session's
speaker folder (its ``delegate.npz``) and the model the session streams, so that its morph
targets are that model's. Like the delegate it is a picture of the speaker's face: served only
with the token, ``Cache-Control: no-store``, never logged, none with ``serve --no-delegate``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from articast.core.errors import InputError

_CACHE: dict[tuple[str, int, int, tuple[str, ...]], bytes] = {}


def vrm_bytes(path: Path, desc: dict[str, Any]) -> bytes:
    """The VRM of the delegate at ``path`` for a session described by ``desc`` (cached per
    file version and model; one clear error when the delegate was made for another model)."""
    from articast.core.delegate.build import Delegate
    from articast.core.delegate.vrm import to_vrm
    from articast.service.wire import model_from_description

    st = path.stat()
    key = (str(path), st.st_mtime_ns, st.st_size, tuple(desc["param_names"]))
    data = _CACHE.get(key)
    if data is None:
        model = model_from_description(desc)
        if model is None:
            raise InputError("the session has no face model")
        delegate = Delegate.load(path)
        if tuple(delegate.param_names) != tuple(model.param_names):
            raise InputError(f"{path} was made for another model: rebuild it with "
                             "'articast delegate'")
        name = str((desc.get("geometry") or {}).get("name") or "speaker")
        data = to_vrm(model, delegate.mesh, delegate.texture, name=name)
        _CACHE.clear()  # one speaker's face at a time in memory
        _CACHE[key] = data
    return data
