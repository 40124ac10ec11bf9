"""The suite's own plumbing (tests/conftest.py): how ``make test`` hands the tests to its two workers (D202, D208).

Whole files per worker, the longest first; the tests marked ``realtime`` are one unit, handed out
first, so one worker runs them one after another while the other runs one file: never more than
one busy process of the suite beside a test that needs wall-clock time.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from tests import conftest

ROOT = Path(__file__).resolve().parents[1]


class _Item(SimpleNamespace):
    """What the ordering hook reads of a test: its file and its marks."""

    def __init__(self, file: str, realtime: bool = False) -> None:
        super().__init__(
            path=Path("/suite") / file, nodeid=f"{file}::t{id(self)}", marks=["realtime"] if realtime else []
        )

    def get_closest_marker(self, name: str) -> Any:
        return name if name in self.marks else None


def test_real_time_tests_come_first_then_the_longest_files_and_a_worker_writes_their_ids(tmp_path: Path) -> None:
    items = [
        _Item("test_short.py"),
        _Item("test_readme_transcript.py"),
        _Item("test_short.py", realtime=True),
        _Item("test_hazard_mutations.py"),
        _Item("test_hazard_mutations.py", realtime=True),
        _Item("test_other.py"),
    ]
    ordered = list(items)
    target = tmp_path / "realtime.json"
    worker = SimpleNamespace(workerinput={conftest.REALTIME_IDS_KEY: str(target)})
    conftest.pytest_collection_modifyitems(worker, ordered)  # type: ignore[arg-type]
    assert ordered == [items[4], items[2], items[3], items[1], items[0], items[5]]
    assert json.loads(target.read_text(encoding="utf-8")) == [items[4].nodeid, items[2].nodeid]
    assert [path.name for path in tmp_path.iterdir()] == ["realtime.json"]  # no temporary file left
    conftest.pytest_collection_modifyitems(SimpleNamespace(), list(items))  # type: ignore[arg-type]  # not a worker: nothing written


@pytest.mark.parametrize(
    ("nodeid", "unit"),
    [
        ("suite/hal/test_a.py::test_x", "suite/hal/test_a.py"),
        ("suite/hal/test_a.py::TestY::test_z[can-sim]", "suite/hal/test_a.py"),
        ("suite/test_b.py::test_rt", "realtime"),
        ("suite/test_b.py::test_rt[a::b]", "realtime"),
    ],
)
def test_the_unit_is_the_file_unless_the_test_is_a_real_time_one(nodeid: str, unit: str) -> None:
    scheduler = SimpleNamespace(
        _realtime_ids=frozenset({"suite/test_b.py::test_rt", "suite/test_b.py::test_rt[a::b]"}), _realtime_ids_path=None
    )
    assert conftest.FilesAndTheRealTimeGroup._split_scope(scheduler, nodeid) == unit  # type: ignore[arg-type]


_SUITE = {
    "conftest.py": (
        "from tests.conftest import (  # noqa: F401\n"
        "    pytest_collection_modifyitems, pytest_configure_node, pytest_unconfigure, pytest_xdist_make_scheduler,\n"
        ")\n"
    ),
    "pytest.ini": "[pytest]\nmarkers =\n    realtime: needs wall-clock time\n",
    # A module fixture shows whether a file stayed on one worker (it would be built once per worker).
    "helper.py": (
        "import json, os, time\n"
        "def note(name):\n"
        "    with open(os.environ['RUN_LOG'], 'a') as f:\n"
        "        f.write(json.dumps([os.environ['PYTEST_XDIST_WORKER'], time.monotonic(), name]) + '\\n')\n"
        "    time.sleep(0.05)\n"
    ),
    "test_long.py": "from helper import note\n" + "".join(f"def test_l{i}():\n    note('long')\n" for i in range(8)),
    "test_short.py": (
        "import pytest\nfrom helper import note\n"
        "def test_s0():\n    note('short')\n"
        "@pytest.mark.realtime\ndef test_s_rt():\n    note('realtime')\n"
        "def test_s1():\n    note('short')\n"
    ),
    "test_more.py": (
        "import pytest\nfrom helper import note\n"
        "@pytest.mark.realtime\ndef test_m_rt():\n    note('realtime')\n"
        + "".join(f"def test_m{i}():\n    note('more')\n" for i in range(3))
    ),
}


@pytest.mark.subprocess
def test_make_test_s_scheduling_runs_the_real_time_tests_together_first_and_keeps_files_whole(tmp_path: Path) -> None:
    for name, text in _SUITE.items():
        (tmp_path / name).write_text(text, encoding="utf-8")
    log = tmp_path / "run.jsonl"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "COV_"))}
    env.update(PYTHONPATH=str(ROOT), RUN_LOG=str(log), PYTHONDONTWRITEBYTECODE="1")
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "--no-loadscope-reorder", "-q",
         "-p", "no:cacheprovider", "-o", "addopts=", "--rootdir", str(tmp_path), str(tmp_path)],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert run.returncode == 0, run.stdout + run.stderr
    assert "15 passed" in run.stdout, run.stdout
    notes = [json.loads(line) for line in log.read_text(encoding="utf-8").splitlines()]
    workers = {
        name: {worker for worker, _, kind in notes if kind == name} for name in ("long", "short", "more", "realtime")
    }
    assert all(len(found) == 1 for found in workers.values()), workers  # each file, and the group, on one worker
    realtime_worker = next(iter(workers["realtime"]))
    on_that_worker = [kind for worker, _, kind in sorted(notes, key=lambda n: n[1]) if worker == realtime_worker]
    assert on_that_worker[:2] == ["realtime", "realtime"]  # the group first, its two tests one after another


def test_a_real_time_test_asks_for_priority_where_allowed_and_the_next_test_gives_it_back() -> None:
    """On its own thread (a Linux nice value is per thread): the suite's 0 and REALTIME_NICE only, never a caller's."""
    seen: list[int] = []

    def steps() -> None:
        allowed = os.geteuid() == 0  # raising a priority needs root or CAP_SYS_NICE; lowering it never does
        conftest._priority_for(True)
        seen.append(os.getpriority(os.PRIO_PROCESS, 0))
        conftest._priority_for(False)
        seen.append(os.getpriority(os.PRIO_PROCESS, 0))
        os.setpriority(os.PRIO_PROCESS, 0, 5)  # `nice -n 5 make test`
        conftest._priority_for(True)
        seen.append(os.getpriority(os.PRIO_PROCESS, 0))
        seen.append(int(allowed))

    thread = threading.Thread(target=steps)
    thread.start()
    thread.join()
    raised = conftest.REALTIME_NICE if seen[3] else 0
    assert seen[:3] == [raised, 0, 5]
