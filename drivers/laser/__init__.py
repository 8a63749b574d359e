"""Line-laser profile sensors: the HD8 model (wire protocol, asyncio client), GigE Vision profilers,
and a ray-casting sensor simulator that speaks both.

* :mod:`drivers.laser.source`: :class:`ProfileBatch` and the :class:`ProfileSource` interface.
* :mod:`drivers.laser.protocol`: the codec (docs/hd8-protocol.md), shared by client and simulator.
* :mod:`drivers.laser.client`: :class:`HD8Client`, the TCP implementation of ``ProfileSource``.
* :mod:`drivers.laser.gige`: ``GigeProfileSource``, GigE Vision / GenICam 3D profilers through Aravis
  (loaded on first use).
* :mod:`drivers.laser.registry`: the one registry of sources, chosen by name (``"hd8"``, ``"gige"``).
* :mod:`drivers.laser.sim`: the sensor simulator (``sim.sensor``, ``sim.scene``, ``sim.optics``;
  imports open3d: load it only where a simulated sensor is needed).
"""

from drivers.laser.client import HD8Client, HD8ClientConfig
from drivers.laser.source import ProfileBatch, ProfileSource, SourceEvent, SourceEventKind, SourceStats

__all__ = [
    "HD8Client",
    "HD8ClientConfig",
    "ProfileBatch",
    "ProfileSource",
    "SourceEvent",
    "SourceEventKind",
    "SourceStats",
]
