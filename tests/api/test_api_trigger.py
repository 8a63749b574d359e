"""Trigger payloads: every kind of bad request is refused with a clear error naming the field."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cellctl.api import (
    MAX_TRIGGER_BYTES,
    ApiCallError,
    ControlError,
    ControlRequest,
    Keys,
    TriggerAccepted,
    TriggerError,
    TriggerRequest,
    call,
    handle_trigger,
    parse_control,
    parse_trigger,
)
from cellctl.api.session import (
    build_zenoh_config,
    close_session,
    declare_async_queryable,
    open_session,
)


@pytest.fixture
def designs(tmp_path: Path) -> Path:
    d = tmp_path / "designs"
    (d / "sail").mkdir(parents=True)
    (d / "sail" / "plate1.stl").write_bytes(b"solid x\nendsolid x\n")
    (tmp_path / "secret.stl").write_text("outside")
    return d


def _req(**over) -> bytes:
    body = {"plate_id": "P-17", "design": "sail/plate1.stl", "placement": {"pos_mm": [1500, 0, 300]}}
    body.update(over)
    return json.dumps(body).encode()


def test_valid_trigger_resolves_the_design_inside_designs_dir(designs):
    req, path = parse_trigger(_req(), designs)
    assert req.plate_id == "P-17" and req.placement.rpy_deg == [0.0, 0.0, 0.0]
    assert path == (designs / "sail" / "plate1.stl").resolve()


@pytest.mark.parametrize(
    ("payload", "code", "field"),
    [
        (b"", "malformed", "payload"),
        (b"{not json", "malformed", "payload"),
        (b"\xff\xfe", "malformed", "payload"),
        (b"[1, 2]", "malformed", "payload"),
        (b"x" * (MAX_TRIGGER_BYTES + 1), "too_large", "payload"),
        (_req(colour="red"), "invalid", "colour"),
        (_req(placement={"pos_mm": [1, 2, 3], "speed": 4}), "invalid", "placement.speed"),
        (_req(placement={"pos_mm": [1, 2]}), "invalid", "placement.pos_mm"),
        (_req(plate_id="../x"), "invalid", "plate_id"),
        (_req(design="../secret.stl"), "invalid", "design"),
        (_req(design="./x.ply"), "invalid", "design"),  # issue 24: "." components were let through
        (_req(design="a/./b.ply"), "invalid", "design"),
        (_req(design="sail/../../secret.stl"), "invalid", "design"),
        (_req(design="/etc/passwd.stl"), "invalid", "design"),
        (_req(design="~/x.stl"), "invalid", "design"),
        (_req(design="sail\\..\\..\\secret.stl"), "invalid", "design"),
        (_req(design="sail/plate1.exe"), "invalid", "design"),
        (_req(design="sail/missing.stl"), "design_not_found", "design"),
    ],
)
def test_bad_trigger_is_refused_naming_the_field(designs, payload, code, field):
    with pytest.raises(TriggerError) as err:
        parse_trigger(payload, designs)
    assert (err.value.code, err.value.field) == (code, field)
    assert field in str(err.value)


def test_symlink_escaping_designs_dir_is_refused(designs):
    (designs / "sail" / "link.stl").symlink_to(designs.parent / "secret.stl")
    with pytest.raises(TriggerError, match="outside designs_dir"):
        parse_trigger(_req(design="sail/link.stl"), designs)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    body=st.one_of(
        st.binary(max_size=300),
        st.dictionaries(
            st.sampled_from(["plate_id", "design", "placement", "note", "x"]),
            st.one_of(st.text(max_size=40), st.integers(), st.none(), st.lists(st.floats(), max_size=4)),
        ).map(lambda d: json.dumps(d).encode()),
    )
)
def test_arbitrary_payloads_raise_only_trigger_error(designs, body):
    try:
        req, path = parse_trigger(body, designs)
    except TriggerError as err:
        assert err.code in ("malformed", "invalid", "too_large", "design_not_found")
        return
    assert isinstance(req, TriggerRequest) and path.is_relative_to(designs.resolve())


def test_trigger_queryable_answers_errors_and_keeps_serving_over_zenoh(hub, designs):
    """Through Zenoh: refused requests get ApiError replies and never reach ``accept``; a valid one does."""
    accepted: list[TriggerRequest] = []

    async def accept(req: TriggerRequest, path: Path) -> TriggerAccepted:
        accepted.append(req)
        return TriggerAccepted(job_id=f"job-{len(accepted)}", state="started")

    async def main():
        keys = Keys(hub.prefix)
        daemon = open_session(build_zenoh_config(hub.section, role="serve"))
        client = None
        try:
            declare_async_queryable(daemon, keys.trigger, lambda q: handle_trigger(q, designs, accept))
            client = open_session(build_zenoh_config(hub.section, role="connect"))
            out = []
            for payload in (
                b"{bad",
                _req(colour="red"),
                _req(design="../secret.stl"),
                b"y" * (MAX_TRIGGER_BYTES + 1),
                _req(),
            ):
                try:
                    out.append(await call(client, keys.trigger, payload, TriggerAccepted, timeout_s=5))
                except ApiCallError as exc:
                    out.append(exc.error)
            with pytest.raises(ApiCallError, match="no reply within 1 s"):
                await call(client, keys.control("pause"), None, TriggerAccepted, timeout_s=1)
            return out
        finally:
            close_session(client)
            close_session(daemon)

    out = asyncio.run(main())
    assert [(o.code, o.field) for o in out[:4]] == [
        ("malformed", "payload"),
        ("invalid", "colour"),
        ("invalid", "design"),
        ("too_large", "payload"),
    ]
    assert out[4] == TriggerAccepted(job_id="job-1", state="started")
    assert [r.plate_id for r in accepted] == ["P-17"]


@pytest.mark.parametrize("payload", [None, b"", b"{}"])
def test_empty_control_payload_means_the_scan_in_progress(payload):
    assert parse_control(payload) == ControlRequest(job_id=None)


def test_control_payload_names_its_job():
    assert parse_control(b'{"job_id": "20261122T044528-c86cf189"}').job_id == "20261122T044528-c86cf189"


@pytest.mark.parametrize(
    ("payload", "code", "field"),
    [
        (b"{oops", "malformed", "payload"),
        (b"[1]", "malformed", "payload"),
        (b"\xff", "malformed", "payload"),
        (b"x" * (MAX_TRIGGER_BYTES + 1), "too_large", "payload"),
        (b'{"job_id": "x", "force": true}', "invalid", "force"),
        (b'{"job_id": "../../etc"}', "invalid", "job_id"),
        (b'{"job_id": 7}', "invalid", "job_id"),
    ],
)
def test_bad_control_payload_is_refused_naming_the_field(payload, code, field):
    with pytest.raises(ControlError) as err:
        parse_control(payload)
    assert (err.value.code, err.value.field) == (code, field)
    assert err.value.to_api_error().code == code


@settings(max_examples=200, deadline=None)
@given(
    body=st.one_of(
        st.binary(max_size=200),
        st.dictionaries(st.text(max_size=10), st.text(max_size=70)).map(lambda d: json.dumps(d).encode()),
    )
)
def test_arbitrary_control_payloads_raise_only_control_error(body):
    try:
        req = parse_control(body)
    except ControlError as err:
        assert err.code in ("malformed", "invalid", "too_large")
        return
    assert req.job_id is None or "/" not in req.job_id
