"""The suite's own plumbing (tests/conftest.py): what the real-time tier of ``make test`` collects (D201).

The parallel tier's collection (the whole suite) stores which files hold a test marked
``realtime``; the real-time tier, run right after with ``--realtime-files-from-cache``, imports
only those. A test must never be lost on the way: a file outside the list is skipped only when a
list was stored, and only a collection of the whole suite stores one.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from tests import conftest


class _Cache:
    def __init__(self, stored: dict[str, Any]) -> None:
        self.stored = stored

    def get(self, key: str, default: Any) -> Any:
        return self.stored.get(key, default)


def _config(root: Path, options: dict[str, Any], stored: dict[str, Any] | None = None, args_source: Any = None) -> Any:
    return SimpleNamespace(
        getoption=lambda name, default=None: options.get(name, default),
        cache=_Cache(stored or {}),
        rootpath=root,
        args_source=args_source,
    )


#: A stored list (files of a made-up suite under ``suite/``, relative to its root).
LISTED = {conftest.REALTIME_FILES_KEY: ["suite/hal/test_a.py", "suite/test_b.py"]}


def test_the_real_time_tier_collects_only_the_listed_test_files(tmp_path: Path) -> None:
    config = _config(tmp_path, {"realtime_files_from_cache": True}, LISTED)
    assert conftest.pytest_ignore_collect(tmp_path / "suite" / "hal" / "test_a.py", config) is False
    assert conftest.pytest_ignore_collect(tmp_path / "suite" / "test_b.py", config) is False
    assert conftest.pytest_ignore_collect(tmp_path / "suite" / "hal" / "test_c.py", config) is True
    # Folders and helpers are pytest's to decide: a conftest is still loaded, a folder still walked.
    assert conftest.pytest_ignore_collect(tmp_path / "suite" / "hal" / "conftest.py", config) is None
    assert conftest.pytest_ignore_collect(tmp_path / "suite" / "hal", config) is None


def test_without_a_stored_list_or_without_the_option_everything_is_collected(tmp_path: Path) -> None:
    path = tmp_path / "suite" / "hal" / "test_c.py"
    assert conftest.pytest_ignore_collect(path, _config(tmp_path, {"realtime_files_from_cache": True})) is None
    assert conftest.pytest_ignore_collect(path, _config(tmp_path, {"realtime_files_from_cache": False}, LISTED)) is None


@pytest.mark.parametrize(
    ("args_source", "options", "whole"),
    [
        (pytest.Config.ArgsSource.TESTPATHS, {}, True),
        (pytest.Config.ArgsSource.ARGS, {}, False),  # files or node ids named: a part of the suite
        (pytest.Config.ArgsSource.TESTPATHS, {"lf": True}, False),  # last-failed collects a part
        (pytest.Config.ArgsSource.TESTPATHS, {"realtime_files_from_cache": True}, False),  # the tier itself
    ],
)
def test_only_a_collection_of_the_whole_suite_stores_the_list(
    tmp_path: Path, args_source: Any, options: dict[str, Any], whole: bool
) -> None:
    assert conftest._whole_suite(_config(tmp_path, options, args_source=args_source)) is whole


def test_this_run_stored_the_files_of_every_real_time_test_it_saw(request: pytest.FixtureRequest) -> None:
    """In a whole-suite run (``make test``'s parallel tier), the stored list names this suite's real-time files."""
    config = request.config
    if not conftest._whole_suite(config):
        pytest.skip("this run collected a part of the suite: it stores no list")
    assert config.cache is not None
    stored = config.cache.get(conftest.REALTIME_FILES_KEY, None)
    assert stored is not None
    assert "tests/test_hazard_mutations.py" in stored  # its rows that name real-time tests (D199)
    assert "tests/daror_runtime/console/test_signals.py" in stored
    assert all((config.rootpath / name).is_file() for name in stored)
