"""The one error hierarchy of the project, rooted in :class:`DarorError`.

The root lives in ``hal`` because ``hal`` must never import ``daror_runtime``; the runtime's
errors (``daror_runtime.errors``) derive from these classes, so one ``except DarorError``
catches everything this project raises on purpose.

Two branches matter to callers:

* :class:`InputError`: something a person handed in (a file, a field, a command-line value) is
  not what was expected. The command line maps it to exit code 2 and nothing is written.
* everything else under :class:`DarorError` is a failure of the run itself (exit code 1).
"""

from __future__ import annotations


class DarorError(Exception):
    """Root of every error raised on purpose by ``hal`` and ``daror_runtime``."""


class InputError(DarorError):
    """Bad input from a person: a file, a field or a command-line value (CLI exit code 2)."""


class DescriptionError(InputError):
    """A robot description or simulation scenario file is missing, malformed or inconsistent."""


class ShapeError(DarorError, ValueError):
    """An array of the wrong shape reached an API: a programming error, not a person's input."""


class HalConfigError(InputError):
    """A HAL configuration (a YAML file or the command-line flags that stand for one) is malformed."""


class BackendUnavailableError(InputError):
    """A HAL backend that is not built yet, or that needs a Python package which is not installed."""


class HalError(DarorError):
    """The hardware (or its simulation) failed: a drive, the bus, the simulator."""


class HalNotOpenError(HalError):
    """``read``/``write`` (or a simulation hook) on a backend that is not open: call ``open()`` first."""
