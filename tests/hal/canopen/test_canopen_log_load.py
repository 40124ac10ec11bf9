"""The load of each SYNC cycle of a candump log (hal/canopen/log_load.py, D160)."""

from __future__ import annotations

import gzip
from pathlib import Path

import pytest

from hal.canopen.log_load import cycle_loads

LOG = """\
(1000.000000) daror 000#0101 T
(1000.000000) daror 601#2F60600000000000 T
(1000.000000) daror 080# T
(1000.000100) daror 201#0F000000 T
(1000.000200) daror 181#370600000000 R
(1000.002500) daror 080# T
(1000.002600) daror 701#05 R
(1000.002700) daror 181#370600000000 R
(1000.002800) daror 602#2387600000000000 T
(1000.005000) daror 080# T
(1000.005100) daror 000#8001 T
"""


def test_each_cycle_is_the_frames_between_two_syncs(tmp_path: Path) -> None:
    path = tmp_path / "can.log.gz"
    with gzip.open(path, "wt") as out:
        out.write(LOG)
    loads = cycle_loads(path)
    # before the first SYNC (start-up) and after the last (shutdown): no cycle
    # cycle 1: SYNC 55 + RPDO 4 B (95) + TPDO 6 B (115) = 265; cycle 2: SYNC + heartbeat 65 + TPDO 115 + SDO 135 = 370
    assert dict(loads.bits) == {265: 1, 370: 1}
    assert (loads.cycles, loads.worst_bits) == (2, 370)
    assert loads.worst_at_s == pytest.approx(1000.0025)
    assert loads.share(370, 400.0, 1_000_000) == pytest.approx(0.148)
    assert dict(cycle_loads(path, until_s=1000.001).bits) == {265: 1}  # the cycles whose SYNC came earlier


def test_a_line_that_is_not_a_frame_and_a_cut_log_are_named(tmp_path: Path) -> None:
    text = tmp_path / "can.log"
    text.write_text(LOG + "garbage\n")
    with pytest.raises(ValueError, match=r"can.log: line 12: not a candump -L frame: 'garbage'"):
        cycle_loads(text)
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(gzip.compress(LOG.encode() * 50)[:-20])
    with pytest.raises(ValueError, match=r"cut.log.gz: the compressed log ends early"):
        cycle_loads(cut)
