"""A simulated drive's steady SYNC as straight-line code, generated once per layout of its PDOs.

:meth:`hal.canopen.sim.drive.SimulatedSeaDrive.steady_sync` is the cycle a running session nearly
always is: one RPDO (or none), then the SYNC. Written generically it walks the drive's PDO layout
(which objects, which limits, which TPDO fields, which transmission types) every SYNC, and that walk
cost seven times the work itself (issue 25, D171). This module writes that walk out once for one
layout: the RPDO's objects unpacked into names, the sensors' counts kept in names the TPDOs are
packed from, the limits and transmission types as constants. The drive asks for a new program
whenever its PDO parameters change (the layout is derived again then, as before).

The program does the same steps as the generic code, in the same order, on the same drive state
(:func:`steady_program`'s docstring lists them). ``tests/hal/canopen/test_canopen_steady_cycle.py`` holds them
to it: the same random sessions with and without the steady cycle give the same samples and the
same bus log, byte for byte.

Design time only: the source is built and compiled outside the tick (at the first steady SYNC after
a change of layout, a handful of times a session).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from hal.canopen.cia402.statemachine import PowerState

#: A steady program: ``(rpdo, q_rad, theta_rad, tau_nm, estop_operator, estop_pilot, now_s) -> applied torque, N m``.
SteadyProgram = Callable[[tuple[int, bytes] | None, float, float, float, bool, bool, float], float]
#: The program's own "no stored value" (a missing entry in the drive's stored values).
_UNSET = object()
#: An RPDO as the drive's layout gives it: comm index, unpack, length, per object its key and limits.
_SteadyRpdo = tuple[int, Callable[[bytes], tuple[Any, ...]], int, tuple[tuple[tuple[int, int], Any], ...]]
#: A TPDO as the drive's layout gives it: comm index, CAN-ID, transmission type, pack, per field its key and storage.
_SteadyTpdo = tuple[int, int, int, Callable[..., bytes], tuple[tuple[tuple[int, int] | None, bool], ...]]


def steady_program(
    drive: Any,
    rpdos: dict[int, _SteadyRpdo],
    tpdos: tuple[_SteadyTpdo, ...],
    sensors: tuple[tuple[tuple[int, int], float, tuple[int, int]], ...],
    statusword_key: tuple[int, int],
    controlword_key: tuple[int, int],
    target_torque_key: tuple[int, int],
    max_torque_key: tuple[int, int] | None,
    int16_high: int,
) -> SteadyProgram:
    """The steady SYNC of ``drive`` for this layout, compiled.

    The steps, as :meth:`SimulatedSeaDrive.steady_sync` documents them: a reading that is not
    finite goes the general way (``receive``, then ``on_sync``, which raises); the RPDO is
    unpacked and its arrival time stored; the e-stop inputs stored, the power stage supplied; the
    sensors quantised into their objects (saturated at their types); the SYNC counted; the RPDO's
    objects written in mapping order (an object with limits stored when in range; the controlword
    skipped when idle, else checked and written; any other checked and written); the statusword of
    this state and these inputs (cached per state and inputs); each TPDO packed and sent when due
    (types 1-240: every n-th SYNC; others: on a change of its data); the torque the power stage
    applies returned, N m.

    Each step's lines come from one ``_…_lines`` function below, in this order; each adds the
    constants and callables its lines name to ``names`` (the program's globals).

    Args:
        drive: the drive (its methods and dictionaries are bound into the program).
        rpdos: the valid synchronous RPDOs by CAN-ID: comm index, unpack, length, per object its
            key and its limits (None: a write that acts).
        tpdos: the valid TPDOs: comm index, CAN-ID, transmission type, pack, per field its key
            (None: the statusword) and whether it is stored rather than computed.
        sensors: per sampled object its key, scale (rad or N m per count) and bounds, in the order
            of the readings (theta, q, tau).
        statusword_key, controlword_key: the statusword (0x6041) and the controlword (0x6040).
        target_torque_key: the target torque object (0x6071).
        max_torque_key: the max torque object (0x6072) when the drive has one, else None.
        int16_high: the largest torque without a max torque object, per mille.
    """
    names = _bound_names(drive, statusword_key, target_torque_key)
    lines = _not_finite_lines()
    lines += _rpdo_unpack_lines(rpdos, names)
    sensor_lines, local_of = _inputs_and_sensor_lines(rpdos, sensors, names)
    lines += sensor_lines
    lines += _rpdo_write_lines(rpdos, controlword_key, names)
    lines += _statusword_lines()
    for n, tpdo in enumerate(tpdos):
        lines += _tpdo_lines(n, tpdo, local_of, names)
    lines += _applied_torque_lines(target_torque_key, max_torque_key, int16_high, names)
    return _compiled(lines, names, drive.node_id)


def _bound_names(drive: Any, statusword_key: tuple[int, int], target_torque_key: tuple[int, int]) -> dict[str, Any]:
    """The program's globals every layout needs: the drive's methods and dictionaries bound once (a
    global lookup in the program, not an attribute walk each SYNC), the constants, the builtins used."""
    return {
        "drive": drive,
        "isfinite": math.isfinite,
        "values": drive._values,
        "heard": drive._rpdo_heard_s,
        "last": drive._tpdo_last,
        "get": drive._get,
        "send": drive._send,
        "write": drive._write,
        "write_problem": drive._write_problem,
        "controlword_idle": drive._controlword_idle,
        "computed": drive._computed_value,
        "receive": drive.receive,
        "on_sync": drive.on_sync,
        "STATUSWORD_KEY": statusword_key,
        "OPERATION_ENABLED": PowerState.OPERATION_ENABLED,
        "UNSET": _UNSET,
        "TARGET_KEY": target_torque_key,
        "NM_PER_PERMILLE": drive._nm_per_permille,
        "int": int,
        "float": float,
        "bool": bool,
        "round": round,
        "max": max,
        "min": min,
        "isinstance": isinstance,
    }


def _not_finite_lines() -> list[str]:
    """The program's signature, and a reading that is not finite sent the general way (which raises)."""
    return [
        "def program(rpdo, q_rad, theta_rad, tau_nm, estop_operator, estop_pilot, now_s):",
        "    if not (isfinite(q_rad) and isfinite(theta_rad) and isfinite(tau_nm)):",
        "        if rpdo is not None:  # the general way: it raises ValueError, the RPDO taken first",
        "            receive(rpdo[0], rpdo[1], now_s)",
        "        on_sync(q_rad, theta_rad, tau_nm, estop_operator, estop_pilot, now_s, False)",
        "        return drive.applied_torque_nm",
    ]


def _rpdo_unpack_lines(rpdos: dict[int, _SteadyRpdo], names: dict[str, Any]) -> list[str]:
    """Step 1: the RPDO unpacked into ``r<n>_<k>`` (RPDO n, object k), its arrival time stored; none without RPDOs."""
    if not rpdos:
        return []
    lines = ["    if rpdo is not None:", "        cob = rpdo[0]"]
    for n, (cob, (comm, unpack, _, objects)) in enumerate(rpdos.items()):
        names[f"unpack_{n}"] = unpack
        fields = ", ".join(f"r{n}_{k}" for k in range(len(objects)))
        lines.append(f"        {'if' if n == 0 else 'elif'} cob == {cob:#05x}:")
        lines.append(f"            ({fields},) = unpack_{n}(rpdo[1])")
        lines.append(f"            heard[{comm:#06x}] = now_s")
    return lines


def _inputs_and_sensor_lines(
    rpdos: dict[int, _SteadyRpdo],
    sensors: tuple[tuple[tuple[int, int], float, tuple[int, int]], ...],
    names: dict[str, Any],
) -> tuple[list[str], dict[tuple[int, int], str]]:
    """Step 2: the e-stop inputs stored, the supply, the sensors quantised into ``s<k>``, the SYNC counted.

    Returns:
        The lines, and per sensor object no RPDO writes the local its count is in (what the TPDOs
        read of it is this SYNC's sample).
    """
    written_by_rpdo = {key for _, _, _, objects in rpdos.values() for key, _ in objects}
    lines = [
        "    operator, pilot = bool(estop_operator), bool(estop_pilot)",
        "    drive._estop_operator, drive._estop_pilot = operator, pilot",
        "    drive._power_cut = False",
    ]
    local_of: dict[tuple[int, int], str] = {}
    for k, ((key, scale, (low, high)), reading) in enumerate(
        zip(sensors, ("theta_rad", "q_rad", "tau_nm"), strict=False)
    ):
        names[f"SENSOR_{k}"], names[f"SCALE_{k}"] = key, scale
        lines += [
            f"    s{k} = round({reading} / SCALE_{k})",
            f"    s{k} = {low} if s{k} < {low} else {high} if s{k} > {high} else s{k}",
            f"    values[SENSOR_{k}] = s{k}",
        ]
        if key not in written_by_rpdo:  # an RPDO's write would replace the sample before the TPDOs read it
            local_of[key] = f"s{k}"
    lines.append("    sync_count = drive._sync_count = drive._sync_count + 1")
    return lines, local_of


def _rpdo_write_lines(
    rpdos: dict[int, _SteadyRpdo], controlword_key: tuple[int, int], names: dict[str, Any]
) -> list[str]:
    """Step 3: the RPDO's objects written, in mapping order; none without RPDOs."""
    if not rpdos:
        return []
    lines = ["    if rpdo is not None:"]
    for n, (cob, (_, _, _, objects)) in enumerate(rpdos.items()):
        lines.append(f"        {'if' if n == 0 else 'elif'} cob == {cob:#05x}:")
        for k, (key, limits) in enumerate(objects):
            names[f"KEY_{n}_{k}"] = key
            lines += _rpdo_object_lines(f"r{n}_{k}", f"KEY_{n}_{k}", key, limits, controlword_key)
    return lines


def _rpdo_object_lines(
    value: str,
    key_name: str,
    key: tuple[int, int],
    limits: tuple[int | None, int | None] | None,
    controlword_key: tuple[int, int],
) -> list[str]:
    """One RPDO object's write: stored when in its limits (or stored as is without bounds); with no
    limits (a write that acts) checked and written, the controlword skipped first when idle.

    Args:
        value: the local holding the unpacked value.
        key_name: the program's global holding its key.
        key: its (index, subindex).
        limits: its (low, high), either None when unbounded; None for a write that acts.
        controlword_key: the controlword's key (0x6040).
    """
    if limits is not None:
        low, high = limits
        tests = [f"{value} >= {low}"] if low is not None else []
        tests += [f"{value} <= {high}"] if high is not None else []
        if not tests:
            return [f"            values[{key_name}] = {value}"]
        return [
            f"            if not isinstance({value}, int) or ({' and '.join(tests)}):",
            f"                values[{key_name}] = {value}",
        ]
    check = f"write_problem({key[0]:#06x}, {key[1]}, {value}) is None"
    if key == controlword_key:
        check = f"not controlword_idle({value}) and {check}"
    return [
        f"            if {check}:",
        f"                write({key[0]:#06x}, {key[1]}, {value}, now_s)",
    ]


def _statusword_lines() -> list[str]:
    """Step 4a: the statusword of this state and these inputs, computed only when either changed."""
    return [
        "    power = drive._power",
        "    cached = drive._steady_statusword",
        "    if cached[0] is power and cached[1] is operator and cached[2] is pilot:",
        "        statusword = cached[3]",
        "    else:",
        "        statusword = computed(STATUSWORD_KEY)",
        "        drive._steady_statusword = (power, operator, pilot, statusword)",
    ]


def _tpdo_lines(n: int, tpdo: _SteadyTpdo, local_of: dict[tuple[int, int], str], names: dict[str, Any]) -> list[str]:
    """Step 4b: TPDO ``n`` packed, then stored as last sent and sent when due (type 1: every SYNC;
    2-240: every n-th; 0, 254, 255: on a change of its data)."""
    comm, cob, transmission, pack, fields = tpdo
    names[f"pack_{n}"] = pack
    parts = []
    for k, (key, stored) in enumerate(fields):
        if key is None:
            parts.append("statusword")
        elif stored and key in local_of:
            parts.append(local_of[key])
        elif stored:
            names[f"FIELD_{n}_{k}"] = key
            parts.append(f"(values[FIELD_{n}_{k}] if FIELD_{n}_{k} in values else get({key[0]:#06x}, {key[1]}))")
        else:
            parts.append(f"get({key[0]:#06x}, {key[1]})")
    lines = [f"    data = pack_{n}({', '.join(parts)})"]
    if transmission == 1:
        due = None  # every SYNC
    elif 1 <= transmission <= 240:
        due = f"sync_count % {transmission} == 0"
    else:  # 0 (acyclic synchronous), 254/255 (event-driven): on a change of their data
        due = f"last.get({comm:#06x}) != data"
    indent = "    "
    if due is not None:
        lines.append(f"    if {due}:")
        indent = "        "
    lines.append(f"{indent}last[{comm:#06x}] = data")
    lines.append(f"{indent}send({cob:#05x}, data)")
    return lines


def _applied_torque_lines(
    target_torque_key: tuple[int, int],
    max_torque_key: tuple[int, int] | None,
    int16_high: int,
    names: dict[str, Any],
) -> list[str]:
    """Step 5: the torque the power stage applies returned, N m (powered and supplied, no ramp: the
    caller checked): the target torque clamped at the max torque (or ``int16_high``), per mille."""
    lines = [
        "    if power is not OPERATION_ENABLED:",
        "        return 0.0",
        "    target = values.get(TARGET_KEY, UNSET)",
        f"    target = int(get({target_torque_key[0]:#06x}, {target_torque_key[1]}) if target is UNSET else target)",
    ]
    if max_torque_key is not None:  # _get's answer: a stored value, else the factory's (never computed)
        names["MAX_KEY"] = max_torque_key
        lines.append("    limit = values.get(MAX_KEY, UNSET)")
        lines.append(
            f"    limit = int(get({max_torque_key[0]:#06x}, {max_torque_key[1]}) if limit is UNSET else limit)"
        )
    else:
        lines.append(f"    limit = {int16_high}")
    lines.append("    return float(max(-limit, min(limit, target))) * NM_PER_PERMILLE")
    return lines


def _compiled(lines: list[str], names: dict[str, Any], node_id: int) -> SteadyProgram:
    """The program's source compiled and run in ``names`` (its globals); the function, its source attached."""
    source = "\n".join(lines) + "\n"
    exec(compile(source, f"<steady program of node {node_id}>", "exec"), names)
    program: SteadyProgram = names["program"]
    program.source = source  # type: ignore[attr-defined]  # for a reader (tests, a debugger)
    return program
