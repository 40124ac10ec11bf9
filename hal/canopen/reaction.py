"""What a drive does by itself when it loses the master: the SDO writes that configure it, and what it got.

The runtime declares one reaction for every drive (:class:`hal.interface.DriveReaction`): ``ramp_s``
None, disable at once (category 0); a number, ramp the torque from the last target to zero over
``ramp_s`` seconds, then disable (category 1, carried out by the drive). CiA 402 objects, written at
start-up in this order, one transfer in flight per drive (:func:`plan_reaction`)::

    0x6007 abort connection option code = 2 disable voltage      always first: category 0 whatever follows
    0x605E fault reaction option code   = 0 disable drive         always: faults cut the torque at once
    0x605C disable operation option code = 0 disable drive        always: "disable operation" cuts it at once
    ramp only:
    0x6087 torque slope                 = ceil(peak / ramp_s)    per mille/s; then it follows the torque
    0x605A quick stop option code       = 1 slow down on the slow-down ramp, then SWITCH ON DISABLED
    0x6007 abort connection option code = 3 quick stop           only if 0x6087 and 0x605A were taken
    0x605E fault reaction option code   = 1 slow down ramp       only if 0x6087 was taken
    0x605C disable operation option code = 1 slow down ramp      only if 0x6087 was taken

0x605C: the master never commands "disable operation" (its torque off is disable voltage), but a
vendor's tool or a drive's own logic may; it then ends like the master's loss, so that no path
through the power state machine leaves the arm to a firmware default (maxon's is 1, a ramp on
whatever slope the drive holds).

Why code 1 of 0x605A: CiA 402 (IEC 61800-7-201, quick stop option code) defines 1 as "slow down on
slow down ramp and transit into SWITCH ON DISABLED" and 2 as the same on the quick stop ramp; in the
torque modes (profile torque, cyclic synchronous torque) the slow-down ramp is the torque slope
0x6087, while the quick stop ramp is 0x6085 quick stop deceleration, a velocity-mode quantity that
a torque-mode drive may or may not apply to its torque. Code 1 is the one whose ramp is 0x6087 by
the standard's words. Codes 5-8 (stay in QUICK STOP ACTIVE) would leave the power stage on with
nobody to end it.

0x605E: a fault the drive detects itself (an excess temperature, an encoder error) ends like the
master's loss: ramped when the runtime asked for a ramp, at once otherwise. A fault of the power
stage itself (over current, a short) cannot ramp: the drive's hardware cuts it whatever 0x605E says.

The slope at start-up brings the peak torque to zero in ``ramp_s``; while the master commands
torque it rewrites the slope for the torque the drive holds (:mod:`hal.canopen.cia402.torque_slope`).

Capability: a write the EDS lacks the object for is not sent; a write the drive refuses (any SDO
abort: object does not exist, value out of range) is taken as its answer (``may_decline``); either
way the drive keeps what was written before it, and :meth:`ReactionPlan.sentence` says what that
means for it. A missing answer is a transport failure and fails the start-up, as any other.
"""

from __future__ import annotations

from dataclasses import dataclass

from hal.canopen import objects as obj
from hal.canopen.cia301.sdo import SdoClient, SdoTransfer
from hal.canopen.cia402.torque_slope import slope_for
from hal.canopen.dictionary import DriveDictionary

__all__ = ["ReactionPlan", "format_ramp_s", "plan_reaction"]

#: The objects of the reaction, as the messages name them.
NAMES = {
    obj.ABORT_CONNECTION_OPTION_CODE: "0x6007 abort connection option code",
    obj.QUICK_STOP_OPTION_CODE: "0x605A quick stop option code",
    obj.FAULT_REACTION_OPTION_CODE: "0x605E fault reaction option code",
    obj.DISABLE_OPERATION_OPTION_CODE: "0x605C disable operation option code",
    obj.TORQUE_SLOPE: "0x6087 torque slope",
}
#: What the master does with a drive's reaction, in the words of the report.
_CATEGORY_0 = "it disables at once when it loses the master (category 0)"
_UNCONFIGURED = "nothing configures what it does when it loses the master (its firmware decides)"


def format_ramp_s(ramp_s: float) -> str:
    """``ramp_s`` as the report writes it: ``2.0``, ``2.5``, ``0.25``."""
    text = f"{ramp_s:.3g}"
    return text if "." in text or "e" in text else text + ".0"


@dataclass
class ReactionPlan:
    """The reaction writes queued for one drive, and what the drive got once they are done.

    Attributes:
        joint: the drive's joint, 1-4 (the report names it).
        node_id: its node id.
        ramp_s: the ramp the runtime asked for (None: category 0).
        missing: the reaction objects its EDS lacks (their indices), in the order above.
        abort_connection: the baseline 0x6007 = 2 write (None: the EDS has no 0x6007).
        fault_reaction: the baseline 0x605E = 0 write (None: the EDS has no 0x605E).
        slope: the 0x6087 write (None: category 0, or the EDS lacks one of the ramp's objects).
        quick_stop: the 0x605A = 1 write (None: as ``slope``).
        ramp: the final 0x6007 = 3 write (None: as ``slope``).
        fault_ramp: the final 0x605E = 1 write (None: as ``slope``, or the EDS has no 0x605E).
        disable_operation: the baseline 0x605C = 0 write (None: the EDS has no writable 0x605C).
        disable_ramp: the final 0x605C = 1 write (None: as ``slope``, or the EDS has no 0x605C).
        slope_permille_per_s: the slope ``slope`` carries (0: none).
    """

    joint: int
    node_id: int
    ramp_s: float | None
    missing: tuple[int, ...] = ()
    abort_connection: SdoTransfer | None = None
    fault_reaction: SdoTransfer | None = None
    slope: SdoTransfer | None = None
    quick_stop: SdoTransfer | None = None
    ramp: SdoTransfer | None = None
    fault_ramp: SdoTransfer | None = None
    disable_operation: SdoTransfer | None = None
    disable_ramp: SdoTransfer | None = None
    slope_permille_per_s: int = 0

    @property
    def ramps(self) -> bool:
        """True once the drive took every write of the ramp: it ramps over ``ramp_s`` when it loses the master."""
        return self.ramp is not None and self.ramp.succeeded

    @property
    def transfers(self) -> tuple[SdoTransfer, ...]:
        """Every write queued, in order."""
        queued = (
            self.abort_connection,
            self.fault_reaction,
            self.disable_operation,
            self.slope,
            self.quick_stop,
            self.ramp,
            self.fault_ramp,
            self.disable_ramp,
        )
        return tuple(t for t in queued if t is not None)

    def sentence(self) -> str:
        """One sentence on what the drive does when it loses the master (once every write is done)."""
        who = f"drive {self.joint} (node 0x{self.node_id:02X})"
        baseline = self.abort_connection
        if baseline is None:
            return f"{who}: its EDS has no {NAMES[obj.ABORT_CONNECTION_OPTION_CODE]}: {_UNCONFIGURED}"
        if not baseline.succeeded:
            return f"{who}: {_refused(baseline, '2 (disable voltage)')}: {_UNCONFIGURED}"
        faults = self._faults()
        if self.ramp_s is None:
            return f"{who}: {_CATEGORY_0}{faults}"
        if self.missing:
            return f"{who}: its EDS has no {NAMES[self.missing[0]]}: {_CATEGORY_0}{faults}"
        for transfer, value in (
            (self.slope, f"{self.slope_permille_per_s} per mille of the rated torque per second"),
            (self.quick_stop, "1 (slow down on the slow-down ramp)"),
            (self.ramp, "3 (quick stop)"),
        ):
            if transfer is not None and transfer.declined is not None:
                return f"{who}: {_refused(transfer, value)}: {_CATEGORY_0}{faults}"
        if not self.ramps:  # not taken for another reason (cancelled): what stands is the baseline
            return f"{who}: its quick stop on losing the master was not configured: {_CATEGORY_0}{faults}"
        return (
            f"{who}: ramps its torque to zero over {format_ramp_s(self.ramp_s)} s, then disables, "
            f"when it loses the master{faults}"
        )

    def _faults(self) -> str:
        """A clause on faults the drive detects itself, where they do not end as the master's loss does."""
        if self.fault_reaction is None:
            return (
                f"; its EDS has no {NAMES[obj.FAULT_REACTION_OPTION_CODE]}: its own faults end as its firmware decides"
            )
        if not self.fault_reaction.succeeded:
            return f"; {_refused(self.fault_reaction, '0 (disable drive)')}: its own faults end as its firmware decides"
        if self.ramps and self.fault_ramp is not None and self.fault_ramp.declined is not None:
            return f"; {_refused(self.fault_ramp, '1 (slow down ramp)')}: its own faults disable it at once"
        return ""


def _refused(transfer: SdoTransfer, value: str) -> str:
    return f"refused {NAMES[transfer.index]} = {value} ({transfer.declined})"


def plan_reaction(
    sdo: SdoClient,
    dictionary: DriveDictionary,
    joint: int,
    node_id: int,
    ramp_s: float | None,
    peak_permille: int,
) -> ReactionPlan:
    """Queue on ``sdo`` the writes that configure ``node_id``'s own reaction to losing the master (see the module docstring).

    Args:
        sdo: the master's SDO client (the writes go after what is queued for the node already).
        dictionary: the drives' EDS: an object it lacks is not written.
        joint: the drive's joint, 1-4.
        node_id: the drive's node id.
        ramp_s: the ramp the runtime asked for, s (None: category 0).
        peak_permille: the drives' peak torque 0x6072: the start-up slope brings it to zero in ``ramp_s``.

    Raises:
        ValueError: ``ramp_s`` is not finite and positive.
    """
    plan = ReactionPlan(joint, node_id, ramp_s)

    def write(index: int, value: int, what: str, needs: tuple[SdoTransfer, ...] = ()) -> SdoTransfer:
        data = dictionary.encode(index, 0, value)
        return sdo.write(node_id, index, 0, data, what, may_decline=True, needs=needs)

    if dictionary.writable(obj.ABORT_CONNECTION_OPTION_CODE):
        plan.abort_connection = write(
            obj.ABORT_CONNECTION_OPTION_CODE, obj.ABORT_DISABLE_VOLTAGE, "abort connection: disable voltage"
        )
    if dictionary.writable(obj.FAULT_REACTION_OPTION_CODE):
        plan.fault_reaction = write(obj.FAULT_REACTION_OPTION_CODE, obj.STOP_DISABLE_DRIVE, "fault reaction: disable")
    if dictionary.writable(obj.DISABLE_OPERATION_OPTION_CODE):
        plan.disable_operation = write(
            obj.DISABLE_OPERATION_OPTION_CODE, obj.STOP_DISABLE_DRIVE, "disable operation: disable"
        )
    if ramp_s is None:
        return plan
    slope = slope_for(peak_permille, ramp_s)
    plan.missing = tuple(
        index
        for index in (obj.ABORT_CONNECTION_OPTION_CODE, obj.TORQUE_SLOPE, obj.QUICK_STOP_OPTION_CODE)
        if not dictionary.writable(index)
    )
    if plan.missing or plan.abort_connection is None:
        return plan
    plan.slope_permille_per_s = slope
    plan.slope = write(obj.TORQUE_SLOPE, slope, "torque slope")
    plan.quick_stop = write(obj.QUICK_STOP_OPTION_CODE, obj.STOP_SLOW_DOWN_RAMP, "quick stop: slow-down ramp")
    plan.ramp = write(
        obj.ABORT_CONNECTION_OPTION_CODE,
        obj.ABORT_QUICK_STOP,
        "abort connection: quick stop",
        needs=(plan.abort_connection, plan.slope, plan.quick_stop),
    )
    if plan.fault_reaction is not None:
        plan.fault_ramp = write(
            obj.FAULT_REACTION_OPTION_CODE,
            obj.STOP_SLOW_DOWN_RAMP,
            "fault reaction: slow-down ramp",
            needs=(plan.fault_reaction, plan.slope),
        )
    if plan.disable_operation is not None:
        plan.disable_ramp = write(
            obj.DISABLE_OPERATION_OPTION_CODE,
            obj.STOP_SLOW_DOWN_RAMP,
            "disable operation: slow-down ramp",
            needs=(plan.disable_operation, plan.slope),
        )
    return plan
