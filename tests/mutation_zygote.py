"""The mutation run's zygote: third-party libraries imported once, a forked child per row (tests/test_hazard_mutations.py).

A row's tests run in a copy of the repository by a fresh ``pytest.main``. Started fresh, each row
would pay the interpreter's start and the imports of numpy, scipy, numba, hypothesis, pydantic and
pytest again (about a second of CPU a row); this process imports them once (``sys.argv[1:]``, never
the repository's own packages), then forks a child for each request. The child changes to the
copy, puts it first on ``sys.path``, takes the request's environment (the copy on ``PYTHONPATH`` for
the processes the tests start), sends its output to the request's file and exits with
``pytest.main``'s code: what ``python -m pytest`` run in the copy would do, without the imports.

Requests come one JSON line at a time on stdin: ``{"cwd", "env", "args", "output"}``; for each the
zygote answers a line ``{"pid": ...}`` when the child is started, then ``{"code": ...}`` when it has
ended (the exit code; a negative one is the signal that ended it). It is started with ``-I`` (so
neither the checkout nor ``PYTHONPATH`` is on its own path) and ends when stdin closes.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import sys
import traceback
from typing import Any


def _run_child(request: dict[str, Any]) -> int:
    """In the forked child: the request's pytest run in its folder; returns the exit code."""
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)  # the zygote's requests are not the tests' input
    out = os.open(request["output"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(out, 1)
    os.dup2(out, 2)
    try:
        cwd = request["cwd"]
        os.chdir(cwd)
        os.environ.clear()
        os.environ.update(request["env"])
        sys.dont_write_bytecode = bool(os.environ.get("PYTHONDONTWRITEBYTECODE"))  # as a fresh interpreter would
        sys.path.insert(0, cwd)
        importlib.invalidate_caches()
        import pytest

        return int(pytest.main(request["args"]))
    except BaseException:  # the child must end here, whatever happened (never back into the zygote's loop)
        traceback.print_exc()
        return 3
    finally:
        sys.stdout.flush()
        sys.stderr.flush()


def _warm_numba() -> None:
    """numba's CPU target with the implementations of the modules imported so far (when numba was preloaded).

    The first kernel a process compiles or loads from its cache fills the target's typing and
    implementation registries (about 0.2 s of CPU); done here once, each child starts from it. Only
    numba's own state: a registry is refreshed again whenever a kernel is typed, so what the copy's
    code registers in the child is added there, as in a fresh process.
    """
    if "numba" not in sys.modules:
        return
    from numba.core.registry import cpu_target

    cpu_target.typing_context.refresh()
    cpu_target.target_context.refresh()


def _answer(message: dict[str, int]) -> None:
    """One line to the test process that asked."""
    sys.stdout.write(json.dumps(message) + "\n")
    sys.stdout.flush()


def main() -> None:
    """Import ``sys.argv[1:]`` (those that are installed), then serve requests until stdin closes."""
    for name in sys.argv[1:]:
        with contextlib.suppress(ImportError):  # not installed here: the child imports what it needs
            importlib.import_module(name)
    _warm_numba()
    for line in sys.stdin:
        request = json.loads(line)
        pid = os.fork()
        if pid == 0:
            os._exit(_run_child(request))
        _answer({"pid": pid})
        _, status = os.waitpid(pid, 0)
        _answer({"code": os.waitstatus_to_exitcode(status)})


if __name__ == "__main__":
    main()
