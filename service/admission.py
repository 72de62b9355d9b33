"""Who may do what, and how much: the checks the app makes before it does any work.

* the token checks of the HTTP routes (:func:`authorise`, :func:`authorise_admin`);
* a session asked for over HTTP (:class:`SessionCreate`), its files confined to the media roots
  (:func:`confined_spec`), its paths named within the kernel's limits (:func:`path_name_problem`);
* the per-address rate budgets of WebSocket handshakes and subscribe requests
  (:class:`AddressBudgets`);
* the subscription limits: per connection, per address, the server's, and the places kept for
  addresses that hold few (:func:`subscription_refusal`).

Nothing here awaits: each check is a function of the request and the counts it is given.
"""

from __future__ import annotations

import os

from fastapi import HTTPException, Request
from pydantic import BaseModel, ConfigDict, Field

from articast.core.errors import ArticastError
from articast.service.middleware import MessageBucket
from articast.service.security import AccessPolicy
from articast.service.settings import HubSettings
from articast.service.worker import SessionSpec


def authorise(access: AccessPolicy, request: Request) -> None:
    """Reading faces: the token when one is configured (401 otherwise)."""
    if not access.token_ok(request.headers.get("authorization"),
                           request.scope.get("query_string", b"")):
        raise HTTPException(401, "this server needs a token: Authorization: Bearer TOKEN "
                            "(or ?token=TOKEN)")


def authorise_admin(access: AccessPolicy, request: Request) -> None:
    """Starting and stopping sessions: always the token (403 when none is configured)."""
    if not access.token:
        raise HTTPException(403, "the session API needs a token: start the server with "
                            "ARTICAST_TOKEN or --token-file")
    authorise(access, request)


class SessionCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    source: str = Field(min_length=1, max_length=4096)
    model: str = ""
    appearance: str = ""
    camera: str = ""
    processor: str = "auto"
    wait_for_subscriber: bool = False
    speaker: str = ""
    preview: bool = False
    readers: int = Field(default=1, ge=1, le=2)
    """2: a speaker's face tracked with two landmark readers (core/faces/two_readers.py)."""


def path_name_problem(path: str) -> str:
    """Why ``path`` cannot name a file on this system ("" if it can): a NUL byte, a name
    over 255 bytes or a path over 4096 (the kernel's limits), said before anything opens it."""
    if "\0" in path:
        return "a file name cannot contain a NUL byte"
    encoded = path.encode("utf-8", "surrogateescape")
    if len(encoded) > 4096:
        return f"a path of {len(encoded)} bytes is over the limit of 4096"
    longest = max((len(part) for part in encoded.split(b"/")), default=0)
    if longest > 255:
        return f"a file name of {longest} bytes is over the limit of 255"
    return ""


def confined_spec(access: AccessPolicy, body: SessionCreate) -> SessionSpec:
    """The spec of a session asked for over HTTP, its files resolved inside the media roots.

    Raises :class:`~articast.service.security.Forbidden` for a device not allowed or a path
    outside the roots (the same answer whether the path exists or not) and
    ``HTTPException(400)`` for a malformed URI.
    """
    from articast.service.sources import SOURCE_KINDS, parse_uri

    try:
        p = parse_uri(body.source)
    except ArticastError as exc:
        raise HTTPException(400, str(exc)) from None
    files = {"model": body.model, "appearance": body.appearance, "camera": body.camera,
             "speaker": body.speaker}
    for field_name, path in (("source", p.target), *files.items()):
        problem = path_name_problem(path)
        if problem:
            raise HTTPException(400, f"{field_name}: {problem}")
    if body.readers != 1 and not body.speaker:
        raise HTTPException(400, f"readers: {body.readers} needs a speaker (a speaker folder "
                                 "from 'articast enroll')")
    access.check_session_files(p.kind, p.target, files)
    if p.kind in ("file", "images", "replay-record"):
        query = body.source.partition("?")[2]
        source = f"{p.kind}:{access.resolve(p.target)}" + (f"?{query}" if query else "")
    else:
        source = body.source
    assert p.kind in SOURCE_KINDS
    resolved = {k: access.resolve(v) if v else "" for k, v in files.items()}
    return SessionSpec(body.name, source, resolved["model"], resolved["appearance"],
                       resolved["camera"], body.processor, body.wait_for_subscriber,
                       options={"readers": body.readers} if body.readers != 1 else {},
                       speaker=resolved["speaker"], preview=body.preview,
                       media_roots=tuple(os.path.realpath(r) for r in access.media_roots))


class AddressBudgets:
    """The rate budgets of each client address: subscribe requests and WebSocket handshakes,
    each a token bucket with bursts of twice its rate. Bounded: the least recently used
    addresses are forgotten first."""

    MAX_KEYS = 65536

    def __init__(self, limits: HubSettings) -> None:
        self.limits = limits
        self._buckets: dict[tuple[str, str], MessageBucket] = {}

    def subscribe(self, key: str) -> MessageBucket:
        """The subscribe-rate budget of one client address."""
        return self._bucket("subscribe", key, self.limits.max_subscribes_per_client_s)

    def handshake(self, key: str) -> MessageBucket:
        """The WebSocket-connection-rate budget of one client address."""
        return self._bucket("handshake", key, self.limits.max_handshakes_per_client_s)

    def _bucket(self, kind: str, key: str, rate: float) -> MessageBucket:
        bucket = self._buckets.pop((kind, key), None)
        if bucket is None:
            bucket = MessageBucket(rate, 2 * rate)
            if len(self._buckets) >= self.MAX_KEYS:
                self._buckets.pop(next(iter(self._buckets)))
        self._buckets[(kind, key)] = bucket
        return bucket


def reserve(limits: HubSettings) -> int:
    """Subscriptions kept for addresses holding fewer than ``reserved_per_client``: at most
    half the server's limit."""
    return max(0, min(limits.reserved_subscribers, limits.max_subscribers // 2))


def subscription_refusal(limits: HubSettings, *, on_connection: int, by_address: int,
                         total: int) -> str:
    """Why a new subscription is refused ("" when it is admitted), given the subscriptions
    held on its connection, by its client address (all its connections) and on the server."""
    if on_connection >= limits.max_subscriptions_per_connection:
        return ("subscription limit per connection "
                f"({limits.max_subscriptions_per_connection}) reached")
    if by_address >= limits.max_subscriptions_per_client:
        return ("subscription limit per client address "
                f"({limits.max_subscriptions_per_client}) reached")
    if total >= limits.max_subscribers:
        return f"the server is at its subscriber limit ({limits.max_subscribers})"
    kept = reserve(limits)
    if total >= limits.max_subscribers - kept and by_address >= limits.reserved_per_client:
        # the last places are kept for addresses that hold few (issue 39: 16 addresses
        # filled the server and a newcomer was refused)
        return (f"the server is nearly full: its last {kept} subscriptions are kept for "
                f"addresses holding fewer than {limits.reserved_per_client}")
    return ""
