"""The demo's session (``daror demo``, part 1 and 3): it ends in compensation, and its data close to their floor.

Issue 27, part 3 (D204): the session's identification data closed only to 0.028 Nm where
``daror identify`` runs reach 0.0015 Nm. Traced: one validation point, the run's first, whose
hysteresis state no log determines (the run begins at rest there); a model that lacks nothing
errs there as much. The demo prints its closure against the floor of its own runs.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

from daror_runtime.demo import DEMO_SCENARIO, _close_the_loop
from daror_runtime.demo.rehearsal import SessionReport, rehearse

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> tuple[SessionReport, Path]:
    folder = tmp_path_factory.mktemp("demo")
    return rehearse(folder / "session", Console(file=io.StringIO()), DEMO_SCENARIO), folder


def test_the_rehearsal_of_the_demo_ends_in_compensation_with_the_arm_carried(
    session: tuple[SessionReport, Path],
) -> None:
    report, folder = session
    assert report.final_state == "compensation"
    holding, unsupported = np.array(report.holding_torque_nm), np.array(report.unsupported_torque_nm)
    assert np.all(holding > 0.5)
    assert np.all(unsupported < 0.1 * holding), (unsupported, holding)
    assert json.loads((folder / "session" / "session.json").read_text(encoding="utf-8"))["ended"]["confirmed"]


def test_the_session_s_data_close_to_the_floor_of_the_same_runs_and_the_demo_says_so(
    session: tuple[SessionReport, Path],
) -> None:
    report, folder = session
    printed = io.StringIO()
    markdown, floor = _close_the_loop(report, folder, Console(file=printed, width=400), DEMO_SCENARIO)
    summary = json.loads((folder / "residual_session" / "summary.json").read_text(encoding="utf-8"))
    assert summary["rmse_before"] > 0.4  # PLF+ alone: the plant's hysteresis (0.421 Nm measured)
    # Issue 27's acceptance: within 1.5x the floor of its own runs (measured 1.00x), all points and
    # without the one whose state no log determines (measured 1.00x: 0.00155 Nm against 0.00155)
    assert floor["rmse_after"] == pytest.approx(summary["rmse_after"])
    assert floor["ratio"] <= 1.5
    determined = floor["determined"]
    assert determined["ratio"] <= 1.5
    assert determined["rmse_after"] < 0.1 * summary["rmse_after"]  # the one point is nearly all of it
    # that point is the validation run's first: the run begins at rest at its first stop
    validation = np.loadtxt(folder / "session" / "identification_validation.csv", delimiter=",", skiprows=1)
    assert summary["undetermined_state"]["t_s"] == [pytest.approx(validation[0, 0])]
    assert determined["left_out_t_s"] == summary["undetermined_state"]["t_s"]
    assert f"{floor['ratio']:.2f}x" in printed.getvalue()
    assert f"{determined['ratio']:.2f}x" in printed.getvalue()
    assert "floor of the session's own runs" in markdown
    # the training run's first stop, before joint 1 had moved far enough, is left out of the verdict
    # on what remains (its shared error made the neighbours alike: lag-1 autocorrelation 0.33)
    diagnosis = json.loads((folder / "residual_session" / "diagnosis.json").read_text(encoding="utf-8"))
    assert any("hysteresis state no log determines" in note for note in diagnosis["notes"])
    assert not any(c["structured"] and c["signal"].startswith("previous point") for c in diagnosis["correlates"]), (
        diagnosis["correlates"]
    )
