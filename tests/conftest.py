"""Shared fixtures: the robot description, the shipped scenarios and small simulated datasets."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

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

# A console session records itself into the lab's records when it ends (issue 28: daror.db beside
# its folder). The suite's hundreds of sessions record nothing unless a test asks: the records' own
# tests pass --db or clear this, and the README transcript runs as its reader would (without it).
os.environ.setdefault("DAROR_DB", "none")


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


#: Seconds the longest files took in one run of the whole suite on two workers (2026-11-29, 15:27 UTC,
#: at 5df0455: the sum of each file's tests, from ``pytest -n 2 --dist loadgroup --junitxml`` in a fresh
#: clone). A scheduling hint only: a stale figure costs balance, never a result.
LONG_FILES_S = {
    "test_hazard_mutations.py": 120,
    "test_readme_transcript.py": 110,
    "test_residual_hysteresis.py": 53,
    "test_hal_contract.py": 46,
    "test_canopen_hil.py": 39,
    "test_web_console.py": 39,
    "test_fault_reactions.py": 35,
    "test_hpsearch.py": 33,
    "test_protocol_design.py": 32,
    "test_console_operator.py": 28,
    "test_residual_learned.py": 22,
    "test_neural.py": 21,
    "test_returning_pilot.py": 19,
    "test_canopen_robot_golden.py": 19,
    "test_session_safety.py": 19,
    "test_boundaries.py": 17,
    "test_signal_map.py": 16,
    "test_yaml_hostile.py": 16,
    "test_canopen_interop_lockstep.py": 15,
    "test_signals.py": 13,
    "test_residual_scale.py": 12,
    "test_demo_session.py": 12,
    "test_session_loop.py": 10,
    "test_residual_cli.py": 10,
    "test_records.py": 10,
    "test_fsm_properties.py": 9,
}


#: The work unit of every test marked ``realtime`` (``make test``: one worker runs them one after
#: another, first, while the other worker runs the longest file; D208).
REALTIME_GROUP = "realtime"
#: Where xdist's workers write the ids of the tests marked ``realtime`` for the controller's
#: scheduler (a key of ``workerinput``; the controller only ever sees test ids, never marks).
REALTIME_IDS_KEY = "daror_realtime_ids"
_REALTIME_IDS_PATH = pytest.StashKey[Path]()


def _is_realtime(item: pytest.Item) -> bool:
    return item.get_closest_marker("realtime") is not None


@pytest.hookimpl(tryfirst=True)  # before ``-m`` deselects: every item, real-time ones included
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The real-time tests first, then the longest files first (stable within a file and among the others).

    ``make test`` hands whole files to its two workers (:class:`FilesAndTheRealTimeGroup`: a
    module's fixtures are built once); starting with the longest keeps one worker from finishing
    alone with a long file left. The tests marked ``realtime`` are one unit, handed out first: one
    worker runs them one after another while the other runs one file, so they share the machine
    with one busy process of the suite at most, and each measures its margin first
    (:func:`_real_time_margin`). Every worker collects the same order (it depends on file names and
    marks only); on a worker, the real-time tests' ids are written where the controller's
    scheduler reads them.
    """
    first_index: dict[str, int] = {}
    for index, item in enumerate(items):
        first_index.setdefault(item.path.name, index)

    def place(item: pytest.Item) -> tuple[bool, int, int]:
        return not _is_realtime(item), -LONG_FILES_S.get(item.path.name, 0), first_index[item.path.name]

    items.sort(key=place)
    target = getattr(config, "workerinput", {}).get(REALTIME_IDS_KEY)
    if target is not None:
        written = Path(f"{target}.{os.getpid()}")
        written.write_text(json.dumps([item.nodeid for item in items if _is_realtime(item)]), encoding="utf-8")
        written.replace(target)  # both workers write the same list; each whole


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node: Any) -> None:
    """Controller side, as xdist starts a worker: where it writes the real-time tests' ids (one file per run)."""
    config = node.config
    if _REALTIME_IDS_PATH not in config.stash:
        config.stash[_REALTIME_IDS_PATH] = Path(tempfile.mkdtemp(prefix="daror-xdist-")) / "realtime.json"
    node.workerinput[REALTIME_IDS_KEY] = str(config.stash[_REALTIME_IDS_PATH])


def pytest_unconfigure(config: pytest.Config) -> None:
    """Controller side, at the end of the run: the folder of the real-time tests' ids goes (nothing is left in /tmp)."""
    path = config.stash.get(_REALTIME_IDS_PATH, None)
    if path is not None:
        shutil.rmtree(path.parent, ignore_errors=True)


try:
    from xdist.scheduler import LoadScopeScheduling
except ImportError:  # pragma: no cover - the dev extra has xdist; a row of the mutation run loads no plug-in
    LoadScopeScheduling = None


if LoadScopeScheduling is not None:

    class FilesAndTheRealTimeGroup(LoadScopeScheduling):  # type: ignore[misc,valid-type]
        """Whole files as the unit (``loadfile``'s), and every test marked ``realtime`` in one unit of its own.

        xdist's own ``loadgroup`` cannot do it here: it marks a group in the test's id, which
        pytest 9 no longer lets a plug-in change. The workers write the real-time tests' ids
        instead (:func:`pytest_collection_modifyitems`), before they report their collection,
        so every id is known when the controller splits the work.
        """

        def __init__(self, config: pytest.Config, log: Any = None, realtime_ids: Path | None = None) -> None:
            super().__init__(config, log)
            self._realtime_ids_path = realtime_ids
            self._realtime_ids: frozenset[str] | None = None

        def _split_scope(self, nodeid: str) -> str:
            if self._realtime_ids is None:
                path = self._realtime_ids_path
                ids = json.loads(path.read_text(encoding="utf-8")) if path is not None and path.exists() else []
                self._realtime_ids = frozenset(ids)
            if nodeid in self._realtime_ids:
                return REALTIME_GROUP
            return nodeid.split("::", 1)[0]


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadgroup`` schedules by :class:`FilesAndTheRealTimeGroup` (``make test``); other modes are xdist's."""
    if LoadScopeScheduling is None or config.getvalue("dist") != "loadgroup":
        return None
    return FilesAndTheRealTimeGroup(config, log, config.stash.get(_REALTIME_IDS_PATH, None))


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


#: The scheduling priority (nice value) a real-time test asks for where the system allows it (root,
#: or CAP_SYS_NICE): what the runtime's own loop asks for is real-time scheduling (daror_runtime/realtime.py).
REALTIME_NICE = -10


def _priority_for(realtime: bool) -> None:
    """This thread's nice value for the coming test: :data:`REALTIME_NICE` for a real-time one where allowed, else 0.

    Only a nice value this suite set (0 or :data:`REALTIME_NICE`) is changed: ``nice make test``
    keeps the caller's. The threads and processes the test starts inherit it.
    """
    current = os.getpriority(os.PRIO_PROCESS, 0)
    target = REALTIME_NICE if realtime else 0
    if current == target or current not in (0, REALTIME_NICE):
        return
    with contextlib.suppress(PermissionError):  # not allowed to raise it: the margin decides alone
        os.setpriority(os.PRIO_PROCESS, 0, target)


@pytest.fixture(autouse=True)
def _real_time_margin(request: pytest.FixtureRequest) -> None:
    """A test marked ``realtime`` needs wall-clock time (threads paced by the clock, a pseudo-terminal).

    It asks for a higher scheduling priority where the system allows it (:data:`REALTIME_NICE`;
    the next test that is not real-time gives it back), then measures the machine's margin: when
    other processes keep the cores so busy that this one gets less than
    :data:`REALTIME_CPU_SHARE` of a core, the test is skipped with the figure and the load instead
    of failing by luck. ``make test`` runs them one after another on one worker, beside one file's
    tests on the other: the suite itself never puts more than one busy process beside them (D208).
    """
    realtime = request.node.get_closest_marker("realtime") is not None
    _priority_for(realtime)
    if not realtime:
        return
    share = cpu_share_now()
    if share < REALTIME_CPU_SHARE:
        load_1min = os.getloadavg()[0]
        nice = os.getpriority(os.PRIO_PROCESS, 0)
        pytest.skip(
            f"this machine cannot give real time now: this process gets {share:.0%} of a core at nice {nice} "
            f"(margin {REALTIME_CPU_SHARE:.0%}), 1-min load {load_1min:.1f}"
        )
