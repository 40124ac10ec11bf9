"""Hostile model files: every one is refused by ``load_model`` and by ``daror evaluate`` / ``daror cvf``
with one line naming the file (and the field where there is one), exit code 2, no traceback, nothing
written, in well under a second.

Most files are made from a real PLF+ model file by editing its JSON text or its document. Where the
point is a value the checksum would otherwise catch first, the document is signed again (as a person
who edits a file and recomputes its checksum would), so the check under test is the one that answers.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from daror_runtime.cli import main
from daror_runtime.data.load import write_dataset
from daror_runtime.errors import InputError, ModelFileError
from daror_runtime.models.files import (
    DESCRIPTION_MAX_ABS,
    MAX_JSON_DEPTH,
    PARAMETER_BOUNDS,
    load_model,
    save_model,
    training_summary,
)
from daror_runtime.models.linear import build_ap, fit_plf_plus
from hal.files import MODEL_MAX_BYTES

#: A refusal may take this long at most (they take milliseconds; the bound catches a hang or a blow-up).
FAST_S = 5.0


@dataclass(frozen=True)
class Good:
    """A real model file, its document, an A Priori model file and validation data for the CLI."""

    plf_plus: Path
    document: dict[str, Any]
    ap_document: dict[str, Any]
    data: Path


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory, dataset_b, description) -> Good:
    folder = tmp_path_factory.mktemp("good_models")
    train, validation = dataset_b
    plf_plus = folder / "plf_plus.json"
    result = fit_plf_plus(train, description)
    save_model(plf_plus, result.model, training_summary(train), result.report)
    ap = folder / "ap.json"
    save_model(ap, build_ap(description, None, True, True).model)
    data = folder / "validation.csv"
    write_dataset(data, validation)
    return Good(
        plf_plus,
        json.loads(plf_plus.read_text(encoding="utf-8")),
        json.loads(ap.read_text(encoding="utf-8")),
        data,
    )


def signed(document: dict[str, Any]) -> dict[str, Any]:
    """``document`` with its checksum recomputed (SHA-256 of the canonical JSON of everything else)."""
    body = {k: v for k, v in document.items() if k != "checksum_sha256"}
    canonical = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()
    return {**body, "checksum_sha256": hashlib.sha256(canonical).hexdigest()}


def test_signing_here_matches_the_files_checksum(good: Good) -> None:
    """The helper signs exactly as the writer does (so the edited files below fail for their own reason)."""
    assert signed(good.document) == good.document
    assert load_model(good.plf_plus)[0].kind == "plf+"


def _copy(document: dict[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps(document))


def _with_parameter(document: dict[str, Any], key: str, index: int | None, value: object) -> dict[str, Any]:
    edited = _copy(document)
    if index is None:
        edited["parameters"][key] = value
    else:
        edited["parameters"][key][index] = value
    return edited


def _theta0_text(good: Good) -> tuple[str, str]:
    """The file's text and the exact text of its first parameter (to replace it in place)."""
    text = good.plf_plus.read_text(encoding="utf-8")
    literal = repr(good.document["parameters"]["theta"][0])
    assert text.count(literal) >= 1
    return text, literal


def _augmented(good: Good, **parameters: object) -> dict[str, Any]:
    """A signed augmented-kind document (a base model plus effects) with ``parameters`` laid over a plain one.

    Without the PLF+ fit's report: ``daror residual`` writes an augmented model without one, and a
    report of kind plf+ under kind augmented is refused (issue 24: the fit's kind must be the file's).
    """
    document = _copy(good.document)
    document["kind"] = "augmented"
    document["fit"] = {}
    document["parameters"] = {
        "base_kind": "plf+",
        "theta": good.document["parameters"]["theta"],
        "elbow_polynomial": good.document["parameters"]["elbow_polynomial"],
        **parameters,
    }
    return signed(document)


# --- the hostile files -----------------------------------------------------------------------

Maker = Callable[[Good, Path], Path]


@dataclass(frozen=True)
class Hostile:
    make: Maker  # writes the file into the folder, returns its path
    fragment: str  # part of the one-line message


def _text(name: str, content: Callable[[Good], str]) -> Maker:
    def make(good: Good, folder: Path) -> Path:
        path = folder / name
        path.write_text(content(good), encoding="utf-8")
        return path

    return make


def _document(name: str, content: Callable[[Good], dict[str, Any]]) -> Maker:
    return _text(name, lambda good: json.dumps(content(good), indent=2))


def _replace_theta0(new: str) -> Callable[[Good], str]:
    def content(good: Good) -> str:
        text, literal = _theta0_text(good)
        return text.replace(literal, new, 1)

    return content


def _fifo(folder: Path) -> Path:
    path = folder / "model.json"
    os.mkfifo(path)
    _unblock_later(path)
    return path


def _unblock_later(fifo: Path) -> None:
    """Should the code under test ever open the FIFO, give it an end of file after a while instead of a hang."""

    def release() -> None:
        with contextlib.suppress(OSError):  # nobody is reading: as it should be
            os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))

    timer = threading.Timer(2 * FAST_S, release)
    timer.daemon = True
    timer.start()


def _huge(folder: Path) -> Path:
    path = folder / "model.json"
    with open(path, "wb") as handle:
        handle.truncate(MODEL_MAX_BYTES + 1)  # sparse: costs no disk
    return path


def _loop(folder: Path) -> Path:
    path = folder / "model.json"
    path.symlink_to(path)
    return path


def _directory(folder: Path) -> Path:
    path = folder / "model.json"
    path.mkdir()
    return path


def _bytes(name: str, content: bytes) -> Maker:
    def make(good: Good, folder: Path) -> Path:
        path = folder / name
        path.write_bytes(content)
        return path

    return make


HOSTILE: dict[str, Hostile] = {
    "NaN parameter": Hostile(
        _text("nan.json", _replace_theta0("NaN")),
        "field parameters.theta.0: NaN is not a number; a model file holds finite numbers only",
    ),
    "Infinity parameter": Hostile(_text("inf.json", _replace_theta0("Infinity")), "field parameters.theta.0: Infinity"),
    "-Infinity parameter": Hostile(
        _text("minus_inf.json", _replace_theta0("-Infinity")), "field parameters.theta.0: -Infinity is not a number"
    ),
    "1e400 parameter": Hostile(
        _text("overflow.json", _replace_theta0("1e400")),
        "field parameters.theta.0: 1e400 is too large for a number (it reads as infinity)",
    ),
    "NaN in the robot description": Hostile(
        _text(
            "nan_robot.json",
            lambda good: good.plf_plus.read_text(encoding="utf-8").replace(
                '"gravity_mps2": 9.81', '"gravity_mps2": NaN'
            ),
        ),
        "field robot.gravity_mps2: NaN is not a number",
    ),
    "200,000 nested brackets": Hostile(
        _text("brackets.json", lambda good: "[" * 200_000 + "]" * 200_000), "nested too deeply"
    ),
    "nested objects past the depth bound": Hostile(
        _text("objects.json", lambda good: '{"a":' * (MAX_JSON_DEPTH + 8) + "1" + "}" * (MAX_JSON_DEPTH + 8)),
        f"nested more than {MAX_JSON_DEPTH} levels deep",
    ),
    "an integer of 5,000 digits": Hostile(
        _text("digits.json", _replace_theta0("9" * 5000)), "an integer of 5,000 digits"
    ),
    "key written twice": Hostile(
        _text(
            "duplicate.json",
            lambda good: good.plf_plus.read_text(encoding="utf-8").replace(
                '"kind": "plf+",', '"kind": "plf+",\n  "kind": "ap",', 1
            ),
        ),
        "key 'kind' is written twice in one JSON object",
    ),
    "implausible parameter 1e300 (signed)": Hostile(
        _document("1e300.json", lambda good: signed(_with_parameter(good.document, "theta", 6, 1e300))),
        "field parameters.theta.6 (theta3x): 1e+300 is not a plausible parameter; expected |value| <= 10000 Nm",
    ),
    "implausible negative parameter (signed)": Hostile(
        _document("minus.json", lambda good: signed(_with_parameter(good.document, "elbow_polynomial", 2, -2e4))),
        "field parameters.elbow_polynomial.2: -20000 is not a plausible parameter",
    ),
    "a bool where a parameter is meant (signed)": Hostile(
        _document("bool.json", lambda good: signed(_with_parameter(good.document, "theta", 0, True))),
        "field parameters.theta.0 (theta1x): expected a number; got true",
    ),
    "text where a parameter is meant (signed)": Hostile(
        _document("text.json", lambda good: signed(_with_parameter(good.document, "theta", 1, "0.5"))),
        'field parameters.theta.1 (theta1y): expected a number; got "0.5"',
    ),
    "a number where a yes/no is meant (signed)": Hostile(
        _document("flag.json", lambda good: signed(_with_parameter(good.ap_document, "includes_dummy_arm", None, 1))),
        "field parameters.includes_dummy_arm: expected true or false; got 1",
    ),
    "a 1,000-coefficient polynomial (augmented, signed)": Hostile(
        _document("poly.json", lambda good: _augmented(good, joint_polynomials=[[0.1] * 1000, [], [], []])),
        "field parameters.joint_polynomials.0: 1,000 values; expected at most 12",
    ),
    "a joint zero ten radians off (augmented, signed)": Hostile(
        _document("offset.json", lambda good: _augmented(good, angle_offset_rad=[10.0, 0.0, 0.0, 0.0])),
        "field parameters.angle_offset_rad.0: 10 is not a plausible parameter; expected |value| <= 6.28319 rad",
    ),
    "implausible robot description (signed)": Hostile(
        _document(
            "robot.json",
            lambda good: signed({**_copy(good.document), "robot": {**good.document["robot"], "gravity_mps2": 1e300}}),
        ),
        f"field robot.gravity_mps2: 1e+300 is not plausible for a robot description; expected |value| <= "
        f"{DESCRIPTION_MAX_ABS:g}",
    ),
    "format_version true": Hostile(
        _document("version.json", lambda good: signed({**_copy(good.document), "format_version": True})),
        "model file format version true is not supported; expected 1",
    ),
    "a top-level list": Hostile(_text("list.json", lambda good: "[1, 2, 3]"), "not a daror model file"),
    "checksum mismatch": Hostile(
        _document("altered.json", lambda good: _with_parameter(good.document, "theta", 3, 0.5)), "checksum mismatch"
    ),
    "not UTF-8": Hostile(_bytes("latin1.json", b'{"name": "caf\xe9"}'), "not UTF-8 text (byte 0xe9)"),
    "empty file": Hostile(_bytes("empty.json", b""), "not valid JSON (line 1, column 1"),
    "a directory": Hostile(lambda good, folder: _directory(folder), "a directory, not a model file"),
    "a FIFO": Hostile(lambda good, folder: _fifo(folder), "a named pipe (FIFO), not a model file"),
    "larger than MODEL_MAX_BYTES": Hostile(
        lambda good, folder: _huge(folder), f"a model file may have at most {MODEL_MAX_BYTES:,}"
    ),
    "a symbolic link loop": Hostile(lambda good, folder: _loop(folder), "a symbolic link loop"),
}


def test_enough_hostile_model_files() -> None:
    assert len(HOSTILE) >= 15


def test_the_bounds_cover_every_parameter_of_the_linear_and_augmented_kinds(good: Good) -> None:
    numeric = {"theta", "elbow_polynomial", "angle_offset_rad", "gravity_tilt_rad", "torque_gain"}
    numeric |= {"direction_offset_nm", "joint_polynomials"}
    assert set(PARAMETER_BOUNDS) == numeric
    for name in ("angle_offset_rad", "gravity_tilt_rad"):
        assert PARAMETER_BOUNDS[name].max_abs <= 2 * math.pi


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    path = tmp_path / "in"
    path.mkdir()
    return path


@pytest.mark.parametrize("name", list(HOSTILE))
def test_load_model_refuses(name: str, good: Good, folder: Path) -> None:
    hostile = HOSTILE[name]
    path = hostile.make(good, folder)
    started = time.perf_counter()
    with pytest.raises(ModelFileError) as info:
        load_model(path)
    assert time.perf_counter() - started < FAST_S
    message = str(info.value)
    assert isinstance(info.value, InputError)
    assert "\n" not in message, message
    assert message.startswith(f"{path}: "), message
    assert hostile.fragment in message, message


def _refused_by_cli(capsys: pytest.CaptureFixture[str], argv: list[object], path: Path, out: Path) -> str:
    """Run ``argv``: exit code 2, one stderr line naming ``path``, no traceback, ``out`` not written, fast."""
    capsys.readouterr()
    started = time.perf_counter()
    code = main([str(a) for a in argv])
    elapsed = time.perf_counter() - started
    captured = capsys.readouterr()
    assert code == 2, captured.err
    assert elapsed < FAST_S
    assert "Traceback" not in captured.err + captured.out
    lines = captured.err.rstrip("\n").split("\n")
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(f"daror {argv[0]}: error: {path}: "), lines[0]
    assert not out.exists()
    return lines[0]


@pytest.mark.parametrize("name", list(HOSTILE))
def test_evaluate_refuses(
    name: str, good: Good, folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    hostile = HOSTILE[name]
    path = hostile.make(good, folder)
    out = tmp_path / "errors.json"
    line = _refused_by_cli(capsys, ["evaluate", good.plf_plus, path, "--data", good.data, "--json", out], path, out)
    assert hostile.fragment in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]  # nothing else created


@pytest.mark.parametrize("name", list(HOSTILE))
def test_cvf_refuses(name: str, good: Good, folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    hostile = HOSTILE[name]
    path = hostile.make(good, folder)
    out = tmp_path / "cvf.json"
    line = _refused_by_cli(capsys, ["cvf", path, "--json", out], path, out)
    assert hostile.fragment in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_a_device_is_refused_without_reading_it(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    zero = Path("/dev/zero")
    if not zero.exists():
        pytest.skip("no /dev/zero here")
    with pytest.raises(ModelFileError, match=r"^/dev/zero: a device, not a model file"):
        load_model(zero)
    out = tmp_path / "cvf.json"
    _refused_by_cli(capsys, ["cvf", zero, "--json", out], zero, out)


def test_plausible_files_still_load(good: Good, folder: Path) -> None:
    """Parameters at the edge of their bounds, an int where a float is meant, and an augmented model within bounds."""
    edge = _copy(good.document)
    edge["parameters"]["theta"][0] = PARAMETER_BOUNDS["theta"].max_abs
    edge["parameters"]["theta"][1] = 1  # an int is a number
    path = folder / "edge.json"
    path.write_text(json.dumps(signed(edge)), encoding="utf-8")
    model, _ = load_model(path)
    assert model.parameters()["theta"][:2] == [PARAMETER_BOUNDS["theta"].max_abs, 1.0]
    augmented = folder / "augmented.json"
    augmented.write_text(
        json.dumps(_augmented(good, angle_offset_rad=[0.01, 0.0, 0.0, 0.0], torque_gain=[1.1, 1.0, 1.0, 0.9])),
        encoding="utf-8",
    )
    assert load_model(augmented)[0].kind == "augmented"


def test_evaluate_with_a_plausible_model_writes_finite_json(
    good: Good, folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The largest parameters a file may hold still give a JSON report (1e300 once broke it).

    The order-11 polynomials the bounds allow are the augmented kind's (a PLF+ file holds exactly
    its six elbow terms since issue 24): its elbow polynomial and every joint's, at the bound.
    """
    largest = PARAMETER_BOUNDS["elbow_polynomial"].max_abs
    big = _augmented(
        good,
        theta=[PARAMETER_BOUNDS["theta"].max_abs] * 12,
        elbow_polynomial=[largest] * 12,
        joint_polynomials=[[largest] * 12 for _ in range(4)],
    )
    path = folder / "big.json"
    path.write_text(json.dumps(big), encoding="utf-8")
    out = tmp_path / "errors.json"
    assert main(["evaluate", str(path), "--data", str(good.data), "--json", str(out)]) == 0
    capsys.readouterr()
    report = json.loads(out.read_text(encoding="utf-8"))
    assert report
