"""Issue 10: hostile inputs and output paths across every command, one table.

For each case, the real command line (``daror_runtime.cli.main``) must end with exit code 2 and
exactly one line on stderr that names the path and the problem; create nothing; change no file that
was there; print no traceback; and finish within 10 s (no hang: a FIFO is never opened, a device is
never read). The files each case needs are made in a fresh folder.

The loaders' own tables (tests/daror_runtime/data/test_data_hostile.py, tests/hal/test_yaml_hostile.py,
tests/daror_runtime/models/test_model_files_hostile.py) cover what is inside a file; this one covers where the files are
and which command meets them.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from daror_runtime.cli import main
from daror_runtime.logs import configure_logging
from daror_runtime.util.outputs import output_lock
from hal.capabilities import PLANT_FAULT_KINDS

ROOT = Path(__file__).resolve().parents[3]
SPEC = ROOT / "fsm_spec.yaml"


@dataclass(frozen=True)
class Files:
    """What a case's folder holds before the command runs."""

    folder: Path
    train: Path  # a valid stationary dataset
    validation: Path
    model: Path  # a valid model file
    script: Path  # a valid console script
    fifo: Path
    directory: Path
    loop: Path  # a symlink loop
    a_file: Path  # a plain file (where a folder is expected)


@pytest.fixture(scope="module")
def originals(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """A valid dataset pair and model, made once (the cases copy them)."""
    folder = tmp_path_factory.mktemp("originals")
    configure_logging("critical")
    for trajectory in ("training", "validation"):
        assert main(["simulate", "static", "--scenario", "exo", "--trajectory", trajectory,
                     "--out", str(folder / f"{trajectory}.csv")]) == 0  # fmt: skip
    assert main(["fit", "plf+", "--train", str(folder / "training.csv"), "--out", str(folder / "model.json")]) == 0
    configure_logging()
    return {name: (folder / name).read_bytes() for name in ("training.csv", "validation.csv", "model.json")}


@pytest.fixture
def files(tmp_path: Path, originals: dict[str, bytes]) -> Files:
    folder = tmp_path / "case"
    folder.mkdir()
    made = Files(
        folder,
        folder / "train.csv",
        folder / "val.csv",
        folder / "model.json",
        folder / "session.txt",
        folder / "pipe.csv",
        folder / "adir",
        folder / "loop.csv",
        folder / "plain",
    )
    made.train.write_bytes(originals["training.csv"])
    made.validation.write_bytes(originals["validation.csv"])
    made.model.write_bytes(originals["model.json"])
    made.script.write_text("wait 0.1\nadvance\n", encoding="utf-8")
    os.mkfifo(made.fifo)
    made.directory.mkdir()
    os.symlink(made.loop.with_suffix(".other"), made.loop)
    os.symlink(made.loop, made.loop.with_suffix(".other"))
    made.a_file.write_text("not a folder\n", encoding="utf-8")
    return made


def _snapshot(folder: Path) -> dict[str, bytes | None]:
    state: dict[str, bytes | None] = {}
    for path in sorted(folder.rglob("*")):
        if path.is_symlink() or path.is_fifo() or path.is_dir():
            state[str(path)] = None
        else:
            state[str(path)] = path.read_bytes()
    return state


#: A case: a name, the argv built from the case's files, and what the one line must contain.
Case = tuple[str, Callable[[Files], list[str]], Callable[[Files], str]]

DEV_ZERO = "/dev/zero"


def _data_inputs() -> list[Case]:
    """Where a dataset is read: fit --train, evaluate --data, residual --train/--validate, study --train."""
    commands: list[tuple[str, Callable[[Files, str], list[str]]]] = [
        ("fit", lambda f, bad: ["fit", "plf+", "--train", bad, "--out", str(f.folder / "m.json")]),
        ("evaluate", lambda f, bad: ["evaluate", str(f.model), "--data", bad]),
        (
            "residual train",
            lambda f, bad: ["residual", "--train", bad, "--validate", str(f.validation), "--out", str(f.folder / "r")],
        ),
        (
            "residual validate",
            lambda f, bad: ["residual", "--train", str(f.train), "--validate", bad, "--out", str(f.folder / "r")],
        ),
        (
            "study",
            lambda f, bad: [
                "study",
                "data-efficiency",
                "--train",
                bad,
                "--validate",
                str(f.validation),
                "--out",
                str(f.folder / "s"),
            ],
        ),
    ]
    places: list[tuple[str, Callable[[Files], str], str]] = [
        ("missing", lambda f: str(f.folder / "nothing.csv"), "not found"),
        ("directory", lambda f: str(f.directory), "a directory"),
        ("fifo", lambda f: str(f.fifo), "a named pipe (FIFO)"),
        ("device", lambda f: DEV_ZERO, "a device"),
        ("symlink loop", lambda f: str(f.loop), "a symbolic link loop"),
    ]
    cases: list[Case] = []
    for command, argv in commands:
        for place, path, words in places:
            cases.append(
                (
                    f"{command} <- {place}",
                    lambda f, argv=argv, path=path: argv(f, path(f)),
                    lambda f, path=path, words=words: f"{path(f)}: {words}" if words != "not found" else path(f),
                )
            )
    return cases


def _model_inputs() -> list[Case]:
    commands: list[tuple[str, Callable[[Files, str], list[str]]]] = [
        ("evaluate model", lambda f, bad: ["evaluate", bad, "--data", str(f.validation)]),
        ("cvf model", lambda f, bad: ["cvf", bad]),
        (
            "identify feed-forward",
            lambda f, bad: [
                "identify",
                "--scenario",
                "exo",
                "--trajectory",
                "validation",
                "--feedforward",
                bad,
                "--out",
                str(f.folder / "i.csv"),
            ],
        ),
    ]
    places: list[tuple[str, Callable[[Files], str], str]] = [
        ("missing", lambda f: str(f.folder / "nothing.json"), "not found"),
        ("directory", lambda f: str(f.directory), "a directory"),
        ("fifo", lambda f: str(f.fifo), "a named pipe (FIFO)"),
        ("device", lambda f: DEV_ZERO, "a device"),
        ("symlink loop", lambda f: str(f.loop), "a symbolic link loop"),
    ]
    return [
        (
            f"{command} <- {place}",
            lambda f, argv=argv, path=path: argv(f, path(f)),
            lambda f, path=path, words=words: f"{path(f)}: {words}" if words != "not found" else path(f),
        )
        for command, argv in commands
        for place, path, words in places
    ]


def _yaml_inputs() -> list[Case]:
    """Where a YAML or text file is read: fsm check, console --spec/--settings/--script/--hal-config, identify --isb-limits/--waypoints/--scenario/--settings."""
    commands: list[tuple[str, Callable[[Files, str], list[str]]]] = [
        ("fsm check", lambda f, bad: ["fsm", "check", bad]),
        (
            "console spec",
            lambda f, bad: ["console", "--spec", bad, "--script", str(f.script), "--out", str(f.folder / "c")],
        ),
        (
            "console settings",
            lambda f, bad: ["console", "--settings", bad, "--script", str(f.script), "--out", str(f.folder / "c")],
        ),
        ("console script", lambda f, bad: ["console", "--script", bad, "--out", str(f.folder / "c")]),
        (
            "console hal config",
            lambda f, bad: ["console", "--hal-config", bad, "--script", str(f.script), "--out", str(f.folder / "c")],
        ),
        (
            "identify settings",
            lambda f, bad: [
                "identify",
                "--scenario",
                "exo",
                "--trajectory",
                "validation",
                "--settings",
                bad,
                "--out",
                str(f.folder / "i.csv"),
            ],
        ),
        (
            "identify isb limits",
            lambda f, bad: [
                "identify",
                "--scenario",
                "exo",
                "--trajectory",
                "validation",
                "--isb-limits",
                bad,
                "--out",
                str(f.folder / "i.csv"),
            ],
        ),
        (
            "identify waypoints",
            lambda f, bad: [
                "identify",
                "--scenario",
                "exo",
                "--trajectory",
                "validation",
                "--waypoints",
                bad,
                "--out",
                str(f.folder / "i.csv"),
            ],
        ),
        (
            "identify scenario",
            lambda f, bad: [
                "identify",
                "--scenario",
                bad,
                "--trajectory",
                "validation",
                "--out",
                str(f.folder / "i.csv"),
            ],
        ),
    ]
    places: list[tuple[str, Callable[[Files], str], str]] = [
        ("directory", lambda f: str(f.directory), "a directory"),
        ("fifo", lambda f: str(f.fifo), "a named pipe (FIFO)"),
        ("device", lambda f: DEV_ZERO, "a device"),
        ("symlink loop", lambda f: str(f.loop), "a symbolic link loop"),
    ]
    return [
        (
            f"{command} <- {place}",
            lambda f, argv=argv, path=path: argv(f, path(f)),
            lambda f, path=path, words=words: f"{path(f)}: {words}",
        )
        for command, argv in commands
        for place, path, words in places
    ]


def _output_paths() -> list[Case]:
    """Every output a command writes, named badly."""
    file_outputs: list[tuple[str, Callable[[Files, str], list[str]]]] = [
        (
            "simulate --out",
            lambda f, out: ["simulate", "static", "--scenario", "exo", "--trajectory", "validation", "--out", out],
        ),
        (
            "identify --out",
            lambda f, out: ["identify", "--scenario", "exo", "--trajectory", "validation", "--out", out],
        ),
        ("fit --out", lambda f, out: ["fit", "plf+", "--train", str(f.train), "--out", out]),
        ("evaluate --json", lambda f, out: ["evaluate", str(f.model), "--data", str(f.validation), "--json", out]),
        ("cvf --json", lambda f, out: ["cvf", str(f.model), "--json", out]),
        ("fsm diagram --out", lambda f, out: ["fsm", "diagram", "--out", out]),
        ("fsm schema --out", lambda f, out: ["fsm", "schema", "--out", out]),
        ("bench --json", lambda f, out: ["bench", "--only", "nothing-matches", "--json", out]),
    ]
    folder_outputs: list[tuple[str, Callable[[Files, str], list[str]]]] = [
        (
            "residual --out",
            lambda f, out: ["residual", "--train", str(f.train), "--validate", str(f.validation), "--out", out],
        ),
        (
            "study --out",
            lambda f, out: [
                "study",
                "data-efficiency",
                "--train",
                str(f.train),
                "--validate",
                str(f.validation),
                "--out",
                out,
            ],
        ),
        ("console --out", lambda f, out: ["console", "--script", str(f.script), "--out", out]),
        ("demo --out", lambda f, out: ["demo", "--out", out]),
    ]
    cases: list[Case] = []
    file_places: list[tuple[str, Callable[[Files], str], str]] = [
        ("an existing directory", lambda f: str(f.directory), "is a directory; expected a path to a file"),
        ("under a missing folder", lambda f: str(f.folder / "missing" / "x.out"), "does not exist; create it first"),
        ("under a file", lambda f: str(f.a_file / "x.out"), "is a file, not a folder"),
        ("a FIFO", lambda f: str(f.fifo), "exists and is not a regular file"),
        ("a symlink loop", lambda f: str(f.loop), "a symbolic link loop"),
    ]
    for command, argv in file_outputs:
        for place, path, words in file_places:
            cases.append(
                (
                    f"{command} -> {place}",
                    lambda f, argv=argv, path=path: argv(f, path(f)),
                    lambda f, path=path, words=words: words,
                )
            )
    folder_places: list[tuple[str, Callable[[Files], str], str]] = [
        ("an existing file", lambda f: str(f.a_file), "is a file; expected a folder"),
        ("under a missing folder", lambda f: str(f.folder / "missing" / "out"), "does not exist; create it first"),
        ("under a file", lambda f: str(f.a_file / "out"), "is a file, not a folder"),
    ]
    for command, argv in folder_outputs:
        for place, path, words in folder_places:
            cases.append(
                (
                    f"{command} -> {place}",
                    lambda f, argv=argv, path=path: argv(f, path(f)),
                    lambda f, path=path, words=words: words,
                )
            )
    cases.append(
        (
            "fit --out -> its own training file",
            lambda f: ["fit", "plf+", "--train", str(f.train), "--out", str(f.train)],
            lambda f: "refusing to overwrite an input file",
        )
    )
    cases.append(
        (
            "evaluate --json -> the model it reads",
            lambda f: ["evaluate", str(f.model), "--data", str(f.validation), "--json", str(f.model)],
            lambda f: "refusing to overwrite an input file",
        )
    )
    return cases


CASES = _data_inputs() + _model_inputs() + _yaml_inputs() + _output_paths()


def test_the_table_has_a_hundred_distinct_cases() -> None:
    names = [name for name, _, _ in CASES]
    assert len(names) == len(set(names))
    assert len(names) >= 100, len(names)


@pytest.mark.parametrize(("name", "argv", "expected"), CASES, ids=[name for name, _, _ in CASES])
def test_a_hostile_input_or_output_gets_exit_2_and_one_line(
    name: str,
    argv: Callable[[Files], list[str]],
    expected: Callable[[Files], str],
    files: Files,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.chdir(files.folder)
    before = _snapshot(files.folder)
    capsys.readouterr()
    start = time.perf_counter()
    code = main(argv(files))
    elapsed = time.perf_counter() - start
    captured = capsys.readouterr()
    configure_logging()
    assert code == 2, (name, captured.err)
    lines = captured.err.rstrip("\n").split("\n")
    assert len(lines) == 1, f"{name}: not one line: {captured.err!r}"
    assert expected(files) in lines[0], (name, lines[0])
    assert "Traceback" not in captured.out + captured.err
    assert _snapshot(files.folder) == before, f"{name}: something was created or changed"
    assert elapsed < 10.0, f"{name}: {elapsed:.1f} s"


def test_a_second_identify_on_the_same_output_is_refused_and_deletes_nothing(
    files: Files, capsys: pytest.CaptureFixture[str]
) -> None:
    """The first run holds the output (here: a lock held the way a running identify holds it)."""
    out = files.folder / "B.csv"
    crashed = files.folder / ".B.csv.4242-crashed.rec"  # a recording an earlier run left behind
    crashed.write_bytes(b"rows of an earlier run")
    with output_lock(out):
        before = _snapshot(files.folder)
        capsys.readouterr()
        code = main(["identify", "--scenario", "exo", "--trajectory", "validation", "--out", str(out)])
        captured = capsys.readouterr()
        configure_logging()
        assert code == 2
        assert captured.err.strip() == (
            f"daror identify: error: {out}: another daror process (pid {os.getpid()}) is writing it; "
            "wait for it to finish or choose another output"
        )
        assert _snapshot(files.folder) == before
    assert crashed.read_bytes() == b"rows of an earlier run"


# --- the console: the same files named in a session ------------------------------------------------------

CONSOLE_PLACES: list[tuple[str, Callable[[Files], str], str]] = [
    ("missing", lambda f: str(f.folder / "nothing"), "not found"),
    ("directory", lambda f: str(f.directory), "a directory"),
    ("fifo", lambda f: str(f.fifo), "a named pipe (FIFO)"),
    ("device", lambda f: DEV_ZERO, "a device"),
    ("symlink loop", lambda f: str(f.loop), "a symbolic link loop"),
]
CONSOLE_LINES: list[tuple[str, Callable[[Files, str], str]]] = [
    ("rom load", lambda f, bad: f"rom load {bad}"),
    ("model", lambda f, bad: f"model {bad}"),
    ("model validation", lambda f, bad: f"model {f.model} {bad}"),
]
CONSOLE_CASES = [
    (f"console {line} <- {place}", text, path, words)
    for line, text in CONSOLE_LINES
    for place, path, words in CONSOLE_PLACES
]


@pytest.mark.parametrize(("name", "text", "path", "words"), CONSOLE_CASES, ids=[c[0] for c in CONSOLE_CASES])
def test_a_hostile_file_named_in_the_console_is_refused_in_one_line(
    name: str,
    text: Callable[[Files, str], str],
    path: Callable[[Files], str],
    words: str,
    files: Files,
) -> None:
    from daror_runtime.console.commands import parse_context
    from daror_runtime.console.grammar import CommandError, parse_line
    from daror_runtime.fsm.spec import load_fsm_spec
    from hal.robot import load_description

    context = parse_context(load_fsm_spec(), load_description(), PLANT_FAULT_KINDS)
    before = _snapshot(files.folder)
    start = time.perf_counter()
    with pytest.raises(CommandError) as refused:
        parse_line(text(files, path(files)), context)
    message = str(refused.value)
    assert "\n" not in message
    assert path(files) in message
    assert words in message
    assert _snapshot(files.folder) == before
    assert time.perf_counter() - start < 10.0
