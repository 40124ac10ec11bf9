"""Issue 28: the lab's records in a real database (SQLite and PostgreSQL): pilots, sessions, models, data.

A session folder the runtime wrote is recorded with every file's hash; a changed or missing file is
found out; the pilots' verbs refuse what is not a code; a database at another schema is refused in
one line; two writers on one database lose no record.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import stat
from pathlib import Path
from typing import Any

import pytest

from daror_runtime.cli import main
from daror_runtime.data.checksum import file_sha256
from daror_runtime.data.provenance import write_provenance
from daror_runtime.records.index import record_session
from daror_runtime.records.pilots import add_pilot, pilot_record_lines, pilot_summaries, session_rows
from daror_runtime.records.schema import DatasetRecord, ModelRecord, SessionRecord
from daror_runtime.records.store import HEAD_REVISION, RecordsError, database_url, open_store
from daror_runtime.runtime import Runtime
from daror_runtime.session.settings import SessionSettings
from daror_runtime.testing import session_core
from hal.sim.backend import SimHal
from tests.conftest import Models


@pytest.fixture(scope="module")
def session_folder(tmp_path_factory: pytest.TempPathFactory, models: Models) -> Path:
    """A session's folder as the runtime leaves it: a model selected and validated, the support set, ended."""
    folder = tmp_path_factory.mktemp("lab") / "s1"
    runtime = Runtime(SimHal("exo_dummy_arm"), folder, settings=SessionSettings(dummy_arm=True))
    runtime.open()
    try:
        runtime.runner.run_ticks(1)
        runtime.select_model(models.good, models.validation)
        assert runtime.runner.run_until(
            lambda: runtime.model_in_use is not None and not session_core(runtime).jobs.pending, 2.0
        )
        runtime.wait(runtime.set_support(0.6))
        runtime.runner.pass_time(0.1)
        runtime.shutdown("the test ended")
    finally:
        runtime.close()
    shutil.copy(models.validation, folder / "identification_validation.csv")  # a run's data, as a session writes it
    write_provenance(
        folder / "identification_validation.csv",
        "session",
        "DAROR-01 (simulated: exo_dummy_arm)",
        "simulated pilot (exo_dummy_arm)",
        runtime.session_id,
        "validation",
        "exo_dummy_arm",
    )
    return folder


def _copy(folder: Path, tmp_path: Path) -> Path:
    target = tmp_path / "s1"
    shutil.copytree(folder, target)
    return target


def test_a_session_folder_is_recorded_with_its_pilot_files_and_course(
    db_url: str, session_folder: Path, tmp_path: Path, models: Models
) -> None:
    folder = _copy(session_folder, tmp_path)
    document = json.loads((folder / "session.json").read_text(encoding="utf-8"))
    # what the runtime now writes for the records
    assert document["pilot"] == "simulated pilot (exo_dummy_arm)"
    assert document["backend"] == "sim"
    assert document["history"]["states_reached"][0] == "startup"
    assert document["history"]["support_levels"] == [0.6]
    assert document["history"]["started_utc"] <= document["ended_utc"]
    store = open_store(db_url)
    try:
        first = record_session(store, folder)
        again = record_session(store, folder)  # idempotent: one record, updated
        assert first.new
        assert not again.new
        assert (first.pilot, first.datasets, first.models) == ("sim-exo_dummy_arm", 1, 1)
        with store.session() as orm:
            sessions = orm.query(SessionRecord).all()
            assert len(sessions) == 1
            record = sessions[0]
            assert record.session_id == document["session_id"]
            assert record.pilot.code == "sim-exo_dummy_arm"
            assert record.pilot.simulated
            assert record.backend == "sim"
            assert record.robot == "DAROR-01 (simulated: exo_dummy_arm)"
            assert record.support_levels == [0.6]
            assert record.ended_reason == "the test ended"
            assert record.started_utc is not None
            assert record.ended_utc is not None
            assert record.started_utc <= record.ended_utc
            assert record.started_utc.tzinfo is not None
            model = orm.query(ModelRecord).one()
            assert model.in_use
            assert model.validated
            assert model.kind == "plf+"
            assert model.path == str(models.good.resolve())  # a model of an earlier session, used in this one
            assert model.validation_rmse_nm == pytest.approx(document["model"]["validation_rmse_nm"])
            assert model.parameters  # the model file's parameters, for the pilot's trend
            data = orm.query(DatasetRecord).one()
            assert data.run == "validation"
            assert data.provenance["session_id"] == document["session_id"]
        lines = pilot_record_lines(store, "sim-exo_dummy_arm")
        assert lines[0] == "pilot sim-exo_dummy_arm: right arm (simulated)"
        assert not any("[changed]" in line or "[missing]" in line for line in lines)
        # a changed file and a missing one are found out by their hashes
        with (folder / "identification_validation.csv").open("a", encoding="utf-8") as f:
            f.write("\n")
        os.unlink(folder / "session.json")
        lines = pilot_record_lines(store, "sim-exo_dummy_arm")
        assert any(line.endswith("identification_validation.csv [changed]") for line in lines), lines
        summaries = pilot_summaries(store)
        assert [(s.code, s.sessions) for s in summaries] == [("sim-exo_dummy_arm", 1)]
        assert summaries[0].model is not None
        assert summaries[0].model.startswith("plf+ ")
        assert [row[1] for row in session_rows(store)] == ["sim-exo_dummy_arm"]
    finally:
        store.close()


def test_pilots_are_codes_never_duplicated(db_url: str) -> None:
    store = open_store(db_url)
    try:
        add_pilot(store, "P-007", "left", 2016, "ambulant")
        with pytest.raises(RecordsError, match="pilot P-007 is already in"):
            add_pilot(store, "P-007")
        for bad in ("Jean Dupont", "", "x" * 33, "-P1", "sim-exo"):
            with pytest.raises(RecordsError, match=f"pilot {bad!r}"):
                add_pilot(store, bad)
        with pytest.raises(RecordsError, match="--birth-year 1850"):
            add_pilot(store, "P-008", birth_year=1850)
        with pytest.raises(RecordsError, match="--arm 'both'"):
            add_pilot(store, "P-009", "both")
        assert [(s.code, s.arm_side, s.birth_year, s.sessions) for s in pilot_summaries(store)] == [
            ("P-007", "left", 2016, 0)
        ]
        with pytest.raises(RecordsError, match="pilot P-404: not in"):
            pilot_record_lines(store, "P-404")
    finally:
        store.close()


def _synthetic_session(folder: Path, session_id: str, pilot: str) -> Path:
    folder.mkdir(parents=True)
    document = {
        "session_id": session_id,
        "pilot": pilot,
        "state": "compensation",
        "t_s": 12.5,
        "robot": "DAROR-01",
        "backend": "can",
        "history": {"started_utc": "2026-11-29T09:00:00+00:00", "states_reached": ["startup"], "faults": [],
                    "support_levels": [0.5]},
        "ended_utc": "2026-11-29T09:30:00+00:00",
        "ended": {"reason": "quit"},
    }  # fmt: skip
    (folder / "session.json").write_text(json.dumps(document), encoding="utf-8")
    return folder


def _record_many(url: str, root: str, writer: int, count: int, barrier: Any) -> None:
    store = open_store(url)
    try:
        for n in range(count):
            barrier.wait(30)  # both writers record at the same moment
            # both writers meet each new pilot at once: the race for his code is the hard case
            folder = _synthetic_session(Path(root) / f"w{writer}-{n}", f"w{writer}-{n}", f"P-{n:02d}")
            record_session(store, folder)
    finally:
        store.close()


def test_two_writers_on_one_database_lose_no_record(db_url: str, tmp_path: Path) -> None:
    """Two processes (two consoles) record 15 sessions each, each pilot new to both at the same moment."""
    open_store(db_url).close()  # the schema first: two creators of one database is not the case tested
    context = multiprocessing.get_context("forkserver")
    barrier = context.Barrier(2)
    writers = [context.Process(target=_record_many, args=(db_url, str(tmp_path), w, 15, barrier)) for w in range(2)]
    for w in writers:
        w.start()
    for w in writers:
        w.join(120)
    exit_codes = [w.exitcode for w in writers]
    store = open_store(db_url)
    try:
        rows = session_rows(store)
        pilots = [s.code for s in pilot_summaries(store)]
    finally:
        store.close()
    assert exit_codes == [0, 0], f"{len(rows)} sessions recorded"
    assert len(rows) == 30
    assert pilots == [f"P-{n:02d}" for n in range(15)]


def test_a_database_at_another_schema_is_refused_in_one_line(db_url: str) -> None:
    from sqlalchemy import create_engine, text

    open_store(db_url).close()
    engine = create_engine(db_url)
    with engine.begin() as connection:
        connection.execute(text("UPDATE alembic_version SET version_num = '9999'"))
    engine.dispose()
    with pytest.raises(
        RecordsError, match=f"schema revision 9999, this runtime's is {HEAD_REVISION}; expected a runtime"
    ):
        open_store(db_url)


def test_a_foreign_database_is_not_taken_over(tmp_path: Path) -> None:
    import sqlite3

    path = tmp_path / "other.db"
    with sqlite3.connect(path) as connection:
        connection.execute("CREATE TABLE patients (name TEXT)")
    with pytest.raises(RecordsError, match=r"a database with tables \(patients, \.\.\.\) but no records schema"):
        open_store(f"sqlite:///{path}")


def test_a_new_sqlite_file_is_its_owner_s_only(tmp_path: Path) -> None:
    open_store(f"sqlite:///{tmp_path / 'daror.db'}").close()
    mode = stat.S_IMODE((tmp_path / "daror.db").stat().st_mode)
    assert mode == 0o600


def test_where_the_records_are(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DAROR_DB", raising=False)
    assert database_url(None, tmp_path) == f"sqlite:///{tmp_path.resolve() / 'daror.db'}"
    assert database_url("none", tmp_path) is None
    assert database_url("lab/daror.db", None) == f"sqlite:///{Path('lab/daror.db').resolve()}"
    monkeypatch.setenv("DAROR_DB", "postgresql://lab@db.example/daror")
    assert database_url(None, tmp_path) == "postgresql://lab@db.example/daror"
    assert database_url("sqlite:///x.db", tmp_path) == "sqlite:///x.db"


def test_the_commands(tmp_path: Path, session_folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    db = str(tmp_path / "lab.db")
    # a command that only reads does not create an empty database where none is
    assert main(["pilots", "list", "--db", db]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"daror pilots list: error: {db}: no records there; expected --db URL or DAROR_DB (a console "
                   "session records into daror.db beside its session folder)"]  # fmt: skip
    assert not Path(db).exists()
    assert main(["pilots", "add", "P-007", "--birth-year", "2016", "--db", db]) == 0
    assert main(["pilots", "add", "Jean Dupont", "--db", db]) == 2
    assert capsys.readouterr().err.strip().count("\n") == 0
    folder = _copy(session_folder, tmp_path)
    assert main(["sessions", "add", str(folder), "--pilot", "P-007", "--db", db]) == 0
    assert main(["pilots", "list", "--db", db]) == 0
    out = capsys.readouterr().out
    assert "P-007" in out
    assert "1 pilot(s)" in out
    assert main(["sessions", "list", "--pilot", "P-007", "--db", db]) == 0
    assert "1 session(s)" in capsys.readouterr().out
    assert main(["sessions", "list", "--pilot", "P-404", "--db", db]) == 2
    assert main(["db", "upgrade", "--db", db]) == 0
    assert f"schema {HEAD_REVISION} -> {HEAD_REVISION}" in capsys.readouterr().out
    assert main(["pilots", "list", "--db", "mysql://x@y/z"]) == 2
    assert "a mysql database; expected sqlite or postgresql" in capsys.readouterr().err


def test_a_console_session_records_itself_beside_its_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.delenv("DAROR_DB", raising=False)
    script = tmp_path / "s.txt"
    script.write_text("wait 0.2\nquit\n", encoding="utf-8")
    monkeypatch.setenv("DAROR_OPERATOR", "from the environment")
    assert main(["console", "--script", str(script), "--out", str(tmp_path / "s1"), "--operator", "JdV"]) == 0
    out = capsys.readouterr().out
    assert "records: session " in out
    assert f"of pilot sim-exo_dummy_arm in sqlite:///{tmp_path.resolve() / 'daror.db'}" in out
    store = open_store(f"sqlite:///{tmp_path / 'daror.db'}", create=False)
    try:
        assert [row[1] for row in session_rows(store)] == ["sim-exo_dummy_arm"]
        assert [row[3] for row in session_rows(store)] == ["JdV"]  # who ran it: --operator before the environment
    finally:
        store.close()
    assert json.loads((tmp_path / "s1" / "session.json").read_text(encoding="utf-8"))["operator"] == "JdV"
    # an operator's name the records cannot keep: one line, exit 2, nothing written
    assert main(["console", "--script", str(script), "--out", str(tmp_path / "s0"), "--operator", "a\nb"]) == 2
    assert "--operator 'a\\nb': expected initials or a staff code" in capsys.readouterr().err
    assert not (tmp_path / "s0").exists()
    # a database that cannot take it does not undo the session: the line says how to record it later
    assert main(["console", "--script", str(script), "--out", str(tmp_path / "s2"),
                 "--db", "postgresql+psycopg://nobody@127.0.0.1:9/none?connect_timeout=2"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "records: the session was not recorded: " in out
    assert f"record it later: daror sessions add {tmp_path / 's2'}" in out
    assert (tmp_path / "s2" / "session.json").is_file()
    # --db none: nothing recorded
    assert main(["console", "--script", str(script), "--out", str(tmp_path / "s3"), "--db", "none"]) == 0
    assert "records:" not in capsys.readouterr().out
    assert (
        json.loads((tmp_path / "s3" / "session.json").read_text(encoding="utf-8"))["operator"] == "from the environment"
    )


def test_a_pilot_s_report_and_export(
    db_url: str, session_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    first, second = _copy(session_folder, tmp_path / "a"), _copy(session_folder, tmp_path / "b")
    document = json.loads((second / "session.json").read_text(encoding="utf-8"))
    document["session_id"] = "second"  # a later session of the same pilot
    document["history"]["started_utc"] = "2030-01-01T09:00:00+00:00"
    document["model"]["validation_rmse_nm"] = 0.9
    document["model"]["validation_rmse_per_joint_nm"] = [0.1, 0.2, 0.3, 1.7]
    document["online"] = [  # what the runtime keeps of a compensation (issue 29)
        {"model": "PLF+ (model_plf_plus.json)", "rests": 3, "effort_at_rest_rms_nm": [0.1, 0.9, 0.2, 0.4],
         "level_delivered": 0.7, "last_rest": None, "moving_samples": [0, 0, 0, 0],
         "interaction_rms_nm": [None] * 4, "apparent_damping_nms_per_rad": [None] * 4}
    ]  # fmt: skip
    document["comparison"] = {"phase": "done", "verdict": {
        "models": ["PLF+ (model_plf_plus.json)", "A Priori (the robot description)"], "pairs": 6,
        "ratings": {"mean": {"PLF+ (model_plf_plus.json)": 7.9, "A Priori (the robot description)": 0.1},
                    "mean_difference": 7.8, "p_paired_t": 2e-8, "p_wilcoxon": 0.03},
        "preferred": "PLF+ (model_plf_plus.json)", "blocks": []}}  # fmt: skip
    (second / "session.json").write_text(json.dumps(document), encoding="utf-8")
    for folder in (first, second):
        assert main(["sessions", "add", str(folder), "--pilot", "P-007", "--db", db_url]) == 0
    assert main(["pilots", "report", "P-007", "--out", str(tmp_path / "report"), "--db", db_url]) == 0
    report = json.loads((tmp_path / "report" / "report.json").read_text(encoding="utf-8"))
    sessions = report["sessions"]
    assert [s["session_id"] for s in sessions][-1] == "second"  # oldest first
    assert [s["validation_rmse_nm"] for s in sessions][-1] == 0.9
    assert sessions[-1]["validation_rmse_per_joint_nm"][3] == 1.7
    assert sessions[0]["upper_arm_moment_nm"] > 1.0  # the model's upper arm holds the Dummy Arm (m g |p|, Nm)
    assert sessions[0]["support_levels"] == [0.6]
    # the model on the data it was validated on: his elbow gained nothing since (Nm/rad)
    assert abs(sessions[0]["elbow_gained_nm_per_rad"]) < 0.3
    assert sessions[0]["notes"] == []
    assert (tmp_path / "report" / "report.png").stat().st_size > 10_000
    assert "| second |" in (tmp_path / "report" / "report.md").read_text(encoding="utf-8")
    assert sessions[-1]["online"][0]["effort_at_rest_rms_nm"] == [0.1, 0.9, 0.2, 0.4]  # kept by the records
    assert sessions[0]["online"] == []
    assert sessions[-1]["comparison"]["preferred"] == "PLF+ (model_plf_plus.json)"
    assert "- second: blind comparison over 6 pairs: the pilot preferred PLF+" in (
        tmp_path / "report" / "report.md"
    ).read_text(encoding="utf-8")
    assert (
        "- second, PLF+ (model_plf_plus.json): 3 rests, his effort at rest RMS 0.10 0.90 0.20 0.40 Nm, "
        "support delivered 0.70" in (tmp_path / "report" / "report.md").read_text(encoding="utf-8")
    )

    out = tmp_path / "archive"
    assert main(["pilots", "export", "P-007", "--out", str(out), "--db", db_url]) == 0
    manifest = (out / "MANIFEST.sha256").read_text(encoding="utf-8").splitlines()
    assert any(line.endswith("files/second/session.json") for line in manifest)
    for line in manifest:
        digest, name = line.split("  ", 1)
        assert file_sha256(out / name) == digest
    assert {p.name for p in out.iterdir()} >= {"sessions.csv", "models.csv", "datasets.csv", "pilot.json", "files"}
    assert main(["pilots", "export", "P-007", "--out", str(out), "--db", db_url]) == 2  # never written over
    capsys.readouterr()
    (first / "identification_validation.csv").write_text("changed\n", encoding="utf-8")
    assert main(["pilots", "export", "P-007", "--out", str(tmp_path / "archive2"), "--db", db_url]) == 1
    problems = (tmp_path / "archive2" / "problems.txt").read_text(encoding="utf-8")
    assert "identification_validation.csv: changed since it was recorded" in problems
    # the report measures nothing on a file that is not the one recorded, and says why
    assert main(["pilots", "report", "P-007", "--out", str(tmp_path / "report"), "--db", db_url]) == 0
    first_again = json.loads((tmp_path / "report" / "report.json").read_text(encoding="utf-8"))["sessions"][0]
    assert first_again["elbow_gained_nm_per_rad"] is None
    assert first_again["elbow_stiffness_today_nm_per_rad"] is None
    assert "changed since it was recorded" in first_again["notes"][0]
    assert "changed since it was recorded" in (tmp_path / "report" / "report.md").read_text(encoding="utf-8")


def test_a_model_file_unlike_its_record_is_refused(db_url: str, session_folder: Path, tmp_path: Path) -> None:
    """Issue 28, part 6 (hazard H36): a model file the records hold with another hash is never used for compensation."""
    from daror_runtime.records.returning import check_model_file

    folder = _copy(session_folder, tmp_path)
    model = tmp_path / "model_plf_plus.json"
    document = json.loads((folder / "session.json").read_text(encoding="utf-8"))
    shutil.copy(document["model"]["path"], model)
    document["model"]["path"] = str(model)  # the model in use: this folder's copy
    (folder / "session.json").write_text(json.dumps(document), encoding="utf-8")
    store = open_store(db_url)
    try:
        record_session(store, folder)
        check_model_file(store, model)  # as recorded: accepted
        check_model_file(store, tmp_path / "unknown.json")  # not in the records: left to the gate
        edited = json.loads(model.read_text(encoding="utf-8"))
        edited["name"] = "PLF+ (edited)"
        model.write_text(json.dumps(edited), encoding="utf-8")
        with pytest.raises(RecordsError, match=r"not the file the records hold .* never used for compensation"):
            check_model_file(store, model)
        model.unlink()
        with pytest.raises(RecordsError, match="the records hold this model file, and it is gone"):
            check_model_file(store, model)
    finally:
        store.close()


def test_a_returning_pilot_s_model_is_offered_with_his_most_recent_validation_run(
    db_url: str, session_folder: Path, tmp_path: Path
) -> None:
    """His last session ended before its own validation run (in operative_check): the run before it validates
    his model for operative_check (D216)."""
    from daror_runtime.records.returning import pilot_history

    earlier, later = _copy(session_folder, tmp_path / "a"), _copy(session_folder, tmp_path / "b")
    for name in ("identification_validation.csv", "identification_validation.csv.provenance.json"):
        (later / name).unlink()
    document = json.loads((later / "session.json").read_text(encoding="utf-8"))
    document["session_id"] = "later"
    document["history"]["started_utc"] = "2030-01-01T09:00:00+00:00"
    (later / "session.json").write_text(json.dumps(document), encoding="utf-8")
    store = open_store(db_url)
    try:
        for folder in (earlier, later):
            record_session(store, folder, "P-007")
        last = pilot_history(store, "P-007").last_model
        assert last is not None
        assert last.session_id == "later"
        assert last.validation_file == (earlier / "identification_validation.csv").resolve()
    finally:
        store.close()
