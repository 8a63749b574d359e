"""A GenICam description that makes Aravis's fake GigE Vision device a 3D profiler.

Aravis's fake device (``arv-fake-gv-camera-0.8``, or :class:`Aravis.GvFakeCamera` in-process) is a
plain area camera: its description has no SFNC Scan3dControl. :func:`profiler_genicam_xml` takes the
installed Aravis's own description (so every register still matches the fake device's) and adds:

* ``DeviceScanType`` = Linescan3D, ``Scan3dDistanceUnit`` = Millimeter, ``Scan3dOutputMode`` =
  RectifiedC (enumerations over zeroed, read-only spare registers: their entry 0);
* ``Scan3dCoordinateSelector`` (a read-write spare register) selecting A, B or C, and
  ``Scan3dCoordinateScale`` / ``Scan3dCoordinateOffset`` as formulas of it (constants per axis);
* ``Scan3dInvalidDataFlag`` / ``Scan3dInvalidDataValue`` (raw 0 = no return);
* ``AcquisitionLineRate`` = Height / frame period, the profile rate of a line-scan profiler.

The fake device's fill callback (or its stock diagonal ramp) then provides the Mono16 range rows.
"""

from __future__ import annotations

import functools
import re

__all__ = ["SELECTOR_REGISTER", "fake_camera_xml", "profiler_genicam_xml"]

#: spare registers of the fake device's memory (0x10000 bytes; Aravis uses the first 0x1000)
SELECTOR_REGISTER = 0x8000
_ENUM_REGISTER = 0x8004


@functools.cache
def fake_camera_xml() -> str:
    """The installed Aravis's own fake-device description."""
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    xml = Aravis.FakeCamera.new("xml").get_genicam_xml()
    return xml[0] if isinstance(xml, tuple) else xml


def _num(v: float) -> str:
    return f"({v!r})" if v >= 0 else f"(0 - {-v!r})"


def profiler_genicam_xml(
    *,
    a_scale_mm: float,
    a_offset_mm: float,
    c_scale_mm: float,
    c_offset_mm: float,
    invalid_value: int = 0,
    base_xml: str | None = None,
) -> str:
    """The fake device's description plus the Scan3dControl features (see the module docstring)."""
    base = fake_camera_xml() if base_xml is None else base_xml

    def by_axis(a: float, c: float) -> str:
        return f"(SEL = 0) ? {_num(a)} : ((SEL = 2) ? {_num(c)} : (0))"

    def enum(name: str, entries: list[str]) -> str:
        body = "".join(
            f'<EnumEntry Name="{e}" NameSpace="Standard"><Value>{i}</Value></EnumEntry>'
            for i, e in enumerate(entries)
        )
        return f'<Enumeration Name="{name}" NameSpace="Standard">{body}<pValue>Scan3dConstantRegister</pValue></Enumeration>'

    nodes = f"""
	<Category Name="Scan3dControl" NameSpace="Standard">
		<pFeature>DeviceScanType</pFeature>
		<pFeature>Scan3dDistanceUnit</pFeature>
		<pFeature>Scan3dOutputMode</pFeature>
		<pFeature>Scan3dCoordinateSelector</pFeature>
		<pFeature>Scan3dCoordinateScale</pFeature>
		<pFeature>Scan3dCoordinateOffset</pFeature>
		<pFeature>Scan3dInvalidDataFlag</pFeature>
		<pFeature>Scan3dInvalidDataValue</pFeature>
		<pFeature>AcquisitionLineRate</pFeature>
	</Category>
	<IntReg Name="Scan3dConstantRegister" NameSpace="Custom">
		<Address>{_ENUM_REGISTER:#x}</Address><Length>4</Length><AccessMode>RO</AccessMode>
		<pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
	</IntReg>
	{enum("DeviceScanType", ["Linescan3D", "Areascan"])}
	{enum("Scan3dDistanceUnit", ["Millimeter", "Inch"])}
	{enum("Scan3dOutputMode", ["RectifiedC", "UncalibratedC"])}
	<Enumeration Name="Scan3dCoordinateSelector" NameSpace="Standard">
		<EnumEntry Name="CoordinateA" NameSpace="Standard"><Value>0</Value></EnumEntry>
		<EnumEntry Name="CoordinateB" NameSpace="Standard"><Value>1</Value></EnumEntry>
		<EnumEntry Name="CoordinateC" NameSpace="Standard"><Value>2</Value></EnumEntry>
		<pValue>Scan3dCoordinateSelectorRegister</pValue>
	</Enumeration>
	<IntReg Name="Scan3dCoordinateSelectorRegister" NameSpace="Custom">
		<Address>{SELECTOR_REGISTER:#x}</Address><Length>4</Length><AccessMode>RW</AccessMode>
		<pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>BigEndian</Endianess>
	</IntReg>
	<Float Name="Scan3dCoordinateScale" NameSpace="Standard"><pValue>Scan3dCoordinateScaleFormula</pValue></Float>
	<SwissKnife Name="Scan3dCoordinateScaleFormula" NameSpace="Custom">
		<pVariable Name="SEL">Scan3dCoordinateSelectorRegister</pVariable>
		<Formula>{by_axis(a_scale_mm, c_scale_mm)}</Formula>
	</SwissKnife>
	<Float Name="Scan3dCoordinateOffset" NameSpace="Standard"><pValue>Scan3dCoordinateOffsetFormula</pValue></Float>
	<SwissKnife Name="Scan3dCoordinateOffsetFormula" NameSpace="Custom">
		<pVariable Name="SEL">Scan3dCoordinateSelectorRegister</pVariable>
		<Formula>{by_axis(a_offset_mm, c_offset_mm)}</Formula>
	</SwissKnife>
	<Boolean Name="Scan3dInvalidDataFlag" NameSpace="Standard"><pValue>Scan3dInvalidDataFlagValue</pValue></Boolean>
	<Integer Name="Scan3dInvalidDataFlagValue" NameSpace="Custom"><Value>1</Value></Integer>
	<Float Name="Scan3dInvalidDataValue" NameSpace="Standard"><Value>{float(invalid_value)!r}</Value></Float>
	<Float Name="AcquisitionLineRate" NameSpace="Standard"><pValue>AcquisitionLineRateConverter</pValue></Float>
	<Converter Name="AcquisitionLineRateConverter" NameSpace="Custom">
		<pVariable Name="H">Height</pVariable>
		<FormulaTo>(H * 1000000 / FROM)</FormulaTo>
		<FormulaFrom>(H * 1000000 / TO)</FormulaFrom>
		<pValue>AcquisitionFramePeriod</pValue>
	</Converter>
"""
    out, n = re.subn(
        r'(<Category Name="Root"[^>]*>)', r"\1\n\t\t<pFeature>Scan3dControl</pFeature>", base, count=1
    )
    if n != 1:
        raise ValueError("the fake device's description has no Root category")
    out, n = re.subn(r"</RegisterDescription>\s*$", nodes + "\n</RegisterDescription>\n", out)
    if n != 1:
        raise ValueError("the fake device's description does not end with </RegisterDescription>")
    return out
