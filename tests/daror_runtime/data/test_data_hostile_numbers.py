"""Issue 24, defect 9, the data: numbers ``float()`` takes but a data file must not hold, boolean arrays, how
CSV values are written (the shortest decimal that reads back exactly), and ``.npz`` files written deflated
(while the old, stored ones still read).
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
import pytest

from daror_runtime.cli import main
from daror_runtime.data.load import load_dataset, write_dataset
from daror_runtime.data.schema import RawLog, StationaryDataset
from daror_runtime.data.tables import read_table, write_table
from daror_runtime.errors import DataError

HEADER = "q1,q2,q3,q4,tau1,tau2,tau3,tau4"
ROW = "0.1,-0.2,0.3,1.0,1.5,-2.5,0.75,0.125"


def _csv(tmp_path: Path, cell: str, column: int = 5) -> Path:
    """A stationary CSV of three rows whose third has ``cell`` in column ``column`` (0-based)."""
    cells = ROW.split(",")
    cells[column] = cell
    path = tmp_path / "data.csv"
    path.write_text(f"{HEADER}\n{ROW}\n{ROW}\n{','.join(cells)}\n", encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("cell", "expected"),
    [
        ("1_000.5", "'1_000.5' has a digit separator (_); expected a plain decimal number such as 1000.5"),
        ("-2_5", "'-2_5' has a digit separator (_)"),
        ("1e1_0", "'1e1_0' has a digit separator (_)"),
        ("\u0661\u0662", "is not a plain decimal number; expected ASCII digits 0-9"),  # Arabic-Indic 12
        ("\uff11\uff12.5", "is not a plain decimal number; expected ASCII digits 0-9"),  # fullwidth 12.5
        ("2.5\u00a0", "is not a plain decimal number"),  # a no-break space after it
    ],
)
def test_numbers_that_only_python_reads_are_refused_with_file_line_and_column(
    tmp_path: Path, cell: str, expected: str
) -> None:
    assert np.isfinite(float(cell))  # what Python's float() takes, and the file must not
    path = _csv(tmp_path, cell)
    with pytest.raises(DataError) as caught:
        load_dataset(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: line 4, column tau2: ")
    assert expected in message
    assert "\n" not in message


def test_the_command_refuses_a_digit_separator_in_one_line_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _csv(tmp_path, "1_000.5", column=0)
    out = tmp_path / "model.json"
    assert main(["fit", "plf", "--train", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert f"{path}: line 4, column q1: '1_000.5' has a digit separator" in err
    assert not out.exists()


def test_plain_numbers_in_every_spelling_still_read(tmp_path: Path) -> None:
    path = tmp_path / "ok.csv"
    path.write_text(f'{HEADER}\n{ROW}\n 1.5 ,+.5,5.,-1E-3,\t2,0,1e+2,"3.25"\n', encoding="utf-8")
    q = read_table(path).matrix(("q1", "q2", "q3", "q4", "tau1", "tau2", "tau3", "tau4"))
    assert q[1].tolist() == [1.5, 0.5, 5.0, -1e-3, 2.0, 0.0, 100.0, 3.25]


def _npz(path: Path, **arrays: np.ndarray) -> Path:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    path.write_bytes(buffer.getvalue())
    return path


def test_a_boolean_array_in_an_npz_is_refused_naming_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    columns = {name: np.linspace(0.1, 0.5, 5) for name in HEADER.split(",")}
    columns["tau3"] = np.array([True, False, True, True, False])
    path = _npz(tmp_path / "flags.npz", **columns)
    with pytest.raises(DataError, match=r"flags\.npz: variable tau3 holds booleans \(true/false\); expected numbers"):
        read_table(path)
    out = tmp_path / "m.json"
    assert main(["fit", "plf", "--train", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "variable tau3 holds booleans" in err
    assert not out.exists()


# --- writing -------------------------------------------------------------------------------------


def test_csv_cells_are_the_shortest_decimal_that_reads_back_exactly(tmp_path: Path) -> None:
    """0.3756 is written 0.3756 (17 digits wrote 0.37559999999999999); a value that is not 0.3756 keeps the
    digits that make it itself; every value reads back bit for bit (D130)."""
    values = [0.3756, np.nextafter(0.3756, 1.0), 0.1 + 0.2, -1.0, 1e-05, 162.1835, 2.0**-1074, -0.0]
    path = tmp_path / "v.csv"
    write_table(path, {"a": np.array(values)})
    assert path.read_text(encoding="utf-8").splitlines() == [
        "a",
        "0.3756",
        "0.37560000000000004",
        "0.30000000000000004",
        "-1.0",
        "1e-05",
        "162.1835",
        "5e-324",
        "-0.0",
    ]
    back = read_table(path).columns["a"]
    assert np.array_equal(back.view(np.int64), np.array(values).view(np.int64))


def test_a_written_npz_is_deflated_where_it_pays_smaller_and_exact_and_a_stored_one_still_reads(tmp_path: Path) -> None:
    n = 20_000
    t = 12.5 + np.arange(n) * 0.001
    q = np.round(np.column_stack([np.sin(t * k) for k in (0.3, 0.5, 0.7, 1.1)]), 5)  # encoder-like resolution
    rng = np.random.default_rng(4)
    raw = RawLog(t, q, np.gradient(q, t, axis=0), rng.normal(0.0, 2.0, (n, 4)))
    path = tmp_path / "run.raw.npz"
    write_dataset(path, raw)
    with zipfile.ZipFile(path) as archive:
        members = archive.infolist()
    kinds = {m.filename.removesuffix(".npy"): m.compress_type for m in members}
    # Deflated where deflate pays (time, the encoder-like angles), stored where it cannot (the noise, D207).
    assert {kinds[name] for name in ("t", "q1", "q2", "q3", "q4")} == {zipfile.ZIP_DEFLATED}
    assert {kinds[name] for name in ("tau1", "tau2", "tau3", "tau4")} == {zipfile.ZIP_STORED}
    stored = sum(m.file_size for m in members)
    assert path.stat().st_size < 0.7 * stored  # t and q compress well, the noise does not
    back = load_dataset(path)
    assert isinstance(back, RawLog)
    for name in ("t_s", "q_rad", "dq_rad_s", "tau_nm"):
        assert np.array_equal(getattr(back, name).view(np.int64), getattr(raw, name).view(np.int64)), name
    old = _npz(tmp_path / "old.raw.npz", **raw.to_columns())  # what the runtime wrote before issue 24
    with zipfile.ZipFile(old) as archive:
        assert {m.compress_type for m in archive.infolist()} == {zipfile.ZIP_STORED}
    again = load_dataset(old)
    assert isinstance(again, RawLog)
    assert np.array_equal(again.q_rad, raw.q_rad)


def test_a_stationary_dataset_round_trips_through_every_format_unchanged(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    data = StationaryDataset(
        rng.uniform(-2, 2, (50, 4)), rng.normal(0, 4, (50, 4)), rng.choice([-1.0, 1.0], (50, 4)), np.arange(50.0)
    )
    for suffix in (".csv", ".npz", ".mat"):
        path = tmp_path / f"d{suffix}"
        write_dataset(path, data)
        back = load_dataset(path)
        assert isinstance(back, StationaryDataset)
        for name in ("q_rad", "tau_nm", "direction", "t_s"):
            assert np.array_equal(getattr(back, name), getattr(data, name)), (suffix, name)
