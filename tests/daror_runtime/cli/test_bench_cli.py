"""``daror bench`` at the command line (issue 24): the benchmarks' names in its help, and an ``--only``
that matches none of them is one line, exit 2, nothing run and nothing written (it was an empty table, exit 0)."""

from __future__ import annotations

from pathlib import Path

import pytest

from daror_runtime.bench import bench_directory, discover
from daror_runtime.cli import main


@pytest.fixture(scope="module")
def names() -> list[str]:
    return [b.__name__ for b in discover(bench_directory())]


def test_an_only_that_matches_no_benchmark_is_one_line_naming_them_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], names: list[str]
) -> None:
    figures = tmp_path / "figures.json"
    assert main(["bench", "--only", "nosuchbench", "--json", str(figures)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""  # no machine line, no empty table
    assert captured.err.count("\n") == 1
    assert captured.err.startswith("daror bench: error: --only 'nosuchbench' is part of no benchmark's name; ")
    listed = captured.err.split("expected part of one of: ", 1)[1].strip().split(", ")
    assert listed == names
    assert len(names) > 50
    assert not figures.exists()


def test_the_help_and_list_name_every_benchmark_by_script(capsys: pytest.CaptureFixture[str], names: list[str]) -> None:
    with pytest.raises(SystemExit) as done:
        main(["bench", "--help"])
    assert done.value.code == 0
    help_text = capsys.readouterr().out
    assert "--only ONLY" in help_text
    assert "benchmarks by script (--only runs those whose name contains its text):" in help_text
    assert "  canopen: bench_bus_load, bench_can_sim_tick, bench_hil_command, bench_hil_real_time\n" in help_text
    assert main(["bench", "--list"]) == 0
    listing = capsys.readouterr().out
    for text in (help_text, listing):
        lines = [line for line in text.splitlines() if line.startswith("  ") and ": bench_" in line]
        assert [n for line in lines for n in line.split(": ", 1)[1].split(", ")] == names
