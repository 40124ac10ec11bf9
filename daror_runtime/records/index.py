"""A session folder into the records: the session, its pilot, its range of motion, models and datasets.

Reads what the runtime wrote (``session.json``, ``isb_limits.yaml``, each data file's provenance,
the model files); records each file with the SHA-256 it has now. Idempotent: a session already
recorded is updated in place (a session recovered after a crash, then recorded again, keeps one
record). Design time (after the session ended), never in the tick.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import structlog

from daror_runtime.data.checksum import file_sha256
from daror_runtime.data.provenance import PROVENANCE_SUFFIX
from daror_runtime.records.schema import (
    PILOT_CODE_PATTERN,
    DatasetRecord,
    ModelRecord,
    PilotRecord,
    RangeOfMotionRecord,
    SessionRecord,
)
from daror_runtime.records.store import RecordsError, Store
from hal.files import read_text_bounded

log = structlog.get_logger(__name__)

#: ``session.json`` is tens of kB; a bigger file is not a session's.
SESSION_JSON_MAX_BYTES = 16 * 1024 * 1024
_SIMULATED_PILOT = re.compile(r"^simulated pilot \((?P<scenario>[A-Za-z0-9_.-]+)\)$")


@dataclass(frozen=True)
class Recorded:
    """What :func:`record_session` wrote: the session's id, its pilot's code, how many files of each kind."""

    session_id: str
    pilot: str
    datasets: int
    models: int
    range_of_motion: bool
    new: bool  # False: the session was recorded before and its record was updated


def pilot_code(named: str) -> tuple[str, bool]:
    """The records' code of a session's pilot, and whether he is a simulated scenario's.

    ``simulated pilot (exo_dummy_arm)`` (a simulated session that named nobody) is ``sim-exo_dummy_arm``.

    Raises:
        RecordsError: a name that is not a code (letters, digits, ``_ . -``; at most 32).
    """
    simulated = _SIMULATED_PILOT.match(named)
    if simulated is not None:
        return f"sim-{simulated['scenario']}"[:32], True
    if re.match(PILOT_CODE_PATTERN, named) is None:
        raise RecordsError(f"pilot {named!r}: not a code; expected letters, digits, '_', '.', '-' (at most 32)")
    return named, False


def _utc(text: str | None) -> datetime | None:
    if not text:
        return None
    moment = datetime.fromisoformat(text)
    return moment.replace(tzinfo=UTC) if moment.tzinfo is None else moment


def read_session_json(directory: Path) -> dict[str, Any]:
    """The ``session.json`` of ``directory``.

    Raises:
        RecordsError: no such file, not JSON, or not a session's summary.
    """
    path = directory / "session.json"
    if not path.is_file():
        raise RecordsError(f"{path}: no such file; expected the folder of a session (daror console --out DIR)")
    try:
        document = json.loads(read_text_bounded(path, RecordsError, SESSION_JSON_MAX_BYTES, "session summary"))
    except (ValueError, OSError) as exc:
        raise RecordsError(f"{path}: not a session's summary: {exc}") from None
    if not isinstance(document, dict) or not isinstance(document.get("session_id"), str):
        raise RecordsError(f"{path}: no session_id; expected the session.json a session writes")
    return document


def get_pilot(store: Store, code: str) -> PilotRecord | None:
    """The pilot recorded under ``code``, or None."""
    from sqlalchemy import select

    with store.session() as orm:
        return orm.scalars(select(PilotRecord).where(PilotRecord.code == code)).one_or_none()


def record_session(store: Store, directory: Path | str, pilot: str | None = None) -> Recorded:
    """Record the session in ``directory`` (and every file it wrote); ``pilot`` overrides ``session.json``'s.

    A pilot not yet in the records is created (a simulated scenario's pilot marked as such).

    Raises:
        RecordsError: no ``session.json``, no pilot named, a pilot code that is not one.
    """
    from sqlalchemy import select

    directory = Path(directory).resolve()
    document = read_session_json(directory)
    session_id = document["session_id"]
    named = pilot if pilot is not None else document.get("pilot")
    if not named:
        raise RecordsError(f"{directory / 'session.json'}: the session names no pilot; record it with --pilot CODE")
    code, simulated = pilot_code(named)
    now = datetime.now(UTC)
    history = document.get("history") or {}
    ended = document.get("ended") or {}

    def write(orm: Any) -> bool:
        pilot_record = orm.scalars(select(PilotRecord).where(PilotRecord.code == code)).one_or_none()
        if pilot_record is None:
            pilot_record = PilotRecord(code=code, simulated=simulated, created_utc=now)
            orm.add(pilot_record)
            orm.flush()
            log.info("pilot recorded", pilot=code, simulated=simulated, db=store.url_shown)
        record = orm.scalars(select(SessionRecord).where(SessionRecord.session_id == session_id)).one_or_none()
        new = record is None
        if record is None:
            record = SessionRecord(session_id=session_id, recorded_utc=now)
            orm.add(record)
        record.pilot = pilot_record
        record.started_utc = _utc(history.get("started_utc"))
        record.ended_utc = _utc(document.get("ended_utc"))
        record.ended_reason = ended.get("reason")
        record.ended_by_crash = bool(document.get("ended_by_crash", False))
        record.operator = document.get("operator")
        record.robot = str(document.get("robot") or "unknown")
        record.backend = str(document.get("backend") or "unknown")
        record.directory = str(directory)
        record.final_state = str(document.get("state"))
        record.robot_time_s = float(document.get("t_s") or 0.0)
        record.states_reached = list(history.get("states_reached") or [])
        record.faults = list(history.get("faults") or [])
        record.support_levels = list(history.get("support_levels") or [])
        record.online = list(document.get("online") or []) or None
        record.comparison = (document.get("comparison") or {}).get("verdict")
        record.session_json_sha256 = file_sha256(directory / "session.json")
        orm.flush()
        counts["datasets"] = _record_datasets(orm, record, directory)
        counts["models"] = _record_models(orm, record, directory, document.get("model"))
        counts["rom"] = int(_record_range_of_motion(orm, record, directory))
        return new

    counts: dict[str, int] = {}
    new = store.write(write)
    datasets, models, rom = counts["datasets"], counts["models"], bool(counts["rom"])
    log.info("session recorded", session_id=session_id, pilot=code, datasets=datasets, models=models, new=new)
    return Recorded(session_id, code, datasets, models, rom, new)


def _record_datasets(orm: Any, record: SessionRecord, directory: Path) -> int:
    from sqlalchemy import select

    count = 0
    for provenance_file in sorted(directory.glob(f"*{PROVENANCE_SUFFIX}")):
        data = provenance_file.with_name(provenance_file.name[: -len(PROVENANCE_SUFFIX)])
        if not data.is_file():
            continue
        try:
            provenance = json.loads(read_text_bounded(provenance_file, RecordsError, 64 * 1024, "provenance file"))
        except (ValueError, OSError) as exc:
            raise RecordsError(f"{provenance_file}: not a provenance file: {exc}") from None
        path = str(data)
        row = orm.scalars(
            select(DatasetRecord).where(DatasetRecord.session_id == record.id, DatasetRecord.path == path)
        ).one_or_none()
        if row is None:
            row = DatasetRecord(session_id=record.id, path=path)
            orm.add(row)
        row.pilot_id = record.pilot_id
        row.run = provenance.get("run")
        row.sha256 = file_sha256(data)
        row.recorded_utc = _utc(provenance.get("recorded_utc"))
        row.provenance = provenance
        count += 1
    return count


def _record_models(orm: Any, record: SessionRecord, directory: Path, in_use: dict[str, Any] | None) -> int:
    from sqlalchemy import select

    in_use_path = Path(in_use["path"]).resolve() if in_use and in_use.get("path") else None
    files = sorted(p.resolve() for p in directory.glob("model_*.json"))
    if in_use_path is not None and in_use_path not in files and in_use_path.is_file():
        files.append(in_use_path)  # a model of an earlier session, selected and validated in this one
    count = 0
    for model_file in files:
        try:
            document = json.loads(read_text_bounded(model_file, RecordsError, 64 * 1024 * 1024, "model file"))
        except (ValueError, OSError) as exc:
            raise RecordsError(f"{model_file}: not a model file: {exc}") from None
        if not isinstance(document, dict) or document.get("format") != "daror-model":
            raise RecordsError(f"{model_file}: not a model file; expected format daror-model")
        path = str(model_file.resolve())
        row = orm.scalars(
            select(ModelRecord).where(ModelRecord.session_id == record.id, ModelRecord.path == path)
        ).one_or_none()
        if row is None:
            row = ModelRecord(session_id=record.id, path=path, recorded_utc=datetime.now(UTC))
            orm.add(row)
        training = document.get("training") or {}
        row.pilot_id = record.pilot_id
        row.kind = str(document.get("kind"))
        row.sha256 = file_sha256(model_file)
        row.training_path = training.get("source")
        row.training_sha256 = training.get("sha256")
        row.parameters = document.get("parameters") or {}
        used = in_use_path is not None and in_use_path == model_file.resolve()
        row.in_use = used
        if used and in_use is not None:
            row.validated = bool(in_use.get("validated"))
            row.validation_rmse_nm = in_use.get("validation_rmse_nm")
            row.validation_rmse_per_joint_nm = in_use.get("validation_rmse_per_joint_nm")
            row.validation_path = in_use.get("validation_data")
            row.approved_by = in_use.get("approved_by")
            conservative = in_use.get("conservative")
            row.closed_path = None if conservative is None else ("conservative" if conservative else "not conservative")
        count += 1
    return count


def _record_range_of_motion(orm: Any, record: SessionRecord, directory: Path) -> bool:
    from sqlalchemy import delete

    from hal.isb import IsbLimitsError, load_isb_limits

    path = directory / "isb_limits.yaml"
    orm.execute(delete(RangeOfMotionRecord).where(RangeOfMotionRecord.session_id == record.id))
    if not path.is_file():
        return False
    try:
        limits = load_isb_limits(path)
    except IsbLimitsError as exc:
        raise RecordsError(str(exc)) from None
    header = path.read_text(encoding="utf-8").splitlines()[0] if path.stat().st_size else ""
    (elevation, horizontal, axial, elbow) = limits.ranges
    orm.add(
        RangeOfMotionRecord(
            pilot_id=record.pilot_id,
            session_id=record.id,
            source="recorded" if "recorded over" in header else "entered",
            path=str(path),
            sha256=file_sha256(path),
            elevation_lower_deg=elevation.lower_deg,
            elevation_upper_deg=elevation.upper_deg,
            horizontal_rotation_lower_deg=horizontal.lower_deg,
            horizontal_rotation_upper_deg=horizontal.upper_deg,
            axial_rotation_lower_deg=axial.lower_deg,
            axial_rotation_upper_deg=axial.upper_deg,
            elbow_lower_deg=elbow.lower_deg,
            elbow_upper_deg=elbow.upper_deg,
            horizontal_free_below_deg=limits.horizontal_free_below_deg,
            recorded_utc=datetime.fromtimestamp(path.stat().st_mtime, UTC),
        )
    )
    return True
