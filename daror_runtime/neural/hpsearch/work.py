"""The search's work unit, one network shape, and what a worker does with it.

A :class:`WorkUnit` is one network shape (model, layers, width, activation, inputs) with every L1
rate and seed of the grid: all of them are trained in one
:func:`~daror_runtime.neural.training.train_group` call (one compiled program, ``jax.vmap`` over
the networks). :func:`train_unit` runs in a worker process (a local process or a Ray task): it
prepares the process once (:func:`prepare_worker`: XLA's threads, JAX's persistent compilation
cache), trains the unit and returns one :class:`NetworkRow` per network, plain numbers only, so
the result is small to send back.

**What a row says about a network** (the fold network at its minimal validation loss, as the thesis
selects it; with ``validation_folds`` > 1 the fold networks, one per held-out block):

* ``mvl``: the minimal validation loss (the loss's data term on the held-out block, no penalty:
  dimensionless for the scaled loss, Nm^2 for the thesis's) and ``mvl_step``, its loss evaluation;
* ``val_rmse_nm``: the RMSE (Nm, over every joint of every point, Eq. 4.31) of the fold network at
  the MVL step on its held-out block; with several held-out blocks, the root of the mean over the
  blocks of each block's mean squared error (so for the thesis's loss it is ``sqrt(mvl)``);
* ``train_loss_at_mvl``: the fold networks' training loss (data term plus penalty) at the MVL step;
* ``torque_rms_nm`` and ``collapsed``: the RMS of that network's torque over all the training
  points; collapsed when it is below :data:`~daror_runtime.neural.fit.COLLAPSE_FRACTION` of the
  data's torque RMS (the network learned nothing, as the thesis's loss does at lambda 0.1).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import pickle
import signal
import sys
import threading
from dataclasses import dataclass

import numpy as np

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.models.neural import NetworkSpec, network_torque_batch
from daror_runtime.neural.compile_cache import use_compilation_cache
from daror_runtime.neural.fit import COLLAPSE_FRACTION
from daror_runtime.neural.training import NetworkResult, PreparedData, TrainingSettings, prepare_data, train_group

__all__ = [
    "ONE_XLA_THREAD",
    "NetworkRow",
    "UnitResult",
    "WorkUnit",
    "WorkerSetup",
    "prepare_worker",
    "start_local_worker",
    "train_unit",
    "train_unit_in_worker",
]

#: XLA flags that keep a worker's computations on its own thread: the search's parallelism is its
#: workers, one per core; XLA's own threads would only compete with the other worker's, and a
#: reduction split over another number of threads rounds differently (the numbers would depend on
#: the machine's load and the worker count; docs/hpsearch.md).
ONE_XLA_THREAD = ("--xla_cpu_multi_thread_eigen=false",)


@dataclass(frozen=True)
class WorkerSetup:
    """How a worker process is prepared before its first unit.

    Attributes:
        cache_dir: JAX's persistent compilation cache (None: none); shared by the workers.
        one_xla_thread: set :data:`ONE_XLA_THREAD` in ``XLA_FLAGS`` (only effective before the
            process's first JAX computation, which is why the worker does it, not the caller).
    """

    cache_dir: str | None
    one_xla_thread: bool


_prepared_lock = threading.Lock()
_prepared: list[WorkerSetup] = []


def prepare_worker(setup: WorkerSetup) -> None:
    """Prepare this process for training (once; later calls do nothing): XLA's threads, the compilation cache.

    Every program is cached, however small or quick to compile: a cached program loads in
    milliseconds, and the search compiles 144 of them.
    """
    with _prepared_lock:
        if _prepared:
            return
        if setup.one_xla_thread:
            flags = os.environ.get("XLA_FLAGS", "").split()
            os.environ["XLA_FLAGS"] = " ".join(flags + [f for f in ONE_XLA_THREAD if f not in flags])
        if setup.cache_dir is not None:
            use_compilation_cache(setup.cache_dir)
        _prepared.append(setup)


#: The training data of this local worker process (set once by :func:`start_local_worker`).
_worker_data: list[StationaryDataset] = []

#: Linux's ``prctl`` option: the signal a process gets when its parent dies.
_PR_SET_PDEATHSIG = 1


def _die_with_parent(parent: int) -> None:
    """Ask Linux to end this process (SIGTERM) when its parent dies; elsewhere nothing.

    A worker must not outlive the command: killed by SIGKILL, the command cannot end its workers
    itself, and a worker would otherwise train on (for minutes) with nobody to read its result.
    """
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    if os.getppid() != parent:  # the parent died before the request: end now
        os.kill(os.getpid(), signal.SIGTERM)


def start_local_worker(setup: WorkerSetup, data_file: str, parent: int) -> None:
    """A local worker's initialiser: dies with ``parent`` (the command's pid), leaves Ctrl-C to it
    (it ends the workers), reads the training data from ``data_file`` (a pickle the parent wrote,
    see :mod:`.executors`) and keeps it for every unit, prepares the process (:func:`prepare_worker`)."""
    _die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with open(data_file, "rb") as handle:
        _worker_data[:] = [pickle.load(handle)]  # the parent's own file, in its private folder
    prepare_worker(setup)


def train_unit_in_worker(unit: WorkUnit, setup: WorkerSetup) -> UnitResult:
    """:func:`train_unit` on the data :func:`start_local_worker` kept (a local worker's task).

    Raises:
        RuntimeError: the process was not started by :func:`start_local_worker`.
        DataError, IdentifiabilityError: see :func:`train_unit`.
    """
    if not _worker_data:
        raise RuntimeError("train_unit_in_worker runs in a worker started by start_local_worker")
    return train_unit(unit, _worker_data[0], setup)


@dataclass(frozen=True)
class WorkUnit:
    """One network shape and every ``(lambda, seed)`` of the grid: one ``train_group`` call.

    Attributes:
        index: the unit's place in the grid's order of shapes (results are reported in it).
        spec: the shape.
        lambdas: L1 rates, in the grid's order.
        seeds: initialisation seeds, in the grid's order.
        settings: how to train.
    """

    index: int
    spec: NetworkSpec
    lambdas: tuple[float, ...]
    seeds: tuple[int, ...]
    settings: TrainingSettings

    @property
    def n_networks(self) -> int:
        return len(self.lambdas) * len(self.seeds)

    def cost(self) -> float:
        """A relative estimate of the unit's training time, to start the expensive units first.

        Per point and step a hidden layer costs about ``width * (width + 8)`` (its product and its
        activation); a PENN's torque is a gradient, and its training a gradient of that: about
        twice an NNN's (measured: 21 x 25 PENN 88 ms a step, NNN 47 ms; docs/hpsearch.md).
        """
        s = self.spec
        per_layer = s.width * (s.width + 8)
        return (2.0 if s.model == "penn" else 1.0) * (s.layers * per_layer + s.n_weights) * self.n_networks


@dataclass(frozen=True)
class NetworkRow:
    """One trained network of the search (see the module docstring for what each figure is).

    ``group_wall_s``, ``group_cpu_s`` and ``group_compile_s`` are of the whole unit (its networks
    are trained together): wall-clock seconds, the worker's CPU seconds (all threads), of which
    compiling or loading the compiled program from the cache.
    """

    model: str
    layers: int
    width: int
    activation: str
    inputs: str
    l1: float
    seed: int
    mvl: float
    mvl_step: int
    val_rmse_nm: float
    train_loss_at_mvl: float
    torque_rms_nm: float
    collapsed: bool
    group_wall_s: float
    group_cpu_s: float
    group_compile_s: float


@dataclass(frozen=True)
class UnitResult:
    """A trained unit: its rows (lambdas outer, seeds inner) and its cost."""

    unit: WorkUnit
    rows: tuple[NetworkRow, ...]
    wall_s: float
    cpu_s: float
    compile_s: float


def _mean_square(network_params: np.ndarray, result: NetworkResult, q: np.ndarray, tau: np.ndarray) -> float:
    """Mean squared torque error (Nm^2, over points and joints) of one weight vector; inf if not finite."""
    try:
        network = result.scaling.network(result.spec, network_params)
    except ValueError:  # weights that are not finite numbers: training diverged
        return float("inf")
    with np.errstate(all="ignore"):
        error = network_torque_batch(network, q) - tau
        value = float(np.mean(error**2))
    return value if np.isfinite(value) else float("inf")


def _torque_rms(network_params: np.ndarray, result: NetworkResult, q: np.ndarray) -> float:
    """RMS (Nm) of a network's torque over ``q``; inf when it is not finite."""
    return float(np.sqrt(_mean_square(network_params, result, q, np.zeros_like(q))))


def _row(
    result: NetworkResult, prepared: PreparedData, data_rms: float, unit_result: tuple[float, float, float]
) -> NetworkRow:
    blocks = result.settings.held_out()
    squares = [
        _mean_square(params, result, prepared.q[prepared.fold == block], prepared.tau[prepared.fold == block])
        for params, block in zip(result.mvl_parameters, blocks, strict=True)
    ]
    torque_rms = _torque_rms(result.mvl_parameters[0], result, prepared.q)
    wall, cpu, compile_s = unit_result
    spec = result.spec
    return NetworkRow(
        model=spec.model,
        layers=spec.layers,
        width=spec.width,
        activation=spec.activation,
        inputs=spec.inputs,
        l1=result.l1,
        seed=result.seed,
        mvl=result.mvl,
        mvl_step=result.mvl_step,
        val_rmse_nm=float(np.sqrt(np.mean(squares))),
        train_loss_at_mvl=float(result.train_curve[result.mvl_step]),
        torque_rms_nm=torque_rms,
        collapsed=bool(data_rms > 0 and torque_rms < COLLAPSE_FRACTION * data_rms),
        group_wall_s=wall,
        group_cpu_s=cpu,
        group_compile_s=compile_s,
    )


def train_unit(unit: WorkUnit, data: StationaryDataset, setup: WorkerSetup) -> UnitResult:
    """Train every network of ``unit`` on ``data`` together (:func:`train_group`) and describe each.

    Raises:
        DataError, IdentifiabilityError: data that cannot be trained on (see
            :func:`~daror_runtime.neural.training.prepare_data`; the caller checks this first).
    """
    prepare_worker(setup)
    results = train_group(unit.spec, data, unit.lambdas, unit.seeds, unit.settings)
    prepared = prepare_data(unit.spec, data, unit.settings)
    data_rms = float(np.sqrt(np.mean(prepared.tau**2)))
    first = results[0]
    cost = (first.wall_s, first.cpu_s, first.compile_s)
    rows = tuple(_row(r, prepared, data_rms, cost) for r in results)
    return UnitResult(unit, rows, first.wall_s, first.cpu_s, first.compile_s)
