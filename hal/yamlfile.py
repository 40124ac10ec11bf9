"""Load a YAML file into a pydantic model, with errors that name the file, the field and the line.

Every file a person edits in this project (robot description, simulation scenarios, the FSM
spec) goes through :func:`load_yaml_model`, so a typo is reported the same way everywhere::

    hal/daror01.yaml: line 12, field links.2.mass_kg: Input should be greater than 0
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from hal.errors import DescriptionError, InputError

ModelT = TypeVar("ModelT", bound=BaseModel)


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


def format_validation_error(
    source: str, err: ValidationError, root: yaml.Node | None = None, separator: str = "; "
) -> str:
    """One entry per problem, ``source: line L, field a.b.c: message``, joined by ``separator``."""
    lines = []
    for problem in err.errors():
        loc = tuple(problem["loc"])
        field = ".".join(str(p) for p in loc) or "(top level)"
        line = line_of(root, loc)
        where = f"line {line}, " if line is not None else ""
        lines.append(f"{source}: {where}field {field}: {problem['msg']}")
    return separator.join(lines)


def read_yaml(path: Path, error: type[InputError] = DescriptionError) -> tuple[Any, yaml.Node | None]:
    """Parse ``path`` and return ``(data, node tree)``.

    Raises:
        error: the file is missing, unreadable, not YAML, or empty.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{path}: file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{path}: cannot read file ({exc})") from None
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise error(f"{path}: {where}not valid YAML ({problem})") from None
    if data is None:
        raise error(f"{path}: file is empty; expected a YAML mapping")
    return data, root


def load_yaml_model(path: Path | str, model: type[ModelT], error: type[InputError] = DescriptionError) -> ModelT:
    """Read ``path`` and validate it as ``model``.

    Raises:
        error: with file, line and field named, when the file cannot be read or does not match.
    """
    path = Path(path)
    data, root = read_yaml(path, error)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise error(format_validation_error(str(path), exc, root)) from None
