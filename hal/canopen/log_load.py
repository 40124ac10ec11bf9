"""The load of each SYNC cycle of a bus log, counted as the budget counts it (D160).

Reads a candump ``-L`` log (``(stamp) channel ID#DATA [T|R]``, gzip when the name ends in ``.gz``:
what ``daror hil`` and ``--hal-config ... traffic_log`` write) and adds the worst-case bits of every
frame (:func:`hal.canopen.busload.frame_bits`: 55 + 10 s for a standard frame) between one SYNC and
the next. The frames before the first SYNC (start-up in pre-operational) and after the last one
(the shutdown) belong to no cycle.
"""

from __future__ import annotations

import gzip
import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from hal.canopen.busload import frame_bits
from hal.canopen.cia301.nmt import SYNC_COB_ID

__all__ = ["CycleLoads", "cycle_loads"]


@dataclass(frozen=True)
class CycleLoads:
    """The cycles of a log: how many carried how many worst-case bits.

    Attributes:
        bits: worst-case bits of a cycle -> how many cycles carried that many.
        worst_at_s: the log's stamp of the SYNC that opened the worst cycle, s (None: no cycle).
    """

    bits: Counter[int]
    worst_at_s: float | None

    @property
    def cycles(self) -> int:
        return sum(self.bits.values())

    @property
    def worst_bits(self) -> int:
        return max(self.bits, default=0)

    def share(self, bits: int, rate_hz: float, bitrate: int) -> float:
        """``bits`` as a share of what one cycle at ``rate_hz`` can carry (0-1)."""
        return bits * rate_hz / bitrate


def cycle_loads(path: Path, until_s: float | None = None) -> CycleLoads:
    """Worst-case bits of every SYNC cycle in the candump log at ``path``.

    ``until_s``: only the cycles whose SYNC's stamp is earlier (the log's clock), e.g. to leave out
    the shutdown, whose torque-off cycles a lock-step run sends at one robot time; None: all.

    Raises:
        OSError: the file cannot be read.
        ValueError: a line is not a candump ``-L`` frame (the message names the line), or a
            compressed log ends early.
    """
    opener = gzip.open if path.suffix == ".gz" else open
    found: Counter[int] = Counter()
    try:
        with opener(path, "rt", encoding="ascii") as lines:
            worst_at = _count(path, lines, found, math.inf if until_s is None else until_s)
    except EOFError:
        raise ValueError(f"{path}: the compressed log ends early (a run still writing it, or cut short)") from None
    return CycleLoads(found, worst_at)


def _count(path: Path, lines: Iterable[str], found: Counter[int], until_s: float) -> float | None:
    """Add each cycle of ``lines`` to ``found``; the stamp of the worst cycle's SYNC (None: no cycle)."""
    open_bits: int | None = None
    open_stamp = 0.0
    worst_bits, worst_at = -1, None
    for number, line in enumerate(lines, start=1):
        parts = line.split()
        if len(parts) < 3 or "#" not in parts[2] or not parts[0].startswith("("):
            raise ValueError(f"{path}: line {number}: not a candump -L frame: {line.strip()[:80]!r}")
        ident, _, data = parts[2].partition("#")
        bits = frame_bits(len(data) // 2, extended=len(ident) > 3)
        if int(ident, 16) == SYNC_COB_ID and len(ident) == 3:
            if open_bits is not None and open_stamp < until_s:
                found[open_bits] += 1
                if open_bits > worst_bits:
                    worst_bits, worst_at = open_bits, open_stamp
            open_bits, open_stamp = bits, float(parts[0].strip("()"))
        elif open_bits is not None:
            open_bits += bits
    # What follows the last SYNC (the shutdown: torque off, NMT) is no cycle: no SYNC closes it.
    return worst_at
