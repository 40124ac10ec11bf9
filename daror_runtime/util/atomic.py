"""Crash-safe file writes: write a temporary file beside the target, then rename it into place.

A reader never sees a half-written file, and a failed write leaves the previous file (or no file)
untouched. ``os.replace`` is atomic on POSIX when source and target share a directory.
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path

from daror_runtime.errors import DarorError, UsageError


class OutputWriteError(UsageError):
    """An output could not be written because of its path (a directory, a missing or read-only folder)."""


_UMASK = os.umask(0)
os.umask(_UMASK)  # read the process umask once, at import, before any thread could race it


@contextlib.contextmanager
def atomic_path(target: Path | str, suffix: str | None = None, durable: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; on success rename it to ``target``.

    The temporary name keeps ``target``'s extension (or ``suffix``) because some writers
    (``numpy.savez``, ``scipy.io.savemat``) choose the format by extension. ``durable`` False: no
    fsync before the rename; the file is still whole or absent after the process dies (the page
    cache outlives it), only a power cut may lose it (a file rewritten often, whose next version
    is written anyway).
    """
    target = Path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(
            prefix=f".{target.name}.",
            suffix=suffix if suffix is not None else "".join(target.suffixes) or ".tmp",
            dir=target.parent,
        )
    except OSError as exc:
        raise _write_error(target, exc) from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        # mkstemp creates 0600; give the file the mode a plain open() would (or the target's own).
        os.chmod(tmp, stat.S_IMODE(target.stat().st_mode) if target.exists() else 0o666 & ~_UMASK)
        yield tmp
        if durable:
            with open(tmp, "rb+") as handle:
                os.fsync(handle.fileno())
        os.replace(tmp, target)
    except OSError as exc:
        raise _write_error(target, exc) from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


#: Errors of the path itself (a person can fix them): exit code 2. Others (a full disk): exit 1.
_PATH_ERRNOS = (errno.EISDIR, errno.ENOTDIR, errno.ENOENT, errno.EACCES, errno.EPERM, errno.EROFS, errno.ELOOP)


def _write_error(target: Path, exc: OSError) -> DarorError:
    if exc.errno in _PATH_ERRNOS:
        return OutputWriteError(f"{target}: cannot write here ({exc.strerror})")
    return DarorError(f"{target}: writing failed ({exc.strerror}); nothing was written")


def write_text_atomic(target: Path | str, text: str, durable: bool = True) -> None:
    """Write ``text`` (UTF-8) to ``target`` atomically (``durable``: see :func:`atomic_path`)."""
    with atomic_path(target, durable=durable) as tmp:
        tmp.write_text(text, encoding="utf-8")
