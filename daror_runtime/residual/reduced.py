"""Every least-squares problem of a residual analysis, reduced to a few hundred rows without loss.

A model of the analysis predicts joint ``j`` as ``Z_j C_j`` (:mod:`.columns`): a fixed matrix of
columns times coefficients (gains folded in). Factor ``Z_j = Q_j R_j`` once (Householder QR,
accumulated a block of points at a time: TSQR); then for *any* coefficients,
``||Z_j a||= ||R_j a||`` because ``Q_j`` has orthonormal columns. Design, target, residual,
derivative columns and candidate directions of every model built from the same columns are
therefore represented exactly by ``R_j C_j``: at most ``L_j`` rows per joint (a few dozen)
instead of the ``N`` points. Minimum-norm least squares, its rank decision, the residual sum of
squares, the span test of the identifiability check and the standard errors all come out as on
the full matrices, to rounding: nothing is squared (unlike normal equations, which would turn
the ~1e-14 singular values of the rank-deficient PLF regressor into ~1e-8, close to the rank
cut-off of 1e-7).

Cross-validation uses one factor per contiguous fold. The training set of fold ``k`` is the other
folds' factors stacked: ``blockdiag(Q_i)`` has orthonormal columns too, so the stack represents
those rows exactly, and no fold ever copies the data.

Memory: the data, one block of columns (``L_j`` x 8,192 per joint), and the small factors.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import lapack

from daror_runtime.data.schema import StationaryDataset
from daror_runtime.residual.columns import Block, Derivatives, Layout, blocks, fill_columns
from hal.robot import N_JOINTS, FloatArray, Kinematics

#: Factors kept per workspace (each a few hundred kB at most).
_CACHE_SIZE = 12


def _qr_r(matrix: FloatArray) -> FloatArray:
    """``R`` of a Householder QR (rows min(M, L)), overwriting ``matrix`` (Fortran order)."""
    qr, _, _, info = lapack.dgeqrf(matrix, overwrite_a=1)
    if info != 0:
        raise np.linalg.LinAlgError(f"dgeqrf failed (info {info})")
    k = min(matrix.shape)
    return np.triu(qr[:k])


def stack_qr(factors: Sequence[FloatArray], width: int) -> FloatArray:
    """``R`` of the rows of several factors stacked (the QR of their union)."""
    parts = [f for f in factors if f.shape[0]]
    if not parts:
        return np.zeros((0, width))
    return _qr_r(np.asfortranarray(np.vstack(parts)))


def fold_bounds(n_points: int, folds: int) -> list[tuple[int, int]]:
    """Contiguous folds as ``[lo, hi)``: point ``i`` is in fold ``floor(i folds / n)``."""
    return [((k * n_points + folds - 1) // folds, ((k + 1) * n_points + folds - 1) // folds) for k in range(folds)]


@dataclass
class Factor:
    """Per fold and joint, ``R`` of the layout's columns over that fold's points."""

    layout: Layout
    offset_rad: FloatArray
    n_points: int
    bounds: list[tuple[int, int]]
    fold_factors: list[list[FloatArray]]  # [fold][joint]
    _rows: dict[object, list[FloatArray]] = field(default_factory=dict, repr=False)

    @property
    def folds(self) -> int:
        return len(self.bounds)

    def rows(self, which: object = "all") -> list[FloatArray]:
        """Per-joint ``R`` of ``"all"`` points, ``("fold", k)`` or ``("train", k)`` (all but fold k)."""
        if which in self._rows:
            return self._rows[which]
        if which == "all":
            chosen = range(self.folds)
        elif isinstance(which, tuple) and which[0] == "fold":
            chosen = [which[1]]
        elif isinstance(which, tuple) and which[0] == "train":
            chosen = [k for k in range(self.folds) if k != which[1]]
        else:
            raise ValueError(f"unknown row set {which!r}")
        chosen = list(chosen)
        if len(chosen) == 1:
            out = self.fold_factors[chosen[0]]
        elif which == "all":  # used by every solve: worth one more small QR per joint
            out = [
                stack_qr([self.fold_factors[k][j] for k in chosen], len(self.layout.local[j])) for j in range(N_JOINTS)
            ]
        else:  # a training set is solved once: its folds' rows stacked are as good as their QR
            out = [np.vstack([self.fold_factors[k][j] for k in chosen]) for j in range(N_JOINTS)]
        self._rows[which] = out
        return out

    def points(self, which: object = "all") -> int:
        if which == "all":
            return self.n_points
        lo, hi = self.bounds[which[1]]  # type: ignore[index]
        return hi - lo if which[0] == "fold" else self.n_points - (hi - lo)  # type: ignore[index]

    def assemble(self, which: object, coefficients: Sequence[FloatArray]) -> FloatArray:
        """``vstack_j R_j C_j``: the reduced form of the (4 N, m) matrix whose joint-j rows are ``Z_j C_j``.

        ``coefficients[j]`` is (size, m) or (size,) over the layout's global columns.
        """
        rows = self.rows(which)
        parts = []
        for j in range(N_JOINTS):
            c = np.asarray(coefficients[j], dtype=float)
            local = c[self.layout.local[j]]
            parts.append(rows[j] @ local)
        return np.concatenate(parts, axis=0)


def factorize(
    data: StationaryDataset,
    kinematics: Kinematics,
    layout: Layout,
    offset_rad: FloatArray,
    folds: int = 1,
    derivatives: Derivatives | None = None,
) -> Factor:
    """One pass over ``data``: per fold and joint, ``R`` of the layout's columns (TSQR by blocks)."""
    n = len(data)
    bounds = fold_bounds(n, folds)
    widths = [len(local) for local in layout.local]
    factors: list[list[FloatArray]] = []
    for lo, hi in bounds:
        current = [np.zeros((0, w)) for w in widths]
        for b_lo, b_hi in blocks(hi, lo):
            block = Block(
                kinematics,
                data.q_rad[b_lo:b_hi],
                None if data.direction is None else data.direction[b_lo:b_hi],
                data.tau_nm[b_lo:b_hi],
                offset_rad,
            )
            stacked = []
            for j in range(N_JOINTS):
                top = current[j].shape[0]
                matrix = np.empty((top + block.n, widths[j]), order="F")
                matrix[:top] = current[j]
                stacked.append(matrix)
            fill_columns(layout, block, [m.T[:, m.shape[0] - block.n :] for m in stacked], derivatives)
            current = [_qr_r(m) for m in stacked]
        factors.append(current)
    return Factor(layout, np.asarray(offset_rad, dtype=float).copy(), n, bounds, factors)


class FactorCache:
    """The last few factors of one dataset, by layout, encoder offsets, folds and derivative key."""

    def __init__(self) -> None:
        self._entries: OrderedDict[tuple[object, ...], Factor] = OrderedDict()

    def get(self, key: tuple[object, ...]) -> Factor | None:
        factor = self._entries.get(key)
        if factor is not None:
            self._entries.move_to_end(key)
        return factor

    def put(self, key: tuple[object, ...], factor: Factor) -> None:
        self._entries[key] = factor
        self._entries.move_to_end(key)
        while len(self._entries) > _CACHE_SIZE:
            self._entries.popitem(last=False)
