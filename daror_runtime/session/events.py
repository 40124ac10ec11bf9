"""What the operator is told as it happens: transitions, faults, finished work, refused models.

The runtime appends an :class:`Announcement` whenever something happens that the operator must
know without asking (a fault, a state change, identification or training done, a model refused);
the console drains the feed and shows each one on its own line, apart from the prompt. Appending
never blocks (a bounded deque: the oldest are dropped if nobody reads, and the drop is counted), so
the tick may announce.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import StrEnum


class AnnouncementKind(StrEnum):
    TRANSITION = "transition"
    FAULT = "fault"
    REACTION = "reaction"  # what a fault made the robot do, and how it goes on
    IDENTIFICATION = "identification"
    MODEL = "model"
    JOB_FAILED = "job failed"
    SESSION = "session"


@dataclass(frozen=True, slots=True)
class Announcement:
    t_s: float | None  # robot time, when known
    kind: AnnouncementKind
    text: str  # one plain sentence


class Announcements:
    """A bounded feed of announcements, written by any thread, drained by the console.

    Lock-free, so the tick never waits for the console: a deque's ``append`` and ``popleft`` are
    atomic in CPython.

    Args:
        capacity: announcements kept while nobody drains them (the oldest are dropped first).
    """

    def __init__(self, capacity: int = 1000) -> None:
        self._items: deque[Announcement] = deque(maxlen=capacity)
        self.dropped = 0  # counted without a lock: a statistic, may miss a drop under a race

    def announce(self, kind: AnnouncementKind, text: str, t_s: float | None = None) -> None:
        """Add one; never blocks."""
        if len(self._items) == self._items.maxlen:
            self.dropped += 1
        self._items.append(Announcement(t_s, kind, text))

    def drain(self) -> list[Announcement]:
        """Everything announced since the last drain, oldest first."""
        items = []
        while True:
            try:
                items.append(self._items.popleft())
            except IndexError:
                return items
