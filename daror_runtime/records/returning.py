"""A returning pilot: what the records offer a new session of his (his last limits, his last model).

The console asks when the pilot is known (``pilot CODE``, or a simulated scenario's pilot) and when
the operator takes what is offered (``rom last``, ``model last``); each read opens the records,
reads, closes, outside the tick. A model file is offered only if it is the file the records hold
(its SHA-256): a file changed or replaced since is refused for compensation (issue 28, part 6).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from daror_runtime.data.checksum import file_sha256
from daror_runtime.records.index import pilot_code
from daror_runtime.records.pilots import find_pilot
from daror_runtime.records.schema import ModelRecord, RangeOfMotionRecord, SessionRecord
from daror_runtime.records.store import RecordsError, Store
from hal.isb import AngleRange, IsbLimits


@dataclass(frozen=True)
class LastLimits:
    """The pilot's most recent range of motion in the records."""

    limits: IsbLimits
    session_id: str | None
    recorded_utc: datetime
    source: str  # recorded | entered

    def age_days(self, now: datetime | None = None) -> float:
        return ((now or datetime.now(UTC)) - self.recorded_utc).total_seconds() / 86400.0


@dataclass(frozen=True)
class LastModel:
    """The model the pilot's most recent session ended with, validated there."""

    path: Path
    sha256: str
    kind: str
    validation_rmse_nm: float | None
    session_id: str
    #: The stationary data of his most recent validation run on disk: what validates it for
    #: ``operative_check`` before this session has a validation run of its own.
    validation_file: Path | None = None


@dataclass(frozen=True)
class PilotHistory:
    """What the records know of a pilot when a new session of his begins."""

    code: str
    sessions: int
    last_session_utc: datetime | None
    last_limits: LastLimits | None
    last_model: LastModel | None

    def offer(self, max_age_days: float, now: datetime | None = None) -> list[str]:
        """What the console says when the pilot is named: who he is to the records, what may be reused."""
        if self.sessions == 0:
            return [f"pilot {self.code}: new to the records (no earlier session)"]
        when = "-" if self.last_session_utc is None else self.last_session_utc.date().isoformat()
        lines = [f"pilot {self.code}: returning, {self.sessions} earlier session(s), the last on {when}"]
        if self.last_limits is None:
            lines.append("  no range of motion in the records: record it (rom start)")
        else:
            age = self.last_limits.age_days(now)
            if age > max_age_days:
                lines.append(
                    f"  his last range of motion is {age:.0f} days old (the settings allow {max_age_days:g}): record it anew"
                )
            else:
                lines.append(
                    f"  his last range of motion ({age:.0f} days old): rom last takes it, rom start records anew"
                )
        if self.last_model is None:
            lines.append("  no validated model in the records: identify and train as for a new pilot")
        else:
            rmse = "" if self.last_model.validation_rmse_nm is None else f" {self.last_model.validation_rmse_nm:.3f} Nm"
            lines.append(
                f"  his last model, {self.last_model.kind}{rmse}: identify validation, then model last re-validates it "
                "on this session's run (it is used only if it still passes)"
            )
        return lines


def _limits(row: RangeOfMotionRecord) -> IsbLimits:
    return IsbLimits(
        elevation=AngleRange(lower_deg=row.elevation_lower_deg, upper_deg=row.elevation_upper_deg),
        horizontal_rotation=AngleRange(
            lower_deg=row.horizontal_rotation_lower_deg, upper_deg=row.horizontal_rotation_upper_deg
        ),
        axial_rotation=AngleRange(lower_deg=row.axial_rotation_lower_deg, upper_deg=row.axial_rotation_upper_deg),
        elbow=AngleRange(lower_deg=row.elbow_lower_deg, upper_deg=row.elbow_upper_deg),
        horizontal_free_below_deg=row.horizontal_free_below_deg,
    )


def _last_validation_run(sessions: list[SessionRecord]) -> Path | None:
    """The stationary data of the pilot's most recent validation run still on disk (a session that ended
    before its own run, in ``operative_check`` say, leaves the one before it)."""
    for session in reversed(sessions):
        for data in session.datasets:
            run = data.run or ""
            if run.startswith("validation") and not data.path.endswith(".raw.npz") and Path(data.path).is_file():
                return Path(data.path)
    return None


def pilot_history(store: Store, named: str) -> PilotHistory:
    """What the records hold of the pilot ``named`` (a code, or a simulated scenario's pilot).

    Raises:
        RecordsError: ``named`` is not a code.
    """
    from sqlalchemy import select

    code, _ = pilot_code(named)
    with store.session() as orm:
        pilot = find_pilot(orm, code)
        if pilot is None:
            return PilotHistory(code, 0, None, None, None)
        sessions = pilot.sessions
        rom = orm.scalars(
            select(RangeOfMotionRecord)
            .where(RangeOfMotionRecord.pilot_id == pilot.id)
            .order_by(RangeOfMotionRecord.recorded_utc.desc(), RangeOfMotionRecord.id.desc())
        ).first()
        last_limits = None
        if rom is not None:
            session_id = rom.session.session_id if rom.session is not None else None
            last_limits = LastLimits(_limits(rom), session_id, rom.recorded_utc, rom.source)
        last_model = None
        for session in reversed(sessions):
            used = next((m for m in session.models if m.in_use and m.validated), None)
            if used is not None:
                last_model = LastModel(
                    Path(used.path),
                    used.sha256,
                    used.kind,
                    used.validation_rmse_nm,
                    session.session_id,
                    _last_validation_run(sessions),
                )
                break
        return PilotHistory(
            code, len(sessions), sessions[-1].started_utc if sessions else None, last_limits, last_model
        )


def check_model_file(store: Store, path: Path | str) -> None:
    """Refuse a model file the records hold with another SHA-256 (changed or replaced since it was recorded).

    A file the records do not know is not refused here (it is validated as any other).

    Raises:
        RecordsError: the file differs from its record (the session and the two hashes named), or is gone.
    """
    from sqlalchemy import select

    resolved = str(Path(path).resolve())
    with store.session() as orm:
        rows = orm.scalars(
            select(ModelRecord).where(ModelRecord.path == resolved).order_by(ModelRecord.recorded_utc.desc())
        ).all()
        if not rows:
            return
        if not Path(resolved).is_file():
            raise RecordsError(f"{path}: the records hold this model file, and it is gone")
        actual = file_sha256(resolved)
        if all(row.sha256 != actual for row in rows):
            recorded = rows[0]
            raise RecordsError(
                f"{path}: not the file the records hold (sha256 {actual[:12]}..., recorded {recorded.sha256[:12]}... "
                f"in session {recorded.session.session_id}); a model file that does not match its record is never "
                "used for compensation"
            )
