"""Fuzz the trigger boundary: ``cellctl.api.parse_trigger`` and, for a sample, the real queryable over Zenoh.

Whatever arrives, the answer is a valid request resolving to a file inside ``designs_dir`` or a
``TriggerError`` with a known code, a field and a reason; over Zenoh, an ``ApiError`` reply and no
job created. Never another exception.
"""

from __future__ import annotations

import asyncio
import json
import threading
from pathlib import Path

import pytest
import zenoh
from fuzzlib import fuzz_settings, mutated
from hypothesis import example, given
from hypothesis import strategies as st

from cellctl.api import (
    MAX_TRIGGER_BYTES,
    ApiError,
    Keys,
    TriggerAccepted,
    TriggerError,
    handle_trigger,
    new_job_id,
    parse_trigger,
)
from cellctl.api.session import build_zenoh_config, close_session, declare_async_queryable, open_session
from cellctl.config import ZenohSection
from cellctl.jobstore.jobs import JobRecord, JobStore
from tests.support.ports import free_port

CODES = {"too_large", "malformed", "invalid", "design_not_found"}
VALID = {"plate_id": "P-17", "design": "sail/plate1.stl", "placement": {"pos_mm": [1500.0, 0.0, 300.0]}}
VALID_BYTES = json.dumps(VALID).encode()
SEEDS = (
    VALID_BYTES,
    json.dumps(dict(VALID, note="n" * 100, placement={"pos_mm": [1, 2, 3], "rpy_deg": [0, 0, 3]})).encode(),
    json.dumps(dict(VALID, design="sail/../plate1.stl")).encode(),
)


@pytest.fixture(scope="module")
def designs(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("trig")
    d = root / "designs"
    (d / "sail").mkdir(parents=True)
    (d / "sail" / "plate1.stl").write_bytes(b"solid x\nendsolid x\n")
    (root / "secret.stl").write_text("outside")
    (d / "sail" / "escape.stl").symlink_to(root / "secret.stl")
    (d / "loop1.stl").symlink_to("loop2.stl")
    (d / "loop2.stl").symlink_to("loop1.stl")
    return d


def _check(payload: bytes, designs: Path) -> None:
    try:
        req, path = parse_trigger(payload, designs)
    except TriggerError as err:
        assert err.code in CODES and err.field and err.message, err
        return
    assert path.is_file() and path.is_relative_to(designs.resolve())
    assert req.design and all(abs(v) < float("inf") for v in req.placement.pos_mm)


def _absurd_numbers() -> st.SearchStrategy[bytes]:
    number = st.one_of(
        st.floats(allow_nan=True, allow_infinity=True),
        st.integers(min_value=-(10**30), max_value=10**30),
        st.sampled_from(["1e309", "-1e309", "NaN", "Infinity", "9" * 5000, "1" + "0" * 400, "-0"]),
    )

    def payload(values: tuple) -> bytes:
        pos = ", ".join(x if isinstance(x, str) else json.dumps(x) for x in values)
        return (
            '{"plate_id": "P-1", "design": "sail/plate1.stl", "placement": {"pos_mm": [' + pos + "]}}"
        ).encode()

    return st.tuples(number, number, number).map(payload)


_DESIGNS = st.one_of(
    st.text(max_size=300),
    st.sampled_from(
        ["../secret.stl", "sail/escape.stl", "loop1.stl", "é" * 200 + ".stl", "a/" * 120 + "b.stl", "sail/./plate1.stl",
         "/etc/passwd.stl", "sail//plate1.stl", "~root/x.stl", "sail/plate1.STL", "sail/plate1.stl\0.exe"]
    ),
)  # fmt: skip


@fuzz_settings(300)
@given(
    payload=st.one_of(
        st.sampled_from(SEEDS).flatmap(lambda s: mutated(s, SEEDS)),
        _absurd_numbers(),
        _DESIGNS.map(lambda d: json.dumps(dict(VALID, design=d)).encode()),
        st.recursive(st.none() | st.booleans() | st.floats() | st.text(max_size=10), lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=5), c, max_size=3)).map(lambda v: json.dumps(v).encode()),
        st.binary(max_size=MAX_TRIGGER_BYTES + 10),
    )
)  # fmt: skip
# found by fuzzing: each of these escaped parse_trigger as RecursionError, ValueError, OSError or RuntimeError
@example(payload=b"[" * 10_000)
@example(payload=b'{"plate_id": ' + b"9" * 5000 + b"}")
@example(payload=json.dumps(dict(VALID, design="é" * 200 + ".stl")).encode())
@example(payload=json.dumps(dict(VALID, design="loop1.stl")).encode())
def test_any_trigger_payload_is_a_valid_request_or_a_trigger_error_with_a_reason(payload, designs):
    _check(payload, designs)


def test_payload_over_the_limit_is_refused_before_parsing(designs):
    with pytest.raises(TriggerError) as err:
        parse_trigger(b" " * MAX_TRIGGER_BYTES + b"{}", designs)  # would parse, but is one byte too big
    assert err.value.code == "too_large"


# ------------------------------------------------------------------------------ the real queryable


class _Daemon:
    """The daemon's trigger queryable (real handler, real job store) on a loop in a background thread."""

    def __init__(self, designs: Path, data: Path) -> None:
        port = free_port()
        self.section = ZenohSection(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
        self.keys = Keys("cell/fuzz")
        self.store = JobStore(data)
        self.designs = designs
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.session = asyncio.run_coroutine_threadsafe(self._open(), self.loop).result(30)

    async def _open(self) -> zenoh.Session:
        session = open_session(build_zenoh_config(self.section, role="serve"))

        async def accept(req, path):
            rec = self.store.create(
                JobRecord(new_job_id(), req.plate_id, req.design, str(path), req.placement.model_dump())
            )
            return TriggerAccepted(job_id=rec.job_id, state="queued")

        declare_async_queryable(session, self.keys.trigger, lambda q: handle_trigger(q, self.designs, accept))
        return session

    def close(self) -> None:
        close_session(self.session)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


@pytest.fixture(scope="module")
def daemon_and_client(designs, tmp_path_factory):
    daemon = _Daemon(designs, tmp_path_factory.mktemp("data"))
    client = open_session(build_zenoh_config(daemon.section, role="connect"))
    try:
        yield daemon, client
    finally:
        close_session(client)
        daemon.close()


@fuzz_settings(20)
@given(payload=st.sampled_from(SEEDS[:1]).flatmap(lambda s: mutated(s, SEEDS)) | st.binary(max_size=200))
@example(payload=b"[" * 10_000)
@example(payload=b"z" * (MAX_TRIGGER_BYTES + 1))
def test_trigger_queryable_answers_every_mutated_payload_and_creates_a_job_only_when_accepted(
    payload, daemon_and_client
):
    daemon, client = daemon_and_client
    before = len(daemon.store.list())
    replies = list(client.get(daemon.keys.trigger, payload=payload, timeout=10))
    created = len(daemon.store.list()) - before
    assert len(replies) == 1, "no reply: the queryable died or hung"
    reply = replies[0]
    if reply.ok is not None:
        TriggerAccepted.model_validate_json(reply.ok.payload.to_bytes())
        assert created == 1
    else:
        err = ApiError.model_validate_json(reply.err.payload.to_bytes())
        assert err.code in CODES and err.message, err  # never "internal": every refusal names its reason
        assert created == 0
