"""The declared test hook: the parts of a session behind a :class:`~daror_runtime.runtime.Runtime`.

Tests and benchmarks inspect what the operator's door does not show (the safety monitor's latched
faults, the controllers of the modes, the supervisor's listeners) or provoke what no operator
request can (a fault condition in the monitor). They do it through :func:`session_core`, and only
there: library code never imports this module (``tests/test_boundaries.py``), so the console, the
web console and the tools stay behind the runtime's requests and status.
"""

from __future__ import annotations

from daror_runtime.runtime import Runtime
from daror_runtime.session.core import SessionCore

__all__ = ["session_core"]


def session_core(runtime: Runtime) -> SessionCore:
    """The session's parts (FSM supervisor, safety monitor, modes, loop, jobs) behind ``runtime``; for tests and benchmarks only."""
    return runtime._core  # the one declared way past the runtime's door
