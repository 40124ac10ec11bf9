"""Reading a file a person named: only a regular file, of bounded size, with one clear error.

Every input file of this project (YAML descriptions, settings, specs, ISB limits; model files;
datasets) is opened through these functions, so a hostile or mistaken path is refused the same
way everywhere, before anything is read:

* a missing file, a directory, a FIFO (opening one would block for ever), a device (``/dev/zero``
  would grow memory without bound), a socket, a symlink loop, a file we may not read: each named;
* a file larger than the reader's bound (a YAML file is small; a dataset may be large);
* for text, bytes that are not UTF-8 (the line named).

The error class is the caller's (a :class:`~hal.errors.InputError` subclass), so the message
reaches the person as "``FILE``: what is wrong" with exit code 2.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from hal.errors import InputError

#: Bounds by kind of file (bytes). A person's YAML file is a few kilobytes.
YAML_MAX_BYTES = 1 << 20
#: A model file: parameters and a report (a neural model's weights stay well below this).
MODEL_MAX_BYTES = 64 << 20
#: A dataset or raw log: a lab's long log (10^7 rows of 30 columns of text is about 2.5 GB).
DATA_MAX_BYTES = 8 << 30


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a named pipe (FIFO)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def regular_file(path: Path | str, error: type[InputError], max_bytes: int, what: str = "file") -> Path:
    """``path`` if it is a readable regular file of at most ``max_bytes``; never opens it.

    Raises:
        error: missing, a directory, FIFO, device or socket, a symlink loop, not readable, or too
            large; the message names the path and the problem.
    """
    path = Path(path)
    try:
        info = path.stat()  # follows symlinks; a loop raises ELOOP
    except FileNotFoundError:
        raise error(f"{path}: {what} not found") from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise error(f"{path}: a symbolic link loop, not a {what}") from None
        raise error(f"{path}: cannot read the {what} ({exc.strerror})") from None
    if not stat.S_ISREG(info.st_mode):
        raise error(f"{path}: {_kind(info.st_mode)}, not a {what}; expected a regular file")
    if info.st_size > max_bytes:
        raise error(f"{path}: {info.st_size:,} bytes; a {what} may have at most {max_bytes:,}")
    if not os.access(path, os.R_OK):
        raise error(f"{path}: {what} not readable (permission denied)")
    return path


def read_bytes_bounded(path: Path | str, error: type[InputError], max_bytes: int, what: str = "file") -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (checked again while reading: it may grow).

    Raises:
        error: see :func:`regular_file`.
    """
    path = regular_file(path, error, max_bytes, what)
    try:
        with open(path, "rb") as handle:
            data = handle.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror})") from None
    if len(data) > max_bytes:
        raise error(f"{path}: more than {max_bytes:,} bytes; a {what} may have at most {max_bytes:,}")
    return data


def read_text_bounded(path: Path | str, error: type[InputError], max_bytes: int, what: str = "file") -> str:
    """The UTF-8 text of a regular file of at most ``max_bytes``.

    Raises:
        error: see :func:`regular_file`, or bytes that are not UTF-8 (the line named).
    """
    data = read_bytes_bounded(path, error, max_bytes, what)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise error(
            f"{path}: line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x}); expected a UTF-8 {what}"
        ) from None
