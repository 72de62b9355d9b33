"""Synthetic speech sequences: coarticulated control trajectories, head motion, ground truth.

Controls move through a chain of posture tokens drawn from the speaker's corpus targets
(about 4 syllables per second, one target per consonant or vowel) along a quintic path that
passes every target without stopping (coarticulation: velocity there is 0.6 x the mean of the
neighbouring slopes, acceleration zero, so the trajectory is C2 and its acceleration
bounded). *Still segments* hold one posture and the head pose exactly constant for a given
number of frames (for jitter measurements): the first one at rest, one in the middle on a
vowel.

Rigs:
- ``"head"``: a head-mounted camera 22 cm in front of and below the mouth, looking at the lower
  face (which fills most of the frame); the camera moves with the head up to a tiny wobble
  (< 0.5 mm, < 0.3 deg).
- ``"desk"``: a desk camera 56 cm away; the whole face is visible and the head nods, turns and
  drifts (a few degrees, 10-20 mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from articast.core.errors import InputError
from articast.core.model.camera import Camera, Pose, axis_angle, rotation_matrix
from articast.core.model.face import PARAM_NAMES
from articast.core.synthetic.corpus import corpus_controls
from articast.core.synthetic.geometry import SpeakerGeometry, make_geometry

RIGS = ("head", "desk")
HEAD_CENTRE = np.array([0.0, 12.0, -95.0])
"""Centre of head rotations in the head frame (mm), feature point 7.1."""
#: rig -> (camera position, look-at point) in the head frame (mm), horizontal field of view
RIG_GEOMETRY = {
    "head": ((0.0, -40.0, 215.0), (0.0, -16.0, 0.0), 44.0),
    "desk": ((0.0, 5.0, 560.0), (0.0, -5.0, 0.0), 50.0),
}
RAMP_S = 0.12
"""Duration (s) over which head motion slows down into / speeds up out of a still segment."""


def default_camera(rig: str = "head", width: int = 640, height: int = 480) -> Camera:
    """The undistorted camera of ``rig`` at the given image size."""
    _check_rig(rig)
    if int(width) <= 0 or int(height) <= 0:
        raise InputError(f"image size must be positive, got {width}x{height}")
    return Camera.default(int(width), int(height), RIG_GEOMETRY[rig][2])


def rest_pose(rig: str = "head") -> Pose:
    """Head -> camera pose of ``rig`` with the head at rest."""
    _check_rig(rig)
    eye_xyz, target_xyz, _ = RIG_GEOMETRY[rig]
    eye, target = np.asarray(eye_xyz), np.asarray(target_xyz)
    fwd = (target - eye) / np.linalg.norm(target - eye)  # camera z, in the head frame
    right = np.cross(fwd, [0.0, 1.0, 0.0])  # camera x: head up x forward
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)  # camera y
    rot = np.stack([right, down, fwd])  # rows: camera axes in head coordinates
    return Pose(axis_angle(rot), -rot @ eye)


def _check_rig(rig: str) -> None:
    if rig not in RIGS:
        raise InputError(f"rig must be one of {RIGS}, got {rig!r}")


@dataclass(frozen=True, eq=False)
class Sequence:
    """Ground truth of a synthetic sequence.

    times : (F,) s. controls : (F, 7) generating controls. poses : (F, 6) head -> camera,
    axis-angle rotation (rad) then translation (mm). points : (F, N, 3) true geometry, mm, head
    frame. camera : the camera. still : (F,) bool, frames inside a still segment (truth
    identical to the segment's first frame). rig : "head" or "desk". fps : frames per second.
    """

    times: np.ndarray
    controls: np.ndarray
    poses: np.ndarray
    points: np.ndarray
    camera: Camera
    still: np.ndarray
    rig: str
    fps: float

    @property
    def n_frames(self) -> int:
        return int(self.times.size)

    def pose(self, i: int) -> Pose:
        """Head pose of frame ``i``."""
        return Pose.from_vector(self.poses[i])

    def still_segments(self) -> list[tuple[int, int]]:
        """[start, stop) frame ranges of the still segments."""
        edges = np.diff(np.concatenate([[0], self.still.astype(np.int8), [0]]))
        starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


def quintic_path(times: np.ndarray, key_t: np.ndarray, key_x: np.ndarray,
                 key_v: np.ndarray | None = None) -> np.ndarray:
    """Piecewise quintic Hermite path through keyframes, zero acceleration at every keyframe.

    times : (F,) s; key_t : (K,) increasing s; key_x : (K, D) positions; key_v : (K, D)
    velocities per s (default zero: the minimum-jerk path that stops at every keyframe).
    Returns (F, D); constant outside the keyframes. The path is C2: position, velocity and
    acceleration (zero) are continuous at the keyframes.
    """
    key_v = np.zeros_like(key_x) if key_v is None else key_v
    t = np.clip(times, key_t[0], key_t[-1])
    seg = np.clip(np.searchsorted(key_t, t, side="right") - 1, 0, len(key_t) - 2)
    t0, t1 = key_t[seg], key_t[seg + 1]
    span = (t1 - t0)[:, None]
    s = ((t - t0) / (t1 - t0))[:, None]
    s3 = s**3
    h_p1 = s3 * (10 - 15 * s + 6 * s**2)
    h_v0 = s - s3 * (6 - 8 * s + 3 * s**2)
    h_v1 = s3 * (-4 + 7 * s - 3 * s**2)
    return (key_x[seg] + (key_x[seg + 1] - key_x[seg]) * h_p1
            + span * (key_v[seg] * h_v0 + key_v[seg + 1] * h_v1))


def via_velocities(key_t: np.ndarray, key_x: np.ndarray, stop: np.ndarray,
                   gain: float = 0.6) -> np.ndarray:
    """Velocities (K, D) at keyframes for a fluid path: ``gain`` times the mean of the slopes
    of the two neighbouring segments (coarticulation: the articulators do not stop at each
    target), zero where ``stop`` (K,) bool (first/last keyframe, holds)."""
    slope = np.diff(key_x, axis=0) / np.diff(key_t)[:, None]
    v = np.zeros_like(key_x)
    v[1:-1] = gain * 0.5 * (slope[:-1] + slope[1:])
    v[stop] = 0.0
    v[[0, -1]] = 0.0
    return v


def _frozen_time(t: np.ndarray, holds: list[tuple[float, float]], r: float) -> np.ndarray:
    """Motion time: real time ``t`` (F,) minus the time the head spends stopped.

    The head slows down over ``r`` s (raised cosine) before each hold [a, b], stands still
    during it (motion time exactly constant) and speeds up over ``r`` s after it.
    """
    lost = np.zeros_like(t, dtype=np.float64)
    for a, b in holds:
        u, v = t - (a - r), t - b
        k = 0.5 * r / np.pi
        lost += np.select(
            [t < a - r, t < a, t <= b, t < b + r],
            [0.0, 0.5 * u - k * np.sin(np.pi * u / r), r / 2 + (t - a),
             r / 2 + (b - a) + 0.5 * v + k * np.sin(np.pi * v / r)],
            r + (b - a),
        )
    tau = t - lost
    for a, b in holds:
        inside = np.flatnonzero((t >= a) & (t <= b))
        if inside.size:
            tau[inside] = tau[inside[0]]  # exactly, not to rounding
    return tau


def _head_motion(tau: np.ndarray, rig: str, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """Rotation offsets (F, 3) rad and translations (F, 3) mm of the head at motion times."""
    if rig == "desk":
        rot_amp, trans_amp, freqs = np.radians([3.0, 2.5, 1.2]), np.array([6.0, 4.0, 5.0]), (
            0.15, 0.6)
    else:
        rot_amp, trans_amp, freqs = np.radians([0.15, 0.12, 0.1]), np.array([0.25, 0.2, 0.2]), (
            0.3, 1.2)
    out = []
    for amp in (rot_amp, trans_amp):
        f = rng.uniform(*freqs, size=(3, 3))
        ph = rng.uniform(0, 2 * np.pi, size=(3, 3))
        w = np.array([1.0, 0.5, 0.25])
        wave = (np.sin(2 * np.pi * f[None] * tau[:, None, None] + ph[None]) * w).sum(-1)
        wave -= (np.sin(ph) * w).sum(-1)  # start at the rest pose
        out.append(wave * amp / w.sum())
    if rig == "desk":  # a slow drift on top
        drift = rng.normal(0.0, 1.0, 3) * np.array([8.0, 5.0, 10.0])
        out[1] = out[1] + drift * np.tanh(tau / 4.0)[:, None]
    return out[0], out[1]


def make_sequence(seed: int = 0, n_frames: int = 150, fps: float = 50.0, rig: str = "head",
                  still_frames: int = 15, size: tuple[int, int] = (640, 480),
                  geometry: SpeakerGeometry | None = None) -> Sequence:
    """A sequence of the speaker of ``seed`` talking, with its ground truth.

    size : (width, height) of the rig's default camera (:func:`default_camera`).
    still_frames : length of each still segment (0 disables them). The first one (at rest,
    from frame 0) needs at least 2 x still_frames frames, the one in the middle 5 x.
    """
    _check_rig(rig)
    if int(seed) != seed or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    default_camera(rig, *size)  # validates the size before any work
    if int(n_frames) != n_frames or n_frames < 1:
        raise InputError(f"n_frames must be a positive integer, got {n_frames!r}")
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"fps must be positive, got {fps!r}")
    if int(still_frames) != still_frames or still_frames < 0:
        raise InputError(f"still_frames must be a non-negative integer, got {still_frames!r}")
    geom = geometry if geometry is not None else make_geometry(seed)
    rng = np.random.default_rng([int(seed), 0x5E0])
    n_frames, still_frames = int(n_frames), int(still_frames)
    times = np.arange(n_frames) / fps
    duration = times[-1] + 1.0 / fps
    _, tokens = corpus_controls(seed + 1000, geom)  # same phonetics, fresh variability
    rest = np.zeros(len(PARAM_NAMES))
    hold = still_frames / fps  # [t, t + hold] holds at least still_frames frame times
    key_t, key_x, holds = [0.0], [rest], []
    t = 0.0
    if still_frames and duration >= 2 * hold:
        t = hold
        key_t.append(t)
        key_x.append(rest)
        holds.append((0.0, hold))
    mid_hold_done = not still_frames or duration < 5 * hold
    vowels = np.arange(14)  # the corpus lists the 14 vowels first
    while t < duration + 0.2:
        t += rng.uniform(0.09, 0.16)
        if not mid_hold_done and t > duration / 2:
            x = tokens[rng.choice(vowels)]
            key_t += [t, t + hold]
            key_x += [x, x]
            holds.append((t, t + hold))
            t += hold
            mid_hold_done = True
            continue
        key_t.append(t)
        key_x.append(tokens[rng.integers(len(tokens))])
    key_t_a, key_x_a = np.array(key_t), np.array(key_x)
    stop = np.zeros(len(key_t), bool)
    for a, b in holds:
        stop |= (key_t_a >= a) & (key_t_a <= b)
    controls = quintic_path(times, key_t_a, key_x_a, via_velocities(key_t_a, key_x_a, stop))

    tau = _frozen_time(times, [(a if a > 0 else -1.0, b) for a, b in holds], RAMP_S)
    d_rot, d_trans = _head_motion(tau, rig, rng)
    base = rest_pose(rig)
    r_base = base.matrix
    r_m = rotation_matrix(d_rot)  # (F, 3, 3) head motion about HEAD_CENTRE
    rot = np.einsum("ij,fjk->fik", r_base, r_m)
    trans = (np.einsum("ij,fj->fi", r_base, HEAD_CENTRE - np.einsum("fij,j->fi", r_m, HEAD_CENTRE)
                       + d_trans) + base.translation)
    poses = np.concatenate([np.stack([axis_angle(r) for r in rot]), trans], 1)

    still = np.zeros(n_frames, bool)
    for a, b in holds:
        still |= (times >= max(a, 0.0)) & (times <= b)
    points = geom.articulate(controls)
    cam = default_camera(rig, *size)
    return Sequence(times, controls, poses, points, cam, still, rig, float(fps))
