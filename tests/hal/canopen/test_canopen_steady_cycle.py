"""Issue 25, D170: the simulated drives' steady cycle is the general path, frame for frame.

``SimulatedDriveSet._steady_cycle`` takes a cycle of a running session (one RPDO a drive, then the
SYNC, every drive steady) in one call per drive. Two ``can-sim`` backends with the same plant and
seed are driven by the same random session (torque commands, torque off, e-stops pressed and
released, drive faults injected, dropouts, fault resets): one as it runs, one with the steady cycle
switched off so that every frame takes the general path (``receive``, ``on_sync``). Their bus logs
must be the same bytes, and every sample the same numbers; the steady cycle must have run (so the
test compares something) and so must the general path in the same run (faults, start-up).
"""

from __future__ import annotations

from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hal.canopen.backend import SimulatedCanHal
from hal.config import hal_config
from hal.errors import HalError
from hal.interface import Command

#: The Unix time both backends open at: the bus log stamps robot time plus the whole seconds of its opening.
_EPOCH_S = 1_800_000_000.0
#: One step of a session: (what, its argument, how many ticks it lasts).
Step = tuple[str, object, int]

_torques = st.lists(st.floats(-4.0, 4.0, allow_nan=False), min_size=4, max_size=4).map(np.array)
_steps = st.one_of(
    st.tuples(st.just("torque"), _torques, st.integers(1, 60)),
    st.tuples(st.just("off"), st.none(), st.integers(1, 30)),
    st.tuples(st.just("estop"), st.sampled_from([(0, True), (0, False), (1, True), (1, False)]), st.integers(1, 20)),
    st.tuples(st.just("fault"), st.sampled_from(["emcy", "drive_fault", "drop_frames"]), st.integers(1, 20)),
    st.tuples(st.just("reset"), st.none(), st.integers(1, 30)),
)


class _Run:
    """One backend driven by the steps; what it showed, tick by tick."""

    def __init__(self, log: Path, steady: bool) -> None:
        self.hal = SimulatedCanHal(hal_config("can-sim"), traffic_log=log)  # type: ignore[arg-type]
        self.steady_cycles = 0
        self.general_cycles = 0
        drives = self.hal.drive_set
        run_steady = drives._steady_cycle

        def counted() -> bool:
            took = steady and run_steady()
            if took:
                self.steady_cycles += 1
            else:
                self.general_cycles += 1
            return took

        drives._steady_cycle = counted  # type: ignore[method-assign]
        self.seen: list[tuple[object, ...]] = []

    def run(self, steps: list[Step]) -> None:
        hal = self.hal
        with mock.patch("time.time", return_value=_EPOCH_S):  # the bus log's whole seconds: the same for both runs
            hal.open()
        try:
            for what, argument, ticks in steps:
                if what == "estop":
                    which, pressed = argument  # type: ignore[misc]
                    hal.world.press_estop(which, pressed)
                elif what == "fault":
                    hal.world.inject_fault(str(argument), joint=2)
                elif what == "reset":
                    hal.request_fault_reset()
                enable = what == "torque"
                torque = argument if what == "torque" else np.zeros(4)
                for _ in range(ticks):
                    self._tick(Command(torque, enable))
        finally:
            hal.close()

    def _tick(self, command: Command) -> None:
        try:
            sample = self.hal.read()
            self.seen.append((sample.t_s, *sample.q_rad, *sample.dq_rad_s, *sample.theta_rad, *sample.tau_nm,
                              tuple(sample.drives), sample.estop))  # fmt: skip
        except HalError as exc:
            self.seen.append(("fault", str(exc)))
        try:
            self.hal.write(command)
        except HalError as exc:
            self.seen.append(("write refused", str(exc)))


@pytest.mark.slow
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(steps=st.lists(_steps, min_size=3, max_size=10))
def test_the_steady_cycle_sends_and_reads_what_the_general_path_does(tmp_path_factory, steps: list[Step]) -> None:  # type: ignore[no-untyped-def]
    folder = tmp_path_factory.mktemp("steady")
    fast, general = _Run(folder / "steady.log", steady=True), _Run(folder / "general.log", steady=False)
    lead_in: list[Step] = [("torque", np.zeros(4), 50)]  # enabled: the cycles a session is made of
    fast.run(lead_in + steps)
    general.run(lead_in + steps)
    assert fast.steady_cycles > 0
    assert general.steady_cycles == 0
    assert fast.general_cycles > 0  # start-up at least: both paths ran in the same session
    assert fast.seen == general.seen
    assert (folder / "steady.log").read_bytes() == (folder / "general.log").read_bytes()


def test_a_running_session_takes_the_steady_cycle_with_the_master_s_heartbeat(tmp_path: Path) -> None:
    """Every cycle of an enabled session is steady, the ones that carry the master's heartbeat too (one in 40),
    and the drives hear it: their consumers would fault them within 250 ms without it."""
    run = _Run(tmp_path / "bus.log", steady=True)
    counted = run.hal.drive_set._steady_cycle
    general_at: list[int] = []  # the ticks whose cycle took the general path

    def watched() -> bool:
        took = counted()
        if not took:
            general_at.append(len(run.seen))
        return took

    run.hal.drive_set._steady_cycle = watched  # type: ignore[method-assign]
    run.run([("torque", np.full(4, 0.5), 600)])
    lines = (tmp_path / "bus.log").read_text().splitlines()
    master_beats = [line for line in lines if line.split()[2].startswith("77F#")]
    assert len(master_beats) >= 10  # 1.2 s: the master's heartbeat every 100 ms
    assert general_at
    assert all(n < 60 or n == len(run.seen) for n in general_at)
    last = run.seen[-1]
    assert last[0] != "fault"
    assert [d.name for d in last[-2]] == ["ENABLED"] * 4
