"""Motion: the timed trajectory, the safety envelope every set-point passes, and the EGM executor that
streams a trajectory. Planning builds on it; motion imports nothing of planning."""

from cellctl.motion.envelope import EnvelopeLimits, EnvelopeViolation, SafetyEnvelope
from cellctl.motion.executor import (
    ExecState,
    ExecutionResult,
    ExecutorConfig,
    ExecutorError,
    MotionExecutor,
    ProgressEvent,
)
from cellctl.motion.trajectory import TimedTrajectory

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
    "TimedTrajectory",
]
