"""The search's winners as models: each model's best configuration fitted by ``daror fit``, and its command line.

The search ranks fold networks; it builds no model (docs/hpsearch.md). For each model it searched
(PENN, NNN) :func:`fit_winners` writes the ``daror fit`` command that trains the winning
configuration (:func:`fit_arguments`) and runs exactly that fit in this process, through the
registry, so the model file it gives (:data:`WINNER_FILES`) is what the command gives: the same
options, the same data file, the same code. The file is an ordinary model file (``daror evaluate``,
``daror cvf``, a session's ``select``).

What the line says (D132): the configuration (``--layers``, ``--width``, ``--activation``,
``--inputs``, ``--l1``), the search's training as far as ``daror fit`` has options for it
(``--thesis`` for the thesis's loss, ``--folds``, ``--adam-steps``, ``--lbfgs`` or ``--no-lbfgs``),
and the initialisations: when the grid's seeds are ``1000 a, 1000 a + 1, ..., 1000 a + N - 1``
(both built-in grids: 0 and 1), ``--seed a --inits N`` trains the very initialisations the search
trained and keeps the lowest MVL, as the search ranked them. What ``daror fit`` cannot say (another
learning rate, another number of L-BFGS iterations, initialisation seeds it cannot start from) is
listed in :attr:`Winner.differences`: the model is then the line's, trained as the line says, not
a copy of the search's network.
"""

from __future__ import annotations

import shlex
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.models.base import FitResult
from daror_runtime.models.files import model_document, training_summary
from daror_runtime.models.registry import FIT_OPTION_FLAGS, fit_model, options_for
from daror_runtime.neural.fit import TrainingDivergedError, resolve
from daror_runtime.neural.hpsearch.grid import SearchGrid
from daror_runtime.neural.hpsearch.work import NetworkRow
from daror_runtime.neural.presets import MAX_INITS
from hal.robot import RobotDescription

__all__ = ["WINNER_FILES", "Winner", "fit_arguments", "fit_options", "fit_winners"]

#: The model file of each model's winner, in the search's output folder.
WINNER_FILES: dict[str, str] = {"penn": "best_penn.json", "nnn": "best_nnn.json"}

#: The training settings a search and a fit must share for the fit to train what the search ranked
#: (``final_fit`` differs on purpose: the search ranks fold networks, the model is the final fit).
_SHARED_SETTINGS = (
    "loss",
    "folds",
    "validation_folds",
    "adam_steps",
    "learning_rate",
    "lbfgs_steps",
    "lbfgs_memory",
    "stop_tolerance",
)


@dataclass(frozen=True)
class Winner:
    """One model's best configuration, fitted as its ``daror fit`` line fits it.

    Attributes:
        model: ``penn`` or ``nnn``.
        best: the search's network of the winning configuration (its best initialisation).
        argv: the ``daror`` arguments that fit it (``fit``, the kind, ``--train``, ``--out``, options).
        file_name: the model file in the output folder (:data:`WINNER_FILES`); None when the fit
            failed (``problem`` says why).
        document: the model file's JSON document (None with ``file_name``).
        differences: what the line trains differently from the search (empty: the same training).
        problem: why no model file was written (the training diverged), or None.
    """

    model: str
    best: NetworkRow
    argv: tuple[str, ...]
    file_name: str | None
    document: dict[str, Any] | None
    differences: tuple[str, ...]
    problem: str | None = None

    @property
    def command(self) -> str:
        """The shell line: ``daror fit penn --train B.csv --out search/best_penn.json --layers 1 ...``."""
        return shlex.join(("daror", *self.argv))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, for summary.json: ``file``, ``command``, ``argv``, ``differences``, ``problem``."""
        return {
            "file": self.file_name,
            "command": self.command,
            "argv": list(self.argv),
            "differences": list(self.differences),
            "problem": self.problem,
        }


def _initialisations(grid_seeds: Sequence[int], winner_seed: int) -> tuple[dict[str, int], list[str]]:
    """``seed`` and ``inits`` for ``daror fit`` (which starts initialisation ``i`` from ``1000 seed + i``), and
    what they cannot reproduce."""
    seeds = sorted(grid_seeds)
    first = seeds[0]
    if first % 1000 == 0 and len(seeds) <= MAX_INITS and seeds == list(range(first, first + len(seeds))):
        return {"seed": first // 1000, "inits": len(seeds)}, []
    if winner_seed % 1000 == 0:
        return {"seed": winner_seed // 1000, "inits": 1}, []
    start = 1000 * (winner_seed // 1000)
    return {"seed": winner_seed // 1000, "inits": 1}, [
        f"initialisation seed {winner_seed}: daror fit starts from 1000 x --seed + i, so the model starts from "
        f"seed {start} instead"
    ]


def fit_options(best: NetworkRow, grid: SearchGrid) -> tuple[dict[str, Any], list[str]]:
    """The registry's options (field -> value) that fit the configuration of ``best`` as ``grid`` trained it, and
    what of the search's initialisations they cannot reproduce (a seed ``daror fit`` cannot start from)."""
    training = grid.training
    seeds, differences = _initialisations(grid.seeds, best.seed)
    options: dict[str, Any] = {
        **({"thesis": True} if training.loss == "thesis" else {}),
        "layers": best.layers,
        "width": best.width,
        "activation": best.activation,
        "inputs": best.inputs,
        "l1": best.l1,
        **seeds,
        "folds": training.folds,
        "adam_steps": training.adam_steps,
        "lbfgs": training.lbfgs_steps > 0,
    }
    return options, differences


def _arguments(options: dict[str, Any]) -> list[str]:
    out: list[str] = []
    for field, value in options.items():
        spelled = FIT_OPTION_FLAGS[field].split("/")  # "--lbfgs/--no-lbfgs": both ways; "--thesis": on only
        if isinstance(value, bool):
            if value or len(spelled) == 2:
                out.append(spelled[0] if value else spelled[1])
        else:
            out += [spelled[0], repr(value) if isinstance(value, float) else str(value)]
    return out


def fit_arguments(model: str, best: NetworkRow, grid: SearchGrid, train: Path | str, out: Path | str) -> list[str]:
    """The ``daror`` arguments that fit ``best``'s configuration on ``train`` into ``out`` (see the module docstring).

    ``--l1`` is written as Python's shortest repr of the float, which ``float()`` reads back exactly.
    """
    return ["fit", model, "--train", str(train), "--out", str(out), *_arguments(fit_options(best, grid)[0])]


def _settings_differences(model: str, options: dict[str, Any], grid: SearchGrid) -> list[str]:
    """The search's training settings the fit's resolved preset does not share (the learning rate of ``--thesis``)."""
    preset = resolve(model, options_for(model, options))  # type: ignore[arg-type]
    fitted, searched = preset.settings.model_dump(), grid.training.model_dump()
    return [
        f"{name}: the search trained with {searched[name]!r}, daror fit trains with {fitted[name]!r} (no option for it)"
        for name in _SHARED_SETTINGS
        if fitted[name] != searched[name]
    ]


def fit_winners(
    best: dict[str, NetworkRow],
    grid: SearchGrid,
    data: StationaryDataset,
    train: Path | str,
    out_dir: Path,
    description: RobotDescription,
    signal_map_note: str | None = None,
) -> list[Winner]:
    """Fit each model's winner as its ``daror fit`` line does; the files are not written (``report.write_outputs``).

    ``signal_map_note``: the training file's signal map failed and the user trusted it
    (``--trust-signal-map``): each winner's file says so and its line carries the flag.

    Args:
        best: each model's best network (``penn``, ``nnn``), in the order to report them.
        grid: the grid searched (its training).
        data: the training data, as read from ``train``.
        train: the training file as the person named it (it goes into the line and the file's summary).
        out_dir: the search's output folder (the line's ``--out`` is the winner's file there).
        description: the robot (the packaged DAROR-01: the line has no ``--robot``).

    Raises:
        ModelOptionError: a configuration ``daror fit`` refuses (cannot happen for a grid that was searched).
    """
    winners = []
    for model, row in best.items():
        file_name = WINNER_FILES[model]
        options, differences = fit_options(row, grid)
        differences += _settings_differences(model, options, grid)
        argv = tuple(fit_arguments(model, row, grid, train, out_dir / file_name))
        if signal_map_note is not None:
            argv = (*argv, "--trust-signal-map")
        try:
            result: FitResult = fit_model(model, data, description, options_for(model, options))
        except TrainingDivergedError as exc:
            winners.append(Winner(model, row, argv, None, None, tuple(differences), str(exc)))
            continue
        summary = training_summary(data, train)
        if signal_map_note is not None:
            summary = summary.model_copy(update={"signal_map": signal_map_note})
        document = model_document(result.model, summary, result.report)
        winners.append(Winner(model, row, argv, file_name, document, tuple(differences)))
    return winners
