"""What the device simulators (``drivers/*/sim/``) share: the simulators' wing, like them imported
only by another simulator, tests and benchmarks (tests/test_architecture.py)."""
