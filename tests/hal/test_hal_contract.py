"""Every HAL backend against the contract suite (tests/hal_contract.py), python-can's back-to-back style.

Which backends run comes from the registry (:mod:`hal.registry`): each registered backend's
entry names its contract benches (:func:`hal.testing.registered_benches`: ``sim`` in two
scenarios and rates, ``can-sim``, and any plug-in's, such as the stand-in hardware backend of
tests/standin_drives.py when its outside package is installed: tests/test_boundaries.py runs this
module so), plus the test rigs listed here, which run a backend's code on something that is not
its hardware: the ``can`` backend, as on the robot (Notifier thread, wall clock), against drives
answering from a thread. A backend joins by registering; nothing here names it. The checks about
virtual time are skipped for a backend on wall-clock time.
"""

from __future__ import annotations

import pytest

from hal.interface import backend_kinds
from hal.testing import BackendUnderTest, fault_can_drive, registered_benches, world_of
from tests.can_rig import CanOnSimulatedDrives
from tests.hal_contract import HalContract

CAN_RIG = BackendUnderTest(
    "can-on-simulated-drives",
    "can",
    # The drives watch the master's heartbeat, which the master sends only as it ticks (a stalled
    # runtime stops the drives: D81); a test's pauses between calls are not stalls of a runtime.
    # A loaded test machine may starve the drives' thread for a while: generous start-up timeouts.
    # Wall-clock drives behind a test that pauses between steps as hypothesis thinks: the watchdogs' times are
    # the test's, not the robot's (their behaviour is tested in test_canopen_master.py and test_canopen_stop_reactions.py).
    make=lambda: CanOnSimulatedDrives(
        heartbeat_consumer_ms=5000, sdo_timeout_ms=10_000, boot_timeout_ms=10_000, rpdo_deadline_ms=5000
    ),
    latch_fault=lambda hal: world_of(hal).inject_fault("emcy", 1),
    fault_drive=fault_can_drive,
    applied_torque_nm=lambda hal: hal.applied_motor_torque_nm,  # type: ignore[attr-defined]
    rig_wait_s=lambda hal: hal.rig_wait_s,  # type: ignore[attr-defined]
)

#: The test rigs: a registered backend's code on a bench that is not its hardware.
RIGS = [CAN_RIG]

#: Every backend the contract runs against: the registered backends' benches, then the rigs.
BACKENDS_UNDER_TEST = [*registered_benches(), *RIGS]


def test_every_registered_backend_is_under_the_contract() -> None:
    """A registered backend without benches (it needs hardware) must have a rig here; ids are unique."""
    covered = {b.backend for b in BACKENDS_UNDER_TEST}
    assert [kind for kind in backend_kinds() if kind not in covered] == []
    names = [b.name for b in BACKENDS_UNDER_TEST]
    assert len(names) == len(set(names)), names


@pytest.fixture(params=BACKENDS_UNDER_TEST, ids=lambda backend: backend.name)
def backend(request: pytest.FixtureRequest) -> BackendUnderTest:
    return request.param  # type: ignore[no-any-return]


class TestHalContract(HalContract):
    """The contract suite, once per backend under test."""
