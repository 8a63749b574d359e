"""The cell daemon (`cellctl run`): state machine, job store and the asyncio service."""
