"""Faults: what the safety monitor found, in a form a person and the FSM can act on.

Every fault is acted on in the tick it is found, with the reaction the spec declares for its kind
(safety/reactions.py: off, lower or hold; the faulted joint's torque off where it cannot be trusted),
and stays latched until it is cleared (issue 4: acknowledged, then a reset). A fault names its class, the joint (1-4)
where that applies, the measured value, the limit it broke and the robot time.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class FaultKind(StrEnum):
    """Classes of fault; every one is injected in a closed-loop test (tests/daror_runtime/safety/test_safety_loop.py)."""

    JOINT_LIMIT = "joint_limit"  # a joint outside the device's range of motion
    ISB_LIMIT = "isb_limit"  # the shoulder or elbow outside the pilot's recorded ISB limits
    VELOCITY = "velocity"  # a joint moving faster than allowed
    TORQUE = "torque"  # measured spring torque beyond the limit
    DEFLECTION = "deflection"  # spring deflection near its mechanical end stop
    NOT_FINITE = "not_finite"  # NaN or infinity in a reading
    JUMP = "jump"  # an implausible jump of a joint angle between two samples
    STALE = "stale"  # the hardware stopped delivering fresh samples
    ESTOP = "estop"  # an e-stop is pressed
    OVERRUN = "overrun"  # too many deadlines missed in a row, or one long stall
    DRIVE = "drive"  # a drive reports a fault
    HAL = "hal"  # the backend latched an error (a drive lost, an EMCY, the receive thread)
    BUS = "bus"  # the field bus itself failed (CAN bus-off, error-passive): nothing can be commanded reliably
    SOFTWARE = "software"  # the controller or recorder failed, or produced a non-finite command


@dataclass(frozen=True, slots=True)
class Fault:
    kind: FaultKind
    t_s: float
    message: str
    joint: int | None = None  # 1-4
    value: float | None = None
    limit: float | None = None

    def as_dict(self) -> dict[str, object]:
        """For the JSON audit log."""
        return {
            "kind": self.kind.value,
            "t_s": self.t_s,
            "joint": self.joint,
            "value": self.value,
            "limit": self.limit,
            "message": self.message,
        }
