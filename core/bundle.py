"""Versioned ``.npz`` bundles: named float/int arrays plus one JSON metadata document.

Every file articast writes (face models, corpora, appearance models, dense meshes) is such a
bundle, so every loader rejects a wrong kind, a wrong version, a truncated file or NaNs with
one clear :class:`~articast.core.errors.ModelFileError` instead of a numpy traceback.
No pickles: arrays are loaded with ``allow_pickle=False``.
"""

from __future__ import annotations

import contextlib
import json
import os
import struct
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.errors import ArticastError, InputError, ModelFileError
from articast.core.safe_io import load_npz

_META_KEY = "__meta__"
MAX_VALUE = 1e15
"""Largest |value| of any float array in a bundle: beyond it, squares and products overflow
(1e308 in a model ended in LinAlgError)."""


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
    if path.is_dir():
        raise ModelFileError(f"{where}: is a folder, expected an articast {kind} file")
    if not os.path.lexists(path):
        raise ModelFileError(f"{where}: no such file")
    try:
        with load_npz(path) as npz:
            names = list(npz.files)
            if _META_KEY not in names:
                raise ModelFileError(f"{where}: not an articast {kind} file (no metadata)")
            meta = json.loads(bytes(npz[_META_KEY]).decode("utf-8"))
            arrays = {n: np.array(npz[n]) for n in names if n != _META_KEY}
    except ModelFileError:
        raise
    except InputError as exc:  # not a regular file, or an archive declaring too much
        raise ModelFileError(str(exc)) from None
    except READ_ERRORS as exc:
        raise ModelFileError(
            f"{where}: cannot read as an articast {kind} file (truncated or not an npz "
            f"archive: {exc.__class__.__name__})"
        ) from None
    if not isinstance(meta, dict) or meta.get("kind") != kind:
        found = meta.get("kind") if isinstance(meta, dict) else None
        shown = repr(found) if found in KNOWN_KINDS else "another kind"
        raise ModelFileError(f"{where}: expected an articast {kind} file, found {shown}")
    version = meta.get("version")
    if version not in versions:
        shown = repr(version) if isinstance(version, int) else "an unknown one"
        raise ModelFileError(
            f"{where}: {kind} format version {shown} is not supported "
            f"(this articast reads version {', '.join(map(str, versions))})"
        )
    for name, arr in arrays.items():
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise ModelFileError(f"{where}: array {name!r} contains NaN or infinite values")
        if arr.dtype.kind == "f" and arr.size and float(np.max(np.abs(arr))) > MAX_VALUE:
            raise ModelFileError(f"{where}: array {name!r} holds values beyond {MAX_VALUE:g}, "
                                 "which no articast file does")
    return arrays, meta


READ_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError,
               TypeError, IndexError, AttributeError, UnicodeDecodeError, struct.error,
               NotImplementedError, RuntimeError, OverflowError, RecursionError)
"""What numpy, zipfile, zlib and json raise on a corrupt or hostile file."""

KNOWN_KINDS = ("face-model", "appearance-model", "posture-corpus", "dense-binding",
               "landmark-observation")
"""Kinds named in an error (anything else a file claims to be is not echoed)."""


@contextlib.contextmanager
def reading(path: str | os.PathLike[str], what: str) -> Iterator[None]:
    """Turn any decoding error inside the block into one :class:`ModelFileError` line.

    Used around the checks after :func:`load_bundle`: a field of the wrong type or a
    missing metadata key is a defect of the file, not of articast.
    """
    try:
        yield
    except ArticastError as exc:
        if str(path) in str(exc):
            raise
        raise ModelFileError(f"{path}: {exc}") from None
    except READ_ERRORS as exc:
        detail = f"missing field {exc}" if isinstance(exc, KeyError) else type(exc).__name__
        raise ModelFileError(f"{path}: malformed {what} file ({detail})") from None


def require(cond: bool, path: str | os.PathLike[str], message: str) -> None:
    """Raise :class:`ModelFileError` with ``path: message`` unless ``cond``."""
    if not cond:
        raise ModelFileError(f"{path}: {message}")
