"""The HAL contract: what the runtime reads and writes each tick, and how backends plug in.

Like python-can's ``BusABC``: one small abstract base, backends in their own folders
(``hal/sim``, ``hal/canopen``), looked up by name in a registry that imports them lazily. The
runtime talks to hardware only through :class:`Hal`.

Per tick the loop calls :meth:`Hal.read` once, then :meth:`Hal.write` once. A backend reports a
fault in one of two ways: a drive that reports it in its status word (``Sample.drives``), or an
error the backend latched outside the tick (a CAN thread, a lost heartbeat), which
:meth:`Hal.read` raises as :class:`HalFaultError` at the next tick. Either way the safety monitor
turns it into a fault that removes torque in the same tick.

Units: rad, rad/s, Nm, s. Arrays are ``float64`` of shape (4,), joints 1-4 at indices 0-3.
"""

from __future__ import annotations

import importlib
from abc import ABC, abstractmethod
from enum import IntEnum
from types import TracebackType
from typing import Any, NamedTuple

import numpy as np

from hal.errors import DarorError, DescriptionError, HalError
from hal.robot import N_JOINTS, FloatArray, RobotDescription


class DriveState(IntEnum):
    """CiA 402 power state, reduced to what the runtime acts on."""

    DISABLED = 0  # no torque (switch on disabled / ready to switch on / switched on)
    ENABLED = 1  # operation enabled: the drive applies the commanded torque
    FAULT = 2  # the drive reports a fault; it applies no torque until reset


class Sample(NamedTuple):
    """Everything read from the hardware in one tick (immutable; a NamedTuple, built 1,000 times a second).

    ``seq`` increases by one on every fresh reading, so a sample that did not change (a stale
    bus) is recognised. ``t_s`` is the hardware's (or the simulator's) time of the reading.
    ``tau_nm`` is the spring torque as the drive measures it, ``k (theta - q)``, including its
    measurement error. ``estop`` holds the e-stop inputs, ``True`` when pressed (operator, pilot).
    """

    seq: int
    t_s: float
    q_rad: FloatArray
    dq_rad_s: FloatArray
    theta_rad: FloatArray
    tau_nm: FloatArray
    estop: tuple[bool, ...]
    drives: tuple[DriveState, ...]
    drive_fault_codes: tuple[int, ...] = (0, 0, 0, 0)

    @property
    def any_estop(self) -> bool:
        return True in self.estop


class Command(NamedTuple):
    """What is written to the hardware in one tick (immutable).

    ``motor_torque_nm`` is the torque the motor should deliver at the gearbox output (before the
    spring); ``enable`` False means torque off (drives disabled), whatever the torque says.
    """

    motor_torque_nm: FloatArray
    enable: bool

    @staticmethod
    def torque_off() -> Command:
        """The torque-off command (one shared, read-only instance)."""
        return TORQUE_OFF


def _read_only_zeros() -> FloatArray:
    zeros = np.zeros(N_JOINTS)
    zeros.flags.writeable = False
    return zeros


#: Torque off: drives disabled, zero torque.
TORQUE_OFF = Command(_read_only_zeros(), False)


class HalFaultError(HalError):
    """A backend fault latched outside the tick (bus error, lost heartbeat, thread crash)."""


class Hal(ABC):
    """A DAROR-01 as the runtime sees it: read a sample, write a command, nothing else in the tick.

    ``enable``/``disable`` may take several ticks on real drives (CiA 402 state machine); they
    are requests that :meth:`write` carries out step by step, never blocking calls.
    """

    #: Registry name: ``sim``, ``can-sim``, ``can``.
    kind: str = ""

    def __init__(self, description: RobotDescription) -> None:
        self.description = description

    @abstractmethod
    def open(self) -> None:
        """Connect (bus, drives or simulator); drives stay disabled."""

    @abstractmethod
    def close(self) -> None:
        """Remove torque and disconnect. Safe to call twice."""

    @abstractmethod
    def read(self) -> Sample:
        """The newest sample. Never blocks.

        Raises:
            HalFaultError: a fault the backend latched since the previous read.
        """

    @abstractmethod
    def write(self, command: Command) -> None:
        """Apply ``command``. Never blocks; a disabled command removes torque at once."""

    @property
    @abstractmethod
    def rate_hz(self) -> float:
        """The tick rate the backend expects to be read and written at."""

    def __enter__(self) -> Hal:
        self.open()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


#: Backend name -> "module:Class"; imported only when asked for.
BACKENDS: dict[str, str] = {
    "sim": "hal.sim.backend:SimHal",
    "can-sim": "hal.canopen.backend:SimulatedCanHal",
    "can": "hal.canopen.backend:CanHal",
}


def hal_class(kind: str) -> type[Hal]:
    """The backend class registered as ``kind``.

    Raises:
        DescriptionError: unknown kind.
        DarorError: the backend cannot be imported (e.g. a missing dependency).
    """
    try:
        target = BACKENDS[kind]
    except KeyError:
        raise DescriptionError(f"unknown HAL backend {kind!r}; expected one of {', '.join(BACKENDS)}") from None
    module_name, attribute = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise DarorError(f"HAL backend {kind!r} is not available: {exc}") from None
    return getattr(module, attribute)


def open_hal(kind: str, **options: Any) -> Hal:
    """Construct the backend ``kind`` with ``options`` (it is not opened yet)."""
    return hal_class(kind)(**options)
