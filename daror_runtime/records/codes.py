"""A pilot's code: what the settings, the console's ``pilot CODE`` and the records accept (no database here)."""

from __future__ import annotations

#: Letters, digits, ``_ . -``, at most 32, starting with a letter or digit (``P-007``): a code, never a name.
PILOT_CODE_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$"
