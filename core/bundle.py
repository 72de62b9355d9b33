"""Versioned ``.npz`` bundles: named float/int arrays plus one JSON metadata document.

Every file articast writes (face models, corpora, appearance models, dense meshes) is such a
bundle, so every loader rejects a wrong kind, a wrong version, a truncated file or NaNs with
one clear :class:`~articast.core.errors.ModelFileError` instead of a numpy traceback.
No pickles: arrays are loaded with ``allow_pickle=False``.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.errors import ModelFileError

_META_KEY = "__meta__"


def save_bundle(
    path: str | os.PathLike[str],
    kind: str,
    version: int,
    arrays: dict[str, np.ndarray],
    meta: dict[str, Any],
) -> None:
    """Write ``arrays`` and ``meta`` to ``path`` atomically (temp file + rename)."""
    path = Path(path)
    doc = {"kind": kind, "version": int(version), **meta}
    blob = np.frombuffer(json.dumps(doc, sort_keys=True).encode("utf-8"), dtype=np.uint8)
    for name, arr in arrays.items():
        if name == _META_KEY:
            raise ValueError(f"array name {_META_KEY!r} is reserved")
        if np.asarray(arr).dtype == object:
            raise ValueError(f"array {name!r} has dtype object; bundles hold numbers only")
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        np.savez_compressed(fh, **{_META_KEY: blob}, **arrays)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def load_bundle(
    path: str | os.PathLike[str],
    kind: str,
    versions: tuple[int, ...],
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a bundle written by :func:`save_bundle`.

    Returns ``(arrays, meta)``. Raises :class:`ModelFileError` naming the file and the problem
    when the file is missing, not an npz archive, truncated, of another kind or version.
    """
    path = Path(path)
    where = f"{path}"
    if not path.is_file():
        raise ModelFileError(f"{where}: no such file")
    try:
        with np.load(path, allow_pickle=False) as npz:
            names = list(npz.files)
            if _META_KEY not in names:
                raise ModelFileError(f"{where}: not an articast {kind} file (no metadata)")
            meta = json.loads(bytes(npz[_META_KEY]).decode("utf-8"))
            arrays = {n: np.array(npz[n]) for n in names if n != _META_KEY}
    except ModelFileError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError, UnicodeDecodeError) as exc:
        raise ModelFileError(
            f"{where}: cannot read as an articast {kind} file (truncated or not an npz "
            f"archive: {exc.__class__.__name__})"
        ) from None
    if not isinstance(meta, dict) or meta.get("kind") != kind:
        found = meta.get("kind") if isinstance(meta, dict) else None
        raise ModelFileError(f"{where}: expected an articast {kind} file, found kind {found!r}")
    version = meta.get("version")
    if version not in versions:
        raise ModelFileError(
            f"{where}: {kind} format version {version!r} is not supported "
            f"(this articast reads version {', '.join(map(str, versions))})"
        )
    for name, arr in arrays.items():
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise ModelFileError(f"{where}: array {name!r} contains NaN or infinite values")
    return arrays, meta


def require(cond: bool, path: str | os.PathLike[str], message: str) -> None:
    """Raise :class:`ModelFileError` with ``path: message`` unless ``cond``."""
    if not cond:
        raise ModelFileError(f"{path}: {message}")
