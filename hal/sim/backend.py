"""The simulated HAL backend: the dynamic plant behind the :class:`hal.interface.Hal` contract.

Time belongs to the simulator (lock-step): :meth:`SimHal.read` returns the sample at the current
plant time and :meth:`SimHal.write` queues the command and advances the plant by exactly one tick
``1 / rate_hz``. The loop's usual ``read(); write()`` is therefore one tick of robot time, however
fast the CPU runs it.

What the drives do, per tick, in this order (``write``):

1. the command enters a FIFO and the one written ``command_delay_ticks`` earlier comes out; a
   disabled command instead empties the FIFO and removes torque at once (a drive's power stage
   switches off immediately, it does not wait for the bus);
2. joints whose drive has an injected fault get no torque; the plant integrates one RK4 step
   with the motor torque and the pilot's external torque held constant;
3. both encoders of every joint are read (white noise, quantisation), the drive updates its
   velocity estimate (low-passed encoder difference) and the measured spring torque (with the
   direction-dependent error of Sec. 2.2.2, computed with the nominal spring constant; the
   scenario's undeclared angle offset and torque drift on top, docs/simulation.md).

The backend's time is virtual (:attr:`SimHal.virtual_time`): it may run lock-step, and it
drives no hardware. The world around the plant (pilot, e-stop buttons, fault injection) is
:attr:`SimHal.world`, a :class:`hal.capabilities.SimulatedWorld` (:mod:`hal.sim.world`).

Sim-only hooks for tests (not part of the Hal contract; the world uses them):
:meth:`SimHal.set_external_torque`, :meth:`SimHal.press_estop`, :meth:`SimHal.inject_fault`,
:meth:`SimHal.clear_faults`, :meth:`SimHal.truth`. Randomness comes only from the scenario seed
(stream :data:`STREAM_SIM_ENCODERS`), so two instances of one scenario produce identical samples.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from hal.capabilities import PLANT_FAULT_KINDS, BackendBatch, FaultKind
from hal.errors import DescriptionError, HalError, HalNotOpenError, InputError, ShapeError
from hal.interface import CheckedCommand, CheckedSample, Command, DriveState, Hal, HalFaultError, Sample
from hal.kernels import BACKEND_STEP, CompiledFunction
from hal.robot import N_JOINTS, FloatArray, RobotDescription, load_description
from hal.sim import dynamics
from hal.sim.pilot import SimulatedPilot
from hal.sim.plant import DynamicPlant, PlantTruth, joint_vector
from hal.sim.scenario import Scenario, load_scenario
from hal.sim.sensors import SECONDS_PER_MINUTE
from hal.sim.static_dataset import stream

if TYPE_CHECKING:
    from hal.config import AnyHalConfig
    from hal.sim.world import PlantWorld

__all__ = ["DEFAULT_DRIVE_FAULT_CODE", "STREAM_SIM_ENCODERS", "ExternalTorque", "FaultKind", "SimHal"]

#: Random stream of the encoder noise; ids 1-5 belong to hal.sim.static_dataset.
STREAM_SIM_ENCODERS = 6
#: Fault code a drive reports for an injected ``drive_fault`` without a value (CiA 301 "generic error").
DEFAULT_DRIVE_FAULT_CODE = 0x1000

_DQ = slice(2 * N_JOINTS, 3 * N_JOINTS)  # q' in the plant state [q, theta, q', theta']
_FLOAT64 = np.dtype(np.float64)
_JOINT_SHAPE = (N_JOINTS,)
#: Ticks of readings per block (:meth:`SimHal._new_block`): 256 ticks of 4 x 4 float64 are 32 kB.
_BLOCK_TICKS = 256
_BLOCK_ROWS = 4 * _BLOCK_TICKS
_new_tuple = tuple.__new__  # builds the Sample without the NamedTuple's Python-level __new__ (every tick)

#: The pilot pushing: f(t_s, q_true_rad, dq_true_rad_s) -> (4,) external torque on the links, Nm.
ExternalTorque = Callable[[float, FloatArray, FloatArray], FloatArray]


class SimHal(Hal):
    """The DAROR-01 as a lock-step simulation of one scenario.

    Args:
        scenario: a :class:`Scenario` or the name/path of one (default the robot with the Dummy Arm).
        rate_hz: tick rate; one :meth:`write` advances the plant by ``1 / rate_hz``.
        description: the robot description; default the one the scenario names.

    Raises:
        DescriptionError: the scenario cannot be loaded or simulated dynamically (no drive train,
            a body without inertia), or the plant is not stable under RK4 at ``rate_hz``.
        InputError: ``rate_hz`` is not positive and finite.

    Attributes:
        time_s: plant time now, s (the ticks written since the session opened times the tick's
            period). Read it; only the backend moves it. A plain attribute, not a property: the
            CANopen master over this plant reads it ten times a cycle (issue 25).
    """

    kind = "sim"
    virtual_time = True
    drives_hardware = False

    def __init__(
        self,
        scenario: Scenario | str = "exo_dummy_arm",
        rate_hz: float = 1000.0,
        description: RobotDescription | None = None,
    ) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise InputError(f"rate_hz = {rate_hz}: must be positive and finite")
        self.scenario = load_scenario(scenario) if isinstance(scenario, str) else scenario
        super().__init__(description or self.scenario.description())
        self._rate_hz = float(rate_hz)
        self._dt = 1.0 / self._rate_hz
        self.time_s = 0.0
        self._plant = DynamicPlant(self.scenario, self.description)
        if self._dt > self._plant.max_dt_s:
            raise DescriptionError(
                f"scenario {self.scenario.name!r}: at {rate_hz:g} Hz the tick of {self._dt:.3g} s exceeds the plant's "
                f"stable step of {self._plant.max_dt_s:.3g} s; raise rate_hz above {1 / self._plant.max_dt_s:.0f} Hz"
            )
        sensors = self.scenario.sensors
        self._drive_vector = np.zeros(dynamics.DRIVE_VECTOR_SIZE)
        # The drives compute torque with the description's nominal constant, not the plant's
        # as-built one (scenario sea_stiffness_scale): a stiffness error reads as a torque gain error.
        self._drive_vector[dynamics.S_STIFFNESS : dynamics.S_STIFFNESS + N_JOINTS] = (
            self.description.sea.spring_stiffness_nm_per_rad
        )
        self._drive_vector[dynamics.S_RESOLUTION] = self.description.sea.encoder_resolution_rad
        self._drive_vector[dynamics.S_QUANTISE] = 1.0 if sensors.quantise else 0.0
        self._drive_vector[dynamics.S_NOISE] = sensors.encoder_noise_rad
        self._drive_vector[dynamics.S_DIRECTION_ERROR : dynamics.S_DIRECTION_ERROR + N_JOINTS] = (
            sensors.direction_error_nm
        )
        # First-order low-pass 1 / (1 + s / (2 pi f)), discretised exactly for inputs held over a tick.
        self._drive_vector[dynamics.S_FILTER_ALPHA] = 1.0 - math.exp(
            -2.0 * math.pi * sensors.velocity_filter_hz * self._dt
        )
        self._drive_vector[dynamics.S_INVERSE_PLAY] = 1.0 / sensors.direction_play_rad
        # Undeclared sensor effects: calibration constants, not faults (clear_faults keeps them).
        self._drive_vector[dynamics.S_ANGLE_OFFSET : dynamics.S_ANGLE_OFFSET + N_JOINTS] = np.deg2rad(
            sensors.angle_offset_deg
        )
        # Per second, so the tick multiplies once; the same quotient as hal.sim.sensors.read_encoders.
        self._drive_vector[dynamics.S_TORQUE_DRIFT : dynamics.S_TORQUE_DRIFT + N_JOINTS] = (
            np.asarray(sensors.torque_drift_nm_per_min, dtype=float) / SECONDS_PER_MINUTE
        )
        self._drive_vector[dynamics.S_DT] = self._dt
        self._drive_vector[dynamics.S_SUBSTEPS] = self._plant.substeps(self._dt)
        self._drive_vector[dynamics.S_FIFO_LENGTH] = self._plant.command_delay_ticks + 1
        self._zero_torque = np.zeros(N_JOINTS)
        self._external: FloatArray | ExternalTorque | None = None
        self._external_pilot: SimulatedPilot | None = None  # the external torque when it is a SimulatedPilot
        self._estop = (False, False)
        self._estop_pressed_s: float | None = None  # robot time of the press that started the e-stop circuit
        self._power_cut = False
        self._disabled_drives = (DriveState.DISABLED,) * N_JOINTS
        self._enabled_drives = (DriveState.ENABLED,) * N_JOINTS
        self._no_fault_codes = (0,) * N_JOINTS
        self._is_open = False
        self._world: PlantWorld | None = None
        self._batches: SimLockStepBatches | None = None
        # The plant's own arrays, which the tick kernel integrates in place (DynamicPlant never replaces them).
        self._x, self._p, self._work = self._plant.state, self._plant.params, self._plant.work
        # Views the pilot's kernel reads (the true q, q') and writes (the external torque) every tick.
        self._true_q, self._true_dq = self._x[:N_JOINTS], self._x[_DQ]
        self._external_slot = self._drive_vector[dynamics.S_INPUTS + N_JOINTS : dynamics.S_INPUTS + 2 * N_JOINTS]
        self._tick_kernel = dynamics.hal_tick_entry()
        self._reset_session()
        self._load_kernel()

    @classmethod
    def from_config(cls, config: AnyHalConfig) -> SimHal:
        """The simulated plant of a ``sim`` configuration (:class:`hal.config.SimHalConfig`), not opened.

        Raises:
            HalConfigError: ``config`` is not a ``sim`` configuration.
            DescriptionError: the scenario or the robot description cannot be loaded.
            InputError: the rate is not positive and finite.
        """
        from hal.config import SimHalConfig
        from hal.errors import HalConfigError

        if not isinstance(config, SimHalConfig):
            raise HalConfigError(f"the sim backend takes a sim configuration, not {config.backend!r}")
        scenario = load_scenario(config.scenario)
        if config.seed is not None:
            scenario = scenario.model_copy(update={"seed": config.seed})
        description = load_description(config.robot) if config.robot is not None else None
        return cls(scenario, config.rate_hz, description)

    # --- Hal contract ---------------------------------------------------------------------------

    @property
    def rate_hz(self) -> float:
        return self._rate_hz

    @property
    def world(self) -> PlantWorld:
        """The world around the plant (:class:`hal.sim.world.PlantWorld`): one per backend, no pilot until seated."""
        if self._world is None:
            from hal.sim.world import PlantWorld  # the pilot and the shoulder's kinematics: only when asked

            self._world = PlantWorld(self)
        return self._world

    @property
    def lockstep_batches(self) -> SimLockStepBatches:
        """Ticks of the plant and its drives inside compiled code (:class:`SimLockStepBatches`)."""
        if self._batches is None:
            self._batches = SimLockStepBatches(self)
        return self._batches

    def open(self) -> None:
        """Start a session: plant at rest in static equilibrium at the scenario's ``initial_q_deg``.

        Drives are disabled, injected faults cleared, the noise stream restarted from the seed
        (every session of a scenario replays identically). E-stop inputs and the external torque
        are the environment's and stay as they are.
        """
        self._reset_session()
        self._is_open = True

    def close(self) -> None:
        """Remove torque (the FIFO is emptied, drives disabled) and end the session. Safe twice."""
        self._flush_commands()
        self._drives = self._disabled_drives
        self._is_open = False

    def read(self) -> Sample:
        """The sample at the current plant time (the same object if read twice in one tick).

        Raises:
            HalFaultError: a ``bus`` fault was injected since the previous read (raised once).
            HalNotOpenError: the backend is not open.
        """
        if not self._is_open:
            raise HalNotOpenError("simulated HAL is not open; call open() first")
        if self._bus_fault:
            self._bus_fault = False
            raise HalFaultError(f"simulated bus fault at t = {self._tick * self._dt:.6f} s (injected)")
        sample = self._sample
        if sample is None:
            sample = self._sample = self._build_sample()
        return sample

    def write(self, command: Command) -> None:
        """Apply ``command`` and advance the plant by one tick.

        Enabled commands act ``command_delay_ticks`` ticks later; a disabled command removes the
        torque of every joint from this tick on and discards the commands still queued. The plant
        saturates the motor torque at the drive train's ``max_motor_torque_nm``. After a refused
        command the sample of the tick (same ``seq``) is built again: it shows the drives disabled.

        Raises:
            HalNotOpenError: the backend is not open.
            HalError: an enabled command with a non-finite torque (torque is removed first and the
                tick does not advance); the plant diverged (torque removed).
            ShapeError: an enabled command's torque is not of shape (4,) (torque removed first).
        """
        if not self._is_open:
            raise HalNotOpenError("simulated HAL is not open; call open() first")
        enable = command.enable is True or bool(command.enable)
        joints_off = command.joints_off if enable else ()
        if joints_off != self._joints_off:  # rare: a fault reaction takes one joint off, or gives it back
            self._switch_joints_off(joints_off)
        if enable:
            torque = command.motor_torque_nm
            # A CheckedCommand's torque is a float64 ndarray of shape (4,); any other torque is
            # converted, and a wrong shape refused, before it reaches the compiled kernel. After these
            # lines the torque is of the type the kernel's entry point was resolved for
            # (dynamics.HAL_TICK_SIGNATURE; the entry point checks no types itself).
            if type(command) is not CheckedCommand:
                torque = self._checked_torque(torque)
        else:
            torque = self._zero_torque  # torque off whatever the command carries
        if self._external is not None:
            self._external_inputs()
        if self._estop_pressed_s is not None:  # only while a button is pressed
            self._run_estop_circuit()
        row = self._row + 4  # this tick's readings go to the next four rows of the block
        if row == _BLOCK_ROWS:
            row = self._new_block()
        status = self._tick_kernel(self._x, self._p, self._work, self._drive_vector, torque, enable, self._out, row)
        if status < 0:
            if status == dynamics.TICK_NO_NOISE:  # every NOISE_BLOCK_TICKS ticks
                self._refill_noise()
                status = self._tick_kernel(
                    self._x, self._p, self._work, self._drive_vector, torque, enable, self._out, row
                )
            if status < 0:
                self._drives = self._drive_states(False)
                self._refused()
                if status == dynamics.TICK_BAD_COMMAND:
                    raise HalError(f"motor_torque_nm = {torque.tolist()} is not finite; torque removed")
                raise HalError(
                    f"simulated plant diverged at t = {self._tick * self._dt:.6f} s "
                    f"(scenario {self.scenario.name!r}); torque removed"
                )
        if self._any_fault or self._joints_off or self._power_cut:
            self._drives = self._drive_states(status == dynamics.TICK_ENABLED)
        else:
            self._drives = self._enabled_drives if status == dynamics.TICK_ENABLED else self._disabled_drives
        self._tick += 1
        self.time_s = self._tick * self._dt
        self._row = row
        if self._stale_left > 0:
            self._stale_left -= 1
            self._sample = self._stale_sample
        else:
            self._sample = None

    # --- sim-only hooks -------------------------------------------------------------------------

    @property
    def plant(self) -> DynamicPlant:
        """The simulated plant (tests and tools; the runtime must use read/write only)."""
        self._plant.time_s = self._tick * self._dt  # synced here, not every tick: nothing in the tick reads it
        return self._plant

    @property
    def applied_motor_torque_nm(self) -> FloatArray:
        """Motor torque the simulated drives applied during the last tick (4,) Nm (tests only).

        The command that came out of the FIFO, saturated at the drive train's peak torque as the
        plant applies it; zero for a disabled or faulted drive.
        """
        limit = self._plant.max_motor_torque_nm
        return np.clip(self._drive_vector[dynamics.S_INPUTS : dynamics.S_INPUTS + N_JOINTS], -limit, limit)

    def truth(self) -> PlantTruth:
        """The true ``(q, dq, theta, dtheta, tau_spring)`` now (copies), for tests."""
        return self._plant.truth()

    def set_external_torque(self, torque: FloatArray | ExternalTorque | None) -> None:
        """The pilot pushing: torque on the links from outside, Nm, held over each tick.

        ``None`` removes it; a (4,) array is constant; a callable ``f(t_s, q_true, dq_true)``
        returning (4,) is called once per tick with the plant time and true state at the start of
        the tick (copies: it may keep them). A :class:`~hal.sim.pilot.SimulatedPilot` (that very
        class) is evaluated by :meth:`~hal.sim.pilot.SimulatedPilot.torque_into` instead: the same
        torque to the bit, computed from views of the state straight into the drive vector.

        Raises:
            ShapeError: an array not of shape (4,) (a callable's result is checked each tick).
            InputError: a non-finite element.
        """
        if torque is None or callable(torque):
            self._external = torque
            # The exact type: a subclass may compute its torque otherwise than SimulatedPilot.torque_into.
            self._external_pilot = torque if type(torque) is SimulatedPilot else None
            self._drive_vector[dynamics.S_INPUTS + N_JOINTS : dynamics.S_INPUTS + 2 * N_JOINTS] = 0.0
        else:
            self._external = joint_vector(torque, "external torque")
            self._external_pilot = None
            self._drive_vector[dynamics.S_INPUTS + N_JOINTS : dynamics.S_INPUTS + 2 * N_JOINTS] = self._external

    def press_estop(self, which: int, pressed: bool) -> None:
        """Press (True) or release an e-stop: ``which`` 0 is the operator's, 1 the pilot's.

        The simulator only reports the input (``Sample.estop``, from the next sample built);
        removing torque is the runtime's job, which is what the closed-loop tests check.

        Raises:
            InputError: ``which`` is not 0 or 1.
        """
        if isinstance(which, bool) or which not in (0, 1):
            raise InputError(f"e-stop {which!r}: expected 0 (operator) or 1 (pilot)")
        estop = list(self._estop)
        estop[which] = bool(pressed)
        self._estop = (estop[0], estop[1])
        if True in self._estop:
            if self._estop_pressed_s is None:  # the circuit starts at the first press (the relay's timer)
                self._estop_pressed_s = self._tick * self._dt
        else:  # both released: the relay closes again, the power stages have power
            self._estop_pressed_s = None
            self._power_cut = False
            self._drive_vector[dynamics.S_POWER_CUT] = 0.0

    def inject_fault(self, kind: FaultKind, joint: int | None = None, value: float | None = None) -> None:
        """Inject a fault, effective from the next sample built or the next tick.

        Kinds (``joint`` 1-4, None for all joints where it applies):

        * ``"nan"``: the next sample's ``q`` of ``joint`` is NaN (only ``q``: a monitor must check it).
        * ``"jump"``: the ``q`` reading of ``joint`` is offset by ``value`` rad from now on (the
          drive's velocity estimate and measured torque see it too, as with a slipped encoder).
        * ``"stale"``: the next ``value`` (default 1) ticks repeat the latest sample object,
          same ``seq``; afterwards ``seq`` jumps to the tick count (the drives kept counting).
        * ``"drive_fault"``: ``joint``'s drive reports FAULT with fault code ``value`` (default
          0x1000) and applies no torque until :meth:`clear_faults`.
        * ``"bus"``: the next :meth:`read` raises :class:`HalFaultError`.

        Raises:
            HalNotOpenError: the backend is not open.
            InputError: unknown kind, joint not 1-4, or a missing/invalid value.
        """
        if not self._is_open:
            raise HalNotOpenError("simulated HAL is not open; call open() first")
        if kind not in PLANT_FAULT_KINDS:
            raise InputError(f"fault kind {kind!r}; expected one of {', '.join(PLANT_FAULT_KINDS)}")
        if joint is not None and (isinstance(joint, bool) or joint not in range(1, N_JOINTS + 1)):
            raise InputError(f"joint {joint!r}; expected 1-{N_JOINTS} or None for all joints")
        joints = list(range(N_JOINTS)) if joint is None else [joint - 1]
        if kind == "nan":
            self._nan_pending.extend(joints)
        elif kind == "jump":
            offset = _number(value)
            if offset is None or not math.isfinite(offset):
                raise InputError(f"a 'jump' fault needs a finite offset value in rad, got {value!r}")
            for j in joints:
                self._drive_vector[dynamics.S_JUMP + j] += offset
        elif kind == "stale":
            ticks = 1.0 if value is None else _number(value)
            if ticks is None or not ticks.is_integer() or ticks < 1:
                raise InputError(f"a 'stale' fault needs a whole number of ticks >= 1, got {value!r}")
            self._stale_sample = self.read_without_faults()
            self._stale_left = int(ticks)
        elif kind == "drive_fault":
            code = float(DEFAULT_DRIVE_FAULT_CODE) if value is None else _number(value)
            if code is None or not code.is_integer() or not 0 < code <= 0xFFFF:
                raise InputError(f"a drive fault code must be a whole number in 1..0xFFFF, got {value!r}")
            codes = list(self._fault_codes)
            for j in joints:
                self._drive_vector[dynamics.S_FAULTED + j] = 1.0
                codes[j] = int(code)
            self._fault_codes = tuple(codes)
            self._any_fault = True
            self._drives = tuple(DriveState.FAULT if j in joints else state for j, state in enumerate(self._drives))
        else:  # bus
            self._bus_fault = True

    def clear_faults(self) -> None:
        """Clear every injected fault (pending NaN, jump offsets, stale, drive faults, bus).

        A drive whose fault is cleared reports DISABLED until the next enabled command acts.
        """
        self._nan_pending = []
        self._drive_vector[dynamics.S_JUMP : dynamics.S_JUMP + N_JOINTS] = 0.0
        self._stale_left = 0
        self._bus_fault = False
        self._drives = tuple(DriveState.DISABLED if d == DriveState.FAULT else d for d in self._drives)
        self._drive_vector[dynamics.S_FAULTED : dynamics.S_FAULTED + N_JOINTS] = 0.0
        self._any_fault = False
        self._fault_codes = self._no_fault_codes

    # request_fault_reset: the Hal default (nothing). An injected drive fault here stands for a cause
    # that persists (a hot motor): a fault reset edge would leave the drive in FAULT, so the drive
    # leaves it only when the world removes the cause (clear_faults). hal/canopen's simulated drives
    # model the other kind, a fault that a reset clears.

    def read_without_faults(self) -> Sample:
        """The current tick's sample without raising a pending bus fault (hooks and tests).

        Raises:
            HalNotOpenError: the backend is not open.
        """
        if not self._is_open:
            raise HalNotOpenError("simulated HAL is not open; call open() first")
        if self._sample is None:
            self._sample = self._build_sample()
        return self._sample

    # --- internals ------------------------------------------------------------------------------

    def _reset_session(self) -> None:
        self._plant.reset()
        self._tick = 0
        self.time_s = 0.0
        self._rng = stream(self.scenario.seed, STREAM_SIM_ENCODERS)
        self._drive_vector[dynamics.S_JUMP : dynamics.S_STARTED + 1] = 0.0  # jump offsets, sensor state
        self._drive_vector[dynamics.S_TICK] = 0.0
        self._drive_vector[dynamics.S_FAULTED : dynamics.S_FAULTED + N_JOINTS] = 0.0
        self._drive_vector[dynamics.S_JOINT_OFF : dynamics.S_JOINT_OFF + N_JOINTS] = 0.0
        self._joints_off: tuple[int, ...] = ()
        self._flush_commands()
        self._drives = self._disabled_drives
        self._any_fault = False
        self._fault_codes = self._no_fault_codes
        self._nan_pending: list[int] = []
        self._stale_left = 0
        self._stale_sample: Sample | None = None
        self._bus_fault = False
        if self._estop_pressed_s is not None:  # a button held through a reopen: the relay restarts with it
            self._estop_pressed_s = 0.0
        self._refill_noise()
        self._new_block()
        dynamics.sense(self._plant.state, self._drive_vector, self._out, 0)
        self._sample: Sample | None = None

    def _new_block(self) -> int:
        """Start a new block of readings; returns the first row free for a tick's readings.

        The tick kernel writes each tick's four rows (q, dq, theta, tau) into the next free rows of a
        block that only this backend can write (``_out``); a sample's arrays are rows of a read-only
        view of the same memory (``_view``, over a read-only buffer, so they cannot be made writable
        either). Rows are never written again once a sample may show them: the samples stay records,
        with no array allocated and no flag changed per tick. The newest readings (rows
        ``_row.._row + 3``, those of the current sample) are copied to rows 0-3 of the new block, so
        they are always at ``_row`` of ``_out``.
        """
        out = np.empty((_BLOCK_ROWS, N_JOINTS))
        previous = getattr(self, "_out", None)
        if previous is not None:
            out[0:4] = previous[self._row : self._row + 4]
        self._out = out
        self._view = np.frombuffer(memoryview(out).toreadonly(), dtype=np.float64).reshape(out.shape)
        self._row = 0
        return 4

    def _load_kernel(self) -> None:
        """Run the tick kernel once on copies (the entry point is resolved in ``__init__``; this
        first call touches the compiled code and its data, so the loop's first tick does not)."""
        self._tick_kernel(
            self._x.copy(), self._p, dynamics.new_work(), self._drive_vector.copy(), np.zeros(N_JOINTS), True,
            np.empty((4, N_JOINTS)), 0,
        )  # fmt: skip

    def _checked_torque(self, torque: object) -> FloatArray:
        """An enabled command's torque as a float64 ndarray of shape (4,), or refused (torque removed first).

        Raises:
            ShapeError: the torque is not of shape (4,).
        """
        if type(torque) is not np.ndarray or torque.dtype is not _FLOAT64:  # type: ignore[attr-defined]
            torque = np.ascontiguousarray(torque, dtype=np.float64)
        if torque.shape != _JOINT_SHAPE:  # type: ignore[attr-defined]
            self._flush_commands()
            self._drives = self._drive_states(False)
            self._refused()
            raise ShapeError(f"motor_torque_nm: expected shape ({N_JOINTS},), got {torque.shape}")  # type: ignore[attr-defined]
        return torque  # type: ignore[return-value]

    def _external_inputs(self) -> None:
        """Evaluate a callable external torque (the pilot) for this tick into the drive vector (Nm).

        Raises:
            ShapeError: the callable's torque is not of shape (4,).
            InputError: it has a non-finite element (the drive vector keeps the previous tick's torque).
        """
        pilot = self._external_pilot
        if pilot is not None:
            # Views of the state instead of copies (the pilot's kernel only reads them), and the
            # torque straight into the drive vector, finite or not written at all.
            if not pilot.torque_into(self._tick * self._dt, self._true_q, self._true_dq, self._external_slot):
                raise InputError(f"external torque: every element must be finite, got {pilot.torque_nm.tolist()}")
            return
        external = self._external
        if callable(external):
            state = self._plant.state
            value = external(self._tick * self._dt, state[:N_JOINTS].copy(), state[_DQ].copy())
            self._drive_vector[dynamics.S_INPUTS + N_JOINTS : dynamics.S_INPUTS + 2 * N_JOINTS] = joint_vector(
                value, "external torque"
            )

    def _refill_noise(self) -> None:
        # Sequential blocks of one generator: the numbers do not depend on the block size.
        block = self._drive_vector[dynamics.S_NOISE_BLOCK : dynamics.S_NOISE_BLOCK + dynamics.NOISE_BLOCK_SIZE]
        block[:] = self._rng.standard_normal(block.size)
        self._drive_vector[dynamics.S_NOISE_INDEX] = 0.0

    def _flush_commands(self) -> None:
        dynamics.flush_commands(self._drive_vector)

    def _refused(self) -> None:
        """A command was refused (torque removed): the tick's sample is built again with the drives' new state.

        The new sample shows the same readings from rows of its own (a pending NaN is written into
        them), so the old sample's arrays stay as they were.
        """
        if self._stale_left == 0:
            row = self._row + 4
            if row == _BLOCK_ROWS:
                row = self._new_block()
            self._out[row : row + 4] = self._out[self._row : self._row + 4]
            self._row = row
            self._sample = None

    def _drive_states(self, enabled: bool) -> tuple[DriveState, ...]:
        if not self._any_fault and not self._joints_off and not self._power_cut:
            return self._enabled_drives if enabled else self._disabled_drives
        on = DriveState.ENABLED if enabled and not self._power_cut else DriveState.DISABLED
        s = self._drive_vector
        return tuple(
            DriveState.FAULT
            if s[dynamics.S_FAULTED + j] > 0
            else DriveState.DISABLED
            if s[dynamics.S_JOINT_OFF + j] > 0
            else on
            for j in range(N_JOINTS)
        )

    @property
    def power_cut(self) -> bool:
        """True while the e-stop circuit has cut the drives' power stages (safe torque off).

        With the robot's ``estop.wiring`` ``sto`` from the tick a button is pressed; with ``ss1`` once
        the safety relay's ``relay_delay_s`` has run out with a button still pressed. Released
        buttons give the power back (the drives then need an enabled command, as after any torque off).
        """
        return self._power_cut

    def _run_estop_circuit(self) -> None:
        """A button is pressed: cut the power now (sto) or when the relay's delay has run out (ss1)."""
        wiring = self.description.estop
        pressed_s = self._estop_pressed_s
        cut = wiring.wiring == "sto" or (
            pressed_s is not None and self._tick * self._dt >= pressed_s + float(wiring.relay_delay_s or 0.0)
        )
        if cut and not self._power_cut:
            self._power_cut = True
            self._drive_vector[dynamics.S_POWER_CUT] = 1.0

    def _switch_joints_off(self, joints_off: tuple[int, ...]) -> None:
        """Disable the drives of ``joints_off`` (1-4) from this tick on; enable the others again.

        Raises:
            ShapeError: a joint that is not 1-4 (torque is removed first, as for any refused command).
        """
        if any(isinstance(j, bool) or j not in (1, 2, 3, 4) for j in joints_off):
            self._flush_commands()
            self._drives = self._drive_states(False)
            self._refused()
            raise ShapeError(f"joints_off: expected joint numbers 1-{N_JOINTS}, got {joints_off!r}")
        off = self._drive_vector[dynamics.S_JOINT_OFF : dynamics.S_JOINT_OFF + N_JOINTS]
        off[:] = 0.0
        for j in joints_off:
            off[j - 1] = 1.0
        self._joints_off = tuple(sorted(set(joints_off)))

    def _build_sample(self) -> Sample:
        row = self._row
        if self._nan_pending:  # written before any sample shows these rows
            self._out[row, self._nan_pending] = np.nan
            self._nan_pending = []
        view = self._view  # read-only: a sample is a record, nobody may change it afterwards
        tick = self._tick
        # Sample(seq, t_s, q, dq, theta, tau, estop, drives, fault codes), every field given, in order;
        # tuple.__new__ because this runs every tick (the NamedTuple's __new__ is a Python function). A
        # CheckedSample without its check: its arrays are rows of a float64 (n, 4) array, so they are
        # float64 vectors of 4 by construction (tests/daror_runtime/test_kernel_entry_points.py checks every kind of sample).
        return _new_tuple(
            CheckedSample,
            (tick, tick * self._dt, view[row], view[row + 1], view[row + 2], view[row + 3], self._estop,
             self._drives, self._fault_codes),
        )  # fmt: skip


def _number(value: object) -> float | None:
    """``value`` as a float, or None if it is not a number (bools are not numbers here)."""
    if isinstance(value, bool):
        return None
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None


class SimLockStepBatches:
    """:class:`hal.capabilities.LockStepBatches` of a :class:`SimHal`: its tick kernel run by a compiled caller.

    A batch tick is :meth:`SimHal.write` of an enabled command followed by :meth:`SimHal.read`,
    without the Python around them: the same kernel (:func:`hal.sim.dynamics.hal_tick`) on the same
    arrays, so the readings are the very same floats. A batch only starts on a plain tick (open, no
    fault injected or pending, no e-stop pressed, no pilot whose torque is computed per tick) and
    stops before the noise block or the block of readings runs out (both renewed here, between
    ticks, exactly as a write would renew them).
    """

    def __init__(self, hal: SimHal) -> None:
        self._hal = hal
        # The kernel's address for the batch's signature: loaded (or compiled) once, outside any tick.
        self._step = CompiledFunction(dynamics.hal_tick, BACKEND_STEP)
        self._first_row = 0

    def begin(self) -> BackendBatch | None:
        """The batch at the current tick, or None when the next tick needs :meth:`SimHal.write`."""
        hal = self._hal
        if (
            not hal._is_open
            or hal._bus_fault
            or hal._any_fault
            or hal._joints_off
            or hal._stale_left
            or (hal._sample is not None and hal._sample.seq != hal._tick)  # the last tick of a stale spell
            or hal._nan_pending
            or callable(hal._external)
            or True in hal._estop
        ):
            return None
        s = hal._drive_vector
        noise_ticks = int(dynamics.NOISE_BLOCK_SIZE - s[dynamics.S_NOISE_INDEX]) // dynamics.NOISE_PER_TICK
        if noise_ticks == 0:  # what the next write would do first (TICK_NO_NOISE, then a refill)
            hal._refill_noise()
            noise_ticks = dynamics.NOISE_BLOCK_TICKS
        row_ticks = (_BLOCK_ROWS - 4 - hal._row) // 4  # a tick writes rows row + 4 .. row + 7
        if row_ticks < noise_ticks:
            # A new block now rather than in the middle of the batch; the current readings move
            # with it (rows 0-3), and a sample already built keeps the old block's rows.
            hal._new_block()
            row_ticks = _BLOCK_TICKS - 1
        self._first_row = hal._row
        return BackendBatch(
            self._step,
            (hal._x, hal._p, hal._work, s),
            hal._out,
            hal._row,
            hal._tick,
            hal._dt,
            min(noise_ticks, row_ticks),
        )

    def end(self, ticks: int, status: int) -> None:
        """Account for ``ticks`` ticks run; raises when the last one failed (as :meth:`SimHal.write` raises).

        Raises:
            HalError: the plant diverged in the last tick (torque removed, as :meth:`SimHal.write` does).
        """
        hal = self._hal
        if status >= 0:
            hal._tick += ticks
            hal.time_s = hal._tick * hal._dt
            hal._row = self._first_row + 4 * ticks
            hal._drives = hal._enabled_drives if status == dynamics.TICK_ENABLED else hal._disabled_drives
            hal._sample = None
            return
        # The last tick failed inside the kernel: everything before it counts, it does not (as in write).
        hal._tick += ticks - 1
        hal.time_s = hal._tick * hal._dt
        hal._row = self._first_row + 4 * (ticks - 1)
        hal._sample = None
        hal._drives = hal._drive_states(False)
        hal._refused()
        if status == dynamics.TICK_BAD_COMMAND:  # the batch's torque passed the safety filter: not expected
            raise HalError("a batch tick's torque is not finite; torque removed")
        raise HalError(
            f"simulated plant diverged at t = {hal._tick * hal._dt:.6f} s (scenario {hal.scenario.name!r}); torque removed"
        )
