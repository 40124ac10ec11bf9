"""A pilot's code and an operator's name: what the settings, the console and the records accept (no database here)."""

from __future__ import annotations

#: Letters, digits, ``_ . -``, at most 32, starting with a letter or digit (``P-007``): a code, never a name.
PILOT_CODE_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$"
#: Who runs a session, as the lab's records keep it: initials, a staff code or a login name (at most 64
#: letters, digits, spaces and ``_ . @ -``, starting with a letter or digit).
OPERATOR_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9 _.@-]{0,63}$"
