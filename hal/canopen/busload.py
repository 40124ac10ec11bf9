"""How much of a CAN bus a configuration takes: worst-case bits per frame, frames per cycle, the load.

A CAN 2.0A data frame with ``s`` data bytes is ``47 + 8 s`` bits before bit stuffing (start of
frame, 11-bit identifier, RTR, IDE, r0, 4-bit length, the data, 15-bit CRC, delimiters, ACK,
end of frame) plus the 3-bit interframe space. Stuffing inserts a bit after five equal ones, and
in the worst case every fourth bit of the stuffed region (34 + 8 s bits for a standard frame)
adds one (Davis, Burns, Bril and Lukkien, *Controller Area Network (CAN) schedulability analysis:
refuted, revisited and revised*, Real-Time Systems 35, 2007)::

    bits(s) = g + 8 s + 13 + floor((g + 8 s - 1) / 4),   g = 34 (standard), 54 (extended)

which is 55 + 10 s for standard frames: 135 bits at 8 bytes. One cycle of the loop carries the
SYNC and every PDO of every drive; heartbeats come on top at their own periods. The budget bounds
the **worst cycle** (D160): the cycle's frames plus every heartbeat producer's beat in the same
cycle (the drives' heartbeat timers run on their own clocks, so on a real bus any phase happens
and they drift into one cycle sooner or later: staggering them at start-up would not hold). What
is left of a cycle is for the aperiodic traffic (SDO, EMCY, NMT), which the master admits into a
cycle only where it fits (:mod:`hal.canopen.cycle_budget`). A configuration whose worst cycle
exceeds :data:`LOAD_BUDGET` is refused with the numbers; the default loop rate is the highest of
:data:`CANDIDATE_RATES_HZ` within it: for the DAROR-01's four drives on 1 Mbit/s that is 400 Hz
(1,355 + 5 x 65 = 1,680 bits of 2,500: 67.2 %); at 500 Hz the same cycle is 84.0 %.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hal.canopen.cia301.pdo import TRANSMISSION_SYNCHRONOUS, PdoMapping
from hal.errors import HalConfigError

__all__ = ["CANDIDATE_RATES_HZ", "LOAD_BUDGET", "BusLoad", "bus_load", "check_bus_load", "frame_bits", "highest_rate"]

#: The share of the bus a configuration may take: the rest is for SDO, EMCY, NMT and jitter.
LOAD_BUDGET = 0.70
#: Loop rates a default is chosen from (whole-microsecond periods that divide 1 s), Hz.
CANDIDATE_RATES_HZ = (1000.0, 500.0, 400.0, 250.0, 200.0, 125.0, 100.0)


def frame_bits(data_bytes: int, extended: bool = False) -> int:
    """Worst-case bits of one data frame with ``data_bytes`` bytes, stuffing and interframe space included.

    Raises:
        ValueError: ``data_bytes`` not 0-8.
    """
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"a CAN frame carries 0-8 data bytes, not {data_bytes}")
    g = 54 if extended else 34
    return g + 8 * data_bytes + 13 + (g + 8 * data_bytes - 1) // 4


@dataclass(frozen=True)
class BusLoad:
    """The load of one configuration.

    Attributes:
        bitrate: bit/s.
        rate_hz: the loop's (and the SYNC's) rate, Hz.
        frames_per_cycle: SYNC + every synchronous PDO of every drive, per cycle.
        bits_per_cycle: their worst-case bits.
        heartbeat_bits_per_s: the heartbeats of the drives and the master, on average, bit/s.
        heartbeat_burst_bits: every producer's heartbeat in one cycle, worst-case bits.
    """

    bitrate: int
    rate_hz: float
    frames_per_cycle: float
    bits_per_cycle: float
    heartbeat_bits_per_s: float
    heartbeat_burst_bits: float = 0.0

    @property
    def cyclic(self) -> float:
        """The share of the bus the cycle takes (0-1)."""
        return self.bits_per_cycle * self.rate_hz / self.bitrate

    @property
    def total(self) -> float:
        """The cycle and the heartbeats together, on average (0-1)."""
        return self.cyclic + self.heartbeat_bits_per_s / self.bitrate

    @property
    def worst_cycle_bits(self) -> float:
        """The cycle's frames and every heartbeat in the same cycle, worst-case bits."""
        return self.bits_per_cycle + self.heartbeat_burst_bits

    @property
    def worst_cycle(self) -> float:
        """The share of one cycle's bits its worst case takes (0-1): what :data:`LOAD_BUDGET` bounds."""
        return self.worst_cycle_bits * self.rate_hz / self.bitrate

    def describe(self) -> str:
        return (
            f"{self.frames_per_cycle:g} frames and {self.bits_per_cycle:g} worst-case bits a cycle at "
            f"{self.rate_hz:g} Hz, {self.worst_cycle_bits:g} with every heartbeat in it: {self.worst_cycle * 100:.1f} % "
            f"of the cycle's {self.bitrate / self.rate_hz:g} bits at {self.bitrate / 1e6:g} Mbit/s "
            f"(on average {self.total * 100:.1f} %)"
        )


def bus_load(pdos: tuple[PdoMapping, ...], n_drives: int, rate_hz: float, bitrate: int, heartbeat_ms: float) -> BusLoad:
    """The load of ``n_drives`` drives, each with ``pdos``, the SYNC at ``rate_hz`` and heartbeats every ``heartbeat_ms``.

    A PDO of transmission type n (1-240) is counted once every n cycles; event-driven ones (254,
    255) are not cyclic and are not counted (the DAROR mapping has none). The master's heartbeat
    is counted with the drives'.
    """
    frames = 1.0  # SYNC
    bits = float(frame_bits(0))
    for pdo in pdos:
        if TRANSMISSION_SYNCHRONOUS <= pdo.transmission_type <= 240:
            share = n_drives / pdo.transmission_type
            frames += share
            bits += share * frame_bits(pdo.length)
    heartbeat = (n_drives + 1) * frame_bits(1) * 1000.0 / heartbeat_ms
    return BusLoad(bitrate, rate_hz, frames, bits, heartbeat, (n_drives + 1) * frame_bits(1))


def check_bus_load(load: BusLoad, where: str) -> None:
    """Refuse a configuration over :data:`LOAD_BUDGET`.

    Raises:
        HalConfigError: one line with the numbers and the highest rate that fits.
    """
    if load.worst_cycle > LOAD_BUDGET:
        # The worst cycle's bits do not change with the rate; its length does: the highest rate that holds them.
        fits = math.floor(LOAD_BUDGET * load.bitrate / load.worst_cycle_bits)
        raise HalConfigError(
            f"{where}: the bus's worst cycle would be {load.worst_cycle * 100:.1f} % loaded ({load.describe()}); "
            f"the budget is {LOAD_BUDGET * 100:.0f} %: expected rate_hz at most {fits} Hz, or a higher bitrate"
        )


def highest_rate(pdos: tuple[PdoMapping, ...], n_drives: int, bitrate: int, heartbeat_ms: float) -> float:
    """The highest of :data:`CANDIDATE_RATES_HZ` whose worst cycle fits :data:`LOAD_BUDGET`.

    Raises:
        HalConfigError: not even the lowest fits.
    """
    for rate in CANDIDATE_RATES_HZ:
        if bus_load(pdos, n_drives, rate, bitrate, heartbeat_ms).worst_cycle <= LOAD_BUDGET:
            return rate
    lowest = bus_load(pdos, n_drives, CANDIDATE_RATES_HZ[-1], bitrate, heartbeat_ms)
    raise HalConfigError(f"no loop rate fits the bus: even {lowest.describe()}")
