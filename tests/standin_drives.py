"""A stand-in hardware backend for the tests: four CiA 402 drives on wall-clock time, no robot behind them.

It proves what the runtime and the console do with a backend that drives hardware before the
CANopen backend exists (issue 12): ``virtual_time`` False, ``drives_hardware`` True, no simulated
world. It behaves like a drive set as the Hal contract describes it: enabling takes
:data:`ENABLE_STEPS` enabled commands (shutdown, switch on, enable operation), disabling is
immediate, torque is saturated at the drive's peak, a drive in fault applies no torque, and a fault
a bus thread latched (a lost heartbeat) is raised by the next read. The arm does not move: the
sample shows it at rest in a pose well inside every limit.

It is never part of the package: it registers the way a third-party backend does, through the
entry point of a tiny distribution of its own (``tests/data/outside_backend``: ``daror_standin.py``
names :class:`StandInDrives`, its configuration model :class:`StandInHalConfig` and its contract
benches :func:`contract_benches`), which a test puts on ``sys.path``
(:func:`tests.outside.installed`). Some tests register it in code instead, in another backend's
place (``register_backend``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from hal.config import AnyHalConfig, CanHalConfig, CanSimHalConfig, hal_config
from hal.errors import HalConfigError, HalError, HalNotOpenError, ShapeError
from hal.interface import Command, DriveState, Hal, HalFaultError, Sample, open_hal
from hal.isb import Shoulder
from hal.robot import N_JOINTS, FloatArray, RobotDescription, load_description
from hal.testing import BackendUnderTest
from hal.yamlfile import Number

#: Enabled commands a disabled drive needs before it reports ENABLED (CiA 402: three transitions).
ENABLE_STEPS = 3
#: The registry target of the stand-in.
TARGET = "tests.standin_drives:StandInDrives"
#: Its name in the registry (what ``--hal`` and a configuration's ``backend:`` say).
KIND = "stand-in"


class StandInHalConfig(AnyHalConfig):
    """The stand-in drives' configuration (``backend: stand-in``).

    Attributes:
        rate_hz: the SYNC rate, Hz.
    """

    backend: Literal["stand-in"] = "stand-in"
    rate_hz: Annotated[Number, Field(gt=0, le=10_000)] = 1000.0


class StandInDrives(Hal):
    """Four drives on a bus, with wall-clock time.

    Args:
        description: the robot description (default the packaged DAROR-01).
        rate_hz: the SYNC rate, Hz.
        now: monotonic time source, s.
    """

    kind = "stand-in"
    virtual_time = False
    drives_hardware = True

    def __init__(
        self,
        description: RobotDescription | None = None,
        rate_hz: float = 1000.0,
        now: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(description or load_description())
        self._rate_hz = float(rate_hz)
        self._now = now
        shoulder = Shoulder.from_description(self.description)
        # At rest: elevation 30, plane 45, axial 0, elbow 45 deg (inside the device and default ISB limits).
        self._q = shoulder.q_from_isb(np.radians([30.0, 45.0, 0.0, 45.0]))
        self._q.flags.writeable = False
        self._zeros = np.zeros(N_JOINTS)
        self._zeros.flags.writeable = False
        self._peak = float(self.description.sea.max_motor_torque_nm)
        self._lock = threading.Lock()  # the "bus thread" latches faults while the loop reads
        self._latched: str | None = None
        self._is_open = False
        self._steps = [0] * N_JOINTS
        self._faults = [0] * N_JOINTS
        self._estop = (False, False)
        self._applied = np.zeros(N_JOINTS)
        self._seq = 0
        self._t0 = 0.0
        self._t_s = 0.0
        self._sample: Sample | None = None

    @classmethod
    def from_config(cls, config: AnyHalConfig) -> StandInDrives:
        """The drives of a ``stand-in`` configuration, or of a ``can`` one (registered in that backend's place).

        Raises:
            HalConfigError: another backend's configuration.
        """
        if not isinstance(config, StandInHalConfig | CanHalConfig | CanSimHalConfig):
            raise HalConfigError(f"the stand-in drives take a stand-in or can configuration, not {config.backend!r}")
        return cls(rate_hz=config.rate_hz or 1000.0)

    @property
    def rate_hz(self) -> float:
        return self._rate_hz

    # --- the contract -----------------------------------------------------------------------------

    def open(self) -> None:
        with self._lock:
            self._latched = None
        self._steps = [0] * N_JOINTS
        self._faults = [0] * N_JOINTS
        self._applied = np.zeros(N_JOINTS)
        self._seq = 0
        self._t0 = self._now()
        self._t_s = 0.0
        self._sample = None
        self._is_open = True

    def close(self) -> None:
        self._remove_torque()
        self._is_open = False

    def read(self) -> Sample:
        if not self._is_open:
            raise HalNotOpenError("stand-in drives are not open; call open() first")
        with self._lock:
            latched, self._latched = self._latched, None
        if latched is not None:
            raise HalFaultError(latched)
        if self._sample is None:
            drives = tuple(
                DriveState.FAULT if code else DriveState.ENABLED if step >= ENABLE_STEPS else DriveState.DISABLED
                for step, code in zip(self._steps, self._faults, strict=True)
            )
            self._sample = Sample(
                self._seq,
                self._t_s,
                self._q,
                self._zeros,
                self._q,
                self._zeros,
                self._estop,
                drives,
                tuple(self._faults),
            )
        return self._sample

    def write(self, command: Command) -> None:
        if not self._is_open:
            raise HalNotOpenError("stand-in drives are not open; call open() first")
        if command.enable:
            torque = np.asarray(command.motor_torque_nm, dtype=float)
            if torque.shape != (N_JOINTS,):
                self._remove_torque()
                raise ShapeError(f"motor_torque_nm: expected shape ({N_JOINTS},), got {torque.shape}")
            if not np.all(np.isfinite(torque)):
                self._remove_torque()
                raise HalError(f"motor_torque_nm = {torque.tolist()} is not finite; torque removed")
            if any(isinstance(j, bool) or j not in range(1, N_JOINTS + 1) for j in command.joints_off):
                self._remove_torque()
                raise ShapeError(f"joints_off: expected joint numbers 1-{N_JOINTS}, got {command.joints_off!r}")
            for j in range(N_JOINTS):
                if (j + 1) in command.joints_off:
                    self._steps[j] = 0  # that drive disabled at once, the others go on
                elif not self._faults[j]:
                    self._steps[j] = min(self._steps[j] + 1, ENABLE_STEPS)
            on = np.array(
                [step >= ENABLE_STEPS and not code for step, code in zip(self._steps, self._faults, strict=True)]
            )
            self._applied = np.where(on, np.clip(torque, -self._peak, self._peak), 0.0)
        else:
            self._steps = [0] * N_JOINTS
            self._applied = np.zeros(N_JOINTS)
        self._seq += 1  # a SYNC: every drive sends a fresh reading
        self._t_s = max(self._t_s, self._now() - self._t0)
        self._sample = None

    # --- what a test does to the drives -------------------------------------------------------------

    @property
    def applied_motor_torque_nm(self) -> FloatArray:
        """What the drives apply since the last write (4,) Nm."""
        return self._applied.copy()

    def lose_heartbeat(self, node: int) -> None:
        """What the bus thread does when a drive's heartbeat is missing: latch a fault (any thread)."""
        with self._lock:
            self._latched = f"heartbeat of node {node} lost"

    def fault_drive(self, joint: int, code: int = 0x2310) -> None:
        """Drive ``joint`` (1-4) reports a fault (default 0x2310, over-current) and applies no torque."""
        self._faults[joint - 1] = code
        self._steps[joint - 1] = 0
        self._applied[joint - 1] = 0.0
        self._sample = None

    def press_estop(self, which: int, pressed: bool) -> None:
        estop = list(self._estop)
        estop[which] = pressed
        self._estop = (estop[0], estop[1])
        self._sample = None

    def _remove_torque(self) -> None:
        self._steps = [0] * N_JOINTS
        self._applied = np.zeros(N_JOINTS)
        self._sample = None


def contract_benches() -> tuple[BackendUnderTest, ...]:
    """The stand-in on the contract suite's bench: built through the registry, as the runtime gets it."""
    return (
        BackendUnderTest(
            KIND,
            KIND,
            make=lambda: open_hal(hal_config(KIND)),
            latch_fault=lambda hal: hal.lose_heartbeat(2),  # type: ignore[attr-defined]
            fault_drive=lambda hal, joint: hal.fault_drive(joint),  # type: ignore[attr-defined]
            applied_torque_nm=lambda hal: hal.applied_motor_torque_nm,  # type: ignore[attr-defined]
        ),
    )
