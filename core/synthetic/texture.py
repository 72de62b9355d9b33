"""Procedural textures of the synthetic speaker: one BGR uint8 atlas plus a background wall.

The atlas holds one rectangle per material. The skin rectangle is addressed by the *neutral*
head-frame (x, y) of the face (mm), so the texture moves with the tissue; the other
materials (teeth, mouth cavity, head, neck) are addressed by local coordinates (s, t) in
[0, 1]^2 given by :mod:`articast.core.synthetic.render`.

Skin: base tone, low-frequency colour variation (redder cheeks, nose, chin), mottling, pores
and fine grain; red lips with vertical striations and a darker wet inner band; nostrils;
darkened nasolabial folds; eyes and eyebrows.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from articast.core.errors import InputError
from articast.core.synthetic.geometry import SpeakerGeometry, make_geometry
from articast.core.synthetic.surface import nasolabial_distance

ATLAS_SIZE = (1024, 1024)  # (height, width) px
SKIN_PPM = 4.0
"""Atlas pixels per mm of the skin rectangle."""
SKIN_X0, SKIN_Y1 = -85.0, 85.0
"""Neutral head-frame x at the skin rectangle's left edge and y at its top edge (mm)."""
SKIN_SIZE = (840, 680)  # (height, width) px: x in [-85, 85) mm, y in (-125, 85] mm
#: material -> atlas rectangle (x0, y0, width, height) px
MATERIALS: dict[str, tuple[int, int, int, int]] = {
    "teeth": (690, 10, 320, 80),
    "cavity": (690, 100, 320, 100),
    "head": (690, 210, 320, 300),
    "neck": (690, 520, 320, 200),
    "ear": (690, 730, 100, 100),
    "shirt": (800, 730, 200, 100),
}
SKIN_BGR = np.array([128.0, 152.0, 200.0])
LIP_BGR = np.array([88.0, 86.0, 168.0])


@dataclass(frozen=True, eq=False)
class Atlas:
    """image : (H, W, 3) uint8 BGR. Use :meth:`skin_uv` / :meth:`material_uv` for addresses."""

    image: np.ndarray

    @staticmethod
    def skin_uv(xy: np.ndarray) -> np.ndarray:
        """Neutral head-frame (x, y) (..., 2) mm -> atlas pixel coordinates (..., 2) float32."""
        xy = np.asarray(xy, np.float64)
        u = (xy[..., 0] - SKIN_X0) * SKIN_PPM
        v = (SKIN_Y1 - xy[..., 1]) * SKIN_PPM
        return np.stack([u, v], -1).astype(np.float32)

    @staticmethod
    def material_uv(material: str, st: np.ndarray) -> np.ndarray:
        """Local (s, t) in [0, 1] (..., 2) of ``material`` -> atlas pixel coordinates."""
        x0, y0, w, h = MATERIALS[material]
        st = np.clip(np.asarray(st, np.float64), 0.0, 1.0)
        return np.stack([x0 + st[..., 0] * (w - 1), y0 + st[..., 1] * (h - 1)], -1).astype(
            np.float32
        )


def _field(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Zero-mean, unit-s.d. smooth random field (float32) of the given correlation length."""
    f = rng.standard_normal(shape).astype(np.float32)
    if sigma_px > 0:
        f = cv2.GaussianBlur(f, (0, 0), sigma_px)
    return (f - f.mean()) / (f.std() + 1e-6)


def _gauss(x: np.ndarray, y: np.ndarray, cx: float, cy: float, sx: float, sy: float):
    return np.exp(-(((x - cx) / sx) ** 2 + ((y - cy) / sy) ** 2))


def _skin(geom: SpeakerGeometry, rng: np.random.Generator) -> np.ndarray:
    h, w = SKIN_SIZE
    xs = SKIN_X0 + (np.arange(w) + 0.0) / SKIN_PPM
    ys = SKIN_Y1 - np.arange(h) / SKIN_PPM
    x, y = np.meshgrid(xs.astype(np.float32), ys.astype(np.float32))
    img = np.empty((h, w, 3), np.float32)
    img[:] = SKIN_BGR
    low = _field(rng, (h, w), 15 * SKIN_PPM)
    img += low[..., None] * np.array([5.0, 6.0, 7.0], np.float32)
    red = (_gauss(x, y, 42, 5, 16, 14) + _gauss(x, y, -42, 5, 16, 14)
           + 0.8 * _gauss(x, y, 0, 28, 8, 6) + 0.5 * _gauss(x, y, 0, -40, 15, 9))
    img += red[..., None] * np.array([-8.0, -12.0, 6.0], np.float32)
    mottle = _field(rng, (h, w), 2.0 * SKIN_PPM)
    img += mottle[..., None] * np.array([4.0, 4.5, 4.0], np.float32)
    grain = _field(rng, (h, w), 0.6)
    img += grain[..., None] * 6.0
    pores = (rng.random((h, w)) < 0.02).astype(np.float32)
    pores = cv2.GaussianBlur(pores, (0, 0), 0.8)
    img -= (pores / (pores.max() + 1e-6))[..., None] * 28.0
    # nasolabial folds: a darker crease line
    s, u = nasolabial_distance(x, y)
    along = (u > 0.0) * (u < 1.05) * np.clip(u * 6.0, 0, 1)
    img -= (along * np.exp(-((s / 1.6) ** 2)))[..., None] * np.float32(30.0)
    # nostrils
    for side in (-1.0, 1.0):
        nost = np.clip(1.6 * (1.0 - ((x - side * 7.0) / 3.6) ** 2 - ((y - 23.2) / 1.8) ** 2),
                       0, 1)
        nost = cv2.GaussianBlur(nost.astype(np.float32), (0, 0), 0.5 * SKIN_PPM)
        img = img * (1 - 0.75 * nost[..., None])
        crease = np.abs(np.hypot((x - side * 12.0) / 6.5, (y - 26.0) / 7.0) - 1.0) < 0.08
        crease &= (y < 30.0) & (np.abs(x) > 9.0)
        img[crease] *= 0.9
    # lips: fill the neutral outer contour, soft edge, striations; wet inner band
    img = _paint_lips(img, geom, x, rng)
    # eyes and eyebrows
    for side in (-1.0, 1.0):
        ex, ey = side * 32.0, 52.0
        sclera = ((x - ex) / 12.0) ** 2 + ((y - ey) / 4.5) ** 2 < 1.0
        img[sclera] = (218.0, 222.0, 228.0)
        iris = np.hypot(x - ex, y - ey) < 5.0
        img[iris & sclera] = (50.0, 70.0, 95.0)
        pupil = np.hypot(x - ex, y - ey) < 2.0
        img[pupil & sclera] = (15.0, 15.0, 18.0)
        lid = np.abs(((x - ex) / 13.0) ** 2 + ((y - ey) / 5.5) ** 2 - 1.0) < 0.2
        img[lid & (y > ey - 1)] = (40.0, 45.0, 60.0)
        brow = np.abs(y - (64.0 - 0.006 * (x - ex) ** 2 + 1.5 * side * (x - ex) / 15)) < 2.2
        brow &= np.abs(x - ex) < 17.0
        img[brow] = img[brow] * 0.35 + np.array([30.0, 40.0, 55.0]) * 0.65
    return img


def _paint_lips(img: np.ndarray, geom: SpeakerGeometry, x: np.ndarray,
                rng: np.random.Generator) -> np.ndarray:
    h, w = SKIN_SIZE
    ring = geom.ring
    outer = Atlas.skin_uv(geom.uv[ring == 2])
    inner = Atlas.skin_uv(geom.uv[ring == 0])
    beads = Atlas.skin_uv(geom.uv[ring == 1])
    shift = 4  # sub-pixel precision of cv2.fillPoly
    mask = np.zeros((h, w), np.float32)
    cv2.fillPoly(mask, [np.round(outer * (1 << shift)).astype(np.int32)], 1.0, cv2.LINE_AA,
                 shift)
    mask = cv2.GaussianBlur(mask, (0, 0), 0.5 * SKIN_PPM)
    wet = np.zeros((h, w), np.float32)
    band = np.concatenate([inner, 0.5 * (inner + beads)[::-1]])
    cv2.fillPoly(wet, [np.round(band * (1 << shift)).astype(np.int32)], 1.0, cv2.LINE_AA, shift)
    wet = cv2.GaussianBlur(wet, (0, 0), 0.8 * SKIN_PPM)
    stripes = np.sin(x * (2 * np.pi / 1.3)).astype(np.float32)
    stripes += 0.5 * _field(rng, (h, w), 1.0)
    lip = LIP_BGR + stripes[..., None] * np.array([5.0, 5.0, 7.0], np.float32)
    lip = lip * (1.0 - 0.25 * wet[..., None])
    return img * (1.0 - mask[..., None]) + lip * mask[..., None]


def _materials(atlas: np.ndarray, rng: np.random.Generator) -> None:
    # teeth: ivory with dark gaps every ~6.5 mm of arch, translucent edge, pink gums
    x0, y0, w, h = MATERIALS["teeth"]
    s, t = np.meshgrid(np.linspace(0, 1, w), np.linspace(0, 1, h))
    arch_mm = (s - 0.5) * 2.2 * 24.0
    gap = np.exp(-(((np.abs(arch_mm) + 3.25) % 6.5 - 3.25) / 0.35) ** 2)
    teeth = np.array([178.0, 200.0, 212.0]) * (1 - 0.55 * gap[..., None])
    teeth = teeth * (0.85 + 0.15 * np.clip(t / 0.2, 0, 1))[..., None]
    gum = np.clip((t - 0.72) / 0.05, 0, 1)[..., None]
    teeth = teeth * (1 - gum) + np.array([120.0, 120.0, 200.0]) * gum
    teeth += rng.standard_normal((h, w, 1)) * 3.0
    atlas[y0:y0 + h, x0:x0 + w] = np.clip(teeth, 0, 255)
    # mouth cavity: reddish near the lips, black deep inside; tongue on the floor (s > 0.5)
    x0, y0, w, h = MATERIALS["cavity"]
    s, t = np.meshgrid(np.linspace(0, 1, w), np.linspace(0, 1, h))
    rim = np.array([60.0, 58.0, 125.0])
    deep = np.array([14.0, 12.0, 22.0])
    k = np.clip(t * 1.6, 0, 1)[..., None]
    cav = rim * (1 - k) + deep * k
    tongue = ((s > 0.55) & (s < 0.95) & (t > 0.25) & (t < 0.75))[..., None]
    cav = np.where(tongue, np.array([50.0, 50.0, 115.0]), cav)
    cav += rng.standard_normal((h, w, 1)) * 3.0
    atlas[y0:y0 + h, x0:x0 + w] = np.clip(cav, 0, 255)
    # head: hair on top and back (t < 0.42 or far back), skin elsewhere
    x0, y0, w, h = MATERIALS["head"]
    s, t = np.meshgrid(np.linspace(0, 1, w), np.linspace(0, 1, h))
    az = (s - 0.5) * 2 * np.pi  # 0 = facing forward
    hair_line = 0.36 + 0.25 * (1 - np.cos(az)) / 2
    hair = (t < hair_line)[..., None]
    strands = _field(rng, (h, w), 1.0)[..., None] * 10.0
    skin = SKIN_BGR + _field(rng, (h, w), 3.0)[..., None] * 5.0
    head = np.where(hair, np.array([30.0, 42.0, 58.0]) + strands, skin)
    atlas[y0:y0 + h, x0:x0 + w] = np.clip(head, 0, 255)
    # neck: skin, a shirt collar at the bottom
    x0, y0, w, h = MATERIALS["neck"]
    s, t = np.meshgrid(np.linspace(0, 1, w), np.linspace(0, 1, h))
    neck = SKIN_BGR * 0.95 + _field(rng, (h, w), 2.0)[..., None] * 5.0
    shirt = (t > 0.62)[..., None]
    neck = np.where(shirt, np.array([120.0, 80.0, 50.0]) + _field(rng, (h, w), 1.0)[..., None]
                    * 6.0, neck)
    atlas[y0:y0 + h, x0:x0 + w] = np.clip(neck, 0, 255)
    # ears: skin, a darker inner fold; shirt: blue cloth
    x0, y0, w, h = MATERIALS["ear"]
    s, t = np.meshgrid(np.linspace(0, 1, w), np.linspace(0, 1, h))
    ear = SKIN_BGR * (1.0 - 0.25 * np.exp(-(((t - 0.5) / 0.2) ** 2)))[..., None]
    atlas[y0:y0 + h, x0:x0 + w] = np.clip(ear + _field(rng, (h, w), 2.0)[..., None] * 4, 0, 255)
    x0, y0, w, h = MATERIALS["shirt"]
    cloth = np.array([120.0, 80.0, 50.0]) + _field(rng, (h, w), 1.0)[..., None] * 6.0
    atlas[y0:y0 + h, x0:x0 + w] = np.clip(cloth, 0, 255)


def make_atlas(seed: int = 0) -> Atlas:
    """The texture atlas of speaker ``seed`` (deterministic; cached, or as given to
    :func:`preset_atlas`)."""
    preset = _PRESET_ATLASES.get(int(seed))
    return preset if preset is not None else _make_atlas(int(seed))


_PRESET_ATLASES: dict[int, Atlas] = {}


def preset_atlas(seed: int, image: np.ndarray) -> None:
    """Use ``image`` (H, W, 3) uint8, a saved ``make_atlas(seed).image``, as speaker ``seed``'s
    atlas instead of building it (~0.4 s): for a cache of the speaker's assets."""
    img = np.asarray(image)
    if img.shape != ATLAS_SIZE + (3,) or img.dtype != np.uint8:
        raise InputError(f"an atlas is {ATLAS_SIZE + (3,)} uint8, got {img.shape} {img.dtype}")
    img = img.copy()
    img.setflags(write=False)
    _PRESET_ATLASES[int(seed)] = Atlas(img)


@lru_cache(maxsize=4)
def _make_atlas(seed: int) -> Atlas:
    geom = make_geometry(seed)
    rng = np.random.default_rng([seed, 0x7E77])
    atlas = np.zeros(ATLAS_SIZE + (3,), np.float32)
    h, w = SKIN_SIZE
    atlas[:h, :w] = _skin(geom, rng)
    _materials(atlas, rng)
    img = np.clip(atlas, 0, 255).astype(np.uint8)
    img.setflags(write=False)
    return Atlas(img)


def make_background(width: int, height: int, seed: int = 0) -> np.ndarray:
    """A textured wall (H, W, 3) uint8 BGR: gradient, plaster blotches and grain (cached)."""
    return _make_background(int(width), int(height), int(seed))


@lru_cache(maxsize=8)
def _make_background(width: int, height: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng([seed, 0xBAC6])
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    base = np.array([150.0, 165.0, 160.0], np.float32)
    grad = (0.85 + 0.25 * xx / width - 0.1 * yy / height)[..., None]
    blot = _field(rng, (height, width), max(width, height) / 25.0)[..., None] * 8.0
    grain = _field(rng, (height, width), 1.0)[..., None] * 4.0
    img = np.clip(base * grad + blot + grain, 0, 255).astype(np.uint8)
    img.setflags(write=False)
    return img
