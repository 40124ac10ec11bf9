"""The online indicators against the simulated pilot's truth (issue 29): a lock-step session on the plant.

Used by ``bench/bench_online.py`` (the figures of docs/online.md) and by
``tests/daror_runtime/online/test_online_closed_loop.py``. A session walks to compensation with a
PLF+ model fitted on the scenario's simulated identification data (validated on its validation
set, as a session would); the pilot then carries what the robot does not (``carry 1``) while he moves
his arm to a few poses inside his limits and holds each, at each support level. Every observation
period the simulator's truth is kept beside what the runtime measures: the pilot's own torque, the
arm's true holding torque and the model's torque, so each rest the runtime's indicators found is
compared with the pilot's true effort over the same window, and the model's own error there (its
torque minus the true holding torque) is known.

A model of known quality: :class:`OffsetModel` adds a known torque per joint to the model in use
(instrumentation of the simulated bench only, through the declared test hook; nothing of it is in
the runtime).
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from daror_runtime.console.world import SimWorld
from daror_runtime.data.load import write_dataset
from daror_runtime.data.provenance import simulated_pilot, simulated_robot, write_provenance
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.models.files import save_model, training_summary
from daror_runtime.models.registry import fit_model, installation_options
from daror_runtime.online.drift import MEASURE_S as DRIFT_MEASURE_S
from daror_runtime.online.drift import SETTLE_S as DRIFT_SETTLE_S
from daror_runtime.online.drift import DriftResult, corrected_effort
from daror_runtime.online.indicators import MOVING_RAD_S, OBSERVE_PERIOD_S
from daror_runtime.runtime import Runtime
from daror_runtime.session.settings import SessionSettings
from daror_runtime.testing import session_core
from hal.config import hal_config
from hal.interface import open_hal
from hal.isb import IsbLimits
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary

#: The poses the pilot holds (ISB deg: elevation, horizontal rotation, axial rotation, elbow).
POSES_DEG = ((30.0, 40.0, 0.0, 60.0), (50.0, 70.0, 10.0, 90.0), (20.0, 100.0, -10.0, 40.0), (40.0, 60.0, 20.0, 80.0))
LEVELS = (1.0, 0.7, 0.4)
MOVE_S = 2.0
HOLD_S = 2.5


def fitted_model(scenario_name: str, folder: Path) -> tuple[Path, Path]:
    """A PLF+ model file of ``scenario_name`` fitted on its simulated training set, and its validation set.

    Both data files carry the provenance of an earlier session of this simulated pilot (the gate
    validates only on his data).
    """
    scenario = load_scenario(scenario_name)
    robot = simulated_robot(scenario.description().name, scenario.name)
    paths = {}
    for run in ("training", "validation"):
        points = generate_stationary(scenario, run)
        paths[run] = folder / f"{run}.csv"
        write_dataset(paths[run], StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s))
        write_provenance(
            paths[run], "session", robot, simulated_pilot(scenario.name), "earlier-session", run, scenario.name
        )
    training = StationaryDataset(*_columns(generate_stationary(scenario, "training")))
    result = fit_model("plf+", training, scenario.description(), installation_options("plf+", dummy_arm=True))
    model = folder / "model_plf_plus.json"
    save_model(model, result.model, training_summary(training, paths["training"]), result.report)
    return model, paths["validation"]


def _columns(points: Any) -> tuple[Any, ...]:
    return points.q_rad, points.tau_nm, points.direction, points.t_s


class OffsetModel:
    """``model`` plus a known torque per joint (Nm): a model of known error for the simulated bench."""

    def __init__(self, model: Any, offset_nm: np.ndarray) -> None:
        self._model = model
        self._offset = np.asarray(offset_nm, dtype=float)
        self.name = f"{model.name} {'+' if self._offset.sum() >= 0 else '-'} known error"

    def torque(self, q_rad: np.ndarray) -> np.ndarray:
        return np.asarray(self._model.torque(q_rad), dtype=float) + self._offset

    def __getattr__(self, name: str) -> Any:
        return getattr(self._model, name)


@dataclass(frozen=True)
class RestCheck:
    """One rest the runtime's indicators found, beside the simulator's truth over the same window."""

    model: str
    level_asked: float
    level_delivered: float | None
    indicator_nm: np.ndarray  # the runtime's effort at rest, per joint
    truth_nm: np.ndarray  # the pilot's own torque, mean over the rest
    model_error_nm: np.ndarray  # the model's torque minus the true holding torque, mean over the rest
    corrected_nm: np.ndarray | None = None  # the indicator less a drift test's measure near the pose (None: none)

    @property
    def error_nm(self) -> np.ndarray:
        """The indicator against the pilot's true effort."""
        return self.indicator_nm - self.truth_nm

    @property
    def corrected_error_nm(self) -> np.ndarray | None:
        """The indicator corrected by a drift test near the pose, against the pilot's true effort."""
        return None if self.corrected_nm is None else self.corrected_nm - self.truth_nm

    @property
    def estimator_error_nm(self) -> np.ndarray:
        """What the estimate adds to the model's own error at the pose."""
        return self.error_nm - self.model_error_nm


@dataclass(frozen=True)
class DriftCheck:
    """One drift test beside the simulator's truth: the model's true error where the arm was held."""

    result: DriftResult
    model_error_nm: np.ndarray  # the model's torque minus the true holding torque over the test's measure
    held_drift_deg: float  # how far the arm moved once held (the catch's bumplessness), any joint

    @property
    def error_nm(self) -> np.ndarray:
        """The test's unsupported torque against the model's true error there."""
        return np.array(self.result.unsupported_nm) - self.model_error_nm


class SimulatedSession:
    """A lock-step session of ``scenario_name`` walked to compensation with ``model``; truth logged as it runs."""

    def __init__(
        self, scenario_name: str, directory: Path, model: Path, validation: Path, a_priori_first: bool = False
    ) -> None:
        self.hal = open_hal(hal_config("sim", source="bench", scenario=scenario_name))
        self.runtime = Runtime(self.hal, directory, settings=SessionSettings(dummy_arm=True))
        self.runtime.open()
        self.world = SimWorld(self.runtime.world)  # seats the pilot
        self.core = session_core(self.runtime)
        #: every observation period: t, the pilot's torque, the true holding torque, the model's, q, the model's label
        self.truth: list[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]] = []
        self._next_t_s = -np.inf
        self.runtime.runner.run_ticks(1)
        self._model, self._validation = model, validation
        self._a_priori_first = a_priori_first  # as session.txt: the A Priori model confirmed, the model selected later
        if not a_priori_first:
            self._select()
        self._walk_to_compensation()

    def _select(self) -> None:
        self.runtime.select_model(self._model, self._validation)
        self.runtime.runner.run_until(lambda: not self.runtime.busy, 2.0)
        if self.runtime.model_in_use is None or not self.runtime.model_in_use.validated:
            raise RuntimeError(f"the model was not validated: {self.runtime.status()['model_refused']}")

    def _ok(self, ticket: Any) -> None:
        response = self.runtime.wait(ticket)
        if not response.accepted:
            raise RuntimeError(f"{response.request} refused in {response.state}: {response.reason}")

    def _press(self, button: str) -> None:
        self.world.estop(button, True)
        self.runtime.runner.pass_time(0.05)
        self.world.estop(button, False)
        self.runtime.runner.pass_time(0.2)

    def _walk_to_compensation(self) -> None:
        runtime = self.runtime
        while runtime.state_name != "compensation":
            here = runtime.state_name
            if here == "safety_check":
                self._press("operator")
                self._press("pilot")
            elif here == "settings":
                self._ok(runtime.confirm("settings"))
            elif here == "pilot_installation":
                self._ok(runtime.confirm("installation"))
            elif here == "safety_experience":
                self._press("pilot")
                self._ok(runtime.confirm("safety_experience"))
            elif here == "rom_limits":
                self._ok(runtime.set_isb_limits(IsbLimits()))
                if self._a_priori_first:
                    self._ok(runtime.confirm("a_priori_model"))
            elif here == "operative_check":
                self._press("operator")
            elif here == "identification":
                if self._a_priori_first and (runtime.model_in_use is None or not runtime.model_in_use.validated):
                    self._select()
                runtime.runner.run_until(lambda: runtime.at_rest, 5.0)
            self._ok(runtime.advance())
            runtime.runner.pass_time(0.3)

    def run(self, seconds: float) -> None:
        """Let ``seconds`` of robot time pass, the truth kept every observation period."""
        runner, runtime, world = self.runtime.runner, self.runtime, self.world
        compensation = self.core.modes.compensation
        for _ in range(round(seconds / self.core.dt_s)):
            runner.run_ticks(1)
            sample = runtime.last_sample
            if sample is None or sample.t_s < self._next_t_s:
                continue
            self._next_t_s = sample.t_s + OBSERVE_PERIOD_S - 1e-9
            holding, pilot = world.support_torques()
            model = compensation.model
            torque = np.full(4, np.nan) if model is None else np.asarray(model.torque(sample.q_rad), dtype=float)
            label = "" if model is None else str(getattr(model, "name", ""))
            self.truth.append((sample.t_s, pilot.copy(), holding.copy(), torque, sample.q_rad.copy(), label))

    def use_offset(self, offset_nm: np.ndarray) -> str:
        """From now on the model in use is off by ``offset_nm``; returns its label in the indicators."""
        compensation = self.core.modes.compensation
        compensation.model = OffsetModel(compensation.model, offset_nm)
        return compensation.model.name

    def hold_poses(
        self, levels: tuple[float, ...] = LEVELS, poses_deg: tuple[tuple[float, ...], ...] = POSES_DEG
    ) -> None:
        """At each support level the pilot, carrying what the robot does not, moves to each pose and holds it."""
        shoulder = self.runtime.shoulder
        self.world.pilot_carries(1.0)
        for level in levels:
            self._ok(self.runtime.set_support(level))
            self.run(1.5)
            for pose in poses_deg:
                q = shoulder.q_from_isb(np.deg2rad(pose), seed=self.runtime.last_sample.q_rad)
                self.world.pilot_move(q, MOVE_S)
                self.run(MOVE_S + HOLD_S)

    def rest_checks(self) -> list[RestCheck]:
        """Every rest of every model's indicators against the truth over its window."""
        times = np.array([entry[0] for entry in self.truth])
        pilot = np.array([entry[1] for entry in self.truth])
        holding = np.array([entry[2] for entry in self.truth])
        model = np.array([entry[3] for entry in self.truth])
        checks = []
        for label, indicators in self.core.online.by_model.items():
            indicators.interrupt()
            tests = [test for test in self.core.online.drift_tests if test.model == label]
            for rest in indicators.rests:
                window = (times >= rest.t_start_s - 1e-9) & (times <= rest.t_end_s + 1e-9)
                corrected = corrected_effort(rest.pose_rad, rest.effort_nm, tests)
                checks.append(
                    RestCheck(
                        label,
                        rest.level_asked,
                        rest.level_delivered,
                        np.array(rest.effort_nm),
                        pilot[window].mean(axis=0),
                        (model[window] - holding[window]).mean(axis=0),
                        None if corrected is None else np.array(corrected[0]),
                    )
                )
        return checks

    def moving_truth(self, model_name: str) -> tuple[np.ndarray, np.ndarray]:
        """Per joint: the pilot's true torque RMS while that joint moved under ``model_name`` (the
        indicators' criterion: faster than MOVING_RAD_S from the angles), and the number of samples."""
        rows = [entry for entry in self.truth if entry[5] == model_name]
        times = np.array([entry[0] for entry in rows])
        q = np.array([entry[4] for entry in rows])
        pilot = np.array([entry[1] for entry in rows])
        speed = (q[2:] - q[:-2]) / (times[2:] - times[:-2])[:, None]
        contiguous = (times[2:] - times[:-2]) < 3 * OBSERVE_PERIOD_S
        moving = (np.abs(speed) > MOVING_RAD_S) & contiguous[:, None]
        middle = pilot[1:-1]
        rms = np.array(
            [np.sqrt(np.mean(middle[moving[:, j], j] ** 2)) if moving[:, j].any() else np.nan for j in range(4)]
        )
        return rms, moving.sum(axis=0)

    def drift_tests(self, poses_deg: tuple[tuple[float, ...], ...] = POSES_DEG) -> list[DriftCheck]:
        """At each pose: the pilot holds the arm there, the drift test starts and he relaxes at once;
        after the catch and the measure, ``advance`` returns to compensation and he takes his arm back."""
        runtime, world, shoulder = self.runtime, self.world, self.runtime.shoulder
        if self.core.modes.compensation.delivered_support_level != 1.0:
            self._ok(runtime.set_support(1.0))  # the test is of the model's whole support
            self.run(2.5)
        checks = []
        for pose in poses_deg:
            world.pilot_stiffness(1.0)
            world.pilot_carries(1.0)
            q = shoulder.q_from_isb(np.deg2rad(pose), seed=runtime.last_sample.q_rad)
            world.pilot_move(q, MOVE_S)
            self.run(MOVE_S + 1.5)
            before = len(self.core.online.drift_tests)
            self._ok(runtime.drift_test())
            world.pilot_carries(0.0)  # he relaxes: his muscles slack, he holds nothing
            world.pilot_stiffness(0.0)
            start = len(self.truth)
            self.run(2.5)
            if len(self.core.online.drift_tests) != before + 1:
                raise RuntimeError(f"no drift test result at {pose}: {self.core.drift and self.core.drift.phase}")
            result = self.core.online.drift_tests[-1]
            window = self.truth[start:]
            caught_t = result.t_start_s + result.drift_s
            measured = [
                e for e in window if caught_t + DRIFT_SETTLE_S <= e[0] <= caught_t + DRIFT_SETTLE_S + DRIFT_MEASURE_S
            ]
            model_error = np.mean([e[3] - e[2] for e in measured], axis=0)
            held = np.array([e[4] for e in window if e[0] >= caught_t + 0.05])
            checks.append(
                DriftCheck(result, model_error, float(np.rad2deg(np.abs(held - held[0]).max())) if len(held) else 0.0)
            )
            self._ok(runtime.advance())  # back to compensation
            world.pilot_stiffness(1.0)
            world.pilot_carries(1.0)
            world.pilot_hold_here()
            self.run(0.5)
        return checks

    def blind_comparison(self, pairs: int, block_s: float, seed: int) -> dict[str, Any]:
        """A blind comparison of the model in use with the A Priori model, the simulated pilot moving
        between two poses in every block and rating it himself; returns the verdict."""
        runtime, world, shoulder = self.runtime, self.world, self.runtime.shoulder
        world.pilot_stiffness(1.0)
        world.pilot_carries(1.0)
        poses = [shoulder.q_from_isb(np.deg2rad(p), seed=runtime.last_sample.q_rad) for p in POSES_DEG[:2]]
        self._ok(runtime.compare(pairs, block_s, seed))
        for _ in range(2 * pairs):
            while runtime.status()["comparison"]["phase"] != "rating":
                for pose in poses:  # his task in every block: to one pose, hold it, to the other
                    world.pilot_move(pose, MOVE_S)
                    self.run(MOVE_S + 1.5)
                    if runtime.status()["comparison"]["phase"] == "rating":
                        break
            self._ok(runtime.rate(None))
        self.run(0.1)
        comparison = runtime.status()["comparison"]
        if "verdict" not in comparison:
            raise RuntimeError(f"no verdict: {comparison}")
        return comparison["verdict"]

    def close(self) -> None:
        self.runtime.shutdown("bench done")
        self.runtime.close()


def temporary_folder() -> Path:
    return Path(tempfile.mkdtemp(prefix="daror-online-"))
