"""Packages installed from outside daror-runtime, for a test: a folder of distributions put on ``sys.path``.

:data:`OUTSIDE_BACKEND` is the tests' stand-in drives as a third-party package
(``tests/data/outside_backend``: a module and its ``daror_standin-0.1.dist-info`` whose entry point
registers the HAL backend ``stand-in``). :func:`installed` puts such a folder on ``sys.path`` and
makes the HAL registry read the entry points again, as a fresh process with that package installed
would; afterwards both are as they were.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from hal.registry import forget_discovered_backends

#: The stand-in drives' distribution (tests/standin_drives.py's backend, registered from outside).
OUTSIDE_BACKEND = Path(__file__).resolve().parent / "data" / "outside_backend"


@contextmanager
def installed(folder: Path = OUTSIDE_BACKEND) -> Iterator[None]:
    """The distributions of ``folder`` installed for the ``with`` block (their modules importable, their entry points read)."""
    sys.path.insert(0, str(folder))
    importlib.invalidate_caches()  # importlib.metadata caches what each sys.path folder holds
    forget_discovered_backends()
    try:
        yield
    finally:
        sys.path.remove(str(folder))
        importlib.invalidate_caches()
        forget_discovered_backends()
