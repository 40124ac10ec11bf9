"""Issue 24, defect 9: a model file whose parameters belong to another kind, or whose parameter vector has the
wrong length for its kind, is refused by every reader (``load_model``; ``daror evaluate`` and ``daror cvf``
exit 2 with one line naming the file and the field, and write nothing).

Each file is a genuine one edited and signed again (its checksum recomputed), as a person who edits
a file and fixes its checksum would: the checksum then says nothing, and the check of the kind has
to answer.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from daror_runtime.cli import main
from daror_runtime.data.load import write_dataset
from daror_runtime.data.schema import StationaryDataset
from daror_runtime.errors import ModelFileError
from daror_runtime.models.files import load_model, save_model, training_summary
from daror_runtime.models.linear import build_ap, fit_plf, fit_plf_plus
from hal.robot import RobotDescription

Document = dict[str, Any]


def _signed(document: Document) -> Document:
    body = {k: v for k, v in document.items() if k != "checksum_sha256"}
    canonical = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()
    return {**body, "checksum_sha256": hashlib.sha256(canonical).hexdigest()}


@pytest.fixture(scope="module")
def genuine(
    tmp_path_factory: pytest.TempPathFactory,
    dataset_b: tuple[StationaryDataset, StationaryDataset],
    description: RobotDescription,
) -> dict[str, Path]:
    """Genuine model files of every linear kind (A Priori with and without the elbow stiffness), and data."""
    folder = tmp_path_factory.mktemp("genuine")
    train, validation = dataset_b
    paths = {name: folder / f"{name}.json" for name in ("plf", "plf+", "ap", "ap_plain")}
    for name, result in (
        ("plf", fit_plf(train, description)),
        ("plf+", fit_plf_plus(train, description)),
        ("ap", build_ap(description, None, True, True)),
        ("ap_plain", build_ap(description, None, False, False)),
    ):
        save_model(paths[name], result.model, training_summary(train), result.report)
    paths["data"] = folder / "validation.csv"
    write_dataset(paths["data"], validation)
    return paths


def _relabelled(kind: str) -> Callable[[Document], None]:
    """The file says ``kind``, its fit too (the editor was thorough): only the parameters tell."""

    def edit(document: Document) -> None:
        document["kind"] = kind
        document["fit"]["kind"] = kind

    return edit


def _parameter(name: str, value: object) -> Callable[[Document], None]:
    def edit(document: Document) -> None:
        document["parameters"][name] = value

    return edit


def _cut(name: str, keep: int) -> Callable[[Document], None]:
    def edit(document: Document) -> None:
        document["parameters"][name] = document["parameters"][name][:keep]

    return edit


def _kind_only(kind: str) -> Callable[[Document], None]:
    def edit(document: Document) -> None:
        document["kind"] = kind

    return edit


#: (genuine file, edit, the field and the words of the one-line refusal)
CASES: dict[str, tuple[str, Callable[[Document], None], str]] = {
    "PLF parameters in a plf+ file": (
        "plf",
        _relabelled("plf+"),
        "parameters.elbow_polynomial: 0 values; a model of kind plf+ has 6",
    ),
    "PLF+ parameters in a plf file": (
        "plf+",
        _relabelled("plf"),
        "parameters.elbow_polynomial: 6 values; a model of kind plf has none",
    ),
    "A Priori parameters in a plf file": ("ap", _relabelled("plf"), "parameters.elbow_polynomial: 2 values"),
    "A Priori parameters without the stiffness in a plf file": (
        "ap_plain",
        _relabelled("plf"),
        "parameters.includes_dummy_arm: an A Priori model's field in a model of kind plf",
    ),
    "PLF parameters in an ap file": ("plf", _relabelled("ap"), "parameters.includes_dummy_arm: missing"),
    "a PLF+ elbow polynomial cut to 3": (
        "plf+",
        _cut("elbow_polynomial", 3),
        "parameters.elbow_polynomial: 3 values; a model of kind plf+ has 6",
    ),
    "a PLF+ elbow polynomial padded to 8": (
        "plf+",
        _parameter("elbow_polynomial", [0.0] * 8),
        "parameters.elbow_polynomial: 8 values; a model of kind plf+ has 6",
    ),
    "theta of 11 first moments": ("plf", _cut("theta", 11), "parameters.theta: 11 values; a model of kind plf has 12"),
    "an A Priori polynomial of 3 terms": (
        "ap",
        _parameter("elbow_polynomial", [1.0, 2.0, 3.0]),
        "parameters.elbow_polynomial: 3 values; a model of kind ap has none, or 2",
    ),
    "an A Priori stiffness the flags deny": (
        "ap",
        _parameter("includes_elbow_stiffness", False),
        "parameters.elbow_polynomial: 2 values with includes_elbow_stiffness false",
    ),
    "the kind edited, the fit's kind not": (
        "plf",
        _kind_only("plf+"),
        "field kind: 'plf+', but the fit that made these parameters was of kind \"plf\" (field fit.kind)",
    ),
}


def _write(genuine: dict[str, Path], folder: Path, name: str) -> tuple[Path, str]:
    source, edit, expected = CASES[name]
    document = json.loads(genuine[source].read_text(encoding="utf-8"))
    edit(document)
    path = folder / f"{name.replace(' ', '_')}.json"
    path.write_text(json.dumps(_signed(document)), encoding="utf-8")
    return path, expected


@pytest.mark.parametrize("name", list(CASES))
def test_load_model_refuses_parameters_that_are_not_the_kinds(
    genuine: dict[str, Path], tmp_path: Path, name: str
) -> None:
    path, expected = _write(genuine, tmp_path, name)
    with pytest.raises(ModelFileError) as caught:
        load_model(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: ")
    assert expected in message
    assert "\n" not in message


@pytest.mark.parametrize("command", ["evaluate", "cvf"])
@pytest.mark.parametrize("name", ["PLF parameters in a plf+ file", "a PLF+ elbow polynomial cut to 3"])
def test_evaluate_and_cvf_refuse_in_one_line_exit_2_and_write_nothing(
    genuine: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, name: str
) -> None:
    path, expected = _write(genuine, tmp_path, name)
    out = tmp_path / "out.json"
    data = ["--data", str(genuine["data"])] if command == "evaluate" else []
    assert main([command, str(genuine["plf+"]), str(path), *data, "--json", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.count("\n") == 1
    assert f"{path}: " in captured.err
    assert expected in captured.err
    assert "Traceback" not in captured.err
    assert not out.exists()


def test_a_penn_residual_whose_base_holds_another_kinds_parameters_is_refused(
    genuine: dict[str, Path], tmp_path: Path
) -> None:
    """A composed model's base is checked as a model of its own kind (PLF parameters under a plf+ base)."""
    plf = json.loads(genuine["plf"].read_text(encoding="utf-8"))
    document = json.loads(genuine["plf+"].read_text(encoding="utf-8"))
    document["kind"] = "penn-residual"
    document["fit"] = {}
    document["parameters"] = {
        "base": {"kind": "plf+", "name": "PLF+", "parameters": plf["parameters"]},
        "residual": {},
    }
    path = tmp_path / "composed.json"
    path.write_text(json.dumps(_signed(document)), encoding="utf-8")
    with pytest.raises(ModelFileError, match=r"parameters\.base\.parameters\.elbow_polynomial: 0 values"):
        load_model(path)


@pytest.mark.parametrize("name", ["plf", "plf+", "ap", "ap_plain"])
def test_every_genuine_linear_file_still_loads(genuine: dict[str, Path], name: str) -> None:
    model, contents = load_model(genuine[name])
    assert model.kind == contents.kind == {"ap_plain": "ap"}.get(name, name)
    assert model.parameters() == contents.parameters
