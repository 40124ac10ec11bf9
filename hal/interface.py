"""The HAL contract: what the runtime reads and writes each tick, and how backends plug in.

Like python-can's ``BusABC``: one small abstract base, backends in their own folders
(``hal/sim``, ``hal/canopen``) or in other packages, looked up by name in a registry that imports
them lazily (:mod:`hal.registry`: :func:`register_backend`, :func:`backend_kinds`, entry points;
:func:`open_hal` builds one from a :mod:`hal.config` configuration). The runtime talks to
hardware only through :class:`Hal`; what a simulating backend offers besides (the pilot, the
e-stop buttons, fault injection) is the :class:`hal.capabilities.SimulatedWorld` of
:attr:`Hal.world`.

Per tick the loop calls :meth:`Hal.read` once, then :meth:`Hal.write` once. A backend reports a
fault in one of two ways: a drive that reports it in its status word (``Sample.drives``), or an
error the backend latched outside the tick (a CAN thread, a lost heartbeat), which
:meth:`Hal.read` raises as :class:`HalFaultError` at the next tick. Either way the safety monitor
turns it into a fault that removes torque in the same tick.

Every backend must pass the contract suite ``tests/hal_contract.py`` (run by
``tests/hal/test_hal_contract.py``); the docstrings of :class:`Hal` say what it checks.

Units: rad, rad/s, Nm, s. Arrays are ``float64`` of shape (4,), joints 1-4 at indices 0-3.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from enum import IntEnum
from types import TracebackType
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from hal.errors import BackendUnavailableError, HalError, ShapeError
from hal.registry import BackendEntry as BackendEntry
from hal.registry import backend_entry as backend_entry
from hal.registry import backend_kinds as backend_kinds
from hal.registry import import_target
from hal.registry import register_backend as register_backend
from hal.registry import unregister_backend as unregister_backend
from hal.robot import N_JOINTS, FloatArray, RobotDescription

if TYPE_CHECKING:
    from hal.capabilities import LockStepBatches, SimulatedWorld
    from hal.config import AnyHalConfig


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


#: The fields of a sample that hold arrays (float64, shape (4,)).
SAMPLE_ARRAYS = ("q_rad", "dq_rad_s", "theta_rad", "tau_nm")


def _require_joint_vector(name: str, array: object) -> None:
    """Refuse anything but an aligned float64 ndarray of shape (4,): what the compiled kernels are resolved for.

    Raises:
        ShapeError: names the field, the dtype and the shape found.
    """
    if not (
        type(array) is np.ndarray and array.dtype == np.float64 and array.shape == (N_JOINTS,) and array.flags.aligned
    ):
        shape = getattr(array, "shape", None)
        dtype = getattr(array, "dtype", type(array).__name__)
        raise ShapeError(f"{name}: expected a float64 array of shape ({N_JOINTS},), got {dtype} {shape}")


class CheckedSample(Sample):
    """A :class:`Sample` whose four arrays are known to be what the contract says: float64, shape (4,).

    The tick's compiled kernels may then take them through an entry point resolved for exactly
    that type (:mod:`hal.kernels`: no type dispatch, ~0.1-0.35 us a kernel call less); for any
    other sample they go through numba's dispatcher, which checks every argument. A consumer
    tests ``type(sample) is CheckedSample`` (an identity test; a subclass does not count).

    Made by its constructor, which checks the arrays (:class:`~hal.errors.ShapeError` otherwise), or
    by a backend whose arrays have that type by construction (``hal.sim.backend``, which builds it
    with ``tuple.__new__``; ``tests/daror_runtime/test_kernel_entry_points.py`` checks its samples). Otherwise it is a
    ``Sample`` in every respect (equal to one with the same fields, ``isinstance`` of it).
    Replacing a field (``_replace``) gives a plain :class:`Sample`: the new value is not checked.
    """

    __slots__ = ()

    def __new__(cls, *args: object, **kwargs: object) -> CheckedSample:
        sample = Sample(*args, **kwargs)  # type: ignore[arg-type]
        for name in SAMPLE_ARRAYS:
            _require_joint_vector(name, getattr(sample, name))
        return tuple.__new__(cls, sample)

    @classmethod
    def _make(cls, iterable: object) -> Sample:  # type: ignore[override]
        """A plain :class:`Sample` (``_replace`` builds through this: its new values are not checked)."""
        return Sample._make(iterable)  # type: ignore[arg-type]


class Command(NamedTuple):
    """What is written to the hardware in one tick (immutable).

    ``motor_torque_nm`` is the torque the motor should deliver at the gearbox output (before the
    spring); ``enable`` False means torque off (drives disabled), whatever the torque says.
    ``joints_off`` names joints (1-4) whose drive is disabled while the others follow an enabled
    command: a fault that concerns one joint (its drive, its sensors) takes that joint's torque off
    and leaves the others holding the arm (docs/safety.md, fault reactions).
    """

    motor_torque_nm: FloatArray
    enable: bool
    joints_off: tuple[int, ...] = ()

    @staticmethod
    def torque_off() -> Command:
        """The torque-off command (one shared, read-only instance)."""
        return TORQUE_OFF


class CheckedCommand(Command):
    """A :class:`Command` whose torque is known to be a float64 array of shape (4,), like :class:`CheckedSample`.

    The safety filter, the recorder's row and the simulated drives then take the torque without
    checking its type (``type(command) is CheckedCommand``, an identity test) and hand it to kernel
    entry points resolved for that type (:mod:`hal.kernels`); any other command is checked, or
    goes through numba's dispatcher, as before. Made by its constructor, which checks the torque
    (:class:`~hal.errors.ShapeError` otherwise), or by a controller whose torque has that type by
    construction (``daror_runtime.control.motor_position``, with ``tuple.__new__``;
    ``tests/daror_runtime/test_kernel_entry_points.py`` checks what reaches the kernels). :data:`TORQUE_OFF` is
    one. ``_replace`` gives a plain :class:`Command`.
    """

    __slots__ = ()

    def __new__(cls, *args: object, **kwargs: object) -> CheckedCommand:
        command = Command(*args, **kwargs)  # type: ignore[arg-type]
        _require_joint_vector("motor_torque_nm", command.motor_torque_nm)
        return tuple.__new__(cls, command)

    @classmethod
    def _make(cls, iterable: object) -> Command:  # type: ignore[override]
        """A plain :class:`Command` (``_replace`` builds through this: its new values are not checked)."""
        return Command._make(iterable)  # type: ignore[arg-type]


def _read_only_zeros() -> FloatArray:
    zeros = np.zeros(N_JOINTS)
    zeros.flags.writeable = False
    return zeros


#: Torque off: drives disabled, zero torque (a :class:`CheckedCommand`).
TORQUE_OFF = CheckedCommand(_read_only_zeros(), False)


class DriveReaction(NamedTuple):
    """What every drive does by itself when it loses the master (a crashed runtime, a cut bus).

    The runtime can act on every fault it sees; when the runtime itself goes silent only the drives
    are left. ``ramp_s`` None: each drive disables at once (category 0: the arm drops); a number:
    each drive ramps its torque from the last target to zero over ``ramp_s`` seconds, then disables
    (category 1 done by the drive: the arm sinks over that time instead of dropping). Declared in
    ``fsm_spec.yaml`` (``drive_reactions``), handed to the backend before :meth:`Hal.open`.
    """

    ramp_s: float | None


class HalFaultError(HalError):
    """A backend fault latched outside the tick (bus error, lost heartbeat, thread crash)."""


class HalBusFaultError(HalFaultError):
    """The field bus itself failed (a CAN controller bus-off or error-passive): nothing can be commanded reliably.

    The runtime meets it with the ``bus`` fault's reaction, not the ``hal`` one's (a read that failed once).
    """


#: How long consecutive enabled commands may take to bring every healthy drive to ENABLED, s
#: (CiA 402: shutdown, switch on, enable operation; each one or two SYNC periods on a bus).
ENABLE_WITHIN_S = 0.05
#: Longest a :meth:`Hal.read` or :meth:`Hal.write` call may take, s (what the contract suite
#: tolerates on a busy test machine; the loop's budget is a fraction of one 1 ms tick).
NEVER_BLOCKS_S = 0.05


class Hal(ABC):
    """A DAROR-01 as the runtime sees it: read a sample, write a command, nothing else in the tick.

    The contract (checked for every backend by ``tests/hal_contract.py``):

    * **identity**: ``kind`` names the backend, ``rate_hz`` is positive and finite,
      :attr:`virtual_time` and :attr:`drives_hardware` are never both true, and a backend that
      drives hardware has no :attr:`world`.
    * **lifecycle**: :meth:`read` and :meth:`write` before :meth:`open` or after :meth:`close`
      raise :class:`~hal.errors.HalNotOpenError`; :meth:`close` is safe twice and before
      :meth:`open`; :meth:`open` after :meth:`close` starts a new session with every drive
      disabled; ``with hal:`` opens and closes.
    * **never blocks**: every :meth:`read` and :meth:`write` returns within
      :data:`NEVER_BLOCKS_S`, whatever the drives or the bus do.
    * **one reading per tick**: in consecutive ticks (``read(); write()``) ``seq`` increases by
      exactly one; reading again before the next :meth:`write` gives the same ``seq``; ``t_s``
      never decreases. On a backend with :attr:`virtual_time` the first sample after
      :meth:`open` has ``seq`` 0 at ``t_s`` 0 and each tick advances ``t_s`` by ``1 / rate_hz``
      (however long the tick took); on any other backend ``t_s`` follows the wall clock.
    * **torque only on request**: no drive is ENABLED unless the last command written was an
      enabled one; the first sample after :meth:`open` shows every drive DISABLED; after a write
      of a disabled command the next sample shows no drive ENABLED and the drives apply no torque
      (whatever the command's torque: switching off always works). Consecutive enabled commands
      bring every healthy drive to ENABLED within :data:`ENABLE_WITHIN_S`.
    * **one joint off**: after a write of an enabled command whose ``joints_off`` names a joint,
      the next sample shows that joint's drive not ENABLED and it applies no torque, while the
      other drives stay enabled and follow the command; enabled commands without it bring the
      drive back within :data:`ENABLE_WITHIN_S`.
    * **drive limits**: an enabled torque beyond the drive's peak (``description.sea.max_motor_torque_nm``)
      is saturated by the drive at the peak, not refused. An enabled command with a non-finite
      torque raises :class:`~hal.errors.HalError`, one not of shape (4,) raises
      :class:`~hal.errors.ShapeError`; either way torque is removed first (the next sample shows
      no drive ENABLED).
    * **faults**: a fault latched outside the tick is raised as :class:`HalFaultError` by the next
      :meth:`read`, once; the read after returns a sample. A drive in fault reports
      :attr:`DriveState.FAULT` with a non-zero code and applies no torque until its fault is
      cleared.

    ``enable``/``disable`` may take several ticks on real drives (CiA 402 state machine); they
    are requests that :meth:`write` carries out step by step, never blocking calls.
    """

    #: Registry name (:mod:`hal.registry`): ``sim``, ``can-sim``, ``can``, or a plug-in's.
    kind: str = ""
    #: True if the backend owns its time: each :meth:`write` advances it by one tick, however long
    #: the tick took (a simulation). Only such a backend may run lock-step (a virtual clock); a
    #: backend on wall-clock time (hardware, a bus) is refused lock-step by the runtime.
    virtual_time: bool = False
    #: True if the backend moves a real robot, with a child in it. The safe default of a new backend.
    drives_hardware: bool = True

    def __init__(self, description: RobotDescription) -> None:
        self.description = description

    @classmethod
    def from_config(cls, config: AnyHalConfig) -> Hal:
        """The backend built from its configuration (:mod:`hal.config`), not opened yet.

        Raises:
            BackendUnavailableError: this backend cannot be built from a configuration.
            InputError: the configuration names a file or scenario that cannot be loaded.
        """
        raise BackendUnavailableError(f"HAL backend {cls.kind or cls.__name__!r} cannot be built from a configuration")

    @property
    def world(self) -> SimulatedWorld | None:
        """The simulated world around the robot (pilot, e-stop buttons, fault injection), or None.

        None on a backend that drives hardware: there, people and physics are the world. Reading it
        changes nothing (a pilot enters only by :meth:`~hal.capabilities.SimulatedWorld.seat_pilot`).
        """
        return None

    @property
    def lockstep_batches(self) -> LockStepBatches | None:
        """The backend's compiled tick for lock-step batches (:class:`hal.capabilities.LockStepBatches`), or None.

        Only a backend on :attr:`virtual_time` may offer it (the contract suite checks): a batch
        runs ticks as fast as the CPU allows.
        """
        return None

    def request_fault_reset(self) -> None:
        """Ask every drive in fault to reset it, from the next writes on; never blocks.

        On CiA 402 drives this is one rising edge of controlword bit 7 (a drive whose cause
        persists stays in FAULT); a backend that can bring a lost drive back (a CANopen drive
        that went silent or restarted) starts that here too. The runtime calls it when the
        operator acknowledges a fault. A drive that leaves FAULT reports DISABLED until enabled.
        The default does nothing: a backend whose drive faults clear only with their cause.
        """
        return None

    def set_drive_reaction(self, reaction: DriveReaction) -> None:
        """Configure what the drives do by themselves when they lose the master; call before :meth:`open`.

        A backend whose drives can be configured (CANopen: 0x6007, 0x605A, 0x6087, written at
        start-up) does so at :meth:`open` wherever a drive supports it, and says per drive what it
        got in :meth:`drive_reaction_report`. The default: nothing to configure (a simulated plant
        is stepped by the runtime itself: when the runtime stops, so does its world).
        """
        return None

    def drive_reaction_report(self) -> tuple[str, ...]:
        """After :meth:`open`: one sentence per drive on what it does when it loses the master (empty: nothing applies)."""
        return ()

    @abstractmethod
    def open(self) -> None:
        """Connect (bus, drives or simulator) and start a session; every drive stays disabled."""

    @abstractmethod
    def close(self) -> None:
        """Remove torque and disconnect. Safe to call twice, and before :meth:`open`."""

    @abstractmethod
    def read(self) -> Sample:
        """The newest sample (the same ``seq`` until the next :meth:`write`). Never blocks.

        Raises:
            HalFaultError: a fault the backend latched since the previous read (raised once).
            HalNotOpenError: the backend is not open.
        """

    @abstractmethod
    def write(self, command: Command) -> None:
        """Apply ``command``: the tick's end. Never blocks; a disabled command removes torque at once.

        An enabled torque beyond the drives' peak is saturated at the peak.

        Raises:
            HalError: an enabled command with a non-finite torque (torque is removed first).
            ShapeError: an enabled command's torque is not of shape (4,) (torque is removed first).
            HalNotOpenError: the backend is not open.
        """

    @property
    @abstractmethod
    def rate_hz(self) -> float:
        """The tick rate the backend expects to be read and written at, Hz."""

    def __enter__(self) -> Hal:
        self.open()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def hal_class(kind: str) -> type[Hal]:
    """The backend class registered as ``kind`` (:mod:`hal.registry`; its module imported now).

    Raises:
        HalConfigError: unknown kind.
        BackendUnavailableError: the backend is not built yet (its module or class does not
            exist), it needs a Python package that is not installed (the message names it), or a
            plug-in registered it but cannot be loaded.
        HalError: the backend's module failed to import for another reason (a bug).
    """
    target = backend_entry(kind).target
    cls = import_target(kind, target)
    if not (isinstance(cls, type) and issubclass(cls, Hal)):
        module_name, _, attribute = target.partition(":")
        raise BackendUnavailableError(
            f"HAL backend {kind!r} is not built yet: module {module_name} has no Hal class {attribute}"
        )
    return cls


def open_hal(config: AnyHalConfig) -> Hal:
    """The backend ``config.backend`` built from ``config`` (not opened yet: the runtime opens it).

    Raises:
        HalConfigError: an unknown backend.
        BackendUnavailableError: the backend is not built yet or needs a package that is not
            installed (one line naming what is missing; the command line exits 2).
        InputError: a file or scenario the configuration names cannot be loaded.
    """
    return hal_class(config.backend).from_config(config)
