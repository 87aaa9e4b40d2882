"""Why a run ended: one IntEnum, one record."""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class StopReason(IntEnum):
    """Every way a run can end. Each one ends with zero torque sent and the drive disabled."""

    DONE = 0              # the run lasted its duration
    FEEDBACK_TIMEOUT = 1  # no fresh feedback for loop.feedback_timeout
    POSITION_LIMIT = 2
    VELOCITY_LIMIT = 3
    NON_FINITE = 4        # NaN or infinity in feedback, reference or command
    DRIVE_FAULT = 5       # the drive reported a fault (axis error, watchdog, Estop)
    SIGNAL = 6            # SIGINT / SIGTERM / stop requested
    EXCEPTION = 7         # an exception in the loop (re-raised to the caller)
    ENABLE_FAILED = 8     # the drive could not be enabled
    BUS_ERROR = 9         # the CAN bus failed (send refused, ENOBUFS, interface gone)
    RECORDER_FAILED = 10  # the run's recorder failed (disk full, ...): the record would be lost
    #: the host, not the drive: no fresh feedback because the emulated drive itself was not
    #: scheduled, or the drive's watch on the host (watchdog, heartbeat consumer, command
    #: timeout) expired after the host's own commands came too late
    HOST_TOO_SLOW = 11
    UNSTABLE = 12         # the command chattered at its limit or the estimate's oscillation grew


@dataclass(frozen=True)
class Stop:
    reason: StopReason
    detail: str
    cycle: int
    time: float

    def line(self) -> str:
        """The one-line account of the stop."""
        name = self.reason.name.lower()
        at = f" at cycle {self.cycle} (t = {self.time:.4f} s)" if self.cycle >= 0 else ""
        return f"stopped: {name}{at}" + (f": {self.detail}" if self.detail else "")
