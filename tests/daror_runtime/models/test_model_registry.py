"""The model registry as the one list of kinds: capabilities, per-kind options, plugins, tick kernels.

Issue 11, point 5. The registry (``daror_runtime.models.registry``) lists every kind; the settings,
the console, the CLI and the residual analysis ask it. Each kind has its own options model and
refuses an option it does not take. The ``augmented`` kind arrives through the entry point group
``daror_runtime.model_kinds`` (pyproject.toml), read lazily. A model may offer a compiled torque
for the tick (:meth:`CompensationModel.tick_kernel`).
"""

from __future__ import annotations

import importlib.metadata
import json
import re
import subprocess
import sys
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
import pytest
from pydantic import ConfigDict, Field, ValidationError

from daror_runtime.console.grammar import COMMANDS, CommandError, ParseContext, completion_words, parse_line
from daror_runtime.errors import ModelFileError, UnknownModelKindError, UsageError
from daror_runtime.models import registry
from daror_runtime.models.compare import THESIS_TABLE_III
from daror_runtime.models.files import load_model, save_model
from daror_runtime.models.linear import APModel, fit_plf_plus
from daror_runtime.models.registry import (
    BUILTIN_KINDS,
    ENTRY_POINT_GROUP,
    APOptions,
    KindRegistry,
    ModelKind,
    ModelKindPluginError,
    ModelOptionError,
    ModelOptions,
    fit_model,
    installation_options,
    kind_entry,
    kind_names,
    model_class,
    options_for,
)
from daror_runtime.models.regressor import linear_torque
from daror_runtime.residual.kind import MODEL_KIND
from daror_runtime.residual.model import AugmentedModel, AugmentedParameters
from daror_runtime.residual.structure import base_kinds, base_model
from daror_runtime.session.settings import SessionSettings
from hal.robot import RobotDescription
from tests.daror_runtime.models.test_model_files_hostile import signed

ROOT = Path(__file__).resolve().parents[3]
#: The kinds built into daror_runtime.models.registry, in their order.
BUILT_IN = ("ap", "plf", "plf+", "penn", "nnn", "penn-residual")
EVERY_KIND = (*BUILT_IN, "augmented")
#: The kinds a session may train (the neural ones are fitted with `daror fit`, docs/decisions.md D93).
SESSION_KINDS = ("ap", "plf", "plf+", "augmented")


# --- the one list --------------------------------------------------------------------------------


def test_the_installed_package_registers_augmented_through_its_entry_point() -> None:
    """pyproject.toml's entry point is installed (``pip install -e .`` after editing pyproject.toml)."""
    found = {e.name: e.value for e in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}
    assert found == {"augmented": "daror_runtime.residual.kind:MODEL_KIND"}


def test_a_clean_registry_lists_every_kind_built_in_first() -> None:
    clean = KindRegistry()
    assert clean.names() == EVERY_KIND
    assert clean.entry("augmented") is MODEL_KIND
    assert kind_names() == EVERY_KIND
    assert model_class("augmented") is AugmentedModel


@pytest.mark.subprocess
def test_listing_the_kinds_imports_no_model_code_and_no_residual_analysis() -> None:
    """Help texts and the settings check list the kinds; that must stay cheap (no numpy, no scipy)."""
    code = (
        "import sys, json\n"
        "from daror_runtime.models.registry import kind_names, kinds\n"
        "names = kind_names(); [k.summary for k in kinds()]\n"
        "print(json.dumps([list(names), sorted(m for m in sys.modules if m.startswith(('daror_runtime', 'numpy', "
        "'scipy')))]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    names, modules = json.loads(out.stdout)
    assert names == list(EVERY_KIND)
    assert not [m for m in modules if m.startswith(("numpy", "scipy"))]
    assert [m for m in modules if m.startswith("daror_runtime.residual")] == [
        "daror_runtime.residual",
        "daror_runtime.residual.kind",
    ]


def test_a_built_in_kind_is_found_without_reading_the_entry_points() -> None:
    reads: list[int] = []

    def entry_points() -> list[importlib.metadata.EntryPoint]:
        reads.append(1)
        return []

    fresh = KindRegistry(BUILTIN_KINDS, entry_points)
    assert fresh.entry("plf+").kind == "plf+"
    assert reads == []
    with pytest.raises(
        UnknownModelKindError,
        match=r"unknown model kind 'gp'; expected one of ap, plf, plf\+, penn, nnn, penn-residual$",
    ):
        fresh.entry("gp")
    assert fresh.names() == BUILT_IN
    assert reads == [1]  # read once, on the first unknown name; the list reuses it


def test_capabilities_are_attributes_of_the_entries() -> None:
    assert kind_names(lambda k: not k.needs_data) == ("ap",)
    assert kind_names(lambda k: k.residual_base) == ("ap", "plf", "plf+")
    assert kind_names(lambda k: k.session_training) == SESSION_KINDS
    assert kind_names(lambda k: k.takes("dummy_arm")) == ("ap", "penn-residual")


def test_the_residual_analysis_builds_every_base_the_registry_names(description: RobotDescription) -> None:
    assert base_kinds() == kind_names(lambda k: k.residual_base)
    for kind in base_kinds():
        assert base_model(kind, description).kind == kind
    with pytest.raises(UsageError, match=r"--base augmented: the residual analysis augments ap, plf, plf\+"):
        base_model("augmented", description)


def test_an_augmented_model_file_names_a_base_the_registry_knows(description: RobotDescription) -> None:
    with pytest.raises(ModelFileError, match=r"parameters.base_kind: 'penn'; expected one of ap, plf, plf\+"):
        AugmentedModel.from_parameters(
            description, AugmentedParameters(base_kind="penn", theta=[0.0] * 12).model_dump()
        )


def test_the_demos_kinds_are_a_registered_choice() -> None:
    from daror_runtime.demo import DEMO_KINDS  # the demo imports the whole runtime

    for kind in DEMO_KINDS:
        entry = kind_entry(kind)
        assert entry.extra is None, kind  # the demo runs on the base install (make demo)
        assert kind in THESIS_TABLE_III, kind


# --- per-kind options -----------------------------------------------------------------------------


def test_each_kind_has_its_own_frozen_strict_options() -> None:
    assert kind_entry("ap").options is APOptions
    for kind in ("plf", "plf+", "augmented"):
        assert kind_entry(kind).option_names == ("name",), kind
    options = options_for("ap", {"dummy_arm": True})
    assert isinstance(options, APOptions)
    assert (options.dummy_arm, options.with_elbow_stiffness) == (True, True)
    assert options_for("ap", {"dummy_arm": True, "elbow_stiffness": False}).with_elbow_stiffness is False
    with pytest.raises(ValidationError, match="frozen"):
        options.dummy_arm = False  # type: ignore[misc]
    with pytest.raises(ValidationError, match="Extra inputs are not permitted"):
        ModelOptions(dummy_arm=True)  # type: ignore[call-arg]


def test_an_option_the_kind_does_not_take_is_refused() -> None:
    with pytest.raises(ModelOptionError, match=r"^model kind plf does not take dummy_arm; its options: name$"):
        options_for("plf", {"dummy_arm": True})
    flags = {"name": "--name", "seed": "--seed"}
    with pytest.raises(ModelOptionError, match=r"^model kind ap does not take --seed; its options: --name, dummy_arm"):
        options_for("ap", {"seed": 3}, flags)
    with pytest.raises(ModelOptionError, match=r"^model kind ap, option dummy_arm: Input should be a valid boolean"):
        options_for("ap", {"dummy_arm": "yes"})
    assert isinstance(ModelOptionError("x"), UsageError)  # CLI exit code 2


def test_fit_model_checks_the_options_and_the_data(dataset_b, description: RobotDescription) -> None:
    train, _ = dataset_b
    with pytest.raises(ModelOptionError, match="model kind plf does not take dummy_arm"):
        fit_model("plf", train, description, APOptions(dummy_arm=True))
    # another kind's options are fine when only fields this kind takes were set
    assert fit_model("plf", train, description, APOptions(name="mine")).model.name == "mine"
    with pytest.raises(UsageError, match="model kind plf learns from data"):
        fit_model("plf", None, description)
    assert fit_model("ap", None, description, installation_options("ap", dummy_arm=True)).model.name == "A Priori"


def test_the_installed_robot_decides_only_what_the_kind_models() -> None:
    assert installation_options("ap", dummy_arm=True) == APOptions(dummy_arm=True)
    assert installation_options("plf+", dummy_arm=True, name="n") == ModelOptions(name="n")
    assert type(installation_options("augmented", dummy_arm=False)) is ModelOptions


# --- settings and console -------------------------------------------------------------------------


def test_settings_accept_the_kinds_a_session_may_train() -> None:
    for kind in kind_names(lambda k: k.session_training):
        assert SessionSettings(model_kind=kind).model_kind == kind
    with pytest.raises(ValidationError, match=r"unknown model kind 'gp'; expected one of ap, plf, plf\+, augmented"):
        SessionSettings(model_kind="gp")
    with pytest.raises(ValidationError, match="model kind 'penn' cannot be trained in a session; expected one of"):
        SessionSettings(model_kind="penn")
    with pytest.raises(ValidationError, match=r"unknown model kind 'PLF\+'"):
        SessionSettings(model_kind="PLF+")  # keys are exact, as in model files


def fake_registry(*extra: ModelKind) -> Callable[[], Iterable[importlib.metadata.EntryPoint]]:
    """Entry points naming ``extra`` (set as attributes of this module), as if packages registered them."""
    points = []
    for i, entry in enumerate(extra):
        globals()[f"FAKE_KIND_{i}"] = entry
        points.append(importlib.metadata.EntryPoint(entry.kind, f"{__name__}:FAKE_KIND_{i}", ENTRY_POINT_GROUP))
    return lambda: points


SECRET = ModelKind("secret", "not for sessions", "x:Y", "x:fit", session_training=False)


def test_a_kind_a_session_may_not_train_is_refused_by_settings_and_console(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(registry, "_REGISTRY", KindRegistry(BUILTIN_KINDS, fake_registry(SECRET)))
    assert kind_names() == (*BUILT_IN, "secret")
    with pytest.raises(ValidationError, match="model kind 'secret' cannot be trained in a session; expected one of"):
        SessionSettings(model_kind="secret")
    context = ParseContext(state_names=("idle",), has_world=False)
    with pytest.raises(CommandError, match=r"'secret' is not one of ap, plf, plf\+$"):
        parse_line("train secret", context)
    assert "secret" not in completion_words(context)["train"]


def test_the_console_trains_and_lists_the_registrys_kinds() -> None:
    context = ParseContext(state_names=("idle",), has_world=False)
    for kind in SESSION_KINDS:
        assert parse_line(f"train {kind}", context).args == (kind,)
    with pytest.raises(CommandError, match=r"'penn' is not one of ap, plf, plf\+, augmented"):
        parse_line("train penn", context)
    assert list(completion_words(context)["train"]) == list(SESSION_KINDS)
    train = next(c for c in COMMANDS if c.name == "train")
    assert "KIND: ap, plf, plf+, augmented" in train.details


# --- plugins ------------------------------------------------------------------------------------


class SeededOptions(ModelOptions):
    """A plugin kind's own options: a name and a seed."""

    seed: int = Field(0, ge=0)


class LaxOptions(ModelOptions):
    """Options that would let a misspelt option through: refused."""

    model_config = ConfigDict(extra="allow", frozen=True)


SEEDED = ModelKind("seeded", "a plugin kind with a seed", "x:Y", "x:fit", options=SeededOptions)
LAX = ModelKind("broken", "a plugin kind with lax options", "x:Y", "x:fit", options=LaxOptions)


def test_a_plugin_kind_follows_the_built_in_kinds() -> None:
    fresh = KindRegistry(BUILTIN_KINDS, fake_registry(SEEDED))
    assert fresh.names() == (*BUILT_IN, "seeded")
    assert fresh.entry("seeded") is SEEDED
    assert fresh.entry("seeded").option_names == ("name", "seed")


def test_a_plugin_kinds_options_are_checked_like_the_built_in_ones(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(registry, "_REGISTRY", KindRegistry(BUILTIN_KINDS, fake_registry(SEEDED)))
    assert options_for("seeded", {"seed": 7}) == SeededOptions(seed=7)
    with pytest.raises(ModelOptionError, match="model kind seeded, option seed: Input should be greater than or equal"):
        options_for("seeded", {"seed": -1})
    with pytest.raises(ModelOptionError, match="model kind seeded does not take dummy_arm; its options: name, seed"):
        options_for("seeded", {"dummy_arm": True})


def test_a_plugin_cannot_replace_a_built_in_kind() -> None:
    impostor = ModelKind("plf+", "an impostor", "x:Y", "x:fit", session_training=True)
    fresh = KindRegistry(BUILTIN_KINDS, fake_registry(impostor))
    assert fresh.names() == BUILT_IN  # reads the plugins: the impostor is ignored
    assert fresh.entry("plf+") is BUILTIN_KINDS[2]


@pytest.mark.parametrize(
    ("value", "problem"),
    [
        ("tests.no_such_module:MODEL_KIND", "cannot be loaded: ModuleNotFoundError"),
        (f"{__name__}:ROOT", "is a PosixPath, not a daror_runtime.models.registry.ModelKind"),
        (f"{__name__}:SEEDED", "declares kind 'seeded' under the entry point name 'broken'"),
        (f"{__name__}:LAX", "its options model must be frozen and refuse unknown fields"),
    ],
)
def test_a_broken_plugin_is_named_and_keeps_only_its_own_kind_out(value: str, problem: str) -> None:
    points = [importlib.metadata.EntryPoint("broken", value, ENTRY_POINT_GROUP)]
    fresh = KindRegistry(BUILTIN_KINDS, lambda: points)
    assert fresh.names() == BUILT_IN
    with pytest.raises(
        ModelKindPluginError, match=f"model kind 'broken' is registered but cannot be used: .*{problem}"
    ):
        fresh.entry("broken")


def test_a_kind_registered_twice_differently_is_refused() -> None:
    points = [
        importlib.metadata.EntryPoint("seeded", f"{__name__}:SEEDED", ENTRY_POINT_GROUP),
        importlib.metadata.EntryPoint("seeded", f"{__name__}:OTHER_SEEDED", ENTRY_POINT_GROUP),
    ]
    fresh = KindRegistry(BUILTIN_KINDS, lambda: points)
    with pytest.raises(ModelKindPluginError, match="registered more than once"):
        fresh.entry("seeded")


OTHER_SEEDED = ModelKind("seeded", "the same name from another package", "x:Y", "x:fit")


def test_a_model_class_must_declare_its_registry_kind(monkeypatch: pytest.MonkeyPatch) -> None:
    liar = ModelKind("liar", "its class says plf", "daror_runtime.models.linear:PLFModel", "x:fit")
    monkeypatch.setattr(registry, "_REGISTRY", KindRegistry(BUILTIN_KINDS, fake_registry(liar)))
    with pytest.raises(ModelKindPluginError, match="declares kind 'plf'"):
        model_class("liar")


# --- tick kernels -------------------------------------------------------------------------------


def test_linear_models_offer_the_compiled_linear_torque(dataset_b, description: RobotDescription) -> None:
    train, validation = dataset_b
    for model in (APModel.from_description(description, True, True), fit_plf_plus(train, description).model):
        kernel = model.tick_kernel()
        assert kernel is not None
        assert kernel.function is linear_torque
        for q in validation.q_rad[:10]:
            out = np.empty(4)
            kernel.function(q, kernel.parameters, out)
            assert out == pytest.approx(model.torque(q), abs=1e-12)


def test_a_model_without_a_compiled_torque_offers_none(description: RobotDescription) -> None:
    parameters = AugmentedParameters(base_kind="plf+", theta=[0.0] * 12, torque_gain=[1.1, 1.0, 1.0, 1.0])
    assert AugmentedModel(description, parameters).tick_kernel() is None


def test_model_files_look_their_kind_up_in_the_registry(
    tmp_path: Path, description: RobotDescription, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "model.json"
    save_model(path, APModel.from_description(description, True, True))
    document = json.loads(path.read_text(encoding="utf-8"))
    for kind, error, message in [
        ("gp", ModelFileError, "unknown model kind 'gp'; expected one of ap, plf, plf+, penn, nnn, penn-residual"),
        ("broken", ModelKindPluginError, "model kind 'broken' is registered but cannot be used"),
    ]:
        path.write_text(json.dumps(signed({**document, "kind": kind})), encoding="utf-8")
        points = [importlib.metadata.EntryPoint("broken", "tests.no_such_module:MODEL_KIND", ENTRY_POINT_GROUP)]
        monkeypatch.setattr(registry, "_REGISTRY", KindRegistry(BUILTIN_KINDS, lambda points=points: points))
        with pytest.raises(error, match=f"^{re.escape(f'{path}: {message}')}"):
            load_model(path)
