"""The speaker-specific linear articulatory face model (METHOD.md §1).

Geometry in the *head frame*, millimetres: x to the speaker's own left, y up, z forward (out
of the face, towards a frontal camera); origin near the upper incisors on the bite plane.

    x(alpha) = mean + sum_k alpha_k * basis[k]          (N, 3)

``alpha`` is in units of training standard deviations (guided PCA scores are centred and
scaled to unit variance), so ``alpha_k = +-1`` spans one s.d. of the corpus.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from articast.core.bundle import load_bundle, reading, require, save_bundle
from articast.core.errors import InputError

PARAM_NAMES: tuple[str, ...] = ("jaw1", "lips1", "lips2", "lips3", "lips4", "jaw2", "lar1")
"""The seven articulatory parameters, in the paper's order."""

POINT_GROUPS: tuple[str, ...] = (
    "jaw_line",
    "lower_teeth",
    "lip_inner",
    "lip_outer",
    "lip_beads",
    "upper_lip",
    "lower_lip",
    "rest",
)
"""Named point groups. ``upper_lip``/``lower_lip`` are the lip points (inner, outer contour
and beads) on each lip; the other groups partition the points."""

FEATURE_POINTS: tuple[str, ...] = (
    "2.1", "2.2", "2.3", "2.4", "2.5", "2.6", "2.7", "2.8", "2.9", "2.10",
    "8.1", "8.2", "8.3", "8.4", "8.5", "8.6", "8.7", "8.8",
    "9.15", "3.5", "3.6", "7.1",
)  # fmt: skip
"""MPEG-4 feature points a model labels (FAP.md)."""

MODEL_KIND = "face-model"
MODEL_VERSION = 1


def _frozen(a: np.ndarray, dtype: type) -> np.ndarray:
    a = np.array(a, dtype=dtype, copy=True)
    a.setflags(write=False)
    return a


MAX_MM = 1e5
"""|coordinate| and |basis value| of a model, mm (100 m): 1e308 in a model file made the
fits fail with LinAlgError in a crash-restart loop before."""

@dataclass(frozen=True, eq=False)
class ParamStats:
    """Training statistics of the articulatory parameters, each an array of shape (K,)."""

    mean: np.ndarray
    std: np.ndarray
    min: np.ndarray
    max: np.ndarray

    def __post_init__(self) -> None:
        for name in ("mean", "std", "min", "max"):
            object.__setattr__(self, name, _frozen(getattr(self, name), np.float64))

    @classmethod
    def from_scores(cls, scores: np.ndarray) -> ParamStats:
        """Statistics of ``scores`` (V, K)."""
        scores = np.asarray(scores, dtype=np.float64)
        return cls(scores.mean(0), scores.std(0), scores.min(0), scores.max(0))


def range_motion(basis: np.ndarray, stats: ParamStats) -> np.ndarray:
    """(K, P): how far (mm) each of P points moves under each parameter over its training
    range (max - min), from their basis (K, P, 3). What the point selection, the occlusion
    test and the rigid points of the live flow each judge a point by."""
    return np.linalg.norm(basis, axis=2) * (stats.max - stats.min)[:, None]


@dataclass(frozen=True, eq=False)
class FaceModel:
    """A linear articulatory model.

    Attributes
    ----------
    mean : ndarray (N, 3) float64, mm, head frame
    basis : ndarray (K, N, 3) float64, mm per unit alpha
    param_names : K names (normally :data:`PARAM_NAMES`)
    stats : training statistics of alpha
    point_names : N names
    groups : group name -> int array of point indices
    triangles : ndarray (T, 3) int32, counter-clockwise seen from the front (+z)
    feature_points : MPEG-4 label (e.g. ``"8.3"``) -> point index
    fapu_overrides : FAPU name (``"ES0"``, ``"ENS0"``...) -> value in mm, for models without
        the points that would define it
    name : free text identifying the speaker
    """

    mean: np.ndarray
    basis: np.ndarray
    param_names: tuple[str, ...] = PARAM_NAMES
    # None as an argument means "unit statistics"; __post_init__ always fills it, so readers
    # see a ParamStats (typed so: no Optional narrowing at every use)
    stats: ParamStats = None  # type: ignore[assignment]
    point_names: tuple[str, ...] = ()
    groups: Mapping[str, np.ndarray] = field(default_factory=dict)
    triangles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))
    feature_points: Mapping[str, int] = field(default_factory=dict)
    fapu_overrides: Mapping[str, float] = field(default_factory=dict)
    name: str = "speaker"

    def __post_init__(self) -> None:
        mean = _frozen(self.mean, np.float64)
        basis = _frozen(self.basis, np.float64)
        if mean.ndim != 2 or mean.shape[1] != 3:
            raise InputError(f"mean must have shape (N, 3), got {mean.shape}")
        n = mean.shape[0]
        if basis.ndim != 3 or basis.shape[1:] != (n, 3):
            raise InputError(f"basis must have shape (K, {n}, 3), got {basis.shape}")
        k = basis.shape[0]
        if len(self.param_names) != k:
            raise InputError(f"{len(self.param_names)} parameter names for {k} basis vectors")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(basis))):
            raise InputError("mean and basis must be finite")
        names = tuple(self.point_names) or tuple(f"p{i}" for i in range(n))
        if len(names) != n:
            raise InputError(f"{len(names)} point names for {n} points")
        stats = self.stats or ParamStats(np.zeros(k), np.ones(k), -3 * np.ones(k), 3 * np.ones(k))
        if stats.mean.shape != (k,):
            raise InputError(f"parameter statistics must have shape ({k},)")
        groups = {}
        for g, idx in self.groups.items():
            idx = _frozen(idx, np.int64).ravel()
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                raise InputError(f"group {g!r} indexes points outside 0..{n - 1}")
            groups[g] = idx
        tri = _frozen(self.triangles, np.int32).reshape(-1, 3)
        if tri.size and (tri.min() < 0 or tri.max() >= n):
            raise InputError(f"triangles index points outside 0..{n - 1}")
        fp = {str(lab): int(i) for lab, i in self.feature_points.items()}
        bad = [lab for lab, i in fp.items() if not 0 <= i < n]
        if bad:
            raise InputError(f"feature points {bad} index points outside 0..{n - 1}")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "basis", basis)
        object.__setattr__(self, "param_names", tuple(self.param_names))
        object.__setattr__(self, "point_names", names)
        object.__setattr__(self, "stats", stats)
        object.__setattr__(self, "groups", MappingProxyType(groups))
        object.__setattr__(self, "triangles", tri)
        object.__setattr__(self, "feature_points", MappingProxyType(fp))
        object.__setattr__(
            self, "fapu_overrides", MappingProxyType(dict(self.fapu_overrides))
        )

    # ------------------------------------------------------------------ geometry
    @property
    def n_points(self) -> int:
        return int(self.mean.shape[0])

    @property
    def n_params(self) -> int:
        return int(self.basis.shape[0])

    def shape(self, alpha: np.ndarray) -> np.ndarray:
        """Geometry at ``alpha``.

        alpha : array (..., K) -> returns (..., N, 3) float64 mm, head frame.
        """
        alpha = np.asarray(alpha, dtype=np.float64)
        if alpha.shape[-1:] != (self.n_params,):
            raise InputError(f"alpha must end in ({self.n_params},), got {alpha.shape}")
        flat = self.basis.reshape(self.n_params, -1)
        out = alpha @ flat + self.mean.reshape(-1)
        return out.reshape(alpha.shape[:-1] + (self.n_points, 3))

    def alpha_dict(self, alpha: np.ndarray) -> dict[str, float]:
        """``{name: value}`` for one alpha (K,)."""
        return {n: float(v) for n, v in zip(self.param_names, np.asarray(alpha), strict=True)}

    def alpha_from_dict(self, values: Mapping[str, float]) -> np.ndarray:
        """Alpha (K,) from ``{name: value}``; missing names are 0, unknown names an error."""
        unknown = set(values) - set(self.param_names)
        if unknown:
            raise InputError(f"unknown parameters {sorted(unknown)}; known: {self.param_names}")
        return np.array([float(values.get(n, 0.0)) for n in self.param_names])

    def group(self, name: str) -> np.ndarray:
        """Indices of the named group (empty if the model has none)."""
        return self.groups.get(name, np.zeros(0, np.int64))

    def point(self, label: str) -> int:
        """Point index of an MPEG-4 feature-point label such as ``"8.3"``."""
        try:
            return self.feature_points[label]
        except KeyError:
            raise InputError(f"model {self.name!r} labels no feature point {label}") from None

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the model as a versioned bundle (see :mod:`articast.core.bundle`)."""
        arrays = {
            "mean": self.mean,
            "basis": self.basis,
            "triangles": self.triangles,
            "stats": np.stack([self.stats.mean, self.stats.std, self.stats.min, self.stats.max]),
        }
        for g, idx in self.groups.items():
            arrays[f"group__{g}"] = idx
        meta = {
            "name": self.name,
            "param_names": list(self.param_names),
            "point_names": list(self.point_names),
            "feature_points": dict(self.feature_points),
            "fapu_overrides": dict(self.fapu_overrides),
            "groups": list(self.groups),
        }
        save_bundle(path, MODEL_KIND, MODEL_VERSION, arrays, meta)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> FaceModel:
        """Read a model file; raises :class:`~articast.core.errors.ModelFileError` on any defect."""
        arrays, meta = load_bundle(path, MODEL_KIND, (MODEL_VERSION,))
        with reading(path, "face model"):
            for key in ("mean", "basis", "triangles", "stats"):
                require(key in arrays, path, f"missing array {key!r}")
            mean, basis = arrays["mean"], arrays["basis"]
            require(mean.ndim == 2 and mean.shape[1] == 3, path, f"mean has shape {mean.shape}, "
                    "expected (N, 3)")
            n = mean.shape[0]
            require(basis.ndim == 3 and basis.shape[1:] == (n, 3), path,
                    f"basis has shape {basis.shape}, expected (K, {n}, 3)")
            k = basis.shape[0]
            require(bool(np.all(np.abs(mean) <= MAX_MM)) and bool(np.all(np.abs(basis) <= MAX_MM)),
                    path, f"mean or basis values beyond {MAX_MM:g} mm: not a face model")
            # degenerate geometry loaded and tracked "ok" before: a face has extent, and its
            # parameters move it
            spread = (np.linalg.svd(mean - mean.mean(axis=0), compute_uv=False)
                      if n >= 3 else np.ones(2))
            require(float(spread[1]) > 1e-3, path,
                    "the mean shape's points do not span a surface (all at one place, or on "
                    "one line): not a face model")
            require(k == 0 or float(np.abs(basis).max()) >= 1e-6, path,
                    "the basis moves no point (all its values are below 1e-6 mm): not a face "
                    "model")
            require(arrays["stats"].shape == (4, k), path,
                    f"stats has shape {arrays['stats'].shape}, expected (4, {k})")
            names = meta.get("param_names", [])
            require(len(names) == k, path, f"{len(names)} parameter names for {k} basis vectors")
            pnames = meta.get("point_names", [])
            require(len(pnames) == n, path, f"{len(pnames)} point names for {n} points")
            tri = arrays["triangles"]
            require(tri.ndim == 2 and tri.shape[1] == 3, path, f"triangles have shape {tri.shape}")
            require(tri.size == 0 or (tri.min() >= 0 and tri.max() < n), path,
                    "triangles index points that do not exist")
            groups = {g: arrays.get(f"group__{g}", np.zeros(0, np.int64)) for g in meta["groups"]}
            for g, idx in groups.items():
                require(idx.size == 0 or (idx.min() >= 0 and idx.max() < n), path,
                        f"group {g!r} indexes points that do not exist")
            fp = meta.get("feature_points", {})
            require(all(0 <= int(i) < n for i in fp.values()), path,
                    "feature points index points that do not exist")
            s = arrays["stats"]
            return cls(
                mean=mean,
                basis=basis,
                param_names=tuple(names),
                stats=ParamStats(s[0], s[1], s[2], s[3]),
                point_names=tuple(pnames),
                groups=groups,
                triangles=tri,
                feature_points=fp,
                fapu_overrides=meta.get("fapu_overrides", {}),
                name=str(meta.get("name", "speaker")),
            )
