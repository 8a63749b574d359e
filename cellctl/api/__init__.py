"""The cell's one typed contract: Zenoh keys, payload models both ways, the cloud codec, sessions.

``keys`` (the key space), ``models`` (every JSON payload, pydantic, unknown fields refused; the job
parameters and the report are :mod:`analysis.contracts.job`'s models, the placement :mod:`analysis.contracts.placement`'s),
``analysis_job`` (a job's parameters from the configuration), ``cloud_codec`` (the binary cloud),
``session`` (Zenoh sessions, the asyncio bridge, client calls) and ``dispatch`` (the daemon's side
of the job protocol). The package exports the keys, the models and the client calls.
"""

from cellctl.api.keys import CONTROL_ACTIONS, ControlAction, Keys
from cellctl.api.models import *  # noqa: F403
from cellctl.api.models import __all__ as _models_all
from cellctl.api.session import ApiCallError, call, list_workers

__all__ = ["CONTROL_ACTIONS", "ApiCallError", "ControlAction", "Keys", "call", "list_workers", *_models_all]
