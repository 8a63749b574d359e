"""cellctl: the robot laser-scanning cell for curved hull plate inspection."""

__version__ = "0.1.0"
