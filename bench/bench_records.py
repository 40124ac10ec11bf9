"""Pilots over months (issue 28's acceptance): three simulated pilots, three sessions each, through the
console scripts, recorded in the lab's records; the returning sessions against the first.

Each pilot is a scenario with another arm (the Dummy Arm; the heavier arm of ``exo_heavy_arm``; a
lighter arm, three quarters of the Dummy Arm's masses); from session to session his elbow springs
stiffen (x1.0, x1.4, x1.8: a contracture growing, as DMD does). Session 1 is the whole protocol
(``session.txt``, PLF+ trained); sessions 2 and 3 are ``returning_pilot.txt``: his last model from
the records, re-validated on one validation run; his range of motion is recorded anew (``rom last``
replaced by the sweep), as a lab does when his arm changed; the e-stop test of operative_check is
made with his forearm on the armrest (D217). Every session is a whole
``daror console --script`` command (process start to exit); the robot time to compensation is the
session's own (``history.reached_at_s``). Then ``daror pilots report`` for each pilot.

Run alone: ``python bench/bench_records.py OUT_DIR [--stride N]`` writes the sessions, the records
(``OUT_DIR/lab.db``) and the three reports there, and prints the table of docs/records.md.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from daror_runtime.bench import BenchFigure

DAROR = Path(sys.executable).with_name("daror")
ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "daror_runtime" / "console" / "scripts"
SCENARIOS = ROOT / "hal" / "sim" / "scenarios"
#: The pilots: (code, the scenario whose arm he has, the scale of that arm's masses).
PILOTS = (("P-101", "exo_dummy_arm", 1.0), ("P-102", "exo_heavy_arm", 1.0), ("P-103", "exo_dummy_arm", 0.75))
#: His elbow springs' stiffness, session by session (x the scenario's).
STIFFENING = (1.0, 1.15, 1.3)


def _scenario(folder: Path, code: str, base: str, mass_scale: float, session: int) -> Path:
    """The pilot's arm at his ``session``-th session: ``base``'s arm, masses scaled, springs stiffened."""
    source = yaml.safe_load((SCENARIOS / f"{base}.yaml").read_text(encoding="utf-8"))
    arm = source.get("dummy_arm") or yaml.safe_load((SCENARIOS / "exo_dummy_arm.yaml").read_text())["dummy_arm"]
    for part in ("upper_arm", "lower_arm"):
        arm[part]["mass_kg"] = round(arm[part]["mass_kg"] * mass_scale, 4)
    for spring in arm["elbow_springs"]:
        spring["stiffness_nm_per_rad"] = round(spring["stiffness_nm_per_rad"] * STIFFENING[session - 1], 4)
    # one name for all his sessions: the robot is the same robot (a simulated robot is named by its
    # scenario), only his arm changed
    name = f"pilot_{code.lower().replace('-', '_')}"
    document = {"extends": base, "name": name, "summary": f"pilot {code}, session {session}", "dummy_arm": arm}
    path = folder / f"{name}_s{session}.yaml"
    path.write_text(yaml.safe_dump(document, sort_keys=False), encoding="utf-8")
    return path


def _script(folder: Path, code: str, returning: bool) -> Path:
    if returning:
        text = (SCRIPTS / "returning_pilot.txt").read_text(encoding="utf-8").replace("pilot P-007", f"pilot {code}")
        text = text.replace("rom last\n", "rom start\nsim pilot sweep\nwait until still timeout 600\nrom stop\n", 1)
    else:
        text = (SCRIPTS / "session.txt").read_text(encoding="utf-8")
        text = text.replace("expect state settings\n", f"expect state settings\npilot {code}\nexpect accepted\n", 1)
    path = folder / f"{'returning' if returning else 'first'}_{code}.txt"
    path.write_text(text, encoding="utf-8")
    return path


def pilots_over_months(folder: Path, stride: int) -> list[dict[str, Any]]:
    """Run the 9 sessions in ``folder`` (records in ``folder/lab.db``); one row per session."""
    settings = folder / "settings.yaml"
    settings.write_text(f"dummy_arm: true\nidentification:\n  waypoint_stride: {stride}\n", encoding="utf-8")
    db = folder / "lab.db"
    rows = []
    for session in (1, 2, 3):
        for code, base, scale in PILOTS:
            scenario = _scenario(folder, code, base, scale, session)
            script = _script(folder, code, returning=session > 1)
            out = folder / f"{code}_s{session}"
            argv = [str(DAROR), "--log-level", "error", "console", "--script", str(script), "--settings", str(settings),
                    "--scenario", str(scenario), "--out", str(out), "--db", str(db)]  # fmt: skip
            start = time.perf_counter()
            done = subprocess.run(argv, capture_output=True, text=True, check=False)
            wall = time.perf_counter() - start
            summary = json.loads((out / "session.json").read_text(encoding="utf-8"))
            model = summary.get("model") or {}
            rows.append(
                {
                    "pilot": code,
                    "session": session,
                    "exit": done.returncode,
                    "state": summary["state"],
                    "to_compensation_s": summary["history"]["reached_at_s"].get("compensation"),
                    "wall_s": wall,
                    "model": model.get("kind"),
                    "model_file": model.get("path"),
                    "validated": model.get("validated"),
                    "validation_rmse_nm": model.get("validation_rmse_nm"),
                    "elbow_rmse_nm": (model.get("validation_rmse_per_joint_nm") or [None] * 4)[3],
                }
            )
    for code, _, _ in PILOTS:
        subprocess.run(
            [str(DAROR), "pilots", "report", code, "--out", str(folder / f"report_{code}"), "--db", str(db)],
            capture_output=True,
            check=True,
        )
    return rows


def bench_pilots_over_months(quick: bool) -> list[BenchFigure]:
    with tempfile.TemporaryDirectory() as directory:
        rows = pilots_over_months(Path(directory), 20 if quick else 12)
    new = [r["to_compensation_s"] for r in rows if r["session"] == 1 and r["to_compensation_s"] is not None]
    back = [r["to_compensation_s"] for r in rows if r["session"] > 1 and r["to_compensation_s"] is not None]
    failed = [f"{r['pilot']} s{r['session']}: {r['state']}" for r in rows if r["state"] != "compensation"]
    note = "; ".join(failed) if failed else "every session reached compensation"
    walls_new = [r["wall_s"] for r in rows if r["session"] == 1]
    walls_back = [r["wall_s"] for r in rows if r["session"] > 1]
    return [
        BenchFigure(
            "a new pilot: robot time to compensation", statistics.median(new), max(new), "s", len(new), note=note
        ),
        BenchFigure(
            "a returning pilot: robot time to compensation", statistics.median(back), max(back), "s", len(back)
        ),
        BenchFigure(
            "a new pilot's whole console command", statistics.median(walls_new), max(walls_new), "s", len(walls_new)
        ),
        BenchFigure(
            "a returning pilot's whole console command",
            statistics.median(walls_back),
            max(walls_back),
            "s",
            len(walls_back),
        ),
    ]


BENCHMARKS = [bench_pilots_over_months]


if __name__ == "__main__":
    target = Path(sys.argv[1])
    target.mkdir(parents=True, exist_ok=False)
    stride = int(sys.argv[sys.argv.index("--stride") + 1]) if "--stride" in sys.argv else 12
    for row in pilots_over_months(target, stride):
        print(json.dumps(row))
