"""Property tests over the wire: RAPID values survive form encoding, JSON and XHTML events."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.abb_egm.rapid_values import format_string
from drivers.abb_egm.rws_client import RwsClient, RwsClientConfig, parse_event_xhtml
from drivers.abb_egm.sim.model import ControllerModel
from drivers.abb_egm.sim.rws_server import RwsServer

T = "T_ROB1"
# RAPID strings: up to 80 characters of the controller's Latin-1 set, without control characters.
rapid_text = st.text(
    alphabet=st.characters(min_codepoint=32, max_codepoint=255, blacklist_categories=("Cc",)), max_size=80
)


class _Cell:
    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.model = ControllerModel()
        self.model.define_var(T, "CellEgm", "note", "string", '""')
        self.server = RwsServer(self.model, profile="rws1")
        self.loop.run_until_complete(self.server.start())
        self.client = RwsClient(RwsClientConfig(base_url=self.server.base_url))

    def run(self, coro):
        return self.loop.run_until_complete(asyncio.wait_for(coro, 10))

    def close(self) -> None:
        self.run(self.client.close())
        self.run(self.server.stop())
        self.loop.close()


@pytest.fixture(scope="module")
def cell() -> Iterator[_Cell]:
    c = _Cell()
    yield c
    c.close()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(value=rapid_text)
def test_rapid_string_survives_the_round_trip_over_http(cell: _Cell, value: str) -> None:
    cell.run(cell.client.set_rapid_string(T, "note", value))
    assert cell.model.get_string(T, None, "note") == value
    assert cell.run(cell.client.get_rapid_string(T, "note")) == value


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(q=st.lists(st.floats(-400, 400, allow_nan=False), min_size=6, max_size=6), t=st.floats(0.004, 1e6))
def test_num_and_jointtarget_survive_the_round_trip_over_http(cell: _Cell, q: list[float], t: float) -> None:
    cell.run(cell.client.set_rapid_num(T, "egm_cond_time_s", t))
    assert cell.run(cell.client.get_rapid_num(T, "egm_cond_time_s")) == pytest.approx(t, rel=1e-8)
    cell.model.define_var(T, "CellEgm", "jt", "jointtarget", "[[0,0,0,0,0,0],[0,0,0,0,0,0]]")
    cell.run(cell.client.set_rapid_jointtarget(T, "jt", np.array(q)))
    got = cell.run(cell.client.get_rapid_jointtarget(T, "jt"))
    np.testing.assert_allclose(got.robax_deg, q, rtol=1e-8, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(value=rapid_text)
def test_subscription_event_carries_any_rapid_value(value: str) -> None:
    server = RwsServer(ControllerModel(), profile="rws1")
    literal = format_string(value)
    key, fragment = server._event_for(
        "rapid-data", {"task": T, "module": "CellEgm", "name": "note", "value": literal}
    )  # type: ignore[misc]
    assert key == f"rapid:{T}:note"
    (change,) = parse_event_xhtml(fragment)
    assert (change.kind, change.name, change.value) == ("rapid-data", "note", literal)
