"""Model files: self-describing JSON (DESIGN.md section 5), written atomically, checked on load.

A model file holds everything needed to run the model without anything else: its kind, the
format version, its parameters, the full robot description it was fitted for (the regressor
depends on the geometry), a summary of the training data, the fit report and a SHA-256
checksum over all of it. The checksum makes a corrupted or altered file fail loudly at load
time instead of producing wrong torque in the loop.
"""

from __future__ import annotations

import hashlib
import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import DarorError, ModelFileError, UnknownModelKindError
from daror_runtime.models.base import CompensationModel, FitReport
from daror_runtime.models.registry import model_class
from daror_runtime.util.atomic import write_text_atomic
from hal.robot import N_JOINTS, RobotDescription
from hal.yamlfile import format_validation_error

FORMAT = "daror-model"
FORMAT_VERSION = 1


class TrainingSummary(BaseModel):
    """What the model was trained on (enough to recognise the data, not a copy of it)."""

    model_config = ConfigDict(extra="forbid")

    source: str
    sha256: str | None = None
    n_points: int
    has_direction: bool
    q_min_rad: list[float] = Field(min_length=N_JOINTS, max_length=N_JOINTS)
    q_max_rad: list[float] = Field(min_length=N_JOINTS, max_length=N_JOINTS)


class ModelFile(BaseModel):
    """The JSON document of a model file."""

    model_config = ConfigDict(extra="forbid")

    format: Literal["daror-model"]
    format_version: int
    kind: str
    name: str
    created_utc: str
    robot: RobotDescription
    parameters: dict[str, Any]
    training: TrainingSummary | None = None
    fit: dict[str, Any] = Field(default_factory=dict)
    checksum_sha256: str


def file_sha256(path: Path | str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def training_summary(dataset: StationaryDataset, source_path: Path | str | None = None) -> TrainingSummary:
    path = Path(source_path) if source_path is not None else None
    return TrainingSummary(
        source=str(path) if path is not None else dataset.source,
        sha256=file_sha256(path) if path is not None and path.is_file() else None,
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
        "training": None if training is None else training.model_dump(mode="json"),
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


def load_model(path: Path | str) -> tuple[CompensationModel, ModelFile]:
    """Read, verify and rebuild the model in ``path``.

    Raises:
        ModelFileError: missing, not JSON, not a model file, unsupported version, checksum
            mismatch, or parameters that do not fit the kind; the message names the file.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ModelFileError(f"{path}: model file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelFileError(f"{path}: cannot read model file ({exc})") from None
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ModelFileError(
            f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg}); the file is corrupted"
        ) from None
    if not isinstance(document, dict) or document.get("format") != FORMAT:
        raise ModelFileError(f'{path}: not a daror model file; expected a JSON object with "format": "{FORMAT}"')
    if document.get("format_version") != FORMAT_VERSION:
        raise ModelFileError(
            f"{path}: model file format version {document.get('format_version')!r} is not supported; expected {FORMAT_VERSION}"
        )
    try:
        contents = ModelFile.model_validate(document)
    except ValidationError as exc:
        raise ModelFileError(format_validation_error(str(path), exc)) from None
    if _checksum(document) != contents.checksum_sha256:
        raise ModelFileError(
            f"{path}: checksum mismatch; the file was changed or corrupted after it was written, refit or restore it"
        )
    try:
        cls = model_class(contents.kind)
        model = cls.from_parameters(contents.robot, contents.parameters, contents.name)
    except (ModelFileError, UnknownModelKindError) as exc:
        raise ModelFileError(f"{path}: {exc}") from None
    return model, contents
