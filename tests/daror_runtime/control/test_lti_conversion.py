"""The filters' tf2ss / cont2discrete / ss2tf without scipy.signal: scipy's own values, to the bit.

:mod:`daror_runtime.control.lti_conversion` repeats scipy.signal's steps so that a session designs
its filters without importing scipy.signal (~0.5 s of start-up). These tests compare every array
(values, shape, dtype) with scipy.signal itself, over random polynomials and systems of the orders
the filters use and beyond, and check that what is not computed there is left to scipy.
"""

from __future__ import annotations

import re
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import scipy.signal

from daror_runtime.control import lti_conversion
from daror_runtime.control.filters import DiscreteTransferFunction

REPO = Path(__file__).resolve().parents[3]


def _same(got: object, expected: object) -> None:
    """The same arrays, bit for bit (NaN payloads and signed zeros included), with the same shapes and types."""
    if isinstance(expected, tuple):
        assert isinstance(got, tuple)
        assert len(got) == len(expected)
        for g, e in zip(got, expected, strict=True):
            _same(g, e)
        return
    if isinstance(expected, np.ndarray):
        assert isinstance(got, np.ndarray)
        assert got.shape == expected.shape
        assert got.dtype == expected.dtype
        assert got.tobytes() == expected.tobytes()
        return
    assert type(got) is type(expected)
    assert got == expected


def _same_outcome(ours: Callable[[], object], scipys: Callable[[], object]) -> None:
    """The same arrays, or the same exception (type and message), warnings aside."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            expected = scipys()
        except (ValueError, np.linalg.LinAlgError) as exc:
            with pytest.raises(type(exc), match=re.escape(str(exc))):
                ours()
            return
        _same(ours(), expected)


def _polynomials(rng: np.random.Generator, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Random stable and unstable numerators and denominators, orders 1 to 6, scales 1e-6 to 1e4."""
    cases = []
    for _ in range(count):
        order = int(rng.integers(1, 7))
        scale = 10.0 ** rng.uniform(-6, 4)
        den = np.real(np.poly(rng.normal(-1.0, 3.0, order) * scale)) * 10.0 ** rng.uniform(-3, 3)
        num = rng.normal(size=int(rng.integers(1, order + 2))) * 10.0 ** rng.uniform(-3, 3)
        cases.append((num, den))
    return cases


# The filters' own continuous designs: a filtered derivative, a filtered velocity, a low-pass.
FILTER_DESIGNS = [
    (np.array([0.002, 0.0]), np.array([0.0005, 1.0])),
    (np.array([1.0, 0.0]), np.array([0.001, 1.0])),
    (np.array([1.0]), np.array([1.0 / (2 * np.pi * 30.0), 1.0])),
    (np.array([3.5]), np.array([2.0])),
]


@pytest.mark.parametrize("method", ["bilinear", "zoh"])
@pytest.mark.parametrize("dt", [1e-3, 0.5e-3, 0.0123, 1])
def test_cont2discrete_of_a_transfer_function_is_scipys(method: str, dt: float) -> None:
    rng = np.random.default_rng(int(dt * 1e6) + len(method))
    for num, den in FILTER_DESIGNS + _polynomials(rng, 60):
        _same_outcome(
            lambda num=num, den=den: lti_conversion.cont2discrete_tf(num, den, dt, method),
            lambda num=num, den=den: scipy.signal.cont2discrete((num, den), dt, method=method),
        )


def test_tf2ss_is_scipys() -> None:
    rng = np.random.default_rng(7)
    cases = FILTER_DESIGNS + _polynomials(rng, 200)
    # what the filter banks realise: z-domain polynomials normalised to a leading 1, and a delay
    cases += [(np.array([0.25, 0.5, 0.25]), np.array([1.0, -0.3, 0.02])), (np.ones(1), np.array([1.0, 0.0, 0.0]))]
    for num, den in cases:
        _same(lti_conversion.tf2ss(num, den), scipy.signal.tf2ss(num, den))


@pytest.mark.parametrize("method", ["bilinear", "zoh"])
def test_cont2discrete_and_ss2tf_of_a_state_space_system_are_scipys(method: str) -> None:
    rng = np.random.default_rng(11)
    for _ in range(100):
        n, p, q = (int(k) for k in rng.integers(1, 5, size=3))
        a = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-2, 3)
        b, c, d = rng.normal(size=(n, p)), rng.normal(size=(q, n)), rng.normal(size=(q, p))
        dt = float(10.0 ** rng.uniform(-4, -1))
        expected = scipy.signal.cont2discrete((a, b, c, d), dt, method=method)
        got = lti_conversion.cont2discrete_ss(a, b, c, d, dt, method)
        _same(got, expected)
        _same(lti_conversion.ss2tf(*got[:4]), scipy.signal.ss2tf(*expected[:4]))
    # the locked-link SEA of sea_torque_design.zoh_locked_plant
    a, b, c = np.array([[0.0, 1.0], [-2.4e5, -40.0]]), np.array([[0.0], [5.0]]), np.array([[1200.0, 0.0]])
    expected = scipy.signal.cont2discrete((a, b, c, np.zeros((1, 1))), 1e-3, method=method)
    got = lti_conversion.cont2discrete_ss(a, b, c, np.zeros((1, 1)), 1e-3, method)
    _same(got, expected)
    _same(lti_conversion.ss2tf(*got[:4]), scipy.signal.ss2tf(*expected[:4]))


def test_what_is_not_computed_here_is_left_to_scipy() -> None:
    """A numerator scipy calls badly conditioned (trimmed, with its warning), other dtypes and shapes."""
    num, den = np.array([1e-16, 2.0, 1.0]), np.array([1.0, 3.0, 2.0])
    with pytest.warns(scipy.signal.BadCoefficients):
        got = lti_conversion.tf2ss(num, den)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", scipy.signal.BadCoefficients)
        _same(got, scipy.signal.tf2ss(num, den))
        with pytest.warns(scipy.signal.BadCoefficients):
            got_d = lti_conversion.cont2discrete_tf(num, den, 1e-3, "bilinear")
        _same(got_d, scipy.signal.cont2discrete((num, den), 1e-3, method="bilinear"))
    _same(lti_conversion.tf2ss([1.0, 2.0], [1.0, 3.0, 2.0]), scipy.signal.tf2ss([1.0, 2.0], [1.0, 3.0, 2.0]))
    _same(lti_conversion.tf2ss(np.array([2.0]), np.array([4.0])), scipy.signal.tf2ss(np.array([2.0]), np.array([4.0])))
    _same(
        lti_conversion.tf2ss(np.array([1, 2]), np.array([1, 3])), scipy.signal.tf2ss(np.array([1, 2]), np.array([1, 3]))
    )
    _same(lti_conversion.tf2ss(np.array([1.0]), np.array([0.0, 2.0, 1.0])), scipy.signal.tf2ss([1.0], [0.0, 2.0, 1.0]))
    ints = (np.array([[0, 1], [-2, -3]]), np.array([[0], [1]]), np.array([[1, 0]]), np.array([[0]]))
    _same(lti_conversion.cont2discrete_ss(*ints, 0.1, "zoh"), scipy.signal.cont2discrete(ints, 0.1, method="zoh"))
    _same(lti_conversion.ss2tf(*ints), scipy.signal.ss2tf(*ints))
    with pytest.raises(ValueError, match="Improper"):
        lti_conversion.tf2ss(np.ones(3), np.ones(2))
    with pytest.raises(ValueError, match="'foh'"):
        lti_conversion.cont2discrete_tf(np.ones(1), np.ones(2), 0.1, "foh")


def test_the_filters_designed_are_the_ones_scipy_gives() -> None:
    """DiscreteTransferFunction's discretisation and realisation, end to end, against scipy.signal's."""
    for num, den in FILTER_DESIGNS[:3]:
        for method in ("bilinear", "zoh"):
            h = DiscreteTransferFunction.from_continuous(num, den, 1e-3, method)
            num_z, den_z, _ = scipy.signal.cont2discrete((num, den), 1e-3, method=method)
            expected = DiscreteTransferFunction(np.ravel(num_z), np.ravel(den_z), 1e-3)
            _same(h.num, expected.num)
            _same(h.den, expected.den)
            a, b, c, d = scipy.signal.tf2ss(h.num, h.den)
            ours = lti_conversion.tf2ss(h.num, h.den)
            _same(ours, (a, b, c, d))


@pytest.mark.subprocess
def test_a_hil_session_starts_without_scipy_signal() -> None:
    """``daror hil``'s imports and its session's construction (every filter designed) must not pull in
    scipy.signal or scipy.stats (~0.5 s each of start-up)."""
    code = (
        "import sys, tempfile\n"
        "from pathlib import Path\n"
        "import daror_runtime.cli\n"
        "from daror_runtime.cli import main\n"
        "out = Path(tempfile.mkdtemp()) / 'out'\n"
        "script = out.parent / 'one.txt'\n"
        "script.write_text('status\\n')\n"
        "rc = main(['hil', '--script', str(script), '--settings', 'tests/data/hil_settings.yaml', '--out', str(out)])\n"
        "assert rc == 0, rc\n"
        "for name in ('scipy.signal', 'scipy.stats'):\n"
        "    assert name not in sys.modules, name + ' imported'\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
