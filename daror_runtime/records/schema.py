"""The records' tables (SQLAlchemy 2 declarative mapping); every change comes with a migration.

Pseudonymous by design: a pilot is a code (``P-007``), never a name, and his birth year, not his
date of birth; the lab's notes are free text the lab is responsible for. Times are UTC.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, ClassVar

from sqlalchemy import JSON, DateTime, Float, ForeignKey, Integer, String, Text, TypeDecorator, UniqueConstraint
from sqlalchemy.engine import Dialect
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

from daror_runtime.records.codes import PILOT_CODE_PATTERN

__all__ = [
    "PILOT_CODE_PATTERN",
    "Base",
    "DatasetRecord",
    "ModelRecord",
    "PilotRecord",
    "RangeOfMotionRecord",
    "SessionRecord",
    "UtcDateTime",
]


class UtcDateTime(TypeDecorator[datetime]):
    """A timezone-aware UTC time on every backend (SQLite keeps no zone: it is stored and read as UTC)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError(f"{value!r}: a naive time; the records hold UTC times with their zone")
        return value.astimezone(UTC)

    def process_result_value(self, value: datetime | None, dialect: Dialect) -> datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


class Base(DeclarativeBase):
    type_annotation_map: ClassVar[dict[Any, Any]] = {datetime: UtcDateTime, dict[str, Any]: JSON, list[Any]: JSON}


class PilotRecord(Base):
    """A pilot: a code, the arm the robot supports, the birth year; never a name."""

    __tablename__ = "pilots"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    code: Mapped[str] = mapped_column(String(32), unique=True)
    arm_side: Mapped[str] = mapped_column(String(5), default="right")  # right | left
    birth_year: Mapped[int | None] = mapped_column(Integer, default=None)
    notes: Mapped[str] = mapped_column(Text, default="")
    simulated: Mapped[bool] = mapped_column(default=False)  # a simulated scenario's pilot (scripts, the demo)
    created_utc: Mapped[datetime]

    sessions: Mapped[list[SessionRecord]] = relationship(back_populates="pilot", order_by="SessionRecord.started_utc")


class SessionRecord(Base):
    """One session: when, on which robot and backend, who operated, what it reached, how it ended."""

    __tablename__ = "sessions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    session_id: Mapped[str] = mapped_column(String(64), unique=True)  # the runtime's id (session.json)
    pilot_id: Mapped[int] = mapped_column(ForeignKey("pilots.id"))
    started_utc: Mapped[datetime | None]
    ended_utc: Mapped[datetime | None]
    ended_reason: Mapped[str | None] = mapped_column(Text, default=None)
    ended_by_crash: Mapped[bool] = mapped_column(default=False)
    operator: Mapped[str | None] = mapped_column(String(64), default=None)
    robot: Mapped[str] = mapped_column(String(128))
    backend: Mapped[str] = mapped_column(String(64))
    directory: Mapped[str] = mapped_column(Text)
    final_state: Mapped[str] = mapped_column(String(64))
    robot_time_s: Mapped[float] = mapped_column(Float)
    states_reached: Mapped[list[Any]]  # state names, in the order first reached
    faults: Mapped[list[Any]]  # "kind: message" of each fault the session saw
    support_levels: Mapped[list[Any]]  # the support levels delivered (0-1)
    session_json_sha256: Mapped[str | None] = mapped_column(String(64), default=None)
    recorded_utc: Mapped[datetime]
    #: the online indicators per model that compensated (issue 29, docs/online.md; migration 0003)
    online: Mapped[list[Any] | None] = mapped_column(JSON, default=None)
    #: its blind comparison's verdict, if it made one (issue 29, part 3; migration 0003)
    comparison: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)

    pilot: Mapped[PilotRecord] = relationship(back_populates="sessions")
    datasets: Mapped[list[DatasetRecord]] = relationship(back_populates="session", order_by="DatasetRecord.id")
    models: Mapped[list[ModelRecord]] = relationship(back_populates="session", order_by="ModelRecord.id")
    ranges_of_motion: Mapped[list[RangeOfMotionRecord]] = relationship(back_populates="session")


class RangeOfMotionRecord(Base):
    """A pilot's range of motion in ISB angles (deg): recorded in a session, or entered from a file."""

    __tablename__ = "ranges_of_motion"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    pilot_id: Mapped[int] = mapped_column(ForeignKey("pilots.id"))
    session_id: Mapped[int | None] = mapped_column(ForeignKey("sessions.id"), default=None)
    source: Mapped[str] = mapped_column(String(16))  # recorded | entered
    path: Mapped[str | None] = mapped_column(Text, default=None)  # the limits file
    sha256: Mapped[str | None] = mapped_column(String(64), default=None)
    elevation_lower_deg: Mapped[float] = mapped_column(Float)
    elevation_upper_deg: Mapped[float] = mapped_column(Float)
    horizontal_rotation_lower_deg: Mapped[float] = mapped_column(Float)
    horizontal_rotation_upper_deg: Mapped[float] = mapped_column(Float)
    axial_rotation_lower_deg: Mapped[float] = mapped_column(Float)
    axial_rotation_upper_deg: Mapped[float] = mapped_column(Float)
    elbow_lower_deg: Mapped[float] = mapped_column(Float)
    elbow_upper_deg: Mapped[float] = mapped_column(Float)
    horizontal_free_below_deg: Mapped[float] = mapped_column(Float)
    recorded_utc: Mapped[datetime]

    session: Mapped[SessionRecord | None] = relationship(back_populates="ranges_of_motion")


class ModelRecord(Base):
    """A model file a session trained or used: its hash, its data, how it validated, who approved it."""

    __tablename__ = "models"
    __table_args__ = (UniqueConstraint("session_id", "path"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    pilot_id: Mapped[int] = mapped_column(ForeignKey("pilots.id"))
    session_id: Mapped[int] = mapped_column(ForeignKey("sessions.id"))
    kind: Mapped[str] = mapped_column(String(32))
    path: Mapped[str] = mapped_column(Text)
    sha256: Mapped[str] = mapped_column(String(64))
    training_path: Mapped[str | None] = mapped_column(Text, default=None)
    training_sha256: Mapped[str | None] = mapped_column(String(64), default=None)
    validation_path: Mapped[str | None] = mapped_column(Text, default=None)
    validation_rmse_nm: Mapped[float | None] = mapped_column(Float, default=None)
    # per joint (Nm, 4): the elbow's rises first as his stiffness outgrows a model (migration 0002)
    validation_rmse_per_joint_nm: Mapped[list[Any] | None] = mapped_column(JSON, default=None)
    validated: Mapped[bool] = mapped_column(default=False)
    in_use: Mapped[bool] = mapped_column(default=False)  # the model the session ended with
    approved_by: Mapped[str | None] = mapped_column(Text, default=None)
    closed_path: Mapped[str | None] = mapped_column(Text, default=None)  # the closed-path test's verdict
    parameters: Mapped[dict[str, Any]]  # physically meaningful parameters (first moments, stiffness), SI
    recorded_utc: Mapped[datetime]

    session: Mapped[SessionRecord] = relationship(back_populates="models")


class DatasetRecord(Base):
    """A data file a session wrote (stationary points or a raw log), with its provenance."""

    __tablename__ = "datasets"
    __table_args__ = (UniqueConstraint("session_id", "path"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    pilot_id: Mapped[int] = mapped_column(ForeignKey("pilots.id"))
    session_id: Mapped[int] = mapped_column(ForeignKey("sessions.id"))
    run: Mapped[str | None] = mapped_column(String(32), default=None)  # training | validation
    path: Mapped[str] = mapped_column(Text)
    sha256: Mapped[str] = mapped_column(String(64))
    recorded_utc: Mapped[datetime | None]
    provenance: Mapped[dict[str, Any]]

    session: Mapped[SessionRecord] = relationship(back_populates="datasets")
