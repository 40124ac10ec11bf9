"""The stationary reduction's zero-phase Butterworth low-pass, without importing ``scipy.signal``.

``scipy.signal`` takes ~0.5 s and ~50 MB to import (it brings scipy.stats and more along), and
the stationary reduction of every raw log needs one filter of it::

    sos = scipy.signal.butter(2, cutoff_hz, fs=rate_hz, output="sos")
    scipy.signal.sosfiltfilt(sos, x, axis=0, padtype="even")

:func:`butter2_lowpass_sos` and :func:`sosfiltfilt_even` compute exactly that for a second-order
filter, by scipy's own steps (scipy 1.17: ``iirfilter``, ``buttap``, ``lp2lp_zpk``,
``bilinear_zpk``, ``zpk2sos`` with its one section, ``sosfilt_zi``, ``lfilter_zi``, the even
extension, two passes of ``_sosfilt``), with the same numpy calls on the same types, so every
value is scipy's to the bit, and the result has scipy's memory layout (a reduction over it, such
as ``np.linalg.norm(axis=1)``, adds in the same order). ``tests/daror_runtime/data/test_stationary_reduction.py``
checks both against ``scipy.signal`` itself. Other orders are left to ``scipy.signal``
(:mod:`daror_runtime.data.stationary` falls back).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from hal.robot import FloatArray

__all__ = ["ORDER", "butter2_lowpass_sos", "sosfiltfilt_even"]

#: The one filter order computed here.
ORDER = 2


def butter2_lowpass_sos(cutoff_hz: float, rate_hz: float) -> FloatArray:
    """``scipy.signal.butter(2, cutoff_hz, fs=rate_hz, output="sos")``: one section, shape (1, 6).

    Raises:
        ValueError: the cut-off is not inside (0, rate / 2) (as scipy).
    """
    wn = np.asarray(cutoff_hz, dtype=np.float64)
    fs = float(rate_hz)
    wn = wn / (fs / 2)
    if np.any(wn <= 0) or np.any(wn >= 1):
        raise ValueError(f"Digital filter critical frequencies must be 0 < Wn < fs/2 (fs={fs} -> fs/2={fs / 2})")
    # buttap(2): the analog prototype
    z = np.asarray([], dtype=np.float64)
    m = np.arange(-ORDER + 1, ORDER, 2, dtype=np.float64)
    p = -np.exp(1j * np.pi * m / (2 * ORDER))
    k = 1.0
    # pre-warp (a digital filter is designed at fs = 2)
    fs = 2.0
    warped = 2 * fs * np.tan(np.pi * wn / fs)
    # lp2lp_zpk(z, p, k, wo=warped)
    wo = float(warped)
    degree = p.shape[0] - z.shape[0]
    z = wo * z
    p = wo * p
    k = k * wo**degree
    # bilinear_zpk(z, p, k, fs=2.0)
    fs2 = 2.0 * fs
    z_z = (fs2 + z) / (fs2 - z)
    p_z = (fs2 + p) / (fs2 - p)
    z_z = np.concatenate((z_z, -np.ones(degree)))
    k_z = k * np.real(np.prod(fs2 - z) / np.prod(fs2 - p))
    # zpk2sos(z_z, p_z, k_z), pairing "nearest": the two zeros at -1 are real (_cplxreal keeps them);
    # the poles are one conjugate pair, which _cplxreal replaces by the mean of the pair.
    gain = np.asarray(k_z).real
    poles = p_z[np.lexsort((abs(p_z.imag), p_z.real))]
    upper, lower = poles[poles.imag > 0], poles[poles.imag < 0]
    tol = 100 * np.finfo(np.float64).eps
    if len(upper) != 1 or len(lower) != 1 or np.any(abs(upper - lower.conj()) > tol * abs(lower)):
        raise ValueError("the poles of a second-order Butterworth low-pass are not one conjugate pair")
    p1 = ((upper + lower.conj()) / 2)[0]
    zeros = np.concatenate((np.array([]), z_z))  # _cplxreal of real zeros: (empty, the zeros)
    section = _single_section([zeros[0], zeros[1]], [p1, p1.conj()])
    sos = np.zeros((1, 6))
    sos[0] = section
    sos[0][:3] *= gain
    return sos


def _single_section(zeros: list[np.floating], poles: list[np.complexfloating]) -> FloatArray:
    """``_single_zpksos(zeros, poles, 1)``: ``zpk2tf`` with scipy's ``poly`` (``np.convolve``)."""
    z = np.asarray(zeros)
    p = np.asarray(poles)
    k = np.asarray(1, dtype=np.result_type(np.real(z), np.real(p), 1))
    k = np.atleast_1d(k)
    b = np.multiply(k, _poly(z))
    a = np.atleast_1d(np.asarray(_poly(p)))
    sos = np.zeros(6)
    sos[3 - len(b) : 3] = b
    sos[6 - len(a) : 6] = a
    return sos


def _poly(roots: np.ndarray) -> np.ndarray:
    """scipy.signal._polyutils.poly: the coefficients of the polynomial with these roots (1-D)."""
    a = np.ones((1,), dtype=roots.dtype)
    one = np.ones_like(roots[0])
    for root in roots:
        a = np.convolve(a, np.stack((one, -root)), mode="full")
    if np.iscomplexobj(a):
        complex_roots = np.asarray(roots, dtype=np.complex128)
        if np.all(np.sort(np.imag(complex_roots)) == np.sort(np.imag(np.conj(complex_roots)))):
            a = np.asarray(np.real(a), copy=True)
    return a


def sosfiltfilt_even(sos: FloatArray, x: FloatArray) -> FloatArray:
    """``scipy.signal.sosfiltfilt(sos, x, axis=0, padtype="even")`` for one section (``sos`` (1, 6)).

    ``x`` is (n, m) float64 with n > 9 (the padding); returns (n, m), a view laid out as scipy's.

    Raises:
        ValueError: ``sos`` is not one normalised section, or ``x`` is too short (as scipy).
    """
    sos = np.asarray(sos, dtype=np.float64)
    if sos.shape != (1, 6) or not np.all(sos[:, 3] == 1):
        raise ValueError("sos must be one second-order section with sos[:, 3] == 1")
    x = np.asarray(x, dtype=np.float64)
    ntaps = 2 * 1 + 1
    ntaps -= min((sos[:, 2] == 0).sum(), (sos[:, 5] == 0).sum())
    edge = ntaps * 3
    if x.shape[0] <= edge:
        raise ValueError(f"The length of the input vector x must be greater than padlen, which is {edge}.")
    zi = _sosfilt_zi(sos).reshape((1, 2, 1))  # (n_sections, 2 along axis 0, 1)
    # scipy: ext = even_ext(x, edge, axis=0); y = sosfilt(sos, ext, zi=zi * ext[0:1]);
    # y = sosfilt(sos, y[::-1], zi=zi * y[-1:]); return y[::-1][edge:-edge]. Each sosfilt copies
    # its input to C-order rows (one per signal), filters them in place and hands back their
    # (samples, signals) view. Here the extension is copied straight into those rows and reversed
    # in place for the second pass (copies only, so the same values), and one (n, m) array is
    # alive instead of three.
    rows = np.empty((x.shape[1], x.shape[0] + 2 * edge))
    _even_extended_rows(x, edge, rows)
    _sosfilt_rows(sos, rows, _sosfilt_state(zi * x[edge : edge + 1]))  # ext[0:1] is x[edge]
    state = _sosfilt_state(zi * np.moveaxis(rows, -1, 0)[-1:])
    _reverse_rows(rows)
    _sosfilt_rows(sos, rows, state)
    return np.moveaxis(rows, -1, 0)[::-1][edge:-edge]


def _sosfilt_zi(sos: FloatArray) -> FloatArray:
    """``scipy.signal.sosfilt_zi`` for one section: ``lfilter_zi(b, a)`` (the step response's steady state)."""
    zi = np.empty((1, 2), dtype=sos.dtype)
    b = sos[0, :3]
    a = sos[0, 3:]
    zi[0, ...] = 1.0 * _lfilter_zi(b, a)
    return zi


def _lfilter_zi(b: FloatArray, a: FloatArray) -> FloatArray:
    if a[0] != 1.0:
        b = b / a[0]
        a = a / a[0]
    n = max(a.shape[0], b.shape[0])
    # scipy.linalg.companion(a).T, built as scipy builds it
    first_row = -a[..., 1:] / (1.0 * a[..., 0:1])
    companion = np.zeros((*a.shape[:-1], n - 1, n - 1), dtype=first_row.dtype)
    companion[..., 0, :] = first_row
    companion[..., np.arange(1, n - 1), np.arange(0, n - 2)] = 1
    i_minus_a = np.eye(n - 1) - companion.T
    i_minus_a = np.asarray(i_minus_a, dtype=np.result_type(a, b))
    rhs = b[1:] - a[1:] * b[0]
    return np.linalg.solve(i_minus_a, rhs)


def _sosfilt_state(zi: FloatArray) -> FloatArray:
    """scipy's sosfilt state: ``zi`` (sections, 2, signals) as C-order (signals, sections, 2)."""
    zi = np.array(zi, dtype=np.float64)
    return np.ascontiguousarray(np.moveaxis(zi, (0, 1), (-2, -1)).reshape((-1, zi.shape[0], 2)))


@njit(cache=True)
def _sosfilt_rows(sos: FloatArray, x: FloatArray, zi: FloatArray) -> None:  # pragma: no cover - compiled
    """scipy.signal's ``_sosfilt_float``: each row of ``x`` through the sections, in place.

    The same products and sums in the same order (numba, like the C compiler scipy's wheel was
    built with, fuses no multiply-add here: the results are the same to the bit).
    """
    n_signals = x.shape[0]
    n_samples = x.shape[1]
    n_sections = sos.shape[0]
    for i in range(n_signals):
        for n in range(n_samples):
            x_cur = 1.0 * x[i, n]
            for s in range(n_sections):
                x_new = sos[s, 0] * x_cur + zi[i, s, 0]
                zi[i, s, 0] = sos[s, 1] * x_cur - sos[s, 4] * x_new + zi[i, s, 1]
                zi[i, s, 1] = sos[s, 2] * x_cur - sos[s, 5] * x_new
                x_cur = x_new
            x[i, n] = x_cur


@njit(cache=True)
def _even_extended_rows(x: FloatArray, edge: int, out: FloatArray) -> None:  # pragma: no cover - compiled
    """``out[j]`` = signal ``j`` of ``even_ext(x, edge, axis=0)``: ``x[edge:0:-1], x, x[-2:-(edge + 2):-1]``."""
    n = x.shape[0]
    for j in range(x.shape[1]):
        for k in range(edge):
            out[j, k] = x[edge - k, j]
        for k in range(n):
            out[j, edge + k] = x[k, j]
        for k in range(edge):
            out[j, edge + n + k] = x[n - 2 - k, j]


@njit(cache=True)
def _reverse_rows(rows: FloatArray) -> None:  # pragma: no cover - compiled
    """Reverse every row in place."""
    n = rows.shape[1]
    for j in range(rows.shape[0]):
        for k in range(n // 2):
            value = rows[j, k]
            rows[j, k] = rows[j, n - 1 - k]
            rows[j, n - 1 - k] = value
