"""What a session did, kept for the lab's records: the states it reached, its faults, the support it gave.

Appended in a transition or between ticks: list appends, never I/O. ``session.json`` carries it
(``history``), and the records database reads it from there (:mod:`daror_runtime.records`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

#: At most this many faults are kept (a fault that persists is latched once per occurrence).
MAX_FAULTS = 500


def utc_now() -> str:
    """The wall-clock time now, UTC, ISO 8601 to the second (what ``session.json`` and provenance files hold)."""
    return datetime.now(UTC).isoformat(timespec="seconds")


@dataclass
class SessionHistory:
    """The session's course, for the records (not for the loop: nothing reads it in the tick)."""

    started_utc: str = field(default_factory=utc_now)
    states_reached: list[str] = field(default_factory=list)  # in the order first reached
    reached_at_s: dict[str, float] = field(default_factory=dict)  # robot time each was first reached, s
    faults: list[str] = field(default_factory=list)  # "kind: message", at most MAX_FAULTS
    faults_dropped: int = 0
    estop_tests: int = 0  # e-stop presses in the states that test them (expected, not faults)
    support_levels: list[float] = field(default_factory=list)  # each support level the operator set

    def reached(self, state: str, t_s: float | None = None) -> None:
        if state not in self.states_reached:
            self.states_reached.append(state)
            if t_s is not None:
                self.reached_at_s[state] = t_s

    def fault(self, text: str) -> None:
        if len(self.faults) < MAX_FAULTS:
            self.faults.append(text)
        else:
            self.faults_dropped += 1

    def support(self, level: float) -> None:
        if not self.support_levels or self.support_levels[-1] != level:
            self.support_levels.append(float(level))

    def as_dict(self) -> dict[str, Any]:
        return {
            "started_utc": self.started_utc,
            "states_reached": list(self.states_reached),
            "reached_at_s": dict(self.reached_at_s),
            "faults": list(self.faults),
            "faults_dropped": self.faults_dropped,
            "estop_tests": self.estop_tests,
            "support_levels": list(self.support_levels),
        }
