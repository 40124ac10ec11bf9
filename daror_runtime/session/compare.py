"""A blind comparison of two approved models in a session (issue 29, part 3; :mod:`daror_runtime.online.compare`).

``compare a_priori [PAIRS] [SECONDS]`` in state ``compensation`` compares the validated model in use
with the A Priori model the operator confirmed for this pilot (both approved; nothing else is ever
switched in). Blocks of ``SECONDS`` alternate the two in a balanced random order the console does
not show; each switch hands the support over as the mode's entry does (from the springs' torque,
never dipping below what held the arm until the pilot moves it; the unvalidated model's damping
ramps in with it: :meth:`Compensation.switch_model`, at a tick boundary). After each block the session waits for the pilot's rating (``rate N``; on the simulated
plant ``rate sim`` asks the simulated pilot, who rates by his own effort). Each block keeps its own
online indicators; while the comparison runs the per-model indicators pause (they would tell the
operator which model a block has). At the end the verdict is announced, written to
``comparison.json`` and ``comparison.md`` in the session's folder (a job, atomically), and the
support goes back to the validated model. A fault, a reaction or another state stops it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog

from daror_runtime.fsm.spec import StateSpec
from daror_runtime.online.compare import Comparison, verdict_text
from daror_runtime.online.drift import DriftPhase
from daror_runtime.online.indicators import OBSERVE_PERIOD_S, OnlineIndicators
from daror_runtime.session.events import AnnouncementKind
from daror_runtime.session.online import model_label
from daror_runtime.util.atomic import write_text_atomic

if TYPE_CHECKING:
    from daror_runtime.fsm.supervisor import FsmSupervisor, Response, Ticket
    from daror_runtime.models.base import CompensationModel
    from daror_runtime.session.core import SessionCore

log = structlog.get_logger(__name__)

#: A block's default length (s) and the default number of pairs.
BLOCK_S = 20.0
PAIRS = 8


class ComparePhase(StrEnum):
    BLOCK = "block"  # the pilot uses the block's model (handed over at its start)
    RATING = "rating"  # waiting for his rating
    JUDGING = "judging"  # every block rated: the verdict is computed outside the tick
    DONE = "done"
    STOPPED = "stopped"


@dataclass
class CompareRun:
    """A blind comparison under way in a session."""

    comparison: Comparison
    models: tuple[CompensationModel, CompensationModel]
    dampings_nms_per_rad: tuple[float, float]
    inertia_kgm2: Any
    phase: ComparePhase = ComparePhase.BLOCK
    index: int = 0
    indicators: OnlineIndicators | None = None
    next_t_s: float = -np.inf
    effort_sum_nm: float = 0.0
    effort_samples: int = 0
    verdict: dict[str, Any] | None = None
    why_stopped: str = ""
    blind: dict[str, Any] = field(default_factory=dict)

    @property
    def block(self) -> Any:
        return self.comparison.blocks[self.index]

    def status(self) -> dict[str, Any]:
        """What the console shows: the progress, never which model a block has (until the verdict)."""
        document: dict[str, Any] = {
            "phase": self.phase.value,
            "block": self.index + 1,
            "blocks": len(self.comparison.blocks),
            "block_s": self.comparison.block_s,
            "rated": self.comparison.rated,
            "ratings": [b.rating for b in self.comparison.blocks if b.rating is not None],
        }
        if self.verdict is not None:
            document["verdict"] = self.verdict
            document["verdict_text"] = verdict_text(self.verdict)
        if self.why_stopped:
            document["why_stopped"] = self.why_stopped
        return document


def _why_not(core: SessionCore, supervisor: FsmSupervisor) -> str | None:
    state = supervisor.state
    compensation = core.modes.compensation
    if not isinstance(state, StateSpec) or state.name != "compensation":
        return f"a blind comparison runs in state compensation, not in {state.name}"
    selected = supervisor.signals.model
    if selected is None or not selected.validated or compensation.model is core.a_priori:
        return "the model in use must be validated on this pilot's data (it is one of the two)"
    if not core.a_priori_confirmed:
        return "the operator has not confirmed the A Priori model for this pilot (confirm a_priori_model in rom_limits)"
    if core.compare is not None and core.compare.phase not in (ComparePhase.DONE, ComparePhase.STOPPED):
        return "a blind comparison is under way"
    if core.drift is not None and core.drift.phase in (DriftPhase.DRIFTING, DriftPhase.CATCHING):
        return "a drift test is under way"
    if supervisor.reaction is not None or core.monitor.faulted:
        return "a fault or its reaction is under way"
    return None


def request_compare(core: SessionCore, pairs: int = PAIRS, block_s: float = BLOCK_S, seed: int | None = None) -> Ticket:
    """Start a blind comparison of the validated model in use with the confirmed A Priori model."""
    from daror_runtime.fsm.supervisor import Response

    def apply(supervisor: FsmSupervisor) -> Response:
        why = _why_not(core, supervisor)
        if why is not None:
            return core.refuse("compare", why)
        compensation = core.modes.compensation
        model = compensation.model
        if model is None:
            return core.refuse("compare", "no model in use")
        drawn = int(np.random.default_rng().integers(2**31)) if seed is None else seed
        labels = (model_label(core, model), model_label(core, core.a_priori))
        run = CompareRun(
            Comparison.planned(labels, pairs, block_s, drawn),
            (model, core.a_priori),
            (compensation.damping_nms_per_rad, core.settings.unvalidated_model_damping_nms_per_rad),
            core.online.inertia_kgm2,
        )
        core.compare = run
        log.info("blind comparison started", models=list(labels), pairs=pairs, block_s=block_s, seed=drawn)
        _begin_block(core, run)
        return Response("compare", True, supervisor.state_name)

    log.info("request", request="compare", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post("compare", apply)


def _begin_block(core: SessionCore, run: CompareRun) -> None:
    """At a tick boundary: hand the support to the block's model (if it is not the one in use); the block begins."""
    compensation = core.modes.compensation
    block = run.block
    target = run.models[block.model]
    sample = core.signals.sample
    if compensation.model is not target and sample is not None:
        compensation.switch_model(target, run.dampings_nms_per_rad[block.model], sample)
    run.phase = ComparePhase.BLOCK
    block.t_start_s = core.t_s()
    run.indicators = OnlineIndicators(run.inertia_kgm2)
    run.effort_sum_nm, run.effort_samples = 0.0, 0
    run.next_t_s = -np.inf
    core.announcements.announce(
        AnnouncementKind.SESSION,
        f"blind comparison: block {block.number} of {len(run.comparison.blocks)} begins "
        f"({run.comparison.block_s:g} s; the model is not shown)",
        core.t_s(),
    )


def request_rating(core: SessionCore, rating: float | None) -> Ticket:
    """The pilot's rating (0-10) of the block just ended; None: the simulated pilot rates it himself."""
    from daror_runtime.fsm.supervisor import Response

    def apply(supervisor: FsmSupervisor) -> Response:
        run = core.compare
        if run is None or run.phase != ComparePhase.RATING:
            return core.refuse("rate", "no block of a blind comparison waits for a rating")
        value = rating
        if value is None:
            world = core.hal.world
            if world is None:
                return core.refuse("rate", "rate sim needs the simulated pilot; type his rating: rate N")
            effort = run.block.pilot_effort_nm
            value = world.pilot_rating(effort if effort is not None else 0.0)
        if not (isinstance(value, int | float) and np.isfinite(value) and 0.0 <= value <= 10.0):
            return core.refuse("rate", f"a rating is a number from 0 to 10, got {value!r}")
        run.block.rating = float(value)
        log.info("blind comparison: rated", block=run.block.number, rating=float(value))
        if run.index + 1 < len(run.comparison.blocks):
            run.index += 1
            _begin_block(core, run)
        else:
            _finish(core, run)
        return Response(f"rate {value:g}", True, supervisor.state_name)

    log.info("request", request="rate", origin="operator", state=core.supervisor.state_name)
    return core.supervisor.post("rate", apply)


def _finish(core: SessionCore, run: CompareRun) -> None:
    """Every block rated (at a tick boundary): the support back to the validated model; the verdict,
    its files and its announcement in a job (scipy's tests never run in the tick)."""
    compensation = core.modes.compensation
    sample = core.signals.sample
    if compensation.model is not run.models[0] and sample is not None:
        compensation.switch_model(run.models[0], run.dampings_nms_per_rad[0], sample)
    directory = core.session_dir

    def judge() -> None:
        verdict = run.comparison.verdict()
        text = verdict_text(verdict)
        write_text_atomic(directory / "comparison.json", json.dumps(verdict, indent=2) + "\n")
        write_text_atomic(directory / "comparison.md", _markdown(verdict, text))
        run.verdict = verdict
        run.phase = ComparePhase.DONE
        log.info("blind comparison", **{k: v for k, v in verdict.items() if k != "blocks"})
        core.announcements.announce(
            AnnouncementKind.SESSION, text + "; the validated model supports him again", core.t_s()
        )

    run.phase = ComparePhase.JUDGING
    core.jobs.submit("judge the blind comparison", judge)


def _markdown(verdict: dict[str, Any], text: str) -> str:
    lines = [f"# Blind comparison: {verdict['models'][0]} against {verdict['models'][1]}", "", text, ""]
    lines += [
        "| block | model | rating | effort at rest RMS (Nm) | the simulated pilot's effort (Nm) |",
        "|---|---|---|---|---|",
    ]
    for block in verdict["blocks"]:
        effort = block["effort_at_rest_rms_nm"]
        truth = block["pilot_effort_nm"]
        lines.append(
            f"| {block['block']} | {block['model']} | {block['rating']} | "
            f"{'-' if not effort else ' '.join(f'{v:.2f}' for v in effort)} | {'-' if truth is None else f'{truth:.2f}'} |"
        )
    return "\n".join(lines) + "\n"


def _stop(core: SessionCore, run: CompareRun, why: str) -> None:
    run.phase = ComparePhase.STOPPED
    run.why_stopped = why
    log.warning("blind comparison stopped", reason=why, t_s=core.t_s())
    core.announcements.announce(AnnouncementKind.SESSION, f"blind comparison stopped: {why}", core.t_s())


def service_compare(core: SessionCore) -> None:
    """Between ticks: a block's time and indicators; a stop for what ends it."""
    run = core.compare
    if run is None or run.phase in (ComparePhase.JUDGING, ComparePhase.DONE, ComparePhase.STOPPED):
        return
    supervisor = core.supervisor
    sample = core.signals.sample
    if sample is None:
        return
    if supervisor.reaction is not None or core.monitor.faulted:
        _stop(core, run, "a fault: its reaction acts")
        return
    if supervisor.state.name != "compensation":
        _stop(core, run, f"the state changed to {supervisor.state.name}")
        return
    compensation = core.modes.compensation
    seen = compensation.last_model_torque  # what the last tick computed: the model is never called here
    if run.phase != ComparePhase.BLOCK or seen is None or seen[1].t_s < run.next_t_s:
        return
    _, observed, torque = seen
    run.next_t_s = observed.t_s + OBSERVE_PERIOD_S - 1e-9
    indicators = run.indicators
    if indicators is None:
        return
    indicators.observe(
        observed.t_s,
        observed.q_rad,
        compensation.torque.spring_torque_nm(observed),
        np.asarray(torque, dtype=float),
        compensation.support_level,
        handing_over=compensation.handover.active,
    )
    world = core.hal.world
    if world is not None:  # a simulation: the pilot's own effort, for his rating (the truth, never the runtime's)
        pilot = world.pilot_torque_nm()  # read as the plant's last step left it: nothing evaluated here
        run.effort_sum_nm += float(np.abs(pilot).sum())
        run.effort_samples += 1
    block = run.block
    if block.t_start_s is not None and sample.t_s - block.t_start_s >= run.comparison.block_s:
        indicators.interrupt()
        summary = indicators.summary()
        block.t_end_s = sample.t_s
        block.effort_at_rest_rms_nm = list(summary.effort_at_rest_rms_nm) if summary.effort_at_rest_rms_nm else None
        block.interaction_rms_nm = list(summary.interaction_rms_nm)
        block.pilot_effort_nm = run.effort_sum_nm / run.effort_samples if run.effort_samples else None
        run.phase = ComparePhase.RATING
        core.announcements.announce(
            AnnouncementKind.SESSION,
            f"blind comparison: block {block.number} ended: ask the pilot for his rating, 0-10 (rate N"
            + ("; the simulated pilot: rate sim)" if world is not None else ")"),
            sample.t_s,
        )


def comparing(core: SessionCore) -> bool:
    """A blind comparison is in a block or waits for its rating (the per-model indicators pause)."""
    run = core.compare
    return run is not None and run.phase in (ComparePhase.BLOCK, ComparePhase.RATING)


__all__ = [
    "BLOCK_S",
    "PAIRS",
    "ComparePhase",
    "CompareRun",
    "comparing",
    "request_compare",
    "request_rating",
    "service_compare",
]
