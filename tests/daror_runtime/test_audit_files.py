"""Issue 24, defect 9: `--log-json` no longer leaves the session folder without its audit log.

The session folder keeps its own ``audit.jsonl`` whatever the command line says; ``--log-json FILE``
writes the same JSON lines to FILE too (the lab's collector), each line once per file.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import structlog

from daror_runtime.logs import configure_logging, flush_logs


def _events(path: Path) -> list[dict[str, object]]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


@pytest.mark.subprocess
@pytest.mark.slow
def test_a_console_session_with_log_json_keeps_its_own_audit_too(tmp_path: Path) -> None:
    out, extra = tmp_path / "session1", tmp_path / "collector" / "audit.jsonl"
    run = subprocess.run(
        [sys.executable, "-m", "daror_runtime.cli", "--log-json", str(extra), "console", "--out", str(out)],
        input="", capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    own = _events(out / "audit.jsonl")
    copied = _events(extra)
    stopped = [e for e in own if e["event"] == "session stopped: torque off"]
    assert len(stopped) == 1
    assert stopped[0]["torque_off_confirmed"] is True
    session_id = json.loads((out / "session.json").read_text(encoding="utf-8"))["session_id"]
    assert stopped[0]["session_id"] == session_id
    assert [e for e in copied if e.get("session_id") == session_id] == [e for e in own if e.get("session_id")]


def test_every_json_file_gets_each_line_once(tmp_path: Path) -> None:
    first, second = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    try:
        configure_logging("critical", [first, second, tmp_path / "." / "a.jsonl"])  # a named twice: one handle
        structlog.get_logger("test").info("one line", value=1)
        flush_logs()
        for path in (first, second):
            assert [e["event"] for e in _events(path)] == ["one line"]
    finally:
        configure_logging("critical")
