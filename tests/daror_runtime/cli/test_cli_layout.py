"""The layout of ``daror_runtime/cli/``, checked by what the parser does.

Every subcommand ``daror --help`` lists runs through a handler bound to its parser; that handler
is defined in the module that adds the subcommand and declares its flags (a command's flags sit
beside its handler); ``--hal`` offers exactly the registered HAL backends
(:func:`hal.interface.backend_kinds`), read when the parser is built; and ``daror --help`` imports
neither the HAL nor numpy (the flags that need them are declared when their command is used).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from daror_runtime.cli import build_parser
from daror_runtime.cli.common import CommandParser
from hal.interface import backend_kinds, register_backend, unregister_backend

ROOT = Path(__file__).resolve().parents[3]


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The subcommands ``parser``'s help lists, by name (none for a parser that runs a command)."""
    found: dict[str, argparse.ArgumentParser] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            found.update(action.choices)
    return found


def _commands(parser: argparse.ArgumentParser, prefix: str = "") -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """Every command ``daror`` runs (``fsm check``, ``demo``, ...) and its parser, through the groups."""
    for name, sub in _subcommands(parser).items():
        if _subcommands(sub):
            yield from _commands(sub, f"{prefix}{name} ")
        else:
            yield f"{prefix}{name}", sub


def _every_parser(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    yield parser
    for sub in _subcommands(parser).values():
        yield from _every_parser(sub)


def _declared(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """``parser`` with every flag declared, those declared for first use included (as parsing would)."""
    for each in _every_parser(parser):
        if isinstance(each, CommandParser):
            each.declare_now()
    return parser


def _caller_module() -> str:
    return str(sys._getframe(2).f_globals.get("__name__"))


@pytest.fixture
def recorded(monkeypatch: pytest.MonkeyPatch) -> dict[int, str]:
    """The module that called ``add_argument`` for each action, or ``add_parser`` for each parser (by id)."""
    where: dict[int, str] = {}
    add_argument = argparse._ActionsContainer.add_argument
    add_parser = argparse._SubParsersAction.add_parser

    def recording_add_argument(self: Any, *args: Any, **kwargs: Any) -> argparse.Action:
        action = add_argument(self, *args, **kwargs)
        where[id(action)] = _caller_module()
        return action

    def recording_add_parser(self: Any, *args: Any, **kwargs: Any) -> argparse.ArgumentParser:
        parser = add_parser(self, *args, **kwargs)
        where[id(parser)] = _caller_module()
        return parser

    monkeypatch.setattr(argparse._ActionsContainer, "add_argument", recording_add_argument)
    monkeypatch.setattr(argparse._SubParsersAction, "add_parser", recording_add_parser)
    return where


@pytest.fixture
def x_test_backend() -> Iterator[str]:
    """A backend ``x-test`` registered (never built: its module does not exist), unregistered after the test."""
    register_backend("x-test", "tests.never_imported_backend:Never", "tests.never_imported_backend:NeverConfig")
    yield "x-test"
    unregister_backend("x-test")


def test_every_subcommand_the_help_lists_has_a_handler_bound() -> None:
    parser = build_parser()
    listed = parser.format_help()
    top = _subcommands(parser)
    assert {"demo", "fit", "console", "hil", "rt-check", "can", "fsm"} <= set(top)
    for name in top:
        assert f"    {name} " in listed, name
    commands = dict(_commands(parser))
    for name, sub in commands.items():
        handler = sub.get_default("handler")
        assert callable(handler), f"daror {name}: no handler bound"
        assert sub.get_default("command_name") == name
    for name in ("simulate static", "study protocol", "protocol design", "fsm schema", "can tare"):
        assert name in commands


def test_each_handler_is_defined_where_its_command_and_its_flags_are_declared(recorded: dict[int, str]) -> None:
    parser = _declared(build_parser())
    checked = 0
    for name, sub in _commands(parser):
        handler: Callable[..., int] = sub.get_default("handler")
        module = handler.__module__
        assert module.startswith("daror_runtime.cli."), f"daror {name}: handler in {module}"
        assert recorded[id(sub)] == module, f"daror {name}: added in {recorded[id(sub)]}, handler in {module}"
        flags = {
            "/".join(action.option_strings) or action.dest: recorded[id(action)]
            for action in sub._actions
            if recorded.get(id(action), "argparse") != "argparse"  # argparse's own -h
        }
        elsewhere = {flag: where for flag, where in flags.items() if where != module}
        assert elsewhere == {}, f"daror {name}: flags declared outside {module}"
        checked += len(flags)
    assert checked > 100, f"{checked} flags recorded: the check would be vacuous"


def _hal_choices(parser: argparse.ArgumentParser) -> dict[str, tuple[str, ...]]:
    """``--hal``'s choices of every command that has the flag."""
    found = {}
    for name, sub in _commands(_declared(parser)):
        for action in sub._actions:
            if "--hal" in action.option_strings:
                found[name] = tuple(action.choices or ())
    return found


def test_hal_choices_are_the_registered_backends() -> None:
    choices = _hal_choices(build_parser())
    assert {"console", "rt-check"} <= set(choices)
    assert all(offered == backend_kinds() for offered in choices.values()), choices
    assert all("x-test" not in offered for offered in choices.values())


def test_a_backend_registered_is_offered_by_a_new_parser(x_test_backend: str) -> None:
    parser = build_parser()
    choices = _hal_choices(parser)
    assert all(offered == backend_kinds() for offered in choices.values()), choices
    assert all(x_test_backend in offered for offered in choices.values())
    assert parser.parse_args(["rt-check", "--hal", x_test_backend]).hal == x_test_backend
    console = _subcommands(parser)["console"]
    assert "{" + ",".join(backend_kinds()) + "}" in console.format_help()


def test_a_backend_no_longer_registered_is_no_longer_offered() -> None:
    register_backend("x-test", "tests.never_imported_backend:Never", "tests.never_imported_backend:NeverConfig")
    unregister_backend("x-test")
    parser = build_parser()
    with pytest.raises(SystemExit) as refused:
        parser.parse_args(["console", "--hal", "x-test"])
    assert refused.value.code == 2


@pytest.mark.subprocess
def test_daror_help_imports_neither_the_hal_nor_numpy() -> None:
    """The flags that need the HAL's registry are declared on use: ``daror --help`` stays fast."""
    code = (
        "import sys\n"
        "from daror_runtime.cli import main\n"
        "try:\n"
        "    main(['--help'])\n"
        "except SystemExit as exc:\n"
        "    assert exc.code == 0, exc.code\n"
        "heavy = [m for m in ('hal.interface', 'hal.capabilities', 'numpy') if m in sys.modules]\n"
        "assert not heavy, heavy\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=False)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "rt-check" in done.stdout
