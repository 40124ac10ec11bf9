"""Every hazard's test fails without its mitigation (issue 26, point 6; docs/safety.md).

``tests/hazard_mutations.yaml`` names, for every hazard of docs/safety.md's table, the code that
mitigates it (a file and an exact snippet: whole lines, compared without their common indentation),
a replacement that removes the mitigation, and the tests that must then fail. The slow tier
(``pytest -m mutation``) runs each row: the repository's files as git lists them are copied to a
temporary folder, the snippet is replaced there (never in the checkout: others run tests on it), and
the row's tests run in the copy in a pytest process of their own; the row passes only if they fail.
A snippet that does not occur exactly once fails the row: a refactor must update the table, it never
makes a row pass unnoticed.

The copy's code is what runs: the package is installed editable from the checkout, but the editable
finder sits at the end of ``sys.meta_path``, after the path finder, so the copy first on ``sys.path``
(the inner pytest's working folder, and ``PYTHONPATH`` for the processes the tests start) wins. Three
controls prove it and that the copy itself is sound: the copy imports its own ``daror_runtime`` and
``hal`` (also in a process started elsewhere, as the tests' own subprocesses are), an import-time
mutation of the copy is seen by its tests, and the unmutated copy passes a sample of rows' tests.

The rows' pytest processes are forked from a zygote (tests/mutation_zygote.py) that imported the
third-party libraries once: the same run as ``python -m pytest`` in the copy, a second of CPU cheaper.
The copy takes the checkout's bytecode, numba and pytest caches along (``__pycache__``, hard links:
each is only ever replaced, never written in place): the interpreter and pytest check a ``.pyc``
against its source's time and size (``copy2`` keeps both), numba its index against the source's
time and size, so only the mutated file is compiled again and no test module's asserts are rewritten
again (``make test`` lets pytest write those caches, D193). A row whose snippet is inside a
compiled kernel says so (``kernel: true``) and drops every numba cache of the copy, since a kernel's
cache also holds the kernels it calls from other files, unchecked.

The fast test below keeps docs/safety.md's mutation table, the YAML and the hazards table in step.
"""

from __future__ import annotations

import ast
import json
import os
import re
import selectors
import shutil
import signal
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml
from _pytest.config import default_plugins

ROOT = Path(__file__).resolve().parents[1]
TABLE = ROOT / "tests" / "hazard_mutations.yaml"
SAFETY = ROOT / "docs" / "safety.md"
#: The docs section this table is kept in (its heading, without the ``## ``).
SECTION = "Mutation run: every hazard's test fails without its mitigation"
#: A row's tests, in the copy: well under this even on a loaded machine.
ROW_TIMEOUT_S = 300.0


@dataclass(frozen=True)
class Edit:
    """In ``file``, the snippet ``find`` (whole lines, exactly once) becomes ``replace``."""

    file: str
    find: str
    replace: str


@dataclass(frozen=True)
class Row:
    """One mutation: its ``edits`` remove a mitigation; ``tests`` must then fail.

    ``site`` is the mitigation's ``file:function`` (the first edit's file). ``no_code_site`` instead
    of edits: why the hazard has no code to remove (procedural). ``kernel``: an edit is inside a
    compiled kernel, so the copy's numba caches are dropped.
    """

    hazard: str
    name: str
    site: str
    removes: str
    tests: tuple[str, ...] = ()
    edits: tuple[Edit, ...] = ()
    no_code_site: str = ""
    kernel: bool = False

    @property
    def id(self) -> str:
        """The pytest id: the hazard and the row's name."""
        return f"{self.hazard}-{self.name}"


def load_rows(path: Path = TABLE) -> list[Row]:
    """The YAML table's rows, each checked for the fields it needs.

    A row's mutation is ``file``, ``find`` and ``replace``, or a list ``edits`` of them (an edit's
    ``file`` defaults to the row's).
    """
    document = yaml.safe_load(path.read_text(encoding="utf-8"))
    rows = []
    for entry in document["rows"]:
        where = entry.get("file", "")
        edits = entry.get("edits", [entry] if "find" in entry else [])
        row = Row(
            hazard=entry["hazard"],
            name=entry["name"],
            site=entry["site"],
            removes=entry["removes"],
            tests=tuple(entry.get("tests", ())),
            edits=tuple(Edit(e.get("file", where), e["find"], e["replace"]) for e in edits),
            no_code_site=entry.get("no_code_site", ""),
            kernel=bool(entry.get("kernel", False)),
        )
        if row.no_code_site:
            assert not row.edits, f"{row.id}: no code site, yet a mutation"
            assert not row.tests, f"{row.id}: no code site, yet tests"
        else:
            assert row.edits, f"{row.id}: a mutation needs edits (file, find, replace)"
            assert row.tests, f"{row.id}: a mutation needs tests that fail"
            assert all(e.file and e.find and e.find != e.replace for e in row.edits), f"{row.id}: an empty edit"
            assert row.site.startswith(f"{row.edits[0].file}:"), f"{row.id}: the site names its file: {row.site}"
        rows.append(row)
    return rows


ROWS = load_rows()
MUTATIONS = [row for row in ROWS if not row.no_code_site]


def needs_real_time(test_id: str, root: Path = ROOT) -> bool:
    """True if the test ``path::name[...]`` (or ``path::Class::name``) is marked ``realtime`` in its source.

    Read from the source, not imported (an import here would skip pytest's assertion rewriting of
    the module): a module-level ``pytestmark`` or a decorator of the test or its class that names
    ``mark.realtime``.
    """
    path, _, rest = test_id.partition("::")
    names = [part.split("[", 1)[0] for part in rest.split("::")] if rest else []
    tree = ast.parse((root / path).read_text(encoding="utf-8"))

    def marked(node: ast.expr) -> bool:
        return "mark.realtime" in ast.unparse(node)

    for node in tree.body:
        is_pytestmark = isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "pytestmark" for t in node.targets)
        if is_pytestmark and marked(node.value):  # type: ignore[union-attr]
            return True
    scope: list[ast.stmt] = tree.body
    for name in names:
        found = [n for n in scope if isinstance(n, (ast.FunctionDef, ast.ClassDef)) and n.name == name]
        if not found:
            return False
        if any(marked(d) for d in found[0].decorator_list):
            return True
        scope = found[0].body if isinstance(found[0], ast.ClassDef) else []
    return False


def _param(row: Row) -> object:
    """The row as a pytest parameter: marked ``realtime`` when a test it names is.

    Such a test measures the machine's margin first and is skipped without it (tests/conftest.py);
    a skip in the row's run would make the row fail for the machine's load, not the mutation. Marked,
    the row runs with the real-time tests, one after another on one worker (D208), where the margin is there.
    """
    marks = [pytest.mark.realtime] if any(needs_real_time(test) for test in row.tests) else []
    return pytest.param(row, id=row.id, marks=marks)


# --- the copy ----------------------------------------------------------------------------------------


def tracked_files(root: Path = ROOT) -> list[str]:
    """The repository's files as git sees them (tracked, and new ones not ignored), as they are on disk."""
    done = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=root,
        capture_output=True,
        check=True,
    )
    return sorted({name for name in done.stdout.decode("utf-8").split("\0") if name and (root / name).is_file()})


def copy_tree(destination: Path, root: Path = ROOT) -> Path:
    """The tracked files, and the bytecode and numba caches of the packages and tests, linked into ``destination``.

    Hard links where the file system allows (:func:`_link_or_copy`; copying the 471 tracked files
    took 0.1-0.2 s a row, 86 rows a run): :func:`mutate` replaces the file it edits (unlinked, then
    written anew), the interpreter, pytest and numba only ever replace a cache file (a new file
    renamed over it), and no test writes a tracked file, so a row's run cannot change the checkout
    through a link.
    """
    for name in tracked_files(root):
        target = destination / name
        target.parent.mkdir(parents=True, exist_ok=True)
        _link_or_copy(str(root / name), str(target))
    for package in ("daror_runtime", "hal", "tests"):
        for cache in (root / package).rglob("__pycache__"):
            target = destination / cache.relative_to(root)
            if target.parent.is_dir():  # a folder git still knows
                shutil.copytree(cache, target, copy_function=_link_or_copy, dirs_exist_ok=True)
    return destination


def _link_or_copy(source: str, target: str) -> None:
    """``target`` as a hard link to ``source`` (the same file, its time kept), or a copy where no link can be made."""
    try:
        os.link(source, target)
    except OSError:  # another file system, or links not allowed: a copy with its time
        shutil.copy2(source, target)


def _snippet(find: str) -> re.Pattern[str]:
    """Whole source lines that read ``find`` after one common indentation (captured as ``indent``)."""
    lines = find.split("\n")
    parts = [r"^(?P<indent>[ \t]*)" + re.escape(lines[0])]
    parts += [r"\n" + (r"[ \t]*" if not line.strip() else r"(?P=indent)" + re.escape(line)) for line in lines[1:]]
    return re.compile("".join(parts) + "$", re.MULTILINE)


def occurrences(text: str, find: str) -> list[re.Match[str]]:
    """Where ``find`` (whole lines, without their common indentation) occurs in ``text``."""
    return list(_snippet(find).finditer(text))


def mutate(row: Row, copy: Path) -> None:
    """Apply the row's edits to the copy: each snippet must occur exactly once (a refactor updates the table)."""
    for edit in row.edits:
        source = copy / edit.file
        text = source.read_text(encoding="utf-8")
        found = occurrences(text, edit.find)
        assert len(found) == 1, (
            f"{row.id}: the snippet occurs {len(found)} times in {edit.file} (must be exactly once): "
            f"update tests/hazard_mutations.yaml to the code as it is now\n--- find ---\n{edit.find}"
        )
        [match] = found
        indent = match.group("indent")
        replacement = "\n".join(indent + line if line.strip() else "" for line in edit.replace.split("\n"))
        source.unlink()  # a new file: never written through to the checkout's, whatever copied it
        source.write_text(text[: match.start()] + replacement + text[match.end() :], encoding="utf-8")
    if row.kernel:  # a kernel's cache holds the kernels it calls from other files, unchecked
        for pattern in ("*.nbi", "*.nbc"):
            for cache in copy.rglob(pattern):
                cache.unlink()


def environment(copy: Path) -> dict[str, str]:
    """The tests' environment: the copy first on the path; nothing of an outer pytest (or xdist) leaks in."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "COV_CORE_"))}
    env["PYTHONPATH"] = os.pathsep.join([str(copy), *filter(None, [os.environ.get("PYTHONPATH", "")])])
    env.pop("PYTHONSAFEPATH", None)  # it would drop the working folder (the copy) from the path
    return env


#: What a row's tests import before the repository's code: the zygote imports them once (tests/mutation_zygote.py).
#: Third-party modules only, each only imported: pydantic's and numba's submodules that a package's import
#: leaves for later (BaseModel; the CPU target's implementations, loaded with the first cached kernel), the
#: web console's server and client, and pytest's own plug-ins and what they import (every row loaded them).
PRELOAD = (
    "numpy", "scipy.linalg", "scipy.signal", "scipy.optimize", "scipy.interpolate", "scipy.integrate", "numba",
    "hypothesis", "hypothesis.strategies", "hypothesis.stateful", "pydantic", "structlog", "yaml", "rich.console",
    "matplotlib", "transitions", "prompt_toolkit", "jsonschema", "can", "canopen", "pytest", "_pytest.assertion.rewrite",
    "pydantic.main", "pydantic.json_schema", "numba.np.npyimpl", "numba.typed", "numba.experimental.jitclass",
    "numba.cpython.charseq", "numba.cpython.unicode", "transitions.extensions", "durand",
    "fastapi", "fastapi.responses", "fastapi.staticfiles", "uvicorn", "websockets.sync.client", "pexpect",
    *(f"_pytest.{name}" for name in default_plugins), "_hypothesis_pytestplugin", "pdb", "readline",
)  # fmt: skip
#: The inner pytest's options: stop at the first failure; no cache, no plug-ins the rows do not use, no addopts;
#: hypothesis's plug-in module was imported by the zygote, so pytest cannot rewrite its asserts (it says so once).
PYTEST_ARGS = (
    "-x", "-q", "-p", "no:cacheprovider", "-p", "no:anyio", "-p", "no:xdist", "-p", "no:xdist.looponfail", "-o", "addopts=",
    "-W", "ignore::pytest.PytestAssertRewriteWarning",
)  # fmt: skip


@dataclass(frozen=True)
class Outcome:
    """A row's run: pytest's exit code (negative: the signal that ended it) and its output."""

    code: int
    output: str

    def tail(self, lines: int = 60) -> str:
        """The output's last ``lines`` lines."""
        return "\n".join(self.output.splitlines()[-lines:])

    @property
    def only_skipped(self) -> bool:
        """True when every test of the run was skipped (pytest's summary names nothing but skips)."""
        summary = self.output.strip().splitlines()[-1] if self.output.strip() else ""
        return (
            self.code == 0
            and re.fullmatch(r"=*\s*\d+ skipped(, \d+ deselected)? in [\d.]+s( \(.*\))?\s*=*", summary) is not None
        )


class Zygote:
    """The zygote process (tests/mutation_zygote.py): third-party imports once, a forked ``pytest.main`` per run."""

    def __init__(self) -> None:
        self._process = subprocess.Popen(
            [sys.executable, "-I", str(ROOT / "tests" / "mutation_zygote.py"), *PRELOAD],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=tempfile.gettempdir(),
        )
        self._selector = selectors.DefaultSelector()
        assert self._process.stdout is not None
        self._selector.register(self._process.stdout, selectors.EVENT_READ)

    def _answer(self, timeout_s: float) -> dict[str, int] | None:
        assert self._process.stdout is not None
        if not self._selector.select(timeout_s):
            return None
        line = self._process.stdout.readline()
        assert line, f"the zygote ended (exit code {self._process.poll()})"
        return json.loads(line)  # type: ignore[no-any-return]

    def run(self, copy: Path, tests: tuple[str, ...] | list[str], timeout_s: float = ROW_TIMEOUT_S) -> Outcome:
        """``tests`` run in ``copy`` by a forked child, as ``python -m pytest`` started there would run them."""
        assert self._process.stdin is not None
        output = copy.parent / f"{copy.name}.pytest.txt"
        request = {"cwd": str(copy), "env": environment(copy), "args": [*PYTEST_ARGS, *tests], "output": str(output)}
        self._process.stdin.write(json.dumps(request) + "\n")
        self._process.stdin.flush()
        started = self._answer(60.0)
        assert started is not None, "the zygote did not start the run"
        ended = self._answer(timeout_s)
        if ended is None:  # a hung row: its child (by its id) ends, the zygote reports the signal
            os.kill(started["pid"], signal.SIGKILL)
            ended = self._answer(60.0)
            assert ended is not None
        return Outcome(ended["code"], output.read_text(encoding="utf-8", errors="replace"))

    def close(self) -> None:
        """Close the zygote's input: it ends."""
        assert self._process.stdin is not None
        self._process.stdin.close()
        self._process.wait(timeout=60)
        self._selector.close()


@pytest.fixture(scope="session")
def zygote() -> Iterator[Zygote]:
    """One zygote per test process (per xdist worker)."""
    started = Zygote()
    yield started
    started.close()


# --- the slow tier: each row's tests fail with its mitigation removed ------------------------------------


@pytest.mark.slow
@pytest.mark.mutation
@pytest.mark.parametrize("row", [_param(row) for row in MUTATIONS])
def test_the_hazards_test_fails_without_its_mitigation(row: Row, tmp_path: Path, zygote: Zygote) -> None:
    copy = copy_tree(tmp_path / "copy")
    mutate(row, copy)
    done = zygote.run(copy, row.tests)
    if done.only_skipped:
        # A real-time test skips when the machine lacks its margin now (docs/testing.md): the
        # mitigation is then judged neither way, and saying "caught" or "missed" would be luck.
        pytest.skip(f"{row.id}: not judged now: its test skipped in the mutated tree ({done.tail(1)})")
    assert done.code == 1, (
        f"{row.id}: with the mitigation removed ({row.removes}) the tests exited {done.code}, "
        f"not 1 (a test failed): {' '.join(row.tests)}\n{done.tail()}"
    )


@pytest.mark.subprocess
@pytest.mark.slow
@pytest.mark.mutation
def test_the_copy_imports_its_own_code_also_from_a_process_started_elsewhere(tmp_path: Path) -> None:
    """What the tests' own subprocesses import (``PYTHONPATH``): the copy's packages, not the editable install's."""
    copy = copy_tree(tmp_path / "copy")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    code = "import daror_runtime, hal; print(daror_runtime.__file__); print(hal.__file__)"
    for cwd in (copy, elsewhere):
        done = subprocess.run(
            [sys.executable, "-c", code], cwd=cwd, env=environment(copy), capture_output=True, text=True, check=True
        )
        files = [Path(line).resolve() for line in done.stdout.split()]
        assert len(files) == 2
        assert all(f.is_relative_to(copy.resolve()) for f in files), (cwd, files)


@pytest.mark.slow
@pytest.mark.mutation
def test_a_mutation_of_the_copy_is_what_its_tests_run(tmp_path: Path, zygote: Zygote) -> None:
    """A control row: the copy's ``hal`` refuses to import, and the run in the copy sees it (the checkout's would not)."""
    copy = copy_tree(tmp_path / "copy")
    package = copy / "hal" / "__init__.py"
    text = package.read_text(encoding="utf-8")
    package.unlink()
    package.write_text(text + '\nraise ImportError("the mutated copy was imported")\n', encoding="utf-8")
    done = zygote.run(copy, ["tests/test_hazard_mutations.py::test_the_docs_table_and_the_yaml_agree"])
    assert done.code != 0
    assert "the mutated copy was imported" in done.output, done.tail()


#: The unmutated copy passes these rows' tests: a row's failure is its mutation's, not the copy's.
CONTROL_SAMPLE = ("H1", "H6", "H8", "H14", "H33")
#: Their tests.
CONTROL_TESTS = sorted({t for row in MUTATIONS if row.hazard in CONTROL_SAMPLE for t in row.tests})
#: With the real-time tests when a sampled test needs real time (as a row is: :func:`_param`).
CONTROL_MARKS = [pytest.mark.realtime] if any(needs_real_time(t) for t in CONTROL_TESTS) else []


@pytest.mark.slow
@pytest.mark.mutation
@pytest.mark.parametrize("sample", [pytest.param(CONTROL_SAMPLE, id="sample", marks=CONTROL_MARKS)])
def test_the_unmutated_copy_passes_a_sample_of_the_rows_tests(
    tmp_path: Path, zygote: Zygote, sample: tuple[str, ...]
) -> None:
    copy = copy_tree(tmp_path / "copy")
    tests = sorted({t for row in MUTATIONS if row.hazard in sample for t in row.tests})
    assert len(tests) >= len(CONTROL_SAMPLE)
    done = zygote.run(copy, tests)
    assert done.code == 0, done.tail()
    passed = re.search(r"\b(\d+) passed\b", done.output)
    assert passed is not None, done.tail()
    assert int(passed.group(1)) >= len(tests), done.tail()  # a parametrised test's node id runs every case
    assert not re.search(r"\b(skipped|xfailed|deselected)\b", done.output), done.tail()


# --- fast: the docs' table, the YAML and the hazards agree ---------------------------------------------


def test_a_row_that_names_a_real_time_test_runs_in_the_real_time_tier() -> None:
    """A module's ``pytestmark`` and a test's decorator are found; a row naming such a test is marked ``realtime``."""
    assert needs_real_time(
        "tests/hal/canopen/test_canopen_interop.py::test_start_up_refuses_a_drive_whose_units_are_not_its_eds[not-cia402]"
    )
    assert needs_real_time(
        "tests/hal/canopen/test_canopen_stop_reactions.py::"
        "test_on_the_hardware_code_path_the_drives_are_configured_and_the_slope_follows"
    )
    assert not needs_real_time(
        "tests/daror_runtime/session/test_session_loop.py::test_full_session_start_to_compensation"
    )
    assert not needs_real_time("tests/hal/canopen/test_canopen_stop_reactions.py::no_such_test")
    marked = {row.id for row in MUTATIONS if _param(row).marks}  # type: ignore[attr-defined]
    assert "H18-device-type-check" in marked
    assert marked == {row.id for row in MUTATIONS if any(needs_real_time(t) for t in row.tests)}
    assert [mark.name for mark in CONTROL_MARKS] == (["realtime"] if any(map(needs_real_time, CONTROL_TESTS)) else [])


def _table(markdown: str, heading: str) -> list[list[str]]:
    """The cells of the first table after ``heading`` (a ``## `` heading), without its header rows."""
    section = markdown.split(f"\n## {heading}\n", 1)
    assert len(section) == 2, f"docs/safety.md has no section '## {heading}'"
    body = section[1].split("\n## ", 1)[0]
    lines = [line for line in body.splitlines() if line.startswith("|")]
    return [[cell.strip() for cell in line.strip().strip("|").split(" | ")] for line in lines[2:]]


def _ticked(cell: str) -> list[str]:
    """The words of a cell in backticks."""
    return re.findall(r"`([^`]+)`", cell)


def test_the_docs_table_and_the_yaml_agree() -> None:
    """docs/safety.md's mutation table lists the YAML's rows (hazard, site, tests) in order; every hazard has one."""
    markdown = SAFETY.read_text(encoding="utf-8")
    hazards = {cells[0] for cells in _table(markdown, "Hazards and mitigations")}
    assert hazards, "no hazards table"
    documented = []
    for cells in _table(markdown, SECTION):
        assert len(cells) == 4, cells
        hazard, site, _removes, tests = cells
        documented.append((hazard, tuple(_ticked(site)), tuple(_ticked(tests))))
    tabled = [(row.hazard, (row.site,), ("no code site",) if row.no_code_site else row.tests) for row in ROWS]
    only_docs = [r for r in documented if r not in tabled]
    only_yaml = [r for r in tabled if r not in documented]
    assert not only_docs, f"in docs/safety.md, not in tests/hazard_mutations.yaml: {only_docs}"
    assert not only_yaml, f"in tests/hazard_mutations.yaml, not in docs/safety.md: {only_yaml}"
    assert documented == tabled, "the same rows, in another order"
    without = sorted(hazards - {row.hazard for row in ROWS}, key=lambda h: int(h.lstrip("HR")))
    assert not without, f"hazards of docs/safety.md without a row: {without}"
    unknown = sorted({row.hazard for row in ROWS} - hazards)
    assert not unknown, f"rows for hazards docs/safety.md does not list: {unknown}"
    assert len({row.id for row in ROWS}) == len(ROWS), "row names are unique per hazard"
    for row in MUTATIONS:
        for edit in row.edits:
            assert (ROOT / edit.file).is_file(), edit.file
            count = len(occurrences((ROOT / edit.file).read_text(encoding="utf-8"), edit.find))
            assert count == 1, f"{row.id}: the snippet occurs {count} times in {edit.file}"
        for test in row.tests:
            path, _, name = test.partition("::")
            assert (ROOT / path).is_file(), test
            function = name.split("[", 1)[0]
            if function:
                assert re.search(rf"def {re.escape(function)}\b", (ROOT / path).read_text(encoding="utf-8")), test


@pytest.mark.parametrize(
    ("code", "output", "only_skipped"),
    [
        (0, "s                                                 [100%]\n1 skipped in 0.25s\n", True),
        (0, "ss\n2 skipped, 3 deselected in 1.02s\n", True),
        (0, ".s\n1 passed, 1 skipped in 0.31s\n", False),  # a test ran and passed: the mutation was missed
        (1, "Fs\n1 failed, 1 skipped in 0.40s\n", False),
        (0, "", False),
    ],
)
def test_a_run_that_only_skipped_is_told_from_one_that_passed(code: int, output: str, only_skipped: bool) -> None:
    """A real-time test that skipped for want of margin leaves its row unjudged, never "caught" (H31 under load)."""
    assert Outcome(code, output).only_skipped is only_skipped
