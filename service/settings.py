"""Service settings: one frozen dataclass per policy.

Each field is settable from an environment variable ``ARTICAST_<FIELD>`` (upper case) and,
for the ones the CLI exposes, from ``--<field-with-dashes>``; the command line wins over the
environment, the environment over the defaults.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

from articast.core.errors import InputError

S = TypeVar("S")


def _opt(default: Any, help: str) -> Any:  # noqa: A002 - argparse's word
    return field(default=default, metadata={"help": help})


@dataclass(frozen=True)
class CaptureSettings:
    """How a capture thread treats its source."""

    retry_initial_s: float = _opt(0.5, "first wait before reopening an unavailable camera")
    retry_max_s: float = _opt(10.0, "longest wait between reopening attempts (backoff cap)")


@dataclass(frozen=True)
class HubSettings:
    """Limits of the fan-out to subscribers."""

    max_queue: int = _opt(4, "frames queued per subscriber before the oldest is dropped")
    max_queue_limit: int = _opt(256, "deepest queue a subscriber may ask for")
    max_subscribers: int = _opt(2000, "subscriptions the server accepts in all")
    max_subscriptions_per_connection: int = _opt(16, "sessions one connection may follow")
    max_message_bytes: int = _opt(65536, "largest client message or HTTP body accepted")
    ws_max_size: int = _opt(1 << 20, "largest WebSocket message read at all (else close 1009)")
    stall_timeout_s: float = _opt(30.0, "disconnect a subscriber whose send is stuck this long")
    socket_buffer_bytes: int = _opt(32768, "bytes buffered per connection after its queue: "
                                    "bounds how stale a slow client's frames can get")
    max_messages_per_s: float = _opt(20.0, "client messages per second per connection (bursts "
                                     "of twice that); beyond: dropped with an error, and a "
                                     "connection far over it is closed (1008)")
    max_connections_per_client: int = _opt(256, "open TCP connections per client address "
                                           "(an IPv6 client: per /64)")
    max_subscriptions_per_client: int = _opt(256, "subscriptions of one client address, all "
                                             "its connections together (an IPv6 client: per "
                                             "/64): one address cannot fill --max-subscribers")
    max_handshakes_per_client_s: float = _opt(20.0, "WebSocket connections per second one "
                                              "client address may open (bursts of twice "
                                              "that); beyond: 429 before the handshake")
    reserved_subscribers: int = _opt(200, "the last of --max-subscribers kept for client "
                                     "addresses holding fewer than --reserved-per-client "
                                     "(at most half the limit): a newcomer still gets in when "
                                     "a few addresses have filled the server")
    reserved_per_client: int = _opt(4, "an address holding fewer subscriptions than this may "
                                    "use the reserved ones")
    max_subscribes_per_client_s: float = _opt(20.0, "subscribe requests per second of one "
                                              "client address, all its connections together "
                                              "(bursts of twice that); beyond: refused with "
                                              "rate_limited, and bystanders keep their frames")
    receive_buffer_bytes: int = _opt(65536, "kernel receive buffer per connection (0: the "
                                     "system's, megabytes): what a client sends faster than "
                                     "it is read waits on the client's side")
    close_timeout_s: float = _opt(2.0, "a WebSocket connection the server closed (or whose "
                                  "handler ended) is dropped this long after, answered or "
                                  "not; what its peer sends meanwhile is not parsed beyond "
                                  "64 kB")
    max_token_failures: int = _opt(5, "wrong tokens of one address answered at once; each "
                                   "further one waits its turn, 1 s doubling to "
                                   "--token-delay-max-s (the right token never waits)")
    token_delay_max_s: float = _opt(60.0, "longest wait before a wrong token is answered")
    max_header_bytes: int = _opt(16384, "largest HTTP request head (request line + headers)")
    header_timeout_s: float = _opt(10.0, "close a connection whose request head is not "
                                   "complete this long after it started (slowloris)")


@dataclass(frozen=True)
class SessionPolicy:
    """How sessions run and recover."""

    worker: str = _opt("auto", "thread | process | auto (a process per tracking session; one "
                       "ground-truth session may run in a thread): faces never share a GIL")
    restart_initial_s: float = _opt(0.5, "first wait before restarting a crashed session")
    restart_max_s: float = _opt(30.0, "longest wait between restarts (backoff cap)")
    max_restarts: int = _opt(20, "crashes before a session is declared failed")
    max_sessions: int = _opt(8, "sessions the server runs at most (POST beyond: 429)")
    worker_stall_s: float = _opt(10.0, "a running session that produces nothing this long is "
                                  "declared stalled and its worker restarted (0: never)")
    worker_start_s: float = _opt(120.0, "a starting session (opening its source, loading or "
                                 "building its models, compiling; it says what it does) "
                                 "that reports nothing this long is declared stalled and "
                                 "its worker restarted (0: never)")


@dataclass(frozen=True)
class ServerSettings:
    host: str = _opt("127.0.0.1", "address to listen on")
    port: int = _opt(8765, "port to listen on (0: any free port)")
    record: str = _opt("", "write every session's frames as JSONL into this folder")
    shutdown_timeout_s: float = _opt(5.0, "wait this long for connections and workers to end")
    log_level: str = _opt("warning", "uvicorn and articast log level")
    scan: str = _opt("", "show this bound, textured head scan on the avatar page, animated by "
                     "the stream (a binding from 'articast bind-dense SCAN --landmarks FILE', "
                     "made against the sessions' model; docs/DENSE_TRANSFER.md)")
    vmc: str = _opt("", "also send every session's head pose, ARKit mouth/jaw blendshapes "
                        "and, where seen, blinks, gaze (eye bones) and brows over the VMC "
                        "protocol (OSC/UDP) to HOST[:PORT] (default port 39539)")
    vmc_names: str = _opt("perfect-sync", "VMC blendshape names: perfect-sync (UpperCamel, "
                          "JawOpen: perfect-sync VRM avatars) or arkit (lowerCamel, jawOpen); "
                          "the VRM vowels A I U E O are sent either way")


def from_env(cls: type[S], env: Mapping[str, str] | None = None, **overrides: Any) -> S:
    """Build ``cls`` from its defaults, ``ARTICAST_*`` variables, then ``overrides``.

    ``None`` overrides are ignored (an argparse option that was not given).
    """
    env = os.environ if env is None else env
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        key = f"ARTICAST_{f.name.upper()}"
        if key in env:
            values[f.name] = _convert(f.type, env[key], key)
    values.update({k: v for k, v in overrides.items() if v is not None})
    return cls(**values)


def _convert(type_name: Any, raw: str, key: str) -> Any:
    t = str(type_name)
    try:
        if t == "int":
            return int(raw)
        if t == "float":
            return float(raw)
        if t == "bool":
            return raw.strip().lower() in ("1", "true", "yes", "on")
        return raw
    except ValueError:
        raise InputError(f"{key}={raw!r} is not a valid {t}") from None


def add_arguments(parser: Any, cls: type, skip: tuple[str, ...] = ()) -> None:
    """Mirror the fields of a settings class as ``--options`` (default None: env/defaults)."""
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        t = {"int": int, "float": float}.get(str(f.type), str)
        parser.add_argument(
            "--" + f.name.replace("_", "-"), dest=f.name, type=t, default=None,
            help=f"{f.metadata.get('help', '')} (default {f.default!r}; "
            f"env ARTICAST_{f.name.upper()})".lstrip(),
        )


def from_args(cls: type[S], args: Any) -> S:
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    return from_env(cls, **{k: v for k, v in vars(args).items() if k in names})
