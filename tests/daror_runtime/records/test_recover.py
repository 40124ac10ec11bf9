"""Issue 28, part 5: a session that died is not lost.

A console session killed with SIGKILL during its identification run leaves ``session.json`` as of its
last transition (kept current at every one) and the run's recording; ``daror sessions recover``
turns the recording into the raw log and the dataset, marks the session ended by a crash and
records it.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from daror_runtime.cli import main
from daror_runtime.data.load import load_dataset
from daror_runtime.data.provenance import read_provenance
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.records.schema import SessionRecord
from daror_runtime.records.store import open_store

ROOT = Path(__file__).resolve().parents[3]
SCRIPT = ROOT / "daror_runtime" / "console" / "scripts" / "session.txt"
#: Killed once the training run's recording holds this much (about 20 s of the run at 1 kHz).
KILL_AT_BYTES = 4_000_000


@pytest.mark.slow
@pytest.mark.subprocess
def test_a_session_killed_during_identification_is_recovered_and_recorded(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "s"
    recording = folder / ".identification_training.csv.rec"
    process = subprocess.Popen(
        [sys.executable, "-m", "daror_runtime.cli", "console", "--script", str(SCRIPT), "--out", str(folder)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 180.0
        while not (recording.is_file() and recording.stat().st_size > KILL_AT_BYTES):
            assert process.poll() is None, "the session ended before its identification run"
            assert time.monotonic() < deadline, "the identification run did not start"
            time.sleep(0.05)
        os.killpg(process.pid, signal.SIGKILL)  # kill -9: no handler, no ending, nothing written after
    finally:
        process.wait(10)
    assert process.returncode == -signal.SIGKILL
    # what the crash left: session.json as of the last transition (the runtime keeps it current)
    left = json.loads((folder / "session.json").read_text(encoding="utf-8"))
    assert left["state"] == "identification"
    assert left["ended"] is None
    assert "identification" in left["history"]["states_reached"]
    assert left["history"]["estop_tests"] >= 3  # the e-stop tests are tests, not the session's faults
    assert left["history"]["faults"] == []
    assert not (folder / "identification_training.csv").exists()

    db = tmp_path / "lab.db"
    assert main(["sessions", "recover", str(folder), "--db", str(db)]) == 0
    out = capsys.readouterr().out
    assert "raw log identification_training.raw.npz (" in out
    assert "session.json: marked ended by a crash in state identification" in out
    raw = load_dataset(folder / "identification_training.raw.npz")
    points = load_dataset(folder / "identification_training.csv")
    assert isinstance(raw, RawLog)
    assert isinstance(points, StationaryDataset)
    assert len(raw) >= KILL_AT_BYTES // (8 * 40)  # every complete row of the recording (rows of < 40 values)
    assert len(points) >= 3
    provenance = read_provenance(folder / "identification_training.csv")
    assert provenance is not None
    assert provenance.session_id == left["session_id"]
    assert provenance.pilot == "simulated pilot (exo_dummy_arm)"
    assert provenance.run == "training (recovered after a crash)"
    ended = json.loads((folder / "session.json").read_text(encoding="utf-8"))
    assert ended["ended_by_crash"] is True
    assert ended["ended_utc"] is not None
    store = open_store(f"sqlite:///{db}", create=False)
    try:
        with store.session() as orm:
            record = orm.query(SessionRecord).one()
            assert record.ended_by_crash
            assert record.final_state == "identification"
            assert {d.run for d in record.datasets} == {"training (recovered after a crash)"}
    finally:
        store.close()
    # again: nothing overwritten, one record
    before = (folder / "identification_training.csv").read_bytes()
    assert main(["sessions", "recover", str(folder), "--db", str(db)]) == 0
    out = capsys.readouterr().out
    assert "left as it is" in out
    assert "the session had ended; nothing to mark" in out
    assert (folder / "identification_training.csv").read_bytes() == before
