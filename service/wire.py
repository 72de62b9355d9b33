"""From worker records to wire messages: session descriptions, hello, and frame encoding.

A tracked frame is encoded once per *view* (set of streams + encoding) and the bytes are
shared by every subscriber of that view; only the 4-byte ``dropped`` field differs per
subscriber and is spliced in (JSON: it is the last key; binary: fixed offset).
"""

from __future__ import annotations

import json
import struct
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from articast.client import protocol as P
from articast.service.clock import MONO_TO_EPOCH as _MONO_TO_EPOCH


def epoch(t_monotonic: float) -> float:
    """A ``time.monotonic()`` stamp on the epoch clock (one offset per process)."""
    return t_monotonic + _MONO_TO_EPOCH


def now() -> float:
    return time.monotonic() + _MONO_TO_EPOCH


# ----------------------------------------------------------------------------- descriptions
def describe(model: Any, camera: Any, param_names: tuple[str, ...]) -> dict[str, Any]:
    """What hello says about a session's model and camera (JSON-ready, no numpy)."""
    d: dict[str, Any] = {"param_names": list(param_names), "param_stats": None,
                         "geometry": None, "camera": camera.to_dict() if camera else None}
    if model is not None:
        s = model.stats
        d["param_names"] = list(model.param_names)
        d["param_stats"] = {k: [float(v) for v in getattr(s, k)]
                            for k in ("mean", "std", "min", "max")}
        d["geometry"] = {
            "name": model.name, "n_points": model.n_points,
            "mean": model.mean.astype(np.float32).ravel().tolist(),
            "basis": model.basis.astype(np.float32).ravel().tolist(),
            "triangles": model.triangles.ravel().tolist(),
            "point_names": list(model.point_names),
            "feature_points": dict(model.feature_points),
            "fapu_overrides": {k: float(v) for k, v in model.fapu_overrides.items()},
            "groups": {g: [int(i) for i in idx] for g, idx in model.groups.items()},
        }
    return d


def model_from_description(d: dict[str, Any]) -> Any:
    """Rebuild a FaceModel from :func:`describe` output (None without geometry)."""
    from articast.core.model.face import FaceModel, ParamStats

    g = d.get("geometry")
    if not g:
        return None
    n, names = int(g["n_points"]), tuple(d["param_names"])
    st = d.get("param_stats")
    return FaceModel(
        mean=np.asarray(g["mean"], np.float64).reshape(n, 3),
        basis=np.asarray(g["basis"], np.float64).reshape(len(names), n, 3),
        param_names=names,
        **({"stats": ParamStats(*(np.asarray(st[k]) for k in ("mean", "std", "min", "max")))}
           if st else {}),
        point_names=tuple(g.get("point_names") or ()),
        triangles=np.asarray(g.get("triangles") or [], np.int32).reshape(-1, 3),
        feature_points=g.get("feature_points") or {},
        groups={k: np.asarray(v, np.int64) for k, v in (g.get("groups") or {}).items()},
        fapu_overrides=g.get("fapu_overrides") or {},
        name=g.get("name", "speaker"),
    )


# ----------------------------------------------------------------------------- records
@dataclass(frozen=True)
class FrameRecord:
    """What a worker sends per tracked frame (picklable, no numpy; times on the epoch clock)."""

    seq: int
    frame: int
    t: float
    t_capture: float
    t_tracked: float
    alpha: tuple[float, ...]
    rotation: tuple[float, ...]
    translation: tuple[float, ...]
    quality: dict[str, Any]
    source_dropped: int = 0
    lips: dict[str, float] | None = None
    eyes: dict[str, Any] | None = None  # UpperFace.eyes_dict() (live tracking) or None
    brows: dict[str, Any] | None = None

    def to_json(self, param_names: list[str]) -> dict[str, Any]:
        """The recording line (a superset of ``TrackResult.to_dict``)."""
        return {"type": "frame", "seq": self.seq, "frame": self.frame, "t": self.t,
                "t_capture": self.t_capture, "t_tracked": self.t_tracked,
                "alpha": dict(zip(param_names, self.alpha, strict=True)),
                "pose": {"rotation": list(self.rotation), "translation": list(self.translation)},
                "lips": self.lips, "quality": self.quality,
                **({"eyes": self.eyes, "brows": self.brows} if self.eyes is not None else {})}


def relative_pose(rotation: Any, translation: Any, neutral_rotation: Any,
                  neutral_translation: Any) -> dict[str, list[float]]:
    """The head relative to the speaker's neutral pose, in the neutral head frame:
    rotation ``R_n^T R`` (axis-angle, rad) and translation ``R_n^T (t - t_n)`` (mm)."""
    from articast.core.model.camera import axis_angle, rotation_matrix

    rn = rotation_matrix(np.asarray(neutral_rotation, float))
    rel = rn.T @ rotation_matrix(np.asarray(rotation, float))
    shift = rn.T @ (np.asarray(translation, float) - np.asarray(neutral_translation, float))
    return {"rotation": [float(v) for v in axis_angle(rel)],
            "translation": [float(v) for v in shift]}


@dataclass(frozen=True)
class StatusEvent:
    session: str
    state: str
    detail: str
    t: float


@dataclass(frozen=True)
class ReadyEvent:
    session: str


View = tuple[tuple[str, ...], str]
"""(sorted streams, encoding)."""


@dataclass(eq=False)
class FrameEvent:
    """A frame as published on the hub: the record plus per-view encodings, made lazily."""

    session: str
    sid: int
    record: FrameRecord
    param_names: list[str]
    mesh_basis: Any = None  # (mean (3N,), basis (K, 3N)) float32 or None
    outputs: Any = None  # articast.service.outputs.Outputs (fap, arkit) or None
    neutral: Any = None  # the session's neutral head pose (rotation, translation) or None
    _cache: dict[View, str | bytes] = field(default_factory=dict)

    def encoded(self, view: View) -> str | bytes:
        out = self._cache.get(view)
        if out is None:
            out = self._cache[view] = self._encode(view)
        return out

    def for_subscriber(self, view: View, dropped: int) -> str | bytes:
        """The message for one subscriber: shared bytes, ``dropped`` spliced in if non-zero."""
        out = self.encoded(view)
        if not dropped:
            return out
        if isinstance(out, str):
            return f"{out[:-2]}{dropped}}}"
        o = P.DROPPED_OFFSET
        return b"".join((out[:o], struct.pack("<I", dropped & 0xFFFFFFFF), out[o + 4:]))

    def values(self, streams: tuple[str, ...]) -> dict[str, Any]:
        r = self.record
        v: dict[str, Any] = {}
        if "articulatory" in streams:
            v["articulatory"] = dict(zip(self.param_names, r.alpha, strict=True))
        if "pose" in streams:
            v["pose"] = {"rotation": list(r.rotation), "translation": list(r.translation)}
            if self.neutral is not None:
                v["pose"]["head"] = relative_pose(r.rotation, r.translation, *self.neutral)
        if "mesh" in streams and self.mesh_basis is not None:
            mean, basis = self.mesh_basis
            v["mesh"] = (mean + np.asarray(r.alpha, np.float32) @ basis).tolist()
        if self.outputs is not None and ("fap" in streams or "arkit" in streams):
            alpha = np.asarray(r.alpha)
            upper = _upper(r)
            if "fap" in streams:
                v["fap"] = self.outputs.fap(alpha, np.asarray(r.rotation),
                                            np.asarray(r.translation), bool(r.quality["ok"]),
                                            None if self.neutral is None else self.neutral[0])
                if upper is not None:
                    v["fap"] = self.outputs.with_upper_fap(v["fap"], upper)
            if "arkit" in streams:
                v["arkit"] = self.outputs.arkit_weights(alpha)
                if upper is not None:  # the eyes and brows seen, after the mouth's
                    from articast.core.outputs.upper import arkit_upper

                    v["arkit"].update(arkit_upper(upper))
        return v

    def _encode(self, view: View) -> str | bytes:
        streams, encoding = view
        r = self.record
        msg = {"type": "frame", "session": self.session, "seq": r.seq, "frame": r.frame,
               "t": r.t, "t_capture": r.t_capture, "t_tracked": r.t_tracked, "t_sent": now(),
               "values": self.values(streams), "lips": r.lips, "quality": r.quality,
               "dropped": 0}
        if r.eyes is not None:  # (JSON: before "dropped", its last key)
            msg = {**{k: v for k, v in msg.items() if k != "dropped"}, "eyes": r.eyes,
                   "brows": r.brows, "dropped": 0}
        if encoding == "binary":
            return P.encode_frame_binary(msg, self.sid, self.param_names)
        text = json.dumps(msg, separators=(",", ":"))
        assert text.endswith('"dropped":0}')
        return text


def _upper(r: FrameRecord) -> Any:
    """The record's eyes and brows as an UpperFace (None without them)."""
    if r.eyes is None:
        return None
    from articast.core.faces.upper import UpperFace

    return UpperFace.from_dicts(r.eyes, r.brows)


def hello(session: str, sid: int, desc: dict[str, Any], source: dict[str, Any] | None,
          sub: P.Subscribe, state: str, streams: list[Any], scan_url: str | None = None) -> str:
    """The hello message for one subscription (JSON text); ``scan_url`` names the server's
    head scan (``--scan``) for this session, so that a page asks for it only when there is one."""
    msg = P.Hello(
        session=session, sid=sid, streams=streams, encoding=sub.encoding, rate=sub.rate,
        param_names=desc["param_names"],
        param_stats=desc["param_stats"],
        camera=desc["camera"],
        geometry=desc["geometry"] if sub.geometry else None,
        fapu=desc.get("fapu"),
        dense_url=desc.get("dense_url"),
        preview_url=desc.get("preview_url"),
        delegate_url=desc.get("delegate_url"),
        scan_url=scan_url,
        source=P.SourceDescription(**source) if source else None,
        state=state,
    )
    return msg.model_dump_json(exclude_none=False)


def status_text(ev: StatusEvent, dropped: int = 0) -> str:
    return P.Status.model_validate({"session": ev.session, "state": ev.state, "detail": ev.detail,
                                    "t": ev.t, "dropped": dropped}).model_dump_json()


def error_text(code: str, reason: str, session: str | None = None) -> str:
    return P.Error.model_validate({"code": code, "reason": reason[:500],
                                   "session": session}).model_dump_json()
