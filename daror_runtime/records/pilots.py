"""The records' queries and the pilots' verbs: add a pilot, summarise them, one pilot's record, the sessions."""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from daror_runtime.data.checksum import file_sha256
from daror_runtime.records.schema import PILOT_CODE_PATTERN, ModelRecord, PilotRecord, SessionRecord
from daror_runtime.records.store import RecordsError, Store

if TYPE_CHECKING:
    from sqlalchemy.orm import Session

#: A birth year the records accept (a pilot is a child or an adult of our time).
BIRTH_YEAR_RANGE = (1900, 2100)


def check_code(code: str) -> str:
    """``code`` if it is a pilot's code.

    Raises:
        RecordsError: letters, digits, ``_ . -`` expected, at most 32, starting with a letter or digit.
    """
    if re.match(PILOT_CODE_PATTERN, code) is None:
        raise RecordsError(
            f"pilot {code!r}: not a code; expected letters, digits, '_', '.', '-' (at most 32), e.g. P-007"
        )
    if code.startswith("sim-"):
        raise RecordsError(f"pilot {code!r}: codes starting with sim- are the simulated scenarios' pilots")
    return code


def add_pilot(
    store: Store, code: str, arm_side: str = "right", birth_year: int | None = None, notes: str = ""
) -> PilotRecord:
    """Add a pilot under ``code``.

    Raises:
        RecordsError: not a code, already recorded, an arm other than right or left, a birth year out of range.
    """
    from sqlalchemy import select

    check_code(code)
    if arm_side not in ("right", "left"):
        raise RecordsError(f"--arm {arm_side!r}: expected right or left")
    if birth_year is not None and not BIRTH_YEAR_RANGE[0] <= birth_year <= BIRTH_YEAR_RANGE[1]:
        raise RecordsError(
            f"--birth-year {birth_year}: expected a year between {BIRTH_YEAR_RANGE[0]} and {BIRTH_YEAR_RANGE[1]}"
        )

    def write(orm: Any) -> PilotRecord:
        if orm.scalars(select(PilotRecord).where(PilotRecord.code == code)).one_or_none() is not None:
            raise RecordsError(f"pilot {code} is already in {store.url_shown}")
        pilot = PilotRecord(
            code=code, arm_side=arm_side, birth_year=birth_year, notes=notes, created_utc=datetime.now(UTC)
        )
        orm.add(pilot)
        return pilot

    return store.write(write)


@dataclass(frozen=True)
class PilotSummary:
    code: str
    arm_side: str
    birth_year: int | None
    simulated: bool
    sessions: int
    last_session_utc: datetime | None
    model: str | None  # "plf+ 0.42 Nm" of the last session's model in use


def pilot_summaries(store: Store) -> list[PilotSummary]:
    """Every pilot, by code, with his sessions' count, the last session and the model it ended with."""
    from sqlalchemy import select
    from sqlalchemy.orm import selectinload

    out = []
    with store.session() as orm:
        pilots = orm.scalars(
            select(PilotRecord)
            .options(selectinload(PilotRecord.sessions).selectinload(SessionRecord.models))
            .order_by(PilotRecord.code)
        )
        for pilot in pilots:
            sessions = pilot.sessions
            last = sessions[-1] if sessions else None
            model = _in_use(last) if last is not None else None
            out.append(
                PilotSummary(
                    pilot.code,
                    pilot.arm_side,
                    pilot.birth_year,
                    pilot.simulated,
                    len(sessions),
                    None if last is None else last.started_utc,
                    None if model is None else _model_text(model),
                )
            )
    return out


def _in_use(session: SessionRecord) -> ModelRecord | None:
    return next((m for m in session.models if m.in_use), None)


def _model_text(model: ModelRecord) -> str:
    rmse = "" if model.validation_rmse_nm is None else f" {model.validation_rmse_nm:.3f} Nm"
    return f"{model.kind}{rmse}" + ("" if model.validated else " (not validated)")


def _file_state(path: str, sha256: str | None) -> str:
    """``ok``, ``missing`` or ``changed``: the file against the hash the records hold."""
    file = Path(path)
    if not file.is_file():
        return "missing"
    if sha256 is not None and file_sha256(file) != sha256:
        return "changed"
    return "ok"


def find_pilot(orm: Session, code: str) -> PilotRecord | None:
    """The pilot under ``code`` with his sessions, their models, ranges of motion and datasets loaded; or None."""
    from sqlalchemy import select
    from sqlalchemy.orm import selectinload

    sessions = selectinload(PilotRecord.sessions)
    return orm.scalars(
        select(PilotRecord)
        .where(PilotRecord.code == code)
        .options(
            sessions.selectinload(SessionRecord.models),
            sessions.selectinload(SessionRecord.ranges_of_motion),
            sessions.selectinload(SessionRecord.datasets),
        )
    ).one_or_none()


def load_pilot(orm: Session, code: str, url_shown: str) -> PilotRecord:
    """:func:`find_pilot`, refused when he is not in the records.

    Raises:
        RecordsError: no pilot under ``code``.
    """
    pilot = find_pilot(orm, code)
    if pilot is None:
        raise RecordsError(f"pilot {code}: not in {url_shown}; expected one of: daror pilots list")
    return pilot


def pilot_record_lines(store: Store, code: str) -> list[str]:
    """One pilot's record in lines: who, then each session with its range of motion and models.

    Each file is checked against its hash: ``missing`` or ``changed`` is said where it is.

    Raises:
        RecordsError: no pilot under ``code``.
    """
    with store.session() as orm:
        pilot = load_pilot(orm, code, store.url_shown)
        born = "" if pilot.birth_year is None else f", born {pilot.birth_year}"
        lines = [f"pilot {pilot.code}: {pilot.arm_side} arm{born}{' (simulated)' if pilot.simulated else ''}"]
        if pilot.notes:
            lines.append(f"  notes: {pilot.notes}")
        lines.append(f"  {len(pilot.sessions)} session(s)")
        for session in pilot.sessions:
            started = "-" if session.started_utc is None else session.started_utc.isoformat(timespec="minutes")
            ended = "crashed" if session.ended_by_crash else (session.ended_reason or "not ended")
            lines.append(
                f"  session {session.session_id} {started} on {session.robot} ({session.backend}): "
                f"reached {session.final_state}, {ended}; {len(session.faults)} fault(s); "
                f"support {', '.join(f'{s:g}' for s in session.support_levels) or '-'}"
            )
            for rom in session.ranges_of_motion:
                lines.append(
                    f"    range of motion ({rom.source}): elevation {rom.elevation_lower_deg:g}..{rom.elevation_upper_deg:g}, "
                    f"horizontal {rom.horizontal_rotation_lower_deg:g}..{rom.horizontal_rotation_upper_deg:g}, "
                    f"axial {rom.axial_rotation_lower_deg:g}..{rom.axial_rotation_upper_deg:g}, "
                    f"elbow {rom.elbow_lower_deg:g}..{rom.elbow_upper_deg:g} deg"
                )
            for model in session.models:
                state = _file_state(model.path, model.sha256)
                lines.append(
                    f"    model {_model_text(model)}{' in use' if model.in_use else ''}: {model.path}"
                    + ("" if state == "ok" else f" [{state}]")
                )
            for data in session.datasets:
                state = _file_state(data.path, data.sha256)
                lines.append(f"    data ({data.run or '-'}): {data.path}" + ("" if state == "ok" else f" [{state}]"))
    return lines


def session_rows(store: Store, pilot: str | None = None) -> list[tuple[str, ...]]:
    """Each session (``pilot``'s only, if given), oldest first, as the cells of ``daror sessions list``.

    Raises:
        RecordsError: ``pilot`` is not in the records.
    """
    from sqlalchemy import select
    from sqlalchemy.orm import selectinload

    with store.session() as orm:
        query = (
            select(SessionRecord)
            .options(selectinload(SessionRecord.pilot))
            .order_by(SessionRecord.started_utc, SessionRecord.id)
        )
        if pilot is not None:
            record = orm.scalars(select(PilotRecord).where(PilotRecord.code == pilot)).one_or_none()
            if record is None:
                raise RecordsError(f"pilot {pilot}: not in {store.url_shown}; expected one of: daror pilots list")
            query = query.where(SessionRecord.pilot_id == record.id)
        rows = []
        for s in orm.scalars(query):
            rows.append(
                (
                    s.session_id,
                    s.pilot.code,
                    "-" if s.started_utc is None else s.started_utc.isoformat(timespec="minutes"),
                    s.operator or "-",
                    s.robot,
                    s.backend,
                    s.final_state,
                    "crashed" if s.ended_by_crash else (s.ended_reason or "not ended"),
                    str(len(s.faults)),
                )
            )
    return rows
