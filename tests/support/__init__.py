"""Test harnesses shared by several test folders and the benchmarks; imported as ``tests.support.<name>``.

* ``ports``: :func:`free_port` (the one loopback port picker);
* ``surfaces``: analytic plate surfaces with known answers and their grid meshes;
* ``simcell``: the acquisition against the controller and HD8 simulators in one process;
* ``e2e_cell``: a simulated cell in real processes (``cellctl sim``, ``run``, ``worker``);
* ``faultcell``, ``cellfaults``, ``tcp_forwarder``: fault injection on that cell;
* ``results_fixture``: a synthetic results directory for the report.
* ``plans``: the placements, settings and session plans of the planning and motion tests;
* ``hub``: a loopback-only Zenoh hub for one test cell (tests/zenoh, tests/api);
* ``skiplog``: the run's log of skips and fallbacks (``record_fallback`` for a retry that goes on).

A helper used by one folder only stays in that folder.
"""
