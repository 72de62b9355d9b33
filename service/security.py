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

import hmac
import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path
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


def _host_name(value: str) -> str:
    """``example.com:8765`` / ``[::1]:80`` -> ``example.com`` / ``::1`` (lower case)."""
    value = value.strip().lower()
    if value.startswith("["):
        return value[1:].split("]", 1)[0]
    if value.count(":") == 1:
        return value.split(":", 1)[0]
    return value


def load_token(env: dict[str, str] | os._Environ[str] | None = None,
               token_file: str = "") -> str:
    """The secret from ``--token-file`` or ``ARTICAST_TOKEN`` (file wins); "" if neither."""
    env = os.environ if env is None else env
    if token_file:
        try:
            token = Path(token_file).read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(f"--token-file {token_file}: cannot read it "
                             f"({type(exc).__name__})") from None
        if not token:
            raise InputError(f"--token-file {token_file}: the file is empty")
        return token
    return (env.get("ARTICAST_TOKEN") or env.get("ARTICAST_API_TOKEN") or "").strip()


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
        if name in (h.lower() for h in self.allowed_hosts):
            return True
        if is_loopback(name):
            return True
        if is_wildcard(self.bind_host):
            # listening on every address: the names are unknown here; a token is required
            # to bind like this, so a rebinding page still cannot read anything
            return bool(self.token)
        return name == _host_name(self.bind_host)

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
