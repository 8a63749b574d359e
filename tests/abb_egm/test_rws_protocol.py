"""RWS's words (resource paths, media types, controller states) have one home,
drivers/abb_egm/rws_protocol.py, which the client, the simulator and the daemon share."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from drivers.abb_egm import rws_protocol as rw

REPO = Path(__file__).resolve().parents[2]
#: the modules that speak RWS (besides the vocabulary itself)
SPEAKERS = [
    "drivers/abb_egm/rws_client.py",
    "drivers/abb_egm/cell_egm.py",
    "drivers/abb_egm/sim/rws_server.py",
    "drivers/abb_egm/sim/model.py",
    "cellctl/config.py",
    # the daemon, and the job store split out of it (issue 45)
    *sorted(
        str(p.relative_to(REPO)) for d in ("daemon", "jobstore") for p in (REPO / "cellctl" / d).glob("*.py")
    ),
]
STATE_WORDS = set(rw.CTRL_STATES) | set(rw.OPMODES)


def _vocabulary_literals(path: str) -> list[str]:
    """String literals of ``path`` that spell an RWS resource, a media type or a controller state
    (docstrings aside: they explain the words, they do not use them). Media types count in the
    drivers only: the daemon's are Zenoh encodings, not RWS's."""
    media = path.startswith("drivers/")
    tree = ast.parse((REPO / path).read_text(encoding="utf-8"))
    docstrings = {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }
    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Constant) and isinstance(node.value, str)) or id(node) in docstrings:
            continue
        v = node.value
        if (
            v.startswith(("/rw", "/subscription", "/logout", "/poll/"))
            or v in STATE_WORDS
            or (media and v.startswith("application/"))
        ):
            found.append(f"{path}:{node.lineno}: {v!r}")
    return found


@pytest.mark.parametrize("path", SPEAKERS)
def test_rws_speakers_spell_no_resource_media_type_or_state_themselves(path: str) -> None:
    found = _vocabulary_literals(path)
    assert not found, "use drivers/abb_egm/rws_protocol.py:\n" + "\n".join(found)


def test_the_check_finds_a_spelled_out_path_and_state(tmp_path: Path, monkeypatch) -> None:
    planted = tmp_path / "planted.py"
    planted.write_text(
        '"""Reads /rw/panel/opmode."""\nPATH = "/rw/panel/opmode"\nif s == "motoron":\n    pass\n'
    )
    monkeypatch.setattr(f"{__name__}.REPO", tmp_path)
    assert _vocabulary_literals("planted.py") == [
        "planted.py:2: '/rw/panel/opmode'",
        "planted.py:3: 'motoron'",
    ]


@pytest.mark.parametrize(
    ("profile", "module", "expected"),
    [
        ("rws1", None, "/rw/rapid/symbol/data/RAPID/T_ROB1/egm_end"),
        ("rws1", "CellEgm", "/rw/rapid/symbol/data/RAPID/T_ROB1/CellEgm/egm_end"),
        ("rws2", None, "/rw/rapid/symbol/RAPID/T_ROB1/egm_end/data"),
        ("rws2", "CellEgm", "/rw/rapid/symbol/RAPID/T_ROB1/CellEgm/egm_end/data"),
    ],
)
def test_symbol_path_spells_each_profile(profile, module, expected) -> None:
    assert rw.symbol_path(profile, "T_ROB1", "egm_end", module) == expected


def test_paths_quote_the_names_a_caller_gives() -> None:
    assert rw.symbol_path("rws1", "T ROB", "a/b") == "/rw/rapid/symbol/data/RAPID/T%20ROB/a%2Fb"
    assert rw.signal_path("do 1", "Local", "DRV_1") == "/rw/iosystem/signals/Local/DRV_1/do%201"
    assert rw.task_path("T/ROB1") == "/rw/rapid/tasks/T%2FROB1"


def test_profile_dependent_and_composed_paths() -> None:
    assert rw.ctrl_state_path("rws1") == "/rw/panel/ctrlstate"
    assert rw.ctrl_state_path("rws2") == "/rw/panel/ctrl-state"
    assert rw.execution_action_path("resetpp") == "/rw/rapid/execution/resetpp"
    assert rw.elog_path(0) == "/rw/elog/0" and rw.elog_path(0, 17) == "/rw/elog/0/17"
    assert rw.mechunit_path("ROB_1", "jointtarget") == "/rw/motionsystem/mechunits/ROB_1/jointtarget"
    assert rw.EXECUTION_SUBSCRIPTION == "/rw/rapid/execution;ctrlexecstate"
    assert rw.symbol_subscription("T_ROB1", "egm_end") == "/rw/rapid/symbol/data/RAPID/T_ROB1/egm_end;value"
    assert rw.signal_subscription("do1") == "/rw/iosystem/signals/do1;state"
    assert rw.V2 in rw.HAL_JSON_V2 and rw.V2 in rw.XHTML_V2 and rw.V2 in rw.FORM_V2
