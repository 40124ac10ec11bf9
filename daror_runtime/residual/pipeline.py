"""``daror residual`` as a function: load, check, diagnose, close the loop, (learn what remains,) report."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.data.signal_map import require_signal_map
from daror_runtime.errors import DataError, UsageError
from daror_runtime.residual.data import ResidualInputs, load_pair
from daror_runtime.residual.diagnosis import Closure, Diagnosis, closure, diagnose
from daror_runtime.residual.effects import FAMILIES, family
from daror_runtime.residual.evidence import DiagnosisSettings, residual_structure
from daror_runtime.residual.hysteresis import PointHistory
from daror_runtime.residual.learned import LearnedRemainder, learn_remainder, require_neural_extra
from daror_runtime.residual.model import AugmentedModel, augmented_model
from daror_runtime.residual.report import write_report
from daror_runtime.residual.structure import base_model
from daror_runtime.residual.travel import TravelChoice, choose_direction_signal, with_signal
from hal.robot import N_JOINTS, FloatArray, RobotDescription


@dataclass(frozen=True)
class ResidualRun:
    inputs: ResidualInputs
    diagnosis: Diagnosis
    closure: Closure
    model: AugmentedModel
    files: dict[str, Path]
    learned: LearnedRemainder | None = None
    travel: TravelChoice | None = None  # the direction offset against the hysteresis, when tested
    #: (points, joints) of the validation data: True where a found hysteresis's state is not in the
    #: log (:func:`unknown_hysteresis_state`); None when no hysteresis was found
    unknown_state: np.ndarray | None = None


#: ``--effects none``: test no family (the base model alone, e.g. before ``--learned``).
NO_FAMILIES = "none"


def parse_families(text: str | None) -> tuple[str, ...] | None:
    """``--effects a,b`` as family names (None: all families; ``none``: no family, an empty tuple).

    Raises:
        UsageError: an unknown or repeated name.
    """
    if text is None:
        return None
    if text.strip() == NO_FAMILIES:
        return ()
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names:
        raise UsageError(
            f"--effects {text!r}: expected comma-separated family names: {', '.join(FAMILIES)}, or {NO_FAMILIES}"
        )
    for name in names:
        family(name)
    if len(set(names)) != len(names):
        raise UsageError(f"--effects {text!r}: a family is named twice")
    return names


def unknown_hysteresis_state(diagnosis: Diagnosis, history: PointHistory, travel_rad: FloatArray) -> np.ndarray | None:
    """(points, joints) True where a point's hysteresis state is not in its log, on the joints whose hysteresis was found."""
    joints = [f.effect.joint - 1 for f in diagnosis.found if f.effect.family == "hysteresis" and f.effect.joint]
    if not joints:
        return None
    unknown = np.zeros((len(history.point_index), N_JOINTS), dtype=bool)
    unknown[:, joints] = history.undetermined(travel_rad)[:, joints]
    return unknown


def structure_on_known_states(
    diagnosis: Diagnosis, train: StationaryDataset, history: PointHistory, travel_rad: FloatArray
) -> Diagnosis:
    """The structure left in the residual judged without the training points whose hysteresis state no log determines.

    A run's first stop can come before its joints have moved far enough to settle the state: its
    points share one error no model can avoid (a model that lacks nothing has it too), which the
    remaining-structure tests would call structure (the neighbours' lag-1 autocorrelation). They
    stay in the fit; only the verdict on what remains leaves them out, and a note says so.
    """
    unknown = unknown_hysteresis_state(diagnosis, history, travel_rad)
    if unknown is None:
        return diagnosis
    kept = ~unknown.any(axis=1)
    left_out = int(len(kept) - kept.sum())
    if left_out == 0 or kept.sum() < 3:
        return diagnosis
    correlates = residual_structure(diagnosis.final_fit.residual_nm[kept], train.subset(kept), diagnosis.settings)
    note = (
        f"{left_out} training point(s) whose hysteresis state no log determines (before the joints had moved far "
        "enough after the run began) were left out of the remaining-structure tests"
    )
    return replace(diagnosis, correlates=correlates, notes=[*diagnosis.notes, note])


def run_residual(
    train_path: Path | str,
    validate_path: Path | str,
    out_dir: Path | str,
    description: RobotDescription,
    base_kind: str = "plf+",
    families: tuple[str, ...] | None = None,
    dummy_arm: bool = False,
    settings: DiagnosisSettings | None = None,
    learned: bool = False,
    raw_paths: tuple[Path | str | None, Path | str | None] | None = None,
    trust_signal_map: bool | None = None,
) -> ResidualRun:
    """The whole analysis; every check runs before anything is fitted or written.

    ``trust_signal_map``: each file's signal map is judged from physics (issue 27) and a failed one
    refused (False), or accepted and said so in the report (True); None: not judged (a caller that
    made the data itself).

    ``raw_paths``: the raw logs of the training and validation runs (the hysteresis family's
    signal); None for either: the ``NAME.raw.*`` file beside its dataset, else the points in order.

    ``learned``: after the named effects, learn what remains with a PENN and an NNN
    (:mod:`.learned`) and report what it is.

    Raises:
        ExtraNotInstalledError: ``learned`` without the extra ``nn``.
        DataError: a file that does not match, a pair that does not belong together, a
            direction effect asked for on data without ``dir``, or (SignalMapError) a file whose
            columns are not what their names say.
        UsageError: an unknown base kind or family.
        IdentifiabilityError: the training data cannot identify the base model.
    """
    base_model(base_kind, description, dummy_arm)  # refuses an unknown base before reading data
    if learned:
        require_neural_extra()
    judge = None
    if trust_signal_map is not None:
        trust = trust_signal_map

        def judge(data: StationaryDataset | RawLog) -> str | None:
            return require_signal_map(data, description, dummy_arm, trust).trust_note()

    inputs = load_pair(train_path, validate_path, raw_paths=raw_paths, judge=judge)
    settings = settings or DiagnosisSettings()
    if families is not None:
        if not inputs.has_direction:
            asked = [n for n in families if family(n).needs_direction]
            if asked:
                raise DataError(
                    f"{inputs.train.source}: no dir1..dir4 columns, but --effects asks for {', '.join(asked)}, "
                    "which needs the sign of each joint's last motion; record dir1..dir4 or drop it from --effects"
                )
        settings = replace(settings, families=families)
    diagnosis = diagnose(inputs.train, description, base_kind, settings, dummy_arm)
    train, validate, choice, unknown_state = inputs.train, inputs.validate, None, None
    histories = (inputs.train_history, inputs.validate_history)
    if "hysteresis" in settings.families and histories[0] is not None and histories[1] is not None:
        choice = choose_direction_signal(diagnosis, train, histories[0], description, settings, dummy_arm)
        if choice is not None and choice.hysteresis:
            diagnosis = choice.diagnosis
            train = with_signal(train, histories[0], choice.travel_rad)
            validate = with_signal(validate, histories[1], choice.travel_rad)
            unknown_state = unknown_hysteresis_state(diagnosis, histories[1], choice.travel_rad)
            diagnosis = structure_on_known_states(diagnosis, train, histories[0], choice.travel_rad)
    result = closure(diagnosis, validate, unknown_state)
    model = augmented_model(diagnosis.final_fit, travel_rad=diagnosis.travel_rad)
    remainder = learn_remainder(model, train, validate, description) if learned else None
    files = write_report(
        out_dir, diagnosis, result, model, train, validate, train_path, remainder, choice, inputs.signal_map_notes
    )
    return ResidualRun(inputs, diagnosis, result, model, files, remainder, choice, unknown_state)
