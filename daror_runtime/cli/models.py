"""``daror fit``, ``daror evaluate``, ``daror cvf``: compensation models fitted, compared, tested (Tables III, IV).

Every list of model kinds in their help comes from the model registry
(:mod:`daror_runtime.models.registry`; cheap: it imports no model code).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import structlog
from rich.console import Console

from daror_runtime.cli.common import (
    TRUST_SIGNAL_MAP_HELP,
    CommandParser,
    Commands,
    UsageError,
    bind,
    output_file,
    write_json,
)

log = structlog.get_logger(__name__)


def register(commands: Commands) -> None:
    """``daror fit``, ``daror evaluate`` and ``daror cvf`` on ``commands``."""
    _register_fit(commands)

    ev = commands.add_parser("evaluate", help="RMSE and nRMSE of models on a dataset (Table III)")
    ev.add_argument("models", type=Path, nargs="+", metavar="MODEL.json")
    ev.add_argument("--data", type=Path, required=True, help="stationary dataset or raw log")
    ev.add_argument("--json", type=Path, help="write the figures as JSON here")
    ev.add_argument("--trust-signal-map", action="store_true", help=TRUST_SIGNAL_MAP_HELP)
    bind(ev, cmd_evaluate)

    cvf = commands.add_parser("cvf", help="closed-path energy test: is the model conservative? (Table IV)")
    cvf.add_argument("models", type=Path, nargs="+", metavar="MODEL.json")
    cvf.add_argument("--json", type=Path, help="write the figures as JSON here")
    cvf.add_argument("--start", type=_joint_angles, help="start q1,q2,q3,q4 in rad (default: centre of the range)")
    cvf.add_argument(
        "--refinements",
        type=int,
        choices=[1, 2],
        default=2,
        help="tenfold step refinements after pi/400 (default 2: down to pi/40000)",
    )
    cvf.add_argument("--strict", action="store_true", help="exit 1 when a model is not conservative")
    bind(cvf, cmd_cvf)


def _register_fit(commands: Commands) -> None:
    """``daror fit KIND``: its kinds, and which kind takes each option, from the registry."""
    from daror_runtime.models.registry import kinds

    every_kind = kinds()
    without_data = [k.kind for k in every_kind if not k.needs_data]

    def taken_by(option: str) -> str:
        return ", ".join(k.kind for k in every_kind if k.takes(option)) or "no registered kind"

    fit = commands.add_parser(
        "fit",
        help=f"fit a compensation model: {', '.join(k.kind for k in every_kind)}",
        epilog="model kinds:\n" + "\n".join(f"  {k.kind:10s} {k.summary}" for k in every_kind),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    fit.add_argument("kind", help=f"model kind: {', '.join(k.kind for k in every_kind)} (see the list below)")
    fit.add_argument(
        "--train", type=Path, help=f"stationary dataset or raw log (optional for {', '.join(without_data)})"
    )
    fit.add_argument("--out", type=Path, required=True, help="model file to write (JSON)")
    fit.add_argument("--name", help="model name shown in tables (default: the kind's name)")
    fit.add_argument("--robot", type=Path, help="robot description YAML (default: the packaged DAROR-01)")
    fit.add_argument("--trust-signal-map", action="store_true", help=TRUST_SIGNAL_MAP_HELP)
    fit.add_argument(
        "--dummy-arm",
        action="store_true",
        default=None,
        help=f"{taken_by('dummy_arm')}: include the Dummy Arm (Eq. 4.5)",
    )
    stiff = fit.add_mutually_exclusive_group()
    stiff.add_argument(
        "--elbow-stiffness",
        dest="elbow_stiffness",
        action="store_true",
        default=None,
        help=f"{taken_by('elbow_stiffness')}: include the first-order elbow stiffness (Eq. 4.7); default with --dummy-arm",
    )
    stiff.add_argument("--no-elbow-stiffness", dest="elbow_stiffness", action="store_false")
    fit.add_argument(
        "--seed", type=int, default=None, help=f"random seed of the models that use one ({taken_by('seed')})"
    )
    _add_network_flags(fit, taken_by)
    fit.add_argument(
        "--base",
        default=None,
        metavar="KIND",
        help=f"{taken_by('base')}: the physical model fitted first "
        f"({', '.join(k.kind for k in every_kind if k.physical)}; default plf+)",
    )
    bind(fit, cmd_fit)


def _add_network_flags(fit: CommandParser, taken_by: Callable[[str], str]) -> None:
    """The neural kinds' options of ``daror fit`` (daror_runtime.neural.presets): each replaces one field of the preset.

    ``taken_by(option)`` names the kinds that take ``option``. Values are checked by the kind's
    options model, so a kind that does not take one refuses it.
    """
    nets = taken_by("layers")
    fit.add_argument(
        "--thesis",
        action="store_true",
        default=None,
        help=f"{taken_by('thesis')}: the thesis's network and loss (Tables I, II; Eq. 3.7) instead of the default",
    )
    fit.add_argument("--layers", type=int, default=None, metavar="N", help=f"{nets}: hidden layers (1-32)")
    fit.add_argument("--width", type=int, default=None, metavar="N", help=f"{nets}: units per hidden layer (1-256)")
    fit.add_argument("--activation", default=None, metavar="A", help=f"{nets}: tanh, sigmoid, relu or softplus")
    fit.add_argument("--inputs", default=None, metavar="q|sincos", help=f"{nets}: q, or [sin q, cos q] (Eq. 4.28)")
    fit.add_argument("--l1", type=float, default=None, metavar="X", help=f"{taken_by('l1')}: L1 rate lambda")
    fit.add_argument(
        "--inits", type=int, default=None, metavar="N", help=f"{taken_by('inits')}: initialisations (best MVL kept)"
    )
    fit.add_argument("--folds", type=int, default=None, metavar="K", help=f"{taken_by('folds')}: validation blocks")
    fit.add_argument(
        "--adam-steps", dest="adam_steps", type=int, default=None, metavar="N", help=f"{nets}: full-batch Adam steps"
    )
    lbfgs = fit.add_mutually_exclusive_group()
    lbfgs.add_argument(
        "--lbfgs", dest="lbfgs", action="store_true", default=None, help=f"{taken_by('lbfgs')}: finish with L-BFGS"
    )
    lbfgs.add_argument("--no-lbfgs", dest="lbfgs", action="store_false")


def _joint_angles(text: str) -> list[float]:
    """A flag type: ``q1,q2,q3,q4`` in rad (argparse's one-line error otherwise)."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected four comma-separated angles in radians") from None
    if len(values) != 4:
        raise argparse.ArgumentTypeError(f"{text!r}: expected four angles (q1,q2,q3,q4), got {len(values)}")
    return values


def _fit_options_given(args: argparse.Namespace) -> dict[str, Any]:
    """The model options given on the ``daror fit`` command line, by field name (flags left out are absent)."""
    from daror_runtime.models.registry import FIT_OPTION_FLAGS

    given = {field: getattr(args, field) for field in FIT_OPTION_FLAGS}
    return {field: value for field, value in given.items() if value is not None}


def cmd_fit(args: argparse.Namespace, console: Console) -> int:
    """Fit a model of ``KIND`` (its options from the flags) and write its model file.

    Raises:
        UsageError: a kind that learns from data without ``--train``, or a flag the kind does not take.
    """
    from daror_runtime.data.load import load_stationary_checked
    from daror_runtime.models.files import save_model, training_summary
    from daror_runtime.models.registry import FIT_OPTION_FLAGS, fit_model, kind_entry, options_for
    from hal.robot import load_description

    kind = args.kind.lower()
    entry = kind_entry(kind)
    # the kind's own options: a flag it does not take is refused here, before any work
    options = options_for(kind, _fit_options_given(args), FIT_OPTION_FLAGS)
    if args.train is None and entry.needs_data:
        raise UsageError(f"model kind {kind} learns from data; give --train FILE")
    output_file(args.out, args.train)
    description = load_description(args.robot)
    dataset, signal_map = (
        load_stationary_checked(args.train, description, bool(args.dummy_arm), args.trust_signal_map)
        if args.train is not None
        else (None, None)
    )
    log.info("fit requested", kind=kind, train=None if args.train is None else str(args.train))
    result = fit_model(kind, dataset, description, options)
    summary = training_summary(dataset, args.train) if dataset is not None else None
    trusted = signal_map.trust_note() if signal_map is not None else None
    if summary is not None and trusted is not None:
        summary = summary.model_copy(update={"signal_map": trusted})
    save_model(args.out, result.model, summary, result.report)
    report = result.report
    log.info("model written", path=str(args.out), kind=kind, duration_s=round(report.duration_s, 6))
    console.print(f"{args.out}: {result.model.display_name} model {result.model.name!r} ({kind})")
    if trusted is not None:
        console.print(f"  training data {trusted}", markup=False)
    if report.training is not None:
        t = report.training
        console.print(
            f"  training: {t.n_points} points, RMSE {t.rmse_nm:.4g} Nm, nRMSE {t.nrmse:.4g}, per joint "
            + " ".join(f"{v:.3g}" for v in t.rmse_per_joint_nm)
        )
    if report.rank is not None:
        console.print(f"  regressor rank {report.rank} of {report.n_parameters} parameters; identifiable combinations:")
        for b in report.base_parameters:
            console.print(f"    {b.expression():58s} = {b.value:+.5g} +- {b.std_error:.2g}")
        if report.unidentifiable:
            console.print(f"  no effect on torque at all: {', '.join(report.unidentifiable)}")
    for note in report.notes:
        console.print(f"  {note}")
    return 0


def _load_models(paths: Sequence[Path]) -> tuple[list[Any], list[Any]]:
    """The models of ``paths`` and their files' training summaries; models of one name labelled apart by their paths."""
    from daror_runtime.models.compare import distinct_labels
    from daror_runtime.models.files import load_model

    loaded = [load_model(p) for p in paths]
    models = [model for model, _ in loaded]
    for model, label in zip(models, distinct_labels([m.name for m in models], paths), strict=True):
        model.name = label
    return models, [contents.training for _, contents in loaded]


def cmd_evaluate(args: argparse.Namespace, console: Console) -> int:
    """RMSE and nRMSE (Nm) of the models on a dataset, with their extrapolation; optionally as JSON."""
    from daror_runtime.data.load import load_stationary_checked
    from daror_runtime.models.compare import evaluate_models, evaluation_document, evaluation_table
    from hal.robot import load_description

    if args.json is not None:
        output_file(args.json, args.data, *args.models)
    from daror_runtime.residual.data import prediction_signal

    models, training = _load_models(args.models)
    # the models' own robot: the relations are judged with its springs and geometry
    description = models[0].description if models else load_description()
    data, signal_map = load_stationary_checked(args.data, description, trust_signal_map=args.trust_signal_map)
    trusted = signal_map.trust_note()
    signals = [prediction_signal(m, data, args.data) for m in models]
    evaluations = evaluate_models(models, data, signals, training)
    console.print(evaluation_table(evaluations, f"Errors on {args.data} ({len(data)} points), Eq. 4.31-4.32"))
    if trusted is not None:
        console.print(f"{args.data}: {trusted}", markup=False)
    for e in evaluations:
        x = e.extrapolation
        if x is not None and x.n_outside and x.rmse_outside_nm is not None:
            inside = "none inside" if x.rmse_inside_nm is None else f"{x.rmse_inside_nm:.3g} Nm inside"
            console.print(
                f"{e.name}: {x.n_outside} of {x.n_points} points outside its training range, extrapolated: "
                f"RMSE {x.rmse_outside_nm:.3g} Nm there, {inside}"
            )
    if args.json is not None:
        document = evaluation_document(evaluations)
        if trusted is not None:
            document["signal_map"] = trusted
        write_json(args.json, document)
        console.print(f"{args.json}: written")
    return 0


def cmd_cvf(args: argparse.Namespace, console: Console) -> int:
    """The closed-path energy test of each model; exit 1 with ``--strict`` when one is not conservative."""
    from daror_runtime.models.compare import cvf_document, cvf_models, cvf_table
    from daror_runtime.models.cvf import THESIS_STEPS_RAD

    if args.json is not None:
        output_file(args.json, *args.models)
    models, _ = _load_models(args.models)
    steps = THESIS_STEPS_RAD[: args.refinements + 1]
    evaluations = cvf_models(models, args.start, steps)
    console.print(cvf_table(evaluations))
    if args.json is not None:
        write_json(args.json, cvf_document(evaluations))
        console.print(f"{args.json}: written")
    return 0 if all(e.result.conservative for e in evaluations) or not args.strict else 1
