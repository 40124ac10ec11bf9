"""Minimum-norm least squares through the SVD pseudo-inverse (thesis Eq. 3.27-3.29).

``theta* = K^+ tau = V_1 Sigma_1^-1 U_1^T tau`` is the minimum-norm solution for a rank-deficient
regressor (the DAROR-01's has rank 8 of 12). ``U`` is never needed: with ``G = K^T K =
V Sigma^2 V^T``, ``theta* = V_1 Sigma_1^-2 V_1^T K^T tau``. ``V`` and ``Sigma`` are therefore taken
from the symmetric eigen-decomposition of the small Gram matrix (P x P, P <= ~20), which BLAS
forms in one pass over the 4N x P regressor: 25,000 points fit in milliseconds instead of the
tens of milliseconds a tall SVD takes here.

Squaring ``K`` squares its condition number; two steps of iterative refinement on the residual
(each one pass over K) restore the accuracy of the direct SVD. Rank is decided on the
column-scaled regressor (scaling changes no rank), and the minimum-norm property is restored in
the original parameters by projecting out the null space of ``K``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from hal.errors import ShapeError

#: Singular values below this fraction of the largest (column-scaled) count as zero.
DEFAULT_RCOND = 1e-7
#: Singular values below this fraction of the largest are re-measured directly (see below).
_DIRECT_BELOW = 1e-4


@dataclass(frozen=True)
class LeastSquaresFit:
    """Result of :func:`min_norm_least_squares`."""

    theta: np.ndarray  # (P,) minimum-norm solution
    rank: int
    singular_values: np.ndarray  # (P,) of the column-scaled regressor, descending
    null_space: np.ndarray  # (P, P - rank) orthonormal basis of null(K), original coordinates
    gram: np.ndarray  # (P, P) K^T K, original coordinates
    residual: np.ndarray  # (M,) y - K theta
    residual_sum_squares: float
    n_rows: int

    @property
    def degrees_of_freedom(self) -> int:
        """Equations left over once the identifiable combinations are fixed."""
        return self.n_rows - self.rank

    @property
    def residual_variance(self) -> float:
        """Unbiased estimate of the residual variance; NaN when no equation is left over."""
        return self.residual_sum_squares / self.degrees_of_freedom if self.degrees_of_freedom > 0 else float("nan")


def min_norm_least_squares(
    regressor_t: np.ndarray, target: np.ndarray, rcond: float = DEFAULT_RCOND, refinement_steps: int = 2
) -> LeastSquaresFit:
    """Solve ``min ||K theta - y||`` with the minimum-norm ``theta``.

    Args:
        regressor_t: ``K^T``, shape (P, M): one contiguous row per parameter.
        target: ``y``, shape (M,).
        rcond: relative singular-value cut-off on the column-scaled regressor.
        refinement_steps: passes of iterative refinement.
    """
    kt = np.asarray(regressor_t, dtype=float)
    y = np.asarray(target, dtype=float).reshape(-1)
    if kt.ndim != 2 or kt.shape[1] != y.shape[0]:
        raise ShapeError(f"regressor_t must be (P, M) with M = len(target); got {kt.shape} and {y.shape}")
    gram = kt @ kt.T
    norms = np.sqrt(np.diag(gram))
    scale = np.where(norms > 0, 1.0 / np.where(norms > 0, norms, 1.0), 1.0)
    eigenvalues, vectors = scipy.linalg.eigh(gram * scale[:, None] * scale[None, :], check_finite=False)
    order = np.argsort(eigenvalues)[::-1]
    eigenvalues, vectors = np.clip(eigenvalues[order], 0.0, None), vectors[:, order]
    singular = np.sqrt(eigenvalues)
    # Squaring leaves small singular values only accurate to ~sqrt(eps) of the largest; for the
    # few that are small, measure ||K S w|| directly, which is accurate to ~eps.
    small = np.flatnonzero(singular < _DIRECT_BELOW * singular[0])
    if small.size:
        singular[small] = np.linalg.norm((scale[:, None] * vectors[:, small]).T @ kt, axis=1)
        resort = np.argsort(singular)[::-1]
        singular, eigenvalues, vectors = singular[resort], eigenvalues[resort], vectors[:, resort]
    rank = int(np.sum(singular > rcond * singular[0])) if singular[0] > 0 else 0
    kept, inv = vectors[:, :rank], 1.0 / eigenvalues[:rank]
    null_space = np.linalg.qr(scale[:, None] * vectors[:, rank:])[0] if rank < len(scale) else np.zeros((len(scale), 0))

    def solve(rhs: np.ndarray) -> np.ndarray:
        phi = kept @ (inv * (kept.T @ (scale * rhs)))
        theta = scale * phi
        return theta - null_space @ (null_space.T @ theta)

    theta = solve(kt @ y)
    for _ in range(refinement_steps):
        theta = theta + solve(kt @ (y - kt.T @ theta))
    residual = y - kt.T @ theta
    return LeastSquaresFit(
        theta=theta,
        rank=rank,
        singular_values=singular,
        null_space=null_space,
        gram=gram,
        residual=residual,
        residual_sum_squares=float(residual @ residual),
        n_rows=y.shape[0],
    )
