"""The ``can`` backend (the hardware code path) on a virtual bus, against simulated drives in their own thread.

:class:`CanOnSimulatedDrives` is :class:`hal.canopen.backend.CanHal` exactly as it runs on the
robot (python-can's Notifier thread receives, the wall clock is its time), with the simulated SEA
drives of ``can-sim`` serving the bus from a thread of their own, as real drives answer on their
own time. Opening it switches the drives on; closing it stops their thread. For the HAL contract
suite and the real-time benchmark; never part of the package.

A bus cycle takes time: the drives answer a SYNC from their own thread. A test that reads right
after it wrote would ask for the answers to a SYNC still on the wire, so the rig's
:meth:`CanOnSimulatedDrives.read` first waits until the drives' thread has processed every SYNC
the master sent and the master's receive thread has stored every frame the drives sent, woken by
those events (the drives' thread after each pass over the bus, the receive thread after each frame
it stores), not on a fixed period: the contract counts ticks, not periods, and a check that needs
wall-clock time sleeps itself (the master itself never waits; a loop on the real-time clock, which
does pace the ticks, opens the rig with ``paced=False``).
"""

from __future__ import annotations

import functools
import itertools
import threading
import time

import can
import numpy as np

from hal.canopen.backend import CanHal
from hal.canopen.profile import DriveProfile, resolve_profiles
from hal.canopen.sim.bus import SimulationBus
from hal.canopen.sim.drives import SimulatedDriveSet
from hal.canopen.sim.world import CanSimWorld
from hal.config import CanHalConfig
from hal.interface import Command, Sample
from hal.robot import RobotDescription, load_description
from hal.sim.backend import SimHal
from hal.sim.scenario import Scenario, load_scenario

_CHANNELS = itertools.count(1)


# What a rig is built from, read once a process: frozen models and the EDS's read-only dictionary (a rig
# is made for each of the contract's random sequences: reading the YAML and EDS files again was ~30 ms each).
@functools.cache
def _plant_scenario(name: str) -> Scenario:
    """The scenario's plant, its encoders not quantised (the drives quantise, in the units of their EDS)."""
    scenario = load_scenario(name)
    return scenario.model_copy(update={"sensors": scenario.sensors.model_copy(update={"quantise": False})})


@functools.cache
def _description() -> RobotDescription:
    return load_description()


_PROFILES: dict[tuple[str, float], tuple[DriveProfile, ...]] = {}


def _profiles(settings: CanHalConfig, spring_k_nm_per_rad: float) -> tuple[DriveProfile, ...]:
    """The drives of ``settings`` (:func:`resolve_profiles`), resolved once for every rig configured alike."""
    key = (settings.model_copy(update={"channel": ""}).model_dump_json(), spring_k_nm_per_rad)
    if key not in _PROFILES:
        _PROFILES[key] = resolve_profiles(settings, spring_k_nm_per_rad)
    return _PROFILES[key]


#: The longest a read waits for the drives' thread and the receive thread (a loaded test machine), s.
_ANSWER_WITHIN_S = 0.5


class _DriveBus(SimulationBus):
    """The drives' handle: counts the frames it has put on the bus (:attr:`sent`), for the rig's wait."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.sent = 0
        self._count = threading.Lock()  # the drives' thread sends, and a test's fault injection

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        super().send(msg, timeout)
        with self._count:  # counted once in every receiver's queue
            self.sent += 1


class _MasterBus(SimulationBus):
    """The master's handle: counts the drives' frames its receive thread has stored (:attr:`stored`), and says so.

    The backend's receive thread (python-can's Notifier) takes a frame with :meth:`recv`, hands it to
    its listeners (the backend's stores it), then calls :meth:`recv` again: every frame taken before
    that call is stored.
    """

    def __init__(self, *args: object, answered: threading.Condition, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.stored = 0
        self._taken = 0
        self._answered = answered

    def recv(self, timeout: float | None = None) -> can.Message | None:
        if self._taken != self.stored:
            with self._answered:
                self.stored = self._taken
                self._answered.notify_all()
        message = super().recv(timeout)
        if message is not None and not message.is_error_frame:  # an error frame is no drive's
            self._taken += 1
        return message


class _ThreadedDrives(SimulatedDriveSet):
    """``can-sim``'s drives serving from their thread, saying when they processed the bus (for the rig's wait)."""

    def __init__(self, *args: object, answered: threading.Condition | None) -> None:
        super().__init__(*args)  # type: ignore[arg-type]
        self._answered = answered  # None: nobody waits (a rig paced by a real-time clock)

    def step(self) -> None:
        try:
            super().step()
        finally:
            if self._answered is not None:
                with self._answered:
                    self._answered.notify_all()

    def stop_thread(self) -> None:
        """As :class:`SimulatedDriveSet`'s, the thread woken at once (its blocking receive waits up to 5 ms)."""
        bus = self.bus
        if self._thread is not None and isinstance(bus, SimulationBus):
            self._running.clear()
            bus.put_error_frame(0, b"")  # in its own queue: no drive's frame, only a wake-up
        super().stop_thread()


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
        settings = CanHalConfig(interface="virtual", channel=self._channel, **config)  # type: ignore[arg-type]
        description = _description()
        profiles = _profiles(settings, description.sea.spring_stiffness_nm_per_rad)
        super().__init__(settings, description, profiles=profiles)
        self._plant = SimHal(_plant_scenario(scenario), self.rate_hz, self.description)
        self._drive_bus: SimulationBus | None = None
        #: Notified by the drives' thread after each pass over the bus and by the master's receive thread
        #: after each frame it stored (the rig's wait in :meth:`read`).
        self._answered = threading.Condition()
        #: The master's handle and the drives', counting what they carry, while open (a rig that waits: paced).
        self._counting: tuple[_MasterBus, _DriveBus] | None = None
        self.drives = _ThreadedDrives(
            None, self._plant, self.profiles, settings.master_node_id, answered=self._answered if paced else None
        )
        self._world = CanSimWorld(self._plant.world, self.drives)
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
        if self._paced:
            master_bus = _MasterBus(channel=self._channel, preserve_timestamps=True, answered=self._answered)
            drive_bus = _DriveBus(channel=self._channel, preserve_timestamps=True)
            self._given_bus, self._drive_bus, self._counting = master_bus, drive_bus, (master_bus, drive_bus)
        else:  # nothing counted: the benchmark's threads carry no more than the backend's
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

        After a write: once the drives' thread has processed every SYNC the master sent and the
        master's receive thread has stored every frame the drives sent; on a loaded test machine
        the threads may need longer than a period, which a bus on the robot never does (up to 0.5 s
        is waited).
        """
        self.rig_wait_s = 0.0
        if self._written and self._paced:
            began = time.perf_counter()
            self._written = False
            master = self.master
            with self._answered:
                self._answered.wait_for(lambda: self._cycle_answered(master.syncs), _ANSWER_WITHIN_S)
            self.rig_wait_s = time.perf_counter() - began  # the rig's own pacing: not the backend's time
        return super().read()

    def _cycle_answered(self, syncs: int) -> bool:
        """The drives processed ``syncs`` SYNCs, and everything they sent since (their answers) is stored."""
        if self._counting is None:
            return True
        master_bus, drive_bus = self._counting
        # the SYNC count first: the frames the drives sent for those SYNCs are in ``sent`` read after it
        return self.drives.syncs >= syncs and master_bus.stored >= drive_bus.sent

    def write(self, command: Command) -> None:
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
        self._given_bus = self._drive_bus = self._counting = None
