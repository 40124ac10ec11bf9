"""Every HAL backend against the contract suite (tests/hal_contract.py), python-can's back-to-back style.

The list :data:`BACKENDS_UNDER_TEST` is where a backend joins: ``sim`` (two scenarios and rates)
now, ``can-sim`` and ``can`` (against a virtual bus) once ``hal/canopen`` exists (issue 12). The
stand-in hardware backend (tests/standin_drives.py: wall-clock time, CiA 402 drives) runs the same
checks; the ones about virtual time are skipped for it, as they will be for ``can``.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from hal.config import hal_config
from hal.interface import BACKENDS, Command, HalFaultError, hal_class, open_hal, register_backend
from hal.robot import N_JOINTS
from tests.can_rig import CanOnSimulatedDrives
from tests.hal_contract import BackendUnderTest, HalContract
from tests.standin_drives import TARGET

STANDIN = "stand-in"


def _world(hal: Any) -> Any:
    world = hal.world
    assert world is not None
    return world


SIM = BackendUnderTest(
    "sim",
    make=lambda: open_hal(hal_config("sim")),
    latch_fault=lambda hal: _world(hal).inject_fault("bus"),
    fault_drive=lambda hal, joint: _world(hal).inject_fault("drive_fault", joint),
    applied_torque_nm=lambda hal: hal.applied_motor_torque_nm,
)
SIM_EXO_500HZ = BackendUnderTest(
    "sim-exo-500Hz",
    make=lambda: open_hal(hal_config("sim", scenario="exo", rate_hz=500.0, seed=7)),
    latch_fault=lambda hal: _world(hal).inject_fault("bus"),
    fault_drive=lambda hal, joint: _world(hal).inject_fault("drive_fault", joint, 0x2310),
    applied_torque_nm=lambda hal: hal.applied_motor_torque_nm,
)
STANDIN_DRIVES = BackendUnderTest(
    STANDIN,
    make=lambda: hal_class(STANDIN)(),  # through the registry, as the runtime would get it
    latch_fault=lambda hal: hal.lose_heartbeat(2),
    fault_drive=lambda hal, joint: hal.fault_drive(joint),
    applied_torque_nm=lambda hal: hal.applied_motor_torque_nm,
)


def _fault_can_drive(hal: Any, joint: int) -> None:
    """The drive's power stage faults; its EMCY is taken here (on CAN a drive fault comes with one: HalFaultError)."""
    _world(hal).inject_fault("drive_fault", joint)
    hal.write(Command(np.full(N_JOINTS, 1.0), True))
    with pytest.raises(HalFaultError, match=f"drive {joint}: EMCY 0x2310"):
        hal.read()


CAN_SIM = BackendUnderTest(
    "can-sim",
    make=lambda: open_hal(hal_config("can-sim")),
    latch_fault=lambda hal: _world(hal).inject_fault("emcy", 1),
    fault_drive=_fault_can_drive,
    applied_torque_nm=lambda hal: hal.applied_motor_torque_nm,
)

CAN_RIG = BackendUnderTest(
    "can-on-simulated-drives",
    # The drives watch the master's heartbeat, which the master sends only as it ticks (a stalled
    # runtime stops the drives: D81); a test's pauses between calls are not stalls of a runtime.
    # A loaded test machine may starve the drives' thread for a while: generous start-up timeouts.
    # Wall-clock drives behind a test that pauses between steps as hypothesis thinks: the watchdogs' times are
    # the test's, not the robot's (their behaviour is tested in test_canopen_master.py and test_canopen_stop_reactions.py).
    make=lambda: CanOnSimulatedDrives(
        heartbeat_consumer_ms=5000, sdo_timeout_ms=10_000, boot_timeout_ms=10_000, rpdo_deadline_ms=5000
    ),
    latch_fault=lambda hal: _world(hal).inject_fault("emcy", 1),
    fault_drive=_fault_can_drive,
    applied_torque_nm=lambda hal: hal.applied_motor_torque_nm,
    rig_wait_s=lambda hal: hal.rig_wait_s,  # type: ignore[attr-defined]
)

#: Every backend the contract runs against: the CAN master both in lock-step over simulated drives
#: (can-sim) and as on the robot (Notifier thread, wall clock) against drives answering from a thread.
BACKENDS_UNDER_TEST = [SIM, SIM_EXO_500HZ, STANDIN_DRIVES, CAN_SIM, CAN_RIG]


@pytest.fixture(scope="module", autouse=True)
def standin_registered() -> Iterator[None]:
    """The stand-in hardware backend in the registry for this module only."""
    previous = register_backend(STANDIN, TARGET)
    yield
    if previous is None:
        del BACKENDS[STANDIN]
    else:
        BACKENDS[STANDIN] = previous


@pytest.fixture(params=BACKENDS_UNDER_TEST, ids=lambda backend: backend.name)
def backend(request: pytest.FixtureRequest) -> BackendUnderTest:
    return request.param  # type: ignore[no-any-return]


class TestHalContract(HalContract):
    """The contract suite, once per backend under test."""
