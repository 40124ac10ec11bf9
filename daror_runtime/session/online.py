"""The session's online indicators (issue 29): observed between ticks, one set per model that compensated.

:func:`observe_online` runs in the service between ticks (in lock-step after every tick, with a
loop of its own every service period): every :data:`~daror_runtime.online.indicators.OBSERVE_PERIOD_S`
of robot time, while a compensation mode delivers a model's support without a fault or a reaction, it reads the last sample and the model's torque there and observes it. Any
other moment interrupts the indicators (a rest ends; no acceleration spans the gap). Each model
that compensates gets its own indicators, keyed by its name and file, so a comparison of two models
(issue 29, part 3) reads both.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from daror_runtime.online.drift import DriftPhase, DriftResult, corrected_effort
from daror_runtime.online.indicators import OBSERVE_PERIOD_S, OnlineIndicators

if TYPE_CHECKING:
    from daror_runtime.models.base import CompensationModel
    from daror_runtime.session.core import SessionCore
    from hal.robot import FloatArray


@dataclass
class OnlineRecord:
    """The indicators of every model that compensated in this session, in the order they first did."""

    inertia_kgm2: FloatArray
    by_model: dict[str, OnlineIndicators] = field(default_factory=dict)
    next_t_s: float = -np.inf  # the robot time of the next observation
    drift_tests: list[DriftResult] = field(default_factory=list)  # every drift test (part 2), oldest first
    model: object | None = None  # the model observed last (identity: a new object is a new selection)
    label: str | None = None  # its label, the key of its indicators

    def indicators_for(self, label: str) -> OnlineIndicators:
        indicators = self.by_model.get(label)
        if indicators is None:
            indicators = self.by_model[label] = OnlineIndicators(self.inertia_kgm2)
        return indicators

    def interrupt(self) -> None:
        if self.label is not None:
            self.by_model[self.label].interrupt()
        self.model = self.label = None

    def as_list(self) -> list[dict[str, Any]]:
        """JSON-ready, per model: ``{"model": label, ...summary}`` (``session.json``, ``status``)."""
        entries = []
        drift_tests = list(self.drift_tests)
        labels = list(self.by_model.items())
        for label in dict.fromkeys(test.model for test in drift_tests):  # a model only drift-tested
            if label not in self.by_model:
                labels.append((label, OnlineIndicators(self.inertia_kgm2)))
        for label, indicators in labels:
            summary = indicators.summary()
            entry = {"model": label, **summary.as_dict()}
            own = [test for test in drift_tests if test.model == label]
            entry["drift_tests"] = [test.as_dict() for test in own]
            last = summary.last_rest
            corrected = None if last is None else corrected_effort(last.pose_rad, last.effort_nm, own)
            if entry["last_rest"] is not None:  # his effort less the model's error a drift test measured there
                entry["last_rest"]["effort_corrected_nm"] = (
                    None if corrected is None else [round(v, 4) for v in corrected[0]]
                )
            entries.append(entry)
        return entries


def model_label(core: SessionCore, model: CompensationModel) -> str:
    """The model's name and its file (``PLF+ (model_plf_plus.json)``) as the operator knows it."""
    if model is core.a_priori:
        return "A Priori (the robot description)"
    summary = core.progress.last_model
    path = summary.get("path") if summary is not None else None
    name = getattr(model, "name", type(model).__name__)
    return f"{name} ({path.rsplit('/', 1)[-1]})" if isinstance(path, str) and path else str(name)


def observe_online(core: SessionCore) -> None:
    """Observe the last tick that delivered a model's support, if it is time; else interrupt.

    What is observed is what that tick computed (:attr:`Compensation.last_model_torque`): this runs
    on the service's thread while the loop may be in a tick, and never calls the model itself.
    """
    compensation = core.modes.compensation
    seen = compensation.last_model_torque
    record = core.online
    if seen is None:
        return
    model, sample, torque = seen
    if sample.t_s < record.next_t_s:
        return
    record.next_t_s = sample.t_s + OBSERVE_PERIOD_S - 1e-9
    if core.drift is not None and core.drift.phase in (DriftPhase.DRIFTING, DriftPhase.CATCHING):
        record.interrupt()  # the relaxed arm in a drift test is no rest and no motion of the pilot's
        return
    if core.compare is not None and core.compare.phase in ("block", "rating"):
        record.interrupt()  # a blind comparison keeps its own per block; these would name the block's model
        return
    supervisor = core.supervisor
    delivering = supervisor.state.mode == "compensation" and supervisor.reaction is None and not core.monitor.faulted
    latest = core.signals.sample
    stale = latest is not None and latest.t_s - sample.t_s > 3 * OBSERVE_PERIOD_S
    if not delivering or stale:
        record.interrupt()  # not delivering now, or the last tick that did is long past
        return
    if model is not record.model or record.label is None:
        record.interrupt()
        record.model, record.label = model, model_label(core, model)
    record.indicators_for(record.label).observe(
        sample.t_s,
        sample.q_rad,
        compensation.torque.spring_torque_nm(sample),
        np.asarray(torque, dtype=float),
        compensation.support_level,
        handing_over=compensation.handover.active,
    )


__all__ = ["OnlineRecord", "model_label", "observe_online"]
