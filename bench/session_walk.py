"""A lock-step session walked to compensation: the common path the tick benchmarks time.

Shared by ``bench_fault_reactions.py`` and ``compare_tick.py``. It uses only the runtime's public
session API as it stood before issue 23 too, so that ``compare_tick.py`` can time the same walk on
an older commit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.runtime import Runtime
from daror_runtime.session.settings import SessionSettings
from hal.isb import IsbLimits, default_shoulder
from hal.sim.backend import SimHal
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary

#: Where the pilot holds his arm before he goes limp: flexed forward 40 deg, elbow at 70 deg.
POSE_ISB_DEG = (40.0, 60.0, 0.0, 70.0)


def session_in_compensation(directory: Path) -> tuple[Runtime, SimHal]:
    """A lock-step session walked to compensation with a validated PLF+ model, the pilot limp, the arm raised."""
    from daror_runtime.console.world import SimWorld
    from daror_runtime.data.load import write_dataset
    from daror_runtime.models.files import save_model, training_summary
    from daror_runtime.models.registry import fit_model, installation_options

    scenario = load_scenario("exo_dummy_arm")
    points = generate_stationary(scenario, "training")
    train = StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s)
    held_out = generate_stationary(scenario, "validation")
    validation = directory / "validation.csv"
    write_dataset(validation, StationaryDataset(held_out.q_rad, held_out.tau_nm, held_out.direction, held_out.t_s))
    try:  # since issue 24 a session validates only on a recording of its pilot (compare_tick also walks older trees)
        from daror_runtime.data.provenance import simulated_pilot, simulated_robot, write_provenance
    except ImportError:
        pass
    else:
        robot = simulated_robot(scenario.description().name, scenario.name)
        write_provenance(validation, "session", robot, simulated_pilot(scenario.name), "earlier", "validation")
    model = directory / "plf_plus.json"
    fitted = fit_model("plf+", train, scenario.description(), installation_options("plf+", dummy_arm=True))
    save_model(model, fitted.model, training_summary(train, None), fitted.report)

    hal = SimHal(scenario)
    runtime = Runtime(hal, directory / "session", settings=SessionSettings(dummy_arm=True))
    runtime.open()
    world = SimWorld(hal.world)
    runtime.runner.run_ticks(1)
    runtime.select_model(model, validation)
    runtime.runner.run_until(lambda: not runtime.busy, 2.0)

    def press(button: str) -> None:
        world.estop(button, True)
        runtime.runner.pass_time(0.05)
        world.estop(button, False)
        runtime.runner.pass_time(0.2)

    steps = {
        "safety_check": lambda: (press("operator"), press("pilot")),
        "settings": lambda: runtime.wait(runtime.confirm("settings")),
        "pilot_installation": lambda: runtime.wait(runtime.confirm("installation")),
        "safety_experience": lambda: (press("pilot"), runtime.wait(runtime.confirm("safety_experience"))),
        "rom_limits": lambda: runtime.wait(runtime.set_isb_limits(IsbLimits())),
        "operative_check": lambda: press("operator"),
    }
    while runtime.state_name != "compensation":
        steps.get(runtime.state_name, lambda: runtime.runner.run_until(lambda: runtime.at_rest, 5.0))()
        runtime.wait(runtime.advance())
        runtime.runner.pass_time(0.3)
    shoulder = default_shoulder()
    end = world.pilot_move(shoulder.q_from_isb(np.deg2rad(POSE_ISB_DEG), seed=hal.truth().q_rad))
    runtime.runner.pass_time(end - hal.time_s + 1.0)
    world.pilot_carries(0.0)
    world.pilot_stiffness(0.0)
    runtime.runner.pass_time(2.0)
    return runtime, hal
