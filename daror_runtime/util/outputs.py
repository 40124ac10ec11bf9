"""Output paths a person names: checked before any work, and one writer at a time.

A command checks its outputs before it reads or computes anything, so a wrong ``--out`` costs
nothing and leaves nothing behind:

* a file output must not be an existing directory (or FIFO, device), its folder must exist and be
  a folder we may write in, and it must not be one of the command's inputs;
* a folder output must not be an existing file, its parent must exist and be writable.

Commands that write for a long time (a protocol run, a session, a study) hold an
:func:`output_lock` on their output: a second process naming the same output is refused at once
instead of deleting or mixing the first one's files. The lock is an ``flock`` on a hidden file
beside the output (released by the kernel if the process dies), removed when the command ends.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import stat
from collections.abc import Iterator
from pathlib import Path

from daror_runtime.errors import UsageError


class OutputPathError(UsageError):
    """An output path that cannot be written: a directory where a file is meant, a missing folder, ..."""


class OutputBusyError(UsageError):
    """Another process is writing the same output."""


def _folder_problem(folder: Path) -> str | None:
    try:
        info = folder.stat()
    except FileNotFoundError:
        return f"the folder {folder} does not exist; create it first"
    except OSError as exc:
        if exc.errno == errno.ENOTDIR:
            return f"{_first_file_in(folder)} is a file, not a folder"
        if exc.errno == errno.ELOOP:
            return f"the folder {folder} is a symbolic link loop"
        return f"the folder {folder} cannot be used ({exc.strerror})"
    if not stat.S_ISDIR(info.st_mode):
        return f"{folder} is a file, not a folder"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"the folder {folder} is not writable"
    return None


def _first_file_in(folder: Path) -> Path:
    """The first component of ``folder`` that exists and is not a directory (for "X is a file")."""
    for parent in reversed((folder, *folder.parents)):
        if parent.exists() and not parent.is_dir():
            return parent
    return folder


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _stat(path: Path, expected: str) -> os.stat_result | None:
    """``path``'s status, None when it does not exist or a parent is the problem (named by the caller).

    Raises:
        OutputPathError: ``path`` is a symbolic link loop.
    """
    try:
        return path.stat()
    except FileNotFoundError:
        return None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise OutputPathError(f"{path}: a symbolic link loop; expected {expected}") from None
        return None  # a parent problem: named by the caller


def check_output_file(path: Path | str, *inputs: Path | str | None) -> Path:
    """``path`` if a file can be written there (atomically: temp file, then rename); nothing is created.

    Raises:
        OutputPathError: an existing directory, FIFO or device; a missing, unwritable or non-folder
            parent; one of ``inputs``.
    """
    path = Path(path)
    if path.name in ("", ".", ".."):
        raise OutputPathError(f"{path}: not a file name; expected a path to a file")
    info = _stat(path, "a path to a file")
    if info is not None and stat.S_ISDIR(info.st_mode):
        raise OutputPathError(f"{path}: is a directory; expected a path to a file")
    if info is not None and not stat.S_ISREG(info.st_mode):
        raise OutputPathError(f"{path}: exists and is not a regular file; expected a path to a file")
    problem = _folder_problem(path.parent)
    if problem is not None:
        raise OutputPathError(f"{path}: {problem}")
    for source in inputs:
        if source is not None and _same(path, Path(source)):
            raise OutputPathError(f"{path}: refusing to overwrite an input file; choose another output path")
    return path


def check_output_dir(path: Path | str, *inputs: Path | str | None) -> Path:
    """``path`` if a folder can be written there (created if missing, its parent must exist); nothing is created.

    Raises:
        OutputPathError: an existing file; a missing, unwritable or non-folder parent; an existing
            folder that is not writable; a folder that holds one of ``inputs`` under a name the
            command writes is the command's own business (checked by it).
    """
    path = Path(path)
    info = _stat(path, "a folder")
    if info is not None:
        if not stat.S_ISDIR(info.st_mode):
            raise OutputPathError(f"{path}: is a file; expected a folder")
        if not os.access(path, os.W_OK | os.X_OK):
            raise OutputPathError(f"{path}: the folder is not writable")
        return path
    problem = _folder_problem(path.parent if path.parent != Path("") else Path("."))
    if problem is not None:
        raise OutputPathError(f"{path}: {problem}")
    for source in inputs:
        if source is not None and _same(path, Path(source)):
            raise OutputPathError(f"{path}: refusing to write into an input; choose another output folder")
    return path


def lock_path(output: Path | str) -> Path:
    output = Path(output)
    return output.with_name(f".{output.name}.lock")


@contextlib.contextmanager
def output_lock(output: Path | str) -> Iterator[None]:
    """Hold the exclusive right to write ``output`` (a file or a folder) while the block runs.

    Raises:
        OutputBusyError: another process holds it (its pid named when known).
    """
    path = lock_path(output)
    for _ in range(5):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode("ascii", "replace").strip()
            os.close(fd)
            who = f" (pid {holder})" if holder.isdigit() else ""
            raise OutputBusyError(
                f"{output}: another daror process{who} is writing it; wait for it to finish or choose another output"
            ) from None
        # The holder before us may have removed the file after we opened it: then ours is not the lock.
        try:
            current = os.stat(path).st_ino
        except FileNotFoundError:
            current = None
        if current == os.fstat(fd).st_ino:
            break
        os.close(fd)
    else:
        raise OutputBusyError(f"{output}: its lock keeps changing hands; try again")
    try:
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode("ascii"))
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)
