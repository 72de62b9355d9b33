"""One clock for a room spread over machines: Redis's own ``TIME`` (issue 41).

Every process of a room reaches the same Redis; a time that one machine stamps and another
reads (a frame's capture time, a relayed voice packet's send time, a session entry's
heartbeat) travels in **Redis's clock** and is converted back at the receiving process, so
that two machines whose wall clocks differ (no NTP, a wrong clock) still agree on when a
frame was captured. The membership's leases already live in Redis's clock
(:mod:`articast.service.room_presence`).

**Estimate.** :class:`OffsetEstimate` (pure): samples ``(local send, redis time, local
receive)`` of ``TIME`` round trips; the offset (Redis's clock minus this machine's) is the
Redis time minus the midpoint of the round trip with the smallest duration (NTP's rule: its
one-way delays are nearest equal), its uncertainty half that round trip (the offset is
within it whatever the asymmetry).
:class:`RedisClock` (one per process, :data:`CLOCK`) takes :data:`SAMPLES` round trips as
soon as it is started and every :data:`REFRESH_S` after, on a daemon thread with a
synchronous client of its own (so that the media process's forwarder threads, the workers
and the event loops read it alike, never waiting on Redis; a forked child keeps the estimate
and starts a thread of its own when it is started). The offset and its uncertainty are logged at
start and when the offset moves by more than :data:`MOVED_S`; an offset over :data:`WRONG_S`
is one warning line (this machine's clock is wrong). Redis unreachable: the last estimate is
kept (0 before the first: times are then sent as they are, as before).

**Exact on one machine.** A message stamped this way carries its clock's identity
(:data:`CLOCK_ID`: the kernel's boot id, shared by every process and container of one
machine) and the offset it was converted with; a receiver of the same identity subtracts that
offset, which gives back the sender's stamp exactly (one machine has one wall clock), and
only a receiver on another clock uses its own estimate.

:data:`SKEW_S` (``ARTICAST_CLOCK_SKEW_S``) is **test-only**: it shifts this process's wall
clock (and its children's, which inherit the environment) by that many seconds, as if it ran
on a machine whose clock is that far off, so that one machine can test what two machines
whose clocks differ do (tests/test_room_redis.py). It is read once, at import.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from typing import Any

log = logging.getLogger("articast.clock")

SKEW_S = float(os.environ.get("ARTICAST_CLOCK_SKEW_S", "") or 0.0)
"""Test-only: this process's wall clock is shifted by this many seconds (see the module)."""
SAMPLES = 8
"""``TIME`` round trips per estimate."""
REFRESH_S = 10.0
"""How often the estimate is made again (a clock without NTP drifts ~0.5 ms in 10 s at
50 ppm)."""
MOVED_S = 0.002
"""An estimate that moved more than this (beyond both uncertainties) is logged."""
WRONG_S = 1.0
"""An offset larger than this: this machine's clock is wrong, said in one line."""


def _boot_id() -> str:
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            return f.read().strip()
    except OSError:  # not Linux: the host's name (one clock per host)
        return os.uname().nodename if hasattr(os, "uname") else "?"


CLOCK_ID = _boot_id() + (f"{SKEW_S:+g}" if SKEW_S else "")
"""This machine's wall clock (see the module: a skewed test process is another clock)."""


MONO_TO_EPOCH = time.time() + SKEW_S - time.monotonic()
"""This process's monotonic clock to the epoch, read once: :func:`wall`."""


def wall() -> float:
    """This process's wall clock: ``time.monotonic()`` on the epoch as ``time.time()`` (with
    the test-only :data:`SKEW_S`) read it at start. Every stamp that crosses machines is made
    on it (``articast.service.wire.now``), and the offset to Redis is measured on it: a clock
    stepped while the process runs (an administrator fixing a wrong clock) moves neither its
    stamps nor its offset (slewing, as NTP does, moves both alike)."""
    return time.monotonic() + MONO_TO_EPOCH


class OffsetEstimate:
    """Redis's clock minus this machine's, from ``TIME`` round trips (pure: fed samples)."""

    def __init__(self) -> None:
        self.best: tuple[float, float] | None = None  # (round trip, offset)
        self.n = 0

    def add(self, sent: float, redis_t: float, received: float) -> None:
        """One round trip: sent and received on this machine's clock, ``redis_t`` what
        ``TIME`` said (seconds)."""
        rtt = received - sent
        if rtt < 0:  # the local clock stepped back mid-trip: no information
            return
        self.n += 1
        if self.best is None or rtt < self.best[0]:
            self.best = (rtt, redis_t - (sent + received) / 2)

    @property
    def offset(self) -> float | None:
        return None if self.best is None else self.best[1]

    @property
    def uncertainty(self) -> float | None:
        """Half the shortest round trip: the true offset is within this of :attr:`offset`."""
        return None if self.best is None else self.best[0] / 2


class RedisClock:
    """This process's offset to Redis's clock (see the module's docstring)."""

    def __init__(self) -> None:
        self.offset = 0.0
        self.uncertainty: float | None = None
        """None until a first estimate (then :attr:`offset` is 0: times are not converted)."""
        self.measured = 0.0  # time.monotonic() of the last estimate
        self.url = ""
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._failing = False
        self._quiet = True
        self._wake = threading.Event()
        if hasattr(os, "register_at_fork"):  # a forked child (the media process, a worker)
            os.register_at_fork(after_in_child=self._forked)  # keeps the estimate, not the thread

    def _forked(self) -> None:
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._thread = None
        self.url = ""

    # ------------------------------------------------------------------ conversions
    def to_redis(self, t: float) -> float:
        """A stamp on this machine's wall clock, in Redis's (see :meth:`outgoing` for stamps
        that travel with the clock they came from)."""
        return t + self.offset

    def outgoing(self) -> tuple[float, list[Any] | None]:
        """``(offset, stamp)``: add the offset to this machine's stamps, send the stamp with
        them (read at once: a refresh between the two would make them disagree)."""
        stamp = self.stamp()
        return (0.0, None) if stamp is None else (stamp[1], stamp)

    def stamp(self) -> list[Any] | None:
        """What travels with stamps converted by :meth:`to_redis`: ``[clock, offset]``
        (None before a first estimate: the stamps went as they are)."""
        return None if self.uncertainty is None else [CLOCK_ID, self.offset]

    def local(self, t: float, stamp: Any) -> float:
        """A stamp in Redis's clock (converted with ``stamp``, the sender's
        :meth:`stamp`) on this machine's wall clock. No ``stamp`` (a sender that does not
        convert): ``t`` as it came."""
        if not stamp:
            return t
        try:
            clock, offset = stamp
            if clock == CLOCK_ID:
                return t - float(offset)
        except (TypeError, ValueError):
            pass
        return t - self.offset

    def redis_now(self) -> float:
        return wall() + self.offset

    def status(self) -> dict[str, Any]:
        """For ``/healthz``: how far this machine's clock is ahead of Redis's (ms; negative:
        behind), the estimate's uncertainty (ms) and its age (s)."""
        if self.uncertainty is None:
            return {"ahead_of_redis_ms": None}
        return {"ahead_of_redis_ms": round(-1000 * self.offset, 3),
                "uncertainty_ms": round(1000 * self.uncertainty, 3),
                "age_s": round(time.monotonic() - self.measured, 1)}

    # ------------------------------------------------------------------ estimating
    def start(self, url: str, quiet: bool = False) -> None:
        """Estimate against ``url``'s Redis (the last URL given, when a process is given more
        than one) at once and every :data:`REFRESH_S` after, on a daemon thread: this never
        waits on Redis. Until the first estimate, stamps go as they are (:meth:`stamp` is
        None). ``quiet``: the first estimate is logged at INFO only (a helper process, such
        as the media process or a worker: its main process says it)."""
        with self._lock:
            if url == self.url and self._thread is not None:
                return
            self.url = url
            self._quiet = self._quiet and quiet
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="redis clock",
                                                daemon=True)
                self._thread.start()
            else:
                self._wake.set()

    def measure(self, samples: int = SAMPLES) -> bool:
        """One estimate (:data:`SAMPLES` ``TIME`` round trips); False if Redis is away."""
        import redis

        url = self.url
        est = OffsetEstimate()
        try:
            client = redis.Redis.from_url(url, socket_connect_timeout=1.0, socket_timeout=1.0)
            try:
                client.ping()  # (the connection made first: not in the round trips)
                for _ in range(samples):
                    sent = wall()
                    sec, usec = client.time()
                    est.add(sent, sec + usec / 1e6, wall())
            finally:
                client.close()
        except Exception as exc:  # noqa: BLE001 - Redis away: the last estimate is kept
            if not self._failing:
                log.warning("cannot read Redis's clock at %s (%r): times that cross machines "
                            "use the last estimate (%+.1f ms)", url.split("@")[-1], exc,
                            1000 * self.offset)
            self._failing = True
            return False
        if self._failing:
            log.warning("Redis's clock can be read again")
        self._failing = False
        assert est.offset is not None and est.uncertainty is not None
        self.update(est.offset, est.uncertainty)
        return True

    def update(self, offset: float, uncertainty: float) -> None:
        """Take an estimate; log it (one line) when it is the first or it moved."""
        before, u_before = self.offset, self.uncertainty
        self.offset, self.uncertainty, self.measured = offset, uncertainty, time.monotonic()
        if u_before is not None and abs(offset - before) <= MOVED_S + uncertainty + u_before:
            return
        level = logging.INFO if self._quiet else logging.WARNING
        ahead = -offset  # (this machine's clock minus Redis's)
        how = (f"{1000 * abs(ahead):.3f} ms {'ahead of' if ahead >= 0 else 'behind'} Redis's "
               f"(± {1000 * uncertainty:.3f} ms)")
        if u_before is not None:
            how += f"; it was {-1000 * before:+.3f} ms"
        if abs(offset) > WRONG_S:
            log.log(level, "this machine's clock is wrong: %s (is NTP running?); the room "
                    "corrects the times it sends, but fix the clock", how)
        elif u_before is None:
            log.log(level, "this machine's clock is %s: times that cross machines travel in "
                    "Redis's clock", how)
        else:
            log.log(level, "this machine's clock moved against Redis's: %s", how)

    def _run(self) -> None:
        while True:
            self.measure()
            self._wake.wait(REFRESH_S)
            self._wake.clear()


CLOCK = RedisClock()
"""This process's clock against its Redis."""
