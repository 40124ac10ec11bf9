"""Where a dataset came from: a provenance file beside it (issue 24).

A model is validated for compensation only on data recorded from *this pilot* on *this robot*
(docs/safety.md H26). Which pilot and robot a data file holds is not in its numbers, so every data
file the runtime writes gets a small JSON document beside it, ``<file>.provenance.json``:

* ``source``: how the data was made: ``session`` (an identification run of an operator's session),
  ``identify`` (``daror identify``: the closed-loop protocol on a simulated robot), ``simulate``
  (``daror simulate static``: synthetic points from the simulator's statics, no robot, no loop);
* ``robot``: the robot it was recorded on (``DAROR-01``; ``DAROR-01 (simulated: exo_dummy_arm)``
  for a simulated one);
* ``pilot``: the pilot's code in the lab's records (``P-007``: no name), ``simulated pilot
  (exo_dummy_arm)`` on a simulated robot, or None when nobody said;
* ``session_id``, ``run`` (``training`` / ``validation``), ``recorded_utc``, ``scenario``;
* ``sha256`` of the data file: a provenance file moved beside other data does not vouch for it.

Data from elsewhere (another lab's files, a spreadsheet) has no provenance file: it can still be
analysed offline (``daror fit``, ``evaluate``, ``residual``), but a session does not validate a
model on it. A sidecar rather than a header: the CSV, ``.npz`` and ``.mat`` readers stay as they
are, and other tools (a spreadsheet, MATLAB) read the data file unchanged (D127).
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from daror_runtime.data.checksum import file_sha256
from daror_runtime.errors import DataError
from daror_runtime.util.atomic import write_text_atomic
from hal.files import read_text_bounded
from hal.yamlfile import Integer, format_validation_error

#: What is appended to a data file's name for its provenance file.
PROVENANCE_SUFFIX = ".provenance.json"
#: A provenance file is a few hundred bytes; a bigger one is not ours.
PROVENANCE_MAX_BYTES = 64 * 1024
#: Sources whose data was recorded by the robot's own loop and sensors (what may validate a model).
RECORDED_SOURCES = ("session", "identify")


class Provenance(BaseModel):
    """Who and what a data file holds (see the module's docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    format: Literal["daror-provenance"] = "daror-provenance"
    format_version: Integer = 1
    source: Literal["session", "identify", "simulate"]
    robot: str = Field(min_length=1)
    pilot: str | None = None
    session_id: str | None = None
    run: str | None = None
    scenario: str | None = None
    recorded_utc: str
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")

    @property
    def recorded(self) -> bool:
        """True when the robot's loop and sensors recorded the data (not synthetic points)."""
        return self.source in RECORDED_SOURCES

    def describe(self) -> str:
        """One line for a person: what, whose, where, when."""
        what = {
            "session": "recorded in session " + (self.session_id or "?"),
            "identify": "recorded by daror identify",
            "simulate": "synthetic points of the simulator (daror simulate static)",
        }[self.source]
        run = f" ({self.run} run)" if self.run else ""
        pilot = self.pilot or "no pilot named"
        return f"{what}{run}: pilot {pilot}, robot {self.robot}, {self.recorded_utc}"


def simulated_robot(robot_name: str, scenario: str) -> str:
    """The robot a simulated scenario stands for (what its recordings' provenance names)."""
    return f"{robot_name} (simulated: {scenario})"


def simulated_pilot(scenario: str) -> str:
    """The pilot a simulated scenario stands for."""
    return f"simulated pilot ({scenario})"


def provenance_path(data_path: Path | str) -> Path:
    """Where the provenance of ``data_path`` is: ``<name>.provenance.json`` beside it."""
    path = Path(data_path)
    return path.with_name(path.name + PROVENANCE_SUFFIX)


def write_provenance(
    data_path: Path | str,
    source: Literal["session", "identify", "simulate"],
    robot: str,
    pilot: str | None = None,
    session_id: str | None = None,
    run: str | None = None,
    scenario: str | None = None,
) -> Provenance:
    """Write the provenance of a data file just written (atomically); returns it.

    Raises:
        DataError: the data file cannot be read (its checksum), or the provenance not written.
    """

    provenance = Provenance(
        source=source,
        robot=robot,
        pilot=pilot,
        session_id=session_id,
        run=run,
        scenario=scenario,
        recorded_utc=datetime.now(UTC).isoformat(timespec="seconds"),
        sha256=file_sha256(data_path),
    )
    write_text_atomic(provenance_path(data_path), provenance.model_dump_json(indent=2) + "\n")
    return provenance


def read_provenance(data_path: Path | str) -> Provenance | None:
    """The provenance of ``data_path``; None when it has none (data from elsewhere).

    Raises:
        DataError: a provenance file that is not one (malformed JSON, a field missing or wrong,
            named in the message), or one that belongs to other data (its checksum differs).
    """

    path = provenance_path(data_path)
    if not path.exists():
        return None
    text = read_text_bounded(path, DataError, PROVENANCE_MAX_BYTES, "provenance file")
    try:
        provenance = Provenance.model_validate(json.loads(text))
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}: not a provenance file: malformed JSON at line {exc.lineno}") from None
    except ValidationError as exc:
        raise DataError(f"not a provenance file: {format_validation_error(str(path), exc)}") from None
    if provenance.sha256 != file_sha256(data_path):
        raise DataError(f"{path}: belongs to other data than {Path(data_path).name} (its checksum differs)")
    return provenance
