"""The simulated cell (``cellctl sim``): the simulators' wiring from ``cell.toml``, its truth, its faults.

* :mod:`cellctl.simcell.service`: the controller and HD8 simulators of ``[sim]`` in one process on
  loopback, looking at the formed plate (``cellctl sim``);
* :mod:`cellctl.simcell.truth`: the formed plate on the bed (:class:`PlateTruth`), the ground truth;
* :mod:`cellctl.simcell.faults`: the run-time fault-control channel over Zenoh (``<prefix>/sim/faults``).

This is the one cellctl package that may import the simulators (``drivers/*/sim/``); the daemon and
everything else in production reach the simulated cell only through its protocols.
"""
