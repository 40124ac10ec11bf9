"""Model files: self-describing JSON (docs/data.md, "Model files"), written atomically, checked on load.

A model file holds everything needed to run the model without anything else: its kind, the
format version, its parameters, the full robot description it was fitted for (the regressor
depends on the geometry), a summary of the training data, the fit report and a SHA-256
checksum over all of it. The checksum makes a corrupted or altered file fail loudly at load
time instead of producing wrong torque in the loop.

:func:`load_model` refuses, each with one line naming the file (and the field where there is one),
before anything reaches a model: a path that is not a regular file of at most
:data:`~hal.files.MODEL_MAX_BYTES` (a directory, a FIFO, a device); text that is not JSON or nests
deeper than :data:`MAX_JSON_DEPTH`; a key written twice in one object; ``NaN``, ``Infinity``, a
number that overflows a float (``1e400``) or an integer of more than :data:`MAX_INT_DIGITS`
digits anywhere; a bool or text where a number is meant; a parameter outside its plausible
magnitude (:data:`PARAMETER_BOUNDS`) or a robot description value beyond
:data:`DESCRIPTION_MAX_ABS`; and, as before, a wrong format, version or checksum.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from daror_runtime.data.checksum import file_sha256
from daror_runtime.data.provenance import Provenance, read_provenance
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import DarorError, ModelFileError, UnknownModelKindError
from daror_runtime.models.base import CompensationModel, FitReport
from daror_runtime.models.registry import ModelKindPluginError, model_class
from daror_runtime.models.regressor import GRAVITY_PARAMETER_NAMES
from daror_runtime.util.atomic import write_text_atomic
from hal.files import MODEL_MAX_BYTES, read_text_bounded
from hal.robot import N_JOINTS, RobotDescription
from hal.yamlfile import Flag, Integer, Number, format_validation_error

FORMAT = "daror-model"
FORMAT_VERSION = 1

#: Deepest nesting of objects and arrays a model file may have (the files we write nest 5 deep).
MAX_JSON_DEPTH = 32
#: Longest integer (in digits) a model file may hold; counts of points stay far below this.
MAX_INT_DIGITS = 19


@dataclass(frozen=True)
class ParameterBound:
    """The plausible magnitude of a model parameter: ``|value| <= max_abs``, in ``unit``."""

    max_abs: float
    unit: str


#: Plausible magnitudes of the parameters of every model kind (ap, plf, plf+: theta and the elbow
#: polynomial; augmented: all of them), SI units. The first moments ``m g p`` of the DAROR-01 with
#: a pilot are tens of Nm, so 10^4 is generous; with it the model torque stays finite (below
#: ~10^10 Nm over the joint ranges, polynomials up to order 11 included) and so do its squares in
#: the metrics, so nothing downstream (``daror evaluate --json``) meets an overflow. Angles are
#: bounded by a turn (a joint zero) and a quarter turn (the base's tilt), a torque gain by 100.
PARAMETER_BOUNDS: dict[str, ParameterBound] = {
    "theta": ParameterBound(1e4, "Nm (first moments m g p)"),
    "elbow_polynomial": ParameterBound(1e4, "Nm/rad^k"),
    "joint_polynomials": ParameterBound(1e4, "Nm/rad^k"),
    "direction_offset_nm": ParameterBound(1e4, "Nm"),
    "torque_gain": ParameterBound(100.0, "(a ratio, 1 nominal)"),
    "angle_offset_rad": ParameterBound(2 * math.pi, "rad"),
    "gravity_tilt_rad": ParameterBound(math.pi / 2, "rad"),
}
#: Most numbers in one parameter vector: the 12 first moments, or a polynomial up to order 11 (the
#: torque bound above assumes it).
MAX_PARAMETER_VECTOR = 12
#: Any other number among a model's parameters (a kind added later).
DEFAULT_PARAMETER_BOUND = ParameterBound(1e4, "SI units")
#: Parameters that are yes/no values (``true``, ``false`` or ``null``; never 1 or "yes").
FLAG_PARAMETERS = frozenset({"includes_dummy_arm", "includes_elbow_stiffness"})
#: A model composed on a base model (``penn-residual``) stores the base as ``{"kind", "name",
#: "parameters"}`` under this key; the base's parameters are checked as a model's own.
NESTED_BASE = "base"
#: Largest magnitude of a number in a model file's robot description (SI units; degrees in ``_deg``).
DESCRIPTION_MAX_ABS = 1e4


class TrainingSummary(BaseModel):
    """What the model was trained on (enough to recognise the data, not a copy of it)."""

    model_config = ConfigDict(extra="forbid")

    source: str
    sha256: str | None = None
    n_points: Integer
    has_direction: Flag
    q_min_rad: list[Number] = Field(min_length=N_JOINTS, max_length=N_JOINTS)
    q_max_rad: list[Number] = Field(min_length=N_JOINTS, max_length=N_JOINTS)
    # whose data it was (the training file's provenance file, when it has one: data/provenance.py)
    provenance: Provenance | None = None
    # set only when the data failed the physics check of its column names and the user accepted it
    # (--trust-signal-map: data/signal_map.py); absent otherwise
    signal_map: str | None = None


class ModelFile(BaseModel):
    """The JSON document of a model file."""

    model_config = ConfigDict(extra="forbid")

    format: Literal["daror-model"]
    format_version: Integer
    kind: str
    name: str
    created_utc: str
    robot: RobotDescription
    parameters: dict[str, Any]
    training: TrainingSummary | None = None
    fit: dict[str, Any] = Field(default_factory=dict)
    checksum_sha256: str


def training_summary(dataset: StationaryDataset, source_path: Path | str | None = None) -> TrainingSummary:
    """What a model is trained on: the file, its checksum and provenance (when it has one), the points' range.

    Raises:
        DataError: the file's provenance file is malformed or belongs to other data.
    """
    path = Path(source_path) if source_path is not None else None
    return TrainingSummary(
        source=str(path) if path is not None else dataset.source,
        sha256=file_sha256(path) if path is not None and path.is_file() else None,
        provenance=read_provenance(path) if path is not None and path.is_file() else None,
        n_points=len(dataset),
        has_direction=dataset.direction is not None,
        q_min_rad=[float(v) for v in np.min(dataset.q_rad, axis=0)],
        q_max_rad=[float(v) for v in np.max(dataset.q_rad, axis=0)],
    )


def _canonical(document: dict[str, Any]) -> bytes:
    return json.dumps(document, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def _checksum(document: dict[str, Any]) -> str:
    body = {k: v for k, v in document.items() if k != "checksum_sha256"}
    return hashlib.sha256(_canonical(body)).hexdigest()


def model_document(
    model: CompensationModel, training: TrainingSummary | None = None, report: FitReport | None = None
) -> dict[str, Any]:
    """The JSON-ready document of ``model`` (what :func:`save_model` writes)."""
    document: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "kind": model.kind,
        "name": model.name,
        "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "robot": model.description.model_dump(mode="json"),
        "parameters": model.parameters(),
        # signal_map only when set: a file trained on trusted data says so, the others are as before
        "training": None
        if training is None
        else training.model_dump(mode="json", exclude={"signal_map"} if training.signal_map is None else None),
        "fit": {} if report is None else report.to_dict(),
    }
    document["checksum_sha256"] = _checksum(document)
    return document


def save_model(
    path: Path | str, model: CompensationModel, training: TrainingSummary | None = None, report: FitReport | None = None
) -> None:
    """Write ``model`` as a model file, atomically."""
    try:
        text = json.dumps(model_document(model, training, report), indent=2, allow_nan=False)
    except ValueError as exc:  # NaN or infinity among the parameters
        raise DarorError(f"{path}: refusing to save model {model.name!r}: {exc}") from None
    write_text_atomic(path, text + "\n")


class _Literal:
    """A JSON value refused after parsing, so that the refusal can name its field (NaN, a 5,000-digit int)."""

    def __init__(self, text: str, problem: str) -> None:
        self.text = text
        self.problem = problem


class _DuplicateKeyError(Exception):
    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.key = key


def _constant(name: str) -> _Literal:
    return _Literal(name, f"{name} is not a number; a model file holds finite numbers only")


def _integer(text: str) -> int | _Literal:
    digits = len(text.lstrip("-"))
    if digits > MAX_INT_DIGITS:
        return _Literal(text, f"an integer of {digits:,} digits; expected at most {MAX_INT_DIGITS}")
    return int(text)


def _number(text: str) -> float | _Literal:
    value = float(text)
    if not math.isfinite(value):
        shown = text if len(text) <= 24 else text[:21] + "..."
        return _Literal(
            text, f"{shown} is too large for a number (it reads as infinity); a model file holds finite numbers only"
        )
    return value


def _object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    document: dict[str, Any] = {}
    for key, value in pairs:
        if key in document:
            raise _DuplicateKeyError(key)
        document[key] = value
    return document


def _parse(path: Path, text: str) -> Any:
    """``text`` as JSON; NaN, infinities and over-long integers left as :class:`_Literal` for :func:`_literal_problems`."""
    try:
        return json.loads(
            text, parse_constant=_constant, parse_int=_integer, parse_float=_number, object_pairs_hook=_object
        )
    except json.JSONDecodeError as exc:
        raise ModelFileError(
            f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg}); the file is corrupted"
        ) from None
    except _DuplicateKeyError as exc:
        raise ModelFileError(
            f"{path}: key {exc.key!r} is written twice in one JSON object; the file was edited or corrupted"
        ) from None
    except RecursionError:
        raise ModelFileError(
            f"{path}: nested too deeply for a model file (more than {MAX_JSON_DEPTH} levels); the file is corrupted"
        ) from None
    except ValueError as exc:  # a number Python cannot convert
        raise ModelFileError(f"{path}: not valid JSON ({str(exc).split(':')[0]}); the file is corrupted") from None


Location = tuple[int | str, ...]


def _walk(value: Any, location: Location = ()) -> Iterator[tuple[Location, Any]]:
    """Every value below ``value`` with its location, depth first, without recursion (a deep file cannot overflow)."""
    stack: list[tuple[Location, Any]] = [(location, value)]
    while stack:
        where, item = stack.pop()
        yield where, item
        if isinstance(item, dict):
            stack.extend(((*where, k), v) for k, v in reversed(item.items()))
        elif isinstance(item, list):
            stack.extend(((*where, i), v) for i, v in reversed(list(enumerate(item))))


def _field(location: Location) -> str:
    return ".".join(str(p) for p in location) or "(top level)"


def _literal_problems(document: Any) -> str | None:
    """The first value that is too deep, not finite or too long, as ``field X: problem``; None if there is none."""
    for location, value in _walk(document):
        if len(location) > MAX_JSON_DEPTH:
            return (
                f"field {_field(location[:4])}...: nested more than {MAX_JSON_DEPTH} levels deep; the file is corrupted"
            )
        if isinstance(value, _Literal):
            return f"field {_field(location)}: {value.problem}"
    return None


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _parameter_name(location: Location, where: Location = ()) -> str:
    """``parameters.theta.6 (theta3x)``: the field (below ``where``), with the name of a first moment where there is one."""
    name = f"parameters.{_field((*where, *location))}"
    if (
        len(location) == 2
        and location[0] == "theta"
        and isinstance(location[1], int)
        and location[1] < len(GRAVITY_PARAMETER_NAMES)
    ):
        name += f" ({GRAVITY_PARAMETER_NAMES[location[1]]})"
    return name


def _parameter_problems(parameters: dict[str, Any], where: Location = ()) -> Iterator[str]:
    """Numbers where numbers are meant, yes/no where yes/no is meant, and every number of a plausible magnitude.

    A base model's parameters (``base.parameters``, :data:`NESTED_BASE`) are checked as a model's own.
    """
    for key, value in parameters.items():
        if key == NESTED_BASE and isinstance(value, dict) and isinstance(value.get("parameters"), dict):
            yield from _parameter_problems(value["parameters"], (*where, key, "parameters"))
            continue
        if key in FLAG_PARAMETERS:
            if value is not None and not isinstance(value, bool):
                yield f"field {_parameter_name((key,), where)}: expected true or false; got {json.dumps(value)[:40]}"
            continue
        bound = PARAMETER_BOUNDS.get(key, DEFAULT_PARAMETER_BOUND)
        numeric = key in PARAMETER_BOUNDS
        for location, item in _walk(value, (key,)):
            if numeric and isinstance(item, list) and len(item) > MAX_PARAMETER_VECTOR:
                yield (
                    f"field {_parameter_name(location, where)}: {len(item):,} values; expected at most "
                    f"{MAX_PARAMETER_VECTOR} (12 first moments, a polynomial up to order 11)"
                )
                break
            if isinstance(item, dict | list):
                continue
            if numeric and not _is_number(item):
                yield f"field {_parameter_name(location, where)}: expected a number; got {json.dumps(item)[:40]}"
            elif _is_number(item) and abs(item) > bound.max_abs:
                yield (
                    f"field {_parameter_name(location, where)}: {item:g} is not a plausible parameter; expected "
                    f"|value| <= {bound.max_abs:g} {bound.unit}"
                )


def _description_problems(robot: object) -> Iterator[str]:
    for location, item in _walk(robot, ("robot",)):
        if _is_number(item) and abs(item) > DESCRIPTION_MAX_ABS:
            yield (
                f"field {_field(location)}: {item:g} is not plausible for a robot description; expected "
                f"|value| <= {DESCRIPTION_MAX_ABS:g} (SI units, degrees where the name ends in _deg)"
            )


class _NestedBase(BaseModel):
    """The entry of a base model inside a composed model's parameters (:data:`NESTED_BASE`)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    kind: str
    name: str | None = None
    parameters: dict[str, Any]


def model_from_parameters(
    description: RobotDescription, kind: str, parameters: dict[str, Any], name: str | None = None
) -> CompensationModel:
    """The model of kind ``kind`` rebuilt from a model file's ``parameters`` (no file read).

    For a kind composed on another model (``nested_base``), the base under :data:`NESTED_BASE` is
    built first, by its own kind, and handed to the kind's ``from_parameters`` in its place.

    Raises:
        ModelFileError: parameters that do not fit the kind (or the base's kind); one line naming
            the field (``parameters.base.parameters.theta`` for the base's).
        UnknownModelKindError: the kind, or the base's kind, is not registered.
        ModelKindPluginError, ExtraMissingError: see :func:`~daror_runtime.models.registry.model_class`.
    """
    cls = model_class(kind)
    if cls.nested_base:
        try:
            entry = _NestedBase.model_validate(parameters.get(NESTED_BASE))
        except ValidationError as exc:
            problem = exc.errors()[0]
            field = ".".join(str(x) for x in (NESTED_BASE, *problem["loc"]))
            raise ModelFileError(f"parameters.{field}: {problem['msg']} (model kind {kind})") from None
        try:
            base = model_from_parameters(description, entry.kind, entry.parameters, entry.name)
        except UnknownModelKindError as exc:
            raise ModelFileError(f"parameters.{NESTED_BASE}.kind: {exc}") from None
        except ModelFileError as exc:
            message = str(exc)
            inner = message.removeprefix("parameters") if message.startswith("parameters") else f": {message}"
            raise ModelFileError(f"parameters.{NESTED_BASE}.parameters{inner}") from None
        parameters = {**parameters, NESTED_BASE: base}
    return cls.from_parameters(description, parameters, name)


def load_model(path: Path | str) -> tuple[CompensationModel, ModelFile]:
    """Read, verify and rebuild the model in ``path``.

    Raises:
        ModelFileError: not a regular file of at most :data:`~hal.files.MODEL_MAX_BYTES`, not UTF-8,
            not JSON, nested too deeply, a key written twice, a value that is not a finite number
            where one is meant, an implausible parameter (:data:`PARAMETER_BOUNDS`), not a model
            file, unsupported version, checksum mismatch, an unknown kind, a kind that is not the one
            its fit recorded (``fit.kind``), or parameters that do not fit the kind (another kind's,
            a vector of the wrong length: each kind's ``from_parameters``); one line naming the file
            (and the field where there is one).
        ModelKindPluginError: the kind is registered by a plugin that cannot be loaded (file named).
        ExtraMissingError: the kind needs an optional extra that is not installed.
    """
    path = Path(path)
    text = read_text_bounded(path, ModelFileError, MODEL_MAX_BYTES, "model file")
    document = _parse(path, text)
    problem = _literal_problems(document)
    if problem is not None:
        raise ModelFileError(f"{path}: {problem}")
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise ModelFileError(f'{path}: not a daror model file; expected a JSON object with "format": "{FORMAT}"')
    version = document.get("format_version")
    if type(version) is not int or version != FORMAT_VERSION:  # not true, not 1.0
        raise ModelFileError(
            f"{path}: model file format version {json.dumps(version)} is not supported; expected {FORMAT_VERSION}"
        )
    try:
        contents = ModelFile.model_validate(document)
    except ValidationError as exc:
        raise ModelFileError(format_validation_error(str(path), exc)) from None
    problems = [*_parameter_problems(contents.parameters), *_description_problems(document["robot"])]
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise ModelFileError(f"{path}: {problems[0]}{more}")
    if _checksum(document) != contents.checksum_sha256:
        raise ModelFileError(
            f"{path}: checksum mismatch; the file was changed or corrupted after it was written, refit or restore it"
        )
    fitted_as = contents.fit.get("kind")
    if fitted_as is not None and fitted_as != contents.kind:  # a kind edited after the fit (checksum signed again)
        raise ModelFileError(
            f"{path}: field kind: {contents.kind!r}, but the fit that made these parameters was of kind "
            f"{json.dumps(fitted_as)[:40]} (field fit.kind); the parameters belong to another kind"
        )
    try:
        model = model_from_parameters(contents.robot, contents.kind, contents.parameters, contents.name)
    except (ModelFileError, UnknownModelKindError) as exc:
        raise ModelFileError(f"{path}: {exc}") from None
    except ModelKindPluginError as exc:  # the installation is broken, not the file: exit code 1
        raise ModelKindPluginError(f"{path}: {exc}") from None
    return model, contents
