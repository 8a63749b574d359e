"""The ABB controller simulator: what a real IRC5 / OmniCore is to the cell, on loopback.

Driven only through its protocols (EGM over UDP, RWS over HTTP); nothing outside the simulators'
wings (``drivers/*/sim/``, ``cellctl/simcell/``), the tests and the benchmarks imports it.

* :mod:`drivers.abb_egm.sim.controller`: :class:`ControllerSim`, the composition, and ``main``
  (``python -m drivers.abb_egm.sim``);
* :mod:`drivers.abb_egm.sim.model`: :class:`ControllerModel`, the controller's state (panel, RAPID
  program, IO, event log), no I/O;
* :mod:`drivers.abb_egm.sim.egm`: :class:`EgmControllerSim`, the controller's EGM side (UDP client,
  control law, joint and speed limits, fault knobs);
* :mod:`drivers.abb_egm.sim.rws_server`: :class:`RwsServer`, RWS 1.0 / 2.0 over aiohttp.

What the simulator shares with the production client lives beside the codec:
:mod:`drivers.abb_egm.codec` (EGM), :mod:`drivers.abb_egm.rapid_values` (RAPID literals and names),
:mod:`drivers.abb_egm.digest` (digest authentication).
"""
