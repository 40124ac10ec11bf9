"""Ask the operating system for what a 1 kHz loop needs: real-time scheduling and locked memory.

On a control computer the loop runs with ``SCHED_FIFO`` priority (it pre-empts ordinary work, so
periodic system activity no longer delays ticks) and with its memory locked (no page fault in the
middle of a tick). Both need privileges; without them the loop still runs, the refusal is logged,
and the overrun watchdog still guards the pilot. Measured effect on the CI VM: overruns per 15 s
at 1 kHz from 7-12 (up to 3 ms late) to 2-3 (up to 1.7 ms), docs/performance.md. ``daror
rt-check`` (:mod:`daror_runtime.rt_check`) measures what a PC gives.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from dataclasses import dataclass

import structlog

log = structlog.get_logger(__name__)

_MCL_CURRENT, _MCL_FUTURE = 1, 2


@dataclass(frozen=True)
class RealtimeGrant:
    """What the OS granted (:func:`request_realtime`)."""

    fifo_priority: int | None  # the SCHED_FIFO priority obtained, None if refused
    memory_locked: bool
    refusals: tuple[str, ...]  # what was refused, and the OS's reason


def request_realtime(priority: int = 50, lock_memory: bool = True) -> RealtimeGrant:
    """Try ``SCHED_FIFO`` at ``priority`` and ``mlockall``; never raises, logs what was refused."""
    refusals: list[str] = []
    obtained: int | None = None
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        obtained = priority
    except (AttributeError, PermissionError, OSError) as exc:
        refusals.append(f"SCHED_FIFO refused ({exc})")
    locked = False
    if lock_memory:
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            locked = libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0
            if not locked:
                refusals.append(f"mlockall refused (errno {ctypes.get_errno()})")
        except OSError as exc:
            refusals.append(f"mlockall unavailable ({exc})")
    grant = RealtimeGrant(obtained, locked, tuple(refusals))
    if refusals:
        log.warning("real-time request partly refused", refusals=list(refusals))
    else:
        log.info("real-time scheduling granted", priority=obtained, memory_locked=locked)
    return grant


def release_realtime() -> None:
    """Back to ordinary scheduling, memory no longer locked (after a real-time run in a process that goes on).

    Never raises: what cannot be undone is logged. Unlocking memory that was not locked is harmless.
    """
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, PermissionError, OSError) as exc:
        log.warning("could not return to ordinary scheduling", reason=str(exc))
    try:
        # mlockall(MCL_FUTURE) would otherwise lock every page the process allocates from now on
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        if libc.munlockall() != 0:
            log.warning("could not unlock memory", errno=ctypes.get_errno())
    except OSError as exc:
        log.warning("could not unlock memory", reason=str(exc))
