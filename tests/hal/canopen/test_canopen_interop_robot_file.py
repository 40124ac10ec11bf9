"""The second drive family (maxon EPOS4, examples/robot/epos4.yaml) on the independent stack: durand drives built from its EDS.

The drives know the vendor's EDS and their robot file node (read as YAML by the harness,
``tests/durand_drives.py``), nothing of ``hal``. The backend is the ``can`` backend on the robot
file, unchanged but for the bus (python-can ``virtual``).

A reasoned subset of the demo session: durand runs on wall-clock threads (a whole session of
24 minutes of robot time would take 24 minutes), so what the session needs of the bus is run
here once each: the start-up (identity 0x1018 from the EDS's [DeviceInfo], 0x6502 with the
torque modes, the robot file's 0x6076 written and read back, 0x60C2 written to the cycle, the
derived PDOs configured in CiA 301's order), enabling every drive within the contract time, a
torque command in the EDS's scale (motor per mille times the gear ratio), the encoders and the
spring torque k (theta - q) read back, both e-stops on 0x60FD (wired normally closed), torque
off, and close leaving every drive disabled. The whole session runs on the project's simulated
drives built from the same EDS (tests/hal/canopen/test_canopen_robot_golden.py's sibling in
tests/hal/canopen/test_canopen_robot_file.py and the slow session test).
"""

from __future__ import annotations

import gc
import itertools
import math
import time
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import can
import durand
import numpy as np
import pytest
from durand.scheduler import get_scheduler
from durand.services.nmt import StateEnum

from hal.canopen.backend import CanHal
from hal.config import CanHalConfig, load_hal_config
from hal.interface import ENABLE_WITHIN_S, Command, DriveState, Sample
from hal.robot import load_description
from tests.durand_drives import DevicePower, DurandDrives, robot_file_drives, sdo_responses

#: The drives are durand nodes on their own threads, the master on its receive thread: wall-clock time.
pytestmark = pytest.mark.realtime

ROBOT_FILE = Path(__file__).resolve().parents[3] / "examples" / "robot" / "epos4.yaml"
DRIVES = robot_file_drives(ROBOT_FILE)
NODE_IDS = tuple(sorted(DRIVES))
TIMEOUT_S = 2.0
NM_PER_PERMILLE = 0.160 * 100 / 1000  # 0x6076 = 160 mNm of the motor, a 100:1 gearbox
_CHANNELS = itertools.count(1)


class Rig:
    def __init__(self, drives: DurandDrives, hal: CanHal) -> None:
        self.drives, self.hal = drives, hal

    def cycle(self, torque_nm: tuple[float, ...] = (0.0,) * 4, enable: bool = False) -> Sample:
        """One cycle: write, wait until every drive handled its SYNC and the master holds their TPDOs, read."""
        before = self.drives.sync_counts()
        self.hal.write(Command(np.asarray(torque_nm, dtype=float), enable))
        self.drives.wait_syncs({n: c + 1 for n, c in before.items()}, TIMEOUT_S)
        time.sleep(0.002)  # the TPDOs' way through the virtual bus to the backend's receive thread
        return self.hal.read()


@pytest.fixture
def rig() -> Iterator[Rig]:
    channel = f"durand-epos4-{next(_CHANNELS)}"
    with ExitStack() as stack:
        drives = stack.enter_context(DurandDrives(channel, NODE_IDS, drives=DRIVES))
        bus = can.Bus(interface="virtual", channel=channel)
        stack.callback(bus.shutdown)
        config = load_hal_config(ROBOT_FILE)
        assert isinstance(config, CanHalConfig)
        hal = CanHal(config.model_copy(update={"interface": "virtual", "channel": channel}), bus=bus)
        stack.callback(hal.close)
        for n in NODE_IDS:
            drives.call(lambda n=n: _heartbeat_period_from_operational(drives.node(n)))
        # The wall-clock start-up the tests time: a full collection of this process's heap (late in the
        # suite, thousands of tests' objects: hundreds of ms holding the GIL) must not stall durand's
        # threads meanwhile (a first OPERATIONAL heartbeat 0.45 s after NMT start once, in a clean run).
        gc.disable()
        try:
            hal.open()
        finally:
            gc.enable()
        yield Rig(drives, hal)
        hal.close()
        assert [drives.power(n) for n in NODE_IDS] == [DevicePower.SWITCH_ON_DISABLED] * 4  # close disables
    assert drives.errors == [], "errors in the drives' threads"


def _heartbeat_period_from_operational(node: durand.MinimalNode) -> None:
    """The node's heartbeat producer starts its period again when the node becomes OPERATIONAL (sending nothing then).

    durand's producer keeps the phase of the 0x1017 write, so its first OPERATIONAL heartbeat came
    anywhere from 0 to 100 ms after NMT start, by how long the wall-clock start-up took between
    the write and the start (17.7 ms once under load: too short a wait to show whether the master
    keeps the SYNC going). Restarted at the state change, as many drives do, it comes one period
    after NMT start every run. Runs in durand's threads, holding its lock (tests/durand_drives.py);
    durand 0.5.0's producer (its ``_handle`` and ``_process_heartbeat``) is used as it uses itself.
    """
    producer = node.heartbeat_producer

    def restart(state: StateEnum) -> None:
        period_ms = int(node.object_dictionary.read(0x1017, 0))
        if state != StateEnum.OPERATIONAL or producer._handle is None or period_ms == 0:
            return
        scheduler = get_scheduler()
        scheduler.cancel(producer._handle)
        producer._handle = scheduler.add(period_ms / 1000, producer._process_heartbeat, args=(period_ms / 1000,))

    node.nmt.state_callbacks.add(restart)


def test_start_up_configures_epos4_drives_that_know_only_their_eds(rig: Rig) -> None:
    for n in NODE_IDS:
        reads = {(i, s): v for kind, i, s, v in sdo_responses(rig.drives.sent(n), n) if kind == "read"}
        assert reads[(0x1018, 1)] == 0xFB  # maxon's vendor id, from the EDS's [DeviceInfo]
        assert reads[(0x1018, 2)] == 0x60500000
        assert reads[(0x6502, 0)] == 0x208  # tq and cst
        assert reads[(0x6076, 0)] == 160  # the robot file's sdo_init, read back
        assert reads[(0x6061, 0)] == 10  # cyclic synchronous torque, read back
        assert rig.drives.read(n, 0x60C2, 1) == 25  # the cycle, 2.5 ms = 25 x 10^-4 s
        assert rig.drives.read(n, 0x60C2, 2) == -4
        assert rig.drives.read(n, 0x1A01, 1) == 0x60E40220  # TPDO2: the link encoder, sensor 2
        if n == NODE_IDS[0]:  # joint 1's drive reads the e-stop chain: its digital inputs too
            assert (rig.drives.read(n, 0x1A01, 0), rig.drives.read(n, 0x1A01, 2)) == (2, 0x60FD0020)
        else:  # the others: the link encoder alone (the worst cycle's budget, D160)
            assert rig.drives.read(n, 0x1A01, 0) == 1


def test_torque_positions_spring_torque_and_estops_cross_the_bus_in_the_robot_files_units(rig: Rig) -> None:
    k = load_description().sea.spring_stiffness_nm_per_rad
    theta, q = (0.30, -0.20, 0.50, 1.00), (0.29, -0.21, 0.52, 1.00)
    written = {n: rig.drives.set_joint(n, theta[j], q[j], 0.0) for j, n in enumerate(NODE_IDS)}
    sample = rig.cycle()
    for _ in range(math.ceil(ENABLE_WITHIN_S * rig.hal.rate_hz)):
        sample = rig.cycle((0.8, -0.8, 0.0, 0.0), enable=True)
        if sample.drives == (DriveState.ENABLED,) * 4:
            break
    assert sample.drives == (DriveState.ENABLED,) * 4
    rig.cycle((0.8, -0.8, 0.0, 0.0), enable=True)
    assert [rig.drives.applied_torque_permille(n) for n in NODE_IDS] == [50, -50, 0, 0]  # 0.8 N m / 0.016
    for j, n in enumerate(NODE_IDS):
        wiring = DRIVES[n][1]
        assert sample.theta_rad[j] == written[n].motor_increments * wiring.rad_per_motor_count
        assert sample.q_rad[j] == written[n].load_increments * wiring.rad_per_link_count
        assert sample.tau_nm[j] == pytest.approx(k * (sample.theta_rad[j] - sample.q_rad[j]), abs=1e-12)
    assert sample.estop == (False, False)
    rig.drives.set_estop(NODE_IDS[0], operator=True, pilot=False)  # the chain is wired to joint 1's drive
    assert rig.cycle((0.8, -0.8, 0.0, 0.0), enable=True).estop == (True, False)
    assert rig.drives.read(NODE_IDS[0], 0x60FD) == 1 << 17  # normally closed: the operator's bit 16 cleared
    rig.drives.set_estop(NODE_IDS[0], operator=False, pilot=True)
    assert rig.cycle().estop == (False, True)
    assert [rig.drives.applied_torque_permille(n) for n in NODE_IDS] == [0, 0, 0, 0]  # torque off


def test_start_up_keeps_the_sync_going_while_it_waits_for_the_operational_heartbeats(rig: Rig) -> None:
    """From NMT start on the master runs the bus (H31): durand sends its first OPERATIONAL heartbeat one period
    (100 ms) after NMT start, and meanwhile every drive gets the SYNC at the loop's rate, never a silent bus."""
    period_s = 1.0 / rig.hal.rate_hz
    for n in NODE_IDS:
        received = rig.drives.received(n)
        start = next(f for f in received if f.cob_id == 0x000 and f.data in (bytes((0x01, n)), b"\x01\x00"))
        operational = next(f for f in rig.drives.sent(n) if f.cob_id == 0x700 + n and f.data == b"\x05")
        syncs = [f.t_s for f in received if f.cob_id == 0x080 and start.t_s <= f.t_s <= operational.t_s]
        waited_s = operational.t_s - start.t_s
        assert waited_s == pytest.approx(0.1, abs=0.05)  # no heartbeat at the state change: one period after it
        assert len(syncs) >= waited_s / period_s / 4  # at the loop's rate, a slow machine's jitter allowed
        assert max(b - a for a, b in itertools.pairwise([start.t_s, *syncs])) < 0.05  # never a silent bus
