"""The filters' ``tf2ss``, ``cont2discrete`` and ``ss2tf``, without importing ``scipy.signal``.

``scipy.signal`` takes ~0.5 s to import (it brings scipy.stats, scipy.interpolate, scipy.optimize
along and parses hundreds of docstrings), and every session designs its torque loops at start-up
with three of its functions (:mod:`daror_runtime.control.filters`,
:func:`daror_runtime.control.sea_torque_design.zoh_locked_plant`)::

    scipy.signal.cont2discrete((num, den), dt, method="bilinear")  # or "zoh"
    scipy.signal.tf2ss(num, den)
    scipy.signal.cont2discrete((a, b, c, d), dt, method="zoh")     # or "bilinear"
    scipy.signal.ss2tf(a, b, c, d)

The functions here compute exactly that by scipy's own steps (scipy 1.17: ``normalize``,
``tf2ss``, ``cont2discrete``'s ``gbt`` with ``alpha = 0.5`` or ``zoh``, ``abcd_normalize``,
``ss2tf``), with the same numpy and :mod:`scipy.linalg` calls on the same types, so every value is
scipy's to the bit (scipy.linalg is imported anyway; its ``solve`` and ``expm`` are the ones
scipy.signal calls, and warn as there, from a line of this module).
``tests/daror_runtime/control/test_lti_conversion.py`` checks them against ``scipy.signal`` itself. What they do not
cover is left to ``scipy.signal``, imported then: a numerator whose leading coefficient normalises
to at most 1e-14 (scipy warns ``BadCoefficients`` and trims it), a denominator of degree 0 or with
a leading zero, anything but float64 arrays of the expected shapes.
"""

from __future__ import annotations

import numpy as np
from scipy import linalg

from hal.robot import FloatArray

__all__ = ["cont2discrete_ss", "cont2discrete_tf", "ss2tf", "tf2ss"]

#: scipy.signal.normalize's threshold: a numerator column at most this (after normalisation) is a
#: leading zero, trimmed with a ``BadCoefficients`` warning.
_NORMALIZE_ZERO = 1e-14


def _normalized(num: FloatArray, den: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """``scipy.signal.normalize(num, den)`` for 1-D float64 polynomials, a leading ``den`` coefficient
    that is not zero and at least two of them; None for anything else (scipy decides)."""
    if not (isinstance(num, np.ndarray) and isinstance(den, np.ndarray)):
        return None
    if num.ndim != 1 or den.ndim != 1 or num.dtype != np.float64 or den.dtype != np.float64:
        return None
    if den.shape[0] < 2 or num.shape[0] == 0 or den[0] == 0.0:
        return None
    num2 = np.expand_dims(num, axis=0)
    num2, den = num2 / den[0], den / den[0]
    if np.all(np.abs(num2[:, 0]) <= _NORMALIZE_ZERO):
        return None  # scipy warns and trims
    return num2[0, :], den


def _tf2ss_normalized(num: FloatArray, den: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``scipy.signal.tf2ss`` after its ``normalize``: the controller canonical form."""
    num = np.asarray([num], num.dtype)
    m = num.shape[1]
    k = len(den)
    if m > k:
        raise ValueError("Improper transfer function. `num` is longer than `den`.")
    num = np.hstack((np.zeros((num.shape[0], k - m), dtype=num.dtype), num))
    d = np.atleast_2d(num[:, 0])
    frow = -np.array([den[1:]])
    a = np.r_[frow, np.eye(k - 2, k - 1)]
    b = np.eye(k - 1, 1)
    c = num[:, 1:] - np.outer(num[:, 0], den[1:])
    d = d.reshape((c.shape[0], b.shape[1]))
    return a, b, c, d


def tf2ss(num: FloatArray, den: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``scipy.signal.tf2ss(num, den)``, to the bit."""
    normalized = _normalized(num, den)
    if normalized is None:
        from scipy import signal

        return signal.tf2ss(num, den)
    return _tf2ss_normalized(*normalized)


def _is_ss(a: FloatArray, b: FloatArray, c: FloatArray, d: FloatArray) -> bool:
    """Four 2-D float64 arrays of consistent, non-empty shapes ``(n, n), (n, p), (q, n), (q, p)``:
    what scipy's ``abcd_normalize`` returns unchanged."""
    arrays = (a, b, c, d)
    if not all(isinstance(m, np.ndarray) and m.ndim == 2 and m.dtype == np.float64 for m in arrays):
        return False
    n, p, q = a.shape[0], b.shape[1], c.shape[0]
    shapes = ((n, n), (n, p), (q, n), (q, p))
    return n > 0 and p > 0 and q > 0 and all(m.shape == s for m, s in zip(arrays, shapes, strict=True))


def _ss2tf(a: FloatArray, b: FloatArray, c: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``scipy.signal.ss2tf(a, b, c, d)`` (input 0) after its ``abcd_normalize``, for :func:`_is_ss`'s
    arrays."""
    nout = d.shape[0]
    b = b[:, 0:1]
    d = d[:, 0:1]
    den = np.poly(a)
    num_states = a.shape[0]
    type_test = a[:, 0] + b[:, 0] + c[0, :] + d + 0.0
    num = np.empty((nout, num_states + 1), type_test.dtype)
    for k in range(nout):
        ck = np.atleast_2d(c[k, :])
        num[k] = np.poly(a - np.dot(b, ck)) + (d[k] - 1) * den
    return num, den


def ss2tf(a: FloatArray, b: FloatArray, c: FloatArray, d: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``scipy.signal.ss2tf(a, b, c, d)`` (input 0), to the bit."""
    if not _is_ss(a, b, c, d):
        from scipy import signal

        return signal.ss2tf(a, b, c, d)
    return _ss2tf(a, b, c, d)


def _discretised(
    a: FloatArray, b: FloatArray, c: FloatArray, d: FloatArray, dt: float, method: str
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """``scipy.signal.cont2discrete((a, b, c, d), dt, method)``'s state-space step."""
    if method == "bilinear":  # scipy: the generalised bilinear transform with alpha = 0.5
        alpha = 0.5
        ima = np.eye(a.shape[0]) - alpha * dt * a
        ad = linalg.solve(ima, np.eye(a.shape[0]) + (1.0 - alpha) * dt * a)
        bd = linalg.solve(ima, dt * b)
        cd = linalg.solve(ima.transpose(), c.transpose())
        cd = cd.transpose()
        dd = d + alpha * np.dot(c, bd)
        return ad, bd, cd, dd
    em_upper = np.hstack((a, b))
    em_lower = np.hstack((np.zeros((b.shape[1], a.shape[0])), np.zeros((b.shape[1], b.shape[1]))))
    em = np.vstack((em_upper, em_lower))
    ms = linalg.expm(dt * em)
    ms = ms[: a.shape[0], :]
    ad = ms[:, 0 : a.shape[1]]
    bd = ms[:, a.shape[1] :]
    return ad, bd, c, d


def _check_method(method: str) -> None:
    if method not in ("bilinear", "zoh"):
        raise ValueError(f"method {method!r} is not computed here; expected 'bilinear' or 'zoh'")


def cont2discrete_ss(
    a: FloatArray, b: FloatArray, c: FloatArray, d: FloatArray, dt: float, method: str
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, float]:
    """``scipy.signal.cont2discrete((a, b, c, d), dt, method=method)`` for ``method`` "bilinear" or
    "zoh", to the bit: ``(ad, bd, cd, dd, dt)``.

    Raises:
        ValueError: another method (scipy's others are not needed here).
    """
    _check_method(method)
    if not _is_ss(a, b, c, d):
        from scipy import signal

        return signal.cont2discrete((a, b, c, d), dt, method=method)
    return (*_discretised(a, b, c, d, dt, method), dt)


def cont2discrete_tf(num: FloatArray, den: FloatArray, dt: float, method: str) -> tuple[FloatArray, FloatArray, float]:
    """``scipy.signal.cont2discrete((num, den), dt, method=method)`` for ``method`` "bilinear" or
    "zoh", to the bit: ``(num_z (1, n + 1), den_z (n + 1,), dt)``.

    Raises:
        ValueError: another method (scipy's others are not needed here).
    """
    _check_method(method)
    normalized = _normalized(num, den)
    if normalized is None:
        from scipy import signal

        return signal.cont2discrete((num, den), dt, method=method)
    num_z, den_z = _ss2tf(*_discretised(*_tf2ss_normalized(*normalized), dt, method))
    return num_z, den_z, dt
