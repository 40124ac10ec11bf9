"""What a HAL backend hands the contract suite: how to build it on a test bench, and the bench's hooks.

The contract suite (``tests/hal_contract.py``, run by ``tests/hal/test_hal_contract.py``) runs against
every registered backend (:mod:`hal.registry`). A backend's registry entry names a function
(:attr:`hal.registry.BackendEntry.benches`) that returns its :class:`BackendUnderTest` records: a
factory of unopened instances that needs no hardware, plus the few hooks only a test bench has
(latch a bus fault, fault a drive, read back the torque the drives apply). A check that needs a
hook a bench does not offer is skipped for it. A plug-in backend defines its benches the same way
(its own module, named in its :class:`~hal.registry.BackendEntry`); it needs nothing of the tests.

This module holds the built-in backends' benches: ``sim`` (two scenarios and rates) and
``can-sim``. The ``can`` backend has none (it needs drives): the suite runs its class on its CAN
rig (``tests/can_rig.py``), which uses :func:`fault_can_drive` too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hal.capabilities import SimulatedWorld
from hal.config import hal_config
from hal.errors import BackendUnavailableError, HalError
from hal.interface import Command, Hal, HalFaultError, open_hal
from hal.registry import backend_entry, backend_kinds, import_target
from hal.robot import N_JOINTS, FloatArray

__all__ = ["BackendUnderTest", "can_sim_benches", "fault_can_drive", "registered_benches", "sim_benches", "world_of"]


@dataclass(frozen=True)
class BackendUnderTest:
    """A backend as the contract suite sees it.

    Attributes:
        name: the test id (unique among the benches and rigs of the suite).
        backend: the registered backend whose code it runs (a test rig: the backend whose class it
            drives), by which the suite checks that every registered backend is covered.
        make: a new, unopened instance.
        latch_fault: latch a fault outside the tick (a bus error, a lost heartbeat) on an open backend.
        fault_drive: put the drive of joint 1-4 in fault on an open backend.
        applied_torque_nm: the torque the drives apply now (4,) Nm, as a test bench measures it.
        rig_wait_s: the time the last ``read`` spent waiting for the test rig itself (a rig that
            paces wall-clock drives to the bus's period), s: not the backend's time.
    """

    name: str
    backend: str
    make: Callable[[], Hal]
    latch_fault: Callable[[Hal], None] | None = None
    fault_drive: Callable[[Hal, int], None] | None = None
    applied_torque_nm: Callable[[Hal], FloatArray] | None = None
    rig_wait_s: Callable[[Hal], float] | None = None


def world_of(hal: Hal) -> SimulatedWorld:
    """The simulated world of ``hal``.

    Raises:
        HalError: the backend has none (it drives hardware): a bench's hook that needs one cannot run.
    """
    world = hal.world
    if world is None:
        raise HalError(f"the {hal.kind} backend has no simulated world to inject faults into")
    return world


def _applied_torque_nm(hal: Hal) -> FloatArray:
    """What the simulated drives apply, Nm (the simulating backends' ``applied_motor_torque_nm``)."""
    return hal.applied_motor_torque_nm  # type: ignore[attr-defined,no-any-return]


def sim_benches() -> tuple[BackendUnderTest, ...]:
    """The ``sim`` backend twice: the default scenario at 1 kHz, and ``exo`` at 500 Hz with a seed."""
    return (
        BackendUnderTest(
            "sim",
            "sim",
            make=lambda: open_hal(hal_config("sim")),
            latch_fault=lambda hal: world_of(hal).inject_fault("bus"),
            fault_drive=lambda hal, joint: world_of(hal).inject_fault("drive_fault", joint),
            applied_torque_nm=_applied_torque_nm,
        ),
        BackendUnderTest(
            "sim-exo-500Hz",
            "sim",
            make=lambda: open_hal(hal_config("sim", scenario="exo", rate_hz=500.0, seed=7)),
            latch_fault=lambda hal: world_of(hal).inject_fault("bus"),
            fault_drive=lambda hal, joint: world_of(hal).inject_fault("drive_fault", joint, 0x2310),
            applied_torque_nm=_applied_torque_nm,
        ),
    )


def fault_can_drive(hal: Hal, joint: int) -> None:
    """Fault the power stage of drive ``joint`` (1-4) on a CAN backend over simulated drives, and take its EMCY.

    On CAN a drive fault comes with an EMCY, which the next read raises as :class:`HalFaultError`;
    the hook takes it here, so that the suite's next read shows the drive in FAULT.

    Raises:
        HalFaultError: the read raised another fault than the drive's EMCY 0x2310.
        HalError: the read raised nothing: the drive faulted without an EMCY.
    """
    world_of(hal).inject_fault("drive_fault", joint)
    hal.write(Command(np.full(N_JOINTS, 1.0), True))
    expected = f"drive {joint}: EMCY 0x2310"
    try:
        hal.read()
    except HalFaultError as exc:
        if expected in str(exc):
            return
        raise
    raise HalError(f"drive {joint} was faulted but the next read raised no HalFaultError ({expected!r})")


def can_sim_benches() -> tuple[BackendUnderTest, ...]:
    """The ``can-sim`` backend: the CAN master in lock-step over simulated drives, its default configuration."""
    return (
        BackendUnderTest(
            "can-sim",
            "can-sim",
            make=lambda: open_hal(hal_config("can-sim")),
            latch_fault=lambda hal: world_of(hal).inject_fault("emcy", 1),
            fault_drive=fault_can_drive,
            applied_torque_nm=_applied_torque_nm,
        ),
    )


def registered_benches() -> tuple[BackendUnderTest, ...]:
    """The benches of every registered backend that has them, in the registry's order (plug-ins included).

    Raises:
        BackendUnavailableError: a backend's benches function cannot be imported (one line naming it).
        HalError: a benches function gives something else than :class:`BackendUnderTest` records of its
            own backend.
    """
    benches: list[BackendUnderTest] = []
    for kind in backend_kinds():
        target = backend_entry(kind).benches
        if target is None:
            continue
        function = import_target(kind, target)
        if not callable(function):
            raise BackendUnavailableError(f"HAL backend {kind!r}: its benches {target} is not a function")
        given = tuple(function())
        wrong = [b for b in given if not (isinstance(b, BackendUnderTest) and b.backend == kind)]
        if wrong:
            raise HalError(
                f"HAL backend {kind!r}: its benches {target} gave {wrong[0]!r}; "
                f"expected hal.testing.BackendUnderTest records with backend={kind!r}"
            )
        benches += given
    return tuple(benches)
