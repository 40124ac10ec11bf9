"""docs/fsm.md shows the spec as it is: its diagram, every guard and every mode."""

from __future__ import annotations

from pathlib import Path

from daror_runtime.fsm.diagram import mermaid
from daror_runtime.fsm.guards import GUARDS
from daror_runtime.fsm.modes import MODES
from daror_runtime.fsm.spec import DEFAULT_SPEC_PATH, load_fsm_spec

DOC = (Path(__file__).resolve().parents[3] / "docs" / "fsm.md").read_text(encoding="utf-8")


def test_the_documented_diagram_is_the_spec_s() -> None:
    block = DOC.split("```mermaid\n", 1)[1].split("```", 1)[0]
    assert block == mermaid(load_fsm_spec(DEFAULT_SPEC_PATH)), "run: daror fsm diagram and paste it into docs/fsm.md"


def test_every_guard_and_mode_is_documented() -> None:
    missing = [f"guard {g}" for g in GUARDS if f"| `{g}` |" not in DOC]
    missing += [f"mode {m}" for m in MODES if f"| `{m}` |" not in DOC]
    assert not missing, f"docs/fsm.md does not describe: {', '.join(missing)}"
