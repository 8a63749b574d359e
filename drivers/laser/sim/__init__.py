"""The HD8 sensor simulator: profiles over TCP, ray-cast from a scene at the robot's true pose.

Driven only through its protocol (:mod:`drivers.laser.protocol`, shared with the client); nothing
outside the simulators' wings (``drivers/*/sim/``, ``cellctl/simcell/``), the tests and the benchmarks
imports it.

* :mod:`drivers.laser.sim.sensor`: :class:`LaserSimulator` (control and data servers, clock, fault
  knobs) and ``main`` (``python -m drivers.laser.sim``);
* :mod:`drivers.laser.sim.scene`: triangle scenes (plane, step, box, plate solid, the cell's bed and
  supports) and the ray caster (open3d);
* :mod:`drivers.laser.sim.optics`: the laser fan, depth noise and missing returns.
"""
