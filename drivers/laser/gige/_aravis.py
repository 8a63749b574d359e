"""Loading Aravis (GObject introspection) once, with an error that says what to install."""

from __future__ import annotations

import functools
from types import ModuleType

from drivers.laser.gige.errors import AravisUnavailableError

__all__ = ["aravis"]

_HINT = (
    "the GigE Vision source needs PyGObject and Aravis's typelib: "
    "apt-get install gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev (scripts/setup.sh does it)"
    " and pip install 'PyGObject<3.50' (in pyproject.toml)"
)


@functools.cache
def aravis() -> ModuleType:
    """The ``gi.repository.Aravis`` module (0.8).

    Raises:
        AravisUnavailableError: PyGObject or the Aravis-0.8 typelib is missing.
    """
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise AravisUnavailableError(f"{exc}; {_HINT}") from exc
    return Aravis
