"""The synthetic speaker's neutral face surface and anatomical landmarks (head frame, mm).

A smooth height field z(x, y): lips, nose with alae, chin and mentolabial sulcus, eye sockets,
cheekbones, nasolabial folds with the cheek bulge beside them, and the drop under the lower
border of the mandible to the throat. Vectorised over any array shape.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import PchipInterpolator

ARCH_RADIUS = 24.0
"""Radius of the dental arch (mm): incisors at z ~ 0, molars curving back."""


def smooth_step(u: np.ndarray) -> np.ndarray:
    """0 -> 1 logistic ramp, ``0.5 * (1 + tanh(u))``."""
    return 0.5 * (1.0 + np.tanh(u))


def softplus(u: np.ndarray, k: float) -> np.ndarray:
    """Smooth ``max(u, 0)`` with rounding scale ``k`` (same units as u)."""
    return k * np.logaddexp(0.0, np.asarray(u) / k)


def jaw_border_y(x: np.ndarray) -> np.ndarray:
    """y (mm) of the lower border of the mandible under head-frame x (mm)."""
    return -52.0 + 24.0 * (np.asarray(x) / 60.0) ** 2


def arch_z(x: np.ndarray) -> np.ndarray:
    """z (mm) of the labial face of the upper dental arch at x (mm); 0 at the incisors."""
    x = np.clip(np.abs(np.asarray(x)), 0.0, ARCH_RADIUS * 0.999)
    return -(ARCH_RADIUS - np.sqrt(ARCH_RADIUS**2 - x**2)) * 1.6


_NOSE_H = PchipInterpolator([14.0, 20.0, 23.0, 27.0, 31.0, 40.0, 52.0, 64.0, 75.0],
                            [0.0, 1.0, 8.0, 19.0, 20.0, 14.0, 9.0, 5.0, 3.0])


def neutral_height(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Neutral face surface z(x, y) (mm, head frame), vectorised over any shape."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    ax = np.abs(x)
    radius = 48.0 + 22.0 * np.exp(-(((y - 28.0) / 18.0) ** 2))  # cheekbones stand out
    z = 7.0 + 5.0 * smooth_step((y - 45.0) / 12.0)  # brow/forehead forward
    z = z - x**2 / (2 * radius) - 9.0 * (ax / 70.0) ** 4
    e = (x / 27.0) ** 2 + ((y + 1.0) / 13.0) ** 2
    z = z + 6.0 * np.exp(-2.0 * e**2) + 1.5 * smooth_step(y / 3.0) * np.exp(-(e**2))  # lips
    z = z + 7.0 * np.exp(-((x / 21.0) ** 2 + ((y + 40.0) / 10.0) ** 2))  # chin
    z = z - 2.0 * np.exp(-((x / 18.0) ** 2 + ((y + 22.0) / 5.0) ** 2))  # mentolabial sulcus
    width = 7.0 + 10.0 * np.exp(-(((y - 24.0) / 5.0) ** 2))  # nose, alae at y ~ 24
    yn = np.clip(y, 14.0, 75.0)
    z = z + _NOSE_H(yn) * np.exp(-((x / width) ** 2)) * (y > 14.0)
    z = z - 7.0 * np.exp(-(((ax - 32.0) / 13.0) ** 2 + ((y - 52.0) / 9.0) ** 2))  # eye sockets
    z = z - nasolabial_profile(x, y)
    z = z - 44.0 * smooth_step((jaw_border_y(x) - y) / 6.0)  # under the jaw
    return z


def nasolabial_distance(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (mm, + lateral) to the nasolabial fold and position along it (0..1)."""
    ax = np.abs(np.asarray(x, np.float64))
    p0, p1 = np.array([20.0, 23.0]), np.array([35.0, -9.0])
    d = p1 - p0
    length = np.hypot(*d)
    rel_x, rel_y = ax - p0[0], np.asarray(y, np.float64) - p0[1]
    u = (rel_x * d[0] + rel_y * d[1]) / length**2
    normal = np.array([d[1], -d[0]]) / length  # points laterally (+x) and down
    signed = rel_x * normal[0] + rel_y * normal[1]
    return signed, u


def nasolabial_profile(x: np.ndarray, y: np.ndarray, depth: float = 1.8) -> np.ndarray:
    """Depth (mm, to subtract from z) of the nasolabial crease, with the cheek bulge beside it."""
    s, u = nasolabial_distance(x, y)
    along = smooth_step(u * 8.0) * smooth_step((1.05 - u) * 8.0)
    return along * (depth * np.exp(-((s / 2.5) ** 2)) - 1.5 * np.exp(-(((s - 7.0) / 6.0) ** 2)))
