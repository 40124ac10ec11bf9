"""HAL configurations (hal/config.py), the backend registry and ``open_hal`` (hal/interface.py), and the
``daror console`` options that build a backend (``--hal``, ``--scenario``, ``--hal-config``)."""

from __future__ import annotations

import importlib.metadata
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import structlog

from daror_runtime.cli import main
from daror_runtime.logs import configure_logging
from hal.config import (
    CAN_BITRATES,
    CanHalConfig,
    CanSimHalConfig,
    SimHalConfig,
    config_model,
    hal_config,
    load_hal_config,
)
from hal.errors import BackendUnavailableError, HalConfigError, InputError
from hal.interface import Command, Hal, backend_entry, backend_kinds, hal_class, open_hal, register_backend
from hal.registry import BackendRegistry, broken_backends, registry_restored
from hal.sim.backend import SimHal
from tests.outside import installed
from tests.standin_drives import StandInDrives, StandInHalConfig

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def default_logging() -> Iterator[None]:
    """``main`` configures logging for the process; put the defaults back afterwards."""
    yield
    configure_logging()


@pytest.fixture
def registry() -> Iterator[None]:
    """The backend registry, restored after the test."""
    with registry_restored():
        yield


def write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def one_line(err: str) -> str:
    """The command's own line on stderr (exactly one, the last)."""
    lines = err.rstrip("\n").split("\n")
    own = [line for line in lines if line.startswith("daror console: ")]
    assert own == lines[-1:], f"not one line of the command, at the end: {err!r}"
    return own[0]


# --- the variants ---------------------------------------------------------------------------------


def test_each_backend_has_its_variant_with_defaults() -> None:
    sim = hal_config("sim")
    assert isinstance(sim, SimHalConfig)
    assert (sim.scenario, sim.rate_hz, sim.seed, sim.robot) == ("exo_dummy_arm", 1000.0, None, None)
    can = hal_config("can")
    assert isinstance(can, CanHalConfig)
    assert (can.interface, can.channel, can.bitrate, can.node_ids) == ("socketcan", "can0", 1_000_000, [1, 2, 3, 4])
    assert (can.rate_hz, can.heartbeat_producer_ms, can.heartbeat_consumer_ms, can.eds) == (None, 100, 250, None)
    can_sim = hal_config("can-sim", scenario="exo")
    assert isinstance(can_sim, CanSimHalConfig)
    assert (can_sim.interface, can_sim.scenario) == ("virtual", "exo")
    assert 1_000_000 in CAN_BITRATES


@pytest.mark.parametrize(
    ("backend", "fields", "problem"),
    [
        ("sim", {"rate_hz": -5.0}, "rate_hz: Input should be greater than 0"),
        ("sim", {"rate_hz": True}, "rate_hz: Input should be a valid number"),
        ("sim", {"seed": 1.5}, "seed: Input should be a valid integer"),
        ("sim", {"interface": "pcan"}, "interface: the sim backend does not take it"),
        ("can", {"scenario": "exo"}, "scenario: the can backend does not take it"),
        ("can", {"bitrate": 999}, "bitrate: Input should be 10000, 20000"),
        ("can", {"node_ids": [1, 2, 2, 4]}, "node_ids: Value error, [1, 2, 2, 4]: expected four different node ids"),
        ("can", {"node_ids": [1, 2, 3]}, "node_ids: List should have at least 4 items"),
        ("can", {"node_ids": [1, 2, 3, 128]}, "node_ids.3: Input should be less than or equal to 127"),
        ("can", {"rate_hz": 5000.0}, "rate_hz: Input should be less than or equal to 2000"),
        ("can", {"heartbeat_consumer_ms": 100}, "heartbeat_consumer_ms: Value error, 100 ms is not longer than"),
        ("can-sim", {"channel": ""}, "channel: String should have at least 1 character"),
    ],
)
def test_fields_are_strict(backend: str, fields: dict[str, object], problem: str) -> None:
    with pytest.raises(HalConfigError) as caught:
        hal_config(backend, source="flags", **fields)
    message = str(caught.value)
    assert message.startswith("flags: ")
    assert problem in message
    assert "\n" not in message


def test_an_unknown_backend_is_named_with_the_choices() -> None:
    with pytest.raises(HalConfigError, match=r"unknown backend 'canbus'; expected one of sim, can-sim, can"):
        hal_config("canbus")


# --- files ----------------------------------------------------------------------------------------


def test_a_file_of_each_variant_loads(tmp_path: Path) -> None:
    sim = load_hal_config(write(tmp_path / "sim.yaml", "backend: sim\nscenario: exo\nrate_hz: 500\nseed: 3\n"))
    assert sim == SimHalConfig(scenario="exo", rate_hz=500.0, seed=3)
    can = load_hal_config(
        write(
            tmp_path / "can.yaml",
            "backend: can\n"
            "interface: pcan\n"
            "channel: PCAN_USBBUS1\n"
            "bitrate: 500000\n"
            "node_ids: [11, 12, 13, 14]\n"
            "rate_hz: 500\n"
            "heartbeat_producer_ms: 50\n"
            "heartbeat_consumer_ms: 120\n"
            "eds: drives/maxon.eds\n",
        )
    )
    assert isinstance(can, CanHalConfig)
    assert (can.interface, can.channel, can.bitrate, can.node_ids) == (
        "pcan",
        "PCAN_USBBUS1",
        500_000,
        [11, 12, 13, 14],
    )
    assert (can.heartbeat_producer_ms, can.heartbeat_consumer_ms) == (50, 120)
    assert can.eds == str(tmp_path / "drives" / "maxon.eds")  # relative to the file, not to the cwd
    can_sim = load_hal_config(write(tmp_path / "can_sim.yaml", "backend: can-sim\nscenario: plants/my.yaml\n"))
    assert isinstance(can_sim, CanSimHalConfig)
    assert can_sim.scenario == str(tmp_path / "plants" / "my.yaml")


def test_a_shipped_scenario_name_stays_a_name_and_an_absolute_path_stays(tmp_path: Path) -> None:
    scenario = tmp_path / "elsewhere.yaml"
    config = load_hal_config(write(tmp_path / "hal.yaml", f"backend: sim\nscenario: {scenario}\n"))
    assert config.scenario == str(scenario)  # type: ignore[union-attr]
    config = load_hal_config(write(tmp_path / "hal.yaml", "backend: sim\nscenario: exo\n"))
    assert config.scenario == "exo"  # type: ignore[union-attr]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("scenario: exo\n", "hal.yaml: field backend: missing; expected one of sim, can-sim, can"),
        ("backend: canbus\n", "hal.yaml: line 1, field backend: unknown backend 'canbus'; expected one of sim"),
        ("backend: 3\n", "hal.yaml: line 1, field backend: unknown backend 3 (int); expected one of"),
        ("backend: sim\nrate_hz: true\n", "hal.yaml: line 2, field rate_hz: Input should be a valid number; got true"),
        (
            "backend: sim\nrate_hz: '500'\n",
            "hal.yaml: line 2, field rate_hz: Input should be a valid number; got the text",
        ),
        ("backend: sim\nrate: 500\n", "hal.yaml: line 2, field rate: Extra inputs are not permitted"),
        ("backend: can\nscenario: exo\n", "hal.yaml: line 2, field scenario: Extra inputs are not permitted"),
        (
            "backend: can\nheartbeat_producer_ms: 300\n",
            "hal.yaml: line 1, field heartbeat_consumer_ms: Value error, 250 ms is not longer than",
        ),
        ("backend: can\nnode_ids: [1, 2, 3, 0]\n", "hal.yaml: line 2, field node_ids.3: Input should be greater than"),
        ("- backend: sim\n", "hal.yaml: line 1: expected a YAML mapping with a backend: key; found a list"),
        ("backend: sim\nbackend: can\n", "hal.yaml: line 2, field backend: key 'backend' is written twice"),
    ],
)
def test_a_bad_file_is_one_line_naming_file_line_and_field(tmp_path: Path, text: str, expected: str) -> None:
    path = write(tmp_path / "hal.yaml", text)
    with pytest.raises(HalConfigError) as caught:
        load_hal_config(path)
    message = str(caught.value)
    assert message.startswith(str(path))
    assert expected.replace("hal.yaml", str(path)) in message
    assert "\n" not in message
    assert isinstance(caught.value, InputError)


def test_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(HalConfigError, match=r"nowhere\.yaml"):
        load_hal_config(tmp_path / "nowhere.yaml")


# --- open_hal and the registry -------------------------------------------------------------------------


def test_open_hal_builds_the_simulated_plant_from_its_configuration() -> None:
    hal = open_hal(hal_config("sim", scenario="exo", rate_hz=500.0, seed=11))
    assert isinstance(hal, SimHal)
    assert (hal.kind, hal.rate_hz, hal.scenario.name, hal.scenario.seed) == ("sim", 500.0, "exo", 11)
    assert hal.virtual_time
    assert not hal.drives_hardware


def test_the_seed_of_the_configuration_replaces_the_scenarios() -> None:
    def readings(seed: int | None) -> np.ndarray:
        hal = open_hal(hal_config("sim", seed=seed))
        hal.open()
        for _ in range(5):
            hal.write(Command.torque_off())
        return hal.read().q_rad.copy()

    np.testing.assert_array_equal(readings(5), readings(5))
    assert not np.array_equal(readings(5), readings(6))
    np.testing.assert_array_equal(readings(None), readings(SimHal("exo_dummy_arm").scenario.seed))


def test_a_scenario_that_cannot_be_loaded_is_an_input_error() -> None:
    with pytest.raises(InputError, match="unknown scenario 'nowhere'"):
        open_hal(hal_config("sim", scenario="nowhere"))


def test_the_registry_imports_a_backend_only_when_asked(registry: None) -> None:
    register_backend("later", "tests.never_imported_backend:Never", "tests.never_imported_config:NeverConfig")
    assert "later" in backend_kinds()
    assert "tests.never_imported_backend" not in sys.modules  # no such modules: nothing happens yet
    assert "tests.never_imported_config" not in sys.modules
    with pytest.raises(BackendUnavailableError) as caught:
        hal_class("later")
    message = str(caught.value)
    assert (
        message == "HAL backend 'later' is not built yet: this installation has no module tests.never_imported_backend"
    )
    assert "No module named" not in message


def test_a_backend_whose_package_is_missing_names_the_package(
    registry: None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    write(tmp_path / "needs_a_package.py", "import daror_no_such_package.bus\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    register_backend("needy", "needs_a_package:Backend", "needs_a_package:Config")
    with pytest.raises(BackendUnavailableError) as caught:
        hal_class("needy")
    assert str(caught.value) == (
        "HAL backend 'needy' needs the Python package 'daror_no_such_package', which is not installed "
        "(pip install daror_no_such_package)"
    )


def test_a_registry_entry_that_is_not_a_hal_is_refused(registry: None) -> None:
    register_backend("odd", "hal.robot:RobotDescription", "hal.config:SimHalConfig")
    with pytest.raises(BackendUnavailableError, match=r"module hal\.robot has no Hal class RobotDescription"):
        hal_class("odd")
    with pytest.raises(HalConfigError, match="expected 'module:Class'"):
        register_backend("bad", "hal.robot", "hal.config:SimHalConfig")
    with pytest.raises(HalConfigError, match="expected 'module:Model'"):
        register_backend("bad", "hal.sim.backend:SimHal", "hal.config")
    with pytest.raises(HalConfigError, match=r"^HAL backend 'bad': config missing; expected"):
        register_backend("bad", "hal.sim.backend:SimHal")
    with pytest.raises(HalConfigError, match="expected a name of lower-case letters, digits and hyphens"):
        register_backend("Bad Name", "hal.sim.backend:SimHal", "hal.config:SimHalConfig")
    assert "bad" not in backend_kinds()
    with pytest.raises(HalConfigError, match="unknown HAL backend 'none'"):
        hal_class("none")


def _without(monkeypatch: pytest.MonkeyPatch, package: str) -> None:
    """This process as a core install sees it: no ``package``, no CANopen backend module loaded yet."""
    import sys

    monkeypatch.setitem(sys.modules, package, None)  # None in sys.modules: "import package" fails
    for name in [m for m in sys.modules if m == "hal.canopen" or m.startswith("hal.canopen.")]:
        monkeypatch.delitem(sys.modules, name)


def _without_python_can(monkeypatch: pytest.MonkeyPatch) -> None:
    _without(monkeypatch, "can")


def test_the_can_backend_says_so_when_canopen_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    _without(monkeypatch, "canopen")
    with pytest.raises(BackendUnavailableError) as caught:
        open_hal(hal_config("can-sim"))
    assert str(caught.value) == (
        "HAL backend 'can-sim' needs the Python package 'canopen', which is not installed "
        "(pip install 'daror-runtime[can]')"
    )


@pytest.mark.parametrize("backend", ["can", "can-sim"])
def test_the_can_backends_say_which_package_a_core_install_lacks(backend: str, monkeypatch: pytest.MonkeyPatch) -> None:
    _without_python_can(monkeypatch)
    with pytest.raises(BackendUnavailableError) as caught:
        open_hal(hal_config(backend))
    assert str(caught.value) == (
        f"HAL backend {backend!r} needs the Python package 'python-can', which is not installed "
        "(pip install 'daror-runtime[can]')"
    )


# --- daror console: the HAL options ----------------------------------------------------------------------

SCRIPT = "expect state startup\nwait 0.01\n"


def console(capsys: pytest.CaptureFixture[str], *argv: object) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["console", *map(str, argv)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_console_on_a_backend_without_its_package_exits_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    _without_python_can(monkeypatch)
    script = write(tmp_path / "s.txt", SCRIPT)
    out = tmp_path / "session"
    code, _, err = console(capsys, "--hal", "can", "--script", script, "--out", out)
    assert code == 2
    assert one_line(err) == (
        "daror console: error: HAL backend 'can' needs the Python package 'python-can', which is not installed "
        "(pip install 'daror-runtime[can]')"
    )
    assert not out.exists()


@pytest.mark.slow
def test_console_runs_on_a_hal_configuration_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = write(tmp_path / "hal.yaml", "backend: sim\nscenario: exo\nrate_hz: 500\n")
    script = write(tmp_path / "s.txt", SCRIPT)
    out = tmp_path / "session"
    code, printed, err = console(capsys, "--hal-config", config, "--script", script, "--out", out)
    assert code == 0, err
    assert "script done: 2 lines, state startup" in printed
    assert (out / "session.json").is_file()


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (
            ["--hal-config", "{config}", "--hal", "sim"],
            "--hal-config names the backend and its scenario; leave out --hal",
        ),
        (["--hal-config", "{config}", "--scenario", "exo"], "leave out --scenario"),
        (
            ["--hal", "can", "--scenario", "exo"],
            "--scenario names a simulated plant: it goes with --hal sim or can-sim",
        ),
        (["--hal-config", "{bad}"], "{bad}: line 2, field rate_hz: Input should be greater than 0"),
        (["--scenario", "nowhere"], "unknown scenario 'nowhere'"),
    ],
)
def test_console_hal_options_that_make_no_sense_exit_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], expected: str
) -> None:
    files = {
        "config": write(tmp_path / "hal.yaml", "backend: sim\n"),
        "bad": write(tmp_path / "bad.yaml", "backend: sim\nrate_hz: 0\n"),
    }
    script = write(tmp_path / "s.txt", SCRIPT)
    out = tmp_path / "session"
    argv = [a.format(**files) for a in argv]
    code, _, err = console(capsys, *argv, "--script", script, "--out", out)
    assert code == 2
    assert expected.format(**files) in one_line(err)
    assert not out.exists()


def test_a_backend_without_from_config_is_refused_in_one_line(registry: None) -> None:
    register_backend("can", "tests.hal.test_hal_config:NoConfiguration", "hal.config:CanHalConfig")
    with pytest.raises(BackendUnavailableError, match=r"^HAL backend 'bare' cannot be built from a configuration$"):
        open_hal(hal_config("can"))


class NoConfiguration(StandInDrives):
    """A backend that does not say how to build it from a configuration (the ABC's default)."""

    kind = "bare"
    from_config = classmethod(Hal.from_config.__func__)  # type: ignore[assignment]  # the ABC's own


# --- backends from other packages (entry points) ----------------------------------------------------


def test_a_backend_from_outside_is_listed_configured_and_opened(tmp_path: Path) -> None:
    """The stand-in drives' package (tests/data/outside_backend) registers ``stand-in`` through its entry point."""
    assert "stand-in" not in backend_kinds()
    with installed():
        assert backend_kinds() == ("sim", "can-sim", "can", "stand-in")  # built-ins first, plug-ins after
        config = load_hal_config(write(tmp_path / "hal.yaml", "backend: stand-in\nrate_hz: 500\n"))
        assert config == StandInHalConfig(rate_hz=500.0)
        assert config_model("stand-in") is StandInHalConfig
        hal = open_hal(config)
        assert isinstance(hal, StandInDrives)
        assert hal.rate_hz == 500.0
        with pytest.raises(HalConfigError) as caught:
            load_hal_config(write(tmp_path / "bad.yaml", "backend: stand-in\nrate: 500\n"))
        assert str(caught.value) == f"{tmp_path / 'bad.yaml'}: line 2, field rate: Extra inputs are not permitted"
        with pytest.raises(HalConfigError, match=r"flags: scenario: the stand-in backend does not take it$"):
            hal_config("stand-in", source="flags", scenario="exo")
        with pytest.raises(HalConfigError, match=r"expected one of sim, can-sim, can, stand-in$"):
            hal_config("canbus")
    assert "stand-in" not in backend_kinds()


def test_the_entry_points_are_read_once_and_only_when_needed() -> None:
    reads: list[int] = []

    def entry_points() -> list[importlib.metadata.EntryPoint]:
        reads.append(1)
        return []

    registry = BackendRegistry(entry_points=entry_points)
    assert registry.entry("sim").target == "hal.sim.backend:SimHal"
    assert registry.entry("can").config == "hal.config:CanHalConfig"
    assert reads == []  # a built-in asked for: nothing read
    assert registry.kinds() == ("sim", "can-sim", "can")
    assert registry.kinds() == ("sim", "can-sim", "can")
    with pytest.raises(HalConfigError, match=r"^unknown HAL backend 'nope'; expected one of sim, can-sim, can$"):
        registry.entry("nope")
    assert reads == [1]


@pytest.mark.subprocess
def test_importing_the_hal_and_building_a_builtin_reads_no_entry_point() -> None:
    """Start-up (``daror hil``, a session on ``sim``) never reads the installed packages' entry points."""
    code = (
        "import importlib.metadata as m\n"
        "everyones = m.entry_points\n"
        "def watched(**selection):\n"
        "    if selection.get('group') == 'daror_runtime.hal_backends':\n"
        "        raise SystemExit('entry points read')\n"
        "    return everyones(**selection)\n"  # others' (numba reads its extensions')
        "m.entry_points = watched\n"
        "from hal.config import hal_config, load_hal_config\n"
        "from hal.interface import hal_class, open_hal\n"
        "open_hal(hal_config('sim'))\n"
        "hal_class('can-sim')\n"
        "hal_config('can')\n"
        "print('ok')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert (done.returncode, done.stdout, done.stderr) == (0, "ok\n", "")


#: A package with broken backend plug-ins (its module and its dist-info written into a test's folder).
BROKEN_MODULE = """
from hal.registry import BackendEntry

ELSEWHERE = BackendEntry("other", "hal.sim.backend:SimHal", "hal.config:SimHalConfig")
NOT_A_MODEL = BackendEntry("not-a-model", "hal.sim.backend:SimHal", "hal.robot:RobotDescription")
WRONG_LITERAL = BackendEntry("wrong-literal", "hal.sim.backend:SimHal", "hal.config:SimHalConfig")
REPLACES_SIM = BackendEntry("sim", "broken_plugins:Nothing", "broken_plugins:Nothing")


def fails():
    raise RuntimeError("no drives\\nfound")
"""
BROKEN_ENTRY_POINTS = """[daror_runtime.hal_backends]
gone = no_such_module_of_a_plugin:BACKEND
number = hal.robot:N_JOINTS
misnamed = broken_plugins:ELSEWHERE
fails = broken_plugins:fails
not-a-model = broken_plugins:NOT_A_MODEL
wrong-literal = broken_plugins:WRONG_LITERAL
sim = broken_plugins:REPLACES_SIM
"""


@pytest.fixture
def broken_plugins(tmp_path: Path) -> Iterator[Path]:
    """A package ``broken-plugins 0.1`` installed, whose backend entry points are broken in every way."""
    folder = tmp_path / "site"
    (folder / "broken_plugins-0.1.dist-info").mkdir(parents=True)
    write(folder / "broken_plugins.py", BROKEN_MODULE)
    write(
        folder / "broken_plugins-0.1.dist-info" / "METADATA",
        "Metadata-Version: 2.1\nName: broken-plugins\nVersion: 0.1\n",
    )
    write(folder / "broken_plugins-0.1.dist-info" / "entry_points.txt", BROKEN_ENTRY_POINTS)
    with installed(folder):
        yield folder


def test_a_broken_plugin_is_one_line_and_the_builtins_work_on(broken_plugins: Path, tmp_path: Path) -> None:
    with structlog.testing.capture_logs() as logs:
        kinds = backend_kinds()
    assert kinds == ("sim", "can-sim", "can", "not-a-model", "wrong-literal")  # their entries load; their models not
    assert backend_entry("sim").target == "hal.sim.backend:SimHal"  # a plug-in never replaces a built-in
    origin = "of package broken-plugins 0.1"
    expected = {
        "fails": f"entry point fails = broken_plugins:fails {origin} cannot be loaded: RuntimeError: no drives found",
        "gone": (
            f"entry point gone = no_such_module_of_a_plugin:BACKEND {origin} cannot be loaded: "
            "ModuleNotFoundError: No module named 'no_such_module_of_a_plugin'"
        ),
        "misnamed": f"entry point misnamed = broken_plugins:ELSEWHERE {origin} gives backend 'other'; expected 'misnamed', its entry point's name",
        "number": f"entry point number = hal.robot:N_JOINTS {origin} gives a int; expected a hal.registry.BackendEntry (or a function returning one)",
    }
    assert broken_backends() == expected
    warned = {entry["backend"]: entry for entry in logs if entry["log_level"] == "warning"}
    assert {name: entry["problem"] for name, entry in warned.items() if "problem" in entry} == expected
    assert "broken_plugins:REPLACES_SIM" in warned["sim"]["plugin"]
    for name, problem in expected.items():
        with pytest.raises(BackendUnavailableError) as caught:
            hal_class(name)
        assert str(caught.value) == f"HAL backend {name!r} cannot be used: {problem}"
        path = write(tmp_path / f"{name}.yaml", f"backend: {name}\n")
        with pytest.raises(BackendUnavailableError) as caught:
            load_hal_config(path)
        assert str(caught.value) == f"{path}: line 1, field backend: HAL backend {name!r} cannot be used: {problem}"
    with pytest.raises(BackendUnavailableError) as caught:
        hal_config("not-a-model", source="flags")
    assert str(caught.value) == (
        "flags: field backend: HAL backend 'not-a-model': its configuration hal.robot:RobotDescription "
        "is not a hal.config.AnyHalConfig model"
    )
    with pytest.raises(BackendUnavailableError) as caught:
        hal_config("wrong-literal", source="flags")
    assert str(caught.value) == (
        "flags: field backend: HAL backend 'wrong-literal': its configuration hal.config:SimHalConfig "
        "has backend: typing.Literal['sim']; expected Literal['wrong-literal']"
    )
    hal = open_hal(hal_config("sim"))  # the built-ins, untouched
    assert isinstance(hal, SimHal)


def test_console_names_a_broken_plugin_in_one_line(
    broken_plugins: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write(tmp_path / "hal.yaml", "backend: gone\n")
    script = write(tmp_path / "s.txt", SCRIPT)
    out = tmp_path / "session"
    code, _, err = console(capsys, "--hal-config", config, "--script", script, "--out", out)
    assert code == 2
    assert one_line(err) == (
        f"daror console: error: {config}: line 1, field backend: HAL backend 'gone' cannot be used: entry point "
        "gone = no_such_module_of_a_plugin:BACKEND of package broken-plugins 0.1 cannot be loaded: "
        "ModuleNotFoundError: No module named 'no_such_module_of_a_plugin'"
    )
    assert not out.exists()
