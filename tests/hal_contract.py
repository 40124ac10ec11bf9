"""The HAL contract suite: what every backend must do, written against :class:`hal.interface.Hal` only.

Like python-can's back-to-back tests, one set of behaviour checks runs against every backend
(``tests/hal/test_hal_contract.py`` takes them from the registry, :mod:`hal.registry`, plus its test
rigs). A backend joins with its :class:`hal.testing.BackendUnderTest` records, named by its
registry entry: a factory of unopened instances plus the few test hooks that only a test bench
has (latch a bus fault, fault a drive, read back the torque the drives apply). A check that needs
a hook the backend does not offer is skipped for it. The checks are the ``test_*`` methods of
:class:`HalContract`; a test module subclasses it as ``Test...`` and provides a ``backend`` fixture.

What is checked (the docstring of :class:`hal.interface.Hal` states the same contract):

* identity: ``kind``, a positive finite ``rate_hz``, ``virtual_time`` and ``drives_hardware``
  as bools, never both; a world only on a backend that drives no hardware; compiled lock-step
  batches only on virtual time, and a batch tick gives the very readings a write and a read give;
* lifecycle: ``read``/``write`` before ``open`` and after ``close`` raise ``HalNotOpenError``;
  ``close`` twice and before ``open`` is safe; ``open`` after ``close`` starts a new session with
  every drive disabled; ``with hal:`` opens and closes;
* the first sample: shapes, dtypes, read-only arrays, two e-stop inputs, four drives DISABLED,
  no fault codes (virtual time: ``seq`` 0 at ``t_s`` 0);
* one reading per tick: ``seq`` +1 per tick, the same ``seq`` when read again before the next
  write, ``t_s`` never decreasing; virtual time: ``t_s = seq / rate_hz``; wall-clock time:
  ``t_s`` follows the wall clock;
* ``read`` and ``write`` never block (each call within ``NEVER_BLOCKS_S``);
* torque only on request: no drive ENABLED unless the last command was enabled; enabled commands
  bring every drive to ENABLED within ``ENABLE_WITHIN_S``; a disabled command (whatever its
  torque, even NaN or the wrong shape) takes effect in the next sample: no drive ENABLED, no
  torque applied;
* drive limits: a torque beyond the peak is saturated at the peak, not refused; a non-finite
  torque raises ``HalError`` and a wrong shape ``ShapeError``, torque removed first;
* faults: a fault latched outside the tick is raised by the next ``read`` as ``HalFaultError``,
  once; a drive in fault reports FAULT with a code and applies no torque;
* a hypothesis state machine: random sequences of open, close, read, enabled, disabled and
  refused writes against the contract's model of the lifecycle, ``seq``, time and drive states.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    precondition,
    rule,
    run_state_machine_as_test,
)

from hal.capabilities import SimulatedWorld
from hal.errors import HalError, HalNotOpenError, ShapeError
from hal.interface import (
    ENABLE_WITHIN_S,
    NEVER_BLOCKS_S,
    SAMPLE_ARRAYS,
    Command,
    DriveState,
    Hal,
    HalFaultError,
    Sample,
)
from hal.robot import N_JOINTS, FloatArray
from hal.testing import BackendUnderTest

OFF = Command.torque_off()
ZERO_ON = Command(np.zeros(N_JOINTS), True)


# --- helpers ---------------------------------------------------------------------------------------


def opened(backend: BackendUnderTest) -> Hal:
    hal = backend.make()
    hal.open()
    return hal


def tick(hal: Hal, command: Command) -> Sample:
    """One tick: read, then write ``command``; the sample read."""
    sample = hal.read()
    hal.write(command)
    return sample


def enable_ticks(hal: Hal) -> int:
    """Ticks within which consecutive enabled commands must have enabled every drive."""
    return math.ceil(ENABLE_WITHIN_S * hal.rate_hz)


def enable(hal: Hal, torque: FloatArray | None = None) -> Sample:
    """Write enabled commands until every drive reports ENABLED (within the contract's time); the sample."""
    command = ZERO_ON if torque is None else Command(torque, True)
    for _ in range(enable_ticks(hal) + 1):
        sample = hal.read()
        if all(d == DriveState.ENABLED for d in sample.drives):
            return sample
        hal.write(command)
    raise AssertionError(f"drives not ENABLED after {enable_ticks(hal)} enabled commands: {hal.read().drives}")


def none_enabled(sample: Sample) -> bool:
    return DriveState.ENABLED not in sample.drives


def needs(backend: BackendUnderTest, hook: str) -> Callable[..., object]:
    value = getattr(backend, hook)
    if value is None:
        pytest.skip(f"{backend.name} offers no {hook} hook")
    return value  # type: ignore[no-any-return]


# --- random sequences against the contract's state machine ------------------------------------------------

#: Enabled torques, Nm: small, at the peak, beyond it (40 Nm on the DAROR-01), of both signs.
TORQUE = st.tuples(*[st.sampled_from([0.0, 0.5, -0.5, 3.0, -3.0, 40.0, -40.0, 60.0, -60.0])] * N_JOINTS).map(np.array)
#: What a torque-off command may carry: anything (it is ignored).
ANY_TORQUE = st.one_of(
    TORQUE,
    st.sampled_from([np.full(N_JOINTS, np.nan), np.array([np.inf, 0.0, 0.0, -np.inf]), np.zeros(3), np.zeros((2, 4))]),
)
BAD = st.sampled_from(["inf", "nan", "shape"])


def contract_machine(backend: BackendUnderTest) -> type[RuleBasedStateMachine]:
    """A hypothesis state machine of the contract's lifecycle, ``seq``, time and drive states for ``backend``."""

    class HalContractMachine(RuleBasedStateMachine):
        def __init__(self) -> None:
            super().__init__()
            self.hal = backend.make()
            self.open = False
            self.last_enabled = False  # the last command written (since open) was enabled and accepted
            self.seq: int | None = None  # the seq the next read must show, when known
            self.t_s = -math.inf

        def teardown(self) -> None:
            self.hal.close()

        @initialize()
        def start_open(self) -> None:
            self.open_backend()

        @rule()
        def open_backend(self) -> None:
            if self.open:
                self.hal.close()
            self.hal.open()
            self.open = True
            self.last_enabled = False
            self.seq = 0 if self.hal.virtual_time else None
            self.t_s = -math.inf

        @rule()
        def close_backend(self) -> None:
            self.hal.close()
            self.open = False

        @rule()
        def read(self) -> None:
            if not self.open:
                with pytest.raises(HalNotOpenError):
                    self.hal.read()
                return
            sample = self.hal.read()
            if self.seq is not None:
                assert sample.seq == self.seq
            self.seq = sample.seq  # read again before the next write: the same seq
            assert sample.t_s >= self.t_s
            self.t_s = sample.t_s
            if self.hal.virtual_time:
                assert sample.t_s == pytest.approx(sample.seq / self.hal.rate_hz, rel=1e-12, abs=1e-12)
            if not self.last_enabled:
                assert none_enabled(sample), sample.drives
            assert tuple(sample.drive_fault_codes) == (0,) * N_JOINTS

        def _written(self, enabled: bool) -> None:
            self.last_enabled = enabled
            if self.seq is not None:
                self.seq += 1

        @rule(torque=TORQUE, look=st.booleans())
        def write_enabled(self, torque: FloatArray, look: bool) -> None:
            if not self.open:
                with pytest.raises(HalNotOpenError):
                    self.hal.write(Command(torque, True))
                return
            self.hal.write(Command(torque, True))
            self._written(True)
            if look:
                self.read()

        @precondition(lambda self: self.open)
        @rule()
        def enable_every_drive(self) -> None:
            """Ticks of enabled commands until every drive is ENABLED (within the contract's time)."""
            for _ in range(enable_ticks(self.hal) + 1):
                self.read()
                if all(d == DriveState.ENABLED for d in self.hal.read().drives):
                    return
                self.hal.write(ZERO_ON)
                self._written(True)
            raise AssertionError(f"drives not ENABLED within {ENABLE_WITHIN_S} s of enabled commands")

        @rule(torque=ANY_TORQUE, look=st.booleans())
        def write_disabled(self, torque: FloatArray, look: bool) -> None:
            if not self.open:
                with pytest.raises(HalNotOpenError):
                    self.hal.write(Command(torque, False))
                return
            self.hal.write(Command(torque, False))  # switching off always works
            self._written(False)
            if look:  # effective on the next sample
                self.read()

        @precondition(lambda self: self.open)
        @rule(bad=BAD)
        def write_refused(self, bad: str) -> None:
            torque = {"inf": np.array([0.0, np.inf, 0.0, 0.0]), "nan": np.full(N_JOINTS, np.nan)}.get(bad, np.zeros(5))
            with pytest.raises(ShapeError if bad == "shape" else HalError):
                self.hal.write(Command(torque, True))
            self.last_enabled = False
            self.seq = None  # a refused command may or may not count as a tick
            self.read()  # torque was removed: no drive ENABLED in the next sample

        @invariant()
        def closed_means_refused(self) -> None:
            if not self.open:
                with pytest.raises(HalNotOpenError):
                    self.hal.read()

    HalContractMachine.__name__ = f"HalContractMachine[{backend.name}]"
    return HalContractMachine


class HalContract:
    """The contract's checks, as test methods over a ``backend`` fixture (a :class:`BackendUnderTest`).

    A test module subclasses it as ``TestSomething`` and provides the ``backend`` fixture.
    """

    # --- identity and lifecycle --------------------------------------------------------------------------

    def test_identity(self, backend: BackendUnderTest) -> None:
        """``kind``, ``rate_hz``, ``virtual_time``, ``drives_hardware`` and ``world`` say what the backend is."""
        hal = backend.make()
        assert isinstance(hal.kind, str)
        assert hal.kind
        assert math.isfinite(hal.rate_hz)
        assert hal.rate_hz > 0
        assert isinstance(hal.virtual_time, bool)
        assert isinstance(hal.drives_hardware, bool)
        assert not (hal.virtual_time and hal.drives_hardware), "hardware time cannot be virtual"
        world = hal.world
        if hal.drives_hardware:
            assert world is None, "a backend that drives hardware has no simulated world"
        if world is not None:
            assert isinstance(world, SimulatedWorld)
            assert hal.world is world  # reading it changes nothing: the same world
        if not hal.virtual_time:
            assert hal.lockstep_batches is None, "only a backend on virtual time may run ticks in compiled batches"

    def test_a_batch_tick_is_a_write_and_a_read(self, backend: BackendUnderTest) -> None:
        """A backend's compiled batch gives the very readings read/write give for the same commands."""
        reference, batched = backend.make(), backend.make()
        if batched.lockstep_batches is None:
            pytest.skip(f"{backend.name} runs no compiled batches")
        torque = np.array([0.5, -1.0, 0.75, 0.25])
        with reference, batched:
            batches = batched.lockstep_batches
            for tick in range(300):  # past a block of readings and of noise
                reference.write(Command(torque, True))
                begun = batches.begin()
                assert begun is not None
                assert begun.ticks >= 1
                assert begun.seq == tick
                x, p, work, s = begun.state
                status = begun.step.kernel(x, p, work, s, torque.copy(), True, begun.readings, begun.row + 4)
                batches.end(1, status)
                expected, got = reference.read(), batched.read()
                assert got.seq == expected.seq
                assert got.t_s == expected.t_s
                assert got.drives == expected.drives
                for name in SAMPLE_ARRAYS:
                    np.testing.assert_array_equal(getattr(got, name), getattr(expected, name), err_msg=name)

    def test_read_and_write_need_an_open_backend(self, backend: BackendUnderTest) -> None:
        """Before ``open`` and after ``close``, ``read`` and ``write`` raise ``HalNotOpenError``; ``close`` is safe twice."""
        hal = backend.make()
        with pytest.raises(HalNotOpenError):
            hal.read()
        with pytest.raises(HalNotOpenError):
            hal.write(OFF)
        hal.close()  # before open: safe
        hal.open()
        tick(hal, OFF)
        hal.close()
        hal.close()  # twice: safe
        with pytest.raises(HalNotOpenError):
            hal.read()
        with pytest.raises(HalNotOpenError):
            hal.write(OFF)
        with pytest.raises(HalNotOpenError):
            hal.write(ZERO_ON)

    def test_context_manager(self, backend: BackendUnderTest) -> None:
        """``with hal:`` opens the backend and closes it at the end."""
        hal = backend.make()
        with hal as entered:
            assert entered is hal
            assert isinstance(tick(hal, OFF), Sample)
        with pytest.raises(HalNotOpenError):
            hal.read()

    def test_first_sample(self, backend: BackendUnderTest) -> None:
        """The first sample after ``open``: typed, read-only, every drive DISABLED, no fault code."""
        hal = opened(backend)
        try:
            sample = hal.read()
            assert isinstance(sample, Sample)
            assert isinstance(sample.seq, int)
            assert isinstance(sample.t_s, float)
            assert math.isfinite(sample.t_s)
            for array in (sample.q_rad, sample.dq_rad_s, sample.theta_rad, sample.tau_nm):
                assert isinstance(array, np.ndarray)
                assert array.shape == (N_JOINTS,)
                assert array.dtype == np.float64
                assert np.all(np.isfinite(array))
                with pytest.raises(ValueError, match="read-only"):
                    array[0] = 1.0
            assert len(sample.estop) == 2
            assert all(isinstance(pressed, bool) for pressed in sample.estop)
            assert sample.drives == (DriveState.DISABLED,) * N_JOINTS
            assert all(isinstance(state, DriveState) for state in sample.drives)
            assert tuple(sample.drive_fault_codes) == (0,) * N_JOINTS
            if hal.virtual_time:
                assert sample.seq == 0
                assert sample.t_s == 0.0
        finally:
            hal.close()

    def test_reopen_starts_a_new_session(self, backend: BackendUnderTest) -> None:
        """``open`` after ``close``: every drive DISABLED again (virtual time: back at ``seq`` 0, ``t_s`` 0)."""
        hal = opened(backend)
        enable(hal)
        hal.close()
        hal.open()
        try:
            sample = hal.read()
            assert sample.drives == (DriveState.DISABLED,) * N_JOINTS
            if hal.virtual_time:
                assert (sample.seq, sample.t_s) == (0, 0.0)
        finally:
            hal.close()

    # --- time and sequence ------------------------------------------------------------------------------

    def test_one_reading_per_tick(self, backend: BackendUnderTest) -> None:
        """``seq`` +1 per tick, unchanged when read again before the write; ``t_s`` never decreases."""
        hal = opened(backend)
        try:
            previous = hal.read()
            for n in range(1, 60):
                assert hal.read().seq == previous.seq  # one reading per tick
                hal.write(OFF if n % 2 else ZERO_ON)
                sample = hal.read()
                assert sample.seq == previous.seq + 1
                assert sample.t_s >= previous.t_s
                previous = sample
        finally:
            hal.close()

    def test_virtual_time_advances_one_period_per_tick(self, backend: BackendUnderTest) -> None:
        """On virtual time, the sample of tick ``n`` is at ``t_s = n / rate_hz``, however long the tick took."""
        hal = opened(backend)
        try:
            if not hal.virtual_time:
                pytest.skip(f"{backend.name} runs on wall-clock time")
            for n in range(200):
                sample = tick(hal, ZERO_ON)
                assert sample.seq == n
                assert sample.t_s == pytest.approx(n / hal.rate_hz, rel=1e-12, abs=1e-12)
            time.sleep(0.01)  # wall time does not count
            hal.write(OFF)
            assert hal.read().t_s == pytest.approx(201 / hal.rate_hz, rel=1e-12)
        finally:
            hal.close()

    def test_wall_clock_time_follows_the_wall_clock(self, backend: BackendUnderTest) -> None:
        """Without virtual time, ``t_s`` advances with the wall clock (the hardware's time of the reading)."""
        hal = opened(backend)
        try:
            if hal.virtual_time:
                pytest.skip(f"{backend.name} owns its time")
            before = tick(hal, OFF)
            time.sleep(0.02)
            hal.write(OFF)
            after = hal.read()
            assert after.t_s - before.t_s >= 0.015
        finally:
            hal.close()

    def test_read_and_write_never_block(self, backend: BackendUnderTest) -> None:
        """Every ``read`` and ``write`` returns within ``NEVER_BLOCKS_S``, enabling, disabling, in fault.

        The backend's own time is measured: what a test rig waits for its wall-clock drives inside
        ``read`` (:attr:`BackendUnderTest.rig_wait_s`) is not the backend blocking (issue 26).
        """
        hal = opened(backend)
        worst = 0.0
        rig_wait_s = backend.rig_wait_s or (lambda _hal: 0.0)
        try:
            for n in range(300):
                command = OFF if n % 100 > 80 else ZERO_ON
                began = time.perf_counter()
                hal.read()
                middle = time.perf_counter()
                hal.write(command)
                ended = time.perf_counter()
                worst = max(worst, middle - began - rig_wait_s(hal), ended - middle)
                if n == 150 and backend.latch_fault is not None:
                    backend.latch_fault(hal)
                    began = time.perf_counter()
                    with pytest.raises(HalFaultError):
                        hal.read()
                    worst = max(worst, time.perf_counter() - began)
        finally:
            hal.close()
        assert worst < NEVER_BLOCKS_S, f"a call took {worst * 1e3:.1f} ms"

    # --- torque only on request ---------------------------------------------------------------------------

    def test_no_drive_enabled_without_an_enabled_command(self, backend: BackendUnderTest) -> None:
        """Torque-off commands never enable a drive."""
        hal = opened(backend)
        try:
            for _ in range(2 * enable_ticks(hal)):
                assert none_enabled(tick(hal, OFF))
        finally:
            hal.close()

    def test_enabled_commands_enable_every_drive_in_time(self, backend: BackendUnderTest) -> None:
        """Consecutive enabled commands enable every drive within ``ENABLE_WITHIN_S``; they stay enabled."""
        hal = opened(backend)
        try:
            enable(hal)
            for _ in range(20):
                assert tick(hal, ZERO_ON).drives == (DriveState.ENABLED,) * N_JOINTS
        finally:
            hal.close()

    @pytest.mark.parametrize(
        "torque",
        [np.full(N_JOINTS, 5.0), np.array([np.nan, 1.0, np.inf, 0.0]), np.zeros(2)],
        ids=["torque", "nan", "wrong-shape"],
    )
    def test_torque_off_is_effective_on_the_next_sample(self, backend: BackendUnderTest, torque: FloatArray) -> None:
        """A disabled command, whatever its torque, is accepted: the next sample shows no drive ENABLED, no torque applied."""
        hal = opened(backend)
        try:
            enable(hal, np.full(N_JOINTS, 1.0))
            hal.read()
            hal.write(Command(torque, False))
            assert none_enabled(hal.read())
            if backend.applied_torque_nm is not None:
                np.testing.assert_array_equal(backend.applied_torque_nm(hal), 0.0)
            for _ in range(5):
                assert none_enabled(tick(hal, OFF))
        finally:
            hal.close()

    @pytest.mark.parametrize("off", [(2,), (1, 4)], ids=["joint-2", "joints-1-4"])
    def test_joints_off_disables_those_drives_and_leaves_the_others_on(
        self, backend: BackendUnderTest, off: tuple[int, ...]
    ) -> None:
        """``joints_off``: those drives are not ENABLED in the next sample and apply no torque; the others follow
        the command; commands without it enable them again within ``ENABLE_WITHIN_S``."""
        hal = opened(backend)
        try:
            enable(hal, np.full(N_JOINTS, 1.0))
            command = Command(np.full(N_JOINTS, 1.0), True, off)
            hal.read()
            hal.write(command)
            sample = hal.read()
            kept = [j for j in range(1, N_JOINTS + 1) if j not in off]
            assert all(sample.drives[j - 1] != DriveState.ENABLED for j in off), sample.drives
            if backend.applied_torque_nm is not None:
                np.testing.assert_array_equal(backend.applied_torque_nm(hal)[[j - 1 for j in off]], 0.0)
            for _ in range(5):  # the others carry on (the drives may act a few ticks after a command)
                sample = tick(hal, command)
            sample = hal.read()
            assert all(sample.drives[j - 1] == DriveState.ENABLED for j in kept), sample.drives
            assert all(sample.drives[j - 1] != DriveState.ENABLED for j in off), sample.drives
            if backend.applied_torque_nm is not None:
                applied = backend.applied_torque_nm(hal)
                np.testing.assert_array_equal(applied[[j - 1 for j in off]], 0.0)
                np.testing.assert_allclose(applied[[j - 1 for j in kept]], 1.0)
            assert enable(hal, np.full(N_JOINTS, 1.0)).drives == (DriveState.ENABLED,) * N_JOINTS
        finally:
            hal.close()

    def test_a_joint_number_outside_1_to_4_is_refused_and_removes_torque(self, backend: BackendUnderTest) -> None:
        """``joints_off`` naming no joint of the robot is a programming error: ``ShapeError``, torque removed first."""
        hal = opened(backend)
        try:
            enable(hal, np.full(N_JOINTS, 1.0))
            hal.read()
            with pytest.raises(ShapeError):
                hal.write(Command(np.full(N_JOINTS, 1.0), True, (5,)))
            assert none_enabled(hal.read())
        finally:
            hal.close()

    # --- drive limits -------------------------------------------------------------------------------------

    def test_torque_beyond_the_peak_is_saturated(self, backend: BackendUnderTest) -> None:
        """An enabled torque beyond the drive's peak is accepted and saturated at the peak (both signs)."""
        applied = needs(backend, "applied_torque_nm")
        hal = opened(backend)
        try:
            peak = float(hal.description.sea.max_motor_torque_nm)
            enable(hal)
            command = Command(np.array([2.0, -2.0, 1.5, -10.0]) * peak, True)
            for _ in range(5):  # the drives may act a few ticks after the command (a bus, a FIFO)
                tick(hal, command)
                assert np.all(np.abs(applied(hal)) <= peak + 1e-9)
            assert hal.read().drives == (DriveState.ENABLED,) * N_JOINTS
            np.testing.assert_allclose(applied(hal), [peak, -peak, peak, -peak])
        finally:
            hal.close()

    @pytest.mark.parametrize(
        ("torque", "error"),
        [
            (np.array([0.0, np.inf, 0.0, 0.0]), HalError),
            (np.array([np.nan, 0.0, 0.0, 0.0]), HalError),
            (np.zeros(3), ShapeError),
            (np.zeros((2, 4)), ShapeError),
        ],
        ids=["inf", "nan", "short", "matrix"],
    )
    def test_bad_enabled_commands_are_refused_and_remove_torque(
        self, backend: BackendUnderTest, torque: FloatArray, error: type[Exception]
    ) -> None:
        """A non-finite torque raises ``HalError``, a wrong shape ``ShapeError``; torque is removed first."""
        hal = opened(backend)
        try:
            enable(hal, np.full(N_JOINTS, 1.0))
            hal.read()
            with pytest.raises(error):
                hal.write(Command(torque, True))
            assert none_enabled(hal.read())
            if backend.applied_torque_nm is not None:
                np.testing.assert_array_equal(backend.applied_torque_nm(hal), 0.0)
            enable(hal)  # the backend keeps working: enabling again works
        finally:
            hal.close()

    # --- faults -----------------------------------------------------------------------------------------

    def test_a_latched_fault_is_raised_by_the_next_read_once(self, backend: BackendUnderTest) -> None:
        """A fault latched outside the tick: ``HalFaultError`` at the next read, once; the read after gives a sample."""
        latch = needs(backend, "latch_fault")
        hal = opened(backend)
        try:
            for _ in range(3):
                tick(hal, ZERO_ON)
            latch(hal)
            with pytest.raises(HalFaultError):
                hal.read()
            assert isinstance(hal.read(), Sample)
            hal.write(OFF)  # switching off works after a fault
            assert none_enabled(hal.read())
        finally:
            hal.close()

    def test_a_drive_in_fault_reports_it_and_applies_no_torque(self, backend: BackendUnderTest) -> None:
        """A drive in fault reports FAULT with a non-zero code and applies no torque; the others carry on."""
        fault_drive = needs(backend, "fault_drive")
        hal = opened(backend)
        try:
            enable(hal, np.full(N_JOINTS, 1.0))
            fault_drive(hal, 2)
            command = Command(np.full(N_JOINTS, 1.0), True)
            for _ in range(5):
                sample = tick(hal, command)
            sample = hal.read()
            assert sample.drives[1] == DriveState.FAULT
            assert sample.drive_fault_codes[1] != 0
            assert sample.drives[0] == sample.drives[2] == sample.drives[3] == DriveState.ENABLED
            if backend.applied_torque_nm is not None:
                applied = backend.applied_torque_nm(hal)
                assert applied[1] == 0.0
                np.testing.assert_allclose(applied[[0, 2, 3]], 1.0)
        finally:
            hal.close()

    @pytest.mark.slow
    def test_random_sequences_keep_the_contract(self, backend: BackendUnderTest) -> None:
        """Random sequences of open, close, read and writes (enabled, disabled, refused) keep the contract."""
        run_state_machine_as_test(
            contract_machine(backend),
            settings=settings(
                max_examples=200,
                stateful_step_count=40,
                deadline=None,
                suppress_health_check=[HealthCheck.too_slow],
                database=None,
            ),
        )
