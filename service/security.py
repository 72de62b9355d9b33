"""Who may use the service, and what a client may make it open.

One :class:`AccessPolicy` (frozen) holds every rule; the app asks it four questions:

* :meth:`AccessPolicy.token_ok` — the shared secret (``ARTICAST_TOKEN`` or ``--token-file``),
  sent as ``Authorization: Bearer TOKEN`` or, for browsers, ``?token=TOKEN``; compared in
  constant time (``hmac.compare_digest``). With no token configured every request passes
  (the server then listens on loopback only unless ``--insecure-no-token``).
* :meth:`AccessPolicy.host_ok` — the ``Host`` header names this server (DNS rebinding: a
  page on ``evil.example`` that resolves to 127.0.0.1 sends ``Host: evil.example``).
* :meth:`AccessPolicy.origin_ok` — a browser's ``Origin`` is this server's own origin, a
  loopback origin, or one of ``--allowed-origin``; no Origin (a non-browser client) passes.
* :meth:`AccessPolicy.check_session_files` — a session added over HTTP may open only files
  under ``--media-root`` folders and devices named by ``--allow-device``; the answer for a
  path outside the roots is the same whether it exists or not (no existence oracle).

The token is never logged and never part of an error message or an API answer.
"""

from __future__ import annotations

import contextlib
import hmac
import ipaddress
import logging
import os
import re
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from articast.core.errors import InputError

LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
FILE_KINDS = ("file", "images", "replay-record")


class Forbidden(Exception):
    """A request the policy refuses: ``status`` (401/403) and a reason safe to show."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status, self.reason = status, reason


def is_loopback(host: str) -> bool:
    host = host.strip("[]")
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def is_wildcard(host: str) -> bool:
    return host.strip("[]") in ("0.0.0.0", "::", "")


_HOST_RE = re.compile(r"(?:\[(?P<v6>[0-9a-f:.]+(?:%[0-9a-z._~-]+)?)\]|(?P<name>[0-9a-z._-]+))"
                      r"(?::(?P<port>[0-9]{1,5}))?")


def _host_name(value: str) -> str:
    """``example.com:8765`` / ``[::1]:80`` -> ``example.com`` / ``::1`` (lower case); ""
    for anything that is not a host name or address with an optional port (issue 39:
    ``127.0.0.1:1@evil.example`` was read as 127.0.0.1; userinfo, paths, spaces, a second
    port, an unbracketed IPv6 address are not a ``Host``)."""
    m = _HOST_RE.fullmatch(value.strip().lower())
    if m is None:
        return ""
    return m.group("v6") or m.group("name") or ""


def load_token(env: dict[str, str] | os._Environ[str] | None = None,
               token_file: str = "") -> str:
    """The secret from ``--token-file`` or ``ARTICAST_TOKEN`` (file wins); "" if neither."""
    env = os.environ if env is None else env
    if token_file:
        from articast.core.safe_io import read_regular_bytes

        try:
            data = read_regular_bytes(token_file, MAX_TOKEN_FILE_BYTES, what="--token-file")
            token = data.decode("utf-8").strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"--token-file {token_file}: cannot read it "
                             f"({type(exc).__name__})") from None
        if not token:
            raise InputError(f"--token-file {token_file}: the file is empty")
        return token
    return (env.get("ARTICAST_TOKEN") or env.get("ARTICAST_API_TOKEN") or "").strip()


MIN_TOKEN_BYTES = 16
MAX_TOKEN_FILE_BYTES = 4096


def check_token_strength(token: str) -> None:
    """A token shorter than 16 bytes is refused at start: guessing one, even slowed down by
    the per-address back-off, is within reach; 16 random bytes are not."""
    if token and len(token.encode("utf-8")) < MIN_TOKEN_BYTES:
        raise InputError(f"the token has {len(token.encode('utf-8'))} bytes: use at least "
                         f"{MIN_TOKEN_BYTES} (e.g. python -c 'import secrets; "
                         "print(secrets.token_urlsafe(24))')")


def client_key(host: str | None) -> str:
    """The address limits and back-offs count by: an IPv4 address, or an IPv6 client's /64
    (one host gets a whole /64 and can pick any address in it)."""
    if not host:
        return "?"
    try:
        ip = ipaddress.ip_address(host.strip("[]").split("%", 1)[0])
    except ValueError:
        return host
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, 64), strict=False))
    return str(ip)


class FailedAttempts:
    """Wrong tokens per client address, and how long the answer to the next one waits.

    The first ``free`` failures are answered at once; every further one waits its turn (one
    answer at a time per address) and then ``initial_s``, doubling to ``max_s``. The right
    token is never held: it is compared (in constant time) before any of this, so clients
    behind one NAT keep working while another guesses from the same address (issue 39: the
    lock-out refused the right token too), and the guessing still gets one answer per
    ``max_s`` at most. A success does not forget the address (a guesser behind the NAT of
    a working client would get its free failures back); ``forget_s`` without a failure does.
    Bounded: at most ``max_addresses`` are remembered (the oldest forgotten first)."""

    def __init__(self, free: int = 5, initial_s: float = 1.0, max_s: float = 60.0,
                 forget_s: float = 600.0, max_addresses: int = 65536) -> None:
        self.free, self.max_s, self.forget_s = free, max_s, forget_s
        self.initial_s = min(initial_s, max_s)
        self.max_addresses = max_addresses
        self._failures: dict[str, tuple[int, float]] = {}  # key -> (count, last failure)
        self._turns: dict[str, tuple[Any, int]] = {}  # key -> (asyncio.Lock, users)

    def failed(self, key: str, t: float, at_least: int = 0) -> float:
        """Count a wrong token; how long its answer waits (0: answered at once).
        ``at_least``: the address's count elsewhere too (a room's servers share it through
        Redis): the higher of the two counts."""
        count, last = self._failures.pop(key, (0, t))
        count = max(at_least, 1 if t - last > self.forget_s else count + 1)
        if len(self._failures) >= self.max_addresses:
            self._failures.pop(next(iter(self._failures)))
        self._failures[key] = (count, t)
        if count <= self.free:
            return 0.0
        return min(self.max_s, self.initial_s * 2.0 ** min(30, count - self.free - 1))

    @contextlib.asynccontextmanager
    async def turn(self, key: str) -> AsyncIterator[None]:
        """One failure of ``key`` at a time (concurrent guesses queue, each waiting its own
        delay: the answers' rate stays bounded however many connections guess)."""
        import asyncio

        lock, users = self._turns.get(key) or (asyncio.Lock(), 0)
        self._turns[key] = (lock, users + 1)
        try:
            async with lock:
                yield
        finally:
            lock, users = self._turns[key]
            if users <= 1:
                del self._turns[key]
            else:
                self._turns[key] = (lock, users - 1)


@dataclass(frozen=True)
class AccessPolicy:
    token: str = ""
    """The shared secret; "" = no token (then only loopback binding is allowed by the CLI)."""
    bind_host: str = "127.0.0.1"
    allowed_hosts: tuple[str, ...] = ()
    """Extra names the ``Host`` header may carry (``*``: any)."""
    allowed_origins: tuple[str, ...] = ()
    """Extra browser origins (``https://app.example``; ``*``: any)."""
    media_roots: tuple[str, ...] = ()
    """Folders whose files sessions added over HTTP may open."""
    allowed_devices: tuple[str, ...] = ()
    """Cameras (``/dev/videoN``) sessions added over HTTP may open."""

    def __repr__(self) -> str:  # never show the token
        return (f"AccessPolicy(token={'set' if self.token else 'none'}, "
                f"bind_host={self.bind_host!r}, media_roots={self.media_roots!r}, "
                f"allowed_devices={self.allowed_devices!r})")

    # ------------------------------------------------------------------ token
    def token_ok(self, authorization: str | None, query_string: bytes | str = b"") -> bool:
        if not self.token:
            return True
        offered = ""
        if authorization and authorization[:7].lower() == "bearer ":
            offered = authorization[7:].strip()
        if not offered and query_string:
            qs = query_string.decode("latin-1") if isinstance(query_string, bytes) \
                else query_string
            offered = dict(parse_qsl(qs)).get("token", "")
        return hmac.compare_digest(offered.encode("utf-8", "replace"),
                                   self.token.encode("utf-8"))

    # ------------------------------------------------------------------ host and origin
    def host_ok(self, host_header: str | None) -> bool:
        if "*" in self.allowed_hosts:
            return True
        if host_header is None:
            return True  # HTTP/1.0 without Host: not a browser, nothing to rebind
        name = _host_name(host_header)
        if not name:
            return False  # not a host name at all
        if name in (h.lower() for h in self.allowed_hosts):
            return True
        if is_loopback(name):
            return True
        if is_wildcard(self.bind_host):
            # listening on every address: the names are unknown here; a token is required
            # to bind like this, so a rebinding page still cannot read anything
            return bool(self.token)
        return name == self.bind_host.strip().strip("[]").lower()

    def origin_ok(self, origin: str | None, host_header: str | None) -> bool:
        if origin is None:
            return True  # not a browser (browsers always send Origin on WebSocket)
        if "*" in self.allowed_origins or origin in self.allowed_origins:
            return True
        parts = urlsplit(origin)
        if parts.scheme not in ("http", "https") or not parts.hostname:
            return False  # "null" (sandboxed frames, file://) and anything odd
        if is_loopback(parts.hostname):
            return True
        return host_header is not None and parts.netloc.lower() == host_header.strip().lower()

    # ------------------------------------------------------------------ files and devices
    def check_session_files(self, kind: str, target: str, files: dict[str, str]) -> None:
        """Raise :class:`Forbidden` unless the source and the asset files may be opened.

        ``kind``/``target`` come from the parsed source URI; ``files`` maps a field name
        (model, appearance, camera) to its path ("" = not given).
        """
        if kind == "v4l2":
            device = target or "/dev/video0"
            if device.isdigit():
                device = f"/dev/video{device}"
            if device not in self.allowed_devices:
                raise Forbidden(403, f"camera {device} is not allowed over HTTP (start the "
                                "server with --allow-device " f"{device})")
        elif kind in FILE_KINDS:
            self._check_path("source", target)
        for field_name, path in files.items():
            if path:
                self._check_path(field_name, path)

    def resolve(self, path: str) -> str:
        """``path`` made absolute (relative: against the first media root)."""
        p = Path(path).expanduser()
        if not p.is_absolute() and self.media_roots:
            p = Path(self.media_roots[0]) / p
        return os.path.realpath(p)

    def _check_path(self, field_name: str, path: str) -> None:
        if not self.media_roots:
            raise Forbidden(403, f"{field_name}: this server opens no files for HTTP clients "
                            "(start it with --media-root DIR)")
        real = self.resolve(path)
        for root in self.media_roots:
            r = os.path.realpath(root)
            if real == r or real.startswith(r.rstrip(os.sep) + os.sep):
                return
        # the same answer whether the path exists or not: no existence oracle
        raise Forbidden(403, f"{field_name}: only files under the server's media roots "
                        "may be opened")


# ---------------------------------------------------------------------------------- logs
_SECRET_PATTERNS = (
    re.compile(r"(?i)(token=)[^&\s\"'#]+"),                       # ?token=... in a URL
    re.compile(r"(?i)(authorization['\"]?\s*[:,=]\s*[(b'\"\s]*bearer\s+)[^\s'\")\],]+"),
)
_REFUSED_HANDSHAKE = ('%s - "WebSocket %s" %d', "connection rejected (%d %s)")


def redact(text: str, token: str = "") -> str:
    """``text`` with every ``token=VALUE``, ``Authorization: Bearer VALUE`` and the token
    itself replaced by ``…``."""
    for pattern in _SECRET_PATTERNS:
        text = pattern.sub(r"\1…", text)
    if token:
        text = text.replace(token, "…")
    return text


class _RedactingRecord(logging.LogRecord):
    secret = ""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        # formatters that read the arguments themselves (uvicorn's access log) see them
        # redacted too
        if isinstance(self.args, tuple):
            self.args = tuple(redact(a, self.secret) if isinstance(a, str) else a
                              for a in self.args)

    def getMessage(self) -> str:  # noqa: N802 - logging's name
        return redact(super().getMessage(), self.secret)


def _drop_refusal_echo(record: logging.LogRecord) -> bool:
    """uvicorn's and websockets' own lines for a refused handshake: the app logs it once,
    as a refusal, with the reason."""
    return record.msg not in _REFUSED_HANDSHAKE


def install_log_redaction(token: str) -> None:
    """Make every log record of this process redact the token (the access log's
    ``"WebSocket /ws?token=…"``, debug dumps of ``Authorization`` headers), at every level
    and through every handler: the records themselves are built redacting."""
    _RedactingRecord.secret = token or _RedactingRecord.secret
    logging.setLogRecordFactory(_RedactingRecord)
    for name in ("uvicorn.error", "websockets.server"):
        logger = logging.getLogger(name)
        if _drop_refusal_echo not in logger.filters:
            logger.addFilter(_drop_refusal_echo)
