"""A scan's texture for the browser avatar: texture coordinates per facet corner of a Wavefront
OBJ (``vt``, ``f v/vt``), the texture image (JPEG or PNG, from the .obj's ``mtllib`` +
``map_Kd`` or given), and the render mesh a client draws: one render vertex per distinct
(point, texture coordinate) pair, so a seam of the texture atlas splits a point in two while
both copies move with the point (``render_index``).

Kept in the binding file as extra arrays (``uv``, ``render_index``, ``render_triangles``,
``texture``), read by :func:`texture_from_arrays`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from articast.core.errors import InputError

MAX_TEXTURE_BYTES = 32 * 1024 * 1024
"""A texture image, bytes (32 MiB: an 8k JPEG); beyond, a file is not one."""

TEXTURE_ARRAYS = ("uv", "render_index", "render_triangles", "texture")


@dataclass(frozen=True, eq=False)
class ScanTexture:
    """render_index : (R,) int, the scan point of each render vertex; uv : (R, 2) texture
    coordinates (OBJ convention: v = 0 at the bottom of the image); triangles : (Q, 3) int
    into the render vertices, row q drawn where the scan's facet q is; image : the encoded
    JPEG or PNG; mime : its type."""

    render_index: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray
    image: bytes
    mime: str

    def arrays(self) -> dict[str, np.ndarray]:
        return {"uv": self.uv.astype(np.float32), "render_index": self.render_index,
                "render_triangles": self.triangles,
                "texture": np.frombuffer(self.image, np.uint8)}


def image_mime(data: bytes, source: str = "<texture>") -> str:
    """``image/jpeg`` or ``image/png`` from the file's first bytes, else :class:`InputError`."""
    if data[:3] == b"\xff\xd8\xff":
        return "image/jpeg"
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return "image/png"
    raise InputError(f"{source}: the texture must be a JPEG or PNG image")


def parse_obj_uv(text: str, source: str = "<obj>") -> tuple[np.ndarray, np.ndarray]:
    """Texture coordinates (U, 2) and, per triangle of :func:`~articast.core.dense.mesh.
    parse_obj` (same fans, same order), the ``vt`` index of each corner (Q, 3), -1 where a
    corner has none."""
    uv: list[list[float]] = []
    corners: list[list[int]] = []
    for n, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0] not in ("vt", "f"):
            continue
        try:
            if parts[0] == "vt":
                if len(parts) < 3:
                    raise ValueError("a texture coordinate needs u and v")
                uv.append([float(parts[1]), float(parts[2])])
                continue
            idx = []
            for p in parts[1:]:
                fields = p.split("/")
                t = int(fields[1]) if len(fields) > 1 and fields[1] else 0
                idx.append(t - 1 if t > 0 else len(uv) + t if t < 0 else -1)
        except ValueError as exc:
            raise InputError(f"{source}: line {n}: {exc}") from None
        if any(i >= len(uv) or (i < 0 and i != -1) for i in idx):
            raise InputError(f"{source}: line {n}: face refers to a texture coordinate not "
                             "defined before")
        corners.extend([idx[0], idx[j], idx[j + 1]] for j in range(1, len(idx) - 1))
    arr = np.array(uv, np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{source}: texture coordinates must be finite")
    return arr, np.array(corners, np.int64).reshape(-1, 3)


def render_mesh(triangles: np.ndarray, uv: np.ndarray, corner_uv: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """render_index (R,), uv (R, 2), render triangles (Q, 3) from the scan's triangles (Q, 3),
    its texture coordinates (U, 2) and the ``vt`` of each corner (Q, 3), all >= 0."""
    pairs = np.stack([triangles.ravel(), corner_uv.ravel()], 1)
    uniq, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return uniq[:, 0], uv[uniq[:, 1]], inverse.reshape(-1, 3)


def material_image(obj_text: str, obj_path: str | os.PathLike[str]) -> Path | None:
    """The ``map_Kd`` image of the first ``mtllib`` of an OBJ that names one and exists,
    relative to the .obj's folder; None when there is none."""
    folder = Path(obj_path).parent
    for line in obj_text.splitlines():
        parts = line.split(maxsplit=1)
        if len(parts) == 2 and parts[0] == "mtllib":
            mtl = folder / parts[1].strip()
            if not mtl.is_file():
                continue
            from articast.core.safe_io import read_regular_bytes

            text = read_regular_bytes(mtl).decode("utf-8", errors="replace")
            for mline in text.splitlines():
                mparts = mline.split()
                if len(mparts) >= 2 and mparts[0] == "map_Kd":
                    image = mtl.parent / mparts[-1]
                    if image.is_file():
                        return image
    return None


def scan_texture(obj_text: str, triangles: np.ndarray, image: bytes,
                 source: str = "<obj>", image_source: str = "<texture>",
                 drawn: np.ndarray | None = None) -> ScanTexture:
    """The :class:`ScanTexture` of a scan: its OBJ text, its triangles (Q, 3) as
    :func:`~articast.core.dense.mesh.parse_obj` reads them, and the encoded image.
    drawn : (Q,) bool, the facets to draw (default all; e.g. not those across the lips,
    :func:`~articast.core.dense.scan.mouth_facets`)."""
    if len(image) > MAX_TEXTURE_BYTES:
        raise InputError(f"{image_source}: larger than {MAX_TEXTURE_BYTES >> 20} MiB")
    mime = image_mime(image, image_source)
    uv, corner_uv = parse_obj_uv(obj_text, source)
    if len(corner_uv) != len(triangles) or len(triangles) == 0 or np.any(corner_uv < 0):
        raise InputError(f"{source}: a texture needs texture coordinates (vt) on every facet "
                         "corner (f v/vt ...)")
    keep = np.ones(len(triangles), bool) if drawn is None else np.asarray(drawn, bool)
    index, ruv, tris = render_mesh(triangles[keep], uv, corner_uv[keep])
    return ScanTexture(index.astype(np.int64), ruv, tris.astype(np.int64), bytes(image), mime)


def texture_from_arrays(arrays: dict[str, np.ndarray], n_points: int,
                        source: str = "<binding>") -> ScanTexture | None:
    """The texture kept in a binding file's arrays (None when it has none); checks shapes."""
    if "texture" not in arrays:
        return None
    try:
        index = np.asarray(arrays["render_index"], np.int64)
        uv = np.asarray(arrays["uv"], np.float64)
        tris = np.asarray(arrays["render_triangles"], np.int64)
        image = np.asarray(arrays["texture"], np.uint8).tobytes()
    except KeyError as exc:
        raise InputError(f"{source}: texture without array {exc}") from None
    r = len(index)
    if (index.ndim != 1 or uv.shape != (r, 2) or tris.ndim != 2 or tris.shape[1] != 3
            or (r and (index.min() < 0 or index.max() >= n_points))
            or (tris.size and (tris.min() < 0 or tris.max() >= r))):
        raise InputError(f"{source}: the texture's arrays do not fit its {n_points} points")
    return ScanTexture(index, uv, tris, image, image_mime(image, source))


CAVITY_INSET = 0.4
CAVITY_DEPTH_MM = (8.0, 20.0)


def mouth_cavity(points: np.ndarray, modes: np.ndarray, triangles: np.ndarray,
                 drawn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A dark mouth behind the lips of a scan whose facets across the lips are not drawn
    (:func:`~articast.core.dense.scan.mouth_facets`): most scans are masks, open behind the
    face, so the opening would show the background.

    points (M, 3) mm head frame, modes (K, M, 3) per unit alpha, triangles (Q, 3), drawn (Q,)
    bool. The edges between a drawn facet and one that is not (the lips' edges) are joined to
    a copy of themselves drawn ``CAVITY_INSET`` towards their centre and
    ``CAVITY_DEPTH_MM[0]`` back, then to one point ``CAVITY_DEPTH_MM[1]`` behind the centre;
    every added point moves as the mean of the points it comes from, so the cavity stays
    linear in alpha and follows the lips. Returns the added points (C, 3), their modes
    (K, C, 3) and facets (F, 3) indexing ``[points; added points]`` (empty when all is drawn).
    """
    k = modes.shape[0]
    empty = (np.zeros((0, 3)), np.zeros((k, 0, 3)), np.zeros((0, 3), np.int64))
    if drawn.all():
        return empty
    kept, cut = _edges(triangles[drawn]), _edges(triangles[~drawn])
    uniq, counts = np.unique(kept, axis=0, return_counts=True)
    border = uniq[counts == 1]  # the drawn mesh's border: the scan's own, and the lips'
    cut_keys = set(map(tuple, cut.tolist()))
    lips = np.array([e for e in border.tolist() if tuple(e) in cut_keys], np.int64)
    if len(lips) == 0:
        return empty
    ring = np.unique(lips)
    m = len(points)
    centre, centre_modes = points[ring].mean(0), modes[:, ring].mean(1)
    back = np.array([0.0, 0.0, 1.0])
    inset = (1 - CAVITY_INSET) * points[ring] + CAVITY_INSET * centre - CAVITY_DEPTH_MM[0] * back
    inset_modes = (1 - CAVITY_INSET) * modes[:, ring] + CAVITY_INSET * centre_modes[:, None]
    added = np.concatenate([inset, (centre - CAVITY_DEPTH_MM[1] * back)[None]])
    added_modes = np.concatenate([inset_modes, centre_modes[:, None]], axis=1)
    where = np.full(m, -1, np.int64)
    where[ring] = m + np.arange(len(ring))
    a, b = lips[:, 0], lips[:, 1]
    a2, b2, tip = where[a], where[b], m + len(ring)
    facets = np.concatenate([np.c_[a, b, b2], np.c_[a, b2, a2],
                             np.c_[a2, b2, np.full(len(a), tip)]])
    return added, added_modes, facets


def _edges(tris: np.ndarray) -> np.ndarray:
    return np.sort(tris[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
