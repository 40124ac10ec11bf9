"""Issue 28, part 3 and 6: a returning pilot is ready in minutes, with his model re-validated.

A first session of pilot P-007 (the whole protocol, PLF+ trained) is recorded; his second session
takes his last limits and his last model from the records and reaches compensation after one
validation run, with the model re-validated on it. A model file changed since the records hold it
is refused for compensation.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from daror_runtime.cli import main
from daror_runtime.records.pilots import pilot_record_lines
from daror_runtime.records.returning import pilot_history
from daror_runtime.records.store import RecordsError, open_store

ROOT = Path(__file__).resolve().parents[3]
SCRIPTS = ROOT / "daror_runtime" / "console" / "scripts"
SETTINGS = ROOT / "tests" / "data" / "hil_settings.yaml"  # every 12th waypoint, the Dummy Arm installed


def first_session_script(folder: Path, code: str) -> Path:
    """The shipped full session with the pilot named in settings."""
    text = (SCRIPTS / "session.txt").read_text(encoding="utf-8")
    named = text.replace("expect state settings\n", f"expect state settings\npilot {code}\nexpect accepted\n", 1)
    assert named != text
    path = folder / f"first_{code}.txt"
    path.write_text(named, encoding="utf-8")
    return path


def returning_script(folder: Path, code: str) -> Path:
    text = (SCRIPTS / "returning_pilot.txt").read_text(encoding="utf-8").replace("pilot P-007", f"pilot {code}")
    path = folder / f"returning_{code}.txt"
    path.write_text(text, encoding="utf-8")
    return path


def _console(script: Path, out: Path, db: str) -> int:
    return main(["console", "--script", str(script), "--settings", str(SETTINGS), "--out", str(out), "--db", db])


@pytest.mark.slow
def test_a_returning_pilot_reaches_compensation_with_his_model_re_validated(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], db_url: str
) -> None:
    db = db_url
    assert _console(first_session_script(tmp_path, "P-007"), tmp_path / "s1", db) == 0
    first_out = capsys.readouterr().out
    assert "pilot P-007: new to the records (no earlier session)" in first_out
    first = json.loads((tmp_path / "s1" / "session.json").read_text(encoding="utf-8"))
    assert first["state"] == "compensation"
    assert first["pilot"] == "P-007"

    assert _console(returning_script(tmp_path, "P-007"), tmp_path / "s2", db) == 0
    out = capsys.readouterr().out
    assert "pilot P-007: returning, 1 earlier session(s)" in out
    assert "his last range of motion (0 days old): rom last takes it" in out
    model_file = tmp_path.resolve() / "s1" / "model_plf_plus.json"
    first_id = first["session_id"]
    # in rom_limits, for operative_check: validated on his last session's run; in identification: on this one's
    assert (
        f"his last model: {model_file} (plf+, session {first_id}), validated on his validation run of session {first_id}"
        in out
    )
    assert f"his last model: {model_file} (plf+, session {first_id}), validated on this session's validation run" in out
    second = json.loads((tmp_path / "s2" / "session.json").read_text(encoding="utf-8"))
    assert second["state"] == "compensation"
    assert second["faults"] == []
    model = second["model"]
    assert model["path"] == str(tmp_path.resolve() / "s1" / "model_plf_plus.json")  # the first session's file
    assert model["validated"] is True
    assert model["validation_data"] == f"this session's validation run ({second['session_id']})"
    for angle, (lower, upper) in first["isb_limits_deg"].items():  # his limits, as the limits file keeps them (0.1 deg)
        assert second["isb_limits_deg"][angle] == pytest.approx([lower, upper], abs=0.051)
    assert "training" not in second["identification_saved"]  # no training run: minutes, not a quarter hour
    assert second["t_s"] < 0.6 * first["t_s"], (second["t_s"], first["t_s"])
    store = open_store(db, create=False)
    try:
        history = pilot_history(store, "P-007")
        assert history.sessions == 2
        assert history.last_model is not None
        assert history.last_model.session_id == second["session_id"]  # the model in use, re-validated there
        lines = pilot_record_lines(store, "P-007")
        assert sum("in use" in line for line in lines) == 2
    finally:
        store.close()

    # part 6: the model file changed since the records hold it is refused for compensation
    document = json.loads(model_file.read_text(encoding="utf-8"))
    document["name"] = "PLF+ (edited)"
    model_file.write_text(json.dumps(document), encoding="utf-8")
    store = open_store(db, create=False)
    try:
        from daror_runtime.records.returning import check_model_file

        with pytest.raises(RecordsError, match=r"not the file the records hold .* never used for compensation"):
            check_model_file(store, model_file)
    finally:
        store.close()
    assert _console(returning_script(tmp_path, "P-007"), tmp_path / "s3", db) == 1  # its model line fails
    captured = capsys.readouterr()
    assert "not the file the records hold" in captured.out + captured.err, captured.out[-2000:]
    third = json.loads((tmp_path / "s3" / "session.json").read_text(encoding="utf-8"))
    assert third["model"] is None  # the edited file never supported him
    assert third["state"] == "rom_limits"  # refused where it was first asked for


@pytest.mark.slow
def test_a_returning_pilot_s_model_that_no_longer_fits_him_is_withdrawn(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """His elbow springs stiffened (x1.3); his last model, approved for operative_check on his last session's
    run, fails on this session's run: its approval is withdrawn and compensation is not reached with it."""
    import yaml

    base = yaml.safe_load((ROOT / "hal" / "sim" / "scenarios" / "exo_dummy_arm.yaml").read_text(encoding="utf-8"))
    arm = base["dummy_arm"]
    scenarios = []
    for session, scale in ((1, 1.0), (2, 1.3)):
        for spring in arm["elbow_springs"]:
            spring["stiffness_nm_per_rad"] = 2.84 * scale
        path = tmp_path / f"s{session}.yaml"
        path.write_text(yaml.safe_dump({"extends": "exo_dummy_arm", "name": "pilot_p_008", "dummy_arm": arm}))
        scenarios.append(path)
    settings = tmp_path / "settings.yaml"  # his first model validates at 0.42 Nm; 0.6 Nm is the lab's limit
    settings.write_text("dummy_arm: true\nmax_validation_rmse_nm: 0.6\nidentification:\n  waypoint_stride: 12\n")
    db = str(tmp_path / "lab.db")

    def console(script: Path, out: str, scenario: Path) -> int:
        return main(["console", "--script", str(script), "--settings", str(settings), "--scenario", str(scenario),
                     "--out", str(tmp_path / out), "--db", db])  # fmt: skip

    assert console(first_session_script(tmp_path, "P-008"), "s1", scenarios[0]) == 0
    capsys.readouterr()
    script = returning_script(tmp_path, "P-008")
    text = script.read_text(encoding="utf-8")  # his range recorded anew: his arm rests elsewhere now
    script.write_text(
        text.replace("rom last\n", "rom start\nsim pilot sweep\nwait until still timeout 600\nrom stop\n")
    )
    assert console(script, "s2", scenarios[1]) == 1  # the advance out of identification is refused
    captured = capsys.readouterr()
    out = captured.out + captured.err
    assert "failed validation: RMSE" in out
    assert "its earlier approval in this session is withdrawn" in out
    second = json.loads((tmp_path / "s2" / "session.json").read_text(encoding="utf-8"))
    assert second["state"] == "identification"
    assert second["model"] is None
    assert second["model_refused"]["validation_rmse_nm"] > 0.6


def _heavier_arm(tmp_path: Path, session: int, spring_scale: float) -> Path:
    """Pilot P-102's arm (the heavier arm of ``exo_heavy_arm``), his elbow springs x``spring_scale``."""
    import yaml

    base = yaml.safe_load((ROOT / "hal" / "sim" / "scenarios" / "exo_heavy_arm.yaml").read_text(encoding="utf-8"))
    arm = base["dummy_arm"]
    for spring in arm["elbow_springs"]:
        spring["stiffness_nm_per_rad"] = round(spring["stiffness_nm_per_rad"] * spring_scale, 4)
    path = tmp_path / f"p102_s{session}.yaml"
    path.write_text(yaml.safe_dump({"extends": "exo_heavy_arm", "name": "pilot_p_102", "dummy_arm": arm}))
    return path


ESTOP_ON_THE_REST = (
    "sim rest here\nsim estop operator on\nwait 0.3\nsim estop operator off\nwait 1\nsim rest off\nwait 1\nadvance\n"
)


@pytest.mark.slow
def test_a_changed_pilot_s_e_stop_test_on_the_armrest_keeps_his_arm_in_his_range(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """D217: the heavier arm, his springs x1.3 since his first session, his range recorded anew. The
    shipped script tests the e-stop in operative_check with his forearm on the armrest and reaches
    compensation with no fault. Without the rest, the drop with the torque off takes his elbow beyond
    his range (an ISB fault latched, the advance refused); the guide's way out (wait while the
    reaction lowers his arm to its rest, acknowledge) leads on to compensation."""
    db = str(tmp_path / "lab.db")

    def console(script: Path, out: str, scenario: Path) -> int:
        return main(["console", "--script", str(script), "--settings", str(SETTINGS), "--scenario", str(scenario),
                     "--out", str(tmp_path / out), "--db", db])  # fmt: skip

    assert console(first_session_script(tmp_path, "P-102"), "s1", _heavier_arm(tmp_path, 1, 1.0)) == 0
    stiffer = _heavier_arm(tmp_path, 2, 1.3)
    script = returning_script(tmp_path, "P-102")
    shipped = script.read_text(encoding="utf-8").replace(
        "rom last\n", "rom start\nsim pilot sweep\nwait until still timeout 600\nrom stop\n"
    )
    assert ESTOP_ON_THE_REST in shipped  # the shipped script's procedure
    script.write_text(shipped)
    assert console(script, "s2", stiffer) == 0
    on_the_rest = json.loads((tmp_path / "s2" / "session.json").read_text(encoding="utf-8"))
    assert on_the_rest["state"] == "compensation"
    assert on_the_rest["history"]["faults"] == []  # the e-stop tests are not faults of the session

    # without the rest: the drop latches an ISB fault on the elbow; the advance is refused until the
    # reaction has lowered his arm to its rest and the operator acknowledged
    script.write_text(
        shipped.replace(
            ESTOP_ON_THE_REST,
            "sim estop operator on\nwait 0.3\nsim estop operator off\nwait 2\nadvance\nexpect refused\n"
            "expect state operative_check\nwait 8\nack\nexpect accepted\nwait 1\nadvance\n",
        )
    )
    capsys.readouterr()
    assert console(script, "s3", stiffer) == 0
    out = capsys.readouterr().out
    assert "fault: isb_limit: elbow" in out
    assert "unmet: no_active_faults" in out or "advance: refused" in out
    dropped = json.loads((tmp_path / "s3" / "session.json").read_text(encoding="utf-8"))
    assert dropped["state"] == "compensation"
    assert dropped["history"]["faults"]
    assert all(fault.startswith("isb_limit: elbow") for fault in dropped["history"]["faults"])

    # his report: the model is session 1's (its stiffness unchanged), today's stiffness follows his
    # springs: x1.3 of exo_heavy_arm's 3.6 Nm/rad is 1.08 Nm/rad more than at his first session
    from daror_runtime.records.report import pilot_trend

    with open_store(f"sqlite:///{db}", create=False) as store:
        trend = pilot_trend(store, "P-102")
    assert len(trend) == 3
    assert trend[1].elbow_stiffness_nm_per_rad == trend[0].elbow_stiffness_nm_per_rad  # re-validated, not retrained
    first, *stiffer_sessions = (t.elbow_stiffness_today_nm_per_rad for t in trend)
    assert first is not None
    assert abs(first - 3.6) < 0.5
    for today in stiffer_sessions:
        assert today is not None
        assert today - first == pytest.approx(0.3 * 3.6, rel=0.15)
