"""The ``can`` backend (the hardware code path) on a virtual bus, against simulated drives in their own thread.

:class:`CanOnSimulatedDrives` is :class:`hal.canopen.backend.CanHal` exactly as it runs on the
robot (python-can's Notifier thread receives, the wall clock is its time), with the simulated SEA
drives of ``can-sim`` serving the bus from a thread of their own, as real drives answer on their
own time. Opening it switches the drives on; closing it stops their thread. For the HAL contract
suite and the real-time benchmark; never part of the package.

A bus cycle takes time: four drives' frames need 1.4 ms of a 1 Mbit/s bus, and the drives answer a
SYNC from their own thread. A test that reads right after it wrote would ask for the answers to a
SYNC still on the wire, so the rig's :meth:`CanOnSimulatedDrives.read` comes one period after the
last write, as the runtime's real-time clock starts the next tick (the master itself never waits).
"""

from __future__ import annotations

import itertools
import time

import can
import numpy as np

from hal.canopen.backend import CanHal
from hal.canopen.sim.bus import SimulationBus
from hal.canopen.sim.drives import SimulatedDriveSet
from hal.canopen.sim.world import CanSimWorld
from hal.config import CanHalConfig
from hal.interface import Command, Sample
from hal.sim.backend import SimHal
from hal.sim.scenario import load_scenario

_CHANNELS = itertools.count(1)


class CanOnSimulatedDrives(CanHal):
    """``can`` over a virtual bus; the drives of ``can-sim`` answer from their thread (see the module docstring).

    Its own code is the hardware backend's; what it moves is a simulation, so it says so
    (``drives_hardware`` False, with a simulated world) while its time stays the wall clock's.
    """

    kind = "can-rig"
    drives_hardware = False

    def __init__(self, scenario: str = "exo_dummy_arm", paced: bool = True, **config: object) -> None:
        self._paced = paced  # False: a real-time clock paces the reads (a loop on RealTimeClock)
        self._channel = f"can-rig-{next(_CHANNELS)}"
        plant_scenario = load_scenario(scenario)
        plant_scenario = plant_scenario.model_copy(
            update={"sensors": plant_scenario.sensors.model_copy(update={"quantise": False})}
        )
        settings = CanHalConfig(interface="virtual", channel=self._channel, **config)  # type: ignore[arg-type]
        super().__init__(settings)
        self._plant = SimHal(plant_scenario, self.rate_hz, self.description)
        self._drive_bus: can.BusABC | None = None
        self.drives = SimulatedDriveSet(None, self._plant, self.profiles, settings.master_node_id)
        self._world = CanSimWorld(self._plant.world, self.drives)
        self._period_s = 1.0 / self.rate_hz
        self._last_write_s = 0.0
        self._written = False
        #: The time the last read waited for the drives' thread (the rig's pacing), s: not the backend's.
        self.rig_wait_s = 0.0

    @property
    def world(self) -> CanSimWorld:  # type: ignore[override]
        return self._world

    @property
    def applied_motor_torque_nm(self) -> np.ndarray:
        return self.drives.applied_motor_torque_nm

    def open(self) -> None:
        """Both bus handles new, the drives switched on and serving from their thread, then the master's start-up."""
        if self._is_open:
            self.close()
        self._given_bus = SimulationBus(channel=self._channel, preserve_timestamps=True)
        self._drive_bus = SimulationBus(channel=self._channel, preserve_timestamps=True)
        self.drives.attach(self._drive_bus)
        self.drives.power_on()
        started = time.monotonic()
        self.drives.start_thread(lambda: time.monotonic() - started)
        try:
            super().open()
        except Exception:
            self._release()
            raise

    def read(self) -> Sample:
        """The master's read once the bus finished the last cycle (see the module docstring).

        At least one period after the last write, and once the drives answered its SYNC and the
        master's receive thread has taken their frames: on a loaded test machine the threads may
        need longer than a period, which a bus on the robot never does (up to 0.5 s is waited).
        """
        self.rig_wait_s = 0.0
        if self._written and self._paced:
            began = time.perf_counter()
            self._written = False
            wait = self._last_write_s + self._period_s - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            deadline = time.perf_counter() + 0.5
            master = self.master
            while self.drives.syncs < master.syncs and time.perf_counter() < deadline:
                time.sleep(0.0002)
            settled = -1
            while time.perf_counter() < deadline:  # the receive thread has taken every frame sent
                pending = self._drive_bus_backlog()
                if pending == 0 and settled == 0:
                    break
                settled = pending
                time.sleep(0.0002)
            self.rig_wait_s = time.perf_counter() - began  # the rig's own pacing: not the backend's time
        return super().read()

    def _drive_bus_backlog(self) -> int:
        """Frames the master's handle has not taken yet (its queue on the virtual bus)."""
        bus = self._given_bus
        return 0 if bus is None else bus.queue.qsize()

    def write(self, command: Command) -> None:
        self._last_write_s = time.perf_counter()
        self._written = True
        super().write(command)

    def close(self) -> None:
        try:
            super().close()
        finally:
            self._release()

    def _release(self) -> None:
        self.drives.stop_thread()
        self.drives.attach(None)
        for bus in (self._given_bus, self._drive_bus):
            if bus is not None:
                bus.shutdown()
        self._given_bus = self._drive_bus = None
