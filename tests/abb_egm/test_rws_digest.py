"""Digest auth (RFC 2617, MD5, qop=auth): the client's answer against the server's check, no sockets."""

from __future__ import annotations

import base64

from aiohttp.test_utils import make_mocked_request
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.abb_egm.digest import parse_auth_params
from drivers.abb_egm.rws_client import _DigestState
from drivers.abb_egm.sim.model import ControllerModel
from drivers.abb_egm.sim.rws_server import RwsServer
from tests.conftest import SHARED

# User names and passwords as a controller's UAS allows them: printable, no double quote.
text = st.text(
    alphabet=st.characters(min_codepoint=33, max_codepoint=126, exclude_characters='"\\'),
    min_size=1,
    max_size=20,
)
uris = st.sampled_from(
    ["/rw/panel/ctrlstate?json=1", "/rw/rapid/execution?action=start&json=1", "/logout?json=1"]
)


def _server(user: str, password: str) -> RwsServer:
    return RwsServer(ControllerModel(), profile="rws1", users={user: password})


@settings(max_examples=50, deadline=None)
@given(user=text, password=text, uri=uris, method=st.sampled_from(["GET", "POST"]))
def test_client_digest_answer_is_accepted_for_the_right_password(
    user: str, password: str, uri: str, method: str
) -> None:
    server = _server(user, password)
    state = _DigestState(parse_auth_params(server._challenge()[7:]))
    header = state.header(method, uri, user, password)
    req = make_mocked_request(method, uri, headers={"Authorization": header})
    assert server._check_authorization(req) == (user, False)


@settings(max_examples=50, deadline=None)
@given(user=text, password=text, wrong=text)
def test_client_digest_answer_is_refused_for_a_wrong_password(user: str, password: str, wrong: str) -> None:
    if wrong == password:
        wrong += "x"
    server = _server(user, password)
    state = _DigestState(parse_auth_params(server._challenge()[7:]))
    uri = "/rw/panel/ctrlstate?json=1"
    req = make_mocked_request("GET", uri, headers={"Authorization": state.header("GET", uri, user, wrong)})
    assert server._check_authorization(req) == (None, False)


def test_challenge_has_the_fields_of_the_captured_irc5_challenge() -> None:
    """Same fields and values as the RobotWare 6 challenge in ../shared/testdata/rws/headers/."""
    challenge = (
        SHARED / "testdata/rws/headers/rws1_401_digest_challenge_and_authorization.from_wireshark_comment.txt"
    )
    captured_line = next(ln for ln in challenge.read_text().splitlines() if ln.startswith("# Digest realm"))
    captured = parse_auth_params(captured_line[len("# Digest ") :])
    ours = _server("u", "p")._challenge()
    assert ours.startswith("Digest ")
    p = parse_auth_params(ours[7:])
    assert p.keys() == captured.keys()
    for key in ("realm", "domain", "qop", "opaque", "algorithm", "stale"):
        assert p[key] == captured[key], key
    # the nonce has the controller's form: base64 of "<hex>:<realm>:<hex time>:0"
    decoded = base64.b64decode(p["nonce"]).decode().split(":")
    assert decoded[1:2] == [captured["realm"]] and decoded[-1] == "0"
    assert base64.b64decode(captured["nonce"]).decode().split(":")[1] == captured["realm"]


def test_client_answer_reproduces_the_captured_irc5_authorization() -> None:
    """The client's digest answer to the captured challenge, with the captured cnonce, is the captured
    response hash (Default User / robotics)."""
    lines = (
        (
            SHARED
            / "testdata/rws/headers/rws1_401_digest_challenge_and_authorization.from_wireshark_comment.txt"
        )
        .read_text()
        .splitlines()
    )
    challenge = parse_auth_params(next(ln for ln in lines if ln.startswith("# Digest realm"))[9:])
    answer = parse_auth_params(next(ln for ln in lines if ln.startswith("# Digest username"))[9:])
    state = _DigestState(challenge)
    ours = parse_auth_params(
        state.header("GET", answer["uri"], "Default User", "robotics", cnonce=answer["cnonce"])[7:]
    )
    assert ours["response"] == answer["response"]
    assert ours["nc"] == answer["nc"] and ours["opaque"] == answer["opaque"]


def test_rfc2617_example_response() -> None:
    """The worked example of RFC 2617 section 3.5 (Mufasa / Circle Of Life) gives the RFC's response."""
    state = _DigestState(
        {
            "realm": "testrealm@host.com",
            "qop": "auth",
            "nonce": "dcd98b7102dd2f0e8b11d0f600bfb0c093",
            "opaque": "x",
        }
    )
    header = state.header("GET", "/dir/index.html", "Mufasa", "Circle Of Life", cnonce="0a4f113b")
    p = parse_auth_params(header[7:])
    assert p["response"] == "6629fae49393a05397450978507c4ef1"
    assert p["nc"] == "00000001" and p["uri"] == "/dir/index.html" and p["opaque"] == "x"
    second = parse_auth_params(state.header("GET", "/dir/index.html", "Mufasa", "Circle Of Life")[7:])
    assert second["nc"] == "00000002"
