"""MPEG-4 facial animation parameters from the tracked state (METHOD.md §4, FAP.md).

Units (FAPU) are measured once on the neutral face: the model's mean shape unless another
neutral posture is given. A geometric FAP is the displacement of its feature point from the
neutral, along the FAP's positive direction (``articast.core.outputs.fap_table``), divided by
its unit, rounded
to the nearest integer. Everything geometric is computed in the **head frame** (x = the
speaker's own left, y up, z forward), so head motion alone leaves every lip and jaw FAP at 0,
and "left"/"right" are the face's own sides (``stretch_l_cornerlip`` moves 8.3/2.4 towards +x).

Choices (also in ``docs/FAP_CHOICES.md``):

* **Lower-lip FAPs are relative to the jaw** (default, ``jaw_relative=True``). In MPEG-4
  players (Xface, Greta, visage) ``open_jaw`` already carries the lower lip and the chin down
  with the jaw, and the lower-lip FAPs are added on top; absolute values would move the lower
  lip twice. So the vertical FAPs of the points carried by the jaw (2.3, 2.8, 2.9, 8.2, 8.7,
  8.8 and the chin 2.10; FAPs 5, 10, 11, 18, 52, 57, 58) use the point's vertical displacement
  minus the jaw point's (2.1), i.e. they are offsets on top of ``open_jaw``. Only the vertical
  is made relative, as ``open_jaw`` is vertical: ``push_b_lip`` stays absolute, because how a
  player's jaw rotation moves the lip forward or back is the player's own (its hinge is not
  ours). ``jaw_relative=False`` gives absolute values.
  :func:`reconstruct_feature_points` undoes exactly what was chosen.
* **Unidirectional FAPs are not clipped.** The neutral is the corpus mean, around which the jaw
  moves both ways; clipping ``open_jaw`` at 0 would lose the closing movements and break the
  reconstruction. Pass a closed-mouth ``neutral_alpha`` if a player needs them non-negative.
* **Head rotation** (FAPs 48-50) is the head's rotation relative to a reference pose, by
  default :data:`articast.core.model.camera.FRONTAL` (a camera facing the face), expressed in
  the reference
  head frame: ``R_rel = R_ref^T R``, decomposed as ``R_rel = R_y(yaw) R_x(pitch) R_z(roll)``
  (intrinsic yaw, then pitch, then roll). With the head axes above, pitch down, yaw to the
  speaker's left and roll to the speaker's right are all positive rotations about +x, +y, +z,
  which are exactly the MPEG-4 positive directions. Angles are in AU = 1e-5 rad.
* ``IRISD0`` (iris diameter, eyelid points 3.1/3.3) is not measurable on our models: it is read
  from ``fapu_overrides["IRISD0"]`` if declared, else derived as ``ES0 * 11.7 / 63`` (adult
  iris diameter 11.7 mm over interpupillary distance 63 mm). No FAP we compute uses it.
* ``fapu_overrides`` take precedence over labelled points: an override is a declaration by the
  author of the model file.
* ``.fap`` text files carry unquantised integer FAP values; ``quant_step`` of the table belongs
  to the binary encoder and is not applied.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from articast.core.errors import InputError
from articast.core.model.camera import FRONTAL, rotation_matrix
from articast.core.model.face import FaceModel
from articast.core.outputs.fap_io import (
    FapSequence,
    format_fap,
    parse_fap,
    read_fap,
    sanitise_name,
    write_fap,
)
from articast.core.outputs.fap_table import FAP_TABLE, N_FAPS

__all__ = [
    "AU", "Fapu", "FapEncoder", "FapSequence", "GEOMETRIC_FAPS", "HEAD_FAPS",
    "JAW_RELATIVE_FAPS", "fap_values", "fapu_from_model", "format_fap", "head_angles",
    "lip_aperture", "lip_width", "parse_fap", "read_fap", "reconstruct_feature_points",
    "sanitise_name", "write_fap",
]  # fmt: skip

AU = 1e-5
"""Angle unit of FAPs 48-50, in radians."""

GEOMETRIC_FAPS: tuple[int, ...] = tuple(range(3, 19)) + tuple(range(51, 61))
"""Lip and jaw FAPs computed from feature-point displacements."""

HEAD_FAPS: tuple[int, ...] = (48, 49, 50)
"""head_pitch, head_yaw, head_roll."""

JAW_RELATIVE_FAPS: tuple[int, ...] = (5, 10, 11, 18, 52, 57, 58)
"""Vertical FAPs of points carried by the jaw: relative to open_jaw when ``jaw_relative``."""

DIRECTIONS: dict[str, tuple[float, float, float]] = {
    "up": (0.0, 1.0, 0.0),
    "down": (0.0, -1.0, 0.0),
    "left": (1.0, 0.0, 0.0),  # the face's own left is +x in the head frame
    "right": (-1.0, 0.0, 0.0),
    "forward": (0.0, 0.0, 1.0),
}
"""Unit vectors (head frame) of the FAP positive directions used by geometric FAPs."""

IRIS_OVER_EYE_SEPARATION = 11.7 / 63.0
"""Default IRISD0 / ES0 when IRISD0 is not declared (adult averages)."""

JAW_POINT = "2.1"


@dataclass(frozen=True)
class Fapu:
    """Face animation parameter units measured on the neutral face, in mm.

    A FAP in unit ``MW`` moves its point by ``value * MW0 / 1024`` mm (idem MNS, ENS, ES,
    IRISD); an ``AU`` FAP is ``value * 1e-5`` rad.
    """

    MW0: float
    MNS0: float
    ENS0: float
    ES0: float
    IRISD0: float

    def unit(self, name: str) -> float:
        """Size of one FAP unit: mm for ``"MW"``, ``"MNS"``, ... ; rad for ``"AU"``."""
        if name == "AU":
            return AU
        try:
            return float(getattr(self, f"{name}0")) / 1024.0
        except AttributeError:
            raise InputError(f"unknown FAP unit {name!r}") from None

    def as_dict(self) -> dict[str, float]:
        """``{"MW0": mm, ...}`` (e.g. for the service's hello message)."""
        return {k: float(getattr(self, k)) for k in ("MW0", "MNS0", "ENS0", "ES0", "IRISD0")}


def fapu_from_model(model: FaceModel, neutral_alpha: np.ndarray | None = None) -> Fapu:
    """FAPU of ``model`` measured on its neutral face (FAP.md, table of units).

    MW0 = 8.3.x - 8.4.x, MNS0 = 9.15.y - 2.2.y, ENS0 = 3.5.y - 9.15.y, ES0 = 3.5.x - 3.6.x on
    ``model.shape(neutral_alpha)`` (default: the mean), each replaced by
    ``model.fapu_overrides`` when declared; IRISD0 as in the module docstring.
    Raises :class:`InputError` when a unit can neither be measured nor is declared, or is not
    positive (e.g. the left/right labels are swapped).
    """
    neutral = _neutral_shape(model, neutral_alpha)
    over = dict(model.fapu_overrides)
    recipes = {
        "MW0": (("8.3", 0), ("8.4", 0)),
        "MNS0": (("9.15", 1), ("2.2", 1)),
        "ENS0": (("3.5", 1), ("9.15", 1)),
        "ES0": (("3.5", 0), ("3.6", 0)),
    }
    values: dict[str, float] = {}
    for name, ((pa, ax), (pb, bx)) in recipes.items():
        if name in over:
            values[name] = float(over[name])
            continue
        missing = [p for p in (pa, pb) if p not in model.feature_points]
        if missing:
            raise InputError(
                f"model {model.name!r} cannot define {name}: no feature point(s) {missing} "
                f"and no fapu_overrides[{name!r}]"
            )
        values[name] = float(neutral[model.point(pa), ax] - neutral[model.point(pb), bx])
    values["IRISD0"] = float(over.get("IRISD0", values["ES0"] * IRIS_OVER_EYE_SEPARATION))
    for name, v in values.items():
        if not (np.isfinite(v) and v > 0):
            raise InputError(
                f"FAPU {name} of model {model.name!r} is {v:.3f} mm; it must be positive "
                "(check the left/right feature-point labels: left is the speaker's own, +x)"
            )
    return Fapu(**values)


def _neutral_shape(model: FaceModel, neutral_alpha: np.ndarray | None) -> np.ndarray:
    if neutral_alpha is None:
        return model.mean
    a = np.asarray(neutral_alpha, dtype=np.float64)
    if a.shape != (model.n_params,) or not np.all(np.isfinite(a)):
        raise InputError(f"neutral_alpha must be {model.n_params} finite numbers, got {a!r}")
    return model.shape(a)


def head_angles(rotation: np.ndarray, reference_rotation: np.ndarray = FRONTAL) -> np.ndarray:
    """Head pitch (down), yaw (left), roll (right) relative to a reference pose.

    rotation : (F, 3) axis-angle rad, head -> camera (``Pose.rotation``).
    reference_rotation : (3,) axis-angle rad of the pose taken as "no rotation".
    Returns (F, 3) rad: ``R_ref^T R = R_y(yaw) R_x(pitch) R_z(roll)`` (module docstring).
    """
    rel = np.swapaxes(rotation_matrix(reference_rotation), -1, -2) @ rotation_matrix(rotation)
    pitch = np.arcsin(np.clip(-rel[:, 1, 2], -1.0, 1.0))
    yaw = np.arctan2(rel[:, 0, 2], rel[:, 2, 2])
    roll = np.arctan2(rel[:, 1, 0], rel[:, 1, 1])
    return np.stack([pitch, yaw, roll], axis=-1)


class FapEncoder:
    """FAPs of one speaker model: FAPU, directions and feature points precomputed once.

    Parameters
    ----------
    model : the speaker model; its ``feature_points`` say which points are MPEG-4 points.
    reference_rotation : (3,) axis-angle rad, the head pose whose head FAPs are 0
        (default :data:`~articast.core.model.camera.FRONTAL`; the CLI can use a session's first
        frame).
    jaw_relative : lower-lip and chin FAPs relative to the jaw (module docstring).
    neutral_alpha : (K,) posture of the neutral face (default: the mean, alpha = 0).

    Attributes
    ----------
    fapu : :class:`Fapu`. mask : (68,) bool, True for the FAPs this model can produce
        (geometric FAPs whose feature point is labelled, and the head FAPs).
    """

    def __init__(
        self,
        model: FaceModel,
        *,
        reference_rotation: np.ndarray = FRONTAL,
        jaw_relative: bool = True,
        neutral_alpha: np.ndarray | None = None,
    ) -> None:
        ref = np.asarray(reference_rotation, dtype=np.float64)
        if ref.shape != (3,) or not np.all(np.isfinite(ref)):
            raise InputError(f"reference_rotation must be 3 finite numbers, got {ref!r}")
        self.model = model
        self.reference_rotation = ref
        self.jaw_relative = bool(jaw_relative)
        self.fapu = fapu_from_model(model, neutral_alpha)
        self.neutral = _neutral_shape(model, neutral_alpha)
        if self.jaw_relative and JAW_POINT not in model.feature_points:
            raise InputError(f"jaw-relative FAPs need feature point {JAW_POINT} (the jaw)")
        specs = [FAP_TABLE[n - 1] for n in GEOMETRIC_FAPS]
        specs = [s for s in specs if s.feature_point in model.feature_points]
        self.faps = np.array([s.number for s in specs], dtype=np.int64)
        self.labels = tuple(s.feature_point for s in specs)
        self.points = np.array([model.point(lab) for lab in self.labels], dtype=np.int64)
        self.directions = np.array([DIRECTIONS[s.direction] for s in specs]).reshape(-1, 3)
        self.units = np.array([self.fapu.unit(s.unit) for s in specs])
        self.relative = np.array(
            [self.jaw_relative and s.number in JAW_RELATIVE_FAPS for s in specs], dtype=bool
        )
        self.mask = np.zeros(N_FAPS, dtype=bool)
        self.mask[self.faps - 1] = True
        self.mask[np.array(HEAD_FAPS) - 1] = True
        self.mask.setflags(write=False)

    def values(self, alpha: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """FAP values of F frames.

        alpha : (F, K) articulatory parameters. pose : (F, 6) rotation (axis-angle rad) then
        translation (mm), head -> camera, as ``Pose.as_vector()``.
        Returns ``(values, mask)``: values (F, 68) int64, FAP n in column n - 1, 0 where masked;
        mask (68,) bool (:attr:`mask`).
        """
        alpha, pose = self._check(alpha, pose)
        model = self.model
        pts = model.mean[self.points] + np.einsum("fk,kgc->fgc", alpha, model.basis[:, self.points])
        disp = pts - self.neutral[self.points]  # (F, G, 3) mm, head frame
        if self.relative.any():
            jaw = model.point(JAW_POINT)
            jaw_dy = model.mean[jaw, 1] + alpha @ model.basis[:, jaw, 1] - self.neutral[jaw, 1]
            disp[:, self.relative, 1] -= jaw_dy[:, None]
        out = np.zeros((alpha.shape[0], N_FAPS), dtype=np.int64)
        geo = np.einsum("fgc,gc->fg", disp, self.directions) / self.units
        out[:, self.faps - 1] = np.rint(geo).astype(np.int64)
        ang = head_angles(pose[:, :3], self.reference_rotation) / AU
        out[:, np.array(HEAD_FAPS) - 1] = np.rint(ang).astype(np.int64)
        return out, self.mask.copy()

    def frame_dict(self, alpha: np.ndarray, pose: np.ndarray) -> dict[str, int]:
        """FAPs of one frame as ``{"3": value, ...}`` (FAP numbers as strings, masked-in FAPs
        only), e.g. for the ``fap`` stream of the service. alpha (K,), pose (6,) rad, mm."""
        values, mask = self.values(np.reshape(alpha, (1, -1)), np.reshape(pose, (1, -1)))
        return {str(n + 1): int(values[0, n]) for n in np.flatnonzero(mask)}

    def _check(self, alpha: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        alpha = np.asarray(alpha, dtype=np.float64)
        pose = np.asarray(pose, dtype=np.float64)
        k = self.model.n_params
        if alpha.ndim != 2 or alpha.shape[1] != k:
            raise InputError(f"alpha must have shape (F, {k}), got {alpha.shape}")
        if pose.shape != (alpha.shape[0], 6):
            raise InputError(f"pose must have shape ({alpha.shape[0]}, 6), got {pose.shape}")
        if not (np.all(np.isfinite(alpha)) and np.all(np.isfinite(pose))):
            raise InputError("alpha and pose must be finite")
        return alpha, pose


def fap_values(
    model: FaceModel, alpha: np.ndarray, pose: np.ndarray, **options: object
) -> tuple[np.ndarray, np.ndarray]:
    """FAPs of F frames: ``FapEncoder(model, **options).values(alpha, pose)``.

    alpha : (F, K); pose : (F, 6) rad, mm. Returns values (F, 68) int64 and mask (68,) bool.
    """
    return FapEncoder(model, **options).values(alpha, pose)  # type: ignore[arg-type]


def reconstruct_feature_points(encoder: FapEncoder, values: np.ndarray) -> dict[str, np.ndarray]:
    """Head-frame positions of the feature points implied by FAP values (the inverse map).

    values : (F, 68) FAP values as produced by ``encoder``. Returns ``{label: (F, 3) mm}``
    for every feature point moved by a geometric FAP: the neutral position plus, for each FAP
    moving it, ``value * unit`` along its direction; for jaw-relative FAPs, plus the jaw's
    vertical displacement (``-open_jaw * MNS0 / 1024``) along that direction. Components no FAP
    controls stay at their neutral value. Rounding limits the accuracy to half a unit per FAP.
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != N_FAPS:
        raise InputError(f"FAP values must have shape (F, {N_FAPS}), got {v.shape}")
    moves = v[:, encoder.faps - 1] * encoder.units  # (F, G) mm along each direction
    jaw = np.zeros((v.shape[0], 3))
    jaw[:, 1] = -v[:, 2] * encoder.fapu.unit("MNS")  # open_jaw (FAP 3) is the jaw's drop
    out: dict[str, np.ndarray] = {}
    for i, lab in enumerate(encoder.labels):
        if lab not in out:
            out[lab] = np.repeat(encoder.neutral[encoder.points[i]][None], v.shape[0], axis=0)
        step = moves[:, i]
        if encoder.relative[i]:
            step = step + jaw @ encoder.directions[i]
        out[lab] = out[lab] + step[:, None] * encoder.directions[i]
    return out


def lip_aperture(points: dict[str, np.ndarray]) -> np.ndarray:
    """Inner lip aperture (F,) mm: distance from 2.2 to 2.3 (``{label: (F, 3)}``)."""
    return np.linalg.norm(points["2.2"] - points["2.3"], axis=-1)


def lip_width(points: dict[str, np.ndarray]) -> np.ndarray:
    """Outer lip width (F,) mm: distance from 8.3 to 8.4 (``{label: (F, 3)}``)."""
    return np.linalg.norm(points["8.3"] - points["8.4"], axis=-1)
