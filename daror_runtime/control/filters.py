"""Discrete linear filters for the 1 kHz tick: transfer functions and per-joint filter banks.

Every filter the controllers run is designed in continuous time (or directly in z) with
:mod:`scipy.signal`'s ``cont2discrete`` and ``tf2ss``, discretised once at construction
(bilinear/Tustin or zero-order hold), and then executed as a discrete state-space system whose
state is kept explicitly in an array. Both functions are computed by
:mod:`daror_runtime.control.lti_conversion`, scipy's to the bit, without importing scipy.signal
(~0.5 s of every session's start-up):

    y[k]   = C x[k] + D u[k]
    x[k+1] = A x[k] + B u[k]

A :class:`FilterBank` holds one such SISO filter per joint (the same or different coefficients),
with the matrices stacked along a leading joint axis so that one call updates all four joints. The
stacked arrays (:attr:`FilterBank.a` ...) are what the compiled per-tick kernels of
:mod:`daror_runtime.control.sea_torque` read; the Python methods here are for construction,
analysis and tests. The same matrices feed the passivity analysis, so what is analysed is exactly
what runs.

Units are those of the signals filtered; times in seconds, frequencies in Hz unless a name says
``rad_s``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import linalg

import daror_runtime.control.lti_conversion as lti_conversion
from daror_runtime.control.base import ControlDesignError
from daror_runtime.errors import ShapeError
from hal.robot import FloatArray

ComplexArray = NDArray[np.complex128]

#: Coefficients whose magnitude is below this fraction of the largest are treated as zero when
#: trimming leading zeros of a polynomial (tf2ss and cont2discrete leave round-off there).
_TRIM_RELATIVE = 1e-13


def _trim(poly: FloatArray) -> FloatArray:
    """Drop leading (near-)zero coefficients; a zero polynomial becomes ``[0.0]``."""
    poly = np.atleast_1d(np.asarray(poly, dtype=float)).ravel()
    scale = float(np.max(np.abs(poly))) if poly.size else 0.0
    if scale == 0.0:
        return np.zeros(1)
    nonzero = np.flatnonzero(np.abs(poly) > _TRIM_RELATIVE * scale)
    return poly[nonzero[0] :].copy()


@dataclass(frozen=True)
class DiscreteTransferFunction:
    """``H(z) = num(z) / den(z)``, polynomials in descending powers of ``z``, sample period ``dt_s``.

    The denominator is normalised to a leading coefficient of 1. Construct with
    :meth:`from_continuous` (scipy's ``cont2discrete``) or directly from z-domain polynomials.

    Raises:
        ControlDesignError: an empty or zero denominator, a non-positive period, or an improper
            transfer function (numerator degree above the denominator's: not causal).
    """

    num: FloatArray
    den: FloatArray
    dt_s: float

    def __post_init__(self) -> None:
        num, den = _trim(self.num), _trim(self.den)
        if not np.all(np.isfinite(num)) or not np.all(np.isfinite(den)):
            raise ControlDesignError("transfer function coefficients must be finite")
        if den[0] == 0.0:
            raise ControlDesignError("transfer function denominator is zero")
        if not (np.isfinite(self.dt_s) and self.dt_s > 0.0):
            raise ControlDesignError(f"sample period must be positive, got {self.dt_s!r} s")
        if len(num) > len(den) and np.any(num != 0.0):
            raise ControlDesignError(
                f"improper (non-causal) transfer function: numerator degree {len(num) - 1} "
                f"above denominator degree {len(den) - 1}"
            )
        object.__setattr__(self, "num", num / den[0])
        object.__setattr__(self, "den", den / den[0])

    @classmethod
    def from_continuous(
        cls,
        num_s: Sequence[float] | FloatArray,
        den_s: Sequence[float] | FloatArray,
        dt_s: float,
        method: str = "bilinear",
    ) -> DiscreteTransferFunction:
        """Discretise ``num(s)/den(s)`` with ``method`` ("bilinear" (Tustin) or "zoh").

        Raises:
            ControlDesignError: unknown method or an improper continuous transfer function.
        """
        if method not in ("bilinear", "zoh"):
            raise ControlDesignError(f"unknown discretisation method {method!r}; expected 'bilinear' or 'zoh'")
        num_c, den_c = _trim(np.asarray(num_s, dtype=float)), _trim(np.asarray(den_s, dtype=float))
        if len(num_c) > len(den_c):
            raise ControlDesignError("improper continuous transfer function cannot be discretised")
        if len(den_c) == 1:  # a static gain: cont2discrete cannot realise order 0
            return cls(num_c / den_c[0], np.ones(1), dt_s)
        num_z, den_z, _ = lti_conversion.cont2discrete_tf(num_c, den_c, dt_s, method)
        return cls(np.asarray(num_z, dtype=float).ravel(), np.asarray(den_z, dtype=float).ravel(), dt_s)

    @classmethod
    def gain(cls, value: float, dt_s: float) -> DiscreteTransferFunction:
        """A static gain."""
        return cls(np.array([float(value)]), np.ones(1), dt_s)

    @classmethod
    def delay(cls, ticks: int, dt_s: float) -> DiscreteTransferFunction:
        """``z^-ticks``.

        Raises:
            ControlDesignError: a negative delay.
        """
        if ticks < 0:
            raise ControlDesignError(f"a delay cannot be negative, got {ticks} ticks")
        den = np.zeros(ticks + 1)
        den[0] = 1.0
        return cls(np.ones(1), den, dt_s)

    @classmethod
    def from_zpk(
        cls, zeros: Sequence[complex], poles: Sequence[complex], dc_gain: float, dt_s: float
    ) -> DiscreteTransferFunction:
        """From zeros and poles (conjugate pairs complete), scaled to ``H(1) = dc_gain``.

        Building from factors avoids root-finding polynomials with clustered roots (a multiple zero
        at ``z = -1`` comes back from ``np.roots`` smeared by ~1e-4).

        Raises:
            ControlDesignError: a pole or zero at ``z = 1`` (no finite, non-zero DC gain).
        """
        num = np.real(np.poly(np.asarray(zeros, dtype=complex))) if len(zeros) else np.ones(1)
        den = np.real(np.poly(np.asarray(poles, dtype=complex))) if len(poles) else np.ones(1)
        at_one = np.polyval(num, 1.0) / np.polyval(den, 1.0) if np.polyval(den, 1.0) != 0.0 else 0.0
        if at_one == 0.0 or not np.isfinite(at_one):
            raise ControlDesignError("from_zpk needs no pole or zero at z = 1")
        return cls(num * (dc_gain / at_one), den, dt_s)

    # --- algebra ---------------------------------------------------------------------------

    def _check_period(self, other: DiscreteTransferFunction) -> None:
        if not np.isclose(self.dt_s, other.dt_s, rtol=1e-12, atol=0.0):
            raise ControlDesignError(f"cannot combine filters of periods {self.dt_s} s and {other.dt_s} s")

    def __mul__(self, other: DiscreteTransferFunction) -> DiscreteTransferFunction:
        """Series connection."""
        self._check_period(other)
        return DiscreteTransferFunction(np.polymul(self.num, other.num), np.polymul(self.den, other.den), self.dt_s)

    def __add__(self, other: DiscreteTransferFunction) -> DiscreteTransferFunction:
        """Parallel connection."""
        self._check_period(other)
        num = np.polyadd(np.polymul(self.num, other.den), np.polymul(other.num, self.den))
        return DiscreteTransferFunction(num, np.polymul(self.den, other.den), self.dt_s)

    def inverse(self) -> DiscreteTransferFunction:
        """``1 / H``; may be improper (check :attr:`relative_degree` before realising it).

        Raises:
            ControlDesignError: ``H`` is identically zero.
        """
        if not np.any(self.num != 0.0):
            raise ControlDesignError("cannot invert a zero transfer function")
        # Build without the causality check: an inverse is usually improper until multiplied by Q.
        out = object.__new__(DiscreteTransferFunction)
        num, den = _trim(self.den), _trim(self.num)
        object.__setattr__(out, "num", num / den[0])
        object.__setattr__(out, "den", den / den[0])
        object.__setattr__(out, "dt_s", self.dt_s)
        return out

    def feedback(self, other: DiscreteTransferFunction | None = None) -> DiscreteTransferFunction:
        """Negative feedback ``H / (1 + H G)`` with ``G = other`` (unity if None)."""
        other = other or DiscreteTransferFunction.gain(1.0, self.dt_s)
        self._check_period(other)
        num = np.polymul(self.num, other.den)
        den = np.polyadd(np.polymul(self.den, other.den), np.polymul(self.num, other.num))
        return DiscreteTransferFunction(num, den, self.dt_s)

    # --- properties ------------------------------------------------------------------------

    @property
    def relative_degree(self) -> int:
        """Denominator degree minus numerator degree: the delay in ticks before an input shows."""
        return len(self.den) - len(self.num)

    @property
    def poles(self) -> ComplexArray:
        return np.roots(self.den).astype(complex)

    @property
    def zeros(self) -> ComplexArray:
        return np.roots(self.num).astype(complex)

    @property
    def is_stable(self) -> bool:
        """All poles strictly inside the unit circle."""
        return bool(np.all(np.abs(self.poles) < 1.0))

    @property
    def dc_gain(self) -> float:
        """``H(1)``; infinite for a pole at ``z = 1``."""
        den = np.polyval(self.den, 1.0)
        return float(np.polyval(self.num, 1.0) / den) if den != 0.0 else float("inf")

    def response(self, frequencies_hz: FloatArray) -> ComplexArray:
        """Frequency response ``H(exp(j 2 pi f dt))`` at the given frequencies."""
        z = np.exp(2j * np.pi * np.asarray(frequencies_hz, dtype=float) * self.dt_s)
        return np.polyval(self.num, z) / np.polyval(self.den, z)

    def state_space(self) -> tuple[FloatArray, FloatArray, FloatArray, float]:
        """A balanced state-space realisation ``(A (n, n), B (n,), C (n,), D)``.

        Balancing (a diagonal similarity transform) keeps the companion form's coefficients of
        similar size, which matters for filters with poles close to ``z = 1``.

        Raises:
            ControlDesignError: the transfer function is improper.
        """
        if self.relative_degree < 0:
            raise ControlDesignError("cannot realise an improper (non-causal) transfer function")
        order = len(self.den) - 1
        if order == 0:
            return np.zeros((0, 0)), np.zeros(0), np.zeros(0), float(self.num[0])
        a, b, c, d = lti_conversion.tf2ss(self.num, self.den)
        _, (scale, _) = linalg.matrix_balance(a, permute=False, separate=True)
        a = a * scale[None, :] / scale[:, None]
        b = b.ravel() / scale
        c = c.ravel() * scale
        return a, b, c, float(np.asarray(d).ravel()[0]) if np.size(d) else 0.0


class FilterBank:
    """One discrete SISO filter per joint, executed as stacked state-space systems.

    Arrays (joint axis first, every channel padded to the bank's largest order ``n``, at least 1):
    ``a`` (N, n, n), ``b`` (N, n), ``c`` (N, n), ``d`` (N,), state ``x`` (N, n). Padding adds
    states that neither the input reaches nor the output sees, so responses are unchanged.

    Raises:
        ControlDesignError: no filters, mixed sample periods, or an improper filter.
    """

    def __init__(self, filters: Sequence[DiscreteTransferFunction]) -> None:
        if not filters:
            raise ControlDesignError("a filter bank needs at least one filter")
        periods = {f.dt_s for f in filters}
        if len(periods) != 1:
            raise ControlDesignError(f"filters of one bank must share the sample period, got {sorted(periods)}")
        self.dt_s = filters[0].dt_s
        self.filters = tuple(filters)
        realisations = [f.state_space() for f in filters]
        order = max(1, *(r[0].shape[0] for r in realisations))
        n_ch = len(filters)
        self.a = np.zeros((n_ch, order, order))
        self.b = np.zeros((n_ch, order))
        self.c = np.zeros((n_ch, order))
        self.d = np.zeros(n_ch)
        for j, (a, b, c, d) in enumerate(realisations):
            m = a.shape[0]
            self.a[j, :m, :m] = a
            self.b[j, :m] = b
            self.c[j, :m] = c
            self.d[j] = d
        self.x = np.zeros((n_ch, order))
        # Steady state per unit of constant input, (I - A)^-1 B, solved once here so that reset()
        # (called in the tick when a mode takes over) is one multiplication. Zero for an integrator.
        self._steady = np.zeros((n_ch, order))
        eye = np.eye(order)
        for j in range(n_ch):
            try:
                self._steady[j] = np.linalg.solve(eye - self.a[j], self.b[j])
            except np.linalg.LinAlgError:
                self._steady[j] = 0.0

    @classmethod
    def replicate(cls, tf: DiscreteTransferFunction, channels: int) -> FilterBank:
        """The same filter on ``channels`` channels."""
        return cls([tf] * channels)

    @property
    def channels(self) -> int:
        return self.a.shape[0]

    @property
    def order(self) -> int:
        return self.a.shape[1]

    def _as_input(self, u: FloatArray | float) -> FloatArray:
        u = np.broadcast_to(np.asarray(u, dtype=float), (self.channels,))
        return u

    def output(self, u: FloatArray | float) -> FloatArray:
        """``y = C x + D u`` without advancing the state; u (N,) or a scalar for every channel.

        Raises:
            ShapeError: ``u`` does not broadcast to (N,).
        """
        try:
            u = self._as_input(u)
        except ValueError:
            raise ShapeError(f"filter bank input must broadcast to ({self.channels},)") from None
        return np.einsum("jn,jn->j", self.c, self.x) + self.d * u

    def advance(self, u: FloatArray | float) -> None:
        """``x = A x + B u``."""
        try:
            u = self._as_input(u)
        except ValueError:
            raise ShapeError(f"filter bank input must broadcast to ({self.channels},)") from None
        self.x = np.einsum("jmn,jn->jm", self.a, self.x) + self.b * u[:, None]

    def step(self, u: FloatArray | float) -> FloatArray:
        """Output for input ``u``, then advance: one tick."""
        y = self.output(u)
        self.advance(u)
        return y

    def reset(self, u0: FloatArray | float = 0.0) -> None:
        """Set the state to the steady state of a constant input ``u0`` (zero: all zeros).

        For a channel with a pole at ``z = 1`` (an integrator) the state is set to zero instead,
        since no finite steady state exists.
        """
        u0 = self._as_input(u0)
        self.x = self._steady * u0[:, None]

    def response(self, frequencies_hz: FloatArray) -> ComplexArray:
        """Frequency response of every channel's realisation, (N, F): ``C (zI - A)^-1 B + D``."""
        z = np.exp(2j * np.pi * np.asarray(frequencies_hz, dtype=float) * self.dt_s)
        eye = np.eye(self.order)
        out = np.empty((self.channels, z.size), dtype=complex)
        for j in range(self.channels):
            resolvent = np.linalg.solve(z[:, None, None] * eye[None] - self.a[j][None], self.b[j][None, :, None])
            out[j] = (resolvent[..., 0] @ self.c[j]) + self.d[j]
        return out
