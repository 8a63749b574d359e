"""The one registry of profile sources: a protocol name -> its :class:`ProfileSource` class.

Modelled on python-can's backend registry (``can.Bus(interface="socketcan")``): a name maps to a
module and a class, imported only when chosen, so a cell with an HD8 never loads Aravis and a vendor's
SDK is needed only where its sensor is used. Built-in names are in :data:`SOURCES`; a vendor package
adds its own with :func:`register_source` or, without touching this repository, with an entry point in
the group :data:`ENTRY_POINT_GROUP` (``name = "package.module:ClassName"``). docs/sensors.md says how.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from drivers.laser.source import ProfileSource

__all__ = [
    "ENTRY_POINT_GROUP",
    "SOURCES",
    "UnknownSourceError",
    "available_sources",
    "open_source",
    "register_source",
    "source_class",
]

#: entry-point group a separately installed vendor source registers under
ENTRY_POINT_GROUP = "cellctl.profile_sources"

#: built-in sources: protocol name -> (module, class)
SOURCES: dict[str, tuple[str, str]] = {
    "hd8": ("drivers.laser.client", "HD8Client"),
    "gige": ("drivers.laser.gige.source", "GigeProfileSource"),
}


class UnknownSourceError(ValueError):
    """No source is registered under the name (the message lists those that are)."""

    def __init__(self, name: str) -> None:
        self.name = name
        super().__init__(f"no profile source {name!r}; known: {', '.join(available_sources())}")


def _entry_points() -> dict[str, str]:
    return {ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP)}


def available_sources() -> list[str]:
    """Every name a source can be chosen by (built-in, registered, installed entry points)."""
    return sorted(set(SOURCES) | set(_entry_points()))


def register_source(name: str, module: str, class_name: str) -> None:
    """Add (or replace) the source ``name``: ``module.class_name``, imported when first chosen."""
    SOURCES[name] = (module, class_name)


def source_class(name: str) -> type[ProfileSource]:
    """The class of source ``name`` (imports its module now).

    Raises:
        UnknownSourceError: nothing is registered under ``name``.
        TypeError: what is registered is not a :class:`ProfileSource`.
    """
    if name in SOURCES:
        module, cls_name = SOURCES[name]
    else:
        target = _entry_points().get(name)
        if target is None:
            raise UnknownSourceError(name)
        module, _, cls_name = target.partition(":")
    cls = getattr(importlib.import_module(module), cls_name)
    if not (isinstance(cls, type) and issubclass(cls, ProfileSource)):
        raise TypeError(f"profile source {name!r} ({module}.{cls_name}) is not a ProfileSource")
    return cls


def open_source(name: str, *args: Any, **kwargs: Any) -> ProfileSource:
    """A new (not yet connected) source ``name``, built with its own class's arguments."""
    return source_class(name)(*args, **kwargs)
