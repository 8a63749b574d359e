"""Hypothesis profiles for long fuzz runs (``--hypothesis-profile=fuzz-long``); see fuzzlib.py."""

from hypothesis import settings

# Registering does not load: the default profile (and its counts) stay for every other test.
settings.register_profile("fuzz-long", max_examples=5_000, deadline=None)
settings.register_profile("fuzz-soak", max_examples=50_000, deadline=None)
