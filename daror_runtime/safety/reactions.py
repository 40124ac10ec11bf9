"""What a set of faults makes the robot do: the reaction the spec declares, combined and never softened.

``fsm_spec.yaml`` declares, per fault kind (and per state where it must differ), one of three
stops (IEC 60204-1 categories; docs/safety.md, "Fault reactions"):

* ``off`` (category 0): torque off now;
* ``lower`` (category 1): hold the pose under gravity support, lower the arm at a bounded speed to
  the session's rest pose, hand it to its rest, then torque off;
* ``hold`` (category 2): hold the pose under gravity support until the operator acts.

A fault that means a joint cannot be trusted (its drive, torque path or sensors) also takes *that
joint's* torque off (``faulted_joint: off``): the other joints go on holding the arm.

:func:`plan_reaction` turns the faults of a tick into a :class:`ReactionPlan`; :func:`escalate`
combines it with the reaction already under way. A reaction only ever gets stricter while its
faults are latched (hold < lower < off; joints once off stay off; the A Priori support once
chosen stays): a second fault can never give back torque the first one took away. Both run in
the tick the fault is found: a handful of comparisons, no allocation beyond the plan.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Literal, NamedTuple

from daror_runtime.fsm.spec import FaultReaction, Reaction
from daror_runtime.safety.faults import Fault, FaultKind
from hal.interface import DriveState
from hal.robot import N_JOINTS

__all__ = ["CATEGORY", "ReactionPlan", "escalate", "plan_reaction"]

#: The stop category of each reaction (IEC 60204-1).
CATEGORY: dict[str, int] = {"off": 0, "lower": 1, "hold": 2}
#: How strict a reaction is: a reaction under way only ever moves up this order.
_RANK: dict[str, int] = {"hold": 0, "lower": 1, "off": 2}
_ALL_JOINTS = tuple(range(1, N_JOINTS + 1))

Support = Literal["model", "a_priori"]


class ReactionPlan(NamedTuple):
    """What the robot does about the latched faults.

    Attributes:
        reaction: off, lower or hold (for the joints that keep torque).
        joints_off: joints (1-4) whose torque is off whatever the reaction (untrusted, or not holding).
        support: the gravity support a hold or lowering uses: the model in use or the A Priori model.
        within_s: an e-stop's bound (safe stop 1): torque off at the latest this long after the start, s.
        causes: what decided it, for the audit log ("estop", "drive 2", ...), in the order found.
    """

    reaction: Reaction
    joints_off: tuple[int, ...]
    support: Support
    within_s: float | None
    causes: tuple[str, ...]

    @property
    def category(self) -> int:
        """The stop category (0, 1, 2) of the reaction."""
        return CATEGORY[self.reaction]

    @property
    def holds(self) -> bool:
        """True when some joint keeps torque: the reaction's controller runs."""
        return self.reaction != "off"


def _cause(fault: Fault) -> str:
    return f"{fault.kind.value} {fault.joint}" if fault.joint is not None else fault.kind.value


def plan_reaction(
    faults: Iterable[Fault],
    state: str,
    reactions: Mapping[FaultKind, FaultReaction],
    estop_wiring: str,
    drives: tuple[DriveState, ...],
) -> ReactionPlan:
    """The reaction ``faults`` command in ``state`` (the spec's ``fault_reactions``).

    Args:
        faults: the faults to react to (at least one; the latched ones and those of this tick).
        state: the state the faults were found in (its overrides apply).
        reactions: the spec's reaction per fault kind.
        estop_wiring: the robot's e-stop wiring, ``sto`` or ``ss1``: with ``sto`` a pressed button
            has already cut the drives' power in hardware, so the e-stop's reaction is off.
        drives: the drives' states when the faults were found: a joint whose drive was not
            enabled held nothing, so no reaction gives it torque.

    Returns:
        The strictest reaction any fault asks for; every joint a fault names as untrusted, and
        every joint whose drive held nothing, off. Off altogether when no joint keeps torque.

    Raises:
        KeyError: a fault kind the spec has no reaction for (the spec checker refuses such a spec).
    """
    reaction: Reaction = "hold"
    off: set[int] = {j for j, d in zip(_ALL_JOINTS, drives, strict=False) if d != DriveState.ENABLED}
    support: Support = "model"
    within_s: float | None = None
    causes: list[str] = []
    seen = False
    for fault in faults:
        seen = True
        entry = reactions[fault.kind]
        wanted = entry.in_state(state)
        if fault.kind == FaultKind.ESTOP:
            if estop_wiring == "sto":
                wanted = "off"  # the buttons cut the power stages themselves: nothing is left to lower with
            elif wanted == "lower":
                within_s = entry.within_s if within_s is None else min(within_s, entry.within_s or within_s)
        if _RANK[wanted] > _RANK[reaction]:
            reaction = wanted
        if entry.faulted_joint == "off":
            # A fault that names no joint concerns them all (a reading of every joint, the whole bus).
            off.update((fault.joint,) if fault.joint is not None else _ALL_JOINTS)
        if entry.support == "a_priori":
            support = "a_priori"
        cause = _cause(fault)
        if cause not in causes:
            causes.append(cause)
    if not seen:
        raise ValueError("plan_reaction needs at least one fault")
    joints_off = tuple(sorted(off))
    if len(joints_off) == N_JOINTS:
        reaction = "off"
    return ReactionPlan(reaction, joints_off, support, within_s if reaction == "lower" else None, tuple(causes))


def escalate(current: ReactionPlan | None, new: ReactionPlan) -> ReactionPlan:
    """``new`` combined with the reaction under way: never less strict than either.

    The stricter reaction, every joint either takes off, the A Priori support if either chose it,
    the tighter e-stop bound, and both causes.
    """
    if current is None:
        return new
    reaction = new.reaction if _RANK[new.reaction] > _RANK[current.reaction] else current.reaction
    joints_off = tuple(sorted(set(current.joints_off) | set(new.joints_off)))
    if len(joints_off) == N_JOINTS:
        reaction = "off"
    support: Support = "a_priori" if "a_priori" in (current.support, new.support) else "model"
    bounds = [b for b in (current.within_s, new.within_s) if b is not None]
    causes = current.causes + tuple(c for c in new.causes if c not in current.causes)
    return ReactionPlan(reaction, joints_off, support, min(bounds) if bounds and reaction == "lower" else None, causes)
