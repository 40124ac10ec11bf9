"""The columns every model of a residual analysis is built from, evaluated a block of points at a time.

A model of the analysis predicts joint ``j`` at point ``n`` as ``G_j sum_c C[c] Z[c, j, n]``: a
linear combination of a fixed set of *global columns* ``Z`` (the layout), scaled by the joint's
torque gain. The layout holds

* the gravity regressor for each vector of an *up basis* (``e_y`` alone, or ``e_x, e_y, e_z``
  when the gravity tilt is free: a tilted base only changes the up direction ``u`` seen by the
  untilted chain, and the regressor is linear in ``u``, so a tilted model is a combination of
  the three),
* the elbow polynomial ``q4^k``, the direction columns ``dir_j``, the stiffness powers ``q_j^k``,
* the measured torque ``tau`` (the target is a column like the others),
* optionally *derivative columns*: the derivative of a given model's prediction with respect to
  one of its nonlinear parameters (encoder offsets, gains, tilt), computed analytically.

Angles are the measured ones minus the layout's encoder offsets. On joint ``j`` only the columns
that can be non-zero there are kept (:attr:`Layout.local`): ``Z_j`` is an (n, L_j) matrix.

The regressor entry of link ``i``'s moment component ``c`` on joint ``j`` is
``R_i e_c . (u x z_j)`` for ``i >= j`` (zero otherwise), ``R_i`` the rotor orientation and
``z_j`` the joint axis in the world (docs/residual.md, "Scale"). With ``U_j = sum_{i>=j} R_i
theta_i`` the summed first moment of links ``j..4``, the gravity torque is ``tau_j = u . (z_j x
U_j)`` and its derivative with respect to ``q_k`` is ``u . (z_a x (z_b x U_b))``, ``a = min(j,
k)``, ``b = max(j, k)``: the Hessian of the potential, used for the encoder-offset derivatives
instead of finite differences that rebuild every column.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from hal.robot import N_JOINTS, FloatArray, Kinematics

N_GRAVITY = 12
#: Points evaluated at once: large enough for BLAS and LAPACK to run at speed, small enough
#: that a block's columns (about 50 x 8,192 doubles per joint) stay in cache-sized memory.
BLOCK_POINTS = 8192

FREE_TILT_BASIS = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


@dataclass(frozen=True)
class Layout:
    """Which global columns exist, in order: gravity (per up vector), polynomial, dir, stiffness, tau, derivatives."""

    ups: tuple[tuple[float, float, float], ...] = ((0.0, 1.0, 0.0),)
    n_poly: int = 0
    direction_joints: tuple[int, ...] = ()  # 0-based joints with a dir column
    stiffness: tuple[tuple[int, int], ...] = ()  # (0-based joint, number of powers q^0..)
    n_derivatives: int = 0

    # -- global indices ---------------------------------------------------------------------

    def gravity(self, a: int, p: int) -> int:
        return a * N_GRAVITY + p

    def poly(self, k: int) -> int:
        return len(self.ups) * N_GRAVITY + k

    def direction(self, joint: int) -> int:
        return self.poly(self.n_poly) + self.direction_joints.index(joint)

    def stiffness_power(self, joint: int, k: int) -> int:
        start = self.poly(self.n_poly) + len(self.direction_joints)
        for j, powers in self.stiffness:
            if j == joint:
                if k >= powers:
                    raise IndexError(f"stiffness power {k} of joint {joint + 1} is not in the layout")
                return start + k
            start += powers
        raise IndexError(f"joint {joint + 1} has no stiffness columns in the layout")

    @property
    def tau(self) -> int:
        return self.poly(self.n_poly) + len(self.direction_joints) + sum(p for _, p in self.stiffness)

    def derivative(self, d: int) -> int:
        return self.tau + 1 + d

    @property
    def size(self) -> int:
        return self.tau + 1 + self.n_derivatives

    @property
    def free_tilt(self) -> bool:
        return len(self.ups) == 3

    def with_derivatives(self, n: int) -> Layout:
        return Layout(self.ups, self.n_poly, self.direction_joints, self.stiffness, n)

    @cached_property
    def local(self) -> tuple[np.ndarray, ...]:
        """Global indices of the columns that can be non-zero on each joint, in block order."""
        out = []
        for j in range(N_JOINTS):
            cols = [self.gravity(a, p) for a in range(len(self.ups)) for p in range(3 * j, N_GRAVITY)]
            if j == N_JOINTS - 1:
                cols += [self.poly(k) for k in range(self.n_poly)]
            if j in self.direction_joints:
                cols.append(self.direction(j))
            for joint, powers in self.stiffness:
                if joint == j:
                    cols += [self.stiffness_power(j, k) for k in range(powers)]
            cols.append(self.tau)
            cols += [self.derivative(d) for d in range(self.n_derivatives)]
            out.append(np.array(cols, dtype=np.intp))
        return tuple(out)

    def up_coefficients(self, u: FloatArray) -> FloatArray:
        """Coefficients of ``u`` on the up basis (raises when a fixed basis does not hold ``u``)."""
        basis = np.asarray(self.ups, dtype=float)
        if self.free_tilt:
            return np.asarray(u, dtype=float).copy()
        if not np.allclose(basis[0], u, rtol=0.0, atol=1e-13):
            raise ValueError(f"layout built for up vector {basis[0]}, asked for {u}")
        return np.ones(1)


def up_vector(tilt_rad: FloatArray) -> FloatArray:
    """The world's up direction seen by the untilted chain of a base tilted ``Rx(a) Rz(b)``: ``(Rx Rz)^T e_y``."""
    a, b = float(tilt_rad[0]), float(tilt_rad[1])
    ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    return np.array([sb * ca, cb * ca, -sa])


def up_vector_derivatives(tilt_rad: FloatArray) -> FloatArray:
    """``d u / d(about_x)`` and ``d u / d(about_z)``, (2, 3)."""
    a, b = float(tilt_rad[0]), float(tilt_rad[1])
    ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    return np.array([[-sb * sa, -cb * sa, -ca], [cb * ca, -sb * ca, 0.0]])


@dataclass(frozen=True)
class Derivatives:
    """Derivative columns of one model's prediction: the model (global coefficients ``c`` of its
    unscaled prediction, gains) and what to differentiate by.

    ``requests`` entries: ``("delta", k)`` an encoder offset of joint k (0-based), ``("gain", k)``,
    ``("tilt", i)`` (i = 0 about x, 1 about z; only with a single up vector, ``up_derivatives``).
    """

    coefficients: FloatArray
    gains: FloatArray
    requests: tuple[tuple[str, int], ...]
    up_derivatives: FloatArray | None = None


def _cross(e: FloatArray, z: FloatArray) -> FloatArray:
    """``e x z`` for a constant 3-vector ``e`` and (3, n) ``z``; exact zeros where ``e`` has them."""
    out = np.zeros_like(z)
    ex, ey, ez = (float(v) for v in e)
    if ey:
        out[0] += ey * z[2]
        out[2] -= ey * z[0]
    if ez:
        out[0] -= ez * z[1]
        out[1] += ez * z[0]
    if ex:
        out[1] -= ex * z[2]
        out[2] += ex * z[1]
    return out


def _cross_field(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a x b`` for (3, n) fields."""
    return np.stack([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


class Block:
    """Everything one block of points needs: angles seen by the model, rotations, axes."""

    def __init__(
        self,
        kinematics: Kinematics,
        q_rad: FloatArray,
        direction: FloatArray | None,
        tau_nm: FloatArray | None,
        offset_rad: FloatArray,
    ) -> None:
        q_model = q_rad - offset_rad[None, :]
        self.n = q_model.shape[0]
        self.q = np.ascontiguousarray(q_model.T)  # (4, n)
        self.direction = None if direction is None else np.ascontiguousarray(direction.T)
        self.tau = None if tau_nm is None else np.ascontiguousarray(tau_nm.T)
        self.rotors = kinematics.rotor_rotations_component_major(q_model)  # (4, 3, 3, n)
        self.axes = [np.ascontiguousarray(self.rotors[j, :, 2]) for j in range(N_JOINTS)]  # z_j, (3, n)

    def powers(self, joint: int, count: int) -> FloatArray:
        """``q_j^0 .. q_j^(count-1)``, (count, n), by successive products."""
        out = np.empty((count, self.n))
        if count:
            out[0] = 1.0
        for k in range(1, count):
            np.multiply(out[k - 1], self.q[joint], out=out[k])
        return out


def fill_columns(
    layout: Layout, block: Block, out: Sequence[FloatArray], derivatives: Derivatives | None = None
) -> None:
    """Write each joint's columns into ``out[j]``, shape (L_j, n) (row ``r`` = local column ``r``).

    Derivative columns are computed when the layout has them (``derivatives`` must say which).
    The measured-torque row is zero when the block has no torque (a prediction).
    """
    derived = None
    if layout.n_derivatives:
        if derivatives is None or len(derivatives.requests) != layout.n_derivatives:
            raise ValueError("the layout has derivative columns; say which derivatives to compute")
        derived = derivative_values(layout, block, derivatives)
    stiffness = dict(layout.stiffness)
    for j in range(N_JOINTS):
        rows = out[j]
        row = 0
        width = 3 * (N_JOINTS - j)
        for a in range(len(layout.ups)):
            w = _cross(np.asarray(layout.ups[a]), block.axes[j])
            for i in range(j, N_JOINTS):
                np.einsum("mcn,mn->cn", block.rotors[i], w, out=rows[row : row + 3])
                row += 3
            rows[row - width + 2] = 0.0  # z_j . (u x z_j): zero by construction, not by rounding
        if j == N_JOINTS - 1 and layout.n_poly:
            rows[row : row + layout.n_poly] = block.powers(j, layout.n_poly)
            row += layout.n_poly
        if j in layout.direction_joints:
            if block.direction is None:
                raise ValueError("the layout has direction columns but the data have no dir1..dir4")
            rows[row] = block.direction[j]
            row += 1
        if j in stiffness:
            rows[row : row + stiffness[j]] = block.powers(j, stiffness[j])
            row += stiffness[j]
        rows[row] = 0.0 if block.tau is None else block.tau[j]
        row += 1
        if derived is not None:
            rows[row : row + layout.n_derivatives] = derived[:, j]


def _polynomials(layout: Layout, c: FloatArray) -> list[FloatArray]:
    """Each joint's polynomial coefficients (in its own angle) in the model ``c``."""
    polys = [np.zeros(0) for _ in range(N_JOINTS)]
    if layout.n_poly:
        polys[N_JOINTS - 1] = c[layout.poly(0) : layout.poly(layout.n_poly)].copy()
    for joint, powers in layout.stiffness:
        coefficients = c[layout.stiffness_power(joint, 0) : layout.stiffness_power(joint, 0) + powers]
        size = max(polys[joint].size, powers)
        merged = np.zeros(size)
        merged[: polys[joint].size] += polys[joint]
        merged[:powers] += coefficients
        polys[joint] = merged
    return polys


def derivative_values(layout: Layout, block: Block, spec: Derivatives) -> FloatArray:
    """Derivatives of the model's prediction, (m, 4, n), analytically (see the module docstring)."""
    c = np.asarray(spec.coefficients, dtype=float)
    g = np.asarray(spec.gains, dtype=float)
    n = block.n
    kinds = {kind for kind, _ in spec.requests}
    # Per up vector e_a: w_j = e_a x z_j, U_j = sum_{i >= j} R_i theta_i, V_j = z_j x U_j.
    w: list[list[FloatArray]] = []
    u_sum: list[list[FloatArray]] = []
    v: list[list[FloatArray]] = []
    for a, e in enumerate(layout.ups):
        theta = c[layout.gravity(a, 0) : layout.gravity(a, N_GRAVITY)].reshape(N_JOINTS, 3)
        moments = np.einsum("imcn,ic->imn", block.rotors, theta)  # R_i theta_i, (4, 3, n)
        summed = [moments[N_JOINTS - 1]]
        for i in range(N_JOINTS - 2, -1, -1):
            summed.insert(0, summed[0] + moments[i])
        u_sum.append(summed)
        w.append([_cross(np.asarray(e), block.axes[j]) for j in range(N_JOINTS)])
        v.append([_cross_field(block.axes[j], summed[j]) for j in range(N_JOINTS)])

    def hessian(j: int, k: int) -> FloatArray:
        lo, hi = min(j, k), max(j, k)
        out = np.zeros(n)
        for a in range(len(layout.ups)):
            out += np.einsum("mn,mn->n", w[a][lo], v[a][hi])
        return out

    polys = _polynomials(layout, c)
    value = None
    if "gain" in kinds:
        value = np.zeros((N_JOINTS, n))
        for a in range(len(layout.ups)):
            for j in range(N_JOINTS):
                value[j] += np.einsum("mn,mn->n", w[a][j], u_sum[a][j])
        for j, poly in enumerate(polys):
            if poly.size:
                value[j] += np.polynomial.polynomial.polyval(block.q[j], poly)
        for j in layout.direction_joints:
            if block.direction is not None:
                value[j] += c[layout.direction(j)] * block.direction[j]
    out = np.zeros((len(spec.requests), N_JOINTS, n))
    for d, (kind, index) in enumerate(spec.requests):
        if kind == "delta":
            for j in range(N_JOINTS):
                out[d, j] = hessian(j, index)
            poly = polys[index]
            if poly.size > 1:
                out[d, index] += np.polynomial.polynomial.polyval(
                    block.q[index], np.polynomial.polynomial.polyder(poly)
                )
            out[d] *= -g[:, None]
        elif kind == "gain":
            out[d, index] = value[index]  # type: ignore[index]
        elif kind == "tilt":
            if len(layout.ups) != 1 or spec.up_derivatives is None:
                raise ValueError("tilt derivative columns need a layout with one up vector and its derivatives")
            du = spec.up_derivatives[index]
            for j in range(N_JOINTS):
                vj = v[0][j]
                out[d, j] = g[j] * (du[0] * vj[0] + du[1] * vj[1] + du[2] * vj[2])
        else:
            raise ValueError(f"unknown derivative {kind!r}")
    return out


def blocks(n_points: int, start: int = 0, size: int = BLOCK_POINTS) -> list[tuple[int, int]]:
    """``[lo, hi)`` ranges of at most ``size`` points covering ``start .. n_points``."""
    return [(lo, min(lo + size, n_points)) for lo in range(start, n_points, size)]
