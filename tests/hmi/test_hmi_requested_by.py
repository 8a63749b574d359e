"""The HMI passes the logged-in user with each trigger and control (issue 43, item 5): the body the
cell gets names ``requested_by``, the user the HMI authenticated, whatever the page sent. One HMI
server in this process with the fake link (tests/support/hmi_server.py, no cell)."""

from __future__ import annotations

import json

import aiohttp

from cellctl.api import ControlReply, TriggerAccepted
from cellctl.hmi.server import COOKIE
from tests.support.hmi_server import USERS, LocalHmi


def test_triggers_and_controls_reach_the_cell_with_the_logged_in_user(tmp_path) -> None:
    with LocalHmi(tmp_path) as hmi:
        s = hmi.auth.login("olga", USERS["olga"][1])
        assert s is not None
        hmi.link.replies += [
            TriggerAccepted(job_id="20260101T000000-aaaa0001", state="started"),
            ControlReply(action="abort", job_id="20260101T000000-aaaa0001", state="scanning"),
            ControlReply(action="pause", job_id=None, state="paused"),
        ]

        async def post_all() -> list[int]:
            headers = {"X-CSRF-Token": s.csrf, "Content-Type": "application/json"}
            statuses = []
            async with aiohttp.ClientSession(cookies={COOKIE: s.token}, headers=headers) as http:
                for path, body in [
                    ("/api/trigger", {"plate_id": "P1", "design": "p.ply"}),
                    ("/api/control/abort", {"job_id": "20260101T000000-aaaa0001", "requested_by": "mallory"}),
                    ("/api/control/pause", None),  # an empty body
                ]:
                    data = b"" if body is None else json.dumps(body).encode()
                    async with http.post(hmi.url + path, data=data) as r:
                        statuses.append(r.status)
            return statuses

        statuses = hmi.run(post_all())
        sent = [(what, json.loads(body)) for what, body in hmi.link.sent]
    assert statuses == [200, 200, 200]
    assert sent == [
        ("trigger", {"plate_id": "P1", "design": "p.ply", "requested_by": "olga"}),
        ("abort", {"job_id": "20260101T000000-aaaa0001", "requested_by": "olga"}),  # not the page's "mallory"
        ("pause", {"requested_by": "olga"}),
    ]
