"""Shared fixtures: the robot description, the shipped scenarios and small simulated datasets."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import settings

from daror_runtime.data.load import write_dataset
from daror_runtime.data.provenance import simulated_pilot, simulated_robot, write_provenance
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.logs import configure_logging, flush_logs
from daror_runtime.models.files import save_model, training_summary
from daror_runtime.models.registry import fit_model, installation_options
from hal.robot import RobotDescription, load_description
from hal.sim.scenario import Scenario, load_scenario
from hal.sim.static_dataset import StationarySet, generate_stationary

# Quiet by default: the runtime's audit events go nowhere unless a test asks for them
# (structlog.testing.capture_logs, or configure_logging with a JSON file).
configure_logging("critical")

# A shell runs a background job (`make test &`) with SIGINT ignored, and a command started with it
# ignored never turns Ctrl-C into KeyboardInterrupt: the tests that press Ctrl-C on a `daror`
# command would then time out. A handler here (not "ignored") is reset to the default in every
# command the tests start, whoever started the suite.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# CI draws the same examples every run (derandomize: each test's own seed), so its verdict never
# rests on luck; `make explore` draws new ones, and a case it finds becomes an `@example` (D192).
settings.register_profile("ci", max_examples=200, deadline=None, derandomize=True, database=None)
settings.register_profile("dev", max_examples=50, deadline=None)
settings.register_profile("explore", max_examples=1000, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


def as_dataset(points: StationarySet, source: str = "<simulated>") -> StationaryDataset:
    """The measured part of a simulated set, as the runtime's dataset type."""
    return StationaryDataset(points.q_rad, points.tau_nm, points.direction, points.t_s, source)


@pytest.fixture(autouse=True, scope="module")
def _quiet_logs_after_each_module() -> Iterator[None]:
    """A module that configured logging (a JSON file, a console level) does not leak it to the next."""
    yield
    flush_logs()
    configure_logging("critical")


@pytest.fixture(scope="session")
def description() -> RobotDescription:
    return load_description()


@pytest.fixture(scope="session")
def exo() -> Scenario:
    return load_scenario("exo")


@pytest.fixture(scope="session")
def exo_dummy_arm() -> Scenario:
    return load_scenario("exo_dummy_arm")


@pytest.fixture(scope="session")
def dataset_b(exo_dummy_arm: Scenario) -> tuple[StationaryDataset, StationaryDataset]:
    """Training and validation sets of dataset B (exo + Dummy Arm, noise and direction error)."""
    train = as_dataset(generate_stationary(exo_dummy_arm, "training"), "B-training")
    validation = as_dataset(generate_stationary(exo_dummy_arm, "validation"), "B-validation")
    return train, validation


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261121)


@dataclass(frozen=True)
class Models:
    """Model files of the Dummy Arm scenario for sessions that select a model (issue 9's tests)."""

    good: Path  # PLF+ fitted on the scenario's training set (validates at ~0.42 Nm)
    tripled: Path  # PLF+ fitted on the same set with every torque multiplied by 3 (fails validation)
    training: Path
    validation: Path


def recorded_by_an_earlier_session(path: Path, scenario: Scenario, run: str) -> None:
    """Give ``path`` the provenance an earlier session of ``scenario``'s simulated pilot would have written.

    A session validates a model only on data recorded from its pilot on its robot (issue 24): the
    simulated datasets the tests use stand for such a recording.
    """
    robot = simulated_robot(scenario.description().name, scenario.name)
    write_provenance(path, "session", robot, simulated_pilot(scenario.name), "earlier-session", run, scenario.name)


@pytest.fixture(scope="session")
def models(tmp_path_factory: pytest.TempPathFactory, exo_dummy_arm: Scenario) -> Models:
    folder = tmp_path_factory.mktemp("models")
    points = generate_stationary(exo_dummy_arm, "training")
    files = Models(folder / "plf_plus.json", folder / "plf_plus_x3.json", folder / "train.csv", folder / "val.csv")

    def dataset(set_: StationarySet, scale: float = 1.0) -> StationaryDataset:
        return StationaryDataset(set_.q_rad, set_.tau_nm * scale, set_.direction, set_.t_s)

    write_dataset(files.training, dataset(points))
    write_dataset(files.validation, dataset(generate_stationary(exo_dummy_arm, "validation")))
    for path, run in ((files.training, "training"), (files.validation, "validation")):
        recorded_by_an_earlier_session(path, exo_dummy_arm, run)
    for path, scale in ((files.good, 1.0), (files.tripled, 3.0)):
        data = dataset(points, scale)
        result = fit_model("plf+", data, exo_dummy_arm.description(), installation_options("plf+", dummy_arm=True))
        save_model(path, result.model, training_summary(data, files.training if scale == 1.0 else None), result.report)
    return files


#: Seconds the longest files took in one run of the whole suite on two workers (2026-11-29, load ~2;
#: the sum of each file's tests, from ``pytest -n 2 --dist loadfile --junitxml``; the README's and the
#: CAN sessions' from a fresh-clone ``make test``'s durations after D200). A scheduling hint only: a
#: stale figure costs balance, never a result.
LONG_FILES_S = {
    "test_hazard_mutations.py": 118,
    "test_readme_transcript.py": 86,
    "test_residual_hysteresis.py": 47,
    "test_web_console.py": 36,
    "test_canopen_hil.py": 35,
    "test_hal_contract.py": 35,
    "test_fault_reactions.py": 29,
    "test_hpsearch.py": 29,
    "test_protocol_design.py": 28,
    "test_console_operator.py": 25,
    "test_demo_session.py": 25,
    "test_signal_map.py": 25,
    "test_neural.py": 24,
    "test_residual_learned.py": 19,
    "test_session_safety.py": 15,
    "test_canopen_robot_golden.py": 15,
    "test_boundaries.py": 14,
    "test_canopen_interop_lockstep.py": 12,
}


#: Where a run that collected the whole suite keeps the files that hold real-time tests (pytest's
#: cache, ``.pytest_cache``): ``make test``'s real-time tier, run right after, collects only those.
REALTIME_FILES_KEY = "daror/realtime_files"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--realtime-files-from-cache",
        action="store_true",
        help="collect only the files that held a realtime test in the last whole-suite collection "
        "(make test's real-time tier; everything when no such collection is cached)",
    )


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """With ``--realtime-files-from-cache``: a test file that held no real-time test is not even imported.

    Collecting the whole suite to deselect all but 29 tests was 6 s of the serial real-time tier;
    its seven files take 2.3 s. The list comes from the parallel tier's collection in the same
    ``make test`` (:func:`pytest_collection_modifyitems`), never from an older run of a part.
    """
    if not config.getoption("realtime_files_from_cache") or not collection_path.name.startswith("test_"):
        return None
    assert config.cache is not None
    files = config.cache.get(REALTIME_FILES_KEY, None)
    if files is None:
        return None
    return str(collection_path.relative_to(config.rootpath)) not in files


def _whole_suite(config: pytest.Config) -> bool:
    """True when this run collected every test file (the configured test paths, no last-failed filter)."""
    return (
        config.args_source == pytest.Config.ArgsSource.TESTPATHS
        and not config.getoption("lf", False)
        and not config.getoption("realtime_files_from_cache")
    )


@pytest.hookimpl(tryfirst=True)  # before ``-m`` deselects: every item, real-time ones included
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The longest files first (stable within a file and among the others); remember the real-time files.

    ``make test`` hands whole files to its two workers (``--dist loadfile``: a module's fixtures are
    built once); starting with the longest keeps one worker from finishing alone with a long file
    left. Every worker collects the same order (it depends on file names only). A whole-suite
    collection also stores which files hold a test marked ``realtime`` (:data:`REALTIME_FILES_KEY`).
    """
    first_index: dict[str, int] = {}
    for index, item in enumerate(items):
        first_index.setdefault(item.path.name, index)
    items.sort(key=lambda item: (-LONG_FILES_S.get(item.path.name, 0), first_index[item.path.name]))
    if _whole_suite(config) and config.cache is not None:
        realtime = {
            str(item.path.relative_to(config.rootpath)) for item in items if item.get_closest_marker("realtime")
        }
        config.cache.set(REALTIME_FILES_KEY, sorted(realtime))


#: A real-time test runs only while this process gets at least this share of a core when it asks for one.
REALTIME_CPU_SHARE = 0.4
#: How long the share is measured before a real-time test (s of wall-clock time).
REALTIME_PROBE_S = 0.1


def cpu_share_now(probe_s: float = REALTIME_PROBE_S) -> float:
    """The share of one core a busy thread of this process gets now (CPU time / wall-clock time, 0..1).

    What a real-time test needs is CPU when its threads (the drives, the master, a terminal's
    process) are due; a wake-up latency probe does not see another process keeping the cores busy
    (the scheduler favours a thread that slept), the CPU share does.
    """
    wall_began, cpu_began = time.perf_counter(), time.thread_time()
    while time.perf_counter() - wall_began < probe_s:
        pass
    return (time.thread_time() - cpu_began) / (time.perf_counter() - wall_began)


@pytest.fixture(autouse=True)
def _real_time_margin(request: pytest.FixtureRequest) -> None:
    """A test marked ``realtime`` needs wall-clock time (threads paced by the clock, a pseudo-terminal).

    It measures the machine's margin first: when other processes keep the cores so busy that this
    one gets less than :data:`REALTIME_CPU_SHARE` of a core, the test is skipped with the figure and
    the load instead of failing by luck. ``make test`` runs these tests alone, after the parallel
    tier, so the suite itself never loads the machine under them.
    """
    if request.node.get_closest_marker("realtime") is None:
        return
    share = cpu_share_now()
    if share < REALTIME_CPU_SHARE:
        load_1min = os.getloadavg()[0]
        pytest.skip(
            f"this machine cannot give real time now: this process gets {share:.0%} of a core "
            f"(margin {REALTIME_CPU_SHARE:.0%}), 1-min load {load_1min:.1f}"
        )
