"""The bus log's writer process: candump ``-L`` lines formatted and written beside the control loop.

:class:`hal.canopen.bus.TrafficLog` starts this file as a script in a process of its own
(``python -I -S traffic_writer.py FD PATH EPOCH_S CHANNEL GZIP_LEVEL ENCODING``), so that formatting
millions of lines runs on another core instead of in a thread that holds the control loop's GIL.
It imports the standard library only (no ``hal``, no python-can, no numpy): it starts in tens of
milliseconds.

Its protocol:

* arguments: ``FD`` the log file, opened for appending by the parent and inherited; ``PATH`` its
  name; ``EPOCH_S`` whole seconds added to robot time; ``CHANNEL`` the interface name as given to
  ``TrafficLog``; ``GZIP_LEVEL`` zlib's level of a gzip log (one gzip member whose header names the
  file as ``gzip.open`` does), or ``plain``; ``ENCODING`` the lines' (``ascii`` in a gzip log, the
  locale's in a plain one: what ``gzip.open`` and python-can's writer used before this process).
* standard input: batches, each a 4-byte little-endian length then a ``marshal`` of a list whose
  items are a frame ``(cob_id, data, robot_t_s, sent)`` (int, bytes, float in s, bool), or a list of
  received frames ``(cob_id, data, robot_t_s)`` (what the master drained in one tick, shipped as it
  is: no tuple is rebuilt per frame in the tick). Each batch is written
  with one write and flushed to the OS (a ``.gz`` log: one deflate block per batch). End of input
  (the parent's ``close()``, or the parent gone) ends the log: what came is written, the gzip member
  closed.
* standard output: at the end, one ``marshal`` of ``(lines written, error)``, error being None or
  the text of the first failure (a write that failed: ``OSError``; a batch it cannot read or a frame
  of other types). After a failure nothing more is written: the process reports and exits (status 1).

SIGINT, SIGTERM and SIGHUP are ignored: a Ctrl-C or a service stop reaches the whole process group,
and the parent ends the session in order (torque off, then the log closed); this process ends when
its input does, with every line it was given written.

The lines are python-can's ``CanutilsLogWriter``'s for a standard data frame (:class:`LineFormatter`).
"""

from __future__ import annotations

import gzip
import io
import marshal
import os
import signal
import struct
import sys
from collections.abc import Iterable, Iterator

#: A batch's length prefix on standard input: 4 bytes, little-endian, unsigned.
LENGTH = struct.Struct("<I")


class LineFormatter:
    """candump ``-L`` lines, ``(time) channel ID#DATA T|R``, as python-can's ``CanutilsLogWriter`` writes them.

    Its rules, kept: the time is ``epoch_s + robot_t_s`` (s, ``%f``); a time before the log's first
    frame is written as that first time; the channel of a number is ``canN``. The frames of a cycle
    share their time, so its text is made once a cycle.

    Args:
        epoch_s: whole seconds added to robot time (the session's start, Unix time).
        channel: the interface name written on every line.
    """

    def __init__(self, epoch_s: int, channel: str) -> None:
        self.epoch_s = epoch_s
        self.channel = f"can{channel}" if channel.isdigit() else channel
        self._first_s: float | None = None
        self._stamped_s: float | None = None  # the time of the last line's stamp, and its text
        self._stamp_text = ""
        #: Lines formatted so far.
        self.count = 0

    def lines(self, frames: Iterable[tuple[int, bytes, float, bool] | list[tuple[int, bytes, float]]]) -> str:
        """The lines of ``frames``, each ending in a newline: a frame ``(cob_id, data, robot_t_s, sent)``, or a
        list of received frames ``(cob_id, data, robot_t_s)``; :attr:`count` counts the lines.

        Raises:
            TypeError: a frame is not (int, bytes, float, bool) (``marshal`` sends a numpy scalar as bytes).
            AttributeError: a frame's data is not bytes.
            IndexError: ``sent`` is an int other than 0 and 1.
        """
        epoch, channel, first = self.epoch_s, self.channel, self._first_s
        stamped_s, stamp_text = self._stamped_s, self._stamp_text
        direction = (" R\n", " T\n")  # indexed by ``sent``: anything but a bool or an int raises
        out: list[str] = []
        append = out.append
        for cob_id, data, t_s, sent in _one_by_one(frames):
            timestamp_s = epoch + t_s
            if timestamp_s != stamped_s:
                if first is None:
                    first = timestamp_s or 0.0
                stamped_s = timestamp_s
                stamp_text = f"({max(timestamp_s, first):f}) {channel} "
            append(f"{stamp_text}{cob_id:03X}#{data.hex().upper()}{direction[sent]}")
        self._first_s, self._stamped_s, self._stamp_text = first, stamped_s, stamp_text
        self.count += len(out)
        return "".join(out)


def _one_by_one(
    items: Iterable[tuple[int, bytes, float, bool] | list[tuple[int, bytes, float]]],
) -> Iterator[tuple[int, bytes, float, bool]]:
    """A batch's frames as ``(cob_id, data, robot_t_s, sent)``: a received list flattened here, in this process.

    Raises:
        ValueError: a received frame is not ``(cob_id, data, robot_t_s)``.
    """
    for item in items:
        if type(item) is list:
            for cob_id, data, t_s in item:
                yield cob_id, data, t_s, False
        else:
            yield item


def _read_batch(source: io.BufferedReader) -> bytes | None:
    """The next batch's marshalled bytes, None at the end of input (a batch cut short is the end too)."""
    head = source.read(LENGTH.size)
    if len(head) < LENGTH.size:
        return None
    (size,) = LENGTH.unpack(head)
    body = source.read(size)
    return body if len(body) == size else None


def _report(written: int, error: str | None) -> None:
    """Tell the parent how many lines were written and the failure, if any (its standard output)."""
    try:  # noqa: SIM105 - contextlib would be one import more at start-up
        os.write(1, marshal.dumps((written, error)))
    except OSError:  # the parent is gone: nobody to tell
        pass


def main(argv: list[str]) -> int:
    """Write the batches of standard input to the log (see the module docstring); 0, or 1 after a failure.

    Args:
        argv: this script's arguments, ``[script, FD, PATH, EPOCH_S, CHANNEL, GZIP_LEVEL, ENCODING]``.
    """
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, signal.SIG_IGN)
    fd, path, epoch_s, channel, level, encoding = int(argv[1]), argv[2], int(argv[3]), argv[4], argv[5], argv[6]
    formatter = LineFormatter(epoch_s, channel)
    source = open(0, "rb", closefd=False)  # noqa: SIM115 - standard input, read for this process's whole life
    try:
        raw = open(fd, "ab")  # noqa: SIM115 - closed below, after the gzip member
    except OSError as exc:
        _report(0, str(exc))
        return 1
    file: io.BufferedIOBase = raw
    written = 0
    error: str | None = None
    try:
        if level != "plain":
            file = gzip.GzipFile(filename=path, mode="ab", compresslevel=int(level), fileobj=raw)
        while (batch := _read_batch(source)) is not None:
            frames = marshal.loads(batch)
            file.write(formatter.lines(frames).encode(encoding))  # one write a batch
            file.flush()  # whole lines reach the OS (a .gz log: a whole deflate block)
            written = formatter.count
    except OSError as exc:  # a full disk, a removed stick
        error = str(exc)
    except (TypeError, AttributeError, IndexError, ValueError, EOFError) as exc:  # UnicodeEncodeError too
        error = f"a batch of frames cannot be written as candump lines ({type(exc).__name__}: {exc})"
    for stream in (file, raw) if file is not raw else (raw,):
        try:
            stream.close()  # a .gz log: the member's end (its CRC and size), then the file
        except OSError as exc:
            error = error or str(exc)
    _report(written, " ".join(error.split()) if error is not None else None)
    return 0 if error is None else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv))
