"""One registry of profile sources, chosen by ``[laser] protocol`` (python-can's backend registry)."""

from __future__ import annotations

import sys

import pytest

from cellctl.config import LaserSection
from cellctl.daemon.wiring import laser_source
from drivers.laser.client import HD8Client
from drivers.laser.gige import GigeProfileSource
from drivers.laser.registry import (
    SOURCES,
    UnknownSourceError,
    available_sources,
    open_source,
    register_source,
    source_class,
)
from drivers.laser.source import ProfileSource


def test_both_built_in_sources_are_registered_and_are_profile_sources():
    assert {"hd8", "gige"} <= set(available_sources())
    assert source_class("hd8") is HD8Client and source_class("gige") is GigeProfileSource


def test_an_unknown_source_names_those_that_exist():
    with pytest.raises(UnknownSourceError, match=r"known: .*gige.*hd8"):
        source_class("gocator")


def test_a_registered_class_that_is_not_a_profile_source_is_refused(monkeypatch):
    monkeypatch.setattr("drivers.laser.registry.SOURCES", dict(SOURCES))
    register_source("not-a-source", "collections", "OrderedDict")
    with pytest.raises(TypeError, match="not a ProfileSource"):
        source_class("not-a-source")


def test_a_vendor_source_registers_beside_the_built_in_ones(tmp_path, monkeypatch):
    (tmp_path / "vendor_shim.py").write_text(
        "from drivers.laser.client import HD8Client\nclass VendorSource(HD8Client):\n    pass\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr("drivers.laser.registry.SOURCES", dict(SOURCES))
    register_source("vendor", "vendor_shim", "VendorSource")
    src = open_source("vendor", "127.0.0.1", 1, 2)
    assert isinstance(src, ProfileSource) and type(src).__name__ == "VendorSource"
    sys.modules.pop("vendor_shim", None)


def test_the_hd8_cell_gets_the_hd8_client_and_a_gige_cell_the_gige_source_with_its_settings():
    hd8 = laser_source(LaserSection())
    assert isinstance(hd8, HD8Client) and hd8.control_port == 3190
    las = LaserSection(
        protocol="gige", host="127.0.0.1", gige_device="Aravis-Fake-GV01", points_per_profile=640,
        gige_rows_per_buffer=250, gige_x_offset_px=32, gige_packet_size=8192, watchdog_s=0.7,
    )  # fmt: skip
    src = laser_source(las)
    assert isinstance(src, GigeProfileSource) and src.device == "Aravis-Fake-GV01"
    c = src.config
    assert (c.width, c.x_offset, c.rows_per_buffer, c.packet_size, c.watchdog_timeout_s) == (
        640, 32, 250, 8192, 0.7,
    )  # fmt: skip
    assert isinstance(laser_source(LaserSection(protocol="gige", host="10.0.0.7")), GigeProfileSource)
    assert laser_source(LaserSection(protocol="gige", host="10.0.0.7")).device == "10.0.0.7"


def test_a_protocol_the_cell_does_not_know_is_a_configuration_error():
    with pytest.raises(ValueError, match="protocol"):
        LaserSection(protocol="gocator")
