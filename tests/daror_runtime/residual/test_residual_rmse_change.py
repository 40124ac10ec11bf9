"""Issue 24, defect 9: ``daror residual`` words a change of RMSE as a change (both RMSEs, then the signed
difference), never as a negative RMSE ("validation RMSE -0.2009 Nm")."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from daror_runtime.cli import main
from daror_runtime.data.load import write_dataset
from daror_runtime.residual.report import rmse_change
from hal.sim.scenario import load_scenario
from hal.sim.static_dataset import generate_stationary
from tests.conftest import as_dataset

#: Any RMSE shown as a negative number: the wording this issue removes.
NEGATIVE_RMSE = re.compile(r"RMSE\s+-\d")


def test_a_change_shows_both_rmses_and_the_signed_difference() -> None:
    assert rmse_change(0.62, 0.4191) == "validation RMSE 0.6200 -> 0.4191 Nm (-0.2009 Nm)"
    assert rmse_change(0.40, 0.45, digits=2) == "validation RMSE 0.40 -> 0.45 Nm (+0.05 Nm)"


@pytest.mark.slow
def test_the_command_and_the_report_word_the_found_effects_change_as_a_change(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scenario = load_scenario("residual_direction_offset")
    train, validate = tmp_path / "train.csv", tmp_path / "validate.csv"
    write_dataset(train, as_dataset(generate_stationary(scenario, "training")))
    write_dataset(validate, as_dataset(generate_stationary(scenario, "validation")))
    out = tmp_path / "report"
    assert main(["residual", "--train", str(train), "--validate", str(validate), "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    before, after = summary["rmse_before"], summary["rmse_after"]
    (effect,) = summary["effects"]  # one effect: its change is the whole change
    assert effect["rmse_gain"] == pytest.approx(before - after)
    expected = f"validation RMSE {before:.4f} -> {after:.4f} Nm ({after - before:+.4f} Nm)"
    said = " ".join(stdout.split())  # the console wraps long lines
    assert said.count("found: ") == 1
    assert (
        f"found: joint 2 direction offset 0.6 Nm (the reading is +0.6 Nm x the sign of the last motion) ({expected})"
        in said
    )
    assert after < before  # the effect held: no "did not hold"
    assert "did not hold" not in said
    report = (out / "report.md").read_text()
    assert f"When added: {expected}" in report
    assert not NEGATIVE_RMSE.search(stdout)
    assert not NEGATIVE_RMSE.search(report)
