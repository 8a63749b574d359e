"""Mutation strategies and bounded settings shared by the fuzz tests.

Every fuzz test takes valid messages of its boundary and mutates them the way a bad link, a broken
peer or a hostile client would: bit flips, truncation, extension with junk, a slice duplicated or
deleted, two slices swapped (fields exchanged), two valid messages spliced, or plain random bytes.

Example counts are bounded so that ``tests/fuzz`` runs in well under 90 s on a loaded 2-core box.
For a long run, pick a bigger Hypothesis profile: the counts scale with the profile's
``max_examples`` (100 by default)::

    PYTHONPATH=. .venv/bin/python -m pytest tests/fuzz --hypothesis-profile=fuzz-long   # x50
    PYTHONPATH=. .venv/bin/python -m pytest tests/fuzz --hypothesis-profile=fuzz-soak   # x500

(the profiles are registered in ``tests/fuzz/conftest.py``).
"""

from __future__ import annotations

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

_DEFAULT_MAX_EXAMPLES = 100


def fuzz_settings(max_examples: int) -> settings:
    """Settings for one fuzz test: ``max_examples`` scaled by the loaded profile, no deadline."""
    scale = settings.default.max_examples / _DEFAULT_MAX_EXAMPLES
    return settings(
        max_examples=max(1, int(max_examples * scale)),
        deadline=None,  # socket round trips on a loaded machine: time is not the property
        suppress_health_check=[
            HealthCheck.too_slow,
            HealthCheck.function_scoped_fixture,
            HealthCheck.data_too_large,
        ],
    )


def _flip(data: bytes, positions: list[int], bits: list[int]) -> bytes:
    out = bytearray(data)
    for p, b in zip(positions, bits, strict=False):
        if out:
            out[p % len(out)] ^= 1 << b
    return bytes(out)


@st.composite
def mutated(draw: st.DrawFn, valid: bytes, others: tuple[bytes, ...] = ()) -> bytes:
    """One mutation of ``valid`` (``others``: more valid messages to splice with)."""
    n = len(valid)
    kind = draw(
        st.sampled_from(["flip", "truncate", "extend", "delete", "duplicate", "swap", "splice", "random"])
    )
    if kind == "flip" and n:
        k = draw(st.integers(1, 8))
        return _flip(valid, draw(st.lists(st.integers(0, n - 1), min_size=k, max_size=k)),
                     draw(st.lists(st.integers(0, 7), min_size=k, max_size=k)))  # fmt: skip
    if kind == "truncate" and n:
        return valid[: draw(st.integers(0, n - 1))]
    if kind == "extend":
        return valid + draw(st.binary(min_size=1, max_size=64))
    if kind == "delete" and n > 1:
        a = draw(st.integers(0, n - 1))
        b = draw(st.integers(a + 1, min(n, a + 16)))
        return valid[:a] + valid[b:]
    if kind == "duplicate" and n:
        a = draw(st.integers(0, n - 1))
        b = draw(st.integers(a + 1, min(n, a + 16)))
        return valid[:b] + valid[a:b] + valid[b:]
    if kind == "swap" and n >= 4:
        a = draw(st.integers(0, n - 2))
        b = draw(st.integers(a + 1, n - 1))
        w = draw(st.integers(1, max(1, min(8, b - a, n - b))))
        out = bytearray(valid)
        out[a : a + w], out[b : b + w] = valid[b : b + w], valid[a : a + w]
        return bytes(out)
    if kind == "splice" and others:
        other = draw(st.sampled_from(others))
        return valid[: draw(st.integers(0, n))] + other[draw(st.integers(0, len(other))) :]
    return draw(st.binary(min_size=0, max_size=max(8, 2 * n)))


class Hang(AssertionError):
    """A call that did not return within its bound: the input made the code spin or wait."""


def no_hang(seconds: float):
    """Context manager failing the test with :class:`Hang` when the block runs longer than ``seconds``.

    Main thread only (SIGALRM). The bound is generous: it catches spins and waits, not slowness.
    """
    import contextlib
    import signal

    @contextlib.contextmanager
    def guard():
        def on_alarm(signum, frame):
            raise Hang(f"still running after {seconds} s")

        old = signal.signal(signal.SIGALRM, on_alarm)
        signal.setitimer(signal.ITIMER_REAL, seconds)
        try:
            yield
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)

    return guard()
