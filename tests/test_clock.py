"""One clock for a room spread over machines (service/clock.py): the offset to Redis's clock
estimated from ``TIME`` round trips, and the stamps that cross machines in it."""

import random
import shutil
import time

import pytest

from articast.service.clock import CLOCK_ID, OffsetEstimate, RedisClock


def round_trips(offset, n, rng, base=0.0002, jitter=0.003, asym=0.0):
    """``n`` made-up ``TIME`` round trips to a Redis whose clock is ``offset`` s ahead: each
    way takes ``base`` plus an exponential delay (mean ``jitter``), the way back ``asym``
    more."""
    t = 1_700_000_000.0
    for _ in range(n):
        t += 0.001
        up = base + rng.expovariate(1 / jitter)
        down = base + asym + rng.expovariate(1 / jitter)
        yield t, t + up + offset, t + up + down


@pytest.mark.parametrize("offset", [0.0, 0.0042, -3.0, 37.5])
def test_the_shortest_round_trip_s_midpoint_gives_the_offset_within_half_that_round_trip(offset):
    rng = random.Random(7)
    errors = []
    for _ in range(200):
        est = OffsetEstimate()
        for sample in round_trips(offset, 8, rng):
            est.add(*sample)
        assert est.n == 8
        assert abs(est.offset - offset) <= est.uncertainty + 1e-9
        errors.append(abs(est.offset - offset))
    errors.sort()
    # 8 samples with 3 ms of jitter each way: the best one's asymmetry is ~0.4 ms at worst
    # of the median estimate (1 ms on the worst of 200)
    assert errors[100] < 0.0005 and errors[-1] < 0.002, (errors[100], errors[-1])


def test_an_asymmetric_path_is_within_the_uncertainty_not_hidden():
    """A way back 5 ms longer than the way there: the midpoint is 2.5 ms late (the offset
    2.5 ms short); the stated uncertainty (half the round trip) covers it."""
    est = OffsetEstimate()
    for sample in round_trips(1.0, 8, random.Random(1), jitter=0.0001, asym=0.005):
        est.add(*sample)
    assert abs(est.offset - (1.0 - 0.0025)) < 0.0003
    assert est.uncertainty >= abs(est.offset - 1.0)


def test_a_round_trip_whose_clock_stepped_back_is_no_sample():
    est = OffsetEstimate()
    est.add(10.0, 20.0, 9.0)
    assert est.offset is None and est.uncertainty is None and est.n == 0


def test_a_stamp_from_this_clock_comes_back_exactly_and_from_another_by_this_estimate():
    here = RedisClock()
    assert here.stamp() is None and here.outgoing() == (0.0, None)
    assert here.local(5.0, None) == 5.0  # (a sender that did not convert: as it came)
    here.update(offset=-3.0, uncertainty=0.0001)  # this machine 3 s ahead of Redis
    offset, stamp = here.outgoing()
    assert stamp == [CLOCK_ID, -3.0] and offset == -3.0
    t = 1_700_000_000.123456
    there = RedisClock()
    there.update(offset=-2.9995, uncertainty=0.0001)  # another process, a later estimate
    # same machine: the sender's own offset gives its stamp back, bit for bit
    assert there.local(t + offset, stamp) == t
    # another machine (another clock): Redis's time on this one's clock
    other = ["another-machine", -3.0]
    assert there.local(t + offset, other) == pytest.approx(t - 3.0 + 2.9995, abs=1e-6)
    assert there.local(t, ["x"]) == pytest.approx(t + 2.9995)  # (malformed: this estimate)


def test_an_offset_over_a_second_is_said_in_one_line_and_a_move_in_another(caplog):
    c = RedisClock()
    with caplog.at_level("INFO", logger="articast.clock"):
        c.update(-2.5, 0.0001)
        c.update(-2.5003, 0.0001)  # (within MOVED_S: not said)
        c.update(0.0004, 0.0001)
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2, lines
    assert "clock is wrong: 2500.000 ms ahead of Redis's" in lines[0], lines
    assert "moved against Redis's: 0.400 ms behind Redis's" in lines[1], lines


@pytest.mark.skipif(not shutil.which("redis-server"), reason="needs redis-server")
def test_against_a_real_redis_on_loopback_the_offset_is_near_zero_and_known_to_a_ms():
    """This machine against a redis-server on loopback (one clock): the estimate is within
    its uncertainty of 0, and that is well under a millisecond."""
    from tests.test_redis_scaleout import Redis

    redis = Redis()
    redis.start()
    try:
        c = RedisClock()
        c.url = redis.url
        offsets, bounds = [], []
        for _ in range(20):
            assert c.measure()
            offsets.append(c.offset)
            bounds.append(c.uncertainty)
            time.sleep(0.01)
        print(f"loopback: offset {1e3 * min(offsets):+.3f}..{1e3 * max(offsets):+.3f} ms, "
              f"uncertainty {1e3 * min(bounds):.3f}..{1e3 * max(bounds):.3f} ms (20 estimates "
              f"of 8 round trips)")
        # (Redis's TIME has microseconds; one clock: 0 within the stated bound + 1 µs)
        assert all(abs(o) <= u + 2e-6 for o, u in zip(offsets, bounds, strict=True))
        assert sorted(bounds)[10] < 0.001
        assert abs(c.status()["ahead_of_redis_ms"]) < 1.0
    finally:
        redis.stop()
    c.url = "redis://127.0.0.1:1/0"  # Redis away: False, and the last estimate kept
    kept = c.offset
    assert not c.measure() and c.offset == kept
