"""Fuzz the `cell.toml` loader (cellctl/config.py) and `cellctl config check`.

Random TOML documents over the real section and key names, and byte mutations of the shipped
cell.toml: the loader returns a configuration or raises ``ConfigError`` whose problems are one line
each; ``cellctl config check`` prints them and exits 2, never with a traceback.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from fuzzlib import fuzz_settings, mutated
from hypothesis import example, given
from hypothesis import strategies as st

from cellctl.cli import main as cli_main
from cellctl.config import CellConfig, ConfigError, load_config

REPO = Path(__file__).resolve().parents[2]
SHIPPED = (REPO / "cell.toml").read_bytes()
SECTIONS = {name: list(field.annotation.model_fields) for name, field in CellConfig.model_fields.items()}


@pytest.fixture(autouse=True)
def _no_cell_env(monkeypatch):
    # the environment overrides the file: keep the developer's CELL_* variables out of the property
    import os

    for key in [k for k in os.environ if k.startswith("CELL_")]:
        monkeypatch.delenv(key)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"


_leaf = st.one_of(
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(),
    st.text(max_size=30),
    st.sampled_from(
        ["tcp/127.0.0.1:7447", "http://127.0.0.1:8080", "auto", "peer", "rws2", "sail", "{cell_id}"]
    ),
)
_value = st.recursive(
    _leaf,
    lambda c: st.lists(c, max_size=7) | st.dictionaries(st.text(max_size=8), c, max_size=3),
    max_leaves=12,
)


@st.composite
def _document(draw: st.DrawFn) -> bytes:
    lines = []
    for section in draw(
        st.lists(st.sampled_from([*SECTIONS, "zenoh.access", "sim.faults", "bogus"]), max_size=4, unique=True)
    ):
        keys = [*SECTIONS.get(section.split(".")[0], []), "password", "unknown_key"]
        lines.append(f"[{section}]")
        for key in draw(st.lists(st.sampled_from(keys), max_size=5, unique=True)):
            lines.append(f"{key} = {_toml_value(draw(_value))}")
    return "\n".join(lines).encode()


def _check(tmp_path: Path, doc: bytes) -> None:
    path = tmp_path / "cell.toml"
    path.write_bytes(doc)
    try:
        cfg = load_config(path)
    except ConfigError as err:
        assert err.problems, err
        for problem in err.problems:
            assert problem and "\n" not in problem and "Traceback" not in problem, problem
        return
    assert isinstance(cfg, CellConfig)


@fuzz_settings(50)
@given(doc=_document())
# found by fuzzing: a key with a newline made a two-line problem (now escaped)
@example(doc=b'[sim]\nrws_users = {"a\\nb" = 1}\n[cell]\n"bad\\nkey" = 1\n')
def test_random_toml_documents_load_or_give_one_line_config_errors(doc, tmp_path):
    _check(tmp_path, doc)


@fuzz_settings(50)
@given(doc=mutated(SHIPPED))
# found by fuzzing: tomllib's RecursionError and the 4300-digit ValueError escaped load_config
@example(doc=b"a = " + b"[" * 3000 + b"]" * 3000)
@example(doc=b"[cell]\nid = " + b"9" * 5000)
@example(doc=b"a = {" + b"b = {" * 500 + b"}" * 501)
def test_mutated_shipped_cell_toml_loads_or_gives_one_line_config_errors(doc, tmp_path):
    _check(tmp_path, doc)


@fuzz_settings(12)
@given(doc=mutated(SHIPPED) | _document())
@example(doc=b"a = " + b"[" * 3000 + b"]" * 3000)
def test_config_check_exits_2_with_plain_lines_never_a_traceback(doc, tmp_path, capsys):
    path = tmp_path / "cell.toml"
    path.write_bytes(doc)
    rc = cli_main(["config", "check", str(path)])
    out, err = capsys.readouterr()
    assert rc in (0, 2)
    assert "Traceback" not in out + err
    if rc == 2:
        assert err.strip() and all(line.startswith(str(path)) for line in err.strip().splitlines())
    else:
        assert out.strip() == "ok"
