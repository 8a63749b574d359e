"""drivers.runtime.RateLimitedLog: the one rate-limited warning of the sensor clients, the simulators
and the worker (issue 45: two copies before)."""

from __future__ import annotations

from drivers.runtime import RateLimitedLog


class _Log:
    def __init__(self) -> None:
        self.lines: list[tuple[str, dict]] = []

    def warning(self, event: str, **kw: object) -> None:
        self.lines.append((event, kw))


def test_one_warning_per_event_per_interval_with_the_suppressed_and_total_counts() -> None:
    log = _Log()
    lim = RateLimitedLog(log, interval_s=60.0)
    for k in range(5):
        lim.warning("bad_packet", n=k)
    lim.warning("bad_message")
    assert log.lines == [
        ("bad_packet", {"suppressed": 0, "total": 1, "n": 0}),
        ("bad_message", {"suppressed": 0, "total": 1}),
    ]
    assert lim.count("bad_packet") == 5 and lim.count() == 6


def test_the_next_warning_after_the_interval_says_how_many_were_suppressed() -> None:
    log = _Log()
    lim = RateLimitedLog(log, interval_s=60.0)
    lim.warning("bad_packet")
    lim._interval_ns = 10**12  # hold the interval open while three more come
    for _ in range(3):
        lim.warning("bad_packet")
    lim._interval_ns = 0  # the interval has passed
    lim.warning("bad_packet")
    assert log.lines[-1] == ("bad_packet", {"suppressed": 3, "total": 5})
