"""Load a YAML file into a pydantic model, with errors that name the file, the field and the line.

Every file a person edits in this project (robot description, simulation scenarios, the FSM
spec, session settings, a pilot's ISB limits, waypoints) goes through :func:`read_yaml`, so a
typo is reported the same way everywhere::

    hal/daror01.yaml: line 12, field links.2.mass_kg: Input should be greater than 0

Reading is defensive, because a file a person hands in may be mistaken or hostile:

* only a regular file of at most :data:`~hal.files.YAML_MAX_BYTES` is read (:mod:`hal.files`:
  no directory, FIFO, device such as ``/dev/zero``, nothing huge);
* a key written twice in one mapping is refused naming both lines (PyYAML would let the later one
  win silently: a second ``limits:`` once raised a state's torque limit from 10 to 30 Nm);
* anchors and aliases (``&name``, ``*name``) are refused: nothing a person edits here needs them,
  and they are how a few hundred bytes expand to gigabytes ("billion laughs");
* explicit tags (``!!python/object:...``, ``!!binary``, ``!custom``) and merge keys (``<<``) are
  refused; the rest is read with PyYAML's safe constructor, so no YAML ever creates an object;
* nesting deeper than :data:`MAX_DEPTH` levels, or more than :data:`MAX_NODES` values, is refused
  while the document is composed, before PyYAML's recursive composer could exhaust the stack or the
  file could cost seconds (larger files are parsed by libyaml, when PyYAML has it);
* control characters, a value Python cannot convert (an int of 5,000 digits, 2024-13-45) and
  several documents in one file are refused, each as "not valid YAML" with the line;
* the top level must be a mapping.

The types :data:`Number`, :data:`Integer` and :data:`Flag` make the numbers and yes/no values of
these files strict: pydantic's lax mode would read ``torque_nm: true`` as 1 Nm and ``"30"`` as
30 Nm; with them a bool or a string where a number is meant is refused (an int where a float is
meant stays fine: ``torque_nm: 10``), and so are NaN and infinities.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, NoReturn, TypeVar

import yaml
from pydantic import AllowInfNan, BaseModel, Strict, ValidationError
from yaml.composer import Composer
from yaml.constructor import ConstructorError, SafeConstructor
from yaml.events import AliasEvent, CollectionStartEvent, MappingEndEvent, MappingStartEvent, NodeEvent
from yaml.nodes import MappingNode, ScalarNode, SequenceNode
from yaml.parser import Parser
from yaml.reader import Reader
from yaml.resolver import Resolver
from yaml.scanner import Scanner

from hal.errors import DescriptionError, InputError
from hal.files import YAML_MAX_BYTES, read_text_bounded

try:  # libyaml's parser, when PyYAML was built with it
    from yaml.cyaml import CParser
except ImportError:  # pragma: no cover - depends on the PyYAML build
    CParser = None

__all__ = [
    "MAX_DEPTH",
    "MAX_NODES",
    "Flag",
    "Integer",
    "Number",
    "format_validation_error",
    "line_of",
    "load_yaml_model",
    "read_yaml",
]

ModelT = TypeVar("ModelT", bound=BaseModel)

#: A real number in a file a person edits: an int or a float, finite; never a bool or a string.
Number = Annotated[float, Strict(), AllowInfNan(False)]
#: A whole number: an int; never a bool, a float or a string.
Integer = Annotated[int, Strict()]
#: A yes/no value: ``true`` or ``false``; never ``1`` or the text ``"true"``.
Flag = Annotated[bool, Strict()]

#: Deepest nesting of mappings and lists a file may have (the FSM spec needs 5).
MAX_DEPTH = 64
#: Most values (scalars, lists, mappings) a file may have: the shipped waypoints have about 900.
MAX_NODES = 100_000
#: Files up to this many characters are parsed by PyYAML's pure-Python parser (every file a person
#: writes is far smaller; its messages are the clearest); larger ones by libyaml's, so that even a
#: file of YAML_MAX_BYTES is read in well under a second.
_PYTHON_PARSER_MAX_CHARS = 32 << 10

#: A field path longer than this many parts is shortened in a message (deep nesting).
_MAX_FIELD_PARTS = 8

_MERGE_TAG = "tag:yaml.org,2002:merge"
_STANDARD_PREFIX = "tag:yaml.org,2002:"


class _Refused(yaml.YAMLError):
    """A YAML construct this project refuses, with where it is (line and field)."""

    def __init__(self, mark: yaml.Mark | None, location: tuple[int | str, ...], problem: str) -> None:
        super().__init__(problem)
        self.mark = mark
        self.location = location
        self.problem = problem


def _field(location: tuple[int | str, ...]) -> str:
    parts = [str(p) for p in location]
    if len(parts) > _MAX_FIELD_PARTS:
        half = _MAX_FIELD_PARTS // 2
        return f"{'.'.join(parts[:half])} ... {'.'.join(parts[-half:])}"
    return ".".join(parts)


def _shown_tag(tag: str) -> str:
    return "!!" + tag[len(_STANDARD_PREFIX) :] if tag.startswith(_STANDARD_PREFIX) else tag


class _DefensiveComposer(Composer, SafeConstructor, Resolver):
    """PyYAML's composer and safe constructor, composing defensively (see the module docstring).

    Works on the events of either parser (:class:`_PythonLoader`, :class:`_LibyamlLoader`). Tracks
    the field path, the depth and the number of the nodes composed so far, so that every refusal
    names the line and the field and happens before the work it prevents.
    """

    def _start_defensive(self) -> None:
        Composer.__init__(self)
        SafeConstructor.__init__(self)
        Resolver.__init__(self)
        self._location: list[int | str] = []
        self._depth = 0
        self._nodes = 0

    def _refuse(self, mark: yaml.Mark | None, problem: str, extra: tuple[int | str, ...] = ()) -> NoReturn:
        raise _Refused(mark, (*self._location, *extra), problem)

    def get_single_node(self) -> yaml.Node | None:
        """The document's root node (composed here, also over libyaml's events), or None for an empty file."""
        return Composer.get_single_node(self)

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node:
        if isinstance(parent, MappingNode) and isinstance(index, ScalarNode):
            step: list[int | str] = [index.value]
        elif isinstance(parent, SequenceNode) and isinstance(index, int):
            step = [index]
        else:
            step = []  # the document's root, or a mapping's key
        self._location.extend(step)
        event = self.peek_event()
        if isinstance(event, AliasEvent):
            self._refuse(
                event.start_mark,
                f"YAML aliases (*{event.anchor}) are not allowed; write the value out in full",
            )
        if isinstance(event, NodeEvent) and event.anchor is not None:
            self._refuse(
                event.start_mark,
                f"YAML anchors (&{event.anchor}) are not allowed; write every value out in full",
            )
        tag = getattr(event, "tag", None)
        if tag is not None and tag != "!":
            self._refuse(
                event.start_mark,
                f"YAML tag {_shown_tag(tag)!r} is not allowed; write a plain value (a number, text, true/false, "
                "a list or a mapping)",
            )
        self._nodes += 1
        if self._nodes > MAX_NODES:
            self._refuse(
                event.start_mark, f"more than {MAX_NODES:,} values; expected a file a person writes (a few thousand)"
            )
        collection = isinstance(event, CollectionStartEvent)
        if collection:
            if self._depth >= MAX_DEPTH:
                self._refuse(event.start_mark, f"nested more than {MAX_DEPTH} levels deep; expected a shallow file")
            self._depth += 1
        node: yaml.Node = Composer.compose_node(self, parent, index)
        if collection:
            self._depth -= 1
        del self._location[len(self._location) - len(step) :]
        return node

    def compose_mapping_node(self, anchor: str | None) -> MappingNode:
        """PyYAML's, refusing a key written twice, merge keys (``<<``) and keys that are not plain values."""
        start_event: MappingStartEvent = self.get_event()
        tag = start_event.tag
        if tag is None or tag == "!":
            tag = self.resolve(MappingNode, None, start_event.implicit)
        node = MappingNode(tag, [], start_event.start_mark, None, flow_style=start_event.flow_style)
        seen: dict[tuple[str, str], ScalarNode] = {}
        while not self.check_event(MappingEndEvent):
            key = self.compose_node(node, None)
            if not isinstance(key, ScalarNode):
                kind = "a list" if isinstance(key, SequenceNode) else "a mapping"
                self._refuse(key.start_mark, f"a key must be a plain name, not {kind}")
            if key.tag == _MERGE_TAG:
                self._refuse(key.start_mark, "merge keys (<<) are not allowed; write every key out in full")
            identity = (key.tag, key.value)
            if identity in seen:
                first = seen[identity].start_mark.line + 1
                self._refuse(
                    key.start_mark,
                    f"key {key.value!r} is written twice (first on line {first}); each key may appear only once",
                    (key.value,),
                )
            seen[identity] = key
            value = self.compose_node(node, key)
            node.value.append((key, value))
        end_event = self.get_event()
        node.end_mark = end_event.end_mark
        return node

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:
        """PyYAML's, turning a scalar Python cannot convert (an int of 5,000 digits, 2024-13-45) into a YAML error."""
        try:
            return SafeConstructor.construct_object(self, node, deep)
        except (ValueError, OverflowError) as exc:
            value = str(node.value)
            shown = value if len(value) <= 24 else value[:21] + "..."
            reason = str(exc).split(":")[0]  # Python's first clause; the rest repeats the value
            raise ConstructorError(None, None, f"cannot read the value {shown!r}: {reason}", node.start_mark) from None


class _PythonLoader(Reader, Scanner, Parser, _DefensiveComposer):
    """PyYAML's pure-Python parser under the defensive composer (the clearest syntax messages)."""

    def __init__(self, stream: str) -> None:
        Reader.__init__(self, stream)
        Scanner.__init__(self)
        Parser.__init__(self)
        self._start_defensive()


if CParser is not None:

    class _LibyamlLoader(_DefensiveComposer, CParser):
        """libyaml's parser (C, 10-20 times faster) under the defensive composer, for larger files."""

        def __init__(self, stream: str) -> None:
            CParser.__init__(self, stream)
            self._start_defensive()


def _loader(text: str) -> _DefensiveComposer:
    """The loader for ``text``: pure Python up to :data:`_PYTHON_PARSER_MAX_CHARS`, libyaml above (when built)."""
    if CParser is None or len(text) <= _PYTHON_PARSER_MAX_CHARS:
        return _PythonLoader(text)
    return _LibyamlLoader(text)


def line_of(root: yaml.Node | None, location: tuple[int | str, ...]) -> int | None:
    """1-based line of the YAML node at ``location`` (the deepest existing prefix), or None."""
    node = root
    line = None if node is None else node.start_mark.line + 1
    for key in location:
        if isinstance(node, yaml.MappingNode):
            match = next((v for k, v in node.value if getattr(k, "value", None) == str(key)), None)
            if match is None:
                break
            node = match
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            node = node.value[key]
        else:
            break
        line = node.start_mark.line + 1
    return line


def _describe(value: object) -> str:
    """How a wrong input reads in a message: ``true (a yes/no value)``, ``the text '30'``, ..."""
    if isinstance(value, bool):
        return f"{str(value).lower()} (a yes/no value)"
    if isinstance(value, str):
        shown = value if len(value) <= 40 else value[:37] + "..."
        return f"the text {shown!r}"
    if value is None:
        return "nothing (null)"
    if isinstance(value, list):
        return "a list"
    if isinstance(value, dict):
        return "a mapping"
    if isinstance(value, float | int):
        return repr(value)  # 1.0 stays 1.0: a float where a whole number is meant
    return f"a {type(value).__name__}"


#: pydantic error types where naming what was found helps ("a valid number; got true (a yes/no value)").
_TYPE_ERRORS = frozenset(
    {
        "float_type",
        "int_type",
        "bool_type",
        "string_type",
        "finite_number",
        "int_from_float",
        "literal_error",
        "list_type",
        "tuple_type",
        "dict_type",
        "model_type",
    }
)


def format_validation_error(
    source: str, err: ValidationError, root: yaml.Node | None = None, separator: str = "; "
) -> str:
    """One entry per problem, ``source: line L, field a.b.c: message``, joined by ``separator``.

    A type error also says what was found (``Input should be a valid number; got true (a yes/no value)``).
    """
    lines = []
    for problem in err.errors():
        loc = tuple(problem["loc"])
        message = problem["msg"]
        if loc and loc[-1] == "[key]":  # pydantic's marker of a mapping key that is not allowed: name the key itself
            loc = loc[:-1]
            message = f"unknown key; {message[0].lower()}{message[1:]}"
        field = ".".join(str(p) for p in loc) or "(top level)"
        line = line_of(root, loc)
        where = f"line {line}, " if line is not None else ""
        if problem["type"] in _TYPE_ERRORS and "input" in problem:
            message = f"{message}; got {_describe(problem['input'])}"
        lines.append(f"{source}: {where}field {field}: {message}")
    return separator.join(lines)


def _kind_of(data: object) -> str:
    if data is None:
        return "nothing (null)"
    if isinstance(data, list):
        return "a list"
    if isinstance(data, str):
        return "a single text value"
    if isinstance(data, bool):
        return "a single yes/no value"
    if isinstance(data, int | float):
        return "a single number"
    return f"a {type(data).__name__}"


def _refusal_message(path: Path, exc: _Refused) -> str:
    parts = []
    if exc.mark is not None:
        parts.append(f"line {exc.mark.line + 1}")
    if exc.location:
        parts.append(f"field {_field(exc.location)}")
    return f"{path}: {', '.join(parts)}: {exc.problem}" if parts else f"{path}: {exc.problem}"


def read_yaml(
    path: Path | str,
    error: type[InputError] = DescriptionError,
    expected: str = "a YAML mapping (key: value lines)",
) -> tuple[dict[str, Any], yaml.Node]:
    """Read ``path`` (see the module docstring for what is refused) and return ``(data, node tree)``.

    ``data`` is the top-level mapping; the node tree gives the lines (:func:`line_of`).
    ``expected`` is what a top level that is not a mapping is told it should be.

    Raises:
        error: the file is missing, not a regular file, too large, not UTF-8, not YAML, empty, uses
            something refused here, or is not a mapping; one line naming the file (and the line and
            field where there is one).
    """
    path = Path(path)
    text = read_text_bounded(path, error, YAML_MAX_BYTES, "file")
    bad = Reader.NON_PRINTABLE.search(text)
    if bad is not None:
        line = text.count("\n", 0, bad.start()) + 1
        raise error(f"{path}: line {line}: not valid YAML (control character #x{ord(bad.group()):04x} is not allowed)")
    loader: _DefensiveComposer | None = None
    try:
        loader = _loader(text)
        root = loader.get_single_node()
        data = None if root is None else loader.construct_document(root)
    except _Refused as exc:
        raise error(_refusal_message(path, exc)) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        context, problem = exc.context, exc.problem
        if context and problem and context != problem:
            problem = f"{context}, {problem}"  # "while scanning a simple key, could not find expected ':'"
        problem = " ".join(str(problem or context or exc).split())
        if "maximum nesting depth" in problem:
            # PyYAML >= 6.0.4 bounds nesting in its own scanner, which may look ahead of our composer's
            # depth bound: the same refusal, in the same words, whichever of the two finds it first.
            raise error(f"{path}: {where}nested more than {MAX_DEPTH} levels deep; expected a shallow file") from None
        raise error(f"{path}: {where}not valid YAML ({problem})") from None
    except yaml.YAMLError as exc:
        raise error(f"{path}: not valid YAML ({' '.join(str(exc).split())})") from None
    except RecursionError:  # a safety net: the depth bound above stops far earlier
        raise error(f"{path}: nested too deeply; expected a shallow file") from None
    finally:
        if loader is not None:
            loader.dispose()
    if root is None:
        raise error(f"{path}: file is empty; expected a YAML mapping")
    if not isinstance(data, dict):
        raise error(f"{path}: line {root.start_mark.line + 1}: expected {expected}; found {_kind_of(data)}")
    return data, root


def load_yaml_model(path: Path | str, model: type[ModelT], error: type[InputError] = DescriptionError) -> ModelT:
    """Read ``path`` (:func:`read_yaml`) and validate it as ``model``.

    Raises:
        error: with file, line and field named, when the file cannot be read or does not match.
    """
    path = Path(path)
    data, root = read_yaml(path, error)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise error(format_validation_error(str(path), exc, root)) from None
