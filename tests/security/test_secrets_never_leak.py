"""Secrets (the RWS and Zenoh passwords) never leave their environment variable or secrets file.

A whole job runs in real processes (`cellctl sim`, `cellctl run`, `cellctl worker`) with known,
unique secret values: the RWS password from the environment, the Zenoh password from a secrets file
(and the dictionary), access control on. Afterwards every log line, every file under the data
directory (job.json, report.json, results, raw files), every error reply and every state, event and
report publication is searched for them.
"""

from __future__ import annotations

import asyncio
import json
import uuid
from pathlib import Path

import pytest

from cellctl.api import ApiCallError, Keys, TriggerAccepted, call
from cellctl.api.session import close_session, subscribe
from cellctl.commands.demo_cmd import DEMO_DESIGN
from cellctl.commands.scan_cmd import StatusFollower, wait_for_job
from cellctl.config import load_config
from tests.support.e2e_cell import Cell, open_client, tiny_cell_config, wait_status

pytestmark = pytest.mark.slow


def _files_under(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.is_file()]


def test_a_job_run_leaks_neither_password_to_logs_files_replies_or_publications(tmp_path, monkeypatch):
    rws_secret = f"rws-{uuid.uuid4().hex}"
    zenoh_secret = f"zen-{uuid.uuid4().hex}"
    out = tmp_path / "cell"
    config = tiny_cell_config(out)
    secrets = tmp_path / "secrets"
    secrets.mkdir(mode=0o700)
    pw_file = secrets / "zenoh.secret"
    pw_file.write_text(zenoh_secret + "\n")
    pw_file.chmod(0o600)
    dictionary = secrets / "zenoh-users.txt"
    dictionary.write_text(f"cellctl:{zenoh_secret}\n")
    dictionary.chmod(0o600)
    env = {
        "CELL_RWS_PASSWORD": rws_secret,
        "CELL_ZENOH__ACCESS__ENABLED": "true",
        "CELL_ZENOH__ACCESS__PASSWORD_FILE": str(pw_file),
        "CELL_ZENOH__ACCESS__DICTIONARY_FILE": str(dictionary),
    }
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    cell = Cell(out, config)
    cell.procs.env.update(env)
    cell.cfg = load_config(config)  # with the environment's access settings, for our own client
    assert cell.cfg.zenoh.access.enabled
    published: list[bytes] = []
    replies: list[str] = []

    async def go():
        session = await open_client(cell.cfg)
        keys = Keys(cell.cfg.key_prefix)
        follower = StatusFollower(session, keys)
        subs = [
            subscribe(session, key, lambda s: published.append(s.payload.to_bytes()))
            for key in (keys.state, keys.report("*"), keys.job_event("*"))
        ]
        try:
            await wait_status(follower, lambda s: s.state.value == "idle" and s.workers, 180.0)
            pl = cell.cfg.sim.placement
            req = {"plate_id": "secret-plate", "design": DEMO_DESIGN,
                   "placement": {"pos_mm": list(pl.pos_mm), "rpy_deg": [0.0, 0.0, pl.angle_deg]}}  # fmt: skip
            with pytest.raises(ApiCallError) as refused:
                await call(
                    session, keys.trigger, json.dumps(dict(req, design="../zenoh.secret")), TriggerAccepted
                )
            replies.append(str(refused.value))
            acc = await call(session, keys.trigger, json.dumps(req), TriggerAccepted)
            replies.append(acc.model_dump_json())
            state, message, _ = await wait_for_job(follower, acc.job_id, 300.0)
            replies.append(message)
            return acc.job_id, state
        finally:
            for s in subs:
                s.undeclare()
            follower.close()
            await asyncio.to_thread(close_session, session)

    cell.start()
    try:
        job_id, state = asyncio.run(go())
    finally:
        codes = cell.stop()
    assert state == "done", (state, codes)
    job_dir = Path(cell.cfg.cell.data_dir) / "jobs" / job_id
    assert (job_dir / "job.json").is_file() and (job_dir / "report.json").is_file()
    searched = {
        "logs": _files_under(out / "logs"),
        "data": _files_under(Path(cell.cfg.cell.data_dir)),
    }
    assert searched["logs"] and len(searched["data"]) >= 3
    assert published and replies
    for secret in (rws_secret, zenoh_secret):
        needle = secret.encode()
        for where, files in searched.items():
            leaked = [str(p) for p in files if needle in p.read_bytes()]
            assert not leaked, f"{where}: {leaked}"
        assert not [p for p in published if needle in p]
        assert not [r for r in replies if secret in r]
