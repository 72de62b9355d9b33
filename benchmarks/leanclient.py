"""A lean WebSocket subscriber for load generation: asyncio.Protocol + manual framing.

The benchmarks' clients share two cores with the server; the ``websockets`` library costs
tens of microseconds per message, so 500 of them at 30 Hz would measure the clients, not the
server. This one only parses frame headers and the binary frame header (~2 us per message), or
``json.loads`` for JSON frames.
It is a load generator, not a client library (see clients/python).
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import struct
import time
from typing import Any

from articast.client.protocol import frame_header


def _mask(payload: bytes) -> bytes:
    key = os.urandom(4)
    return key + bytes(b ^ key[i % 4] for i, b in enumerate(payload))


def client_frame(text: str) -> bytes:
    data = text.encode()
    n = len(data)
    head = struct.pack("!BB", 0x81, 0x80 | n) if n < 126 else struct.pack("!BBH", 0x81, 0xFE, n)
    return head + _mask(data)


def pong_frame(payload: bytes) -> bytes:
    """The client's (masked) answer to a server ping: a server closes a client that does not
    answer its keepalive pings (uvicorn: 20 s), which would count as a lost subscriber."""
    return struct.pack("!BB", 0x8A, 0x80 | len(payload)) + _mask(payload)


def answer_pings(transport: Any, buf: bytearray, opcode: int, start: int, end: int) -> None:
    """Send the pong for a ping frame (opcode 9) found in ``buf``."""
    if opcode == 9:
        transport.write(pong_frame(bytes(buf[start:end])))


def upgrade_request(path: str = "/ws") -> bytes:
    """The client's WebSocket upgrade request (HTTP/1.1, loopback)."""
    key = base64.b64encode(os.urandom(16)).decode()
    return (f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            "Sec-WebSocket-Version: 13\r\n\r\n").encode()


def server_frames(buf: bytearray) -> tuple[list[tuple[int, int, int]], int]:
    """The complete (unmasked) WebSocket frames at the start of ``buf``: a list of (opcode,
    payload start, payload end), and how many bytes they take (the caller drops them)."""
    out, off = [], 0
    while len(buf) - off >= 2:
        n, h = buf[off + 1] & 0x7F, 2
        if n == 126:
            if len(buf) - off < 4:
                break
            n, h = struct.unpack_from("!H", buf, off + 2)[0], 4
        elif n == 127:
            if len(buf) - off < 10:
                break
            n, h = struct.unpack_from("!Q", buf, off + 2)[0], 10
        if len(buf) - off < h + n:
            break
        out.append((buf[off] & 0x0F, off + h, off + h + n))
        off += h + n
    return out, off


class LeanSubscriber(asyncio.Protocol):
    def __init__(self, subscribe: dict[str, Any], clock: Any, stats: dict,
                 sample_every: int = 10) -> None:
        self.subscribe, self.clock, self.stats = subscribe, clock, stats
        self.sample_every = sample_every
        self.buf = bytearray()
        self.upgraded = False
        self.done = asyncio.get_running_loop().create_future()
        self.connected = asyncio.get_running_loop().create_future()
        self.got = 0
        self.first_seq: int | None = None
        self.last_seq = 0
        self.dropped0: int | None = None
        self.dropped = 0
        self.lat: list[float] = []

    def connection_made(self, transport: Any) -> None:
        self.transport = transport
        transport.write(upgrade_request())

    def data_received(self, data: bytes) -> None:
        self.buf += data
        if not self.upgraded:
            end = self.buf.find(b"\r\n\r\n")
            if end < 0:
                return
            del self.buf[: end + 4]
            self.upgraded = True
            self.transport.write(client_frame(json.dumps(self.subscribe)))
            self.connected.set_result(None)
        frames, used = server_frames(self.buf)
        for opcode, start, end in frames:
            answer_pings(self.transport, self.buf, opcode, start, end)
            if opcode == 2:
                self._frame(self.buf, start)
            elif opcode == 1:
                self._text(bytes(self.buf[start:end]))
            elif opcode == 8:
                self._finish()
        del self.buf[:used]

    def _frame(self, buf: bytearray, off: int) -> None:
        h = frame_header(buf, off)
        self._count(h.seq, h.t_tracked, h.dropped)

    def _text(self, data: bytes) -> None:
        if data.startswith(b'{"type":"frame"'):
            m = json.loads(data)
            self._count(m["seq"], m["t_tracked"], m["dropped"])

    def _count(self, seq: int, t_tracked: float, drop: int) -> None:
        now = time.time()
        t_start, t_stop = self.clock[0], self.clock[1]
        if now < t_start:
            return
        if now >= t_stop:
            self._finish()
            return
        self.got += 1
        if self.first_seq is None:
            self.first_seq, self.dropped0 = seq, drop
        self.last_seq = seq
        self.dropped = drop - (self.dropped0 or 0)
        if self.got % self.sample_every == 0:
            self.lat.append((now - t_tracked) * 1000)

    def _finish(self) -> None:
        if not self.done.done():
            self.done.set_result(None)
            self.transport.close()

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.connected.done():
            self.connected.set_exception(ConnectionError("connection lost before upgrade"))
        self._finish()
