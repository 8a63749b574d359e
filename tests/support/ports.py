"""Loopback ports for tests: the demo's own picker, so product and tests choose ports one way."""

from cellctl.commands.demo_cmd import free_port

__all__ = ["free_port"]
