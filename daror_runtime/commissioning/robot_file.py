"""Each node's ``calibration:`` in the robot file, written without losing the operator's comments and layout.

The robot file (``backend: can`` with ``nodes:``, docs/canopen.md) is a file a person wrote and
comments. ``daror can zero`` and ``daror can tare`` change one thing in it: the ``calibration:``
mapping of each node they measured (:mod:`hal.canopen.calibration`), merged with what it held (a
tare keeps the zeros and their date, and the other way round). The update is textual: the YAML
parser's marks say where each node's mapping and its ``calibration:`` are; that block alone is
replaced, or inserted after the node's last line, at the node's indentation. Everything else of
the file stays byte for byte, comments included (those inside a replaced ``calibration:`` block
excepted: it is written by the command).

The new text is checked before it replaces the file: parsed again, every value but the
calibrations must be what it was and the calibrations what was measured, and the file must still
load where it loaded before (``verify``). Then the previous file is kept beside it
(``robot.yaml.20261128T093000Z.bak``, never overwritten) and the new one renamed into place (a
crash leaves the old file or the new one, never half of one).
"""

from __future__ import annotations

import copy
import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from daror_runtime.util.atomic import OutputWriteError, atomic_path
from hal.errors import HalConfigError
from hal.files import YAML_MAX_BYTES, read_text_bounded
from hal.yamlfile import read_yaml

__all__ = ["CALIBRATION_KEYS", "check_storable", "read_calibrations", "store_calibrations"]

#: The keys of a node's ``calibration:``, in the order they are written.
CALIBRATION_KEYS = ("motor_zero_counts", "link_zero_counts", "zeroed_utc", "torque_tare_nm", "tared_utc")
#: A value written as YAML text needs no quotes when it is a plain number.
_NUMBER = re.compile(r"^-?\d+(\.\d+)?$")


def read_calibrations(path: Path | str) -> dict[int, dict[str, Any]]:
    """Node id -> the ``calibration:`` mapping the robot file holds for it (empty for a node without one).

    Raises:
        HalConfigError: the file cannot be read, or holds no ``nodes:`` list of mappings with a ``node_id``.
    """
    path = Path(path)
    data, root = read_yaml(path, HalConfigError, "a robot file (a YAML mapping with backend: and nodes:)")
    return {node_id: dict(calibration) for node_id, (_, calibration) in _nodes(path, data, root).items()}


def _nodes(path: Path, data: dict[str, Any], root: yaml.Node) -> dict[int, tuple[yaml.MappingNode, dict[str, Any]]]:
    """Node id -> (its mapping node, its calibration mapping)."""
    if "nodes" not in data:
        raise HalConfigError(
            f"{path}: no nodes: list; calibration is stored per node of a robot file (docs/canopen.md, Robot file): "
            "expected the form with nodes:"
        )
    nodes_node = next(value for key, value in root.value if key.value == "nodes")
    if not isinstance(nodes_node, yaml.SequenceNode) or not isinstance(data["nodes"], list):
        raise HalConfigError(f"{path}: line {nodes_node.start_mark.line + 1}, field nodes: expected a list of nodes")
    found: dict[int, tuple[yaml.MappingNode, dict[str, Any]]] = {}
    for i, (item, value) in enumerate(zip(nodes_node.value, data["nodes"], strict=True)):
        where = f"{path}: line {item.start_mark.line + 1}, field nodes.{i}"
        if not isinstance(item, yaml.MappingNode) or not isinstance(value, dict):
            raise HalConfigError(f"{where}: expected a mapping (joint:, node_id:, ...)")
        node_id = value.get("node_id")
        if not isinstance(node_id, int) or isinstance(node_id, bool):
            raise HalConfigError(f"{where}.node_id: expected the node's id, a whole number")
        calibration = value.get("calibration") or {}
        if not isinstance(calibration, dict):
            raise HalConfigError(f"{where}.calibration: expected a mapping ({', '.join(CALIBRATION_KEYS)})")
        found[node_id] = (item, calibration)
    return found


def store_calibrations(
    path: Path | str,
    updates: dict[int, dict[str, Any]],
    verify: Callable[[Path], object] | None = None,
    stamp: str = "",
) -> Path:
    """Merge ``updates`` (node id -> calibration keys) into the robot file's nodes; the backup of the previous file.

    Args:
        path: the robot file.
        updates: per node id, the keys of :data:`CALIBRATION_KEYS` to set (the others are kept).
        verify: called with the new file (under a temporary name beside it) before it replaces the
            old one; it raises to refuse it (``hal.config.load_hal_config``).
        stamp: the backup's time stamp (``20261128T093000Z``).

    Raises:
        HalConfigError: the file has no such node, a node is a flow mapping (``{...}``) the
            calibration cannot be added to, the new text would not parse to the same file, or
            ``verify`` refused it; nothing was written.
        OutputWriteError: the folder is not writable; nothing was written.
    """
    path = Path(path)
    text, data, new_text, merged = _updated(path, updates)
    backup = _backup_name(path, stamp)
    with atomic_path(path) as tmp:
        _check_new(path, tmp, new_text, data, merged, verify)
        with open(backup, "x", encoding="utf-8") as handle:  # never overwrites: a new name each time
            handle.write(text)
    return backup


def check_storable(path: Path | str, node_ids: list[int], verify: Callable[[Path], object] | None = None) -> None:
    """Refuse now, before anything is measured, a robot file that a calibration of ``node_ids`` could not be stored in.

    The file with a calibration (zeros and a tare) for each node is built and checked as
    :func:`store_calibrations` would, under a temporary name that is removed; the file is not changed.

    Raises:
        HalConfigError, OutputWriteError: as :func:`store_calibrations`.
    """
    path = Path(path)
    trial = {"motor_zero_counts": 0, "link_zero_counts": 0, "zeroed_utc": "2000-01-01T00:00:00Z",
             "torque_tare_nm": 0.0, "tared_utc": "2000-01-01T00:00:00Z"}  # fmt: skip
    _, data, new_text, merged = _updated(path, dict.fromkeys(node_ids, trial))
    try:  # beside the file, so that its relative paths (the EDS files) resolve as they will
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".trial.yaml", dir=path.parent)
    except OSError as exc:
        raise OutputWriteError(f"{path}: cannot write beside it ({exc.strerror})") from None
    os.close(fd)
    try:
        _check_new(path, Path(name), new_text, data, merged, verify)
    finally:
        Path(name).unlink(missing_ok=True)


def _updated(
    path: Path, updates: dict[int, dict[str, Any]]
) -> tuple[str, dict[str, Any], str, dict[int, dict[str, Any]]]:
    """``(old text, old document, new text, each updated node's merged calibration)``.

    Raises:
        HalConfigError: see :func:`store_calibrations`.
    """
    text = read_text_bounded(path, HalConfigError, YAML_MAX_BYTES, "robot file")
    data, root = read_yaml(path, HalConfigError, "a robot file (a YAML mapping with backend: and nodes:)")
    nodes = _nodes(path, data, root)
    unknown = sorted(set(updates) - set(nodes))
    if unknown:
        raise HalConfigError(f"{path}: no node with node_id {unknown} in nodes:; expected one of {sorted(nodes)}")
    starts = _line_starts(text)
    edits: list[tuple[int, int, str]] = []
    merged: dict[int, dict[str, Any]] = {}
    for node_id, values in updates.items():
        item, calibration = nodes[node_id]
        merged[node_id] = {**calibration, **values}
        edits.append(_edit(path, text, starts, item, node_id, merged[node_id]))
    new_text = text
    for start, end, replacement in sorted(edits, reverse=True):
        new_text = new_text[:start] + replacement + new_text[end:]
    return text, data, new_text, merged


def _check_new(
    path: Path,
    tmp: Path,
    new_text: str,
    data: dict[str, Any],
    merged: dict[int, dict[str, Any]],
    verify: Callable[[Path], object] | None,
) -> None:
    """Write ``new_text`` to ``tmp`` and check it (same document but the calibrations; ``verify``), messages naming ``path``.

    Raises:
        HalConfigError: see :func:`store_calibrations`.
    """
    tmp.write_text(new_text, encoding="utf-8")
    _same_but_calibrations(path, tmp, data, merged)
    if verify is None:
        return
    try:
        verify(tmp)
    except HalConfigError as exc:
        problem = str(exc).replace(str(tmp), str(path))
        raise HalConfigError(f"{path}: with a calibration: per node the file would not load; nothing was written "
                             f"({problem})") from None  # fmt: skip


def _line_starts(text: str) -> list[int]:
    starts = [0]
    for i, char in enumerate(text):
        if char == "\n":
            starts.append(i + 1)
    return starts


def _end_of_line(text: str, starts: list[int], line: int) -> int:
    """The offset of the newline that ends ``line`` (0-based), or the end of the text."""
    end = text.find("\n", starts[line]) if line < len(starts) else -1
    return len(text) if end < 0 else end


def _last_line(node: yaml.Node) -> int:
    """The last line (0-based) a node's own text takes: its last scalar or flow collection."""
    if isinstance(node, yaml.ScalarNode) or getattr(node, "flow_style", False):
        mark = node.end_mark
        return mark.line - 1 if mark.column == 0 and mark.line > node.start_mark.line else mark.line
    children: list[yaml.Node] = []
    if isinstance(node, yaml.MappingNode):
        children = [part for pair in node.value for part in pair]
    elif isinstance(node, yaml.SequenceNode):
        children = list(node.value)
    return max((_last_line(child) for child in children), default=node.start_mark.line)


def _edit(
    path: Path, text: str, starts: list[int], item: yaml.MappingNode, node_id: int, calibration: dict[str, Any]
) -> tuple[int, int, str]:
    """``(start, end, replacement)``: the node's ``calibration:`` block replaced, or a new one after its last line."""
    if item.flow_style or not item.value:
        raise HalConfigError(
            f"{path}: line {item.start_mark.line + 1}: node {node_id} is written as a flow mapping {{...}}; "
            "expected a block mapping (one key: value a line) to store its calibration in"
        )
    indent = item.value[0][0].start_mark.column
    for key, value in item.value:
        if key.value == "calibration":
            start = starts[key.start_mark.line] + key.start_mark.column
            end = _end_of_line(text, starts, _last_line(value))
            return start, end, _render(calibration, indent, first_indented=False)
    end = _end_of_line(text, starts, _last_line(item))
    return end, end, "\n" + _render(calibration, indent, first_indented=True)


def _scalar(value: Any) -> str:
    """One value as YAML text: numbers plain, text single-quoted (a time stamp must stay text)."""
    if isinstance(value, bool) or value is None:
        return yaml.safe_dump(value, default_flow_style=True).splitlines()[0]
    if isinstance(value, int | float):
        shown = repr(value)
        return shown if _NUMBER.match(shown) else yaml.safe_dump(value).splitlines()[0]
    return "'" + str(value).replace("'", "''") + "'"


def _render(calibration: dict[str, Any], indent: int, first_indented: bool) -> str:
    keys = [k for k in CALIBRATION_KEYS if k in calibration] + [k for k in calibration if k not in CALIBRATION_KEYS]
    pad = " " * indent
    lines = [f"{pad if first_indented else ''}calibration:                # daror can zero / daror can tare"]
    lines += [f"{pad}  {key}: {_scalar(calibration[key])}" for key in keys]
    return "\n".join(lines)


def _same_but_calibrations(path: Path, new: Path, old_data: dict[str, Any], merged: dict[int, dict[str, Any]]) -> None:
    """The new file parses to the old one with the merged calibrations, and nothing else changed.

    Raises:
        HalConfigError: it does not (a bug of the textual update: the file is left as it was).
    """
    new_data, _ = read_yaml(new, HalConfigError, "a robot file")
    expected = copy.deepcopy(old_data)
    for node in expected["nodes"]:
        if node.get("node_id") in merged:
            node["calibration"] = merged[node["node_id"]]
    if new_data != expected:
        raise HalConfigError(
            f"{path}: the calibration could not be written without changing something else in the file; "
            "nothing was written (expected each node as a block mapping, its keys one a line)"
        )


def _backup_name(path: Path, stamp: str) -> Path:
    """``robot.yaml.<stamp>.bak`` beside the file; ``.2.bak``, ``.3.bak`` if that exists."""
    base = f"{path.name}.{stamp}" if stamp else path.name
    candidate = path.with_name(f"{base}.bak")
    counter = 2
    while candidate.exists():
        candidate = path.with_name(f"{base}.{counter}.bak")
        counter += 1
    return candidate
