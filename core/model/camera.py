"""Pinhole camera with OpenCV's distortion model, head pose, and chessboard calibration.

Frames: *head* (mm, x speaker's left, y up, z forward), *camera* (mm, OpenCV: x right, y down,
z along the optical axis), *image* (px, origin at the centre of the top-left pixel).
A head pose maps head to camera: ``X_cam = R(rotation) @ X_head + translation``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from articast.core.errors import CalibrationError, InputError, ModelFileError

CAMERA_KIND = "articast-camera"
CAMERA_VERSION = 1

FRONTAL = np.array([np.pi, 0.0, 0.0])
"""Axis-angle of a camera looking at the face from the front (head y up -> image y down)."""


def rotation_of(x: float, y: float, z: float) -> np.ndarray:
    """:func:`rotation_matrix` of one axis-angle vector given as three floats (rad) -> (3, 3)
    (the hot path of the optimiser; Python floats, numpy's sine and cosine: theirs and the C
    library's differ in the last bit at times)."""
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = th2**0.5
        a, b = float(np.sin(th)) / th, (1.0 - float(np.cos(th))) / th2
    return np.array([
        [1.0 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z],
        [a * z + b * x * y, 1.0 - b * (x * x + z * z), -a * x + b * y * z],
        [-a * y + b * x * z, a * x + b * y * z, 1.0 - b * (x * x + y * y)],
    ])


def rotation_matrix(r: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, vectorised.

    r : (..., 3) axis-angle, rad -> (..., 3, 3) rotation matrices.
    """
    r = np.asarray(r, dtype=np.float64)
    if r.shape == (3,):
        return rotation_of(*r.tolist())
    theta = np.linalg.norm(r, axis=-1)[..., None, None]
    k = np.zeros(r.shape[:-1] + (3, 3))
    k[..., 0, 1], k[..., 0, 2] = -r[..., 2], r[..., 1]
    k[..., 1, 0], k[..., 1, 2] = r[..., 2], -r[..., 0]
    k[..., 2, 0], k[..., 2, 1] = -r[..., 1], r[..., 0]
    small = theta < 1e-8
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    return np.eye(3) + a * k + b * (k @ k)


def turn_jacobian(points: np.ndarray) -> np.ndarray:
    """(N, 3, 3): d p / d omega of rotated points p = R x (N, 3) under a rotation increment on
    the left, R <- rotation_matrix(omega) R, at omega = 0: -[p]_x (the Gauss-Newton pose
    fits' rotation columns)."""
    p = np.asarray(points, np.float64)
    out = np.zeros((len(p), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = p[:, 2], -p[:, 1]
    out[:, 1, 0], out[:, 1, 2] = -p[:, 2], p[:, 0]
    out[:, 2, 0], out[:, 2, 1] = p[:, 1], -p[:, 0]
    return out


def small_turn(d: np.ndarray) -> np.ndarray:
    """(3,) the rotation vector of a rotation matrix ``d`` (3, 3) close to the identity (the
    vee of its antisymmetric part: exact to first order), e.g. R @ R_ref.T between two poses."""
    return 0.5 * np.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]])


def axis_angle(rot: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rotation_matrix` for one (3, 3) matrix -> (3,) rad."""
    rot = np.asarray(rot, dtype=np.float64)
    # (Python floats: a few times cheaper than numpy's scalars, the same sums; numpy's
    # arccos, which differs from the C library's in the last bit at times)
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = rot.tolist()
    trace = r00 + r11 + r22
    cos = min(max((trace - 1.0) / 2.0, -1.0), 1.0)
    theta = np.arccos(cos)
    if theta < 1e-8:
        return np.array([r21 - r12, r02 - r20, r10 - r01]) / 2
    if np.pi - theta < 1e-4:
        # near pi: the symmetric part gives a a^T exactly, the antisymmetric part
        # w = 2 sin(theta) a (small, zero only at pi) the sign of the axis and, with atan2,
        # an angle that arccos of the trace cannot resolve this close to pi
        w = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
        theta = float(np.arctan2(np.linalg.norm(w) / 2.0, (np.trace(rot) - 1.0) / 2.0))
        m = ((rot + rot.T) / 2.0 - np.cos(theta) * np.eye(3)) / (1.0 - np.cos(theta))
        i = int(np.argmax(np.diag(m)))
        axis = m[i] / np.sqrt(m[i, i])
        if w @ axis < 0:
            axis = -axis
        return axis / np.linalg.norm(axis) * theta
    d = 2.0 * float(np.sin(theta))  # (w / (2 sin theta) * theta, each entry's two roundings)
    th = float(theta)
    return np.array([(r21 - r12) / d * th, (r02 - r20) / d * th, (r10 - r01) / d * th])


@dataclass(frozen=True, eq=False)
class Pose:
    """Rigid head pose: rotation (3,) axis-angle rad, translation (3,) mm (head -> camera)."""

    rotation: np.ndarray = field(default_factory=lambda: FRONTAL.copy())
    translation: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 400.0]))

    def __post_init__(self) -> None:
        for name in ("rotation", "translation"):
            v = np.array(getattr(self, name), dtype=np.float64).reshape(-1)
            # (Python's isfinite on 3 floats: a few times cheaper than numpy's all(isfinite))
            if v.shape != (3,) or not all(map(math.isfinite, v.tolist())):
                raise InputError(f"pose {name} must be 3 finite numbers, got {v!r}")
            v.setflags(write=False)
            object.__setattr__(self, name, v)

    @cached_property
    def matrix(self) -> np.ndarray:
        """(3, 3) rotation matrix, worked out once per pose (a live frame's pose is asked for
        it several times: judged, the eyes' anchor, the lips' gap). Shared: do not write into
        it (it stays writable: the compiled kernels it is handed to are compiled for
        writable arrays, and a read-only one would be a new type, compiled on a first
        frame)."""
        return rotation_matrix(self.rotation)

    def transform(self, points: np.ndarray) -> np.ndarray:
        """Head-frame points (..., 3) mm -> camera-frame points (..., 3) mm."""
        return np.asarray(points) @ self.matrix.T + self.translation

    def inverse_transform(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) -> head frame."""
        return (np.asarray(points) - self.translation) @ self.matrix

    def as_vector(self) -> np.ndarray:
        """(6,) = rotation then translation."""
        return np.concatenate([self.rotation, self.translation])

    @classmethod
    def from_vector(cls, v: np.ndarray) -> Pose:
        v = np.asarray(v, dtype=np.float64)
        return cls(v[:3], v[3:6])

    def to_dict(self) -> dict[str, list[float]]:
        return {"rotation": [float(x) for x in self.rotation],
                "translation": [float(x) for x in self.translation]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Pose:
        """A pose read from a file: 3 + 3 finite numbers of plausible size (a rotation vector
        within 1000 rad, a translation within 1 km), else :class:`InputError`."""
        try:
            pose = cls(d["rotation"], d["translation"])
        except (KeyError, TypeError) as exc:
            raise InputError(
                f"a pose needs 'rotation' and 'translation' (3 numbers each): {exc}"
            ) from None
        if pose.rotation.shape != (3,) or pose.translation.shape != (3,):
            raise InputError("a pose needs 'rotation' and 'translation' of 3 numbers each")
        if not (np.all(np.abs(pose.rotation) <= 1e3) and np.all(np.abs(pose.translation) <= 1e6)):
            raise InputError("pose values must be finite, rotation within 1000 rad and "
                             "translation within 1e6 mm")
        return pose


FOCAL_RANGE = (0.05, 100.0)
"""Plausible focal lengths, in multiples of the image's larger side (a fisheye ~0.3, a long
telephoto ~10): a camera file outside it is a mistake (1e-300 px tracked "ok" before)."""
MAX_DISTORTION = 1e4
"""Plausible |distortion coefficient| (OpenCV's rational model reaches tens)."""


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics (px) and OpenCV distortion ``(k1, k2, p1, p2, k3)`` of a camera."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        d = np.zeros(5)
        given = np.asarray(self.dist, dtype=np.float64).ravel()
        if given.size > 5:
            raise InputError("only the 5-coefficient distortion model (k1,k2,p1,p2,k3) is used")
        d[: given.size] = given
        d.setflags(write=False)
        object.__setattr__(self, "dist", d)
        vals = [self.fx, self.fy, self.cx, self.cy]
        if not all(np.isfinite(vals)) or self.fx <= 0 or self.fy <= 0:
            raise InputError(f"camera intrinsics must be finite with fx, fy > 0: {vals}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise InputError(f"camera image size must be positive: {self.width}x{self.height}")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @classmethod
    def default(cls, width: int = 640, height: int = 480, fov_deg: float = 40.0) -> Camera:
        """An undistorted camera with the given horizontal field of view."""
        f = 0.5 * width / np.tan(np.radians(fov_deg) / 2.0)
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    @cached_property
    def pinhole(self) -> bool:
        """Whether the camera has no distortion (the compiled projections' case)."""
        return not bool(np.any(self.dist != 0))

    @cached_property
    def intrinsics(self) -> np.ndarray:
        """(fx, fy, cx, cy) float64, made once (the compiled projections' argument; shared:
        do not write into it)."""
        return np.array([self.fx, self.fy, self.cx, self.cy], np.float64)

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the usual name
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor``."""
        f = float(factor)
        return Camera(self.fx * f, self.fy * f, (self.cx + 0.5) * f - 0.5,
                      (self.cy + 0.5) * f - 0.5, round(self.width * f),
                      round(self.height * f), self.dist)

    # -------------------------------------------------------------- projection
    def project(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points (M, 3) mm -> pixels (M, 2). Points behind the camera give NaN."""
        return self.project_jacobian(points, jacobian=False)[0]

    def project_one(self, point: np.ndarray) -> np.ndarray:
        """:meth:`project` of one camera-frame point (3,) mm -> (2,) px (NaN behind the
        camera): an undistorted camera's in Python floats, the same operations as the array
        code without its ~10 array calls (the live eyes' anchor, every frame)."""
        if self.dist.any():
            return self.project(np.asarray(point)[None])[0]
        x, y, z = np.asarray(point, np.float64).tolist()
        iz = 1.0 / z if z > 1e-6 else math.nan
        return np.array([self.fx * (x * iz) + self.cx, self.fy * (y * iz) + self.cy])

    def project_jacobian(
        self, points: np.ndarray, jacobian: bool = True
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Project camera-frame points and, optionally, d(pixel)/d(point).

        points : (M, 3) mm camera frame.
        Returns uv (M, 2) px and J (M, 2, 3) px/mm (None if ``jacobian`` is False).
        """
        p = np.asarray(points, dtype=np.float64)
        z = p[..., 2]
        valid = z > 1e-6
        iz = np.where(valid, 1.0 / np.where(valid, z, 1.0), np.nan)
        x, y = p[..., 0] * iz, p[..., 1] * iz
        if not self.dist.any():
            uv = np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=-1)
            if not jacobian:
                return uv, None
            jac = np.zeros(p.shape[:-1] + (2, 3))
            jac[..., 0, 0] = self.fx * iz
            jac[..., 0, 2] = -self.fx * x * iz
            jac[..., 1, 1] = self.fy * iz
            jac[..., 1, 2] = -self.fy * y * iz
            return uv, jac
        k1, k2, p1, p2, k3 = self.dist
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)
        if not jacobian:
            return uv, None
        dr = k1 + 2 * k2 * r2 + 3 * k3 * r2 * r2  # d radial / d r2
        a = radial + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x  # dxd/dx
        b = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y  # dxd/dy == dyd/dx
        c = radial + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x  # dyd/dy
        # d(x, y)/d(X, Y, Z) = iz * [[1, 0, -x], [0, 1, -y]]
        jac = np.empty(p.shape[:-1] + (2, 3))
        jac[..., 0, 0] = self.fx * a * iz
        jac[..., 0, 1] = self.fx * b * iz
        jac[..., 0, 2] = -self.fx * (a * x + b * y) * iz
        jac[..., 1, 0] = self.fy * b * iz
        jac[..., 1, 1] = self.fy * c * iz
        jac[..., 1, 2] = -self.fy * (b * x + c * y) * iz
        return uv, jac

    def project_head(self, points_head: np.ndarray, pose: Pose) -> np.ndarray:
        """Head-frame points (M, 3) mm at ``pose`` -> pixels (M, 2)."""
        return self.project(pose.transform(points_head))

    def inside(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean (M,) true where pixel positions lie at least ``margin`` px inside the image."""
        uv = np.asarray(uv)
        return (
            np.isfinite(uv).all(-1)
            & (uv[..., 0] >= margin) & (uv[..., 0] <= self.width - 1 - margin)
            & (uv[..., 1] >= margin) & (uv[..., 1] <= self.height - 1 - margin)
        )

    # -------------------------------------------------------------- files
    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": CAMERA_KIND, "version": CAMERA_VERSION,
            "width": self.width, "height": self.height,
            "K": self.K.tolist(), "dist": [float(v) for v in self.dist],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "camera") -> Camera:
        try:
            if d.get("kind", CAMERA_KIND) != CAMERA_KIND:  # the other kind is not echoed
                raise ModelFileError(f"{where}: not an articast camera file (its kind differs)")
            if d.get("version", CAMERA_VERSION) != CAMERA_VERSION:
                raise ModelFileError(f"{where}: camera format version unsupported (this "
                                     f"articast reads version {CAMERA_VERSION})")
            k = np.asarray(d["K"], dtype=np.float64)
            if k.shape != (3, 3):
                raise ModelFileError(f"{where}: K must be 3x3, got shape {k.shape}")
            dist = np.asarray(d.get("dist", []), dtype=np.float64)
            if dist.ndim != 1 or dist.size > 14:
                raise ModelFileError(f"{where}: dist must be a list of at most 14 numbers")
            if not (np.all(np.isfinite(k)) and np.all(np.isfinite(dist))):
                raise ModelFileError(f"{where}: camera K or dist holds NaN or infinite values")
            width, height = int(d["width"]), int(d["height"])
            if not (0 < width <= 1 << 16 and 0 < height <= 1 << 16):
                raise ModelFileError(f"{where}: image size {width:.6g}x{height:.6g} is not "
                                     "plausible")  # (1e308: a 309-digit number before)
            if not (k[0, 0] > 0 and k[1, 1] > 0):
                raise ModelFileError(f"{where}: focal lengths in K must be positive")
            size = max(width, height)
            if not (FOCAL_RANGE[0] * size <= min(k[0, 0], k[1, 1])
                    and max(k[0, 0], k[1, 1]) <= FOCAL_RANGE[1] * size):
                raise ModelFileError(
                    f"{where}: focal lengths {k[0, 0]:.4g}, {k[1, 1]:.4g} px are not plausible "
                    f"for a {width}x{height} image (expected {FOCAL_RANGE[0]:g} to "
                    f"{FOCAL_RANGE[1]:g} times its larger side)")
            if not (-width <= k[0, 2] <= 2 * width and -height <= k[1, 2] <= 2 * height):
                raise ModelFileError(f"{where}: principal point {k[0, 2]:.4g}, {k[1, 2]:.4g} px "
                                     f"is far outside the {width}x{height} image")
            if np.any(np.abs(dist) > MAX_DISTORTION):
                raise ModelFileError(f"{where}: distortion coefficients over "
                                     f"{MAX_DISTORTION:g} are not plausible")
            return cls(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height, dist)
        except ModelFileError:
            raise
        except (KeyError, TypeError, ValueError, OverflowError, InputError) as exc:
            detail = f"missing field {exc}" if isinstance(exc, KeyError) else \
                type(exc).__name__
            raise ModelFileError(f"{where}: malformed camera description ({detail})") from None

    def save(self, path: str | os.PathLike[str]) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Camera:
        from articast.core.safe_io import read_regular_bytes

        if Path(path).is_dir():
            raise ModelFileError(f"{path}: is a folder, expected a camera file (.json)")
        if not os.path.lexists(path):
            raise ModelFileError(f"{path}: no such file")
        try:
            doc = json.loads(read_regular_bytes(path, 1 << 20))
        except InputError as exc:
            raise ModelFileError(str(exc)) from None
        except (OSError, ValueError, RecursionError) as exc:
            raise ModelFileError(f"{path}: not a JSON camera file ({type(exc).__name__})"
                                 ) from None
        if not isinstance(doc, dict):
            raise ModelFileError(f"{path}: a camera file holds one JSON object")
        return cls.from_dict(doc, where=str(path))


@dataclass(frozen=True)
class Calibration:
    camera: Camera
    rms_px: float
    images_used: int
    images_rejected: int


def calibrate_chessboard(
    images: Iterable[np.ndarray],
    pattern: tuple[int, int] = (9, 6),
    square_mm: float = 25.0,
) -> Calibration:
    """Calibrate from chessboard views (OpenCV).

    images : iterable of (H, W) or (H, W, 3) uint8 BGR images of one size.
    pattern : inner corners (columns, rows). square_mm : side of one square.
    Raises :class:`CalibrationError` if fewer than 3 views show the whole pattern.
    """
    import cv2

    grid = np.zeros((pattern[0] * pattern[1], 3), np.float32)
    grid[:, :2] = np.mgrid[0 : pattern[0], 0 : pattern[1]].T.reshape(-1, 2) * square_mm
    obj, img, size, rejected = [], [], None, 0
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
    for im in images:
        gray = im if im.ndim == 2 else cv2.cvtColor(im, cv2.COLOR_BGR2GRAY)
        if size is None:
            size = gray.shape[::-1]
        elif gray.shape[::-1] != size:
            raise CalibrationError(f"images differ in size: {size} and {gray.shape[::-1]}")
        found, corners = cv2.findChessboardCorners(gray, pattern)
        if not found:
            rejected += 1
            continue
        corners = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), crit)
        obj.append(grid)
        img.append(corners)
    if len(obj) < 3:
        raise CalibrationError(
            f"the {pattern[0]}x{pattern[1]} chessboard was found in {len(obj)} image(s); "
            "at least 3 are needed (check --pattern: it counts inner corners)"
        )
    rms, k, dist, _, _ = cv2.calibrateCamera(obj, img, size, None, None)
    cam = Camera(k[0, 0], k[1, 1], k[0, 2], k[1, 2], size[0], size[1], dist.ravel()[:5])
    return Calibration(cam, float(rms), len(obj), rejected)
