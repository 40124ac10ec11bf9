"""A third-party package's registration of a HAL backend: the tests' stand-in drives, from outside.

The distribution ``daror-standin`` (this folder: this module and its ``.dist-info``) declares, in
its ``entry_points.txt``, the entry point ``stand-in = daror_standin:BACKEND`` in the group
``daror_runtime.hal_backends``; with this folder on ``sys.path`` (as if pip had installed it),
daror-runtime's registry finds it (``hal.registry``) and the backend appears in ``--hal``, in
configuration files and in the HAL contract suite, with no edit to daror-runtime or its tests.
The backend itself, its configuration model and its contract benches are in
``tests/standin_drives.py``.
"""

from __future__ import annotations

from hal.registry import BackendEntry

#: What the entry point names: the backend, its configuration model and its contract benches.
BACKEND = BackendEntry(
    "stand-in",
    target="tests.standin_drives:StandInDrives",
    config="tests.standin_drives:StandInHalConfig",
    benches="tests.standin_drives:contract_benches",
)
