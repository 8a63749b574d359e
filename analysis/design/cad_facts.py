"""What an IGES or STEP file says about itself before OpenCASCADE reads it: its layout checked, its
length unit and its entity counts (:class:`FileFacts`), and :class:`DesignError`, the one-line refusal
of an unusable design file that every step of the read raises.
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from analysis.design.mesh import MeshError

# IGES global parameter 14 (units flag) -> (name, millimetres per unit); flag 3 names the unit in 15
IGES_UNITS: dict[int, tuple[str, float]] = {
    1: ("inch", 25.4), 2: ("mm", 1.0), 4: ("foot", 304.8), 5: ("mile", 1609344.0), 6: ("m", 1000.0),
    7: ("km", 1.0e6), 8: ("mil", 0.0254), 9: ("micron", 1.0e-3), 10: ("cm", 10.0),
    11: ("microinch", 2.54e-5),
}  # fmt: skip
IGES_UNIT_NAMES = {"IN": 1, "INCH": 1, "MM": 2, "FT": 4, "MI": 5, "M": 6, "KM": 7, "MIL": 8, "UM": 9,
                   "MICRON": 9, "CM": 10, "UIN": 11}  # fmt: skip
STEP_PREFIX_MM = {"$": 1000.0, ".MILLI.": 1.0, ".CENTI.": 10.0, ".DECI.": 100.0, ".KILO.": 1.0e6,
                  ".MICRO.": 1.0e-3}  # fmt: skip
STEP_PREFIX_NAME = {"$": "m", ".MILLI.": "mm", ".CENTI.": "cm", ".DECI.": "dm", ".KILO.": "km",
                    ".MICRO.": "micron"}  # fmt: skip
STEP_CONVERSION_MM = {"INCH": 25.4, "FOOT": 304.8, "FEET": 304.8, "MILLIMETRE": 1.0, "METRE": 1000.0}
# IGES entity types that carry a surface or a face (what a design's faces come from)
IGES_SURFACE_TYPES = {108, 114, 118, 120, 122, 128, 140, 143, 144, 186, 190, 192, 194, 196, 198, 510, 514}
STEP_FACE_TYPES = ("ADVANCED_FACE", "FACE_SURFACE")


class DesignError(MeshError):
    """A design file that cannot be used; the message is one line naming the file and the problem."""


@dataclass(frozen=True)
class FileFacts:
    """What the file says about itself before OpenCASCADE reads it.

    fmt: "IGES" | "STEP"; units: the file's length unit ("m", "mm", ...); mm_per_unit: its size;
    entities: entity counts by type (IGES type numbers as strings, STEP entity names);
    surfaces: how many faces the file declares (IGES surface entities, STEP faces).
    """

    fmt: str
    units: str
    mm_per_unit: float
    entities: dict[str, int]
    surfaces: int


def _iges_fields(text: str) -> list[str]:
    """The global section's parameters (Hollerith strings unwrapped), in order."""
    pd, rd = ",", ";"
    pos = 0
    fields: list[str] = []
    holl = re.compile(r"\s*(\d+)H")
    while pos < len(text):
        m = holl.match(text, pos)
        if m:
            n = int(m.group(1))
            value = text[m.end() : m.end() + n]
            pos = m.end() + n
        else:
            end = pos
            while end < len(text) and text[end] not in (pd, rd):
                end += 1
            value = text[pos:end].strip()
            pos = end
        fields.append(value)
        if len(fields) == 1 and value and len(value) == 1 and m:
            pd = value
        if len(fields) == 2 and value and len(value) == 1 and m:
            rd = value
        if pos >= len(text) or text[pos] == rd:
            break
        pos += 1  # the delimiter
    return fields


def iges_facts(path: Path, data: bytes) -> FileFacts:
    """Check an IGES file's fixed layout and read its units and entity counts (no geometry)."""
    lines = data.decode("latin-1").splitlines()
    sections: dict[str, list[str]] = {k: [] for k in "SGDPT"}
    for k, line in enumerate(lines):
        if not line.strip():
            continue
        if len(line) < 73 or line[72] not in sections:
            if k == len(lines) - 1:
                raise DesignError(f"{path}: truncated IGES file (its last line, {k + 1}, is cut off)")
            raise DesignError(
                f"{path}: corrupted IGES file (line {k + 1} is not an 80-column S/G/D/P/T record)"
            )
        sections[line[72]].append(line[:72])
    if not sections["D"] or not sections["G"]:
        raise DesignError(f"{path}: not an IGES file (no global or directory section)")
    if not sections["T"]:
        raise DesignError(f"{path}: truncated IGES file (the terminate section is missing)")
    counts = re.findall(r"([SGDP])\s*(\d+)", sections["T"][0])
    for letter, n in counts:
        if int(n) != len(sections[letter]):
            raise DesignError(
                f"{path}: truncated or corrupted IGES file (the terminate section counts {int(n)} "
                f"{letter} lines, the file has {len(sections[letter])})"
            )
    if len(sections["D"]) % 2:
        raise DesignError(f"{path}: corrupted IGES file (odd number of directory lines)")
    try:
        types = Counter(int(d[:8]) for d in sections["D"][::2])
    except ValueError:
        raise DesignError(f"{path}: corrupted IGES file (a directory entry has no entity type)") from None
    g = _iges_fields("".join(sections["G"]))
    flag_text = g[13].strip() if len(g) > 13 else ""
    name = g[14].strip().upper() if len(g) > 14 else ""
    if not flag_text:
        raise DesignError(f"{path}: units missing (the IGES global section has no units flag)")
    try:
        flag = int(float(flag_text))
    except ValueError:
        raise DesignError(f"{path}: corrupted IGES global section (units flag {flag_text!r})") from None
    if flag == 3:
        flag = IGES_UNIT_NAMES.get(name, 0)
    if flag not in IGES_UNITS:
        raise DesignError(f"{path}: units missing or unknown (IGES units flag {flag_text}, name {name!r})")
    unit, mm = IGES_UNITS[flag]
    surfaces = sum(n for t, n in types.items() if t in IGES_SURFACE_TYPES)
    # a trimmed surface (143/144) or a face (510) wraps its 128: count the outermost only
    wrappers = types.get(143, 0) + types.get(144, 0) + types.get(510, 0)
    if wrappers:
        surfaces = wrappers + sum(types.get(t, 0) for t in (108, 114, 118, 120, 122, 140) if t != 128)
    else:
        surfaces = types.get(128, 0) + sum(types.get(t, 0) for t in (108, 114, 118, 120, 122, 140))
    return FileFacts("IGES", unit, mm, {str(t): n for t, n in sorted(types.items())}, surfaces)


def step_facts(path: Path, data: bytes) -> FileFacts:
    """Check a STEP Part 21 file's frame and read its length unit and entity counts (no geometry)."""
    text = data.decode("latin-1")
    head = text.lstrip()[:64].upper()
    if not head.startswith("ISO-10303-21"):
        raise DesignError(f"{path}: not a STEP file (no ISO-10303-21 header)")
    if "END-ISO-10303-21" not in text[-4096:].upper():
        raise DesignError(f"{path}: truncated STEP file (no END-ISO-10303-21 at its end)")
    names = Counter(m.group(1).upper() for m in re.finditer(r"#\d+\s*=\s*([A-Za-z_0-9]+)\s*\(", text))
    mm = unit = None
    for stmt in re.findall(r"#\d+\s*=\s*\(([^;]*LENGTH_UNIT[^;]*)\)\s*;", text, flags=re.IGNORECASE):
        si = re.search(r"SI_UNIT\s*\(\s*(\$|\.\w+\.)\s*,\s*\.METRE\.\s*\)", stmt, flags=re.IGNORECASE)
        conv = re.search(r"CONVERSION_BASED_UNIT\s*\(\s*'([^']*)'", stmt, flags=re.IGNORECASE)
        if si and si.group(1).upper() in STEP_PREFIX_MM:
            mm, unit = STEP_PREFIX_MM[si.group(1).upper()], STEP_PREFIX_NAME[si.group(1).upper()]
        elif conv and conv.group(1).upper() in STEP_CONVERSION_MM:
            mm, unit = STEP_CONVERSION_MM[conv.group(1).upper()], conv.group(1).lower()
        if mm is not None:
            break
    if mm is None:
        raise DesignError(f"{path}: units missing (no length unit in the STEP file)")
    faces = sum(names.get(n, 0) for n in STEP_FACE_TYPES)
    return FileFacts("STEP", unit, mm, dict(sorted(names.items())), faces)
