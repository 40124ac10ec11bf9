"""Which aperiodic frames a SYNC cycle has room for: the tick's SDO traffic kept inside the bus budget.

The periodic traffic of a cycle (the SYNC, every synchronous PDO) is fixed by the mapping; the
heartbeats come at their own periods, and the master knows roughly when: each producer's last
heartbeat plus its period. What is left of the cycle's budget (:data:`hal.canopen.busload.LOAD_BUDGET`
of the bits one cycle can carry) is what the master may spend on SDO transfers in the tick (the
torque slope it follows, a lost drive's reconfiguration). A transfer is a request and a response of
up to 8 bytes each; the response may land in the cycle after the request, so a transfer is admitted
only when both cycles have room for all of it (D161). Nothing waits: a transfer that does not fit
waits in the SDO client's queue for a later cycle, and its SDO timeout starts when it is sent.

A producer whose phase is not known yet (no heartbeat heard since it was configured) is counted in
every cycle: the budget errs towards leaving the bus alone.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from hal.canopen.busload import LOAD_BUDGET, frame_bits

__all__ = ["SDO_TRANSFER_BITS", "CycleBudget"]

#: Worst-case bits of one SDO transfer: an 8-byte request and an 8-byte response.
SDO_TRANSFER_BITS = 2 * frame_bits(8)
#: Worst-case bits of one heartbeat (1 data byte).
HEARTBEAT_BITS = frame_bits(1)


class CycleBudget:
    """The room a cycle has for SDO transfers, from its periodic bits and the heartbeats expected in it.

    Args:
        period_s: the SYNC period, s.
        bitrate: the bus bit rate, bit/s.
        periodic_bits: worst-case bits of the cycle's fixed traffic (SYNC and synchronous PDOs).
        heartbeat_periods_s: every heartbeat producer on the bus (the drives' node ids, and the
            master's own under its node id) and its period, s.
        budget: the share of a cycle's bits that may be used (0-1).

    Raises:
        ValueError: a period or the bit rate not positive.
    """

    def __init__(
        self,
        period_s: float,
        bitrate: int,
        periodic_bits: float,
        heartbeat_periods_s: Mapping[int, float],
        budget: float = LOAD_BUDGET,
    ) -> None:
        if period_s <= 0 or bitrate <= 0 or any(p <= 0 for p in heartbeat_periods_s.values()):
            raise ValueError("the SYNC period, the bit rate and every heartbeat period must be positive")
        self.period_s = period_s
        self.budget_bits = budget * bitrate * period_s
        self.periodic_bits = periodic_bits
        self._period_s = dict(heartbeat_periods_s)
        self._last_s: dict[int, float | None] = dict.fromkeys(heartbeat_periods_s)
        #: Transfers held back because their cycle had no room (counted for the bus report).
        self.deferred = 0

    def heard(self, node_id: int, t_s: float) -> None:
        """A heartbeat (or the master's own) of ``node_id`` went over the bus at ``t_s``: its phase."""
        if node_id in self._last_s:
            self._last_s[node_id] = t_s

    def forget(self, node_id: int) -> None:
        """``node_id`` restarts or is reconfigured: its heartbeat's phase is unknown until it is heard again."""
        if node_id in self._last_s:
            self._last_s[node_id] = None

    def heartbeat_bits(self, start_s: float) -> float:
        """Worst-case bits of the heartbeats that may fall in the cycle ``[start_s, start_s + period)``.

        A producer is expected when its next beat (last + k periods) lands within the cycle, widened
        by one cycle each side for the jitter of the drives' own clocks and of the reception time.
        """
        end_s = start_s + self.period_s
        bits = 0.0
        for node_id, last_s in self._last_s.items():
            if last_s is None:
                bits += HEARTBEAT_BITS
                continue
            period = self._period_s[node_id]
            # beats last + k periods (k >= 0: one heard in this cycle is in it) inside the widened window; several if it beats faster
            first_k = max(0, math.ceil((start_s - self.period_s - last_s) / period))
            last_k = math.floor((end_s + self.period_s - last_s) / period)
            bits += HEARTBEAT_BITS * max(0, last_k - first_k + 1)
        return bits

    def room_bits(self, start_s: float) -> float:
        """Bits left in the cycle starting at ``start_s`` after its periodic traffic and its expected heartbeats."""
        return self.budget_bits - self.periodic_bits - self.heartbeat_bits(start_s)

    def transfers(self, start_s: float, wanted: int) -> int:
        """How many of ``wanted`` SDO transfers may start in the cycle at ``start_s`` (this and the next cycle have room).

        The ones that do not fit are counted in :attr:`deferred`.
        """
        if wanted <= 0:
            return 0
        room = min(self.room_bits(start_s), self.room_bits(start_s + self.period_s))
        fits = max(0, int(room // SDO_TRANSFER_BITS))
        admitted = min(wanted, fits)
        self.deferred += wanted - admitted
        return admitted
