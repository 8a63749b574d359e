"""Trigger payload limits: size at the byte, absurd numbers, design paths that try to leave designs_dir."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from cellctl.api import MAX_TRIGGER_BYTES, TriggerError, parse_trigger


@pytest.fixture
def designs(tmp_path: Path) -> Path:
    d = tmp_path / "designs"
    (d / "sail").mkdir(parents=True)
    (d / "sail" / "plate1.stl").write_bytes(b"solid x\nendsolid x\n")
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.stl").write_text("confidential")
    (d / "escape").symlink_to(outside, target_is_directory=True)  # a symlinked directory
    (d / "zero.stl").symlink_to("/dev/zero")
    (d / "folder.stl").mkdir()
    os.mkfifo(d / "pipe.stl")
    return d


def _req(**over) -> dict:
    body = {"plate_id": "P-17", "design": "sail/plate1.stl", "placement": {"pos_mm": [1500.0, 0.0, 300.0]}}
    body.update(over)
    return body


def _refused(body: dict | bytes, designs: Path) -> TriggerError:
    raw = body if isinstance(body, bytes) else json.dumps(body).encode()
    with pytest.raises(TriggerError) as err:
        parse_trigger(raw, designs)
    assert err.value.message
    return err.value


def test_a_payload_of_exactly_the_limit_is_read_and_one_byte_more_is_refused_unparsed(designs):
    body = json.dumps(_req()).encode()
    exact = body[:-1] + b" " * (MAX_TRIGGER_BYTES - len(body)) + b"}"
    assert len(exact) == MAX_TRIGGER_BYTES
    req, _ = parse_trigger(exact, designs)
    assert req.plate_id == "P-17"
    err = _refused(exact[:-1] + b" }", designs)
    assert (err.code, err.field) == ("too_large", "payload")


@pytest.mark.parametrize(
    ("placement", "field"),
    [
        ({"pos_mm": [1e308, 0, 0]}, "placement.pos_mm.0"),
        ({"pos_mm": [0, -1e6, 0]}, "placement.pos_mm.1"),
        ({"pos_mm": [0, 0, 0], "rpy_deg": [0, 0, 1e9]}, "placement.rpy_deg.2"),
        ({"pos_mm": [0, 0, "NaN"]}, "placement.pos_mm.2"),
        ({"pos_mm": [0, 0, 10**400]}, "placement.pos_mm.2"),
    ],
)
def test_absurd_placement_numbers_are_refused_before_any_job_exists(designs, placement, field):
    err = _refused(_req(placement=placement), designs)
    assert (err.code, err.field) == ("invalid", field)


@pytest.mark.parametrize(
    ("design", "code"),
    [
        ("escape/secret.stl", "invalid"),  # through a symlinked directory
        ("zero.stl", "invalid"),  # a symlink to a device outside
        ("sail/../../outside/secret.stl", "invalid"),
        ("sail/%2e%2e/plate1.stl", "design_not_found"),  # no URL decoding: just an odd name
        ("folder.stl", "design_not_found"),  # a directory is not a design
        ("pipe.stl", "design_not_found"),  # nor a FIFO (reading it would block the daemon)
        ("SAIL/plate1.stl", "design_not_found"),
    ],
)
def test_design_paths_that_leave_designs_dir_or_name_no_regular_file_are_refused(designs, design, code):
    err = _refused(_req(design=design), designs)
    assert (err.code, err.field) == (code, "design")


def test_the_refusal_names_the_field_but_never_echoes_a_file_outside(designs):
    err = _refused(_req(design="escape/secret.stl"), designs)
    # neither the file's content nor where the symlink really points is told to the caller
    assert "confidential" not in str(err) and str(designs.parent / "outside") not in str(err)


def _largest_valid_trigger(rows: int) -> bytes:
    """The largest trigger the model accepts, as the most verbose JSON encoder writes it: every
    string at its longest in characters that escape longest (astral characters as two \\uXXXX
    escapes, "/" as "\\/"), every number with the most digits, ``rows`` template rows."""
    astral = "\U0001f6a2"  # a ship: 12 bytes escaped
    row = {
        "name": "/" * 40,
        "edge": "0-3",
        "distance_mm": 1.2345678901234567e-05,
        "angle_deg": 30.000000000000004,
    }
    body = {
        "plate_id": "P" * 64,
        "design": astral * 251 + ".stl",
        "placement": {"pos_mm": [-1.2345678901234567e-05] * 3, "rpy_deg": [-1.2345678901234567e-05] * 3},
        "note": astral * 500,
        "template_table": [{**row, "name": f"{k:03d}" + "/" * 37} for k in range(rows)],
        "design_side": "moulded_down",
        "thickness_mm": 1.2345678901234567e-05,
    }
    return json.dumps(body).replace("/", "\\/").encode()


def test_the_largest_valid_trigger_with_200_template_rows_fits_the_size_limit(designs: Path) -> None:
    from cellctl.api.models import TriggerRequest

    raw = _largest_valid_trigger(200)
    req = TriggerRequest.model_validate_json(raw)  # valid in every field (the design file aside)
    assert len(req.template_table) == 200 and len(req.note) == 500
    assert len(raw) <= MAX_TRIGGER_BYTES, (len(raw), MAX_TRIGGER_BYTES)
    # and a real one through parse_trigger: a full table of 200 rows is accepted
    rows = [{"name": f"FR{k}", "edge": "0-3", "distance_mm": 5.0 * k, "angle_deg": 90.0} for k in range(200)]
    req, _ = parse_trigger(json.dumps(_req(template_table=rows)), designs)
    assert len(req.template_table) == 200


def test_a_template_table_of_201_rows_or_a_bad_row_is_refused_by_name(designs: Path) -> None:
    rows = [{"name": f"FR{k}", "edge": "0-3", "distance_mm": 5.0 * k} for k in range(201)]
    err = _refused(_req(template_table=rows), designs)
    assert (err.code, err.field) == ("invalid", "template_table"), err
    assert "at most 200" in err.message, err.message
    for bad, words in (
        ({"name": "x" * 41, "edge": "0-3", "distance_mm": 1.0}, ("row 1", "at most 40")),
        ({"name": 'say "hi"', "edge": "0-3", "distance_mm": 1.0}, ("row 1", "printable ASCII")),
        ({"name": "FR1", "edge": "0-3", "distance_mm": float("nan")}, ("row 1", "distance")),
        ({"name": "FR1", "edge": "0-3", "distance_mm": 1.0, "angle_deg": 10.0}, ("row 1", "30..150")),
    ):
        err = _refused(_req(template_table=[bad]), designs)
        assert err.field == "template_table" and all(w in err.message for w in words), err.message
    twice = [
        {"name": "FR1", "edge": "0-3", "distance_mm": 1.0},
        {"name": "FR1", "edge": "1-2", "distance_mm": 2.0},
    ]
    assert "appears twice" in _refused(_req(template_table=twice), designs).message
