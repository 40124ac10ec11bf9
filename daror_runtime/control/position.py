"""Joint position control (thesis Sec. 2.2.4): a PD on the link angle, cascaded on the SEA torque loop.

Per joint::

    tau_ref = K_p (q_ref - q) + K_d (dq_ref - dq) + tau_ff(q)       (clipped to the spring's range)
    motor torque = SeaTorqueController(tau_ref)

``q_ref, dq_ref`` come from a trajectory generator (a callable of the time since the controller
was selected); ``tau_ff`` is an optional compensation model (gravity and stiffness), ``dq`` the
drives' velocity estimate (a first-order 50 Hz low-pass of encoder differences).

**Stability of the cascade.** With an ideal first-order torque loop of bandwidth ``w`` the loop
``I s^3 + I w s^2 + w K_d s + w K_p`` is stable for ``w > K_p / K_d``: the thesis gains (700
Nm/rad, 175 Nms/rad) need only ``w > 4 rad/s``. That criterion ignores what bounds the loop from
above: ``K_d / I`` is the bandwidth the velocity loop asks for, and with the link inertias of the
DAROR-01 (0.003-0.6 kg m^2) Kd = 175 asks for 300-60,000 rad/s, far beyond what a 10 Hz torque loop,
a 50 Hz velocity filter and a 1 kHz loop with a one-tick delay can deliver. The full discrete
model (:func:`position_loop_spectral_radius`) shows the thesis gains unstable at every inertia of
the simulated robot (docs/control.md). The controller therefore never runs unchecked gains:

* :func:`design_position_gains` picks, per joint, the stiffest PD that stays stable with every gain
  multiplied by a gain margin (default 2), over the joint's link-inertia range and with the
  destabilising gravity stiffness of the arm. The range's lower end is the *effective* inertia
  ``1 / (M^-1)_jj`` (:meth:`LinkBounds.from_description`): the three shoulder joints, whose axes
  meet at one point, move only 7-10 % of their ``M_jj`` when their neighbours give way; gains sized
  on ``M_jj`` oscillated at 33 Hz on the 4-DoF simulator;
* :class:`PositionPD` refuses (:class:`ControlDesignError`) gains that fail that check, the
  thesis gains included, naming the joint and the spectral radius.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numba
import numpy as np
from scipy import signal

from daror_runtime.control.base import ControlDesignError, ControlError, ControlSettingError
from daror_runtime.control.sea_torque import SeaPlant, SeaTorqueController
from daror_runtime.errors import ShapeError
from daror_runtime.models.base import CompensationModel
from hal.interface import Command, Sample
from hal.robot import N_JOINTS, FloatArray, RobotDescription

#: The thesis's hand-tuned gains (Sec. 2.2.4). Unstable in this cascade: see the module docstring.
THESIS_KP_NM_PER_RAD = 700.0
THESIS_KD_NMS_PER_RAD = 175.0

#: The drives' velocity estimate the PD differentiates with (hal/sim: first-order low-pass, Hz).
DRIVE_VELOCITY_FILTER_HZ = 50.0

#: Spring damping (Nms/rad) of the SEA in the cascade check: the floor of the passivity plant set
#: (docs/control.md, a test keeps them equal). With none at all the sampled torque loop injects a
#: little energy near 100 Hz, which a very light link (the empty elbow, 0.003 kg m^2) picks up.
CASCADE_SPRING_DAMPING_NMS_PER_RAD = 0.05

Reference = Callable[[float], tuple[FloatArray, FloatArray]]


# --- what the controller needs to know about the links ------------------------------------------


@dataclass(frozen=True)
class LinkBounds:
    """Per joint (4,): the range of link inertia about the joint axis (kg m^2) and the largest gravity
    stiffness ``|d g_j / d q_j|`` (Nm/rad) the PD must hold against.
    """

    inertia_min_kgm2: FloatArray
    inertia_max_kgm2: FloatArray
    gravity_stiffness_nm_per_rad: FloatArray

    def __post_init__(self) -> None:
        for name in ("inertia_min_kgm2", "inertia_max_kgm2", "gravity_stiffness_nm_per_rad"):
            value = np.array(getattr(self, name), dtype=float, ndmin=1)
            if value.ndim != 1 or not np.all(np.isfinite(value)):
                raise ShapeError(f"{name} must be a finite vector, got {value!r}")
            object.__setattr__(self, name, value)
        if not (self.inertia_min_kgm2.shape == self.inertia_max_kgm2.shape == self.gravity_stiffness_nm_per_rad.shape):
            raise ShapeError("link bounds must have one value per joint in every field")
        if np.any(self.inertia_min_kgm2 <= 0.0) or np.any(self.inertia_max_kgm2 < self.inertia_min_kgm2):
            raise ControlSettingError("link inertias must satisfy 0 < min <= max")
        if np.any(self.gravity_stiffness_nm_per_rad < 0.0):
            raise ControlSettingError("gravity stiffness bounds must not be negative")

    @classmethod
    def from_description(
        cls,
        description: RobotDescription,
        load_in_minimum: float = 0.0,
        radius_of_gyration_m: float = 0.05,
        samples: int = 2000,
        seed: int = 0,
        rotational_factor: float = 2.0,
    ) -> LinkBounds:
        """Bounds from the design masses and centres of mass, over the joint range.

        Minimum: the *effective* inertia ``1 / (M^-1)_jj`` (every other joint free) of the exoskeleton
        links plus ``load_in_minimum`` times the Dummy Arm
        (0: no arm, the lightest the joint can be; 0.5: a pilot with half the Dummy Arm's mass is
        always installed, as in the identification state). The minimum decides the D-gain limit.
        Maximum: the diagonal ``M_jj`` of links plus the Dummy Arm, times
        ``rotational_factor`` for the segments' own inertia and production tolerance the
        description does not hold. A body without an inertia tensor (the description has none) gets
        ``m radius_of_gyration_m^2`` about every axis: 0.05 m is below the 0.06-0.08 m of the simulated
        as-built segments, and without it the effective inertias of point masses are several times
        too small. Gravity stiffness: ``sum m g r`` of everything beyond the joint (links and Dummy
        Arm), an upper bound on ``|d g_j / d q_j|``.

        Raises:
            ControlSettingError: ``load_in_minimum`` outside [0, 1].
        """
        if not 0.0 <= load_in_minimum <= 1.0:
            raise ControlSettingError(f"load_in_minimum must be in [0, 1], got {load_in_minimum}")
        kinematics = description.kinematics()
        rng = np.random.default_rng(seed)
        lo, hi = description.lower_limits_rad, description.upper_limits_rad
        q = lo + (hi - lo) * rng.random((samples, N_JOINTS))
        rotors = kinematics.rotor_rotations(q)
        origins = kinematics.frame_origins(q)
        exo = [(i, link.mass_kg, np.asarray(link.com_m), link.inertia_kgm2) for i, link in enumerate(description.links)]
        arm = description.dummy_arm
        load = [
            (2, arm.upper_arm_mass_kg, np.array([arm.upper_arm_com_m, 0.0, 0.0]), None),
            (3, arm.lower_arm_mass_kg, np.array([arm.lower_arm_com_m, 0.0, 0.0]), None),
        ]

        def mass_matrix(bodies: list) -> tuple[FloatArray, FloatArray]:
            """M(q) (samples, 4, 4) and the gravity lever bound sum m g |z_j x r| (samples, 4)."""
            m_q = np.zeros((samples, N_JOINTS, N_JOINTS))
            lever = np.zeros((samples, N_JOINTS))
            for link, mass, com, inertia in bodies:
                centre = origins[:, link] + np.einsum("nab,b->na", rotors[:, link], com)
                jv = np.zeros((samples, 3, N_JOINTS))
                jw = np.zeros((samples, 3, N_JOINTS))
                for j in range(link + 1):
                    axis = rotors[:, j, :, 2]
                    jw[:, :, j] = axis
                    jv[:, :, j] = np.cross(axis, centre - origins[:, j])
                    lever[:, j] += mass * description.gravity_mps2 * np.linalg.norm(jv[:, :, j], axis=1)
                m_q += mass * np.einsum("nai,naj->nij", jv, jv)
                moments = np.full(3, mass * radius_of_gyration_m**2) if inertia is None else np.asarray(inertia)
                world = np.einsum("nab,b,ncb->nac", rotors[:, link], moments, rotors[:, link])
                m_q += np.einsum("nai,nab,nbj->nij", jw, world, jw)
            return m_q, lever

        light_load = [(link, load_in_minimum * mass, com, inertia) for link, mass, com, inertia in load]
        m_light, _ = mass_matrix(exo + light_load)
        m_heavy, lever = mass_matrix(exo + load)
        # A joint whose neighbours give way (compliant, or saturated) moves only its effective inertia
        # 1 / (M^-1)_jj, 7-10 % of M_jj for the three shoulder joints, whose axes meet at the CoR.
        inertia_min = (1.0 / np.einsum("nii->ni", np.linalg.inv(m_light))).min(axis=0)
        inertia_max = np.einsum("nii->ni", m_heavy).max(axis=0) * rotational_factor
        gravity = lever.max(axis=0)
        return cls(inertia_min, inertia_max, gravity)


# --- the cascade, analysed in discrete time ------------------------------------------------------


def position_loop_spectral_radius(
    torque: SeaTorqueController,
    plant: SeaPlant,
    link_inertia_kgm2: float,
    kp: float,
    kd: float,
    velocity_filter_hz: float = DRIVE_VELOCITY_FILTER_HZ,
    link_stiffness_nm_per_rad: float = 0.0,
    link_viscous_nms_per_rad: float = 0.0,
    joint: int = 1,
) -> float:
    """Largest closed-loop eigenvalue magnitude of PD + SEA torque loop + SEA + link (below 1: stable).

    The model, linear and sampled at the controller's period: ZOH-discretised motor inertia,
    viscous friction, spring (and its damping), link inertia (plus a link stiffness, negative for
    the destabilising side of gravity, and link viscous friction); the measured link angle, the
    spring torque ``k (theta - q)`` and the motor angle sampled at the tick; the drives' velocity
    estimate ``v[k] = beta v[k-1] + (1 - beta) (q[k] - q[k-1]) / T``; the torque controller's
    state-space model (DOB included); the command delay.

    Raises:
        ControlDesignError: a non-positive link inertia or velocity-filter frequency.
    """
    if not link_inertia_kgm2 > 0.0 or not velocity_filter_hz > 0.0:
        raise ControlDesignError("link inertia and velocity-filter frequency must be positive")
    period = torque.design.period_s
    a_c, b_c, c_c, d_c = torque.linear_model(joint)
    j_m, b_m, k = plant.inertia_kgm2, plant.viscous_nms_per_rad, plant.stiffness_nm_per_rad
    ds, i_l, b_l, k_l = (
        plant.spring_damping_nms_per_rad,
        link_inertia_kgm2,
        link_viscous_nms_per_rad,
        link_stiffness_nm_per_rad,
    )
    # State [theta, theta', q, q'].
    a = np.array(
        [
            [0.0, 1.0, 0.0, 0.0],
            [-k / j_m, -(b_m + ds) / j_m, k / j_m, ds / j_m],
            [0.0, 0.0, 0.0, 1.0],
            [k / i_l, ds / i_l, -(k + k_l) / i_l, -(ds + b_l) / i_l],
        ]
    )
    b = np.array([[0.0], [1.0 / j_m], [0.0], [0.0]])
    ad, bd, *_ = signal.cont2discrete((a, b, np.eye(4), np.zeros((4, 1))), period, "zoh")
    beta = float(np.exp(-2.0 * np.pi * velocity_filter_hz * period))
    delay, n_c = plant.delay_ticks, a_c.shape[0]
    # Closed-loop state: plant (4), command delay line, velocity filter (previous v and q), controller.
    n = 4 + delay + 2 + n_c
    i_v, i_qp, c0 = 4 + delay, 5 + delay, 6 + delay
    q_row, tau_row, theta_row = np.zeros(n), np.zeros(n), np.zeros(n)
    q_row[2] = 1.0
    tau_row[0], tau_row[2] = k, -k
    theta_row[0] = 1.0
    v_row = (1.0 - beta) / period * q_row
    v_row[i_v] += beta
    v_row[i_qp] -= (1.0 - beta) / period
    ref_row = -kp * q_row - kd * v_row
    inputs = np.vstack([ref_row, tau_row, theta_row])  # the controller's [tau_ref, tau_meas, theta]
    command = c_c[0] @ np.eye(n_c, n, c0) + d_c[0] @ inputs
    m = np.zeros((n, n))
    m[:4, :4] = ad
    if delay == 0:
        m[:4] += np.outer(bd[:, 0], command)
    else:
        m[:4, 4 + delay - 1] += bd[:, 0]
        m[4] = command
        for i in range(1, delay):
            m[4 + i, 4 + i - 1] = 1.0
    m[i_v] = v_row
    m[i_qp] = q_row
    m[c0:, c0:] = a_c
    m[c0:] += b_c @ inputs
    return float(np.max(np.abs(np.linalg.eigvals(m))))


def cascade_plant(torque: SeaTorqueController) -> SeaPlant:
    """The nominal SEA of ``torque`` with :data:`CASCADE_SPRING_DAMPING_NMS_PER_RAD`."""
    return replace(
        SeaPlant.nominal(torque.sea, torque.design.delay_ticks),
        spring_damping_nms_per_rad=CASCADE_SPRING_DAMPING_NMS_PER_RAD,
    )


def _cases(bounds: LinkBounds, j: int) -> list[tuple[float, float]]:
    """(inertia, link stiffness) corners the gains must be stable at, for joint index ``j``."""
    lo, hi = bounds.inertia_min_kgm2[j], bounds.inertia_max_kgm2[j]
    inertias = (lo, float(np.sqrt(lo * hi)), hi)
    return [(i, s) for i in inertias for s in (0.0, -bounds.gravity_stiffness_nm_per_rad[j])]


def worst_position_loop(
    torque: SeaTorqueController,
    bounds: LinkBounds,
    kp: FloatArray,
    kd: FloatArray,
    gain_margin: float = 2.0,
    plant: SeaPlant | None = None,
    velocity_filter_hz: float = DRIVE_VELOCITY_FILTER_HZ,
) -> FloatArray:
    """Per joint, the largest spectral radius over the inertia range, gravity stiffness, and gains
    scaled by 1 and ``gain_margin``. Every entry below 1: the gains are accepted.
    """
    plant = plant or cascade_plant(torque)
    out = np.zeros(len(kp))
    for j in range(len(kp)):
        for inertia, stiffness in _cases(bounds, j):
            for g in (1.0, gain_margin):
                radius = position_loop_spectral_radius(
                    torque, plant, inertia, g * kp[j], g * kd[j], velocity_filter_hz, stiffness, joint=j + 1
                )
                out[j] = max(out[j], radius)
    return out


def design_position_gains(
    torque: SeaTorqueController,
    bounds: LinkBounds,
    gain_margin: float = 2.0,
    damping_ratio: float = 1.0,
    plant: SeaPlant | None = None,
    velocity_filter_hz: float = DRIVE_VELOCITY_FILTER_HZ,
) -> tuple[FloatArray, FloatArray]:
    """Per joint, the stiffest PD ``(K_p, K_d)`` whose cascade is stable with margin.

    ``K_d = 2 zeta sqrt(K_p I_min)``: critically damped (``zeta = 1``) at the joint's smallest
    inertia, because ``K_d / I_min`` is the velocity-loop bandwidth the delayed, filtered loop must
    deliver; heavier links are less damped but further from instability. ``K_p`` climbs a
    logarithmic grid from 1 to 2000 Nm/rad and stops before the first value that fails
    :func:`worst_position_loop` (which includes the gravity stiffness, so ``K_p`` ends up above it).

    Raises:
        ControlDesignError: no gain on the grid is stable for some joint.
    """
    grid = np.logspace(0.0, np.log10(2000.0), 49)
    n = len(bounds.inertia_min_kgm2)
    kp, kd = np.zeros(n), np.zeros(n)
    for j in range(n):
        i_min = float(bounds.inertia_min_kgm2[j])
        one = slice(j, j + 1)
        single = LinkBounds(
            bounds.inertia_min_kgm2[one], bounds.inertia_max_kgm2[one], bounds.gravity_stiffness_nm_per_rad[one]
        )
        for candidate in grid:
            d = 2.0 * damping_ratio * np.sqrt(candidate * i_min)
            radius = worst_position_loop(
                torque, single, np.array([candidate]), np.array([d]), gain_margin, plant, velocity_filter_hz
            )
            if radius[0] >= 1.0:
                if kp[j] > 0.0:
                    break
                continue  # below the gravity stiffness: keep climbing
            kp[j], kd[j] = candidate, d
        if kp[j] == 0.0:
            raise ControlDesignError(f"joint {j + 1}: no stable position gain found for these link bounds")
    return kp, kd


# --- references -------------------------------------------------------------------------------

_IN = numba.types.Array(numba.float64, 1, "A", readonly=True)  # read-only accepted, writable matches too


@numba.njit(numba.types.UniTuple(numba.float64[::1], 2)(_IN, _IN, numba.float64, numba.float64), cache=True, nogil=True)
def _minimum_jerk(q0, delta, t_s, duration_s):  # pragma: no cover - compiled
    s = min(max(t_s / duration_s, 0.0), 1.0)
    position = s * s * s * (10.0 + s * (-15.0 + 6.0 * s))
    velocity = s * s * (30.0 + s * (-60.0 + 30.0 * s)) / duration_s
    q = np.empty(q0.shape[0])
    dq = np.empty(q0.shape[0])
    for j in range(q0.shape[0]):
        q[j] = q0[j] + position * delta[j]
        dq[j] = velocity * delta[j]
    return q, dq


def minimum_jerk(q_start_rad: FloatArray, q_end_rad: FloatArray, duration_s: float) -> Reference:
    """A minimum-jerk move from ``q_start`` to ``q_end`` in ``duration_s``, holding ``q_end`` after.

    Returns a reference ``t_s -> (q_ref, dq_ref)`` (rad, rad/s, fresh arrays); before 0 it holds
    ``q_start``. Evaluated by a compiled function: it runs every tick.

    Raises:
        ControlSettingError: a non-positive or non-finite duration, or non-finite end points.
    """
    q0, q1 = np.array(q_start_rad, dtype=float), np.array(q_end_rad, dtype=float)
    if q0.ndim != 1 or q0.shape != q1.shape or not (np.all(np.isfinite(q0)) and np.all(np.isfinite(q1))):
        raise ControlSettingError("minimum-jerk end points must be finite vectors of the same shape")
    if not (np.isfinite(duration_s) and duration_s > 0.0):
        raise ControlSettingError(f"minimum-jerk duration must be positive, got {duration_s!r} s")
    delta = q1 - q0
    duration = float(duration_s)

    def reference(t_s: float) -> tuple[FloatArray, FloatArray]:
        return _minimum_jerk(q0, delta, float(t_s), duration)

    return reference


# --- the controller ---------------------------------------------------------------------------


@numba.njit(numba.int64(_IN, _IN, _IN, _IN, _IN, numba.float64[:, ::1], numba.float64[::1]), cache=True, nogil=True)
def _pd_kernel(q_ref, dq_ref, q, dq, feedforward, gains, out):  # pragma: no cover - compiled
    """``out = clip(kp (q_ref - q) + kd (dq_ref - dq) + ff)``; ``gains`` rows: kp, kd, limit.

    Returns 0, -1 on a length mismatch, or the 1-based joint with a non-finite input.
    """
    n = gains.shape[1]
    if q_ref.shape[0] != n or dq_ref.shape[0] != n or q.shape[0] != n or dq.shape[0] != n:
        return -1
    if feedforward.shape[0] != n or out.shape[0] != n:
        return -1
    for j in range(n):
        if not (
            np.isfinite(q_ref[j]) and np.isfinite(dq_ref[j]) and np.isfinite(q[j]) and np.isfinite(dq[j])
        ) or not np.isfinite(feedforward[j]):
            return j + 1
    for j in range(n):
        value = gains[0, j] * (q_ref[j] - q[j]) + gains[1, j] * (dq_ref[j] - dq[j]) + feedforward[j]
        out[j] = min(max(value, -gains[2, j]), gains[2, j])
    return 0


class PositionPD:
    """Joint PD on the link angle through the SEA torque controller; a :class:`Controller`.

    Args:
        torque: the SEA torque controller the PD's output is the reference of.
        reference: the trajectory, ``t_s -> (q_ref (4,), dq_ref (4,))``, ``t_s`` counted from the
            sample :meth:`reset` was called with.
        bounds: the link inertia range and gravity stiffness per joint the gains are checked over
            (:meth:`LinkBounds.from_description` for the robot).
        kp_nm_per_rad, kd_nms_per_rad: gains, scalar or per joint; None (default) designs them with
            :func:`design_position_gains`.
        feedforward: optional compensation model; its torque at the measured ``q`` is added.
        use_reference_velocity: D acts on ``dq_ref - dq`` (True) or on ``-dq``.
        gain_margin: the gains must keep the cascade stable when multiplied by this.
        max_start_error_rad: :meth:`reset` refuses a reference that starts farther than this
            from the measured angles (the PD would jump).

    Raises:
        ControlDesignError: the gains make the cascade unstable (or leave less than the margin).
        ControlSettingError: gains not positive and finite.
    """

    commands: tuple[str, ...] = ("motor_torque",)

    def __init__(
        self,
        torque: SeaTorqueController,
        reference: Reference,
        bounds: LinkBounds,
        kp_nm_per_rad: float | FloatArray | None = None,
        kd_nms_per_rad: float | FloatArray | None = None,
        *,
        feedforward: CompensationModel | None = None,
        use_reference_velocity: bool = True,
        gain_margin: float = 2.0,
        max_start_error_rad: float = 0.05,
    ) -> None:
        n = torque.n_joints
        self.torque = torque
        self.reference = reference
        self.feedforward = feedforward
        self.use_reference_velocity = use_reference_velocity
        self.max_start_error_rad = max_start_error_rad
        if len(bounds.inertia_min_kgm2) != n:
            raise ShapeError(
                f"link bounds are for {len(bounds.inertia_min_kgm2)} joints, the torque controller for {n}"
            )
        if kp_nm_per_rad is None and kd_nms_per_rad is None:
            kp, kd = design_position_gains(torque, bounds, gain_margin)
        elif kp_nm_per_rad is None or kd_nms_per_rad is None:
            raise ControlSettingError("give both K_p and K_d, or neither (then they are designed)")
        else:
            kp = np.broadcast_to(np.asarray(kp_nm_per_rad, dtype=float), (n,)).copy()
            kd = np.broadcast_to(np.asarray(kd_nms_per_rad, dtype=float), (n,)).copy()
        if not (np.all(np.isfinite(kp)) and np.all(np.isfinite(kd)) and np.all(kp > 0.0) and np.all(kd >= 0.0)):
            raise ControlSettingError(f"position gains must be finite, K_p > 0 and K_d >= 0; got {kp}, {kd}")
        radius = worst_position_loop(torque, bounds, kp, kd, gain_margin)
        if np.any(radius >= 1.0):
            bad = ", ".join(
                f"joint {j + 1}: K_p {kp[j]:g}, K_d {kd[j]:g} -> spectral radius {radius[j]:.3f}"
                for j in np.flatnonzero(radius >= 1.0)
            )
            raise ControlDesignError(
                f"position gains refused, the PD + SEA torque cascade is unstable (or within the gain margin "
                f"{gain_margin:g} of it) for link inertias {bounds.inertia_min_kgm2.round(4)}..{bounds.inertia_max_kgm2.round(4)}"
                f" kg m^2: {bad}"
            )
        self.kp_nm_per_rad, self.kd_nms_per_rad = kp, kd
        self.spectral_radius = radius  # per joint, with the margin: how close to instability
        spring_range = torque.sea.spring_stiffness_nm_per_rad * torque.sea.max_spring_deflection_rad
        # Beyond the spring's end stop the torque loop cannot deliver more; asking for it only winds up.
        self._gains = np.vstack([kp, kd, np.full(n, spring_range)])
        self._t0_s = 0.0
        self._zeros = np.zeros(n)
        self.last_reference_nm = np.zeros(n)

    def reset(self, sample: Sample) -> None:
        """Start the trajectory clock at ``sample.t_s`` and the torque loop at the sample.

        Raises:
            ControlSettingError: the reference starts farther than ``max_start_error_rad`` from the
                measured angles, or is not finite.
            ControlError: the sample is not finite.
        """
        q_ref, _ = self.reference(0.0)
        error = np.asarray(q_ref, dtype=float) - np.asarray(sample.q_rad, dtype=float)
        if not np.all(np.isfinite(error)):
            raise ControlSettingError("the position reference or the measured angles are not finite at the start")
        if np.max(np.abs(error)) > self.max_start_error_rad:
            j = int(np.argmax(np.abs(error)))
            raise ControlSettingError(
                f"joint {j + 1}: the reference starts {error[j]:+.3f} rad from the measured angle "
                f"(more than {self.max_start_error_rad} rad); start trajectories where the robot is"
            )
        self._t0_s = float(sample.t_s)
        self.torque.reset(sample)
        self.last_reference_nm = np.zeros(self.torque.n_joints)

    def update(self, sample: Sample, dt_s: float) -> Command:
        """Motor torques for this tick.

        Raises:
            ShapeError: a reference, sample or model output of the wrong shape.
            ControlError: a non-finite reference, reading or feedforward (joint named).
        """
        q_ref, dq_ref = self.reference(sample.t_s - self._t0_s)
        if not self.use_reference_velocity:
            dq_ref = self._zeros
        feedforward = self._zeros if self.feedforward is None else self.feedforward.torque(sample.q_rad)
        q, dq = sample.q_rad, sample.dq_rad_s
        tau_ref = np.empty(self.torque.n_joints)
        try:
            status = _pd_kernel(q_ref, dq_ref, q, dq, feedforward, self._gains, tau_ref)
        except TypeError:  # not float64 vectors: convert (or refuse), then the same kernel
            q_ref, dq_ref, q, dq, feedforward = (_float_vector(v) for v in (q_ref, dq_ref, q, dq, feedforward))
            status = _pd_kernel(q_ref, dq_ref, q, dq, feedforward, self._gains, tau_ref)
        if status == -1:
            raise ShapeError(
                f"position reference, sample and feedforward must all have shape ({self.torque.n_joints},)"
            )
        if status:
            j = status - 1
            raise ControlError(
                f"joint {status}: non-finite position reference ({q_ref[j]}, {dq_ref[j]}), reading "
                f"({q[j]}, {dq[j]}) or feedforward ({feedforward[j]})"
            )
        self.last_reference_nm = tau_ref
        return Command(self.torque.motor_torque(tau_ref, sample, dt_s), True)


def _float_vector(values: FloatArray) -> FloatArray:
    """A 1-D float64 array (untouched when it already is one; the kernel checks the length).

    Raises:
        ShapeError: not a vector of numbers.
    """
    if type(values) is np.ndarray and values.dtype == np.float64 and values.ndim == 1:
        return values
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ShapeError(f"expected a vector of numbers, got {values!r}") from None
    if array.ndim != 1:
        raise ShapeError(f"expected a vector, got shape {array.shape}")
    return array
