"""A session that died is not lost: what survived a crash turned into data and a session record.

``kill -9`` (or a power cut) of a console session leaves its folder as it was at that moment: the
hidden recordings of an identification run under way (``.identification_KIND.csv.rec``: every
complete row, docs/recorder.md), ``audit.jsonl``, and ``session.json`` as of the last transition
(the runtime keeps it current, D213). :func:`recover_session` turns each recording into the raw
log and, when the run got far enough to hold still somewhere, the stationary dataset (reduced from
the raw log alone: the protocol's own stop windows died with the process), each with its provenance;
it marks ``session.json`` as ended by a crash (kept, rewritten atomically) and returns what it did.
Nothing is overwritten: a file that is already there is left as it is and said so. Design time.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import structlog

from daror_runtime.data.load import RAW_LOG_SUFFIX, raw_log_path, write_dataset
from daror_runtime.data.provenance import write_provenance
from daror_runtime.data.recording_reader import recording_to_raw_log
from daror_runtime.data.stationary import ReductionSettings, reduce_to_stationary
from daror_runtime.errors import DataError
from daror_runtime.records.index import read_session_json
from daror_runtime.records.store import RecordsError
from daror_runtime.session.history import utc_now
from daror_runtime.util.atomic import write_text_atomic

log = structlog.get_logger(__name__)

#: A recovered run's stops averaged into 3 points each, as the protocol's own reduction gives them
#: (its stop windows are not known after a crash: the stops are found from the velocity alone).
RECOVERY_REDUCTION = ReductionSettings(per_stop="mean", points_per_stop=3)
#: What the recorder's file of an identification run is called: ``.identification_KIND.csv.rec``.
RECORDING_GLOB = ".identification_*.rec"


@dataclass
class Recovered:
    """What :func:`recover_session` found and wrote."""

    session_id: str
    lines: list[str] = field(default_factory=list)  # one per thing done or left, for the operator
    written: list[Path] = field(default_factory=list)
    already_ended: bool = False  # session.json said the session had ended: nothing to mark


def _last_audit_time(directory: Path) -> str | None:
    """The time of the audit trail's last complete event (UTC, ISO 8601), or None."""
    audit = directory / "audit.jsonl"
    if not audit.is_file():
        return None
    last = None
    with audit.open("rb") as handle:
        for raw in handle:
            try:
                event = json.loads(raw)
            except ValueError:
                continue  # the line being written when the process died
            if isinstance(event, dict) and isinstance(event.get("timestamp"), str):
                last = event["timestamp"]
    return last


def recover_session(directory: Path | str) -> Recovered:
    """Turn what survived of the session in ``directory`` into data and mark it ended by a crash.

    Raises:
        RecordsError: no ``session.json`` (the folder is not a session's).
        DataError: a recording too damaged to read (named); what was recovered before stays.
    """
    directory = Path(directory).resolve()
    document = read_session_json(directory)
    result = Recovered(document["session_id"])
    for recording in sorted(directory.glob(RECORDING_GLOB)):
        _recover_recording(recording, document, result)
    if document.get("ended") is not None:
        result.already_ended = True
        result.lines.append("session.json: the session had ended; nothing to mark")
        return result
    last_alive = _last_audit_time(directory) or document.get("updated_utc")
    document["ended"] = {
        "reason": "the session's process died (recovered with daror sessions recover)",
        "state": document.get("state"),
    }
    document["ended_by_crash"] = True
    document["ended_utc"] = last_alive
    document["recovered_utc"] = utc_now()
    write_text_atomic(directory / "session.json", json.dumps(document, indent=2, default=str) + "\n")
    result.lines.append(
        f"session.json: marked ended by a crash in state {document.get('state')} (last alive {last_alive or 'unknown'})"
    )
    log.info("session recovered after a crash", session_id=result.session_id, state=document.get("state"))
    return result


def _recover_recording(recording: Path, document: dict[str, Any], result: Recovered) -> None:
    name = recording.name[1 : -len(".rec")]  # .identification_training.csv.rec -> identification_training.csv
    dataset = recording.with_name(name)
    raw_path = raw_log_path(dataset, RAW_LOG_SUFFIX)
    run = name.removeprefix("identification_").split(".")[0]
    if raw_path.exists() or dataset.exists():
        result.lines.append(f"{recording.name}: {raw_path.name} or {dataset.name} is already there; left as it is")
        return
    raw = recording_to_raw_log(recording, drop_nan_rows=True)
    write_dataset(raw_path, raw)
    _provenance(raw_path, document, run)
    result.written.append(raw_path)
    seconds = float(raw.t_s[-1] - raw.t_s[0]) if len(raw) > 1 else 0.0
    try:
        points = reduce_to_stationary(raw, RECOVERY_REDUCTION)
    except DataError as exc:
        result.lines.append(
            f"{recording.name}: raw log {raw_path.name} ({len(raw)} samples, {seconds:.1f} s); no dataset: {exc}"
        )
        return
    write_dataset(dataset, points)
    _provenance(dataset, document, run)
    result.written.append(dataset)
    result.lines.append(
        f"{recording.name}: raw log {raw_path.name} ({len(raw)} samples, {seconds:.1f} s) and dataset "
        f"{dataset.name} ({len(points)} stationary points, reduced from the raw log: the run did not finish)"
    )


def _provenance(path: Path, document: dict[str, Any], run: str) -> None:
    robot = document.get("robot")
    if not robot:
        raise RecordsError(f"{path}: session.json names no robot; expected one written by this runtime")
    write_provenance(
        path,
        "session",
        str(robot),
        document.get("pilot"),
        session_id=document["session_id"],
        run=f"{run} (recovered after a crash)",
        scenario=None,
    )
