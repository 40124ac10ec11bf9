"""The master's handling of one TPDO, as straight-line code generated once per TPDO at configuration.

Every cycle the master decodes eight TPDOs. Written generically (a loop over the mapped objects'
fields, ``setattr`` and ``int`` on each value) that walk cost more than the work (issue 25, D171).
:func:`tpdo_handler` writes it out for one TPDO of one drive: the length test, the unpack into
names, each value to its field of the drive's state, the statusword's power state, and whether the
frame answers the last SYNC. The master builds the handlers once, with its routes.

The handler does what :meth:`hal.canopen.master.CanMaster._dispatch` did for a TPDO, in the same
order; ``tests/hal/canopen/test_canopen_steady_cycle.py`` and the golden sessions hold it to that.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from hal.canopen.cia402.statemachine import PowerState

#: ``(data, t_s, sync, sync_s) -> latency s``: the frame's delay after the last SYNC if it answers it, else -1.0.
TpdoHandler = Callable[[bytes, float, int, float], float]

#: ``struct`` codes whose values are Python ints already (others, a REAL32 or a BOOLEAN, go through ``int``).
_INT_CODES = frozenset("bBhHiIqQ")


def tpdo_handler(
    drive: Any,
    k: int,
    unpack: Callable[[bytes], tuple[int | float | bool, ...]],
    codes: str,
    fields: tuple[str, ...],
    length: int,
    power_of: Callable[[int], PowerState | None],
    latch: Callable[[str], None],
) -> TpdoHandler:
    """The handler of TPDO ``k`` (0-based) of ``drive``, compiled.

    Args:
        drive: the master's record of the drive (its fields are set by name).
        k: the TPDO's number - 1 (its entry in ``drive.tpdo_syncs``).
        unpack: the TPDO codec's unpack; ``codes`` its ``struct`` codes, one per mapped object.
        fields: the drive's field each mapped object goes to, in mapping order.
        length: the TPDO's data length, bytes (another length is latched as a fault and not decoded).
        power_of: the power state of a statusword.
        latch: the master's fault latch.
    """
    names: dict[str, Any] = {"drive": drive, "unpack": unpack, "power_of": power_of, "latch": latch,
                             "FAULT": PowerState.FAULT, "int": int, "len": len}  # fmt: skip
    values = [f"v{n}" for n in range(len(fields))]
    lines = [
        "def handler(data, t_s, sync, sync_s):",
        f"    if len(data) != {length}:",
        f"        latch(f'drive {drive.node_id}: TPDO{k + 1} of {{len(data)}} bytes; expected {length}')",
        "        return -1.0",
        f"    ({', '.join(values)},) = unpack(data)",
    ]
    for value, field, code in zip(values, fields, codes, strict=True):
        lines.append(f"    drive.{field} = {value}" if code in _INT_CODES else f"    drive.{field} = int({value})")
    if "statusword" in fields:
        lines += [
            "    power = power_of(drive.statusword or 0)",
            "    if drive.emcy is not None and drive.power is FAULT and power is not FAULT:",
            "        drive.emcy = None  # a fault reset cleared it, even from a drive that sends no error reset EMCY",
            "    drive.power = power",
        ]
    lines += [
        "    if t_s >= sync_s:  # an answer to the last SYNC (one before it came late: kept, but not fresh)",
        f"        drive.tpdo_syncs[{k}] = sync",
        "        return t_s - sync_s",
        "    return -1.0",
    ]
    source = "\n".join(lines) + "\n"
    exec(compile(source, f"<TPDO{k + 1} handler of node {drive.node_id}>", "exec"), names)
    handler: TpdoHandler = names["handler"]
    handler.source = source  # type: ignore[attr-defined]  # for a reader (tests, a debugger)
    return handler
