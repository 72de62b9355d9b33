"""articast wire protocol, version 1 — shared by the server and the Python client.

Self-contained on purpose: it imports only the standard library and pydantic, so a client can
use it without numpy, OpenCV, FastAPI or the tracker.

Client -> server (JSON text messages)::

    {"type": "subscribe", "session": "alice", "streams": ["articulatory", "pose"],
     "rate": 30, "encoding": "json"}
    {"type": "unsubscribe", "session": "alice"}

Server -> client: ``hello`` (JSON, once per subscription, before any frame), then ``frame``
messages (JSON text, or binary messages when ``encoding`` is ``"binary"``), ``status`` messages
(session state changes) and ``error`` messages (a bad request: the connection stays open).

Times (``t_capture``, ``t_tracked``, ``t_sent``) are seconds since the Unix epoch on the
server's clock, derived from its monotonic clock so their differences are exact latencies.

The binary frame layout (little-endian) is described by :data:`BINARY_HEADER` and
:func:`encode_frame_binary`; docs/SERVICE.md has the table.
"""

from __future__ import annotations

import json
import math
import struct
from typing import Annotated, Any, Literal, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

PROTOCOL_VERSION = 1

Stream = Literal["articulatory", "pose", "fap", "mesh", "arkit"]
DEFAULT_STREAMS: tuple[Stream, ...] = ("articulatory", "pose")
STREAMS: tuple[str, ...] = ("articulatory", "pose", "fap", "mesh", "arkit")
"""Every stream name the protocol knows. ``fap`` and ``arkit`` are reserved: a session that
cannot produce them says so with an ``error`` (code ``unavailable_stream``)."""

Encoding = Literal["json", "binary"]

SessionName = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# ----------------------------------------------------------------------------- client -> server
class Subscribe(_Message):
    """Ask for a session's frames. Subscribing again to the same session replaces the options."""

    type: Literal["subscribe"] = "subscribe"
    session: SessionName
    streams: list[Stream] = Field(default_factory=lambda: list(DEFAULT_STREAMS), min_length=1,
                                 max_length=16)
    rate: float | None = Field(
        default=None, gt=0, le=1000, description="maximum frames per second (None: every frame)"
    )
    encoding: Encoding = "json"
    queue: int | None = Field(
        default=None, ge=1, le=1024,
        description="frames the server may queue for this subscriber before dropping the "
        "oldest (default and cap: the server's limits); a deep queue suits replays",
    )
    geometry: bool = Field(
        default=True, description="include the model geometry (mean, triangles, basis) in hello"
    )
    protocol: int = Field(default=PROTOCOL_VERSION, description="protocol the client speaks")


class Unsubscribe(_Message):
    type: Literal["unsubscribe"] = "unsubscribe"
    session: SessionName


ClientMessage = Annotated[Subscribe | Unsubscribe, Field(discriminator="type")]


# ----------------------------------------------------------------------------- server -> client
class ParamStats(_Message):
    mean: list[float]
    std: list[float]
    min: list[float]
    max: list[float]


class Geometry(_Message):
    """The articulatory model, flat for a browser: ``x(alpha) = mean + sum_k alpha_k basis_k``.

    mean : N*3 floats, mm, head frame (x speaker's left, y up, z forward), point-major.
    basis : K*N*3 floats, mm per unit alpha, parameter-major (basis[k*N*3 + i*3 + c]).
    triangles : T*3 point indices, counter-clockwise seen from the front (+z).
    """

    name: str
    n_points: int
    mean: list[float]
    basis: list[float]
    triangles: list[int]
    point_names: list[str] = Field(default_factory=list)
    feature_points: dict[str, int] = Field(default_factory=dict)
    fapu_overrides: dict[str, float] = Field(
        default_factory=dict, description="MPEG-4 units (mm) the points cannot measure, e.g. "
        "ES0 of a model without eyes")
    groups: dict[str, list[int]] = Field(
        default_factory=dict, description="named point groups (upper_lip, lip_inner, "
        "lower_teeth...): point indices")


class SourceDescription(_Message):
    uri: str
    kind: str
    live: bool
    width: int | None = None
    height: int | None = None
    fps: float | None = None
    detail: dict[str, Any] = Field(default_factory=dict)


class Hello(_Message):
    """Everything an avatar needs to render a session."""

    type: Literal["hello"] = "hello"
    protocol: int = PROTOCOL_VERSION
    session: str
    sid: int = Field(description="session number used in binary frames of this connection")
    streams: list[Stream]
    encoding: Encoding
    rate: float | None
    param_names: list[str]
    param_stats: ParamStats | None = None
    camera: dict[str, Any] | None = Field(
        default=None, description="articast.core.model.camera.Camera.to_dict")
    geometry: Geometry | None = None
    fapu: dict[str, float] | None = Field(default=None, description="FAPU in mm (MPEG-4)")
    dense_url: str | None = Field(
        default=None, description="HTTP path of the dense face mesh and its modes (JSON)")
    preview_url: str | None = Field(
        default=None, description="HTTP path of the newest tracking preview (JPEG: the tracked "
        "video with the fitted mesh, a few per second); only when the session opted in")
    delegate_url: str | None = Field(
        default=None, description="HTTP path of the speaker's own textured face (JSON: mesh, "
        "per-parameter modes, texture and its articulation modes); only for a speaker with "
        "a delegate, with the token, unless the server runs with --no-delegate")
    scan_url: str | None = Field(
        default=None, description="HTTP path of the server's bound head scan for this session "
        "(JSON; its texture at scan_url + '/texture'); only when the server runs with --scan")
    source: SourceDescription | None = None
    state: str = "running"


class Quality(_Message):
    ok: bool = True
    reason: str = ""
    residual: float = 0.0
    evals: int = 0
    iterations: int = 0
    ms: float = 0.0


class RelativePose(_Message):
    rotation: list[float] = Field(min_length=3, max_length=3,
                                  description="axis-angle, rad: R_n^T R")
    translation: list[float] = Field(min_length=3, max_length=3,
                                     description="mm, neutral head frame: R_n^T (t - t_n)")


class PoseValue(_Message):
    rotation: list[float] = Field(min_length=3, max_length=3, description="axis-angle, rad")
    translation: list[float] = Field(min_length=3, max_length=3, description="mm, head->camera")
    head: RelativePose | None = Field(
        default=None, description="the head relative to the speaker's neutral pose (first good "
        "frame, or the first after a re-centre); JSON encoding only")


class FapValue(_Message):
    """Reserved for the FAP stream: FAP number (as a string key) -> integer value, and mask."""

    values: dict[str, int] = Field(default_factory=dict)
    mask: list[int] = Field(default_factory=list, description="FAP numbers present")


class FrameValues(_Message):
    articulatory: dict[str, float] | None = None
    pose: PoseValue | None = None
    fap: FapValue | None = None
    mesh: list[float] | None = Field(default=None, description="N*3 floats, mm, head frame")
    arkit: dict[str, float] | None = None


class Lips(_Message):
    """Lip measures on the fitted model geometry (mm): inner midpoints, inner corners."""

    aperture_mm: float
    width_mm: float


class Eyes(_Message):
    """The eyes of a frame (live tracking of an enrolled speaker). Values are null when
    ``ok`` is false: the eyes were not seen (``reason``), not open."""

    ok: bool
    reason: str = ""
    closure_left: float | None = Field(default=None, description="0 open .. 1 closed")
    closure_right: float | None = None
    gaze_yaw_deg: float | None = Field(default=None, description="to the speaker's left +")
    gaze_pitch_deg: float | None = Field(default=None, description="up +")
    wide_left: float | None = Field(default=None, description="open beyond the speaker's usual "
                                    "open eye, in units of its open-to-closed travel, 0..1")
    wide_right: float | None = None
    lower_lid_left: float | None = Field(default=None, description="the lower lid's rise (a "
                                         "squint), a fraction of the open eye, up +")
    lower_lid_right: float | None = None


class Brows(_Message):
    """The brows of a frame, mm from the speaker's neutral (raise +); null when not ok."""

    ok: bool
    reason: str = ""
    raise_left_mm: float | None = None
    raise_right_mm: float | None = None
    raise_inner_left_mm: float | None = None
    raise_outer_left_mm: float | None = None
    raise_inner_right_mm: float | None = None
    raise_outer_right_mm: float | None = None
    lowering_mm: float | None = Field(default=None, description="inner brows lowered, mm")
    squeeze_left_mm: float | None = Field(default=None, description="inner brow towards the "
                                          "face's midline, mm (a frown)")
    squeeze_right_mm: float | None = None


class Frame(_Message):
    type: Literal["frame"] = "frame"
    session: str
    seq: int = Field(description="per-session sequence number of tracked frames (no gaps)")
    frame: int = Field(description="source frame index (gaps: the tracker skipped frames)")
    t: float = Field(description="media time of the frame in its source, s")
    t_capture: float
    t_tracked: float
    t_sent: float
    values: FrameValues
    lips: Lips | None = Field(
        default=None, description="lip aperture and width (mm) on every frame; null when the "
        "session's model has no inner-lip points")
    quality: Quality
    eyes: Eyes | None = Field(default=None, description="eyelids and gaze, with their own ok "
                              "(eyes can be lost while the lips are fine)")
    brows: Brows | None = Field(default=None, description="brow raise and lowering, own ok")
    dropped: int = Field(description="frames this subscriber lost because it read too slowly")


SessionState = Literal[
    "starting", "running", "unavailable", "stalled", "restarting", "ended", "failed", "stopped"
]


class Status(_Message):
    type: Literal["status"] = "status"
    session: str
    state: SessionState
    detail: str = ""
    t: float = 0.0
    dropped: int = Field(default=0, description="frames this subscriber lost so far")


ErrorCode = Literal[
    "bad_json", "bad_message", "too_large", "binary_not_accepted", "unknown_session",
    "unknown_stream", "unavailable_stream", "unsupported_protocol", "too_many_subscriptions",
    "not_subscribed", "rate_limited", "internal",
]


class Error(_Message):
    type: Literal["error"] = "error"
    code: ErrorCode
    reason: str
    session: str | None = None


ServerMessage = Annotated[Hello | Frame | Status | Error, Field(discriminator="type")]

_client_adapter: TypeAdapter[Any] = TypeAdapter(ClientMessage)
_server_adapter: TypeAdapter[Any] = TypeAdapter(ServerMessage)


class ProtocolError(ValueError):
    """A message that does not follow the protocol; ``code`` is an :data:`ErrorCode`."""

    def __init__(self, code: str, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


MAX_CONTAINERS = 64
"""Arrays and objects one client message may hold (a subscribe needs two): deeper
nesting is refused before parsing, with an error, instead of exhausting the stack."""


def parse_client_message(text: str | bytes) -> Subscribe | Unsubscribe:
    """Validate one client message; raises :class:`ProtocolError` with a readable reason."""
    opened = text.count("[") + text.count("{") if isinstance(text, str) else \
        text.count(b"[") + text.count(b"{")
    if opened > MAX_CONTAINERS:
        raise ProtocolError("bad_message", f"a client message has at most {MAX_CONTAINERS} "
                            "arrays and objects")
    try:
        doc = json.loads(text)
    except (ValueError, UnicodeDecodeError, RecursionError) as exc:
        raise ProtocolError("bad_json", f"not valid JSON: {exc}") from None
    if not isinstance(doc, dict) or "type" not in doc:
        raise ProtocolError("bad_message", "a message is a JSON object with a 'type' field")
    if doc.get("type") == "subscribe" and isinstance(doc.get("streams"), list):
        unknown = [s for s in doc["streams"] if s not in STREAMS]
        if unknown:
            raise ProtocolError(
                "unknown_stream", f"unknown stream(s) {unknown}; known: {list(STREAMS)}"
            )
    try:
        msg = _client_adapter.validate_python(doc)
    except ValidationError as exc:
        raise ProtocolError("bad_message", _short_reason(exc)) from None
    if isinstance(msg, Subscribe) and msg.protocol != PROTOCOL_VERSION:
        raise ProtocolError(
            "unsupported_protocol",
            f"this server speaks protocol {PROTOCOL_VERSION}, not {msg.protocol}",
        )
    if isinstance(msg, Subscribe) and len(set(msg.streams)) != len(msg.streams):
        # ["mesh"] * k must not be k distinct views, each encoded separately
        msg = msg.model_copy(update={"streams": list(dict.fromkeys(msg.streams))})
    return msg


def _short_reason(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors()[:3]:
        loc = ".".join(str(x) for x in err["loc"]) or "message"
        parts.append(f"{loc}: {err['msg']}")
    return "; ".join(parts)


# ----------------------------------------------------------------------------- binary frames
BINARY_MAGIC = b"AC"
BINARY_HEADER = struct.Struct("<2sBBHHIIddddffIBxxxffII")


class FrameHeader(NamedTuple):
    """The fields of :data:`BINARY_HEADER`, by name (unpack with :func:`frame_header`)."""

    magic: bytes
    version: int
    kind: int
    streams: int
    sid: int
    seq: int
    frame: int
    t: float
    t_capture: float
    t_tracked: float
    t_sent: float
    lip_aperture_mm: float
    lip_width_mm: float
    dropped: int
    ok: int
    residual: float
    ms: float
    evals: int
    iterations: int


def frame_header(data: bytes | bytearray | memoryview, offset: int = 0) -> FrameHeader:
    """The header of a binary frame at ``offset``, fields by name (no index to get wrong)."""
    return FrameHeader._make(BINARY_HEADER.unpack_from(data, offset))
BINARY_LAYOUT = """Header of a binary frame, 80 bytes, little-endian:

magic "AC", version u8, kind u8 (1 = frame), streams u16 (bit i = STREAMS[i]), sid u16,
seq u32, frame u32, t f64, t_capture f64, t_tracked f64, t_sent f64, lip aperture f32 and
lip width f32 (mm; NaN when the frame has no lip measures),
dropped u32, ok u8, 3 pad bytes, residual f32, ms f32, evals u32, iterations u32.

Then, for each stream bit set, in STREAMS order:
articulatory: K float32 (K and order from hello.param_names);
pose: 6 float32 (rotation rad, translation mm);
fap: u16 count n, then n x (u16 number, i32 value);
mesh: u32 count m, then m float32 (m = N*3);
arkit: u16 count n, then n float32 (names: reserved, announced in hello).

Then, when bit UPPER_BIT (15) of streams is set, the eyes and brows (live tracking of an
enrolled speaker; the JSON encoding's ``eyes`` and ``brows`` blocks): u8 flags (bit 0 eyes
ok, bit 1 brows ok), u8 n + n bytes the eyes' reason (UTF-8), u8 m + m bytes the brows'
reason, then float32 x EYES_FIELDS and float32 x BROWS_FIELDS (NaN: null).
"""
UPPER_BIT = 1 << 15
EYES_FIELDS = ("closure_left", "closure_right", "gaze_yaw_deg", "gaze_pitch_deg", "wide_left",
               "wide_right", "lower_lid_left", "lower_lid_right")
BROWS_FIELDS = ("raise_left_mm", "raise_right_mm", "raise_inner_left_mm",
                "raise_outer_left_mm", "raise_inner_right_mm", "raise_outer_right_mm",
                "lowering_mm", "squeeze_left_mm", "squeeze_right_mm")


def _reason_bytes(text: str) -> bytes:
    """A reason as at most 255 bytes of UTF-8 (cut on a character boundary)."""
    b = text.encode("utf-8")[:255].decode("utf-8", "ignore").encode("utf-8")
    return bytes([len(b)]) + b


def _nan(v: Any) -> float:
    return math.nan if v is None else float(v)


def _encode_upper(eyes: dict[str, Any], brows: dict[str, Any]) -> bytes:
    flags = (1 if eyes.get("ok") else 0) | (2 if brows.get("ok") else 0)
    return b"".join((bytes([flags]), _reason_bytes(str(eyes.get("reason", ""))),
                     _reason_bytes(str(brows.get("reason", ""))),
                     struct.pack(f"<{len(EYES_FIELDS)}f", *(_nan(eyes.get(k))
                                                            for k in EYES_FIELDS)),
                     struct.pack(f"<{len(BROWS_FIELDS)}f", *(_nan(brows.get(k))
                                                             for k in BROWS_FIELDS))))


def _decode_upper(data: bytes, off: int) -> tuple[dict[str, Any], dict[str, Any]]:
    flags = data[off]
    off += 1
    reasons = []
    for _ in range(2):
        n = data[off]
        reasons.append(data[off + 1:off + 1 + n].decode("utf-8", "replace"))
        off += 1 + n
    ev = struct.unpack_from(f"<{len(EYES_FIELDS)}f", data, off)
    bv = struct.unpack_from(f"<{len(BROWS_FIELDS)}f", data, off + 4 * len(EYES_FIELDS))

    def block(ok: bool, reason: str, names: tuple[str, ...], vals: tuple[float, ...]
              ) -> dict[str, Any]:
        return {"ok": ok, "reason": reason,
                **{k: None if math.isnan(v) else v for k, v in zip(names, vals, strict=True)}}

    return (block(bool(flags & 1), reasons[0], EYES_FIELDS, ev),
            block(bool(flags & 2), reasons[1], BROWS_FIELDS, bv))
KIND_FRAME = 1
DROPPED_OFFSET = 2 + 1 + 1 + 2 + 2 + 4 + 4 + 8 * 5


def stream_bits(streams: list[str] | tuple[str, ...]) -> int:
    return sum(1 << STREAMS.index(s) for s in set(streams))


def _lip_pair(lips: dict[str, float] | None) -> tuple[float, float]:
    if not lips:
        return math.nan, math.nan
    return float(lips["aperture_mm"]), float(lips["width_mm"])


def encode_frame_binary(msg: dict[str, Any], sid: int, param_names: list[str]) -> bytes:
    """Binary encoding of a frame given as the dict of :class:`Frame` (values possibly None).

    The ``dropped`` field sits at :data:`DROPPED_OFFSET` so a server can patch it per
    subscriber without re-encoding.
    """
    values = msg["values"]
    present = [s for s in STREAMS if values.get(s) is not None]
    upper = msg.get("eyes") is not None and msg.get("brows") is not None
    q = msg["quality"]
    parts = [
        BINARY_HEADER.pack(
            BINARY_MAGIC, PROTOCOL_VERSION, KIND_FRAME,
            stream_bits(present) | (UPPER_BIT if upper else 0), sid,
            msg["seq"] & 0xFFFFFFFF, msg["frame"] & 0xFFFFFFFF, msg["t"], msg["t_capture"],
            msg["t_tracked"], msg["t_sent"], *_lip_pair(msg.get("lips")), msg["dropped"],
            int(bool(q["ok"])),
            q["residual"], q["ms"], q["evals"], q["iterations"],
        )
    ]
    if values.get("articulatory") is not None:
        a = values["articulatory"]
        parts.append(struct.pack(f"<{len(param_names)}f", *(a.get(n, 0.0) for n in param_names)))
    if values.get("pose") is not None:
        p = values["pose"]
        parts.append(struct.pack("<6f", *p["rotation"], *p["translation"]))
    if values.get("fap") is not None:
        items = sorted((int(k), int(v)) for k, v in values["fap"]["values"].items())
        parts.append(struct.pack("<H", len(items)))
        parts.extend(struct.pack("<Hi", k, v) for k, v in items)
    if values.get("mesh") is not None:
        m = values["mesh"]
        parts.append(struct.pack(f"<I{len(m)}f", len(m), *m))
    if values.get("arkit") is not None:
        a = list(values["arkit"].values())
        parts.append(struct.pack(f"<H{len(a)}f", len(a), *a))
    if upper:
        parts.append(_encode_upper(msg["eyes"], msg["brows"]))
    return b"".join(parts)


def decode_frame_binary(data: bytes, session_of_sid: dict[int, str],
                        param_names: dict[int, list[str]]) -> Frame:
    """Inverse of :func:`encode_frame_binary` (``param_names`` per sid, from hello)."""
    if len(data) < BINARY_HEADER.size or data[:2] != BINARY_MAGIC:
        raise ProtocolError("bad_message", "not an articast binary frame")
    (_, version, kind, bits, sid, seq, frame, t, t_capture, t_tracked, t_sent, aperture, width,
     dropped, ok, residual, ms, evals, iterations) = frame_header(data)
    if version != PROTOCOL_VERSION or kind != KIND_FRAME:
        raise ProtocolError("unsupported_protocol", f"binary version {version} kind {kind}")
    names = param_names.get(sid, [])
    off = BINARY_HEADER.size
    values: dict[str, Any] = {}
    try:
        if bits & 1:
            a = struct.unpack_from(f"<{len(names)}f", data, off)
            off += 4 * len(names)
            values["articulatory"] = dict(zip(names, a, strict=True))
        if bits & 2:
            p = struct.unpack_from("<6f", data, off)
            off += 24
            values["pose"] = {"rotation": list(p[:3]), "translation": list(p[3:])}
        if bits & 4:
            (n,) = struct.unpack_from("<H", data, off)
            off += 2
            items = [struct.unpack_from("<Hi", data, off + 6 * i) for i in range(n)]
            off += 6 * n
            values["fap"] = {"values": {str(k): v for k, v in items}, "mask": [k for k, _ in items]}
        if bits & 8:
            (m,) = struct.unpack_from("<I", data, off)
            values["mesh"] = list(struct.unpack_from(f"<{m}f", data, off + 4))
            off += 4 + 4 * m
        if bits & 16:
            (n,) = struct.unpack_from("<H", data, off)
            # (keyed by position: the binary frame does not carry the names; str keys as
            # FrameValues wants them, which int keys failed)
            values["arkit"] = {str(i): v for i, v in enumerate(
                struct.unpack_from(f"<{n}f", data, off + 2))}
            off += 2 + 4 * n
        eyes = brows = None
        if bits & UPPER_BIT:
            eyes, brows = _decode_upper(data, off)
    except (struct.error, IndexError) as exc:
        raise ProtocolError("bad_message", f"truncated binary frame: {exc}") from None
    return Frame(
        session=session_of_sid.get(sid, str(sid)), seq=seq, frame=frame, t=t,
        t_capture=t_capture, t_tracked=t_tracked, t_sent=t_sent,
        values=FrameValues.model_validate(values),
        lips=(Lips(aperture_mm=aperture, width_mm=width)
              if math.isfinite(aperture) and math.isfinite(width) else None),
        quality=Quality(ok=bool(ok), residual=residual, ms=ms, evals=evals,
                        iterations=iterations),
        eyes=None if eyes is None else Eyes.model_validate(eyes),
        brows=None if brows is None else Brows.model_validate(brows),
        dropped=dropped,
    )


def parse_server_message(data: str | bytes, sids: dict[int, str] | None = None,
                         param_names: dict[int, list[str]] | None = None) -> Any:
    """Decode one server message: text -> a validated model; bytes -> :class:`Frame`."""
    if isinstance(data, bytes | bytearray) and data[:2] == BINARY_MAGIC:
        return decode_frame_binary(bytes(data), sids or {}, param_names or {})
    return _server_adapter.validate_json(data)


def protocol_schema() -> dict[str, Any]:
    """The JSON Schema of both directions (served at ``/api/protocol``)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"articast protocol v{PROTOCOL_VERSION}",
        "protocol": PROTOCOL_VERSION,
        "streams": list(STREAMS),
        "client_to_server": _client_adapter.json_schema(),
        "server_to_client": _server_adapter.json_schema(),
        "binary_frame": {
            "byte_order": "little-endian",
            "header_struct": BINARY_HEADER.format,
            "header_size": BINARY_HEADER.size,
            "dropped_offset": DROPPED_OFFSET,
            "layout": BINARY_LAYOUT,
        },
    }
