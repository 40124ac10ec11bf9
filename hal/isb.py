"""ISB angles of the glenohumeral joint, the shoulder's inverse kinematics and the pilot's limits.

Thesis Sec. 2.1.1 names three shoulder angles after the ISB recommendation (elevation, horizontal
rotation, axial rotation) but its wording leaves the sequence and the signs open, and Fig. 2.1 is
lost. This module fixes one precise convention (docs/identification.md has the reasoning and a
table of example poses).

Frames (all right-handed):

* world ``Psi_0`` (Sec. 2.1.2): origin in the shoulder's centre of rotation, ``y`` up. The thesis
  does not say which way ``x`` and ``z`` point; we take **+z anterior (forward) and -x lateral (to
  the pilot's right)**. With the opposite choice the hanging arm with a forward-flexing elbow is
  outside the joint ranges and the elbow would flex with negative ``q4`` (docs/identification.md).
* thorax ``T`` (ISB's thorax frame): ``X`` forward, ``Y`` up, ``Z`` lateral, i.e. the columns of
  :data:`THORAX_IN_WORLD` are ``+z``, ``+y``, ``-x`` of the world.
* rotor 3 (the upper-arm segment): ``x`` from the shoulder towards the elbow, ``z`` the elbow axis.

Angles, in radians in code (degrees only in files a person edits):

* **elevation** ``gamma_e`` in [0, pi]: the angle between the upper arm and straight down.
* **horizontal rotation** ``gamma_h`` in (-pi, pi]: the plane of elevation, the azimuth of the upper
  arm about the vertical: 0 = abduction plane (arm to the side), +pi/2 = flexion plane (arm
  forward), positive towards anterior and across the body, negative behind the frontal plane.
  Undefined while the arm hangs (``gamma_e = 0``): it is reported as 0 there.
* **axial rotation** ``gamma_a`` in (-pi, pi]: rotation about the upper arm (positive right-handed
  about the vector from the shoulder to the elbow, which is *external* rotation of the right arm),
  measured from the pose the arm reaches from the neutral by the shortest swing. 0 means: forearm
  forward when the arm hangs, forearm up at 90 deg flexion, forearm forward at 90 deg abduction.
* **elbow** = ``q4``: 0 = straight arm, positive = flexion.

The shoulder rotation, a Y-X-Y sequence in the thorax frame as ISB recommends::

    S(gamma_e, gamma_h, gamma_a) = Ry(gamma_h) Rx(-gamma_e) Ry(-(gamma_h + gamma_a))   (thorax coordinates)
    R_sh = T S T^T,  T = THORAX_IN_WORLD                                                (world coordinates)
    0R_{3,r}(q) = R_sh R3_neutral,  R3_neutral = 0R_{3,r}(q_neutral)

The first two angles are ISB's plane of elevation and elevation; the third differs from ISB's
axial angle ``gamma_ISB = -(gamma_h + gamma_a)`` by the plane of elevation, which removes ISB's
gimbal lock from the axial rotation: ``gamma_a`` is continuous wherever the arm does not point
straight up (outside every workspace), so a limit on it does not flicker as the arm hangs.

The shoulder of the DAROR-01 is singular where its three axes are coplanar (``q2 = 0``: axes 1 and
3 at 120 deg) and where axes 1 and 3 align (``q2 = +-180 deg``, outside the joint range):
``det J = sin^2(60 deg) sin(q2)``. Between them lie two inverse-kinematics branches
(``q2 > 0`` and ``q2 < 0``); the neutral and every shipped waypoint are on ``q2 > 0``.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache
from pathlib import Path

import numpy as np
from numba import njit
from pydantic import BaseModel, ConfigDict, Field

from hal.errors import DescriptionError, InputError, ShapeError
from hal.robot import N_JOINTS, FloatArray, Kinematics, RobotDescription, load_description, rot_x, rot_y, rot_z
from hal.robot import AngleRange as RobotAngleRange
from hal.yamlfile import Number, load_yaml_model, read_yaml

__all__ = [
    "ISB_NAMES",
    "NEUTRAL_ROTOR3_IN_THORAX",
    "THORAX_IN_WORLD",
    "AngleRange",
    "IsbLimits",
    "IsbLimitsError",
    "Shoulder",
    "UnreachablePoseError",
    "default_shoulder",
    "isb_from_q",
    "isb_single",
    "jacobian_sigma_min",
    "load_isb_limits",
    "monitor_isb_function",
    "q_from_isb",
    "shoulder_fk_kernel",
    "shoulder_jacobian",
    "shoulder_rotation",
    "thorax_rotation",
]

#: Names of the four ISB angles, in the order of every (4,) or (N, 4) ISB array.
ISB_NAMES = ("elevation", "horizontal rotation", "axial rotation", "elbow")
#: The same angles as the limits file names them (:class:`IsbLimits`' fields).
ISB_FIELDS = ("elevation", "horizontal_rotation", "axial_rotation", "elbow")

#: Thorax axes in world coordinates (columns: forward, up, lateral = world +z, +y, -x).
THORAX_IN_WORLD = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])

#: Rotor 3 of the neutral pose in thorax coordinates: upper arm down (-Y), rotor y forward (X, so
#: that a positive q4 flexes the forearm forward), elbow axis lateral (Z).
NEUTRAL_ROTOR3_IN_THORAX = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

#: Below this ``sin(gamma_e)`` the arm hangs straight down and the horizontal rotation is reported as 0.
POLE_SIN = 1e-12

#: The neutral pose must be at least this far from a singularity (smallest singular value of J).
NEUTRAL_MIN_SIGMA = 0.3

#: Slack on joint limits and ``cos(q2)`` for round-off in the inverse kinematics.
_LIMIT_SLACK_RAD = 1e-9


class UnreachablePoseError(InputError):
    """An ISB pose (or shoulder rotation) the robot cannot reach inside its joint limits."""


class IsbLimitsError(InputError):
    """A pilot's ISB limits file is missing or does not match the schema (file, line, field named)."""


# --- the pilot's limits ------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class AngleRange(RobotAngleRange):
    """An ISB angle interval in degrees, within -180..180, exposed in radians."""

    lower_deg: Number = Field(ge=-180.0, le=180.0)
    upper_deg: Number = Field(ge=-180.0, le=180.0)


class IsbLimits(_Strict):
    """The pilot's range of motion in ISB angles, recorded by the operator (FSM state ``rom_limits``).

    The defaults are a placeholder until the operator has recorded the pilot's range, not a
    clinical range; they contain every shipped identification waypoint. ``horizontal_free_below_deg``: the horizontal
    rotation (the plane of elevation) is not limited while the elevation is below this angle,
    because it is undefined when the arm hangs and changes arbitrarily fast near there, while the
    arm itself is within this angle of its resting pose.
    """

    elevation: AngleRange = AngleRange(lower_deg=0.0, upper_deg=100.0)
    horizontal_rotation: AngleRange = AngleRange(lower_deg=-20.0, upper_deg=165.0)
    axial_rotation: AngleRange = AngleRange(lower_deg=-75.0, upper_deg=75.0)
    elbow: AngleRange = AngleRange(lower_deg=5.0, upper_deg=120.0)
    horizontal_free_below_deg: Number = Field(20.0, ge=0.0, le=90.0)

    @property
    def ranges(self) -> tuple[AngleRange, AngleRange, AngleRange, AngleRange]:
        return (self.elevation, self.horizontal_rotation, self.axial_rotation, self.elbow)

    @property
    def lower_rad(self) -> FloatArray:
        """Lower bounds (4,) in rad, in the order of :data:`ISB_NAMES`."""
        return np.array([r.lower_rad for r in self.ranges])

    @property
    def upper_rad(self) -> FloatArray:
        """Upper bounds (4,) in rad, in the order of :data:`ISB_NAMES`."""
        return np.array([r.upper_rad for r in self.ranges])

    @property
    def horizontal_free_below_rad(self) -> float:
        return float(np.deg2rad(self.horizontal_free_below_deg))

    def for_box_check(self, isb: FloatArray) -> FloatArray:
        """ISB angles as a plain box test against (lower_rad, upper_rad) must see them.

        Below ``horizontal_free_below_deg`` of elevation the horizontal rotation is replaced by its
        nearest value inside the limits (it is not limited there). Shape as ``isb``, rad.
        """
        isb = np.array(isb, dtype=float)
        low = isb[..., 0] < self.horizontal_free_below_rad
        isb[..., 1] = np.where(
            low,
            np.clip(isb[..., 1], self.horizontal_rotation.lower_rad, self.horizontal_rotation.upper_rad),
            isb[..., 1],
        )
        return isb

    def contains(self, isb: FloatArray) -> bool | np.ndarray:
        """True where ISB angles (4,) or (N, 4) in rad are inside the limits (bool or (N,) bool)."""
        boxed = self.for_box_check(isb)
        inside = np.all((boxed >= self.lower_rad) & (boxed <= self.upper_rad), axis=-1)
        return bool(inside) if np.ndim(inside) == 0 else inside

    def violations(self, isb: FloatArray) -> list[str]:
        """What one pose (4,) in rad violates, one readable phrase per angle; empty when inside."""
        boxed = self.for_box_check(np.asarray(isb, dtype=float).reshape(N_JOINTS))
        found = []
        for name, value, rng in zip(ISB_NAMES, boxed, self.ranges, strict=True):
            deg = float(np.degrees(value))
            if not rng.lower_deg <= deg <= rng.upper_deg:
                found.append(f"{name} {deg:.1f} deg outside [{rng.lower_deg:g}, {rng.upper_deg:g}] deg")
        return found


def isb_limits_yaml(limits: IsbLimits, comment: str = "") -> str:
    """``limits`` as the YAML text :func:`load_isb_limits` reads (degrees, every field written out).

    ``comment``: lines put first as ``#`` comments (whose limits, when and how they were recorded).
    """
    lines = [f"# {line}" for line in comment.splitlines()]
    for name, angle in zip(ISB_FIELDS, limits.ranges, strict=True):
        lines.append(f"{name}: {{lower_deg: {angle.lower_deg:.1f}, upper_deg: {angle.upper_deg:.1f}}}")
    lines.append(f"horizontal_free_below_deg: {limits.horizontal_free_below_deg:.1f}")
    return "\n".join(lines) + "\n"


#: The angles a pilot's limits file must give: the model's defaults are a placeholder, never his range.
LIMITED_ANGLES = ("elevation", "horizontal_rotation", "axial_rotation", "elbow")


def load_isb_limits(path: Path | str) -> IsbLimits:
    """Read a pilot's ISB limits from YAML (degrees); every angle of :data:`LIMITED_ANGLES` must be given.

    Raises:
        IsbLimitsError: the file is missing, not YAML, not a limits file (none of the angles: one line,
            and for a session's ``session.json`` where its limits are), does not match (file, line,
            field named), or leaves an angle out (the placeholder would stand for his range).
    """
    data, _ = read_yaml(path, IsbLimitsError)
    expected = "expected " + ", ".join(LIMITED_ANGLES) + ", each {lower_deg, upper_deg} (docs/isb_limits.md)"
    try:
        limits = load_yaml_model(path, IsbLimits, error=IsbLimitsError)
    except IsbLimitsError:
        if any(name in data for name in IsbLimits.model_fields):
            raise  # a limits file with a mistake: its line and field
        # another kind of file (a session's session.json): one line, not one per field it has
        where = "; a session's limits are in isb_limits.yaml beside its session.json" if "session_id" in data else ""
        raise IsbLimitsError(f"{path}: not a pilot's ISB limits file: {expected}{where}") from None
    missing = [name for name in LIMITED_ANGLES if name not in data]
    if missing:
        raise IsbLimitsError(f"{path}: {', '.join(missing)} not given; {expected}")
    return limits


# --- numba kernels (the 1 kHz tick and the trajectory integrator) ------------------------------


@njit(cache=True, inline="always")
def _mul_rz(a: FloatArray, angle: float, out: FloatArray) -> None:
    """out = a @ Rz(angle); ``out`` must not alias ``a``."""
    c, s = np.cos(angle), np.sin(angle)
    for r in range(3):
        out[r, 0] = c * a[r, 0] + s * a[r, 1]
        out[r, 1] = -s * a[r, 0] + c * a[r, 1]
        out[r, 2] = a[r, 2]


@njit(cache=True, inline="always")
def _mul(a: FloatArray, b: FloatArray, out: FloatArray) -> None:
    """out = a @ b for 3x3; ``out`` must not alias ``a`` or ``b``."""
    for r in range(3):
        for c in range(3):
            out[r, c] = a[r, 0] * b[0, c] + a[r, 1] * b[1, c] + a[r, 2] * b[2, c]


@njit(cache=True)
def shoulder_fk_kernel(q: FloatArray, base: FloatArray, inter: FloatArray, r3: FloatArray, axes: FloatArray) -> None:
    """Rotor-3 orientation and the three shoulder axes of one configuration, into preallocated arrays.

    Args:
        q: joint angles (>= 3,) rad; only q[0:3] are used.
        base: 0R_{1,s} (3, 3). inter: the constant rotor-to-stator rotation Ry(60 deg) (3, 3).
        r3: out (3, 3), world orientation of rotor 3.
        axes: out (3, 3), columns = world joint axes z1, z2, z3 (the shoulder Jacobian).
    """
    a = np.empty((3, 3))
    b = np.empty((3, 3))
    _mul_rz(base, q[0], a)  # rotor 1
    for r in range(3):
        axes[r, 0] = a[r, 2]
    _mul(a, inter, b)  # stator 2
    for r in range(3):
        axes[r, 1] = b[r, 2]
    _mul_rz(b, q[1], a)  # rotor 2
    _mul(a, inter, b)  # stator 3
    for r in range(3):
        axes[r, 2] = b[r, 2]
    _mul_rz(b, q[2], r3)


@njit(cache=True, inline="always")
def _isb_of_thorax_rotation(s: FloatArray, out: FloatArray) -> None:
    """ISB angles (out[0:3]) of the shoulder rotation ``s`` in thorax coordinates."""
    sin_e = np.sqrt(s[0, 1] * s[0, 1] + s[2, 1] * s[2, 1])
    out[0] = np.arctan2(sin_e, s[1, 1])
    out[1] = np.arctan2(-s[0, 1], -s[2, 1]) if sin_e > POLE_SIN else 0.0
    # -gamma_a = gamma_h + (third Y angle), from entries that stay well-conditioned at the lower pole
    out[2] = -np.arctan2(s[0, 2] - s[2, 0], s[0, 0] + s[2, 2])


@njit(cache=True)
def _isb_single_kernel(q: FloatArray, constants: FloatArray) -> FloatArray:
    """ISB angles (4,) of one q; ``constants`` (4, 3, 3) = base, inter, left, right (one argument: each
    array argument costs ~0.3 us of dispatch)."""
    left, right = constants[2], constants[3]
    r3 = np.empty((3, 3))
    axes = np.empty((3, 3))
    shoulder_fk_kernel(q, constants[0], constants[1], r3, axes)
    tmp = np.empty((3, 3))
    s = np.empty((3, 3))
    _mul(left, r3, tmp)
    _mul(tmp, right, s)
    out = np.empty(4)
    _isb_of_thorax_rotation(s, out)
    out[3] = q[3]
    return out


@njit(cache=True)
def _isb_monitor_kernel(q: FloatArray, constants: FloatArray, free_rad: float, h_lo: float, h_hi: float) -> FloatArray:
    """:func:`_isb_single_kernel`, the horizontal rotation then projected into ``[h_lo, h_hi]`` below an
    elevation of ``free_rad`` (:func:`monitor_isb_function`; the comparisons of Python's ``min(max(h, h_lo),
    h_hi)``, so a NaN stays NaN as it did in Python)."""
    out = _isb_single_kernel(q, constants)
    if out[0] < free_rad:
        h = out[1]
        if h_lo > h:  # max(h, h_lo)
            h = h_lo
        if h_hi < h:  # min(h, h_hi)
            h = h_hi
        out[1] = h
    return out


# --- the shoulder ------------------------------------------------------------------------------


def _wrap(angle: FloatArray) -> FloatArray:
    """Angles wrapped to (-pi, pi]."""
    return np.pi - np.mod(np.pi - angle, 2.0 * np.pi)


def _as_rows(values: FloatArray, what: str) -> tuple[FloatArray, bool]:
    """``values`` as (N, 4) float rows, and whether a single (4,) row was given."""
    values = np.asarray(values, dtype=float)
    single = values.ndim == 1
    if single:
        values = values[None, :]
    if values.ndim != 2 or values.shape[1] != N_JOINTS:
        raise ShapeError(f"expected {what} of shape (N, {N_JOINTS}) or ({N_JOINTS},), got {values.shape}")
    return values, single


def _as_isb(isb: FloatArray) -> tuple[FloatArray, bool]:
    return _as_rows(isb, "ISB angles")


def _as_q(q: FloatArray) -> tuple[FloatArray, bool]:
    return _as_rows(q, "joint angles")


def thorax_rotation(isb: FloatArray) -> FloatArray:
    """Shoulder rotation in thorax coordinates, ``Ry(h) Rx(-e) Ry(-(h + a))``; (N, 3, 3) for (N, >=3) rad."""
    isb = np.asarray(isb, dtype=float)
    e, h, a = isb[..., 0], isb[..., 1], isb[..., 2]
    return rot_y(h) @ rot_x(-e) @ rot_y(-(h + a))


class Shoulder:
    """ISB angles and the shoulder's kinematics of one robot description.

    Args:
        kinematics: the chain (hal.robot.Kinematics).
        lower_rad, upper_rad: joint limits (4,), rad; the inverse kinematics answers inside them.
        thorax_in_world: columns = thorax forward, up, lateral in world coordinates.

    Raises:
        UnreachablePoseError: the neutral pose (arm hanging, forearm flexing forward) is outside
            the joint limits.
        hal.errors.DescriptionError: the neutral pose is near a singularity.
    """

    def __init__(
        self,
        kinematics: Kinematics,
        lower_rad: FloatArray,
        upper_rad: FloatArray,
        thorax_in_world: FloatArray = THORAX_IN_WORLD,
    ) -> None:
        self.kinematics = kinematics
        self.lower_rad = np.asarray(lower_rad, dtype=float).copy()
        self.upper_rad = np.asarray(upper_rad, dtype=float).copy()
        if self.lower_rad.shape != (N_JOINTS,) or self.upper_rad.shape != (N_JOINTS,):
            raise ShapeError(f"joint limits must have shape ({N_JOINTS},)")
        self.thorax_in_world = np.asarray(thorax_in_world, dtype=float).copy()
        self._base = np.ascontiguousarray(kinematics.base_rotation)
        self._inter = np.ascontiguousarray(kinematics.inter_rotation)
        inter_deg = kinematics.geometry.inter_axis_deg
        self._cos_inter = float(np.cos(np.deg2rad(inter_deg)))
        self._sin_inter = float(np.sin(np.deg2rad(inter_deg)))
        #: rotor 3 of the neutral pose, world coordinates (3, 3)
        self.r3_neutral = self.thorax_in_world @ NEUTRAL_ROTOR3_IN_THORAX
        # S_thorax = left @ R3(q) @ right, the constant factors of the ISB decomposition
        self._left = np.ascontiguousarray(self.thorax_in_world.T)
        self._right = np.ascontiguousarray(NEUTRAL_ROTOR3_IN_THORAX.T)
        self._constants = np.ascontiguousarray(np.stack([self._base, self._inter, self._left, self._right]))
        centre = 0.5 * (self.lower_rad + self.upper_rad)
        centre[3] = 0.0
        #: joint angles of the neutral pose (4,) rad, elbow as straight as allowed; found once from the kinematics
        straightest = min(max(0.0, float(self.lower_rad[3])), float(self.upper_rad[3]))
        self.q_neutral = self.q_from_rotor3(self.r3_neutral, straightest, seed=centre)
        if self.sigma_min(self.q_neutral) < NEUTRAL_MIN_SIGMA:
            raise DescriptionError(
                f"the neutral pose q = {np.round(np.degrees(self.q_neutral), 1)} deg is near a shoulder singularity"
            )
        # Compiled (or loaded from the cache) now, not in a tick: the angles, and the monitor's projection of
        # them (monitor_isb_function is called by FSM guards inside a tick) for both array types it is given
        _isb_single_kernel(self.q_neutral, self._constants)
        for readonly in (False, True):
            q = self.q_neutral.copy()
            q.flags.writeable = not readonly
            _isb_monitor_kernel(q, self._constants, 0.0, -1.0, 1.0)

    @classmethod
    def from_description(cls, description: RobotDescription) -> Shoulder:
        return cls(description.kinematics(), description.lower_limits_rad, description.upper_limits_rad)

    # --- forward: q -> ISB ------------------------------------------------------------------

    def rotor3(self, q: FloatArray) -> FloatArray:
        """World orientation of rotor 3, (N, 3, 3) for q (N, 4), or (3, 3) for q (4,)."""
        q, single = _as_q(q)
        r3 = self.kinematics.rotor_rotations(q)[:, 2]
        return r3[0] if single else r3

    def rotation_from_q(self, q: FloatArray) -> FloatArray:
        """Shoulder rotation R_sh (world) of configurations: ``R3(q) R3_neutral^T``."""
        return self.rotor3(q) @ self.r3_neutral.T

    def isb_from_q(self, q: FloatArray) -> FloatArray:
        """ISB angles [elevation, horizontal rotation, axial rotation, elbow] in rad.

        Args:
            q: joint angles (N, 4) or (4,), rad.

        Returns:
            (N, 4), or (4,) for a single configuration.

        Raises:
            hal.errors.ShapeError: ``q`` has the wrong shape.
        """
        q, single = _as_q(q)
        s = self._left @ self.kinematics.rotor_rotations(q)[:, 2] @ self._right
        out = np.empty((q.shape[0], N_JOINTS))
        sin_e = np.hypot(s[:, 0, 1], s[:, 2, 1])
        out[:, 0] = np.arctan2(sin_e, s[:, 1, 1])
        out[:, 1] = np.where(sin_e > POLE_SIN, np.arctan2(-s[:, 0, 1], -s[:, 2, 1]), 0.0)
        out[:, 2] = -np.arctan2(s[:, 0, 2] - s[:, 2, 0], s[:, 0, 0] + s[:, 2, 2])
        out[:, 3] = q[:, 3]
        return out[0] if single else out

    def isb_single(self, q: FloatArray) -> FloatArray:
        """ISB angles (4,) rad of one configuration ``q`` (4,) float64 rad; ~1 us (numba).

        Equal to :meth:`isb_from_q` to round-off. Meant for the safety monitor's 1 kHz tick; it
        does not check the shape (a wrong one is a programming error that numba reports).
        """
        return _isb_single_kernel(q, self._constants)

    # --- inverse: ISB -> q ------------------------------------------------------------------

    def shoulder_rotation(self, isb: FloatArray) -> FloatArray:
        """Shoulder rotation R_sh (world) of ISB angles; (3, 3) for (>=3,), (N, 3, 3) for (N, >=3), rad."""
        t = self.thorax_in_world
        return t @ thorax_rotation(isb) @ t.T

    def q_from_isb(
        self, isb: FloatArray, seed: FloatArray | None = None, unreachable_as_nan: bool = False
    ) -> FloatArray:
        """Joint angles of ISB poses: the solution inside the joint limits nearest to ``seed``.

        Args:
            isb: [elevation, horizontal rotation, axial rotation, elbow] (4,) or (N, 4), rad.
            seed: joint angles (4,) or (N, 4), rad; default ``q_neutral``. Of the (at most two)
                inverse-kinematics branches inside the limits, the one nearest to it is returned.
            unreachable_as_nan: a pose without a solution gives a row of NaN instead of an error
                (for screening many poses at once).

        Returns:
            q (4,) or (N, 4), rad.

        Raises:
            UnreachablePoseError: a pose has no solution inside the joint limits (the message names
                the row and the reason); not with ``unreachable_as_nan``.
            hal.errors.ShapeError: wrong shapes.
        """
        isb, single = _as_isb(isb)
        r3 = self.shoulder_rotation(isb) @ self.r3_neutral
        q = self.q_from_rotor3(r3, isb[:, 3], seed=seed, isb_for_messages=isb, unreachable_as_nan=unreachable_as_nan)
        return q[0] if single else q

    def q_from_rotor3(
        self,
        r3: FloatArray,
        elbow_rad: FloatArray | float,
        seed: FloatArray | None = None,
        isb_for_messages: FloatArray | None = None,
        unreachable_as_nan: bool = False,
    ) -> FloatArray:
        """Joint angles that put rotor 3 at world orientation ``r3`` (3, 3) or (N, 3, 3).

        The analytic solution of ``B^T r3 = Rz(q1) Ry(60) Rz(q2) Ry(60) Rz(q3)``: the angle between
        axes 1 and 3 gives ``cos q2`` (two branches, +-q2), then q1 from the azimuth of axis 3 and
        q3 from what remains. Candidates shifted by 2 pi are considered too.

        Args:
            r3: target orientation(s) of rotor 3, world.
            elbow_rad: q4, float or (N,).
            seed: as in :meth:`q_from_isb`.
            isb_for_messages: the ISB angles (N, 4) the rotations came from, quoted in errors.
            unreachable_as_nan: see :meth:`q_from_isb`.

        Raises:
            UnreachablePoseError: see :meth:`q_from_isb`.
        """
        r3 = np.asarray(r3, dtype=float)
        single = r3.ndim == 2
        if single:
            r3 = r3[None]
        if r3.ndim != 3 or r3.shape[1:] != (3, 3):
            raise ShapeError(f"expected rotations of shape (N, 3, 3), got {r3.shape}")
        n = r3.shape[0]
        elbow = np.broadcast_to(np.asarray(elbow_rad, dtype=float), (n,))
        seed_q = self._seed(seed, n)
        m = self._base.T @ r3
        w = m[:, :, 2]  # axis 3 in stator-1 coordinates
        ci, si = self._cos_inter, self._sin_inter
        cos_q2 = (ci * ci - w[:, 2]) / (si * si)
        reach = np.abs(cos_q2) <= 1.0 + _LIMIT_SLACK_RAD
        q2_abs = np.arccos(np.clip(cos_q2, -1.0, 1.0))
        candidates = np.full((n, 2, 3, 3, 3), np.nan)  # branch, shift q1, shift q3, joint
        for b, q2 in enumerate((q2_abs, -q2_abs)):
            v_x = si * ci * (1.0 + np.cos(q2))  # axis 3 of (q1 = 0, q2) in stator-1 coordinates
            v_y = si * np.sin(q2)
            q1 = _wrap(np.arctan2(w[:, 1], w[:, 0]) - np.arctan2(v_y, v_x))
            chain = rot_z(q1) @ self._inter @ rot_z(q2) @ self._inter
            rest = np.swapaxes(chain, -1, -2) @ m
            q3 = np.arctan2(rest[:, 1, 0], rest[:, 0, 0])
            for i, d1 in enumerate((-2 * np.pi, 0.0, 2 * np.pi)):
                for k, d3 in enumerate((-2 * np.pi, 0.0, 2 * np.pi)):
                    candidates[:, b, i, k] = np.stack([q1 + d1, q2, q3 + d3], axis=-1)
        candidates = candidates.reshape(n, -1, 3)
        lo, hi = self.lower_rad[:3] - _LIMIT_SLACK_RAD, self.upper_rad[:3] + _LIMIT_SLACK_RAD
        inside = np.all((candidates >= lo) & (candidates <= hi), axis=-1) & reach[:, None]
        distance = np.where(inside, np.linalg.norm(candidates - seed_q[:, None, :3], axis=-1), np.inf)
        best = np.argmin(distance, axis=1)
        elbow_ok = (elbow >= self.lower_rad[3] - _LIMIT_SLACK_RAD) & (elbow <= self.upper_rad[3] + _LIMIT_SLACK_RAD)
        ok = np.isfinite(distance[np.arange(n), best]) & elbow_ok
        if not np.all(ok) and not unreachable_as_nan:
            row = int(np.flatnonzero(~ok)[0])
            raise UnreachablePoseError(
                self._why_unreachable(row, reach[row], candidates[row], elbow[row], isb_for_messages, n)
            )
        out = np.empty((n, N_JOINTS))
        out[:, :3] = np.clip(candidates[np.arange(n), best], self.lower_rad[:3], self.upper_rad[:3])
        out[:, 3] = np.clip(elbow, self.lower_rad[3], self.upper_rad[3])
        out[~ok] = np.nan
        return out[0] if single else out

    def _seed(self, seed: FloatArray | None, n: int) -> FloatArray:
        if seed is None:
            # Before q_neutral exists (inside __init__) the caller always passes a seed.
            return np.broadcast_to(self.q_neutral, (n, N_JOINTS))
        seed = np.asarray(seed, dtype=float)
        if seed.shape not in ((N_JOINTS,), (n, N_JOINTS)):
            raise ShapeError(f"seed must have shape ({N_JOINTS},) or ({n}, {N_JOINTS}), got {seed.shape}")
        return np.broadcast_to(seed, (n, N_JOINTS))

    def _why_unreachable(
        self, row: int, reach: bool, candidates: FloatArray, elbow: float, isb: FloatArray | None, n: int
    ) -> str:
        where = f"pose {row + 1} of {n}" if n > 1 else "pose"
        if isb is not None:
            where += " (" + ", ".join(
                f"{name} {np.degrees(v):.1f}" for name, v in zip(ISB_NAMES, isb[row], strict=True)
            )
            where += " deg)"
        if not reach:
            return (
                f"{where} is unreachable: the elbow axis would need an angle to joint 1's axis the shoulder cannot make"
            )
        lo, hi = np.degrees(self.lower_rad), np.degrees(self.upper_rad)
        if not self.lower_rad[3] - _LIMIT_SLACK_RAD <= elbow <= self.upper_rad[3] + _LIMIT_SLACK_RAD:
            return f"{where} is unreachable: elbow {np.degrees(elbow):.1f} deg outside joint 4's limits [{lo[3]:g}, {hi[3]:g}] deg"
        wrapped = candidates[np.all(np.abs(candidates) <= np.pi + 1e-12, axis=1)]
        sols = "; ".join(
            "q = (" + ", ".join(f"{np.degrees(v):.1f}" for v in c) + ") deg" for c in wrapped if np.all(np.isfinite(c))
        )
        limits = ", ".join(f"joint {j + 1} [{lo[j]:g}, {hi[j]:g}]" for j in range(3))
        return f"{where} is unreachable inside the joint limits ({limits} deg); the shoulder solutions are {sols}"

    # --- differential kinematics ------------------------------------------------------------

    def shoulder_jacobian(self, q: FloatArray) -> FloatArray:
        """Shoulder angular-velocity Jacobian: world angular velocity of rotor 3 = J @ q_dot[:3].

        Columns are the world joint axes z1, z2, z3. (3, 3) for q (4,); (N, 3, 3) for q (N, 4).
        """
        q, single = _as_q(q)
        jac = np.swapaxes(self.kinematics.joint_axes(q)[:, :3], -1, -2)
        return jac[0] if single else jac

    def sigma_min(self, q: FloatArray) -> float | FloatArray:
        """Smallest singular value of the shoulder Jacobian (float, or (N,)): 0 at a singularity.

        It depends on q2 alone: ``J^T J`` is the Gram matrix of the three unit axes, with
        ``z1.z2 = z2.z3 = cos(60 deg)`` and ``z1.z3 = a = cos^2(60) - sin^2(60) cos(q2)``, whose
        eigenvalues are ``1 - a`` and ``(2 + a -+ sqrt(a^2 + 8 cos^2(60))) / 2``. sqrt(1/2) at best
        (cos q2 = -1/3, q2 = 109.5 deg), 0.60 at the neutral pose, 0 at q2 = 0 and +-180 deg. Equal to the SVD of
        :meth:`shoulder_jacobian` to round-off, and ~100x faster on a path.
        """
        q, single = _as_q(q)
        c, s = self._cos_inter, self._sin_inter
        a = c * c - s * s * np.cos(q[:, 1])
        # Without cancellation near the singularity: 1 - a = 2 s^2 cos^2(q2/2), and the smaller root
        # of the quadratic is the product of the roots, 1 + a - 2 c^2 = 2 s^2 sin^2(q2/2), over the larger.
        half = 0.5 * q[:, 1]
        larger = 0.5 * (2.0 + a + np.sqrt(a * a + 8.0 * c * c))
        lam = np.minimum(2.0 * s * s * np.cos(half) ** 2, 2.0 * s * s * np.sin(half) ** 2 / larger)
        values = np.sqrt(lam)
        return float(values[0]) if single else values


@cache
def default_shoulder() -> Shoulder:
    """The :class:`Shoulder` of the packaged robot description (hal/daror01.yaml), built once."""
    return Shoulder.from_description(load_description())


def isb_from_q(q: FloatArray) -> FloatArray:
    """ISB angles of ``q`` for the packaged robot; see :meth:`Shoulder.isb_from_q`."""
    return default_shoulder().isb_from_q(q)


def isb_single(q: FloatArray) -> FloatArray:
    """ISB angles of one configuration for the packaged robot; see :meth:`Shoulder.isb_single`."""
    return default_shoulder().isb_single(q)


def q_from_isb(isb: FloatArray, seed: FloatArray | None = None) -> FloatArray:
    """Joint angles of ISB poses for the packaged robot; see :meth:`Shoulder.q_from_isb`."""
    return default_shoulder().q_from_isb(isb, seed)


def shoulder_rotation(isb: FloatArray) -> FloatArray:
    """World shoulder rotation of ISB angles; see :meth:`Shoulder.shoulder_rotation`."""
    return default_shoulder().shoulder_rotation(isb)


def shoulder_jacobian(q: FloatArray) -> FloatArray:
    """Shoulder Jacobian for the packaged robot; see :meth:`Shoulder.shoulder_jacobian`."""
    return default_shoulder().shoulder_jacobian(q)


def jacobian_sigma_min(q: FloatArray) -> float | FloatArray:
    """Singularity measure for the packaged robot; see :meth:`Shoulder.sigma_min`."""
    return default_shoulder().sigma_min(q)


def monitor_isb_function(shoulder: Shoulder, limits: IsbLimits) -> Callable[[FloatArray], FloatArray]:
    """The ``isb_angles`` function for a plain box check against ``limits`` in the 1 kHz tick.

    ISB angles of one configuration, with the horizontal rotation projected into its limits while
    the elevation is below ``limits.horizontal_free_below_deg`` (see :class:`IsbLimits`).
    """
    free = float(limits.horizontal_free_below_rad)
    h_lo, h_hi = float(limits.horizontal_rotation.lower_rad), float(limits.horizontal_rotation.upper_rad)

    def angles(q: FloatArray) -> FloatArray:
        return _isb_monitor_kernel(q, shoulder._constants, free, h_lo, h_hi)  # one compiled call a tick

    return angles  # its kernel was loaded with the shoulder (Shoulder.__init__), not in a tick
