"""The ASCII ``.fap`` file that MPEG-4 players read (FAP.md), written and checked strictly.

::

    2.1 talk.fap 25 3           version name fps nframes
    0 0 1 1 1 ... (68 flags)    1 = the FAP is present in the next line
    0 512 -40 31 ...            frame number, then the values of the flagged FAPs in FAP order

The writer produces what all of Xface, Greta, visage and VREng accept: a ``2.1`` header, a name
without spaces, the fps (a whole number when the rate is one; a real rate such as NTSC's 29.97
as a decimal with at most 3 places, which Xface reads as a float: ``float fps; input >> fps``
in ``FAPFile::open``), exactly 68 flags, integer values only, every frame 0..N-1,
single spaces, FAP 1 and 2 masked out, no comments and no blank lines, ``\\n`` line ends.
The reader is a validator too: anything else is an :class:`~articast.core.errors.InputError`
naming the
line and the reason. Files of other tools that set FAP 1 (4 integers) or FAP 2 (6 integers) are
read, their values counted and checked but not returned.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from articast.core.errors import InputError
from articast.core.outputs.fap_table import N_FAPS

VERSION = "2.1"
_INT = re.compile(r"^[+-]?[0-9]+$")
MIN_FPS, MAX_FPS = 0.01, 10_000.0
"""Frame rates a .fap may declare (1e-12 fps, a frame every 31,000 years, was read)."""
MAX_VALUE = 2**31 - 1
"""|FAP value|: players hold them in 32 bits."""
_NUMBER = re.compile(r"^[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)$")
_HIGH_LEVEL_COUNTS = (4, 6)  # values carried by FAP 1 (viseme) and FAP 2 (expression)


@dataclass(frozen=True, eq=False)
class FapSequence:
    """The content of a ``.fap`` file.

    values : (F, 68) int64, FAP n in column n - 1, 0 where not flagged.
    mask : (F, 68) bool, the flags of each frame.
    fps : frames per second. name : the header's name. version : the header's version.
    """

    values: np.ndarray
    mask: np.ndarray
    fps: float
    name: str
    version: str = VERSION

    @property
    def n_frames(self) -> int:
        return int(self.values.shape[0])


def sanitise_name(name: str) -> str:
    """A header name players accept: whitespace and unusual characters become ``_``."""
    clean = re.sub(r"[^A-Za-z0-9._-]+", "_", str(name).strip()).strip("_")
    return clean or "articast"


def fps_text(fps: float) -> str:
    """The header's fps: ``25`` for a whole rate, ``29.97`` for NTSC (at most 3 decimals)."""
    f = float(fps)
    if not (np.isfinite(f) and f >= 0.001):
        raise InputError(f"fps must be a positive number, got {fps}")
    r = round(f, 3)
    return str(int(r)) if r == int(r) else f"{r:.3f}".rstrip("0")


def format_fap(
    values: np.ndarray, mask: np.ndarray, fps: float, name: str
) -> str:
    """The text of a ``.fap`` file.

    values : (F, 68) integers (FAP units; non-integral numbers are refused, round first).
    mask : (68,) or (F, 68) bool, which FAPs each frame carries; FAP 1 and 2 must be False.
    fps : frames per second, positive (written by :func:`fps_text`). name : sanitised.
    """
    vals = np.asarray(values)
    if vals.ndim != 2 or vals.shape[1] != N_FAPS or vals.shape[0] < 1:
        raise InputError(f"FAP values must have shape (F >= 1, {N_FAPS}), got {vals.shape}")
    if vals.dtype.kind == "f":
        if not np.all(np.isfinite(vals)) or np.any(vals != np.rint(vals)):
            raise InputError("FAP values must be integers (round them before writing)")
    elif vals.dtype.kind not in "iu":
        raise InputError(f"FAP values must be integers, got dtype {vals.dtype}")
    vals = vals.astype(np.int64)
    m = np.broadcast_to(np.asarray(mask, dtype=bool), vals.shape) if np.ndim(mask) else None
    if m is None or np.shape(mask) not in ((N_FAPS,), vals.shape):
        raise InputError(f"mask must have shape ({N_FAPS},) or {vals.shape}, got {np.shape(mask)}")
    if m[:, :2].any():
        raise InputError("FAP 1 (viseme) and 2 (expression) must be masked out")
    lines = [f"{VERSION} {sanitise_name(name)} {fps_text(fps)} {vals.shape[0]}"]
    for i in range(vals.shape[0]):
        lines.append(" ".join("1" if b else "0" for b in m[i]))
        lines.append(" ".join([str(i)] + [str(v) for v in vals[i][m[i]]]))
    return "\n".join(lines) + "\n"


def write_fap(
    path: str | os.PathLike[str],
    values: np.ndarray,
    mask: np.ndarray,
    fps: float,
    name: str | None = None,
) -> None:
    """Write a ``.fap`` file (see :func:`format_fap`); the name defaults to the file name."""
    path = Path(path)
    text = format_fap(values, mask, fps, name if name is not None else path.name)
    path.write_text(text, encoding="ascii", newline="\n")


def read_fap(path: str | os.PathLike[str], *, allow_comments: bool = False) -> FapSequence:
    """Read and check a ``.fap`` file (see :func:`parse_fap`)."""
    from articast.core.safe_io import read_regular_bytes

    path = Path(path)
    if not os.path.lexists(path):
        raise InputError(f"{path}: no such file")
    data = read_regular_bytes(path)
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise InputError(f"{path}: line {line}: not ASCII text") from None
    return parse_fap(text, source=str(path), allow_comments=allow_comments)


def parse_fap(text: str, source: str = "<fap>", *, allow_comments: bool = False) -> FapSequence:
    """Parse the text of a ``.fap`` file, rejecting anything players would not all accept.

    allow_comments : skip ``#`` lines (Xface does; Greta rejects them, so by default so do we).
    Raises :class:`InputError` ``"<source>: line <n>: <reason>"``.
    """
    raw = text.split("\n")
    if raw and raw[-1] == "":
        raw.pop()
    lines: list[tuple[int, list[str]]] = []
    for n, line in enumerate(raw, start=1):
        line = line[:-1] if line.endswith("\r") else line
        if allow_comments and line.startswith("#"):
            continue
        if not line.strip():
            raise InputError(f"{source}: line {n}: blank line (Greta rejects them)")
        if line.startswith("#"):
            raise InputError(f"{source}: line {n}: comment line (Greta rejects them)")
        tokens = line.split()
        if " ".join(tokens) != line:
            raise InputError(f"{source}: line {n}: fields must be separated by single spaces")
        lines.append((n, tokens))
    if not lines:
        raise InputError(f"{source}: line 1: empty file, expected the header "
                         "'version name fps nframes'")
    version, name, fps, n_frames = _header(source, *lines[0])
    room = min(n_frames, len(lines) // 2)  # a lying header must not allocate gigabytes
    values = np.zeros((room, N_FAPS), dtype=np.int64)
    mask = np.zeros((room, N_FAPS), dtype=bool)
    pos = 1
    for i in range(n_frames):
        if pos >= len(lines):
            raise InputError(f"{source}: line {lines[-1][0] + 1}: file ends after {i} of "
                             f"{n_frames} frames promised by the header")
        mask[i] = _mask_line(source, *lines[pos])
        if pos + 1 >= len(lines):
            raise InputError(f"{source}: line {lines[pos][0] + 1}: file ends before the values "
                             f"of frame {i} ({n_frames} frames promised by the header)")
        values[i] = _values_line(source, *lines[pos + 1], frame=i, mask=mask[i])
        pos += 2
    if pos < len(lines):
        raise InputError(f"{source}: line {lines[pos][0]}: unexpected content after the last "
                         f"frame (the header promises {n_frames} frames)")
    return FapSequence(values, mask, fps, name, version)


def _header(source: str, n: int, tokens: list[str]) -> tuple[str, str, float, int]:
    where = f"{source}: line {n}: bad header"
    if len(tokens) != 4:
        raise InputError(f"{where}: expected 'version name fps nframes', found "
                         f"{len(tokens)} field(s)")
    version, name, fps, count = tokens
    if not _NUMBER.match(version):
        raise InputError(f"{where}: version {version!r} is not a number such as 2.1")
    if not _NUMBER.match(fps) or not MIN_FPS <= float(fps) <= MAX_FPS:
        raise InputError(f"{where}: fps {fps[:40]!r} is not a number within {MIN_FPS:g} to "
                         f"{MAX_FPS:g}")
    if not _INT.match(count) or int(count) < 0:
        raise InputError(f"{where}: frame count {count!r} is not a non-negative integer")
    return version, name, float(fps), int(count)


def _mask_line(source: str, n: int, tokens: list[str]) -> np.ndarray:
    if len(tokens) != N_FAPS:
        raise InputError(f"{source}: line {n}: expected {N_FAPS} mask flags, found {len(tokens)}")
    bad = [t for t in tokens if t not in ("0", "1")]
    if bad:
        raise InputError(f"{source}: line {n}: mask flags must be 0 or 1, found {bad[0]!r}")
    return np.array([t == "1" for t in tokens])


def _values_line(
    source: str, n: int, tokens: list[str], *, frame: int, mask: np.ndarray
) -> np.ndarray:
    where = f"{source}: line {n}"
    if not _INT.match(tokens[0]):
        raise InputError(f"{where}: frame number {tokens[0]!r} is not an integer")
    if int(tokens[0]) != frame:
        raise InputError(f"{where}: expected frame {frame}, found frame {int(tokens[0])} "
                         "(every frame 0..N-1 must be present, in order)")
    high = [c for c, on in zip(_HIGH_LEVEL_COUNTS, mask[:2], strict=True) if on]
    expected = int(mask[2:].sum()) + sum(high)
    got = len(tokens) - 1
    if got != expected:
        raise InputError(f"{where}: value count mismatch: the mask flags {int(mask.sum())} "
                         f"FAP(s), i.e. {expected} value(s), but the line has {got}")
    for j, t in enumerate(tokens[1:], start=1):
        if not _INT.match(t):
            raise InputError(f"{where}: value {j} ({t!r}) is not an integer")
    ints = [int(t) for t in tokens[1 + sum(high):]]
    big = next((v for v in ints if abs(v) > MAX_VALUE), None)
    if big is not None:  # an int64 overflow (a traceback) beyond 2**63; no FAP is this big
        raise InputError(f"{where}: value {str(big)[:40]} is beyond ±{MAX_VALUE} (32-bit)")
    out = np.zeros(N_FAPS, dtype=np.int64)
    low = np.flatnonzero(mask)
    out[low[low >= 2]] = ints
    return out
