"""The traffic log's own formatter writes exactly the lines python-can's ``CanutilsLogWriter`` writes (D163)."""

from __future__ import annotations

import io
import random
from pathlib import Path

import can

from hal.canopen.bus import TrafficLog

EPOCH = 1_700_000_000


def _python_can_lines(frames: list[tuple[int, bytes, float, bool]], channel: str) -> list[str]:
    stream = io.StringIO()
    writer = can.CanutilsLogWriter(stream, channel=channel)
    for cob_id, data, t_s, sent in frames:
        writer.on_message_received(
            can.Message(timestamp=EPOCH + t_s, arbitration_id=cob_id, data=data, is_extended_id=False,
                        is_rx=not sent, channel=channel, check=False)
        )  # fmt: skip
    return stream.getvalue().splitlines()


def test_the_log_lines_are_python_cans_byte_for_byte(tmp_path: Path) -> None:
    rng = random.Random(25)
    frames = [(0x080, b"", 0.5, True), (0x705, b"\x05", 0.25, False)]  # the second: before the first frame
    t_s = 0.5
    for _ in range(2000):
        t_s += rng.choice((0.0, 0.0025, 1e-7, 123.456789))
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
        frames.append((rng.randrange(0x800), data, t_s, rng.random() < 0.5))
    for channel in ("can0", "vcan1", "7"):
        path = tmp_path / f"{channel}.log"
        log = TrafficLog(path, epoch_s=EPOCH, channel=channel)
        for frame in frames:
            log.frame(*frame)
        log.close()
        assert path.read_text().splitlines() == _python_can_lines(frames, channel)
        assert log.frames_written == len(frames)
