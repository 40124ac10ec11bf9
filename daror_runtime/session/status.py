"""The runtime's status as the operator sees it: one typed, immutable snapshot.

:meth:`daror_runtime.runtime.Runtime.snapshot` builds a :class:`RuntimeStatus` between ticks
(values may be one tick old); the console renders it (``status``), ``session.json`` keeps its
:meth:`RuntimeStatus.as_dict` at the end of a session. Units in the names; joints in the order 1-4.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class GuardState:
    name: str
    description: str
    holds: bool
    why: str | None = None  # when it does not hold: what exactly is missing, in figures (some guards say)


@dataclass(frozen=True)
class EventGate:
    """One operator event from the current state: whether it exists here, and its guards."""

    event: str
    possible: bool  # there is such a transition from this state
    guards: tuple[GuardState, ...] = ()
    why_not: str = ""  # when not possible: why (e.g. "the last state")

    @property
    def unmet(self) -> tuple[GuardState, ...]:
        return tuple(g for g in self.guards if not g.holds)

    @property
    def ready(self) -> bool:
        return self.possible and not self.unmet


@dataclass(frozen=True)
class JointReadings:
    q_deg: tuple[float, ...]
    dq_deg_s: tuple[float, ...]
    spring_torque_nm: tuple[float, ...]  # measured
    motor_command_nm: tuple[float, ...]  # written to the drives in the last tick
    drives: tuple[str, ...]


@dataclass(frozen=True)
class ModelStatus:
    name: str
    kind: str
    path: str | None
    validated: bool
    approved_by: str
    validation_rmse_nm: float | None = None
    validation_rmse_per_joint_nm: tuple[float, ...] | None = None
    max_validation_rmse_nm: float | None = None
    includes_dummy_arm: bool | None = None  # the A Priori model only
    validation_data: str | None = None  # where the validation data came from (this session's run, an earlier one)
    conservative: bool | None = None  # the closed-path test's verdict (None: not tested, the A Priori model)
    closed_path_energy_j: tuple[float, ...] | None = None  # its energy per step size, coarse to fine, J
    nonconservative_confirmed: bool = False  # not conservative, used because the operator confirmed it
    validation_extrapolation: str | None = None  # validation points outside the model's training range, and RMSEs


@dataclass(frozen=True)
class ReactionStatus:
    """What a fault made the robot do (docs/safety.md, "Fault reactions"), while it lasts."""

    reaction: str  # off, lower, hold
    category: int  # IEC 60204-1 stop category: 0, 1, 2
    causes: tuple[str, ...]  # the faults that decided it ("drive 2", "estop")
    joints_off: tuple[int, ...]  # joints whose torque is off whatever the reaction
    support: str  # the gravity support a hold or lowering uses: model or a_priori
    arm_held: bool  # the robot holds or lowers the arm now (torque on, under the reaction)
    lowering_refused: str | None  # why 'lower' would be refused now (None: the operator may ask for it)
    phase: str | None  # hold, lower, handoff, letting go, releasing, held, rested (None: off)
    note: str  # why the arm is held, or how the reaction ended
    since_t_s: float | None  # robot time it began
    rest: str  # what the arm is lowered onto (the settings' rest support)


@dataclass(frozen=True)
class LoopStatus:
    clock: str  # "lock-step", "real time" or "paced" (virtual time paced to the wall clock)
    rate_hz: float
    ticks: int
    overruns: int  # real time only: a paced clock's late ticks are stalls, not overruns
    missed_deadlines: int
    worst_lateness_ms: float
    tick_work_mean_us: float
    tick_work_max_us: float
    dropped_rows: int
    # paced only (0 on the other clocks): the process held the simulated world; never a fault
    stalls: int = 0  # stalls the real-time watchdog would have faulted (3 periods or more late; one per stall)
    lag_ms: float = 0.0  # how far the world is behind its paced grid now (being caught up)
    behind_ms: float = 0.0  # how far the world's time is behind the wall clock since the start (lags dropped + lag)


@dataclass(frozen=True)
class RuntimeStatus:
    """A snapshot of one session (read between ticks)."""

    session_id: str
    pilot: str | None  # the pilot's code, the simulated scenario's pilot, or None (nobody named him)
    t_s: float | None
    state: str
    number: int | None
    superstate: str | None
    mode: str
    description: str
    estop_test_state: bool  # a fault here is met by its reaction and recorded, it does not fail
    gates: dict[str, EventGate]
    faults: list[dict[str, Any]]
    estop_pressed: dict[str, bool]
    estop_tested: list[str]
    confirmed: list[str]
    joints: JointReadings | None
    model: ModelStatus | None
    model_refused: dict[str, Any] | None
    support_level: float
    delivered_support_level: float
    handover_nm: tuple[float, ...]  # what the entry's handover still adds to the model's support
    isb_limits_deg: dict[str, tuple[float, float]] | None
    isb_margin_deg: float  # how far beyond the recorded limits the monitor lets the arm go (the settings')
    rom_recording: bool
    identification_running: dict[str, Any] | None
    identification_saved: dict[str, str]
    last_identification: dict[str, Any] | None
    jobs_pending: bool
    last_error: str | None
    loop: LoopStatus
    transitions: int
    a_priori_includes_dummy_arm: bool  # the settings: what the A Priori model holds besides the robot
    notes: list[str] = field(default_factory=list)  # things the operator should know (settings vs. the world)
    reaction: ReactionStatus | None = None  # what a fault made the robot do, until the reaction ends
    #: the online indicators per model that compensated (issue 29; daror_runtime/online/indicators.py)
    online: list[dict[str, Any]] = field(default_factory=list)
    #: a blind comparison's progress (never the block's model) and, once done, its verdict (issue 29)
    comparison: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (``session.json``, ``status json``)."""
        document = dataclasses.asdict(self)
        document["available"] = {
            name: [g.name for g in gate.unmet] for name, gate in self.gates.items() if gate.possible
        }
        return document
