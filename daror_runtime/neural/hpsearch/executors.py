"""Where the search's work units run: local worker processes, or Ray tasks.

Both executors run the same function on the same units
(:func:`daror_runtime.neural.hpsearch.work.train_unit`), so they give the same numbers. Units are
handed out in the order given (the caller puts the most expensive first, so the last units to
finish are short). Each finished unit is passed to ``on_done`` as it arrives.

* :func:`run_local`: a :class:`concurrent.futures.ProcessPoolExecutor` of ``workers`` processes
  started with ``spawn`` (a fresh interpreter: no copy of a parent that may hold JAX's threads).
  The training data goes to the workers in a file (a pickle in a private temporary folder, removed
  at the end) that each reads once when it starts; what goes through the pipes to a worker, its
  start and its units, is a few hundred bytes each. Through the pipes, the 140 kB of dataset B
  would outgrow a pipe's 64 kB: a parent writing it to a worker that died meanwhile blocks for
  ever (the start of a worker is written by the main thread, which would hang the command; a
  unit, by the queue's thread, which a shutdown then waits for). The workers ignore
  Ctrl-C; on an interruption or an error the parent ends them (SIGTERM, then waits) before it
  re-raises, and on Linux a worker whose parent dies (even by SIGKILL) is ended by the kernel, so
  no worker outlives the command.
* :func:`run_ray`: the units as Ray tasks of one CPU each, on the cluster at ``address``, or on a
  local instance started here (and shut down at the end) with ``workers`` CPUs. Ray is the
  optional extra ``ray``. A Ray instance the caller already started (``ray.init``) is used as it is.
"""

from __future__ import annotations

import importlib
import logging
import multiprocessing
import multiprocessing.context
import os
import pickle
import tempfile
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from types import ModuleType
from typing import Any

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import DarorError
from daror_runtime.models.registry import ExtraNotInstalledError
from daror_runtime.neural.hpsearch.work import (
    UnitResult,
    WorkerSetup,
    WorkUnit,
    start_local_worker,
    train_unit,
    train_unit_in_worker,
)

__all__ = ["EXECUTORS", "WorkerDiedError", "require_ray", "run_local", "run_ray"]

#: The executors ``--executor`` names.
EXECUTORS = ("local", "ray")

#: Seconds a terminated worker gets to exit before it is killed.
_TERMINATE_WAIT_S = 5.0

OnDone = Callable[[UnitResult], None]


class WorkerDiedError(DarorError):
    """A worker process died while training (killed, out of memory): exit code 1, nothing written."""


class _SpawnContext(multiprocessing.context.SpawnContext):
    """The ``spawn`` context, remembering the processes it starts (the pool's workers), to end them."""

    def __init__(self) -> None:
        super().__init__()
        self.started: list[multiprocessing.process.BaseProcess] = []

    def Process(self, *args: Any, **kwargs: Any) -> multiprocessing.process.BaseProcess:  # noqa: N802 - the context's API
        process = multiprocessing.context.SpawnProcess(*args, **kwargs)
        self.started.append(process)
        return process

    def end_all(self) -> None:
        """Terminate every worker still running and wait for it (killed if it does not exit)."""
        alive = [p for p in self.started if p.is_alive()]
        for process in alive:
            process.terminate()
        for process in alive:
            process.join(_TERMINATE_WAIT_S)
            if process.is_alive():
                process.kill()
                process.join()


def run_local(
    units: Sequence[WorkUnit], data: StationaryDataset, setup: WorkerSetup, workers: int, on_done: OnDone
) -> list[UnitResult]:
    """Train ``units`` in ``workers`` local processes; results in the order they finished.

    Raises:
        WorkerDiedError: a worker process died.
        KeyboardInterrupt: Ctrl-C (the workers are ended first).
        Whatever a unit raised (the workers are ended first).
    """
    with tempfile.TemporaryDirectory(prefix="daror-hpsearch-") as folder:
        data_file = Path(folder) / "data.pickle"
        with open(data_file, "wb") as handle:
            pickle.dump(data, handle, protocol=pickle.HIGHEST_PROTOCOL)
        context = _SpawnContext()
        pool = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=context,
            initializer=start_local_worker,
            initargs=(setup, str(data_file), os.getpid()),
        )
        done: list[UnitResult] = []
        pending: set[Future[UnitResult]] = set()
        try:
            pending = {pool.submit(train_unit_in_worker, unit, setup) for unit in units}
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in finished:
                    result = future.result()
                    done.append(result)
                    on_done(result)
        except BrokenProcessPool:
            _stop(pool, context)
            raise WorkerDiedError("a worker process died (killed, or out of memory); nothing was written") from None
        except BaseException:
            _stop(pool, context)
            raise
        pool.shutdown()
    return done


def _stop(pool: ProcessPoolExecutor, context: _SpawnContext) -> None:
    """End the pool: no further unit starts, the workers are ended, the pool's threads are joined.

    The pool's own thread cancels the units not started (``cancel_futures``): a unit cancelled from
    here would stay among the pool's pending items, and when the pool then finds its workers ended
    it sets the error on that cancelled unit; in Python 3.11 that raises in the pool's thread,
    which dies before it closes the pipe to the workers, and the command waits for ever on a
    thread writing into that pipe.
    """
    pool.shutdown(wait=False, cancel_futures=True)
    context.end_all()
    pool.shutdown(wait=True)


def require_ray() -> ModuleType:
    """The ``ray`` module.

    Raises:
        ExtraNotInstalledError: Ray is not installed (one line: what to install; exit code 2).
    """
    try:
        return importlib.import_module("ray")
    except ImportError as exc:
        raise ExtraNotInstalledError(
            "--executor ray needs the optional extra 'ray', which is not installed: "
            f"pip install 'daror-runtime[ray]' ({exc})"
        ) from None


def run_ray(
    units: Sequence[WorkUnit],
    data: StationaryDataset,
    setup: WorkerSetup,
    workers: int,
    address: str | None,
    on_done: OnDone,
) -> list[UnitResult]:
    """Train ``units`` as Ray tasks; results in the order they finished.

    ``address``: a running cluster (``ray.init(address=...)``); None starts a local instance with
    ``workers`` CPUs. A Ray instance already initialised in this process is used as it is and left
    running.

    Raises:
        ExtraNotInstalledError: Ray is not installed.
        WorkerDiedError: a Ray worker died.
        KeyboardInterrupt: Ctrl-C (the tasks are cancelled first).
        Whatever a unit raised (the unit's own exception, as the local executor raises it).
    """
    ray = require_ray()
    started = not ray.is_initialized()
    if started:  # Ray's own messages at ERROR only: the command's output is its progress and its result
        if address is None:
            ray.init(
                address="local",
                num_cpus=workers,
                include_dashboard=False,
                log_to_driver=False,
                logging_level=logging.ERROR,
            )
        else:
            ray.init(address=address, log_to_driver=False, logging_level=logging.ERROR)
    try:
        task = ray.remote(num_cpus=1, max_retries=0)(train_unit)
        data_ref = ray.put(data)
        pending = [task.remote(unit, data_ref, setup) for unit in units]
        done: list[UnitResult] = []
        try:
            while pending:
                finished, pending = ray.wait(pending, num_returns=1)
                for ref in finished:
                    try:
                        result = ray.get(ref)
                    except (
                        ray.exceptions.WorkerCrashedError,
                        ray.exceptions.OutOfMemoryError,
                        ray.exceptions.NodeDiedError,
                    ):
                        raise WorkerDiedError(
                            "a Ray worker died (killed, or out of memory); nothing was written"
                        ) from None
                    except ray.exceptions.RayTaskError as exc:  # the unit's own error, not Ray's traceback text
                        if isinstance(exc.cause, BaseException):
                            raise exc.cause from None
                        raise
                    done.append(result)
                    on_done(result)
        except BaseException:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
        return done
    finally:
        if started:
            ray.shutdown()
