"""The simulated pilot's compiled torque (hal.sim.dynamics.pilot_torque) against the numpy formula.

The pilot (hal.sim.pilot.SimulatedPilot) computed its torque with numpy on arrays until its kernel
replaced that; golden sessions compare bit for bit, so the kernel must give the very same floats.
:class:`NumpyPilot` keeps the numpy formula as it was, and the tests compare every float's bits:
through ``SimulatedPilot.__call__``, through the simulated HAL's tick (views of the state, the
torque straight into the drive vector) and, for the signed zeros and NaNs that a real plant never
produces, through the kernel with a crafted gravity and felt support. A non-finite torque is still
refused with the message it had, and any other callable takes the generic path.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from hal.errors import InputError, ShapeError
from hal.kernels import misfits
from hal.robot import N_JOINTS, FloatArray
from hal.sim import dynamics
from hal.sim.backend import SimHal
from hal.sim.pilot import (
    DEFAULT_ADAPTATION_S,
    DEFAULT_DAMPING_NMS_PER_RAD,
    DEFAULT_STIFFNESS_NM_PER_RAD,
    SimulatedPilot,
)
from hal.sim.plant import DynamicPlant, joint_vector
from tests.daror_runtime.test_kernel_entry_points import Spy

EXTERNAL = slice(dynamics.S_INPUTS + N_JOINTS, dynamics.S_INPUTS + 2 * N_JOINTS)


class NumpyPilot:
    """The pilot's torque as numpy computed it before the kernel (the reference), for one planned move.

    Holds ``q_hold_rad`` until ``start_s``, then moves to ``q_to_rad`` over ``duration_s`` with
    minimum-jerk timing and holds there (what ``SimulatedPilot.move_to`` plans from a hold).
    """

    def __init__(
        self,
        plant: DynamicPlant,
        q_hold_rad: FloatArray,
        carried: float,
        stiffness_scale: float,
        adaptation_s: float,
        move: tuple[FloatArray, float, float] | None,
    ) -> None:
        self.plant = plant
        self.hold = np.array(q_hold_rad, dtype=float)
        self.carried = carried
        self.k = np.asarray(DEFAULT_STIFFNESS_NM_PER_RAD, dtype=float) * stiffness_scale
        self.d = np.asarray(DEFAULT_DAMPING_NMS_PER_RAD, dtype=float)
        self.adaptation_s = adaptation_s
        self.move = move
        self.felt_support = np.zeros(N_JOINTS)
        self.last_t_s: float | None = None
        self.work = dynamics.new_work()
        self.zero = np.zeros(N_JOINTS)
        self.gravity = np.zeros(N_JOINTS)

    def target(self, t_s: float) -> FloatArray:
        if self.move is None:
            return self.hold
        q_to, start_s, duration_s = self.move
        if t_s >= start_s + duration_s:
            # Done: the pilot drops a finished move and holds its end, also if time then goes back
            # (SimulatedPilot._move_at; a back step after the end was first drawn in CI's random run).
            self.hold, self.move = q_to, None
            return q_to
        if t_s < start_s:
            return self.hold
        s = (t_s - start_s) / duration_s
        shape = s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
        return self.hold + (q_to - self.hold) * shape

    def __call__(self, t_s: float, q_rad: FloatArray, dq_rad_s: FloatArray) -> FloatArray:
        torque = self.k * (self.target(t_s) - q_rad) - self.d * dq_rad_s
        dt = 0.0 if self.last_t_s is None else max(t_s - self.last_t_s, 0.0)
        self.last_t_s = t_s
        if dt > 0.0:
            self.felt_support += (1.0 - math.exp(-dt / self.adaptation_s)) * (
                self.plant.spring_torque_nm() - self.felt_support
            )
        if self.carried > 0.0:
            dynamics.bias_torque(q_rad, self.zero, self.plant.params, self.work, self.gravity)
            gravity = self.gravity
            felt = np.clip(self.felt_support, np.minimum(gravity, 0.0), np.maximum(gravity, 0.0))
            torque += self.carried * (gravity - felt)
        return torque


def same_floats(got: FloatArray, expected: FloatArray) -> bool:
    """Bit for bit (the sign of a zero counts), except that any NaN equals any NaN (numpy's NaN sign varies)."""
    got, expected = np.asarray(got, dtype=float), np.asarray(expected, dtype=float)
    nan = np.isnan(expected)
    return bool(np.array_equal(np.isnan(got), nan) and got[~nan].tobytes() == expected[~nan].tobytes())


@pytest.fixture(scope="module")
def hal() -> SimHal:
    hal = SimHal("exo_dummy_arm")
    hal.open()
    return hal


offsets = st.lists(st.floats(-1.0, 1.0), min_size=N_JOINTS, max_size=N_JOINTS).map(np.array)
speeds = st.lists(st.floats(-3.0, 3.0), min_size=N_JOINTS, max_size=N_JOINTS).map(np.array)
#: A tick of either rate, none (the same time again), back in time, or a long pause.
time_steps = st.sampled_from([1e-3, 2.5e-3, 0.0, -0.01]) | st.floats(0.0, 0.5)
#: A plant state near q0: the link angles, speeds, and the springs' stretch and its rate.
plant_states = st.tuples(offsets, speeds, offsets.map(lambda x: 0.05 * x), speeds)
moves = st.none() | st.tuples(offsets, st.floats(-0.2, 0.5), st.floats(0.01, 2.0))
shares = st.sampled_from([0.0, 1.0]) | st.floats(0.0, 1.0)
steps = st.lists(st.tuples(time_steps, st.none() | plant_states, offsets, speeds), min_size=1, max_size=25)


def seated(
    hal: SimHal,
    carried: float,
    stiffness_scale: float,
    adaptation_s: float,
    move: tuple[FloatArray, float, float] | None,
) -> tuple[SimulatedPilot, NumpyPilot, FloatArray]:
    """A pilot on ``hal``'s plant (reopened: at rest at q0, time 0) and its numpy reference."""
    hal.open()
    q0 = hal.plant.q_rad
    pilot = SimulatedPilot(hal.plant, q0, carried, adaptation_s=adaptation_s)
    pilot.set_stiffness_scale(stiffness_scale)
    planned = None
    if move is not None:
        offset, start_s, duration_s = move
        planned = (q0 + offset, start_s, duration_s)
        pilot.move_to(planned[0], start_s, duration_s)
    return pilot, NumpyPilot(hal.plant, q0, carried, stiffness_scale, adaptation_s, planned), q0


def set_plant_state(plant: DynamicPlant, q0: FloatArray, state: tuple[FloatArray, ...] | None) -> None:
    if state is not None:
        q_offset, dq, stretch, stretch_rate = state
        plant.set_state(q0 + q_offset, dq, q0 + q_offset + stretch, dq + stretch_rate)


@given(
    carried=shares,
    stiffness_scale=st.sampled_from([0.0, 1.0, 2.0]) | st.floats(0.0, 2.0),
    adaptation_s=st.sampled_from([DEFAULT_ADAPTATION_S]) | st.floats(0.01, 2.0),
    move=moves,
    ticks=steps,
)
@example(  # back in time after the move's end: the pilot holds the end (signed zeros of a zero stiffness)
    carried=0.0,
    stiffness_scale=0.0,
    adaptation_s=0.3,
    move=(np.array([0.0, 0.0, 0.0, 1.0]), 0.3671875, 0.0546875),
    ticks=[(-0.01, None, np.zeros(4), np.zeros(4)), (0.4375, None, np.zeros(4), np.zeros(4)),
           (-0.01, None, np.zeros(4), np.array([0.0, 0.0, 0.0, 1.0]))],
)  # fmt: skip
def test_the_pilots_torque_is_the_numpy_formulas_to_the_bit(
    hal: SimHal,
    carried: float,
    stiffness_scale: float,
    adaptation_s: float,
    move: tuple[FloatArray, float, float] | None,
    ticks: list[tuple[float, tuple[FloatArray, ...] | None, FloatArray, FloatArray]],
) -> None:
    pilot, reference, q0 = seated(hal, carried, stiffness_scale, adaptation_s, move)
    t_s = 0.0
    for dt, state, q_offset, dq in ticks:
        t_s += dt
        set_plant_state(hal.plant, q0, state)
        q = q0 + q_offset
        expected = reference(t_s, q, dq)
        got = pilot(t_s, list(q), dq[::-1][::-1])  # any float (4,): a list, a view with strides
        assert same_floats(got, expected)
        assert same_floats(pilot.target(t_s), reference.target(t_s))
        assert same_floats(pilot.torque_nm, expected)


@pytest.mark.slow
@given(carried=shares, move=moves, ticks=steps, stops=st.lists(st.booleans(), min_size=25, max_size=25))
def test_the_hal_tick_gives_the_numpy_formulas_torque_to_the_bit(
    hal: SimHal,
    carried: float,
    move: tuple[FloatArray, float, float] | None,
    ticks: list[tuple[float, tuple[FloatArray, ...] | None, FloatArray, FloatArray]],
    stops: list[bool],
) -> None:
    """The fast path: views of the true state, the torque written into the drive vector."""
    pilot, reference, q0 = seated(hal, carried, 1.0, DEFAULT_ADAPTATION_S, move)
    hal.set_external_torque(pilot)
    for (dt, state, _, _), stop in zip(ticks, stops, strict=False):
        hal._tick += round(abs(dt) * 1000)  # plant time only moves on in whole ticks
        hal.time_s = hal._tick * hal._dt  # as SimHal.write moves it
        set_plant_state(hal.plant, q0, state)
        truth = hal.truth()
        expected = reference(hal.time_s, truth.q_rad, truth.dq_rad_s)
        hal._external_inputs()
        assert same_floats(hal._drive_vector[EXTERNAL], expected)
        if stop and carried > 0.5:  # carried or stopped: the reference only knows its one move
            pilot.carried, reference.carried = 1.0 - carried, 1.0 - carried
    hal.set_external_torque(None)


zeros_and_signs = st.sampled_from([0.0, -0.0, 5e-324, -5e-324, 0.25, -0.25, 30.0, -30.0, math.inf, -math.inf, math.nan])


@given(
    gravity_mps2=st.sampled_from([0.0, -0.0, 9.81]),
    q_offset=offsets | st.just(np.zeros(N_JOINTS)),
    felt=st.lists(zeros_and_signs, min_size=N_JOINTS, max_size=N_JOINTS),
    impedance=st.lists(zeros_and_signs, min_size=N_JOINTS, max_size=N_JOINTS),
    carried=shares,
)
def test_the_kernel_clips_signed_zeros_and_nans_as_numpy_does(
    hal: SimHal,
    gravity_mps2: float,
    q_offset: FloatArray,
    felt: list[float],
    impedance: list[float],
    carried: float,
) -> None:
    """``np.clip(s, np.minimum(g, 0), np.maximum(g, 0))`` where ``g`` and ``s`` are signed zeros, tiny, NaN.

    No gravity and no joint springs give ``g`` of exact zeros of either sign (the real plant never
    does); the torque before the weight term is ``impedance`` (stiffness 1 at zero error, no damping).
    """
    hal.open()
    params = hal.plant.params.copy()
    params[dynamics.P_GRAVITY] = gravity_mps2
    params[dynamics.P_N_SPRINGS] = 0
    q = np.zeros(N_JOINTS) + q_offset  # at q = 0, target - q is the impedance term itself (-0.0 too)
    target = q + np.array(impedance)
    stiffness, damping, dq = np.ones(N_JOINTS), np.zeros(N_JOINTS), np.zeros(N_JOINTS)
    gravity = np.zeros(N_JOINTS)
    dynamics.bias_torque(q, np.zeros(N_JOINTS), params, dynamics.new_work(), gravity)
    with np.errstate(invalid="ignore"):
        expected = stiffness * (target - q) - damping * dq
        if carried > 0.0:
            clipped = np.clip(np.array(felt), np.minimum(gravity, 0.0), np.maximum(gravity, 0.0))
            expected += carried * (gravity - clipped)
    vector = np.zeros(dynamics.PILOT_VECTOR_SIZE)
    vector[dynamics.PILOT_STIFFNESS : dynamics.PILOT_STIFFNESS + N_JOINTS] = stiffness
    vector[dynamics.PILOT_FELT_SUPPORT : dynamics.PILOT_FELT_SUPPORT + N_JOINTS] = felt
    out = np.full(N_JOINTS, 7.0)
    finite = dynamics.pilot_torque_entry()(
        q, dq, hal.plant.state, params, dynamics.new_work(), vector,
        target, target, False, 0.0, False, 0.0, carried, out,
    )  # fmt: skip
    got = vector[dynamics.PILOT_TORQUE : dynamics.PILOT_TORQUE + N_JOINTS]
    assert same_floats(got, expected)
    assert finite == bool(np.all(np.isfinite(got)))
    assert same_floats(out, got if finite else np.full(N_JOINTS, 7.0))  # out untouched unless finite


def test_a_non_finite_pilot_torque_is_refused_as_before(hal: SimHal) -> None:
    hal.open()
    pilot = SimulatedPilot(hal.plant, hal.plant.q_rad, stiffness_nm_per_rad=(math.inf, 20.0, 20.0, 10.0))
    hal.set_external_torque(np.array([1.0, 2.0, 3.0, 4.0]))
    hal.set_external_torque(pilot)
    before = hal._drive_vector.copy()
    pilot.hold(hal.plant.q_rad + 0.1)
    with pytest.raises(InputError) as refused:
        hal._external_inputs()
    # the message joint_vector gives the torque, and the drive vector as it was (nothing written)
    with pytest.raises(InputError) as checked:
        joint_vector(pilot.torque_nm, "external torque")
    assert str(refused.value) == str(checked.value)
    assert "inf" in str(refused.value)
    np.testing.assert_array_equal(hal._drive_vector, before)
    hal.set_external_torque(None)


@given(torque=st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=N_JOINTS, max_size=N_JOINTS))
def test_a_generic_callables_non_finite_torque_is_refused_with_the_same_error(hal: SimHal, torque: list[float]) -> None:
    hal.open()
    hal.set_external_torque(lambda t_s, q, dq: np.array(torque))
    before = hal._drive_vector.copy()
    if all(math.isfinite(x) for x in torque):
        hal._external_inputs()
        np.testing.assert_array_equal(hal._drive_vector[EXTERNAL], torque)
    else:
        with pytest.raises(InputError) as refused:
            hal._external_inputs()
        assert str(refused.value) == f"external torque: every element must be finite, got {np.array(torque).tolist()}"
        np.testing.assert_array_equal(hal._drive_vector, before)
    hal.set_external_torque(None)


def test_other_callables_take_the_generic_path_with_copies(hal: SimHal) -> None:
    """A subclass or any function is called with copies of the state (it may keep them)."""
    hal.open()
    kept: list[FloatArray] = []

    class KeepingPilot(SimulatedPilot):
        def __call__(self, t_s: float, q_rad: FloatArray, dq_rad_s: FloatArray) -> FloatArray:
            kept.extend([q_rad, dq_rad_s])
            return super().__call__(t_s, q_rad, dq_rad_s)

    for external in (KeepingPilot(hal.plant, hal.plant.q_rad), lambda t, q, dq: kept.extend([q, dq]) or np.ones(4)):
        kept.clear()
        hal.set_external_torque(external)
        assert hal._external_pilot is None
        hal._external_inputs()
        assert len(kept) == 2
        assert not any(np.shares_memory(array, hal.plant.state) for array in kept)
    hal.set_external_torque(None)


def test_the_pilot_refuses_q_and_dq_of_another_shape(hal: SimHal) -> None:
    pilot = SimulatedPilot(hal.plant, hal.plant.q_rad)
    with pytest.raises(ShapeError):
        pilot(0.0, np.zeros(3), np.zeros(4))
    with pytest.raises(ShapeError):
        pilot(0.0, np.zeros(4), np.zeros((1, 4)))


def test_what_reaches_the_pilots_entry_point_fits_its_signature(hal: SimHal) -> None:
    """The tick's views and every q, dq ``__call__`` accepts (lists, ints, strided views) fit the types."""
    hal.open()
    hal.world.seat_pilot()
    pilot = hal.world.pilot
    spy = Spy(pilot._kernel)
    pilot._kernel = spy
    pilot.move_to(hal.plant.q_rad + 0.2, hal.time_s + 0.01, 0.05)
    for _ in range(100):
        hal._tick += 1
        hal.time_s = hal._tick * hal._dt  # as SimHal.write moves it
        hal._external_inputs()
    pilot(hal.time_s, [0, 1, 2, 3], np.arange(8.0)[::2])
    pilot(hal.time_s, np.zeros(4, dtype=np.float32), (0.0, 0.0, 0.0, 0.0))
    pilot.carried = 0.0
    pilot(hal.time_s + 1.0, np.zeros(4), np.zeros(4))
    assert len(spy.calls) == 103
    for args in spy.calls:
        assert misfits(dynamics.PILOT_TORQUE_SIGNATURE, args) == []
    hal.set_external_torque(None)
