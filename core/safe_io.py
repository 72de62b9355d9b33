"""Opening input files without trusting them: regular files only, bounded reads.

Every loader opens its file through here, so a FIFO (which would block ``open`` or ``read``
for ever), a device (``/dev/zero``: endless), a folder or a file larger than the loader can
sensibly take is one :class:`~articast.core.errors.InputError` naming the file, before any
byte is parsed. The file is opened non-blocking and checked with ``fstat`` on the open
descriptor, so what is checked is what is read (no swap between a check and the open).

``.npz`` archives are checked before NumPy inflates them: every member's declared size, and
the shape its ``.npy`` header declares, must fit ``max_bytes`` (a 4 MB archive may declare
4 GB, or 1e14 elements).
"""

from __future__ import annotations

import errno
import io
import json
import os
import stat
import zipfile
from pathlib import Path
from typing import IO, Any

import numpy as np

from articast.core.errors import InputError

MAX_TEXT_BYTES = 256 * 2**20
"""JSON, JSON lines, .obj, .fap: far above any real file of ours (a 10-minute recording
with meshes is ~60 MB)."""
MAX_NPZ_BYTES = 2**30
"""Inflated size of a model/appearance/corpus/binding archive: 1 GiB (the largest real one
is ~50 MB)."""


def _where(what: str, path: Any) -> str:
    return f"{what} {path}" if what else f"{path}"


def open_regular(path: str | os.PathLike[str], what: str = "",
                 max_bytes: int | None = None, *, follow_symlinks: bool = True) -> IO[bytes]:
    """``path`` opened for reading in binary, if it is a regular file of at most
    ``max_bytes``; else :class:`InputError` naming it. ``follow_symlinks=False`` refuses a
    symbolic link as the last component (``O_NOFOLLOW``)."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    if not follow_symlinks:
        flags |= getattr(os, "O_NOFOLLOW", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise InputError(f"{_where(what, path)}: {open_failure(exc, follow_symlinks)}"
                         ) from None
    except ValueError:  # a NUL byte in the name
        raise InputError(f"{_where(what, repr(str(path)))}: not a valid file name") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = ("a folder" if stat.S_ISDIR(st.st_mode) else
                    "a FIFO" if stat.S_ISFIFO(st.st_mode) else
                    "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode) else
                    "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
            raise InputError(f"{_where(what, path)}: is {kind}, not a regular file")
        if max_bytes is not None and st.st_size > max_bytes:
            raise InputError(f"{_where(what, path)}: {st.st_size} bytes, over the limit of "
                             f"{max_bytes} bytes for this kind of file")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def open_failure(exc: OSError, follow_symlinks: bool = True) -> str:
    """Why a name could not be opened, in words: a link loop said "cannot open it (Too many
    levels of symbolic links)" (issue 39)."""
    if exc.errno == errno.ELOOP:
        return ("a symbolic link loop (its links lead back to themselves)" if follow_symlinks
                else "is a symbolic link, refused here")
    return f"cannot open it ({exc.strerror or exc})"


def inside(real: str, roots: tuple[str, ...]) -> bool:
    """``real`` (a resolved path) is one of ``roots`` or below one."""
    for root in roots:
        r = os.path.realpath(root)
        if real == r or real.startswith(r.rstrip(os.sep) + os.sep):
            return True
    return False


def opened_path(fh: IO[Any]) -> str:
    """The file an open descriptor really is (Linux: its /proc/self/fd link), whatever
    links its name went through."""
    fd = fh.fileno()
    try:
        return os.readlink(f"/proc/self/fd/{fd}")
    except OSError:  # no /proc: resolve the name (the check is then by name, not by fd)
        return os.path.realpath(fh.name) if isinstance(fh.name, str) else ""


def open_confined(path: str | os.PathLike[str], roots: tuple[str, ...], what: str = "",
                  max_bytes: int | None = None) -> IO[bytes]:
    """:func:`open_regular`, and then, if ``roots`` are given, the file actually opened must
    lie under one of them (checked on the descriptor at every open: a link swapped in after
    the session was accepted is caught, and so is a link inside a root's folder pointing
    out of it). Readers that need a name (OpenCV) pass ``/proc/self/fd/N`` of the result."""
    fh = open_regular(path, what, max_bytes)
    if roots and not inside(opened_path(fh), roots):
        fh.close()
        raise InputError(f"{_where(what, path)}: not under the server's media roots (it "
                         "resolves outside them now)")
    return fh


def check_confined(path: str | os.PathLike[str], roots: tuple[str, ...],
                   what: str = "") -> None:
    """For loaders that open by name: ``path`` resolved now must lie under ``roots``
    (nothing to check when there are none)."""
    if roots and not inside(os.path.realpath(path), roots):
        raise InputError(f"{_where(what, path)}: not under the server's media roots (it "
                         "resolves outside them now)")


def require_regular(path: str | os.PathLike[str], what: str = "",
                    max_bytes: int | None = None) -> Path:
    """Check ``path`` is a regular file (of at most ``max_bytes``) and return it: for
    readers that open by name themselves (OpenCV)."""
    open_regular(path, what, max_bytes).close()
    return Path(path)


def read_regular_bytes(path: str | os.PathLike[str], max_bytes: int = MAX_TEXT_BYTES,
                       what: str = "") -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (read bounded even if it grows)."""
    with open_regular(path, what, max_bytes) as fh:
        data = fh.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise InputError(f"{_where(what, path)}: over the limit of {max_bytes} bytes")
    return data


def read_regular_text(path: str | os.PathLike[str], max_bytes: int = MAX_TEXT_BYTES,
                      what: str = "") -> str:
    data = read_regular_bytes(path, max_bytes, what)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{_where(what, path)}: not UTF-8 text") from None


def open_regular_text(path: str | os.PathLike[str], what: str = "",
                      max_bytes: int | None = MAX_TEXT_BYTES) -> IO[str]:
    """A text (UTF-8) reader of a regular file; for line-by-line readers of big files."""
    return io.TextIOWrapper(open_regular(path, what, max_bytes), encoding="utf-8",
                            errors="replace")


def loads_json(text: str | bytes, where: str) -> Any:
    """``json.loads`` with every failure one :class:`InputError` naming ``where`` (JSON
    nested too deeply included: Python's parser recurses)."""
    try:
        return json.loads(text)
    except RecursionError:
        raise InputError(f"{where}: JSON nested too deeply") from None
    except (ValueError, TypeError) as exc:
        detail = exc.msg if isinstance(exc, json.JSONDecodeError) else type(exc).__name__
        raise InputError(f"{where}: not valid JSON ({detail})") from None


def _npy_declared_bytes(member: IO[bytes]) -> int:
    version = np.lib.format.read_magic(member)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(member)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(member)
    else:
        raise ValueError(f"npy version {version}")
    if dtype.hasobject:
        raise ValueError("object arrays are not accepted")
    n = 1
    for d in shape:
        n *= int(d)
    return n * dtype.itemsize


def load_npz(path: str | os.PathLike[str], what: str = "",
             max_bytes: int = MAX_NPZ_BYTES) -> Any:
    """``np.load(path)`` of a regular ``.npz`` file whose members, inflated, fit
    ``max_bytes`` together, by their declared sizes and array shapes, checked before
    anything is inflated (no pickles)."""
    fh = open_regular(path, what)
    try:
        if zipfile.is_zipfile(fh):
            fh.seek(0)
            total = 0
            with zipfile.ZipFile(fh) as zf:
                for info in zf.infolist():
                    total += info.file_size
                    if total > max_bytes:
                        raise InputError(f"{_where(what, path)}: declares {total} bytes inflated, "
                                         f"over the limit of {max_bytes}")
                    if info.filename.endswith(".npy"):
                        with zf.open(info) as member:
                            declared = _npy_declared_bytes(member)
                        if declared > info.file_size or declared > max_bytes:
                            raise InputError(f"{_where(what, path)}: {info.filename} declares "
                                             f"{declared} bytes of array data in a member "
                                             f"of {info.file_size}")
        fh.seek(0)
        data = fh.read()
    except InputError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, OverflowError) as exc:
        raise InputError(f"{_where(what, path)}: not a valid .npz archive "
                         f"({type(exc).__name__})") from None
    finally:
        fh.close()
    return np.load(io.BytesIO(data), allow_pickle=False)
