"""The tick's SDO traffic kept inside a cycle's bus budget (hal/canopen/cycle_budget.py, D161)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hal.canopen.busload import frame_bits
from hal.canopen.cia301.sdo import SDO_REQUEST_BASE, SdoClient
from hal.canopen.cycle_budget import HEARTBEAT_BITS, SDO_TRANSFER_BITS, CycleBudget

ONE_MBIT = 1_000_000
#: The DAROR-01's cycle: SYNC, four RPDOs of 4 bytes, eight TPDOs of 6 bytes.
DAROR_PERIODIC_BITS = frame_bits(0) + 4 * frame_bits(4) + 8 * frame_bits(6)


def test_the_numbers_of_the_daror_cycle_at_400_hz() -> None:
    assert DAROR_PERIODIC_BITS == 1355
    assert SDO_TRANSFER_BITS == 270
    assert HEARTBEAT_BITS == 65
    budget = CycleBudget(1 / 400, ONE_MBIT, DAROR_PERIODIC_BITS, {1: 0.1, 2: 0.1, 3: 0.1, 4: 0.1, 127: 0.1})
    assert budget.budget_bits == pytest.approx(1750.0)
    # Phases unknown: all five heartbeats counted in every cycle: 1750 - 1355 - 325 = 70 bits, no transfer.
    assert budget.room_bits(0.0) == pytest.approx(70.0)
    assert budget.transfers(0.0, 3) == 0
    assert budget.deferred == 3
    # Heard at five different cycles of a 100 ms period: far from them, room for one transfer (395 bits).
    for k, node in enumerate((1, 2, 3, 4, 127)):
        budget.heard(node, 0.010 * k)
    assert budget.room_bits(0.060) == pytest.approx(395.0)
    assert budget.transfers(0.060, 4) == 1
    # The cycle of node 3's next beat (0.120 s) and the ones beside it: one heartbeat, 330 bits, still one transfer.
    assert budget.room_bits(0.1175) == pytest.approx(330.0)
    # A node forgotten (restarted) counts everywhere again.
    budget.forget(2)
    assert budget.room_bits(0.060) == pytest.approx(330.0)


def test_at_500_hz_the_daror_cycle_has_room_for_nothing() -> None:
    """1355 of 2000 bits leaves 45 bits of a 70 % budget: no heartbeat and no SDO transfer fit (D160)."""
    budget = CycleBudget(1 / 500, ONE_MBIT, DAROR_PERIODIC_BITS, {})
    assert budget.room_bits(0.0) == pytest.approx(45.0)
    assert budget.room_bits(0.0) < HEARTBEAT_BITS
    assert budget.transfers(0.0, 1) == 0


@settings(max_examples=300, deadline=None)
@given(
    periods_ms=st.lists(st.integers(10, 1000), min_size=1, max_size=6),
    phases=st.lists(st.floats(0.0, 1.0), min_size=6, max_size=6),
    rate_hz=st.sampled_from([100.0, 250.0, 400.0, 500.0, 1000.0]),
    start_s=st.floats(0.0, 30.0),
)
def test_the_expected_heartbeats_never_undercount_the_ones_that_come(
    periods_ms: list[int], phases: list[float], rate_hz: float, start_s: float
) -> None:
    """Producers beating exactly on their period: every beat inside a cycle is counted for that cycle."""
    period_s = 1.0 / rate_hz
    periods = {node: ms / 1000.0 for node, ms in enumerate(periods_ms, start=1)}
    budget = CycleBudget(period_s, ONE_MBIT, 0.0, periods)
    first_s = {node: -phases[node - 1] * p - 5.0 for node, p in periods.items()}  # beats at first + k p
    for node, p in periods.items():
        # the last beat heard before the cycle (strictly before its start)
        k_last = math.ceil((start_s - first_s[node]) / p) - 1
        budget.heard(node, first_s[node] + k_last * p)
    end_s = start_s + period_s
    coming = 0
    for node, p in periods.items():
        k = math.ceil((start_s - first_s[node]) / p)
        while first_s[node] + k * p < end_s:
            if first_s[node] + k * p >= start_s:
                coming += 1
            k += 1
    assert budget.heartbeat_bits(start_s) >= coming * HEARTBEAT_BITS


def test_a_limited_sdo_client_starts_the_nodes_in_turn() -> None:
    client = SdoClient(timeout_s=0.5)
    for node in (1, 2, 3, 4):
        client.read(node, 0x1000, 0)
        client.read(node, 0x1018, 1)
    assert client.startable() == 4
    started = []
    for step in range(8):
        frames = client.frames_due(step * 0.0025, limit=1)
        assert len(frames) == 1
        cob_id, _ = frames[0]
        node = cob_id - SDO_REQUEST_BASE
        started.append(node)
        # the drive answers at once: an expedited upload response of 4 bytes
        client.on_response(node, bytes([0x43]) + frames[0][1][1:4] + b"\x92\x01\x02\x00")
    assert started == [1, 2, 3, 4, 1, 2, 3, 4]
    assert not client.busy
    assert client.frames_due(1.0, limit=0) == []
