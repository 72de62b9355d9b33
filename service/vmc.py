"""Send the tracked face to VMC-protocol receivers (VSeeFace, VNyan, Warudo, EVMC4U in Unity).

OSC bundles (UDP) per frame, laid out as the common senders lay theirs out and as a reference
receiver (EVMC4U's ``ExternalReceiver``) parses them, every argument typed as the receiver
checks it (``i`` int32, ``f`` float32, ``s`` string). A frame is split into bundles of at most
:data:`MAX_DATAGRAM` bytes (two for the synthetic speaker: ~1.7 kB in all), each starting with
``/VMC/Ext/OK`` and ``/VMC/Ext/T``; in order:

===================================================  =========================================
``/VMC/Ext/OK 1``                                    availability (1: a model is loaded and
                                                     tracking)
``/VMC/Ext/T t``                                     sender time, s since the sender started
``/VMC/Ext/Root/Pos "root" 0 0 0 0 0 0 1``           the avatar's root stays where it is
``/VMC/Ext/Bone/Pos "Head" px py pz qx qy qz qw``    the head, relative to the speaker's
                                                     neutral pose
``/VMC/Ext/Bone/Pos "LeftEye" 0 0 0 qx qy qz qw``    the eyes' gaze relative to the head (and
``/VMC/Ext/Bone/Pos "RightEye" ...``                 ``RightEye``), when the eyes are seen
``/VMC/Ext/Blend/Val name value`` ...                the ARKit eye and brow shapes and the VRM
                                                     presets ``Blink_L Blink_R`` (when seen)
``/VMC/Ext/Blend/Val name value`` ...                ARKit mouth/jaw shapes, then the VRM
                                                     vowels ``A I U E O``
``/VMC/Ext/Blend/Apply``                             the receiver applies the values
===================================================  =========================================

**Blend names.** ``names="perfect-sync"`` (default, ``serve --vmc-names perfect-sync``): the
ARKit names in UpperCamel (``JawOpen``, ``MouthSmileLeft``), the names of the 52 clips of a
"perfect sync" VRM avatar (the convention VSeeFace and others follow); ``names="arkit"``:
Apple's lowerCamel (``jawOpen``). Only the shapes the model drives are sent
(:attr:`~articast.core.outputs.arkit.ArkitMapper.populated`), so other trackers' eye or brow
values on the same receiver are not overwritten. The vowel presets ``A I U E O`` (what an
ordinary VRM avatar has) come from :mod:`articast.core.outputs.vowels`; VRM 1.0 receivers
map them to ``aa ih ou ee oh`` themselves.

**Head pose.** Our pose maps the head frame (x = the speaker's left, y up, z forward;
right-handed) to the OpenCV camera. The head's rotation relative to the speaker's neutral
pose, in the neutral head frame, is ``R_rel = R_n^T R``; the neutral is the session's (the
first good frame, or the first after ``POST /api/sessions/{name}/recentre``), so a speaker at
rest reads 0 whatever the camera's angle. Unity is left-handed with a character looking along
+z, +y up and +x to the character's right, so Unity's axes are ours with x mirrored,
``S = diag(-1, 1, 1)``, and the rotation becomes ``M = S R_rel S`` (a proper rotation), sent
as a unit quaternion (x, y, z, w). A nod down is then a positive rotation about Unity's +x and
a turn to the speaker's left a negative rotation about Unity's +y, as Unity expects. The
position is the head origin's displacement from the neutral, in the same axes, in metres;
many receivers use only the rotation. Mirroring the avatar (a "selfie view") is left to the
receiver.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder
from pythonosc.udp_client import SimpleUDPClient

from articast.core.errors import InputError
from articast.core.model.camera import Pose, rotation_matrix
from articast.core.model.face import FaceModel
from articast.core.outputs.arkit import ArkitMapper
from articast.core.outputs.vowels import VowelMapper
from articast.core.tracking.result import TrackResult

MAX_DATAGRAM = 1400
"""Largest bundle sent, bytes: under a 1500-byte Ethernet MTU with IP and UDP headers."""
_BUNDLE_HEADER = 16  # "#bundle\0" and the time tag

DEFAULT_PORT = 39539
"""The VMC protocol's default receiving (Marionette) port."""

UNITY_FROM_HEAD = np.diag([-1.0, 1.0, 1.0])
"""Head-frame axes -> Unity axes (mirror x: the speaker's left is the character's -x)."""


def quaternion_xyzw(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion (4,) = (x, y, z, w), w >= 0, of a (3, 3) rotation matrix."""
    m = np.asarray(rot, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s,
                      (m[1, 0] - m[0, 1]) / s, s / 4])
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.array([0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s])
        q[i], q[j], q[k] = s / 4, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def head_bone(
    rotation: np.ndarray,
    translation: np.ndarray,
    reference_rotation: np.ndarray,
    reference_translation: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Unity position (3,) m and quaternion (4,) xyzw of the head, from a pose (rad, mm)."""
    r_ref = rotation_matrix(reference_rotation)
    rel = r_ref.T @ rotation_matrix(rotation)
    unity = UNITY_FROM_HEAD @ rel @ UNITY_FROM_HEAD
    offset = UNITY_FROM_HEAD @ (r_ref.T @ (np.asarray(translation) - reference_translation))
    return offset / 1000.0, quaternion_xyzw(unity)


def upper_messages(upper: Any, names: str = "perfect-sync") -> list[OscMessage]:
    """The eyes and brows of a frame (:mod:`articast.core.outputs.upper`), what was seen only:
    the eye bones ``LeftEye`` / ``RightEye`` (the gaze, in the head bone's Unity axes), the
    ARKit eye and brow shapes and the VRM presets ``Blink_L`` / ``Blink_R``."""
    from articast.core.outputs.upper import arkit_upper, eye_rotation

    out = []
    rot = eye_rotation(upper)
    if rot is not None:
        q = quaternion_xyzw(UNITY_FROM_HEAD @ rot @ UNITY_FROM_HEAD)
        for bone in ("LeftEye", "RightEye"):
            out.append(_message("/VMC/Ext/Bone/Pos", bone, 0.0, 0.0, 0.0,
                                *(float(v) for v in q)))
    weights = arkit_upper(upper)
    for name, value in weights.items():
        out.append(_message("/VMC/Ext/Blend/Val", blend_name(name, names), float(value)))
    if "eyeBlinkLeft" in weights:
        out.append(_message("/VMC/Ext/Blend/Val", "Blink_L", float(weights["eyeBlinkLeft"])))
        out.append(_message("/VMC/Ext/Blend/Val", "Blink_R", float(weights["eyeBlinkRight"])))
    return out


def _message(address: str, *args: str | int | float) -> OscMessage:
    b = OscMessageBuilder(address=address)
    for a in args:
        b.add_arg(a)
    return b.build()


NAME_STYLES = ("perfect-sync", "arkit")


def blend_name(arkit_name: str, style: str) -> str:
    """``jawOpen`` -> ``JawOpen`` (perfect-sync) or ``jawOpen`` (arkit)."""
    return arkit_name[0].upper() + arkit_name[1:] if style == "perfect-sync" else arkit_name


class VmcSender:
    """Send one VMC bundle per tracked frame to ``host:port`` over UDP.

    names : ``"perfect-sync"`` (UpperCamel ARKit names, default) or ``"arkit"`` (lowerCamel).
    populated_only : send only the blendshapes the model drives (default).
    vowels : also send the VRM vowel presets ``A I U E O`` (default).
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        *,
        names: str = "perfect-sync",
        populated_only: bool = True,
        vowels: bool = True,
    ) -> None:
        if not 0 < int(port) < 65536:
            raise InputError(f"VMC port must be in 1..65535, got {port}")
        if names not in NAME_STYLES:
            raise InputError(f"VMC names must be one of {', '.join(NAME_STYLES)}, got {names!r}")
        self.address = (host, int(port))
        self.names = names
        self.populated_only = populated_only
        self.vowels = vowels
        self._client = SimpleUDPClient(host, int(port))
        self._mappers: tuple[FaceModel, ArkitMapper, VowelMapper | None] | None = None
        self._t0 = time.monotonic()
        self.frames_sent = 0
        self.frames_dropped = 0
        self.last_error = ""

    def _mappers_for(self, model: FaceModel) -> tuple[ArkitMapper, VowelMapper | None]:
        if self._mappers is None or self._mappers[0] is not model:
            try:
                vowels = VowelMapper(model) if self.vowels else None
            except InputError:  # a model without the lip feature points: no vowels
                vowels = None
            self._mappers = (model, ArkitMapper(model), vowels)
        return self._mappers[1], self._mappers[2]

    def bundles(self, result: TrackResult, model: FaceModel, *, neutral: Pose | None = None,
                t: float = 0.0) -> list[OscBundle]:
        """The OSC bundles of one frame (no I/O): each fits one Ethernet frame
        (:data:`MAX_DATAGRAM` bytes, so no IP fragment can be lost on a LAN) and starts with
        ``/VMC/Ext/OK`` and ``/VMC/Ext/T``; the root and the head come first, the blend
        values next, ``/VMC/Ext/Blend/Apply`` last (receivers keep values until Apply).

        neutral : the speaker's neutral head pose (None: this frame's, i.e. no rotation).
        t : sender time, s (``/VMC/Ext/T``).
        """
        ref = neutral if neutral is not None else result.pose
        pos, quat = head_bone(result.pose.rotation, result.pose.translation,
                              np.asarray(ref.rotation, float), np.asarray(ref.translation, float))
        messages = [
            _message("/VMC/Ext/Root/Pos", "root", 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
            _message("/VMC/Ext/Bone/Pos", "Head", *(float(v) for v in pos),
                     *(float(v) for v in quat)),
        ]
        arkit, vowels = self._mappers_for(model)
        weights = arkit.weights_dict(result.alpha, populated_only=self.populated_only)
        for name, value in weights.items():
            messages.append(_message("/VMC/Ext/Blend/Val", blend_name(name, self.names),
                                     float(value)))
        if vowels is not None:
            for name, value in vowels.weights_dict(result.alpha).items():
                messages.append(_message("/VMC/Ext/Blend/Val", name, float(value)))
        messages[2:2] = upper_messages(result.upper, self.names)
        messages.append(_message("/VMC/Ext/Blend/Apply"))
        head = [_message("/VMC/Ext/OK", 1), _message("/VMC/Ext/T", float(t))]
        groups: list[list[Any]] = [[]]
        size = _BUNDLE_HEADER + sum(4 + m.size for m in head)
        for m in messages:
            if groups[-1] and size + 4 + m.size > MAX_DATAGRAM:
                groups.append([])
                size = _BUNDLE_HEADER + sum(4 + h.size for h in head)
            groups[-1].append(m)
            size += 4 + m.size
        out = []
        for group in groups:
            builder = OscBundleBuilder(IMMEDIATELY)
            for m in (*head, *group):
                builder.add_content(m)
            out.append(builder.build())
        return out

    def send(self, result: TrackResult, model: FaceModel, *,
             neutral: Pose | None = None) -> bool:
        """Send the frame's bundles; never blocks. Returns False (and counts the frame in
        :attr:`frames_dropped`, keeping :attr:`last_error`) if the OS refused a datagram,
        e.g. a full send buffer or an unreachable network: a live stream goes on."""
        packets = self.bundles(result, model, neutral=neutral, t=time.monotonic() - self._t0)
        try:
            for packet in packets:
                self._client.send(packet)
        except OSError as exc:  # includes BlockingIOError on the non-blocking socket
            self.frames_dropped += 1
            self.last_error = f"{exc.__class__.__name__}: {exc}"
            return False
        self.frames_sent += 1
        return True

    def close(self) -> None:
        """Close the UDP socket."""
        sock = getattr(self._client, "_sock", None)
        if sock is not None:
            sock.close()

    def __enter__(self) -> VmcSender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def parse_host_port(text: str, default_port: int = DEFAULT_PORT) -> tuple[str, int]:
    """``"HOST:PORT"`` or ``"HOST"`` -> (host, port), for the service's ``--vmc`` option."""
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, default_port
    try:
        p = int(port)
    except ValueError:
        raise InputError(f"--vmc expects HOST:PORT, got {text!r}") from None
    if not host or not 0 < p < 65536:
        raise InputError(f"--vmc expects HOST:PORT with a port in 1..65535, got {text!r}")
    return host, p
