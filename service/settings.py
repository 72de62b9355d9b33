"""Service settings: one frozen dataclass per policy.

Each field is settable from an environment variable ``ARTICAST_<FIELD>`` (upper case) and,
for the ones the CLI exposes, from ``--<field-with-dashes>``; the command line wins over the
environment, the environment over the defaults.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

from core.errors import InputError

S = TypeVar("S")


@dataclass(frozen=True)
class CaptureSettings:
    """How a capture thread treats its source."""

    retry_initial_s: float = 0.5
    """First wait before reopening an unavailable camera; doubles up to ``retry_max_s``."""
    retry_max_s: float = 10.0
    read_timeout_s: float = 2.0
    """A live source that delivers nothing for this long is considered lost."""


@dataclass(frozen=True)
class HubSettings:
    """Limits of the fan-out to subscribers."""

    max_queue: int = 4
    """Frames queued per subscriber before the oldest is dropped."""
    max_subscribers: int = 2000
    max_subscriptions_per_connection: int = 16
    max_message_bytes: int = 65536
    """Largest client message the app accepts (larger ones get an ``error``)."""
    ws_max_size: int = 1 << 20
    """Largest WebSocket message the protocol layer reads at all (larger: close 1009)."""
    stall_timeout_s: float = 30.0
    """A subscriber whose single send has not completed for this long is disconnected."""


@dataclass(frozen=True)
class SessionPolicy:
    """How sessions run and recover."""

    worker: str = "auto"
    """``thread``, ``process``, or ``auto`` (at most one session tracks in the server's own
    process; every further concurrent session gets a process, so faces never share a GIL)."""
    restart_initial_s: float = 0.5
    restart_max_s: float = 30.0
    max_restarts: int = 20
    """Restarts after crashes before a session is declared failed (input errors never restart)."""


@dataclass(frozen=True)
class ServerSettings:
    host: str = "127.0.0.1"
    port: int = 8765
    record: str = ""
    """Directory where every session's frames are written as JSONL ('' = no recording)."""
    shutdown_timeout_s: float = 5.0
    log_level: str = "warning"


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
            help=f"(default {f.default!r}; env ARTICAST_{f.name.upper()})",
        )


def from_args(cls: type[S], args: Any) -> S:
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    return from_env(cls, **{k: v for k, v in vars(args).items() if k in names})
