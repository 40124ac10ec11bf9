"""``python -m daror_runtime.cli``: the ``daror`` command."""

from daror_runtime.cli import main

raise SystemExit(main())
