"""What turns a frame into a :class:`~articast.core.tracking.result.TrackResult`: the
``FrameProcessor`` seam.

A session's ``processor`` option picks one:

``truth``     pass the source's ground truth through (synthetic speaker, recordings): streams
              exact ground truth to avatars for testing them.
``tracker``   the real tracker (``articast.core.tracking.tracker.Tracker``), one instance per
session run.
``auto``      ``truth`` for recordings; otherwise ``tracker`` when it is available, else
              ``truth`` if the source carries ground truth; else a clear error.
``pkg.mod:fn``  any callable ``fn(context: ProcessorContext) -> FrameProcessor``.

Processors are built inside the worker (thread or process) that uses them, and are called
from that worker only.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from articast.core.errors import ArticastError, InputError
from articast.core.tracking.result import TrackResult
from articast.service.identity import IdentityWarning
from articast.service.source_types import Frame, SourceAssets, SourceInfo


class FrameProcessor(Protocol):
    def process(self, frame: Frame) -> TrackResult: ...


@dataclass(frozen=True)
class ProcessorContext:
    """What a processor factory gets: the session's assets, resolved."""

    session: str
    source: SourceInfo
    model: Any  # articast.core.model.face.FaceModel | None
    camera: Any  # articast.core.model.camera.Camera | None
    appearance: Any  # core.appearance.AppearanceModel | None
    options: dict[str, Any]
    speaker: Any = None  # articast.core.faces.speaker.Speaker | None
    progress: Any = None
    """Callable(str) telling the session (and its console) what a slow first start does."""
    busy: Any = None
    """Callable(str) -> context manager: work known to finish (compiling), said once and
    kept alive while it runs (:func:`articast.service.worker.busy`): not a stall."""


COMPILING = ("compiling the tracking kernels (first run only: 1-2 minutes on a busy machine; "
             "numba caches them)")
"""Measured: 99 s (55 s of CPU) at load ~8 and 125 s to the first frame at load 5-6 on this
2-core machine; "a few seconds" was read as a hang (issue 39)."""


def _warm_up(context: ProcessorContext, only: tuple[str, ...] | None = None) -> None:
    """Compile (first run) or load the cost kernels before frames flow (``only``: those the
    processor calls, :func:`articast.core.tracking.kernels.warm_up`), saying so when it
    compiles: a worker that is starting is not stalled."""
    if kernels_on_disk(only):
        warm_up_kernels(only)  # loaded from numba's cache
    elif context.busy is not None:
        with context.busy(COMPILING):
            warm_up_kernels(only)
    else:
        if context.progress is not None:
            context.progress(COMPILING)
        warm_up_kernels(only)


def kernels_on_disk(only: tuple[str, ...] | None = None) -> bool:
    """Whether numba's cache holds the kernels :func:`warm_up_kernels` would compile."""
    from articast.core.faces import kernels as faces_kernels
    from articast.core.tracking import kernels

    return kernels.compiled_on_disk(only) and (only is not None
                                               or faces_kernels.compiled_on_disk())


def warm_up_kernels(only: tuple[str, ...] | None = None) -> None:
    """Compile or load the tracking kernels (``only``: those,
    :func:`articast.core.tracking.kernels.warm_up`); with ``only`` None, the whole live
    face's, the upper face's compiled iris fit too (:mod:`articast.core.faces.kernels`)."""
    from articast.core.faces import kernels as faces_kernels
    from articast.core.tracking import kernels

    kernels.warm_up(only)
    if only is None:
        faces_kernels.warm_up()


class TruthProcessor:
    """Passes ground truth through; a frame without truth is ``ok=False``."""

    def __init__(self, context: ProcessorContext | None = None) -> None:
        self._last: TrackResult | None = None

    def process(self, frame: Frame) -> TrackResult:
        if frame.truth is not None:
            self._last = frame.truth
            return frame.truth
        import numpy as np

        from articast.core.model.camera import Pose
        from articast.core.model.face import PARAM_NAMES

        last = self._last
        return TrackResult(frame.index, frame.t,
                           last.alpha if last else np.zeros(len(PARAM_NAMES)),
                           last.pose if last else Pose(), ok=False,
                           reason="this frame carries no ground truth")


class TrackerProcessor:
    """Adapter to ``articast.core.tracking.tracker.Tracker``: the only place the service
    touches the tracker.

    Session options: ``rig`` ("head" or "desk": the pose prior), ``initial_pose`` (6 numbers,
    or a Pose; the synthetic source supplies its rig's rest pose) or ``distance_mm`` for a
    search around a frontal face at that distance (default 300).
    """

    def __init__(self, context: ProcessorContext) -> None:
        try:
            from articast.core.tracking.tracker import Tracker
        except ImportError as exc:
            raise ArticastError(f"the tracker is not available: {exc}") from None
        missing = [n for n in ("model", "appearance", "camera") if getattr(context, n) is None]
        if missing:
            raise InputError(
                f"session {context.session!r}: tracking needs {', '.join(missing)} "
                f"(give --{' --'.join(missing)}, or use a source that brings them)"
            )
        from articast.core.model.camera import Pose
        from articast.core.tracking.tracker import TrackingPolicy

        opts = context.options
        rig = str(opts.get("rig", "head"))
        try:
            policy = TrackingPolicy.for_rig(rig)
        except ValueError as exc:
            raise InputError(f"session {context.session!r}: {exc}") from None
        pose = opts.get("initial_pose")
        if pose is not None and not isinstance(pose, Pose):
            try:
                v = [float(x) for x in (pose.split(",") if isinstance(pose, str) else pose)]
                pose = Pose(np.asarray(v[:3]), np.asarray(v[3:6])) if len(v) == 6 else None
            except (TypeError, ValueError):
                pose = None
            if pose is None:
                raise InputError(f"session {context.session!r}: initial_pose must be 6 numbers "
                                 "rx,ry,rz,tx,ty,tz (axis-angle rad, mm)")
        if pose is None:  # a frontal face in front of the camera: searched around it
            pose = Pose(translation=np.array([0.0, 0.0, float(opts.get("distance_mm", 300.0))]))
        self.tracker = Tracker(context.model, context.appearance, context.camera, policy,
                               initial_pose=pose, clock=time.perf_counter)
        from articast.core.tracking.kernels import TRACKER

        _warm_up(context, TRACKER)  # the appearance tracker's kernels only: half the compile

    def process(self, frame: Frame) -> TrackResult:
        if frame.image is None:
            raise InputError("this source has no images to track")
        return self.tracker.track(frame.image, frame.t)


class LiveProcessor:
    """An enrolled speaker (``articast enroll``) tracked with the face finder: started,
    verified and restarted from landmarks (:class:`articast.core.faces.live.LiveTracker`)."""

    def __init__(self, context: ProcessorContext) -> None:
        from articast.core.faces.finder import FaceFinder
        from articast.core.faces.live import LiveTracker, live_policy
        from articast.core.faces.scheme import mediapipe_scheme
        from articast.core.faces.two_readers import TwoReaderTracker, readers_problem

        sp = context.speaker
        rig = str(context.options.get("rig", sp.rig))
        readers = context.options.get("readers", 1)
        try:
            policy = live_policy(rig)
            problem = readers_problem(sp, readers)
            if problem:
                raise ValueError(problem)
        except ValueError as exc:
            raise InputError(f"session {context.session!r}: {exc}") from None
        self.tracker = LiveTracker(sp, FaceFinder.load(), mediapipe_scheme(sp.rig),
                                   tracking=policy, clock=time.perf_counter)
        # readers 2: the opt-in stream of two readers (core/faces/two_readers.py), ~3x the CPU
        self.step: LiveTracker | TwoReaderTracker = (
            TwoReaderTracker.of(self.tracker, tracking=policy) if readers == 2
            else self.tracker)
        _warm_up(context)
        # the session's console and its clients hear it (worker.py's "progress"), once
        say = context.progress or (lambda text: None)
        self.identity = IdentityWarning(sp, say)

    def process(self, frame: Frame) -> TrackResult:
        if frame.image is None:
            raise InputError("this source has no images to track")
        result = self.step.track(frame.image, frame.t)
        self.identity.see(self.tracker)
        return result


def fit_camera(camera: Any, width: int, height: int, what: str = "the frames") -> Any:
    """``camera`` for frames of ``width`` x ``height``: itself at its own size; scaled when the
    aspect ratio matches (the same camera at another resolution: a webcam's 640x480 and
    320x240 share their field of view); else one clear error saying what to do."""
    if not (width and height) or (width, height) == (camera.width, camera.height):
        return camera
    factor = width / camera.width
    if abs(camera.height * factor - height) > 1.0:
        ratio = camera.width / camera.height
        raise InputError(
            f"{what} are {width}x{height} but the camera is {camera.width}x{camera.height}, "
            f"another aspect ratio ({width / height:.3f} vs {ratio:.3f}): enrol (or calibrate) "
            f"on a clip of {width}x{height}, or resize this one to "
            f"{round(height * ratio)}x{height} or {width}x{round(width / ratio)}")
    return camera.scaled(factor)


def scaling_note(camera: Any, width: int, height: int) -> str:
    """One line saying that the camera was scaled to the frames, or ''."""
    if not (width and height) or (width, height) == (camera.width, camera.height):
        return ""
    return (f"camera scaled from {camera.width}x{camera.height} to {width}x{height} (the same "
            "camera at another resolution: same aspect ratio, focal length and centre scaled)")


def load_speaker(folder: str, source: SourceInfo) -> Any:
    """The speaker folder, its camera fitted to the source's frame size (same aspect ratio:
    scaled; another one: a clear error)."""
    from dataclasses import replace

    from articast.core.faces.speaker import Speaker

    sp = Speaker.load(folder)
    if source.width and source.height:
        sp = replace(sp, camera=fit_camera(sp.camera, source.width, source.height,
                                           "the source's frames"))
    return sp


def tracker_available() -> bool:
    try:
        importlib.import_module("articast.core.tracking.tracker")
    except ImportError:
        return False
    return True


def make_processor(name: str, context: ProcessorContext) -> tuple[str, FrameProcessor]:
    """Build the named processor; returns (the name actually used, processor)."""
    kind = context.source.kind
    if name == "auto":
        if kind == "replay-record":  # a recording (or a track file) carries its states: the
            # speaker, if given, is their model (an offline `articast track --speaker` file,
            # smoothed, served to avatars); there are no images to track
            name = "truth"
        elif context.speaker is not None:
            name = "live"
        elif tracker_available() and context.appearance is not None:
            name = "tracker"
        elif kind == "synthetic":
            name = "truth"
        else:
            raise InputError(
                f"session {context.session!r}: no tracker is available for a {kind} source "
                "(the tracker and an appearance model are needed); only sources with ground "
                "truth (synthetic, replay-record) can be served without one"
            )
    if name == "truth":
        return name, TruthProcessor(context)
    if name == "tracker":
        return name, TrackerProcessor(context)
    if name == "live":
        if context.speaker is None:
            raise InputError(f"session {context.session!r}: the live processor needs a "
                             "speaker folder (--speaker, from 'articast enroll')")
        return name, LiveProcessor(context)
    if ":" in name:
        mod, _, attr = name.partition(":")
        try:
            factory = getattr(importlib.import_module(mod), attr)
        except (ImportError, AttributeError) as exc:
            raise InputError(f"processor {name!r} cannot be imported: {exc}") from None
        return name, factory(context)
    raise InputError(f"unknown processor {name!r}: auto, truth, tracker, live or "
                     "module:callable")


def check_processor(name: str, source_kind: str, appearance_given: bool) -> None:
    """Fail before serving when ``name`` cannot work for this kind of source (CLI check)."""
    if name in ("auto", "tracker") and source_kind not in ("replay-record", "synthetic"):
        if not tracker_available():
            raise InputError(f"a {source_kind} source needs the tracker, which "
                             "is not available in this build")
        if not appearance_given:
            raise InputError(f"tracking a {source_kind} source needs --speaker DIR (from "
                             "'articast enroll'), or --appearance and --model")
    if name == "truth" and source_kind not in ("replay-record", "synthetic"):
        raise InputError(f"a {source_kind} source carries no ground truth for --processor truth")


def load_assets(spec_model: str, spec_appearance: str, spec_camera: str,
                from_source: SourceAssets, source: SourceInfo) -> tuple[Any, Any, Any]:
    """Model, appearance, camera: files given for the session win over the source's own."""
    model, appearance, camera = from_source.model, from_source.appearance, from_source.camera
    if spec_model:
        from articast.core.model.face import FaceModel

        model = FaceModel.load(spec_model)
    if spec_camera:
        from articast.core.model.camera import Camera

        camera = Camera.load(spec_camera)
    if spec_appearance:
        try:
            from articast.core.appearance.models import AppearanceModel
        except ImportError as exc:
            raise ArticastError(f"appearance models are not available: {exc}") from None
        appearance = AppearanceModel.load(spec_appearance, model)
    if camera is None and source.width and source.height:
        from articast.core.model.camera import Camera

        camera = Camera.default(source.width, source.height)
    elif camera is not None and source.width and source.height:
        camera = fit_camera(camera, source.width, source.height, "the source's frames")
    return model, appearance, camera
