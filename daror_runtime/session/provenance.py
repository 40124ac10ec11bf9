"""Whose data: the session's robot and pilot, the provenance of what it records, and the validation gate's check.

A model drives the arm only once validated on data recorded from this pilot on this robot (issue 24,
docs/safety.md H26): the session's own validation run, or an earlier recording whose provenance file
(:mod:`daror_runtime.data.provenance`) names the same pilot and robot. On a simulated robot the
scenario is the robot and the pilot: ``DAROR-01 (simulated: exo_dummy_arm)`` and ``simulated pilot
(exo_dummy_arm)``, unless the settings name a pilot.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from daror_runtime.data.provenance import (
    Provenance,
    read_provenance,
    simulated_pilot,
    simulated_robot,
    write_provenance,
)
from daror_runtime.session.core import RequestRefusedError

if TYPE_CHECKING:
    from daror_runtime.session.core import SessionCore


def session_robot(core: SessionCore) -> str:
    """The robot this session runs: the description's name, or the simulated scenario's robot."""
    world = core.hal.world
    return simulated_robot(core.description.name, world.scenario) if world is not None else core.description.name


def session_pilot(core: SessionCore) -> str | None:
    """The pilot of this session: his code (the settings' or ``pilot CODE``), the simulated scenario's pilot, or None."""
    if core.signals.pilot is not None:
        return core.signals.pilot
    world = core.hal.world
    return simulated_pilot(world.scenario) if world is not None else None


def record_provenance(core: SessionCore, data_path: Path, run: str) -> Provenance:
    """Write the provenance of data this session recorded (an identification run's dataset or raw log).

    Raises:
        DataError: the data file cannot be read, or the provenance not written.
    """
    world = core.hal.world
    return write_provenance(
        data_path,
        "session",
        session_robot(core),
        session_pilot(core),
        session_id=core.session_id,
        run=run,
        scenario=world.scenario if world is not None else None,
    )


@dataclass(frozen=True)
class ValidationOrigin:
    """Where the data a model is validated on came from (shown in the status)."""

    path: Path
    kind: Literal["this session", "earlier recording"]
    description: str  # one line for the operator
    pilot: str | None
    robot: str
    session_id: str | None

    def as_dict(self) -> dict[str, str | None]:
        return {
            "path": str(self.path),
            "origin": self.kind,
            "description": self.description,
            "pilot": self.pilot,
            "robot": self.robot,
            "session_id": self.session_id,
        }


def validation_origin(core: SessionCore, validation_path: Path) -> ValidationOrigin:
    """Check that ``validation_path`` holds data recorded from this session's pilot on its robot.

    Accepted: this session's validation run, or a recording (``session`` or ``identify``) whose
    provenance names this session's pilot and robot and whose checksum matches the file.

    Raises:
        RequestRefusedError: data of another pilot or robot, synthetic data, data without
            provenance, or a session that names no pilot (the reason and what to do in one line).
        DataError: a provenance file that is malformed or belongs to other data.
    """
    robot, pilot = session_robot(core), session_pilot(core)
    own = core.signals.identification_saved.get("validation")
    if own is not None and Path(own).resolve() == Path(validation_path).resolve():
        return ValidationOrigin(
            Path(validation_path), "this session", f"this session's validation run ({core.session_id})",
            pilot, robot, core.session_id,
        )  # fmt: skip
    provenance = read_provenance(validation_path)
    if provenance is None:
        raise RequestRefusedError(
            f"{validation_path}: no provenance file beside it ({Path(validation_path).name}.provenance.json), so "
            "nothing says it was recorded from this pilot; validate on this session's validation run "
            "(identify validation) or on a recording of an earlier session of this pilot"
        )
    if not provenance.recorded:
        raise RequestRefusedError(
            f"{validation_path}: {provenance.describe()}: not a recording of the pilot; validate on this session's "
            "validation run (identify validation) or on a recording of an earlier session of this pilot"
        )
    if pilot is None:
        raise RequestRefusedError(
            f"{validation_path}: this session names no pilot (settings: pilot), so no earlier recording can be "
            "shown to be his; name the pilot in the session settings, or validate on this session's validation run"
        )
    if provenance.pilot != pilot or provenance.robot != robot:
        raise RequestRefusedError(
            f"{validation_path}: {provenance.describe()}; this session is pilot {pilot} on {robot}: a model is "
            "validated only on data of this pilot on this robot"
        )
    return ValidationOrigin(
        Path(validation_path), "earlier recording", provenance.describe(), provenance.pilot, provenance.robot,
        provenance.session_id,
    )  # fmt: skip
