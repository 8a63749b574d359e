"""``python -m drivers.laser.sim``: the HD8 simulator as a stand-alone process."""

from drivers.laser.sim.sensor import main

if __name__ == "__main__":
    main()
