"""The paper's evaluation measures (METHOD.md §3, evaluation protocol), on ground truth.

As in the paper, the RMS 3D error compares the model geometry at the tracked alpha with the
model geometry at the *true* alpha (direct inversion of the true 3D points, head frame, all
model points). :func:`rms_to_points` also reports the error against the true points
themselves, which adds the linear model's own approximation error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from articast.core.model.face import FaceModel


def rms_3d(model: FaceModel, alpha: np.ndarray, alpha_true: np.ndarray) -> np.ndarray:
    """Per-frame RMS (mm) over all model points between geometries at alpha and alpha_true.

    alpha, alpha_true : (F, K). Returns (F,).
    """
    d = model.shape(alpha) - model.shape(alpha_true)
    return np.sqrt((d**2).sum(-1).mean(-1))


def rms_to_points(model: FaceModel, alpha: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Per-frame RMS (mm) between the model at alpha (F, K) and true points (F, N, 3)."""
    d = model.shape(alpha) - points
    return np.sqrt((d**2).sum(-1).mean(-1))


def lip_width(model: FaceModel, alpha: np.ndarray) -> np.ndarray:
    """Outer lip corner to corner distance (mm), MPEG-4 points 8.3 - 8.4. alpha (F, K)."""
    g = model.shape(alpha)
    return np.linalg.norm(g[..., model.point("8.3"), :] - g[..., model.point("8.4"), :], axis=-1)


def lip_aperture(model: FaceModel, alpha: np.ndarray) -> np.ndarray:
    """Inner upper-lip midpoint to inner lower-lip midpoint (mm), points 2.2 - 2.3."""
    g = model.shape(alpha)
    return np.linalg.norm(g[..., model.point("2.2"), :] - g[..., model.point("2.3"), :], axis=-1)


def still_pairs(points_true: np.ndarray, tol_mm: float = 1e-6) -> np.ndarray:
    """(F-1,) True where the true geometry does not move between frame i and i+1."""
    step = np.abs(np.diff(points_true, axis=0)).reshape(len(points_true) - 1, -1).max(1)
    return step <= tol_mm


def jitter_mm(model: FaceModel, alpha: np.ndarray, still: np.ndarray) -> float:
    """RMS frame-to-frame motion (mm, over all model points) of the tracked geometry across
    the frame pairs where the truth is still. NaN if there is no still pair."""
    if not still.any():
        return float("nan")
    g = model.shape(alpha)
    d = np.diff(g, axis=0)[still]
    return float(np.sqrt((d**2).sum(-1).mean()))


def lag_frames(tracked: np.ndarray, truth: np.ndarray, max_lag: int = 6) -> int:
    """Lag (frames) of a tracked curve behind the truth: the shift maximising their
    cross-correlation (positive = tracked late)."""
    a = np.asarray(tracked, float) - np.mean(tracked)
    b = np.asarray(truth, float) - np.mean(truth)
    best, best_c = 0, -np.inf
    n = len(a)
    for lag in range(-max_lag, max_lag + 1):
        if lag >= 0:
            c = np.dot(a[lag:], b[:n - lag]) / max(n - lag, 1)
        else:
            c = np.dot(a[:n + lag], b[-lag:]) / max(n + lag, 1)
        if c > best_c:
            best, best_c = lag, c
    return best


@dataclass(frozen=True)
class SequenceScore:
    """Figures of one tracked sequence against its truth."""

    rms_mm: np.ndarray  # (F,) model at tracked vs model at true alpha
    rms_points_mm: np.ndarray  # (F,) model at tracked vs true points
    ok: np.ndarray  # (F,) bool
    evals: np.ndarray  # (F,)
    ms: np.ndarray  # (F,)
    jitter_mm: float
    lag_frames: int  # -999 when the model labels no lip midpoints

    def summary(self, scored: np.ndarray | None = None) -> dict[str, float]:
        """The figures of ``evaluate --json`` (over ``scored`` frames, default the ok ones)."""
        sel = self.ok if scored is None else scored
        r = self.rms_mm[sel] if sel.any() else np.array([np.nan])
        return {
            "rms_mm_mean": float(np.mean(r)),
            "rms_mm_median": float(np.median(r)),
            "rms_mm_p95": float(np.percentile(r, 95)),
            "rms_points_mm_mean": float(np.mean(self.rms_points_mm[sel])) if sel.any() else
            float("nan"),
            "evals_per_frame": float(np.mean(self.evals)),
            "ms_per_frame": float(np.mean(self.ms)),
            "ok_fraction": float(np.mean(self.ok)),
            "jitter_mm": self.jitter_mm,
            "lag_frames": float(self.lag_frames),
        }


def score_sequence(model: FaceModel, alpha: np.ndarray, ok: np.ndarray, evals: np.ndarray,
                   ms: np.ndarray, points_true: np.ndarray) -> SequenceScore:
    """Score a tracked sequence against its true 3D points (F, N, 3), head frame.

    The true alpha is the direct inversion of the true points in ``model``.
    """
    from articast.core.model.build import invert

    alpha_true = invert(model, points_true)
    still = still_pairs(points_true)
    lag = -999
    if {"2.2", "2.3"} <= set(model.feature_points):
        lag = lag_frames(lip_aperture(model, alpha), lip_aperture(model, alpha_true))
    return SequenceScore(
        rms_3d(model, alpha, alpha_true), rms_to_points(model, alpha, points_true),
        np.asarray(ok, bool), np.asarray(evals, float), np.asarray(ms, float),
        jitter_mm(model, alpha, still & ok[1:] & ok[:-1]), lag,
    )
