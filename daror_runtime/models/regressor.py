"""The PLF regressor of the DAROR-01 (thesis Sec. 4.2.1-4.2.2, Eq. 4.8-4.27) and a fast evaluator.

Potential energy is linear in 12 parameters (Eq. 4.19-4.20)::

    V_y(q) = e_y^T [0R_1r(q) 0R_2r(q) 0R_3r(q) 0R_4r(q)] theta,
    theta = [m1 g p1; m2 g p2; m3 g p3 + m4 g delta; m4 g p4]

and the holding torque is its gradient, ``tau = K(q) theta`` with ``K`` of Eq. 4.21-4.23.
PLF+ appends the elbow polynomial ``tau_4 += sum_k mu_k q4^k`` (Eq. 4.25-4.27).

Two implementations of the same map live here on purpose:

* :func:`gravity_regressor` builds ``K(q)`` from the derivative of the rotations (Eq. 4.23):
  it is what least squares needs, vectorised over N configurations;
* :class:`LinearTorqueEvaluator` evaluates ``K(q) theta`` for known parameters by a recursion
  over the chain (gravity direction forward, first moments backward): a few dozen float
  operations, cheap enough for the 1 kHz tick, and vectorised for batches.

Tests check both against each other and against the simulator's independent CoM-Jacobian path.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit

from hal.errors import ShapeError
from hal.robot import N_JOINTS, FloatArray, Kinematics, as_configurations

N_GRAVITY_PARAMETERS = 12
GRAVITY_PARAMETER_NAMES: tuple[str, ...] = tuple(
    f"theta{link}{axis}" for link in range(1, N_JOINTS + 1) for axis in "xyz"
)
_E_Y = np.array([0.0, 1.0, 0.0])


def polynomial_parameter_names(order: int) -> tuple[str, ...]:
    return tuple(f"mu{k}" for k in range(order + 1))


def regressor_parameter_major(kinematics: Kinematics, q: FloatArray, elbow_order: int | None = None) -> FloatArray:
    """``[K(q) K_s(q4)]`` laid out (P, 4, N): row ``[p, j]`` is a contiguous length-N vector.

    P is 12, plus ``elbow_order + 1`` polynomial columns (PLF+, Eq. 4.25-4.27) when given. This
    layout makes ``reshape(P, 4 N)`` a view whose Gram matrix BLAS computes in one pass.

    Entry ``[3 i + c, j, n]`` is ``d/dq_j`` of the vertical component of ``0R_{i,r} e_c``: zero for
    ``j > i`` (Eq. 4.22). With ``0R_{i,r} = 0R_{j,s} Rz(q_j) {}^{j,r}R_{i,r}`` the chain rule only
    touches ``Rz(q_j)``, and ``Rz'(q) = Rz(q) [e_z]x`` (Eq. 4.23), so ``d 0R_{i,r}/dq_j =
    [z_j]x 0R_{i,r}``, ``z_j`` being joint ``j``'s world axis. The vertical row of ``[z_j]x`` is
    ``e_y x z_j = (z_jz, 0, -z_jx)``.
    """
    q = as_configurations(q)
    rotors = kinematics.rotor_rotations_component_major(q)  # (4, 3, 3, N)
    n = q.shape[0]
    n_poly = 0 if elbow_order is None else elbow_order + 1
    out = np.empty((N_GRAVITY_PARAMETERS + n_poly, N_JOINTS, n))
    scratch = np.empty((3, n))
    for j in range(N_JOINTS):
        lead_x, minus_lead_z = rotors[j, 2, 2], rotors[j, 0, 2]  # e_y x z_j = (z_jz, 0, -z_jx)
        for i in range(N_JOINTS):
            block = out[3 * i : 3 * i + 3, j]
            if i < j:
                block.fill(0.0)
                continue
            np.multiply(rotors[i, 0], lead_x, out=block)
            np.multiply(rotors[i, 2], minus_lead_z, out=scratch)
            block -= scratch
    if n_poly:
        powers = out[N_GRAVITY_PARAMETERS:]
        powers[:, :3] = 0.0
        powers[0, 3] = 1.0
        for k in range(1, n_poly):
            np.multiply(powers[k - 1, 3], q[:, 3], out=powers[k, 3])
    return out


def gravity_regressor(kinematics: Kinematics, q: FloatArray) -> FloatArray:
    """``Ktilde(q)`` of Eq. 4.21-4.23, ``tau = K theta``; shape (N, 4, 12) (a strided view)."""
    return np.transpose(regressor_parameter_major(kinematics, q), (2, 1, 0))


@njit(cache=True)
def linear_torque(q: np.ndarray, p: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Holding torque at one ``q`` by the recursion of :class:`LinearTorqueEvaluator`, compiled.

    ``p`` = [b (3), cos 60, sin 60, theta (12), number of polynomial terms, mu ...].
    """
    bx, by, bz, ca, sa = p[0], p[1], p[2], p[3], p[4]
    t = p[5:17]
    c1, s1 = math.cos(q[0]), math.sin(q[0])
    c2, s2 = math.cos(q[1]), math.sin(q[1])
    c3, s3 = math.cos(q[2]), math.sin(q[2])
    c4, s4 = math.cos(q[3]), math.sin(q[3])
    g1x, g1y, g1z = c1 * bx + s1 * by, -s1 * bx + c1 * by, bz
    hx, hz = ca * g1x - sa * g1z, sa * g1x + ca * g1z
    g2x, g2y, g2z = c2 * hx + s2 * g1y, -s2 * hx + c2 * g1y, hz
    hx = ca * g2x - sa * g2z
    g3x, g3y = c3 * hx + s3 * g2y, -s3 * hx + c3 * g2y
    g4x, g4y = c4 * g3x + s4 * g3y, -s4 * g3x + c4 * g3y
    u4x, u4y, u4z = t[9], t[10], t[11]
    u3x = t[6] + c4 * u4x - s4 * u4y
    u3y = t[7] + s4 * u4x + c4 * u4y
    u3z = t[8] + u4z
    rx, ry = c3 * u3x - s3 * u3y, s3 * u3x + c3 * u3y
    u2x, u2y, u2z = t[3] + ca * rx + sa * u3z, t[4] + ry, t[5] - sa * rx + ca * u3z
    rx, ry = c2 * u2x - s2 * u2y, s2 * u2x + c2 * u2y
    u1x, u1y = t[0] + ca * rx + sa * u2z, t[1] + ry
    tau4 = g4y * u4x - g4x * u4y
    n_mu = int(p[17])
    acc = 0.0
    for k in range(n_mu - 1, -1, -1):
        acc = acc * q[3] + p[18 + k]
    out[0] = g1y * u1x - g1x * u1y
    out[1] = g2y * u2x - g2x * u2y
    out[2] = g3y * u3x - g3x * u3y
    out[3] = tau4 + acc


class LinearTorqueEvaluator:
    """Holding torque and potential of ``theta`` (12) plus an elbow polynomial ``mu`` (order+1).

    The recursion: with ``g_j`` the world's up direction seen in rotor frame ``j`` and ``u_j``
    the summed first moment of links ``j..4`` in that frame, ``V_y = g_j . u_j`` for every ``j``
    and ``tau_j = g_j . (e_z x u_j) = g_jy u_jx - g_jx u_jy``.
    """

    def __init__(self, kinematics: Kinematics, theta: Sequence[float], mu: Sequence[float] = ()) -> None:
        theta_arr = np.asarray(theta, dtype=float)
        if theta_arr.shape != (N_GRAVITY_PARAMETERS,):
            raise ShapeError(f"theta must have {N_GRAVITY_PARAMETERS} entries, got shape {theta_arr.shape}")
        self.kinematics = kinematics
        self.theta = theta_arr
        self.mu = np.asarray(mu, dtype=float).reshape(-1)
        base_up = kinematics.base_rotation.T @ _E_Y  # up direction in stator-1 coordinates
        inter = kinematics.inter_rotation
        if not (np.isclose(inter[1, 1], 1.0) and np.allclose(inter[1, [0, 2]], 0.0)):
            raise ShapeError("the fast evaluator assumes stators 2 and 3 are rotated about y")
        if not np.allclose(kinematics.stator_offsets[3], np.eye(3)):
            raise ShapeError("the fast evaluator assumes stator 4 is parallel to rotor 3")
        self._b = tuple(float(v) for v in base_up)
        self._ca, self._sa = float(inter[0, 0]), float(inter[0, 2])
        self._t = tuple(float(v) for v in theta_arr)
        self._mu = tuple(float(v) for v in self.mu)
        self._packed = np.concatenate([base_up, [self._ca, self._sa], theta_arr, [float(self.mu.size)], self.mu])

    # -- one configuration, plain floats: this is the path inside the tick -------------------

    def torque(self, q: Sequence[float]) -> np.ndarray:
        """Holding torque (Nm) at one configuration ``q`` (rad, 4 values): the compiled recursion (~1 us)."""
        out = np.empty(N_JOINTS)
        linear_torque(np.asarray(q, dtype=np.float64), self._packed, out)
        return out

    @property
    def packed_parameters(self) -> np.ndarray:
        """The parameter vector of the compiled :func:`linear_torque` (for compiled controllers)."""
        return self._packed

    # -- N configurations, numpy ----------------------------------------------------------

    def _chain(self, q: FloatArray) -> tuple[list[FloatArray], list[FloatArray]]:
        """Up directions ``g_j`` and first moments ``u_j``, each (N, 3), for j = 1..4."""
        c, s = np.cos(q), np.sin(q)
        ca, sa = self._ca, self._sa
        n = q.shape[0]
        g = [np.empty((n, 3)) for _ in range(N_JOINTS)]
        prev = np.broadcast_to(np.asarray(self._b), (n, 3))
        for j in range(N_JOINTS):
            if j in (1, 2):  # through A^T = Ry(60 deg)^T
                px = ca * prev[:, 0] - sa * prev[:, 2]
                pz = sa * prev[:, 0] + ca * prev[:, 2]
                py = prev[:, 1]
            else:
                px, py, pz = prev[:, 0], prev[:, 1], prev[:, 2]
            g[j][:, 0] = c[:, j] * px + s[:, j] * py
            g[j][:, 1] = -s[:, j] * px + c[:, j] * py
            g[j][:, 2] = pz
            prev = g[j]
        t = self.theta.reshape(N_JOINTS, 3)
        u = [np.empty((n, 3)) for _ in range(N_JOINTS)]
        u[3][:] = t[3]
        for j in (2, 1, 0):
            nxt = u[j + 1]
            rx = c[:, j + 1] * nxt[:, 0] - s[:, j + 1] * nxt[:, 1]
            ry = s[:, j + 1] * nxt[:, 0] + c[:, j + 1] * nxt[:, 1]
            rz = nxt[:, 2]
            if j == 2:  # stator 4 is parallel to rotor 3
                u[j][:, 0], u[j][:, 1], u[j][:, 2] = t[j, 0] + rx, t[j, 1] + ry, t[j, 2] + rz
            else:
                u[j][:, 0] = t[j, 0] + ca * rx + sa * rz
                u[j][:, 1] = t[j, 1] + ry
                u[j][:, 2] = t[j, 2] - sa * rx + ca * rz
        return g, u

    def torque_batch(self, q: FloatArray) -> FloatArray:
        """Holding torque (Nm) at N configurations; (N, 4) in, (N, 4) out."""
        q = as_configurations(q)
        g, u = self._chain(q)
        tau = np.empty_like(q)
        for j in range(N_JOINTS):
            tau[:, j] = g[j][:, 1] * u[j][:, 0] - g[j][:, 0] * u[j][:, 1]
        if self.mu.size:
            tau[:, 3] += np.polynomial.polynomial.polyval(q[:, 3], self.mu)
        return tau

    def potential_batch(self, q: FloatArray) -> FloatArray:
        """Potential energy (J, up to a constant) whose gradient is :meth:`torque_batch`; (N,)."""
        q = as_configurations(q)
        g, u = self._chain(q)
        energy = np.einsum("nk,nk->n", g[0], u[0])
        if self.mu.size:
            integral = np.concatenate([[0.0], self.mu / np.arange(1, self.mu.size + 1)])
            energy = energy + np.polynomial.polynomial.polyval(q[:, 3], integral)
        return energy
