"""Motion: the safety envelope every set-point passes, and the EGM executor that streams a plan."""

from cellctl.motion.envelope import EnvelopeLimits, EnvelopeViolation, SafetyEnvelope
from cellctl.motion.executor import (
    ExecState,
    ExecutionResult,
    ExecutorConfig,
    ExecutorError,
    MotionExecutor,
    ProgressEvent,
)

__all__ = [
    "EnvelopeLimits",
    "EnvelopeViolation",
    "ExecState",
    "ExecutionResult",
    "ExecutorConfig",
    "ExecutorError",
    "MotionExecutor",
    "ProgressEvent",
    "SafetyEnvelope",
]
