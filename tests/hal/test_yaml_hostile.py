"""Hostile YAML for every loader that reads a file a person hands in (``hal/yamlfile.py``).

The FSM spec (``daror fsm check``), session settings (``daror console --settings``), simulation
scenarios (``daror simulate static --scenario``) and a pilot's ISB limits (``daror identify
--isb-limits``): each hostile file is refused by the loader with an :class:`InputError` naming the
file (and the line and field where there is one), and by the command with exit code 2, its error
line naming the file, no traceback, nothing created, quickly (the billion laughs and the deep
nesting included: a refusal takes milliseconds; :data:`FAST_S` catches a blow-up or a hang).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from daror_runtime.cli import main
from daror_runtime.errors import InputError
from daror_runtime.fsm.spec import DEFAULT_SPEC_PATH, FsmSpecError, load_fsm_spec
from daror_runtime.session.settings import SessionSettingsError, load_session_settings
from hal.errors import DescriptionError
from hal.files import YAML_MAX_BYTES
from hal.isb import IsbLimitsError, load_isb_limits
from hal.sim.scenario import load_scenario
from hal.yamlfile import MAX_DEPTH, MAX_NODES

FAST_S = 5.0
SPEC_TEXT = DEFAULT_SPEC_PATH.read_text(encoding="utf-8")
SHORT_SCRIPT = "wait 0.1\nquit\n"


# --- the hostile files -------------------------------------------------------------------------


@dataclass(frozen=True)
class Hostile:
    """A hostile file: how to make it (in a folder, as ``name``), what the refusal says, on which line."""

    make: Callable[[Path, str], Path]
    fragment: str
    line: int | None = None


def text(content: str, fragment: str, line: int | None = None) -> Hostile:
    def make(folder: Path, name: str) -> Path:
        path = folder / name
        path.write_text(content, encoding="utf-8")
        return path

    return Hostile(make, fragment, line)


def raw(content: bytes, fragment: str, line: int | None = None) -> Hostile:
    def make(folder: Path, name: str) -> Path:
        path = folder / name
        path.write_bytes(content)
        return path

    return Hostile(make, fragment, line)


def _unblock_later(fifo: Path) -> None:
    """Should the code under test ever open the FIFO, give it an end of file after a while instead of a hang."""

    def release() -> None:
        with contextlib.suppress(OSError):  # nobody is reading: as it should be
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))

    timer = threading.Timer(2 * FAST_S, release)
    timer.daemon = True
    timer.start()


def _fifo(folder: Path, name: str) -> Path:
    path = folder / name
    os.mkfifo(path)
    _unblock_later(path)
    return path


def _directory(folder: Path, name: str) -> Path:
    path = folder / name
    path.mkdir()
    return path


def _loop(folder: Path, name: str) -> Path:
    path = folder / name
    path.symlink_to(path)
    return path


def _zero(folder: Path, name: str) -> Path:
    zero = Path("/dev/zero")
    if not zero.exists():
        pytest.skip("no /dev/zero here")
    return zero


def _laughs() -> str:
    """The billion laughs: 10 levels of 10 aliases, 10^10 strings once expanded."""
    rows = ['lol0: &lol0 "lol"']
    rows += [f"lol{k}: &lol{k} [{', '.join([f'*lol{k - 1}'] * 10)}]" for k in range(1, 10)]
    return "\n".join(rows) + "\n"


#: Hostile whatever the loader: refused while reading, before the file's schema is looked at.
GENERIC: dict[str, Hostile] = {
    "billion laughs": text(_laughs(), "YAML anchors (&lol0) are not allowed", 1),
    "an alias": text("name: x\nother: *nowhere\n", "YAML aliases (*nowhere) are not allowed", 2),
    "200,000 nested brackets": text(
        "a: " + "[" * 200_000 + "]" * 200_000 + "\n", f"nested more than {MAX_DEPTH} levels"
    ),
    "200,000 nested flow mappings": text("a: " + "{a: " * 100_000 + "1" + "}" * 100_000 + "\n", "nested more than"),
    "100 levels of block nesting": text(
        "".join("  " * k + "a:\n" for k in range(100)) + "  " * 100 + "a: 1\n",
        f"nested more than {MAX_DEPTH} levels",
        MAX_DEPTH + 1,
    ),
    "python object tag": text(
        'name: !!python/object/apply:os.system ["touch pwned"]\n',
        "YAML tag '!!python/object/apply:os.system' is not allowed",
        1,
    ),
    "custom tag": text("name: !include other.yaml\n", "YAML tag '!include' is not allowed", 1),
    "binary tag": text("name: !!binary aGVsbG8=\n", "YAML tag '!!binary' is not allowed", 1),
    "merge key": text("name: x\nsub:\n  <<: {a: 1}\n  b: 2\n", "merge keys (<<) are not allowed", 3),
    "a list, not a mapping": text("- 1\n- 2\n", "found a list", 1),
    "a scalar, not a mapping": text("just some words\n", "found a single text value", 1),
    "null, not a mapping": text("~\n", "found nothing (null)", 1),
    "two documents": text("name: a\n---\nname: b\n", "expected a single document in the stream", 2),
    "a list as a key": text("? [a, b]\n: 1\n", "a key must be a plain name, not a list", 1),
    "a NUL byte": text("name: a\x00b\n", "control character #x0000 is not allowed", 1),
    "not UTF-8": raw(b"name: caf\xe9\n", "not UTF-8 text (byte 0xe9)", 1),
    "an integer of 5,000 digits": text("name: x\nseed: " + "9" * 5000 + "\n", "Exceeds the limit (4300 digits)", 2),
    "a date that does not exist": text("name: 2024-13-45\n", "month must be in 1..12", 1),
    f"more than {MAX_NODES:,} values": text(
        "a: [" + ",".join(["0"] * (MAX_NODES + 10)) + "]\n", f"more than {MAX_NODES:,} values"
    ),
    "larger than YAML_MAX_BYTES": text("#" * (YAML_MAX_BYTES + 1), f"a file may have at most {YAML_MAX_BYTES:,}"),
    "empty": text("", "file is empty"),
    "only comments": text("# nothing here\n\n", "file is empty"),
    "an unclosed bracket": text("name: [unclosed\n", "not valid YAML"),
    "tab indentation": text("a:\n\tb: 1\n", "not valid YAML", 2),
    "a directory": Hostile(_directory, "a directory, not a file"),
    "a FIFO": Hostile(_fifo, "a named pipe (FIFO), not a file"),
    "/dev/zero": Hostile(_zero, "a device, not a file"),
    "a symbolic link loop": Hostile(_loop, "a symbolic link loop"),
}


def _spec_edit(old: str, new: str) -> str:
    assert SPEC_TEXT.count(old) == 1, old
    return SPEC_TEXT.replace(old, new)


_INSTALLATION_LIMITS = "    limits: {torque_nm: 10.0, velocity_rad_s: 1.0}\n"


def _spec_line(content: str, needle: str) -> int:
    return content[: content.index(needle)].count("\n") + 1


_DUPLICATE_LIMITS = _spec_edit(
    "    mode: minimal_impedance\n" + _INSTALLATION_LIMITS,
    "    mode: minimal_impedance\n" + _INSTALLATION_LIMITS + "    limits: {torque_nm: 30.0, velocity_rad_s: 1.0}\n",
)
_TORQUE_TRUE = _spec_edit(
    "    mode: minimal_impedance\n" + _INSTALLATION_LIMITS,
    "    mode: minimal_impedance\n    limits: {torque_nm: true, velocity_rad_s: 1.0}\n",
)

#: Hostile for one loader: what a lax reader would have accepted in that file.
SPECIFIC: dict[str, dict[str, Hostile]] = {
    "spec": {
        "second limits raises the torque limit": text(
            _DUPLICATE_LIMITS,
            "field states.3.limits: key 'limits' is written twice",
            _spec_line(_DUPLICATE_LIMITS, "torque_nm: 30.0"),
        ),
        "torque_nm true": text(
            _TORQUE_TRUE,
            "field states.3.limits.torque_nm: Input should be a valid number; got true",
            _spec_line(_TORQUE_TRUE, "torque_nm: true"),
        ),
    },
    "settings": {
        "support_level true": text(
            "support_level: true\n", "field support_level: Input should be a valid number; got true", 1
        ),
        "support_level as text": text('support_level: "0.8"\n', "got the text '0.8'", 1),
        "isb_margin_deg .inf": text(
            "isb_margin_deg: .inf\n", "field isb_margin_deg: Input should be a finite number", 1
        ),
        "waypoint_stride 2.0": text(
            "identification:\n  waypoint_stride: 2.0\n",
            "field identification.waypoint_stride: Input should be a valid integer",
            2,
        ),
        "dummy_arm 1": text("dummy_arm: 1\n", "field dummy_arm: Input should be a valid boolean; got 1", 1),
        "support_level twice": text(
            "support_level: 0.5\nsupport_level: 1.0\n",
            "field support_level: key 'support_level' is written twice (first on line 1)",
            2,
        ),
        "model_kind not registered": text(
            "support_level: 0.8\nmodel_kind: gp\n",
            "field model_kind: unknown model kind 'gp'; expected one of ap, plf, plf+, augmented",
            2,
        ),
        "model_kind not trained in a session": text(
            "support_level: 0.8\nmodel_kind: penn\n",
            "field model_kind: model kind 'penn' cannot be trained in a session; expected one of ap, plf, plf+, augmented",
            2,
        ),
        "model_kind in capitals": text("model_kind: PLF+\n", "field model_kind: unknown model kind 'PLF+'", 1),
        "model_kind a number": text("model_kind: 5\n", "field model_kind: Input should be a valid string; got 5", 1),
    },
    "scenario": {
        "seed true": text("extends: exo\nname: x\nseed: true\n", "field seed: Input should be a valid integer", 3),
        "gravity as text": text(
            'extends: exo\nname: x\ngravity_mps2: "9.81"\n', "field gravity_mps2: Input should be a valid number", 3
        ),
        "tilt .inf": text("extends: exo\nname: x\nmounting_tilt_deg: [.inf, 0.0]\n", "finite number", 3),
        "quantise 1": text(
            "extends: exo\nname: x\nsensors: {quantise: 1}\n",
            "field sensors.quantise: Input should be a valid boolean",
            3,
        ),
        "name twice": text(
            "extends: exo\nname: x\nname: y\n", "field name: key 'name' is written twice (first on line 2)", 3
        ),
    },
    "isb": {
        "lower_deg true": text(
            "elevation: {lower_deg: true, upper_deg: 80}\n",
            "field elevation.lower_deg: Input should be a valid number; got true",
            1,
        ),
        "lower_deg as text": text('elbow: {lower_deg: "10", upper_deg: 100}\n', "got the text '10'", 1),
        "elbow twice": text(
            "elbow: {lower_deg: 10, upper_deg: 100}\nelbow: {lower_deg: 0, upper_deg: 150}\n",
            "field elbow: key 'elbow' is written twice (first on line 1)",
            2,
        ),
        "upper_deg twice in one mapping": text(
            "elevation: {lower_deg: 0, upper_deg: 80, upper_deg: 170}\n",
            "field elevation.upper_deg: key 'upper_deg' is written twice",
            1,
        ),
        "horizontal_free_below_deg .nan": text(
            "horizontal_free_below_deg: .nan\n", "field horizontal_free_below_deg: Input should be a finite number", 1
        ),
    },
}

LOADERS = ("spec", "settings", "scenario", "isb")
CASES = [(loader, name) for loader in LOADERS for name in GENERIC] + [
    (loader, name) for loader in LOADERS for name in SPECIFIC[loader]
]


def _hostile(loader: str, name: str) -> Hostile:
    return SPECIFIC[loader][name] if name in SPECIFIC[loader] else GENERIC[name]


def test_enough_distinct_hostile_inputs() -> None:
    distinct = len(GENERIC) + sum(len(v) for v in SPECIFIC.values())
    assert distinct >= 25
    assert all(SPECIFIC[loader] for loader in LOADERS)


# --- through the loaders ---------------------------------------------------------------------

ERRORS: dict[str, type[InputError]] = {
    "spec": FsmSpecError,
    "settings": SessionSettingsError,
    "scenario": DescriptionError,
    "isb": IsbLimitsError,
}


def _load(loader: str, path: Path) -> object:
    if loader == "spec":
        return load_fsm_spec(path)
    if loader == "settings":
        return load_session_settings(path)
    if loader == "scenario":
        return load_scenario(path)
    return load_isb_limits(path)


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    path = tmp_path / "in"
    path.mkdir()
    return path


def _snapshot(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


@pytest.mark.parametrize(("loader", "name"), CASES)
def test_the_loader_refuses(loader: str, name: str, folder: Path) -> None:
    hostile = _hostile(loader, name)
    path = hostile.make(folder, "hostile.yaml")
    before = _snapshot(folder)
    started = time.perf_counter()
    with pytest.raises(ERRORS[loader]) as info:
        _load(loader, path)
    assert time.perf_counter() - started < FAST_S
    message = str(info.value)
    assert isinstance(info.value, InputError)
    assert "\n" not in message, message
    assert message.startswith(f"{path}: "), message
    assert hostile.fragment in message, message
    if hostile.line is not None:
        assert message.startswith(f"{path}: line {hostile.line}"), message
    assert _snapshot(folder) == before


# --- through the commands --------------------------------------------------------------------


def _argv(loader: str, path: Path, tmp_path: Path) -> tuple[list[object], Path]:
    """The command that reads ``path`` with ``loader``, and the output it would create."""
    if loader == "spec":
        return ["fsm", "check", path], tmp_path / "nothing"
    if loader == "settings":
        script = tmp_path / "script.txt"
        script.write_text(SHORT_SCRIPT, encoding="utf-8")
        out = tmp_path / "session"
        return ["console", "--settings", path, "--script", script, "--out", out], out
    if loader == "scenario":
        out = tmp_path / "data.csv"
        return ["simulate", "static", "--scenario", path, "--trajectory", "validation", "--out", out], out
    out = tmp_path / "identified.csv"
    argv: list[object] = ["identify", "--scenario", "exo_dummy_arm", "--trajectory", "validation"]
    return [*argv, "--out", out, "--isb-limits", path], out


@pytest.mark.parametrize(("loader", "name"), CASES)
def test_the_command_refuses(
    loader: str, name: str, folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    hostile = _hostile(loader, name)
    path = hostile.make(folder, "hostile.yaml")
    argv, out = _argv(loader, path, tmp_path)
    before = _snapshot(tmp_path)
    capsys.readouterr()
    started = time.perf_counter()
    code = main([str(a) for a in argv])
    elapsed = time.perf_counter() - started
    captured = capsys.readouterr()
    assert code == 2, captured.err
    assert elapsed < FAST_S
    assert "Traceback" not in captured.err + captured.out
    command = " ".join(str(a) for a in argv[: 2 if argv[0] in ("fsm", "simulate") else 1])
    own = [x for x in captured.err.rstrip("\n").split("\n") if x.startswith(f"daror {command}: ")]
    assert len(own) == 1, captured.err
    assert own[0].startswith(f"daror {command}: error: {path}: "), own[0]
    assert hostile.fragment in own[0]
    assert not out.exists()
    assert _snapshot(tmp_path) == before  # nothing created


# --- what is still fine ---------------------------------------------------------------------


def test_an_int_where_a_float_is_meant_and_plain_files_still_load(folder: Path) -> None:
    settings = folder / "settings.yaml"
    settings.write_text("support_level: 1\nidentification:\n  waypoint_stride: 3\ndummy_arm: true\n", encoding="utf-8")
    loaded = load_session_settings(settings)
    assert (loaded.support_level, loaded.identification.waypoint_stride, loaded.dummy_arm) == (1.0, 3, True)
    limits = folder / "limits.yaml"
    limits.write_text(
        "elevation: {lower_deg: 0, upper_deg: 80}\nhorizontal_rotation: {lower_deg: 0, upper_deg: 90}\n"
        "axial_rotation: {lower_deg: -30, upper_deg: 30}\nelbow: {lower_deg: 10, upper_deg: 100}\n",
        encoding="utf-8",
    )
    assert load_isb_limits(limits).elevation.upper_deg == 80.0
    scenario = folder / "scenario.yaml"
    scenario.write_text("extends: exo\nname: x\nseed: 7\ngravity_mps2: 10\n", encoding="utf-8")
    assert (load_scenario(scenario).seed, load_scenario(scenario).gravity_mps2) == (7, 10.0)
    assert load_fsm_spec(DEFAULT_SPEC_PATH).version == 1


def test_a_large_plain_file_is_read_quickly(folder: Path) -> None:
    """Near the node bound and the size bound, a well-formed file is still read in well under FAST_S."""
    path = folder / "big.yaml"
    path.write_text("name: x\nbig: [" + ",".join(["1"] * (MAX_NODES - 10)) + "]\n", encoding="utf-8")
    assert path.stat().st_size < YAML_MAX_BYTES
    started = time.perf_counter()
    with pytest.raises(IsbLimitsError, match=r"big\.yaml: not a pilot's ISB limits file"):
        load_isb_limits(path)  # read in full, then refused by the schema (none of its fields)
    assert time.perf_counter() - started < FAST_S
