"""GigE Vision / GenICam 3D profile sensors through Aravis (docs/sensors.md).

* :mod:`drivers.laser.gige.source`: :class:`GigeProfileSource`, the :class:`ProfileSource` of a
  GigE Vision profiler (SFNC Scan3dControl range rows), and :func:`discover`.
* :mod:`drivers.laser.gige.scan3d`: range rows <-> profiles, row stamps, block-id unwrapping: the
  codec the source and the simulator's GigE Vision device share.
* :mod:`drivers.laser.gige.genicam`: the GenICam features the source reads and writes.

Aravis is loaded on first use (PyGObject + ``gir1.2-aravis-0.8``), so importing this package costs
nothing on a cell with an HD8.
"""

from drivers.laser.gige.errors import (
    AravisUnavailableError,
    DeviceNotFoundError,
    FeatureError,
    GigeError,
    MissingFeatureError,
    NotAProfilerError,
    PixelFormatError,
)
from drivers.laser.gige.source import GigeProfileSource, GigeSourceConfig, GigeStats, discover

__all__ = [
    "AravisUnavailableError",
    "DeviceNotFoundError",
    "FeatureError",
    "GigeError",
    "GigeProfileSource",
    "GigeSourceConfig",
    "GigeStats",
    "MissingFeatureError",
    "NotAProfilerError",
    "PixelFormatError",
    "discover",
]
